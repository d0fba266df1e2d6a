"""One front door per step: each step run once through ``procam`` and once through its Blender operator writes the
same folder (manifests equal apart from where they are, when and how long), and each loads with the step's ``read``.

Tiny lab (camera 96×72) and few iterations: this checks the plumbing, not the optimisation.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")  # before pymeshlab (shared Embree), and the operators need it

from procam.addon.capture.format import CaptureSet  # noqa: E402
from procam.addon.cli.app import main  # noqa: E402
from procam.addon.imageio import read_image, write_image  # noqa: E402
from procam.addon.steps import calibrate, compensate, diagnose, evaluate, show  # noqa: E402

#: Keys whose values say when or how long, not what: left out of the comparison.
VOLATILE = ("seconds", "time", "written", "started", "finished", "procam_version", "fit_seconds")
#: A written frame's checksum and size (these exact keys only): Dr.Jit's parallel sums can move one pixel by one
#: 16-bit level between two runs (seen: 1 of 32,400 values), which changes them; the frames themselves are
#: compared by :func:`_same_frames`. Input hashes (calibration, sources) are still compared.
FRAME_FINGERPRINT = ("sha256", "bytes")


def _normal(value, roots):
    """A manifest with its folders' paths replaced by a placeholder and the volatile keys left out."""
    if isinstance(value, dict):
        return {k: _normal(v, roots) for k, v in value.items()
                if k not in FRAME_FINGERPRINT and not any(w in k for w in VOLATILE)}
    if isinstance(value, list):
        return [_normal(v, roots) for v in value]
    if isinstance(value, str):
        for root in roots:
            value = value.replace(str(root), "ROOT")
        return value
    if isinstance(value, float) and math.isfinite(value):
        return float(f"{value:.6g}")  # render sums may differ in the last bits between two runs
    return value


def _same(a: Path, b: Path, manifest: str, roots) -> None:
    da = _normal(json.loads((a / manifest).read_text()), roots)
    db = _normal(json.loads((b / manifest).read_text()), roots)
    assert da == db


def _same_frames(a: Path, b: Path) -> None:
    """The frame files of two folders: the same names, pixels within two 16-bit levels."""
    names = sorted(p.name for p in a.glob("frame_*.png"))
    assert names and names == sorted(p.name for p in b.glob("frame_*.png"))
    for name in names:
        assert np.abs(read_image(a / name) - read_image(b / name)).max() <= 2 / 65535


