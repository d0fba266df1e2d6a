"""Every step's ``read()`` returns a typed view, and each command prints its step's ``summary()``: the figures a
user reads on the terminal are the sidebar's, in the same words. Nothing here renders: the steps are replaced by
ones that write a small manifest, as the real ones would."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from procam.addon.cli.app import EXIT_OK, main
from procam.addon.imageio import write_image
from procam.addon.steps import calibrate, compensate, diagnose, evaluate, show

GAP = {
    "format": "procam-gap", "version": 1, "headline": "The camera's response is not modelled: compensate with it.",
    "warnings": ["a blur of about a texel can go unseen; --scale 0.9 looks at 2.0 texels a pixel"],
    "residual": {"rmse": 0.031, "psnr": 30.2, "rmse_structured": 0.02},
    "residual_after": {"rmse": 0.021, "psnr": 33.6, "rmse_structured": 0.01},
    "effects": [{"name": "response", "params": {}, "heldout_rmse_before": 0.03, "heldout_rmse_after": 0.02,
                 "reduction": 0.33, "confidence": {"level": "high"}}],
    "selected": ["response"], "absorbed": [], "session": {"changed": False}, "modelled": True,
    "unexplained": {"detected": False, "explained_share": 0.8, "unexplained_rmse": 0.004, "where": None},
    "regions": [{"bbox": [0, 0, 4, 4], "share": 0.55, "description": "projector border", "cause": "response"}]}

METRICS = {
    "format": "procam-evaluation", "version": 1, "complete": True, "range": None,
    "targets": [{"name": "a", "status": "done", "psnr": 25.0, "ssim": 0.9, "range_ceiling": 31.0,
                 "uncompensated": {"psnr": 20.0, "ssim": 0.8}, "image": "a_comparison.png"}],
    "mean": {"psnr": 25.0, "ssim": 0.9}, "mean_uncompensated": {"psnr": 20.0, "ssim": 0.8},
    "flicker": {"pairs": 1, "captured": 0.01, "targets": 0.008, "excess": 0.002, "uncompensated": 0.02}}

SHOW = {
    "format": "procam-show", "version": 1, "mode": "open-loop", "complete": True,
    "frames": {"1": {"number": 1, "status": "done", "file": "frame_0001.png", "psnr_model": 30.0}},
    "runs": [{"run": 1, "status": "complete", "frames": 1, "done": 1, "skipped": 0, "failed": 0, "seconds": 2.5,
              "where": "this process"}]}

COMPENSATION = {
    "format": "procam-compensation", "version": 1, "mode": "open-loop", "complete": True,
    "effects": {"used": ["response"], "not_inverted": []},
    "targets": [{"name": "a", "status": "done", "input": "a_input.png", "frame": "a_frame.png",
                 "simulated": "a_simulated.png", "seconds": 3.0, "psnr_simulated_start": 20.0,
                 "psnr_simulated": 27.5, "mode": "open-loop"}]}


def _pose() -> list[list[float]]:
    pose = np.eye(4)
    pose[:3, 3] = [0.2, -0.1, 0.05]
    return pose.tolist()


CALIBRATION = {
    "format": "procam-calibration", "camera_from_projector": _pose(), "init": "graycode",
    "surface_report": {"vertices": 120, "faces": 200, "source": "graycode"}, "losses": {"pose": 0.01, "warp": 0.04},
    "warp_report": {"corners_before_px": {"median": 2.5}, "corners_after_px": {"median": 0.1}},
    "stages": {"surface": "run", "pose": "run", "warp": "run"},
    "warnings": ["the white capture is saturated on 3% of the lit area"],
    "seconds": {"surface": 1.0, "pose": 2.0, "warp": 3.0}}


def _write(folder: Path, name: str, doc: dict) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_text(json.dumps(doc))
    return folder


def test_every_step_reads_into_a_typed_view(tmp_path):
    gap = diagnose.read(_write(tmp_path / "gap", "gap.json", GAP))
    assert gap.selected == ["response"] and gap.headline.startswith("The camera's") and len(gap.warnings) == 1
    assert [e["name"] for e in gap.effects] == ["response"] and gap.regions[0]["share"] == 0.55
    ev = evaluate.read(_write(tmp_path / "ev", "metrics.json", METRICS))
    write_image(tmp_path / "ev" / "a_comparison.png", np.zeros((4, 4, 3), np.float32))
    assert ev.complete and ev.mean["psnr"] == 25.0 and ev.targets[0]["name"] == "a"
    assert ev.comparisons() == [("a", tmp_path / "ev" / "a_comparison.png")]
    sh = show.read(_write(tmp_path / "show", "show.json", SHOW))
    assert sh.complete and sh.status == "complete" and sh.frames["1"]["status"] == "done" and len(sh.runs) == 1


def test_a_comparison_image_outside_the_evaluation_folder_is_refused(tmp_path):
    doc = {**METRICS, "targets": [{**METRICS["targets"][0], "image": "../elsewhere.png"}]}
    with pytest.raises(evaluate.EvaluationError, match="comparison image"):
        evaluate.read(_write(tmp_path / "ev", "metrics.json", doc)).comparisons()


def _printed(capsys, what: str, summary) -> None:
    out = capsys.readouterr().out
    assert summary.ok
    assert out.splitlines() == [f"{what}", f"  {summary.headline}", *(f"  {line}" for line in summary.lines)]


def test_each_command_prints_its_steps_summary(tmp_path, monkeypatch, capsys):
    cal = _write(tmp_path / "cal", "calibration.json", CALIBRATION)
    target = tmp_path / "a.png"
    write_image(target, np.zeros((4, 4, 3), np.float32))

    def step(name: str, doc: dict, result=None):
        def run(options, progress=None, cancel=None, **_):
            _write(Path(options.out), name, doc)
            return result(options) if result else doc
        return run

    monkeypatch.setattr("procam.addon.cli.calibrate.calibrate", step("calibration.json", CALIBRATION))
    assert main(["calibrate", str(tmp_path), "--out", str(tmp_path / "c"), "--no-blend-output"]) == EXIT_OK
    _printed(capsys, f"calibration: {tmp_path / 'c'}", calibrate.summary(tmp_path / "c"))
    _write(tmp_path / "c", "transport.json", {"megabytes": 12, "seconds": 25.2})
    s = calibrate.summary(tmp_path / "c")
    assert "warning: the white capture is saturated on 3% of the lit area" in s.lines
    assert s.lines[-1] == "transport operator: 12 MB in 25 s"  # added later by a precompute: still shown

    monkeypatch.setattr("procam.addon.cli.diagnose.diagnose", step("gap.json", GAP))
    assert main(["diagnose", str(cal), "--out", str(tmp_path / "d")]) == EXIT_OK
    s = diagnose.summary(tmp_path / "d")
    _printed(capsys, f"diagnosis: {tmp_path / 'd'}", s)
    assert "selected: response" in s.lines
    assert any(line.startswith("held-out residual: RMSE 0.0310") for line in s.lines)

    monkeypatch.setattr("procam.addon.cli.evaluate.evaluate", step("metrics.json", METRICS))
    assert main(["evaluate", str(cal), "--inputs", str(tmp_path), "--targets", str(target), "--device", "lab:x",
                 "--out", str(tmp_path / "e")]) == EXIT_OK
    s = evaluate.summary(tmp_path / "e")
    _printed(capsys, f"evaluation: {tmp_path / 'e'}", s)
    assert any("flicker over 1 consecutive pair(s)" in line for line in s.lines)

    monkeypatch.setattr("procam.addon.cli.compensate.compensate",
                        step("compensation.json", COMPENSATION, lambda o: compensate.CompensationView(o.out, {}, [])))
    assert main(["compensate", str(cal), str(target), "--out", str(tmp_path / "k")]) == EXIT_OK
    s = compensate.summary(tmp_path / "k")
    _printed(capsys, f"compensation: {tmp_path / 'k'}", s)
    assert "effect models: response" in s.lines

    monkeypatch.setattr("procam.addon.cli.show.prepare_show",
                        step("show.json", SHOW, lambda o: show.ShowResult(Path(o.out), done=[1], total=1)))
    assert main(["show", str(cal), str(target), "--out", str(tmp_path / "s")]) == EXIT_OK
    s = show.summary(tmp_path / "s")
    _printed(capsys, f"show: {tmp_path / 's'}", s)
    assert "run 1: 1 frame(s) compensated, 0 already finished, 0 failed, 2.5 s (this process)" in s.lines
