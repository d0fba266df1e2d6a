"""The calibration folder end to end on lab data, and what a failed calibration leaves behind (nothing)."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from procam.addon.cli.app import main
from procam.addon.errors import CalibrationError
from procam.addon.lab.truth import LabTruth
from procam.addon.capture.format import CaptureSet
from procam.addon.imageio import read_image, write_image
from procam.addon.stages.calibrate import white_saturation
from procam.addon.blender.blend_file import save_calibration_blend
from procam.addon.steps.calibrate import CalibrateOptions
from procam.addon.steps.calibrate import read as read_calibration
from procam.addon.steps.calibrate import run as run_calibration
from procam.addon.stages.metrics import psnr, ssim


@pytest.fixture(scope="module")
def calibrated(lab_set, tmp_path_factory):
    captures, truth = lab_set("vedge", "realistic")
    out = tmp_path_factory.mktemp("cal") / "calibration"
    cal = run_calibration(CalibrateOptions(captures, out, with_blend=True), blend_writer=save_calibration_blend)
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
    back = read_calibration(out)
    assert np.allclose(back.rig.projector.camera_from_projector, est.camera_from_projector)
    assert back.warp is not None and np.allclose(back.warp.w_shifts, cal.warp.w_shifts, atol=1e-5)
    assert doc["white_saturated_share"] < 0.01 and back.warnings == []  # realistic: its glossy lobe clips 0.1 %


def test_a_saturated_white_capture_is_reported(calibrated, tmp_path, capsys):
    """A highlight or too long an exposure clips the white capture: the albedo is then too dark, so say so."""
    captures, _, _, _ = calibrated
    bright = tmp_path / "bright"
    shutil.copytree(captures, bright)
    white = bright / CaptureSet.load(bright, verify_images=False).entry("white").file
    write_image(white, np.clip(3.0 * read_image(white), 0, 1))
    share = white_saturation(CaptureSet.load(bright))
    assert share > 0.3
    assert main(["calibrate", str(bright), "--out", str(tmp_path / "cal"), "--stages", "surface",
                 "--no-blend-output"]) == 0
    assert "saturated on" in capsys.readouterr().out
    cal = read_calibration(tmp_path / "cal", complete=False)
    assert cal.report["white_saturated_share"] == pytest.approx(share)
    assert "shorter exposure" in cal.warnings[0]


def test_the_calibration_keeps_the_camera_lens_its_photographs_lost(calibrated, tmp_path):
    """A capture set imported with a rig file records the camera lens taken out of its photographs; its
    calibration keeps that record, so a live camera's frames go through the same lens even where the capture set
    is no longer beside the calibration (tests/test_capture.py: test_a_live_camera_sees_through_…)."""
    from procam.addon.steps.stage_c import camera_lens_of

    captures, _, _, _ = calibrated
    mine = tmp_path / "set"
    shutil.copytree(captures, mine)
    doc = json.loads((mine / "capture.json").read_text())
    cam = CaptureSet.load(mine, verify_images=False).camera.intrinsics
    doc["camera_lens_removed"] = {"camera": cam.to_dict(), "distortion": [-0.1, 0.02, 0, 0, 0], "source": "rig"}
    (mine / "capture.json").write_text(json.dumps(doc))
    assert main(["calibrate", str(mine), "--out", str(tmp_path / "cal"), "--stages", "surface",
                 "--no-blend-output"]) == 0
    shutil.rmtree(mine)
    lens = camera_lens_of(read_calibration(tmp_path / "cal", complete=False))
    assert lens is not None and np.allclose(lens.distortion, [-0.1, 0.02, 0, 0, 0]) and lens.camera == cam


def test_an_albedo_brighter_than_the_simulated_irradiance_is_not_clipped(calibrated, tmp_path):
    """Read in camera units the albedo exceeds 1 where the camera is brighter than the simulation (a gain, a tone
    curve): it is kept, so the model is not too dark there; a spike far above the surface's brightest is capped."""
    from procam.addon.stages.calibrate import ALBEDO_SPIKE, albedo_from_captures

    captures, _, _, cal = calibrated
    base = albedo_from_captures(CaptureSet.load(captures), cal.surface, cal.rig)
    bright = tmp_path / "bright"
    shutil.copytree(captures, bright)
    brighter = CaptureSet.load(bright, verify_images=False)
    for kind in ("white", "black"):
        path = bright / brighter.entry(kind).file
        write_image(path, np.clip(1.25 * read_image(path), 0, 1))
    albedo = albedo_from_captures(CaptureSet.load(bright), cal.surface, cal.rig)
    lit = base.mean(axis=2) > 0.3
    ratio = np.median(albedo[lit] / base[lit], axis=0)
    assert np.allclose(ratio, 1.25, atol=0.03) and (albedo[lit] > 1.0).mean() > 0.1
    assert albedo.max() <= ALBEDO_SPIKE * np.percentile(albedo[lit], 99.9) + 1e-6


