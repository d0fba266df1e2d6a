"""The camera's effects of a rig of several projectors: fitted once on every projector's patterns, named as the
camera's (not one projector's), and modelled in the joint compensation."""

from __future__ import annotations

import json

import numpy as np
import pytest


def test_the_camera_curve_takes_every_projectors_sum_to_light():
    """Each projector's model is in its own white's units: the shared scale takes the projectors' sum to light
    exactly where they all show white, and where one lights alone."""
    from procam.addon.gap.compensation import SharedCamera
    from procam.addon.gap.models import camera_curve, inverse_camera_curve

    curve = 0.8
    w1 = np.full((2, 3, 3), 0.6, np.float32)
    w2 = np.full((2, 3, 3), 0.3, np.float32)
    w2[:, 0] = 0.0  # projector 2 does not light the first column
    cam = SharedCamera({"camera_response": {"curve": curve}}, [w1, w2])
    # each white is its projector's light through the curve: both at white give the sum of their light
    seen = camera_curve(inverse_camera_curve(w1, curve) + inverse_camera_curve(w2, curve), curve)
    assert cam.to_model(seen) == pytest.approx(w1 + w2, abs=2e-3)


@pytest.fixture(scope="module")
def camera_lab(tmp_path_factory):
    """Two projectors side by side on the curve, the camera with a tone curve (strength 0.7), no projector effect;
    calibrated and diagnosed (the camera curve and each projector's tone curve as candidates)."""
    from procam.addon.capture.targets import natural_target
    from procam.addon.cli.app import main
    from procam.addon.imageio import write_image

    root = tmp_path_factory.mktemp("camera")
    assert main(["lab", "--surface", "curve", "--projectors", "2", "--overlap", "0.2", "--effects",
                 "camera_response=0.7", "--scale", "0.2", "--samples", "4", "--out", str(root / "lab"), "--truth",
                 str(root / "lab.truth.json")]) == 0
    assert main(["calibrate", str(root / "lab"), "--out", str(root / "cal"), "--no-blend-output"]) == 0
    assert main(["diagnose", str(root / "cal"), "--out", str(root / "diag"), "--spp", "8", "--effects",
                 "response,camera_response", "--max-effects", "2"]) == 0
    write_image(root / "city.png", natural_target("city", (120, 90)))
    return root


def test_a_camera_curve_is_named_the_cameras_and_fitted_once(camera_lab):
    doc = json.loads((camera_lab / "diag" / "gap.json").read_text())
    joint = doc["joint"]
    assert joint["shared"] == ["camera_response"]
    assert joint["params"]["camera_response"]["curve"] == pytest.approx(0.7, abs=0.15)
    assert doc["headline"].startswith("The camera's tone curve")
    assert doc["differs"] is None  # not one projector's difference
    assert joint["residual_after"] < 0.7 * joint["residual"]
    assert joint["compensation"]["shared"] == joint["params"]


def test_compensation_with_the_cameras_curve_modelled_is_better(camera_lab, tmp_path, capsys):
    """--effects auto selects the camera's curve fitted once (and naming it works): the capture through the lab is
    closer to the target than without it, and compensation.json records it."""
    from procam.addon.cli.app import main

    root = camera_lab
    scores = {}
    for effects in ("none", "auto", "camera_response"):
        comp, ev = tmp_path / f"comp-{effects}", tmp_path / f"eval-{effects}"
        assert main(["compensate", str(root / "cal"), str(root / "city.png"), "--iterations", "20", "--effects",
                     effects, "--diagnosis", str(root / "diag"), "--out", str(comp)]) == 0
        assert main(["evaluate", str(root / "cal"), "--inputs", str(comp), "--targets", str(root / "city.png"),
                     "--device", f"lab:{root / 'lab.truth.json'}", "--out", str(ev)]) == 0
        scores[effects] = json.loads((ev / "metrics.json").read_text())["mean"]["psnr"]
        record = json.loads((comp / "compensation.json").read_text())["effects"]
        if effects != "none":
            assert record["camera"]["used"] == ["camera_response"]
    assert scores["auto"] > scores["none"] + 2.0, scores
    assert scores["camera_response"] > scores["none"] + 2.0, scores
