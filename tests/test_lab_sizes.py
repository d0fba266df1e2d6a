"""The lab at another projector or camera size than the demo's (``procam lab --projector-size 1920x1080``): square
pixels at another aspect, the demo's own sizes unchanged."""

from __future__ import annotations

import pytest

from procam.addon.rig.demo import demo_rig
from procam.addon.steps.capture import LabOptions, pixel_size


def test_a_16_9_projector_and_camera_keep_square_pixels_and_the_demo_throw():
    base = demo_rig()
    hd = demo_rig((1536, 864), (1920, 1080))
    k, k0 = hd.projector.intrinsics, base.projector.intrinsics
    assert k.size == (1920, 1080) and k.fx == pytest.approx(k.fy)
    assert k.throw_ratio == pytest.approx(k0.throw_ratio) and k.shift == pytest.approx(k0.shift)
    assert hd.projector.input_size == (1440, 1080)
    c = hd.camera.intrinsics
    assert c.size == (1536, 864) and c.fx == pytest.approx(c.fy) and c.fx / c.width == pytest.approx(
        base.camera.intrinsics.fx / base.camera.intrinsics.width)


def test_the_demo_aspect_is_scaled_as_before():
    small, base = demo_rig((64, 48), (80, 60)), demo_rig()
    assert small.projector.intrinsics == base.projector.intrinsics.scaled(80, 60)
    assert small.camera.intrinsics == base.camera.intrinsics.scaled(64, 48)
    assert small.projector.input_size == (60, 60)


def test_lab_sizes_parse_and_refuse_bad_text():
    assert pixel_size("1920x1080") == (1920, 1080)
    for bad in ("1920", "1920x", "axb", "4x3"):
        with pytest.raises(ValueError):
            pixel_size(bad)
    assert LabOptions.__dataclass_fields__["projector_size"].default == (800, 600)