def test_existing_calibration_is_not_overwritten(calibrated):
    captures, _, out, _ = calibrated
    before = (out / "calibration.json").read_bytes()
    assert main(["calibrate", str(captures), "--out", str(out), "--no-blend-output"]) == 2
    assert (out / "calibration.json").read_bytes() == before


def _copy_without(captures: Path, folder: Path, kinds: tuple[str, ...]) -> Path:
    """A copy of a capture set whose manifest leaves out the images of ``kinds``."""
    shutil.copytree(captures, folder)
    doc = json.loads((folder / "capture.json").read_text())
    doc["images"] = [e for e in doc["images"] if e["kind"] not in kinds]
    (folder / "capture.json").write_text(json.dumps(doc))
    return folder


def test_failed_calibration_leaves_nothing(calibrated, tmp_path):
    captures, _, _, _ = calibrated
    broken = _copy_without(captures, tmp_path / "broken", ("checker", "graycode"))
    with pytest.raises(CalibrationError, match="neither a checkerboard nor Gray-code"):
        run_calibration(CalibrateOptions(broken, tmp_path / "cal"))
    assert not (tmp_path / "cal").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["broken"]


def test_a_session_without_a_checkerboard_gets_its_warp_from_the_gray_code(calibrated, tmp_path):
    """OpenCV's structured-light sequence has no checkerboard: stage B fits the warp to the decoded Gray code."""
    captures, _, _, _ = calibrated
    session = _copy_without(captures, tmp_path / "session", ("checker", "surface"))
    run_calibration(CalibrateOptions(session, tmp_path / "cal", precompute=False))  # the warp is weighed, no stage C
    report = json.loads((tmp_path / "cal" / "calibration.json").read_text())["warp_report"]
    assert report["source"] == "graycode"
    assert report["corners_after_px"]["median"] < 0.6  # the decoded texel is whole: ±0.5 in each axis


def test_a_pose_from_the_spec_states_its_uncertainty_and_it_covers_the_error(calibrated):
    """A pose fitted with the intrinsics as given came with no ± at all: it now states one σ of position and axis
    (the Gray code's spread, the depth sensor's errors, each spec value wrong by its prior), which covers its true
    error, names what makes most of it, and says the camera's lens is not in it when none was calibrated."""
    from procam.addon.stages.intrinsics import COVER_SIGMAS
    from procam.addon.steps.calibrate import summary

    _, truth_path, out, cal = calibrated
    u = json.loads((out / "calibration.json").read_text())["pose_uncertainty"]
    assert u["intrinsics"] == "held as given" and u["given_by"] == "spec" and u["camera_lens"] == "none calibrated"
    truth, est = LabTruth.load(truth_path).rig.projector, cal.rig.projector
    error_m = float(np.linalg.norm(est.position - truth.position))
    error_deg = float(np.degrees(np.arccos(np.clip(est.direction @ truth.direction, -1, 1))))
    assert 0 < error_m <= COVER_SIGMAS * u["position_std_m"] and error_deg <= COVER_SIGMAS * u["axis_std_deg"]
    assert {"data", "depth bias", "projector_focal at its spec", "camera_focal at its spec"} <= set(u["parts"])
    whole = np.sqrt(sum(p["position_m"] ** 2 for p in u["parts"].values()))
    assert whole == pytest.approx(u["position_std_m"], rel=1e-9)  # the parts make the whole
    line = next(t for t in summary(out).lines if t.startswith("Pose uncertainty"))
    assert f"±{100 * u['position_std_m']:.1f} cm" in line and "most of the position from" in line
    assert "taken as distortion-free" in line


def test_metrics():
    rng = np.random.default_rng(0)
    a = rng.random((40, 50, 3)).astype(np.float32)
    assert psnr(a, a) == float("inf") and ssim(a, a) == pytest.approx(1.0)
    assert psnr(np.clip(a + 0.01, 0, 1), a) == pytest.approx(40.0, abs=0.6)
    assert ssim(np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1), a) < 0.9


