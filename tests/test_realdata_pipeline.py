"""The whole pipeline on real photographs: an OpenCV-order board session calibrated and diagnosed.

``realdata/kamino410-procam-calibration``: a real camera, a real 1024×768 projector with a large lens shift and a
distorting lens, a printed board before a wall and a table; Gray code, white and black only (no depth image, no
checkerboard, no validation patterns, no surface photo). The checks are on what the photographs plainly hold,
not thresholds fitted to them.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from procam.addon.capture.format import CaptureSet
from procam.addon.cli.app import main

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "realdata" / "kamino410-procam-calibration"
POSES = [f"capture_{i}" for i in range(4)]

needs_real = pytest.mark.skipif(not all((REAL / p / "graycode_41.png").is_file() for p in POSES),
                                reason=f"real captures not found at {REAL} (the shared realdata folder is absent)")


@pytest.fixture(scope="module")
def real_run(tmp_path_factory) -> Path:
    """calibrate-rig → patterns --layout opencv → import-captures --rig → calibrate → diagnose, as a user would."""
    root = tmp_path_factory.mktemp("real")
    steps = [["calibrate-rig", *(str(REAL / p) for p in POSES), "--board", "9x7", "--square", "0.025",
              "--projector", "1024x768", "--out", str(root / "rig.json")],
             ["patterns", "--projector-width", "1024", "--projector-height", "768", "--area", "frame",
              "--no-validation", "--layout", "opencv", "--out", str(root / "sequence")],
             ["import-captures", str(root / "sequence"), str(REAL / "capture_0"), "--rig", str(root / "rig.json"),
              "--encoding", "linear", "--out", str(root / "captures")],
             ["calibrate", str(root / "captures"), "--out", str(root / "cal"), "--init", "nominal",
              "--no-blend-output", "--no-precompute"],
             ["diagnose", str(root / "cal"), "--out", str(root / "gap"), "--scale", "0.1", "--spp", "16"]]
    for argv in steps:
        assert main(argv) == 0, argv[0]
    return root


@needs_real
def test_the_opencv_layout_is_the_sessions_own_sequence(real_run):
    doc = json.loads((real_run / "sequence" / "sequence.json").read_text())
    assert len(doc["frames"]) == 42 and [f["kind"] for f in doc["frames"][-2:]] == ["white", "black"]
    for i in (0, 1, 19, 20, 39, 40, 41):
        ours = cv2.imread(str(real_run / "sequence" / doc["frames"][i]["file"]), cv2.IMREAD_UNCHANGED)
        ours = (ours.mean(axis=2) if ours.ndim == 3 else ours) / 65535.0
        theirs = cv2.imread(str(REAL / "graycode_pattern" / f"pattern_{i:02d}.png"), cv2.IMREAD_GRAYSCALE) / 255.0
        assert float(np.abs(ours - theirs).mean()) < 1e-3, i


@needs_real
def test_a_real_session_calibrates_with_the_projectors_lens_taken_into_account(real_run):
    captures = CaptureSet.load(real_run / "captures")
    # fx and fy of the calibrated camera differ by 0.05 %: the photographs become a square-pixel pinhole's
    assert captures.camera.intrinsics.square_pixels
    assert captures.projector.lens_distortion is not None
    cal = json.loads((real_run / "cal" / "calibration.json").read_text())
    tri = cal["surface_report"]["triangulation"]
    # without the projector's k1 k2 the epipolar gate rejected 48 % of the decoded pixels
    assert tri["rejected"] < 0.05 * tri["decoded"] and tri["reprojection_rms_px"] < 0.6
    warp = cal["warp_report"]
    assert warp["source"] == "graycode"
    assert warp["corners_before_px"]["median"] > 2.0 and warp["corners_after_px"]["median"] < 1.0
    # the surface came from this Gray code with these intrinsics: it cannot judge the pose, and says why
    assert "triangulated from this Gray code" in cal["pose_uncertainty"]["why"]


@needs_real
def test_the_diagnosis_runs_on_the_gray_code_alone_and_finds_the_projectors_black_level(real_run):
    doc = json.loads((real_run / "gap" / "gap.json").read_text())
    assert any("no validation patterns" in w for w in doc["warnings"])
    names = [e["name"] for e in doc["effects"]]
    assert "response" not in names and "camera_response" not in names  # binary patterns cannot test them
    # the black capture is 5 % of the white one where the model shows none: the first thing to say
    assert doc["selected"][0] == "black_level"
    assert doc["residual_after"]["rmse"] < 0.8 * doc["residual"]["rmse"]
    assert "no validation patterns" in (real_run / "gap" / "summary.md").read_text()


@needs_real
def test_intrinsics_are_not_fitted_against_a_surface_triangulated_with_them(real_run, capsys):
    # the surface comes from this Gray code and the board's intrinsics: it cannot judge them (a fit against it
    # moved the board's projector focal length by 6.5 %, reprojecting the same Gray code "better")
    out = real_run / "cal-fit"
    assert main(["calibrate", str(real_run / "captures"), "--out", str(out), "--init", "nominal",
                 "--no-blend-output", "--no-precompute", "--projector-intrinsics", "fit"]) == 2
    assert "triangulated from its own Gray code" in capsys.readouterr().err and not out.exists()
