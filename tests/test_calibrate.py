"""The calibration folder end to end on lab data, and what a failed calibration leaves behind (nothing)."""

import json
import shutil

import numpy as np
import pytest

from procam.addon.cli import main
from procam.addon.errors import CalibrationError
from procam.addon.lab.lab import LabTruth
from procam.addon.stages.calibrate import Calibration, calibrate
from procam.addon.stages.metrics import psnr, ssim


@pytest.fixture(scope="module")
def calibrated(lab_set, tmp_path_factory):
    captures, truth = lab_set("vedge", "realistic")
    out = tmp_path_factory.mktemp("cal") / "calibration"
    cal = calibrate(captures, out)
    return captures, truth, out, cal


def test_calibration_folder_is_complete_and_accurate(calibrated):
    _, truth_path, out, cal = calibrated
    for name in ("calibration.json", "surface.npz", "surface.obj", "albedo.png", "scene.blend",
                 "diagnostics/pose_mask.png", "diagnostics/warp_grid.png"):
        assert (out / name).is_file(), name
    doc = json.loads((out / "calibration.json").read_text())
    assert np.asarray(doc["camera_from_projector"]).shape == (4, 4)
    assert set(doc["seconds"]) >= {"surface", "pose", "warp"}
    truth = LabTruth.load(truth_path).rig.projector
    est = cal.rig.projector
    assert np.linalg.norm(est.position - truth.position) < 0.02  # metres, at 0.3 scale
    assert np.degrees(np.arccos(np.clip(est.direction @ truth.direction, -1, 1))) < 0.5
    back = Calibration.load(out)
    assert np.allclose(back.rig.projector.camera_from_projector, est.camera_from_projector)
    assert back.warp is not None and np.allclose(back.warp.w_shifts, cal.warp.w_shifts, atol=1e-5)


def test_existing_calibration_is_not_overwritten(calibrated):
    captures, _, out, _ = calibrated
    before = (out / "calibration.json").read_bytes()
    assert main(["calibrate", str(captures), "--out", str(out), "--no-blend-output"]) == 2
    assert (out / "calibration.json").read_bytes() == before


def test_failed_calibration_leaves_nothing(calibrated, tmp_path):
    captures, _, _, _ = calibrated
    broken = tmp_path / "broken"
    shutil.copytree(captures, broken)
    doc = json.loads((broken / "capture.json").read_text())
    doc["images"] = [e for e in doc["images"] if e["kind"] != "checker"]
    (broken / "capture.json").write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match="checker"):
        calibrate(broken, tmp_path / "cal")
    assert not (tmp_path / "cal").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["broken"]


def test_metrics():
    rng = np.random.default_rng(0)
    a = rng.random((40, 50, 3)).astype(np.float32)
    assert psnr(a, a) == float("inf") and ssim(a, a) == pytest.approx(1.0)
    assert psnr(np.clip(a + 0.01, 0, 1), a) == pytest.approx(40.0, abs=0.6)
    assert ssim(np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1), a) < 0.9