def test_depth_bias_read_from_the_wall_image(calibrated):
    """The lab's capture set carries the depth sensor's image of a wall at a known distance; calibration reads
    the sensor's bias from it (never from the truth) and the surface lies where the true one is."""
    captures, truth_path, _, cal = calibrated
    sr = cal.report["surface_report"]
    bias = LabTruth.load(truth_path).effects["depth_noise"]["bias"]
    assert bias > 0 and sr["depth_offset"] == pytest.approx(bias, abs=0.002)
    assert sr["depth_offset_source"].startswith("wall depth image depth/wall.npy")
    from procam.addon.capture.format import CaptureSet
    from procam.addon.stages.surface import scene_depth
    cs = CaptureSet.load(captures)
    depth, offset, source = scene_depth(cs, 0.004)
    assert offset == 0.004 and source == "given" and depth.shape == cs.depth_info.intrinsics.size[::-1]


def test_wall_offset_refuses_bad_walls():
    from procam.addon.errors import SurfaceError
    from procam.addon.surface.reconstruct import wall_depth_offset
    wall = np.full((30, 40), 1.51)
    assert wall_depth_offset(wall, 1.5) == pytest.approx(0.01)
    with pytest.raises(SurfaceError, match="mostly empty"):
        wall_depth_offset(np.where(np.arange(40) < 35, np.nan, wall), 1.5)
    with pytest.raises(SurfaceError, match="more than a sensor bias"):
        wall_depth_offset(wall * 1000, 1.5)  # millimetres
    with pytest.raises(SurfaceError, match="wall distance"):
        wall_depth_offset(wall, -1)


def test_stages_one_at_a_time(calibrated, tmp_path, capsys):
    """Surface, then pose, then warp, each a run of its own: each reuses the folder's earlier stages, an
    unfinished calibration is refused where a complete one is needed, and the end equals one full run."""
    captures, _, _, full = calibrated
    out = tmp_path / "cal"
    with pytest.raises(CalibrationError, match="run the earlier stages first"):
        run_calibration(CalibrateOptions(captures, out, stages="pose"))
    with pytest.raises(CalibrationError, match="skip one"):
        run_calibration(CalibrateOptions(captures, out, stages="surface,warp"))
    cal = run_calibration(CalibrateOptions(captures, out, stages="surface", with_blend=False))
    assert cal.stages == {"surface": "run", "pose": "not run", "warp": "not run"} and cal.warp is None
    with pytest.raises(CalibrationError, match="has not run pose, warp yet.*--stages pose,warp"):
        read_calibration(out)
    assert main(["compensate", str(out), "city", "--out", str(tmp_path / "comp")]) == 2
    assert "has not run pose, warp yet" in capsys.readouterr().err
    with pytest.raises(CalibrationError, match="has not run stage\\(s\\) pose"):
        run_calibration(CalibrateOptions(captures, out, stages="warp"))
    cal = run_calibration(CalibrateOptions(captures, out, stages="pose", with_blend=False))
    assert cal.stages == {"surface": "reused", "pose": "run", "warp": "not run"}
    assert np.allclose(cal.rig.projector.camera_from_projector, full.rig.projector.camera_from_projector, atol=1e-6)
    assert main(["calibrate", str(captures), "--out", str(out), "--stages", "warp", "--no-blend-output"]) == 0
    done = read_calibration(out)
    assert done.stages == {"surface": "reused", "pose": "reused", "warp": "run"} and not done.missing_stages
    assert np.allclose(done.warp.w_shifts, full.warp.w_shifts, atol=1e-5)
    names = {p.name for p in (out / "diagnostics").iterdir()}
    assert {"pose_mask.png", "warp_grid.png"} <= names  # the pose's images kept through the warp-only run
    other = tmp_path / "other"
    shutil.copytree(captures, other)
    with pytest.raises(CalibrationError, match="was made from"):
        run_calibration(CalibrateOptions(other, out, stages="warp"))


