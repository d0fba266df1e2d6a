"""The diagnosis on rigs that changed during the session, and on effects it has no model for.

Tiny lab sets (scale 0.2); the calibration is the truth's geometry (``lab_calibration``), so these test the
diagnosis itself. The matrix over surfaces, strengths and seeds is ``scripts/bench_diagnosis.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

from procam.addon.capture.format import CaptureSet
from procam.addon.gap.remainder import Remainder, _kernel_terms
from procam.addon.gap.session import check_session
from procam.addon.steps import diagnose as diagnose_step

TINY = dict(scale=0.2, samples=8)

pytestmark = pytest.mark.blender


def test_a_static_rig_neither_drifts_nor_moves(lab_set):
    report = check_session(CaptureSet.load(lab_set("vedge", "glossy=0.5,noise=0.5", **TINY)[0]))
    assert report.closing_white and not report.changed
    assert max(map(abs, report.drift_rgb)) < 0.01 and report.motion_rms_px < 0.08


def test_a_warming_projector_is_seen_as_light_that_drifts(lab_set):
    report = check_session(CaptureSet.load(lab_set("vedge", "warmup=0.5", **TINY)[0]))
    assert report.drift_detected and not report.motion_detected
    r, g, b = report.drift_rgb
    assert b > g > r > 0 and b == pytest.approx(0.06 * (np.exp(-0.04 / 0.35) - np.exp(-1 / 0.35)), abs=0.015)
    assert "warming up" in report.sentence()


def test_a_knocked_surface_is_seen_as_motion(lab_set):
    report = check_session(CaptureSet.load(lab_set("curve", "surface_moved=0.5", **TINY)[0]))
    assert report.motion_detected and not report.drift_detected
    assert "moved" in report.sentence()


def test_no_effect_is_named_with_high_confidence_when_the_rig_changed(lab_calibration, tmp_path):
    cal_dir, _, _ = lab_calibration("vedge", "warmup=0.5", **TINY)
    doc = diagnose_step.run(diagnose_step.DiagnoseOptions(cal_dir, tmp_path / "gap", scale=1.0, spp=8))
    assert doc["session"]["changed"] and doc["session"]["drift_detected"]
    levels = {e["name"]: e["confidence"]["level"] for e in doc["effects"] if e["name"] in doc["modelled"]}
    assert all(v == "low" for v in levels.values()), levels
    assert "changed during the session" in (tmp_path / "gap" / "summary.md").read_text()


def test_the_noise_floor_of_the_smoothed_residual():
    # white noise of variance v leaves v·Σg² after the smoothing, read back from its high-pass as remainder() does
    g0, g2 = _kernel_terms(1.5)
    assert g2 == pytest.approx(1 / (4 * np.pi * 1.5 ** 2), rel=0.05) and g0 == pytest.approx(2 * g2, rel=0.05)
    import cv2
    noise = np.random.default_rng(0).normal(0, 0.01, (400, 400)).astype(np.float32)
    smooth = cv2.GaussianBlur(noise, (0, 0), 1.5)
    hp = noise - smooth
    v = float((hp[20:-20, 20:-20] ** 2).mean()) / (1 - 2 * g0 + g2)
    assert v == pytest.approx(1e-4, rel=0.05)
    assert float((smooth[20:-20, 20:-20] ** 2).mean()) == pytest.approx(v * g2, rel=0.1)


def test_unexplained_needs_both_a_large_share_and_a_visible_remainder():
    floor = 1e-6
    kept = Remainder(0.01, floor, before_mse=1e-4, after_mse=6e-5, edges_before_mse=0, edges_after_mse=0)
    assert kept.explained_share == pytest.approx((1e-4 - 6e-5) / (1e-4 - floor)) and kept.detected
    fitted = Remainder(0.01, floor, before_mse=1e-4, after_mse=1e-5, edges_before_mse=0, edges_after_mse=0)
    assert not fitted.detected and fitted.explained_share > 0.9
    tiny = Remainder(0.01, floor, before_mse=2e-6, after_mse=2e-6, edges_before_mse=0, edges_after_mse=0)
    assert not tiny.detected  # nothing above the floor worth a word


def _doc(**over):
    doc = {"session": {"changed": False, "sentence": ""}, "modelled": [], "absorbed": [], "regions": [],
           "unexplained": {"detected": False, "explained_share": 1.0, "where": "", "unexplained_rmse": 0.0}}
    return {**doc, **over}


def test_the_headline_is_one_sentence_a_technician_can_act_on():
    from procam.addon.gap.diagnose import headline

    size = (640, 480)
    assert "nothing to fix" in headline(_doc(), size)
    bottom = [{"bbox": [200, 380, 240, 90], "share": 0.6, "cause": "defocus", "tags": []}]
    text = headline(_doc(modelled=["defocus"], regions=bottom), size)
    assert text.startswith("The projector is out of focus towards the bottom") and "refocus" in text
    # an effect over the whole lit area, or a place that belongs to another cause, places nothing
    whole = [{**bottom[0], "tags": ["whole lit area"]}]
    assert "towards" not in headline(_doc(modelled=["defocus"], regions=whole), size)
    assert "towards" not in headline(_doc(modelled=["defocus"], regions=[{**bottom[0], "cause": "glossy"}]), size)
    changed = _doc(modelled=["black_level"], session={"changed": True, "sentence": "the surface moved"})
    assert "capture again" in headline(changed, size) and "black" not in headline(changed, size)
    left = {"detected": True, "explained_share": 0.2, "where": "near a surface crease", "unexplained_rmse": 0.004}
    assert "no model for remains near a surface crease" in headline(_doc(unexplained=left), size)
    assert "80% of the residual" in headline(_doc(modelled=["response"], unexplained=left), size)
