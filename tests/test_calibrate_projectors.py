"""Calibrating several projectors into one calibration folder: the surface once, stages A and B per projector, the
albedo from all of them, one transport operator per projector, and the one-projector views every step reads."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from procam.addon.capture.format import CaptureSet
from procam.addon.cli.app import main
from procam.addon.errors import CalibrationError
from procam.addon.lab.lab import run_lab
from procam.addon.lab.truth import LabTruth, make_truth
from procam.addon.outputs import write_manifest
from procam.addon.rig.model import Rig
from procam.addon.stages.calibrate import Calibration, _lit_albedo, albedo_from_projectors
from procam.addon.stages.warp_model import Warp
from procam.addon.steps import calibrate as calibrate_step
from procam.addon.steps import layout
from procam.addon.steps import transport as transport_step
from procam.addon.steps.calibrate import CalibrateOptions


def errors(cal: Calibration, truth: LabTruth) -> list[tuple[float, float]]:
    """Each projector's (position error in cm, axis error in degrees) against the lab's truth."""
    out = []
    for k in range(cal.projector_count):
        est, true = cal.for_projector(k).rig.projector, truth.rig.projectors[k]
        angle = np.degrees(np.arccos(np.clip(est.direction @ true.direction, -1, 1)))
        out.append((100 * float(np.linalg.norm(est.position - true.position)), float(angle)))
    return out


def lab(root: Path, truth) -> tuple[Path, Path]:
    run_lab(truth, root / "captures", truth_path=root / "truth.json")
    return root / "captures", root / "truth.json"


@pytest.fixture(scope="module")
def two(tmp_path_factory):
    """Two projectors side by side on the curve, 20 % overlap; camera 128×96, projectors 160×120, 4 spp;
    calibrated end to end with both transport operators."""
    root = tmp_path_factory.mktemp("two")
    captures, truth = lab(root, make_truth("curve", samples=4, camera_size=(128, 96), projector_size=(160, 120),
                                           projectors=2, overlap=0.2))
    out = root / "calibration"
    cal = calibrate_step.run(CalibrateOptions(captures, out))
    return captures, truth, out, cal


def test_two_projectors_calibrate_into_one_folder(two):
    captures, truth_path, out, cal = two
    truth = LabTruth.load(truth_path)
    assert cal.projector_count == 2 and cal.projector_index == 0
    assert cal.rig.projector is cal.rig.projectors[0] and cal.warp is cal.warps[0]
    # measured at this size: 0.16 cm / 0.06° and 0.19 cm / 0.08°
    for position_cm, angle_deg in errors(cal, truth):
        assert position_cm < 1.0 and angle_deg < 0.3, errors(cal, truth)
    doc = json.loads((out / "calibration.json").read_text())
    assert len(doc["projectors"]) == 2 and len(doc["rig"]["projectors"]) == 2
    for k, entry in enumerate(doc["projectors"]):
        assert {"camera_from_projector", "warp", "pose", "warp_report", "losses", "seconds"} <= set(entry)
        np.testing.assert_allclose(entry["camera_from_projector"], cal.rig.projectors[k].camera_from_projector)
    assert doc["camera_from_projector"] == doc["projectors"][0]["camera_from_projector"]  # a one-projector reader
    for name in ("pose_mask", "warp_grid", "p2_pose_mask", "p2_warp_grid"):
        assert (out / "diagnostics" / f"{name}.png").is_file(), name
    # read back: the same rig, warps and per-projector reports; written again, the same bytes
    back = calibrate_step.read(out)
    assert back.projector_count == 2
    for k in range(2):
        np.testing.assert_allclose(back.rig.projectors[k].camera_from_projector,
                                   cal.rig.projectors[k].camera_from_projector)
        assert np.allclose(back.warps[k].w_shifts, cal.warps[k].w_shifts, atol=1e-5)
    again = out.parent / "again.json"
    write_manifest(again, calibrate_step.manifest(back))
    assert again.read_bytes() == (out / "calibration.json").read_bytes()
    lines = "\n".join(calibrate_step.summary(out).lines)
    for text in ("Projector 1 pose", "Projector 2 pose", "Projector 2 at (", "Projector 2 warp: corners",
                 "transport operator of projector 2"):
        assert text in lines, lines
    assert "Calibrated 2 projectors" in calibrate_step.summary(out).headline


def test_each_projectors_view_is_a_one_projector_calibration(two):
    _, _, out, _ = two
    cal = calibrate_step.read(out)
    for k in range(2):
        view = cal.for_projector(k)
        assert view.projector_index == k and view.projector_count == 1 and view.rig.others == ()
        assert view.rig.projector is cal.rig.projectors[k] and view.warp is cal.warps[k]
        assert view.surface is cal.surface and view.folder == cal.folder and view.capture_dir == cal.capture_dir
        own = cal.report["projectors"][k]
        assert view.report["pose"] == own["pose"] and view.report["warp_report"] == own["warp_report"]
        assert view.report["surface_report"] == cal.report["surface_report"] and "projectors" not in view.report
        assert view.report["seconds"]["pose"] == own["seconds"]["pose"]
        assert view.for_projector(0) is view
    assert cal.for_projector(1).report["pose"] != cal.for_projector(0).report["pose"]
    for bad in (2, -1, True, "1"):
        with pytest.raises(CalibrationError, match="numbered 0 to 1"):
            cal.for_projector(bad)


def test_each_projector_has_its_transport_operator(two, capsys):
    _, _, out, _ = two
    assert layout.transport_files(0) == ("transport.npz", "transport.json")
    assert layout.transport_files(1) == ("transport_p2.npz", "transport_p2.json")
    cal = calibrate_step.read(out)
    ops = [transport_step.load(cal.for_projector(k), bounces=1, seed=0) for k in range(2)]
    assert all(op is not None for op in ops)
    assert json.loads((out / "transport_p2.json").read_text())["file"] == "transport_p2.npz"
    # each lights its own part of the camera: their direct light differs
    lit = [op.direct(np.ones((*op.input_size[::-1], 3), np.float32)).mean(axis=-1) > 0.01 for op in ops]
    assert lit[0].any() and lit[1].any() and (lit[0] != lit[1]).mean() > 0.1
    # precompute finds both stored; removing projector 2's renders that one only
    assert main(["precompute", str(out)]) == 0
    assert capsys.readouterr().out.count("transport operator in") == 2
    (out / "transport_p2.npz").unlink()
    assert transport_step.load(cal.for_projector(1), bounces=1, seed=0) is None
    assert main(["precompute", str(out)]) == 0
    assert "(projector 2, transport_p2.npz)" in capsys.readouterr().out
    assert transport_step.load(cal.for_projector(1), bounces=1, seed=0) is not None


def test_the_albedo_comes_from_every_projector(two):
    captures, _, _, cal = two
    cs = CaptureSet.load(captures)
    views = [(cs.for_projector(k), cal.for_projector(k).rig) for k in range(2)]
    both = albedo_from_projectors(views, cal.surface)
    parts = [_lit_albedo(c, cal.surface, r, 0.05) for c, r in views]
    only_second = parts[1][1] & ~parts[0][1]
    assert only_second.mean() > 0.05
    # where only projector 2 lights, its own reading, not the photo that fills in where none does (but for the few
    # spikes capped at ALBEDO_SPIKE × the lit 99th percentile)
    same = np.isclose(both[only_second], np.clip(parts[1][0][only_second], 0, None), rtol=1e-5, atol=1e-6)
    assert same.all(axis=1).mean() > 0.99
    overlap = parts[0][1] & parts[1][1]
    low, high = np.minimum(parts[0][0], parts[1][0]), np.maximum(parts[0][0], parts[1][0])
    assert np.all((both[overlap] >= low[overlap] - 1e-5) & (both[overlap] <= high[overlap] + 1e-5))


def test_stages_rerun_for_every_projector(two, tmp_path):
    captures, _, out, cal = two
    part = tmp_path / "part"
    shutil.copytree(out, part)
    done = calibrate_step.run(CalibrateOptions(captures, part, stages="warp", precompute=False))
    assert done.stages == {"surface": "reused", "pose": "reused", "warp": "run"}
    for k in range(2):
        np.testing.assert_allclose(done.rig.projectors[k].camera_from_projector,
                                   cal.rig.projectors[k].camera_from_projector)
        assert done.for_projector(k).report["pose"] == cal.for_projector(k).report["pose"]
    assert (part / "diagnostics" / "p2_pose_mask.png").is_file()  # projector 2's pose images kept


@pytest.mark.parametrize("kind, message", [
    ("white", "projector 2: the white capture .* is no brighter than the black capture"),
    ("graycode", "projector 2: the Gray-code captures .* decode to only 0 camera pixels"),
])
def test_a_projector_that_lights_nothing_is_named_and_nothing_written(two, tmp_path, kind, message):
    captures, _, _, _ = two
    bad = tmp_path / "bad"
    shutil.copytree(captures, bad)
    cs = CaptureSet.load(bad, verify_images=False)
    black = next(e for e in cs.entries if e.kind == "black" and e.projector == 1)
    for e in cs.entries:
        if e.projector == 1 and e.kind == kind:
            shutil.copy(bad / black.file, bad / e.file)  # projector 2 dark: its frames never reached the camera
    with pytest.raises(CalibrationError, match=message):
        calibrate_step.run(CalibrateOptions(bad, tmp_path / "cal"))
    assert not (tmp_path / "cal").exists()


def test_options_of_one_projector_are_refused_for_several(two, tmp_path):
    captures, _, _, _ = two
    with pytest.raises(CalibrationError, match="is one projector's"):
        calibrate_step.run(CalibrateOptions(captures, tmp_path / "b", init="given", initial_pose=np.eye(4)))
    assert list(tmp_path.iterdir()) == []


def test_each_projectors_intrinsics_fitted_to_its_own_gray_code_the_camera_held(two, tmp_path):
    """--projector-intrinsics fit with several projectors: each projector's K judged on its own Gray code (its own
    record and summary line), the camera's focal length held as given (every projector's poses rest on it)."""
    captures, truth_path, _, spec = two
    cal = calibrate_step.run(CalibrateOptions(captures, tmp_path / "fit", projector_intrinsics="fit",
                                              precompute=False))
    given = CaptureSet.load(captures, verify_images=False).camera.intrinsics
    assert cal.rig.camera.intrinsics == given
    for k in range(2):
        fit = cal.for_projector(k).report["projector_intrinsics"]
        held = fit["uncertainty"]["values"]["camera_focal"]
        assert held["kept"] == "spec" and held["reason"] == "shared", held
        assert fit["camera_focal"]["held"] == "shared" and not fit["camera_focal"]["determined"]
        assert "every projector's" in fit["summary"]
    text = "\n".join(calibrate_step.summary(tmp_path / "fit").lines)
    assert text.count("projector intrinsics (fitted to the Gray code)") == 2
    # the lab's spec is right here: fitted or kept, no projector lands worse than with the spec by more than a hair
    for (p_fit, a_fit), (p_spec, a_spec) in zip(errors(cal, LabTruth.load(truth_path)),
                                                errors(spec, LabTruth.load(truth_path))):
        assert p_fit < p_spec + 0.3 and a_fit < a_spec + 0.1


def test_projectors_of_different_resolutions(tmp_path):
    laid = make_truth("plane", samples=2, camera_size=(128, 96), projector_size=(160, 120), projectors=2)
    small = laid.rig.projectors[1].scaled(120, 90)
    captures, truth_path = lab(tmp_path, make_truth("plane", samples=2, rig=Rig(laid.rig.camera, laid.rig.projector,
                                                                                   (small,))))
    cal = calibrate_step.run(CalibrateOptions(captures, tmp_path / "cal", precompute=False))
    assert [p.intrinsics.size for p in cal.rig.projectors] == [(160, 120), (120, 90)]
    assert cal.warps[0].size != cal.warps[1].size
    for position_cm, angle_deg in errors(cal, LabTruth.load(truth_path)):  # measured: 0.26 cm / 0.11°, 0.17 / 0.07
        assert position_cm < 1.0 and angle_deg < 0.3


def test_a_calibration_of_one_projector_is_written_as_before(tmp_path):
    """No ``projectors`` list for one projector, for_projector(0) is itself, its operator keeps its names; with
    two (the truth's rig, no stages run) the list is written and read back."""
    truth = make_truth("plane", camera_size=(64, 48), projector_size=(80, 60), projectors=2)
    for count in (1, 2):
        rig = truth.rig if count == 2 else Rig(truth.rig.camera, truth.rig.projector)
        warps = [Warp.identity(p.input_size) for p in rig.projectors]
        cal = Calibration(rig, truth.surface, warps[0], "captures", {"stages": {}}, other_warps=tuple(warps[1:]))
        folder = tmp_path / f"cal{count}"
        folder.mkdir()
        calibrate_step.write(folder, cal, {})
        doc = json.loads((folder / "calibration.json").read_text())
        assert ("projectors" in doc) == (count == 2) and ("projectors" in doc["rig"]) == (count == 2)
        back = calibrate_step.read(folder)
        assert back.projector_count == count and len(back.warps) == count
        if count == 1:
            assert back.for_projector(0) is back
            assert list(doc) == ["format", "version", "capture_set", "rig", "camera_from_projector", "warp",
                                 "surface", "stages"]
        else:
            assert back.for_projector(1).warp.size == warps[1].size


def test_the_scene_holds_every_projector(two, tmp_path, run_python):
    from procam.addon.blender.blend_file import save_calibration_blend

    _, _, out, _ = two
    cal = calibrate_step.read(out)
    folder = tmp_path / "cal"
    folder.mkdir()
    calibrate_step.write(folder, cal, {}, blend_writer=save_calibration_blend)
    proc = run_python("""
        import sys, json, bpy
        from procam.addon.blender import rig as blender_rig
        bpy.ops.wm.open_mainfile(filepath=sys.argv[1], load_ui=False)
        scene = bpy.data.scenes["ProCam Calibration"]
        print(json.dumps([p.camera_from_projector.tolist() for p in blender_rig.read_rig(scene).projectors]))
    """, str(folder / "scene.blend"))
    assert proc.returncode == 0, proc.stderr
    poses = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(poses) == 2
    for k in range(2):
        np.testing.assert_allclose(poses[k], cal.rig.projectors[k].camera_from_projector, atol=1e-4)


def test_a_projector_left_on_during_anothers_sequence_is_refused_by_name(tmp_path):
    """Projector 2 showed grey while projector 1's black capture was taken: calibrate refuses, naming both, before
    any stage runs (the set has no Gray code or checkerboard: the check comes first), and writes nothing."""
    from procam.addon.errors import CaptureError

    rig = make_truth("plane", camera_size=(64, 48), projector_size=(80, 60), projectors=2).rig
    shape = (48, 64, 3)
    left, right = np.zeros(shape), np.zeros(shape)
    left[:, :36], right[:, 28:] = 0.6, 0.6  # projector 1 lights the left, projector 2 the right
    rng = np.random.default_rng(3)

    def write(path: Path, leak: float) -> Path:
        with CaptureSet.writer(path, rig.camera, rig.projector, others=rig.others) as w:
            for k, (proj, light) in enumerate(zip(rig.projectors, (left, right))):
                size = (*proj.intrinsics.size[::-1], 3)
                on = leak * right if k == 0 else 0.0
                w.add("black", np.clip(0.02 + on + rng.normal(0, 0.01, shape), 0, 1), projector_index=k,
                      frame=np.zeros(size))
                w.add("white", np.clip(0.02 + light + on + rng.normal(0, 0.01, shape), 0, 1), projector_index=k,
                      frame=np.ones(size))
        return path

    with pytest.raises(CaptureError, match="projector 2 was not black while projector 1's captures were taken"):
        calibrate_step.run(CalibrateOptions(write(tmp_path / "leak", 0.5), tmp_path / "cal", with_blend=False))
    assert not (tmp_path / "cal").exists()
    # the same set taken properly gets past the check, to the next refusal (no pattern for stage B)
    with pytest.raises(CalibrationError, match="neither a checkerboard nor Gray-code"):
        calibrate_step.run(CalibrateOptions(write(tmp_path / "fine", 0.0), tmp_path / "cal", with_blend=False))