@pytest.mark.parametrize("shift", ["0,127", "-60,-200"])
def test_a_projector_far_from_its_image_calibrates(tmp_path, shift):
    """A real projector's lens shift (its principal point 1.27 or 2 image heights outside the frame) goes through
    the lab, Gray-code PnP, stage A and stage B like the demo's 15 %."""
    captures, truth_path = tmp_path / "captures", tmp_path / "truth.json"
    assert main(["lab", "--out", str(captures), "--truth", str(truth_path), "--surface", "curve", "--scale", "0.25",
                 "--samples", "4", f"--projector-shift={shift}"]) == 0
    truth = LabTruth.load(truth_path).rig.projector
    assert truth.intrinsics.shift == pytest.approx(tuple(float(v) / 100 for v in shift.split(",")))
    cal = run_calibration(CalibrateOptions(captures, tmp_path / "calibration", precompute=False))  # no stage C here
    est = cal.rig.projector
    assert est.intrinsics == truth.intrinsics
    assert np.linalg.norm(est.position - truth.position) < 0.01
    assert np.degrees(np.arccos(np.clip(est.direction @ truth.direction, -1, 1))) < 0.3


@pytest.fixture(scope="module")
def wrong_spec(tmp_path_factory):
    """Lab sets whose projector spec is 10 % off in focal length and 20 % of the height off in lens shift."""
    root = tmp_path_factory.mktemp("spec")

    def make(surface: str, shift: str = "0,15", camera_fov_error: float = 0.0, effects: str = ""):
        name = f"{surface}-{shift.replace(',', '_')}-{camera_fov_error:g}{'-' + effects if effects else ''}"
        captures, truth = root / name, root / f"{name}.truth.json"
        if not captures.exists():
            assert main(["lab", "--out", str(captures), "--truth", str(truth), "--surface", surface, "--scale", "0.4",
                         "--samples", "4", "--nominal-error", "10,20", "--projector-shift", shift,
                         "--camera-fov-error", str(camera_fov_error), *(["--effects", effects] if effects else [])
                         ]) == 0
        return captures, LabTruth.load(truth)
    return make


@pytest.mark.parametrize("shift", ["0,15", "0,127"])
def test_projector_intrinsics_fitted_without_a_board(wrong_spec, tmp_path, shift):
    """A spec 10 % off in focal length and 20 % of the height in shift; also with the principal point far below the
    frame, which OpenCV's own calibration refuses as a start."""
    captures, truth = wrong_spec("curve", shift)
    true_k = truth.rig.projector.intrinsics
    assert CaptureSet.load(captures).projector.intrinsics.fx == pytest.approx(1.1 * true_k.fx)
    # K and the pose are stage A's: the warp and the transport operator after it are not what this test weighs
    spec = run_calibration(CalibrateOptions(captures, tmp_path / "spec", with_blend=False, stages="surface,pose"))
    fit = run_calibration(CalibrateOptions(captures, tmp_path / "fit", with_blend=False, projector_intrinsics="fit",
                                           stages="surface,pose"))
    k = fit.rig.projector.intrinsics
    assert k.fx == pytest.approx(true_k.fx, rel=0.02) and k.fy == pytest.approx(true_k.fy, rel=0.02)
    assert abs(k.cx - true_k.cx) < 2.0 and abs(k.cy - true_k.cy) < 2.0
    report = fit.report["projector_intrinsics"]
    assert report["determined"] == {"focal": True, "principal_point": True}
    assert report["rms_fitted_px"] < report["rms_nominal_px"]
    errors = {}
    for name, cal in (("spec", spec), ("fit", fit)):
        p, t = cal.rig.projector, truth.rig.projector
        errors[name] = (np.linalg.norm(p.position - t.position),
                        np.degrees(np.arccos(np.clip(p.direction @ t.direction, -1, 1))))
    assert errors["fit"][0] < 0.01 and errors["fit"][1] < 0.3
    assert errors["spec"][0] > 5 * errors["fit"][0]  # a wrong spec really moves the pose: the fit is what fixes it


