"""Cycles (the Blender scene) and Mitsuba (the model f̂) agree on a lens-shifted projector lighting a
curved, textured surface: checkerboard corners on the same camera pixels, the same intensity with no
fitted scale (issue 2, item 5)."""

import numpy as np
import pytest

from procam.addon.rig.demo import demo_projector, demo_rig
from procam.addon.rig.model import Rig
from procam.addon.surface.shapes import builtin_surface

pytestmark = pytest.mark.blender


@pytest.fixture(scope="module")
def rig_and_surface():
    rig = demo_rig((320, 240), (400, 300))
    k = rig.projector.intrinsics
    assert abs(k.cy - k.height / 2) >= 0.1 * k.height  # principal point ≥ 10 % of the height off centre
    surface = builtin_surface("curve")
    assert np.ptp(surface.vertices[:, 2]) > 0.2 and surface.albedo.std() > 0.05  # non-planar, textured
    return rig, surface


@pytest.mark.parametrize("bounces, intensity_limit", [(0, 0.01), (1, 0.05)])
def test_cycles_and_mitsuba_agree(rig_and_surface, bounces, intensity_limit):
    from procam.addon.lab.crosscheck import run_cross_check

    rig, surface = rig_and_surface
    check = run_cross_check(rig, surface, bounces=bounces, samples=64, spp=64)
    s = check.summary()
    print(s)
    assert s["corners"] >= 30
    assert s["corner_offset_median_px"] < 0.2
    assert s["corner_offset_max_px"] < 1.0
    assert check.intensity_rel_diff < intensity_limit
    assert check.lit_pixels > 0.2 * 320 * 240


def test_cycles_and_mitsuba_agree_at_a_large_lens_shift():
    """The realdata projector's shift: image 1.27 heights above the lens axis (principal point far below the frame)."""
    from procam.addon.lab.crosscheck import run_cross_check

    rig = Rig(demo_rig((320, 240), (400, 300)).camera, demo_projector(400, 300, shift=(0.0, 1.27)))
    k = rig.projector.intrinsics
    assert k.cy > k.height * 1.7  # principal point far outside the frame
    check = run_cross_check(rig, builtin_surface("curve"), bounces=0, samples=64, spp=64)
    s = check.summary()
    print(s)
    assert s["corners"] >= 30
    assert s["corner_offset_median_px"] < 0.2
    assert s["corner_offset_max_px"] < 1.0
    assert check.intensity_rel_diff < 0.01


def test_cross_check_detects_a_wrong_projector(rig_and_surface):
    """The measurement itself can fail: a Mitsuba model with a projector 2 px off must show it."""
    from procam.addon.lab.crosscheck import checkerboard_frame, measure, predicted_corners
    from procam.addon.render.forward import ForwardModel
    from procam.addon.rig.model import Intrinsics, Projector

    rig, surface = rig_and_surface
    k = rig.projector.intrinsics
    shifted = Projector(Intrinsics(k.width, k.height, k.fx, k.fy, k.cx + 2.0, k.cy),
                        rig.projector.camera_from_projector, rig.projector.intensity * 1.05)
    good = ForwardModel(rig, surface, spp=16, smoothing_eps=0.0, clamp=False)
    bad = ForwardModel(Rig(rig.camera, shifted), surface, spp=16, smoothing_eps=0.0, clamp=False)
    frames = {"white": np.ones((k.height, k.width, 3), np.float32),
              "checker": checkerboard_frame(k.width, k.height, 40)}
    a = {n: good.render(f) for n, f in frames.items()}
    b = {n: bad.render(f) for n, f in frames.items()}
    m = measure(a, b, predicted_corners(rig, surface, 40), 20.0, 0)
    assert np.median(m.corner_offsets) > 0.5
    assert m.intensity_rel_bias == pytest.approx(-0.05 / 1.05, abs=0.01)