def test_every_step_writes_the_same_folder_from_the_command_line_and_from_blender(registered, tmp_path):
    scene = bpy.context.scene
    cli, ui = tmp_path / "cli", tmp_path / "ui"
    roots = (cli, ui)
    lab = ["--surface", "vedge", "--scale", "0.15", "--samples", "4", "--seed", "0"]

    # capture (the virtual lab)
    assert main(["lab", *lab, "--out", str(cli / "captures"), "--truth", str(cli / "truth.json")]) == 0
    assert bpy.ops.procam.run_lab(surface="vedge", use_scene_rig=False, samples=4, scale=0.15, seed=0,
                                  out_dir=str(ui / "captures"), truth_path=str(ui / "truth.json")) == {"FINISHED"}
    _same(cli / "captures", ui / "captures", "capture.json", roots)
    CaptureSet.load(ui / "captures")
    captures, truth = cli / "captures", cli / "truth.json"  # one lab set for the steps after it

    # calibrate
    assert main(["calibrate", str(captures), "--out", str(cli / "calibration"), "--no-blend-output",
                 "--projector-intrinsics", "fit"]) == 0
    scene.procam_capture_dir, scene.procam_calibration_dir = str(captures), str(ui / "calibration")
    scene.procam_projector_intrinsics = "fit"
    assert bpy.ops.procam.calibrate() == {"FINISHED"}
    _same(cli / "calibration", ui / "calibration", "calibration.json", roots)
    assert "projector_intrinsics" in json.loads((ui / "calibration" / "calibration.json").read_text())
    calibrate.read(ui / "calibration")
    cal = cli / "calibration"  # one calibration for the steps after it (its hash is in their manifests)

    # compensate, closed loop through the lab
    targets = tmp_path / "targets"
    targets.mkdir()
    rng = np.random.default_rng(3)
    for i in range(2):
        write_image(targets / f"t{i}.png", rng.uniform(0.2, 0.8, (30, 40, 3)).astype(np.float32))
    files = sorted(targets.glob("*.png"))
    assert main(["compensate", str(cal), *map(str, files), "--out", str(cli / "compensation"), "--iterations", "3",
                 "--device", f"lab:{truth}"]) == 0
    scene.procam_calibration_dir, scene.procam_compensation_dir = str(cal), str(ui / "compensation")
    for f in files:
        scene.procam_targets.add().filepath = str(f)
    scene.procam_compensation_mode, scene.procam_device, scene.procam_iterations = "CLOSED", f"lab:{truth}", 3
    assert bpy.ops.procam.compensate() == {"FINISHED"}
    _same(cli / "compensation", ui / "compensation", "compensation.json", roots)
    assert len(compensate.read(ui / "compensation").targets) == 2

    # evaluate, through the lab
    assert main(["evaluate", str(cal), "--inputs", str(cli / "compensation"), "--targets", *map(str, files),
                 "--device", f"lab:{truth}", "--out", str(cli / "evaluation")]) == 0
    scene.procam_evaluation_dir = str(ui / "evaluation")
    assert bpy.ops.procam.evaluate() == {"FINISHED"}
    _same(cli / "evaluation", ui / "evaluation", "metrics.json", roots)
    assert evaluate.read(ui / "evaluation").complete

    # show, open loop, from the image sequence folder
    assert main(["show", str(cal), str(targets), "--out", str(cli / "show"), "--iterations", "3"]) == 0
    scene.procam_compensation_mode, scene.procam_target_folder = "OPEN", str(targets)
    scene.procam_targets.clear()
    scene.procam_show_dir = str(ui / "show")
    assert bpy.ops.procam.prepare_show() == {"FINISHED"}
    _same(cli / "show", ui / "show", "show.json", roots)
    _same_frames(cli / "show", ui / "show")
    assert show.read(ui / "show").complete

    # export the compensated frames
    assert main(["export-frames", str(cli / "compensation"), "--out", str(cli / "frames")]) == 0
    scene.procam_compensation_dir = str(ui / "compensation")
    assert bpy.ops.procam.export_frames(directory=str(ui / "frames")) == {"FINISHED"}
    _same(cli / "frames", ui / "frames", "frames.json", roots)
    _same_frames(cli / "frames", ui / "frames")

    # diagnose (the defaults of both front-ends)
    assert main(["diagnose", str(cal), "--out", str(cli / "diagnosis")]) == 0
    scene.procam_diagnosis_dir = str(ui / "diagnosis")
    assert bpy.ops.procam.diagnose() == {"FINISHED"}
    _same(cli / "diagnosis", ui / "diagnosis", "gap.json", roots)
    assert diagnose.read(ui / "diagnosis").selected is not None

    # A capture set whose camera lens was taken out (undistort-captures): its calibration lives in the pinhole
    # camera, so the lab's frames must go through that lens, whichever front door projects through the lab.
    rig = _rig_file(tmp_path / "rig.json", CaptureSet.load(captures), [-0.3, 0.1, 0.0, 0.0, 0.0])
    assert main(["undistort-captures", str(captures), "--rig", str(rig), "--out", str(tmp_path / "pinhole")]) == 0
    lens_cal = tmp_path / "pinhole-calibration"
    assert main(["calibrate", str(tmp_path / "pinhole"), "--out", str(lens_cal), "--no-blend-output"]) == 0
    assert "camera_lens_removed" in json.loads((lens_cal / "calibration.json").read_text())
    assert main(["compensate", str(lens_cal), *map(str, files), "--out", str(cli / "lens-compensation"),
                 "--iterations", "3", "--device", f"lab:{truth}"]) == 0
    assert main(["evaluate", str(lens_cal), "--inputs", str(cli / "lens-compensation"), "--targets",
                 *map(str, files), "--device", f"lab:{truth}", "--out", str(cli / "lens-evaluation")]) == 0
    scene.procam_calibration_dir, scene.procam_compensation_dir = str(lens_cal), str(ui / "lens-compensation")
    scene.procam_evaluation_dir = str(ui / "lens-evaluation")
    scene.procam_compensation_mode, scene.procam_device, scene.procam_iterations = "CLOSED", f"lab:{truth}", 3
    assert bpy.ops.procam.compensate() == {"FINISHED"}
    _same(cli / "lens-compensation", ui / "lens-compensation", "compensation.json", roots)
    assert bpy.ops.procam.evaluate() == {"FINISHED"}
    _same(cli / "lens-evaluation", ui / "lens-evaluation", "metrics.json", roots)


def _rig_file(path: Path, captures: CaptureSet, distortion) -> Path:
    """A rig.json as `procam calibrate-rig` writes it for the lab set's camera and projector, with ``distortion``
    as the camera's lens (board squares: the set keeps its own projector pose)."""
    from procam.addon.stages.rig_calibration import RigCalibration
    from procam.addon.steps.rig import write

    cam, proj = captures.camera.intrinsics, captures.projector.intrinsics
    return write(path, RigCalibration.known(cam.size, proj.size, cam.opencv_matrix(), distortion,
                                            proj.opencv_matrix()))