def test_a_camera_lens_a_rig_calibration_took_out_is_not_fitted_again(wrong_spec, tmp_path):
    """Photographs whose lens a board calibration of the camera took out (undistort-captures): the fit holds the
    camera's lens at none instead of freeing it again, where it would trade against the projector's focal length,
    and says so; the projector's K and pose are still fitted."""
    from procam.addon.lab.effects import lens_of
    from procam.addon.stages.rig_calibration import RigCalibration
    from procam.addon.steps.rig import write

    captures, truth = wrong_spec("curve", effects="distortion=0.5")
    lens = lens_of(truth.effects)
    assert lens is not None and lens[0] != 0  # the lab's camera has a lens to take out
    cam, proj = truth.rig.camera.intrinsics, truth.rig.projector.intrinsics
    write(tmp_path / "rig.json", RigCalibration.known(cam.size, proj.size, cam.opencv_matrix(), [*lens, 0.0],
                                                      proj.opencv_matrix()))
    assert main(["undistort-captures", str(captures), "--rig", str(tmp_path / "rig.json"), "--out",
                 str(tmp_path / "pinhole")]) == 0
    fit = run_calibration(CalibrateOptions(tmp_path / "pinhole", tmp_path / "fit", with_blend=False,
                                           projector_intrinsics="fit", stages="surface,pose"))
    report = fit.report["projector_intrinsics"]
    held = report["camera_distortion"]
    assert held["held"] == "taken out of the photographs by a rig calibration" and not held["determined"]
    assert held["k1"] == held["k2"] == 0.0 and "not fitted again" in report["summary"]
    assert fit.rig.projector.intrinsics.fx == pytest.approx(proj.fx, rel=0.02)
    p, t = fit.rig.projector, truth.rig.projector
    assert np.linalg.norm(p.position - t.position) < 0.01
    assert np.degrees(np.arccos(np.clip(p.direction @ t.direction, -1, 1))) < 0.3


def test_a_wrong_camera_field_of_view_is_fitted_with_the_projector(wrong_spec, tmp_path):
    """The camera's FoV 5° off as well (its focal length 9.5 % short): on the curve the Gray code pins the camera's
    focal length too, and the projector's K and pose come out as with a right camera."""
    captures, truth = wrong_spec("curve", camera_fov_error=5.0)
    given = CaptureSet.load(captures).camera.intrinsics
    assert given.fx < 0.92 * truth.rig.camera.intrinsics.fx
    fit = run_calibration(CalibrateOptions(captures, tmp_path / "fit", with_blend=False, projector_intrinsics="fit",
                                           stages="surface,pose"))
    report = fit.report["projector_intrinsics"]
    assert report["camera_focal"]["determined"] and "camera focal length: fitted" in report["summary"]
    assert fit.rig.camera.intrinsics.fx == pytest.approx(truth.rig.camera.intrinsics.fx, rel=0.01)
    assert fit.rig.projector.intrinsics.fx == pytest.approx(truth.rig.projector.intrinsics.fx, rel=0.02)
    p, t = fit.rig.projector, truth.rig.projector
    assert np.linalg.norm(p.position - t.position) < 0.01
    assert np.degrees(np.arccos(np.clip(p.direction @ t.direction, -1, 1))) < 0.3


def test_a_flat_wall_leaves_the_projector_spec_as_it_is(wrong_spec, tmp_path):
    """One view of a plane cannot separate focal length from distance: the fit says so and keeps the spec."""
    captures, _ = wrong_spec("plane")
    fit = run_calibration(CalibrateOptions(captures, tmp_path / "fit", with_blend=False, projector_intrinsics="fit",
                                           stages="surface,pose"))
    report = fit.report["projector_intrinsics"]
    assert report["determined"] == {"focal": False, "principal_point": False}
    assert fit.rig.projector.intrinsics == CaptureSet.load(captures).projector.intrinsics
    assert fit.rig.camera.intrinsics == CaptureSet.load(captures).camera.intrinsics
    assert not report["camera_focal"]["determined"]
    assert "kept at the spec" in report["summary"] and "flat surface" in report["summary"]


def test_a_known_pose_from_a_rig_calibration_is_kept(calibrated, tmp_path):
    """Imported with a metric rig file, the capture set knows the projector's pose: --init nominal keeps it (the
    mask only checks it), where a rough nominal pose is refined."""
    captures, truth_path, _, _ = calibrated
    known = tmp_path / "known"
    shutil.copytree(captures, known)
    doc = json.loads((known / "capture.json").read_text())
    pose = LabTruth.load(truth_path).rig.projector.camera_from_projector
    doc["projector"]["camera_from_projector"] = pose.tolist()
    doc["projector_pose_known"] = True
    (known / "capture.json").write_text(json.dumps(doc))
    cal = run_calibration(CalibrateOptions(known, tmp_path / "cal", init="nominal", stages="surface,pose",
                                           with_blend=False))
    assert np.array_equal(cal.rig.projector.camera_from_projector, pose)
    assert cal.report["pose"]["info"]["pose_known"] and cal.report["pose"]["info"]["mask_check"]["iou"] > 0.9
