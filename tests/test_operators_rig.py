"""Calibrate Rig and Import Captures' depth and photograph controls headless through bpy.ops: the real board
photographs in, rig.json out and handed to Import Captures; bad inputs reported, nothing written."""

import json
import os
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from procam.addon import jobs  # noqa: E402
from procam.addon.blender import rig as blender_rig  # noqa: E402
from procam.addon.capture.format import CaptureSet  # noqa: E402
from procam.addon.imageio import read_image, write_image  # noqa: E402
from procam.addon.steps import rig as rig_step  # noqa: E402
from tests.test_calibrate_rig import POSES, REAL, needs_real  # noqa: E402
from tests.test_panels import RecordingLayout, texts  # noqa: E402


def _board_scene(sessions: Path, out: Path, pattern: str = "*") -> bpy.types.Scene:
    scene = bpy.context.scene
    scene.procam_board_sessions_dir = str(sessions)
    scene.procam_board_sessions_filter = pattern
    scene.procam_board_corners = (9, 7)
    scene.procam_board_projector_size = (1024, 768)
    scene.procam_rig_file = str(out)
    return scene


def _linked_sessions(root: Path, poses: list[str]) -> Path:
    """A parent folder whose subfolders link to the real poses' images (cheap; any image can be replaced)."""
    for p in poses:
        (root / p).mkdir(parents=True)
        for f in sorted((REAL / p).glob("graycode_*.png")):
            os.symlink(f, root / p / f.name)
    return root


def _draw_board_panel() -> str:
    calls = []
    bpy.types.PROCAM_PT_board.draw(type("Drawn", (), {"layout": RecordingLayout(calls)})(), bpy.context)
    return " ".join(t for t in texts(calls).split(" | ") if t)  # wrapped lines joined again


@needs_real
def test_calibrate_rig_on_the_real_photographs_fills_import_captures(registered, tmp_path, capfd):
    """The realdata folder holds the four poses and, beside them, the pattern images themselves: the name filter
    keeps the poses; the rig.json agrees with the CLI's bounds and becomes Import Captures' Rig Calibration."""
    out = tmp_path / "rig.json"
    scene = _board_scene(REAL, out, "capture_*")
    assert "4 board poses: capture_0, capture_1, capture_2, capture_3" in _draw_board_panel()
    assert bpy.ops.procam.calibrate_rig() == {"FINISHED"}
    cal = rig_step.read(out)
    assert cal.used == tuple(POSES) and cal.stereo_rms < 1.0 and not cal.metric
    assert json.loads(out.read_text())["sessions"] == [str(REAL / p) for p in POSES]
    assert jobs.BOARD.get("calibrate_rig").status == jobs.DONE
    assert scene.procam_rig_file == str(out)
    assert bpy.context.window_manager.operator_properties_last("procam.import_captures").rig_file == str(out)
    report = capfd.readouterr()
    said = report.out + report.err
    assert "Rig calibrated from 4 of 4 poses" in said and "capture_3 " in said and "stereo" in said
    assert "stereo RMS" in _draw_board_panel()
    # An existing rig.json is kept unless Replace Results is on.
    with pytest.raises(RuntimeError, match="never overwritten"):
        bpy.ops.procam.calibrate_rig()
    assert jobs.BOARD.get("calibrate_rig").status == jobs.FAILED


@needs_real
def test_calibrate_rig_bad_inputs_are_reported(registered, tmp_path):
    """Each mistake is an error report that says what to do; no rig.json appears and the scene keeps its path."""
    out = tmp_path / "rig.json"
    scene = bpy.context.scene
    with pytest.raises(RuntimeError, match="choose the folder of board sessions"):
        bpy.ops.procam.calibrate_rig()
    sessions = _linked_sessions(tmp_path / "board", POSES[:3])
    (sessions / "notes").mkdir()  # a subfolder without images is not a pose
    scene = _board_scene(sessions / POSES[0], out)
    with pytest.raises(RuntimeError, match="holds the images of one pose itself"):
        bpy.ops.procam.calibrate_rig()
    scene.procam_board_sessions_dir = str(sessions)
    scene.procam_board_sessions_filter = "capture_[01]"
    assert "2 board poses: capture_0, capture_1 (at least 3 needed)" in _draw_board_panel()
    with pytest.raises(RuntimeError, match=r"2 board pose folder\(s\).*capture_0, capture_1.*at least 3"):
        bpy.ops.procam.calibrate_rig()
    scene.procam_board_sessions_filter = "*"
    scene.procam_board_projector_size = (1920, 1080)  # the step refuses: these sessions hold 42 images, not 46
    with pytest.raises(RuntimeError, match="1920×1080.*46"):
        bpy.ops.procam.calibrate_rig()
    assert jobs.BOARD.get("calibrate_rig").status == jobs.FAILED
    # A pose whose board cannot be found is skipped by name; two poses left are too few.
    scene.procam_board_projector_size = (1024, 768)
    white = sessions / POSES[2] / "graycode_40.png"
    img = read_image(white)
    white.unlink()
    write_image(white, np.full_like(img, float(np.median(img))))
    with pytest.raises(RuntimeError, match=r"only 2 of 3 board poses are usable.*capture_2.*chessboard"):
        bpy.ops.procam.calibrate_rig()
    assert not out.exists() and scene.procam_rig_file == str(out)
    assert bpy.context.window_manager.operator_properties_last("procam.import_captures").rig_file == ""


def test_import_captures_with_depth_units_and_without_the_exposure_check(registered, tmp_path, capfd):
    """A depth map in millimetres given as such arrives in metres; the exposure check can be turned off; a depth
    file that does not exist is reported, and nothing is written."""
    import cv2

    scene = bpy.context.scene
    bpy.ops.procam.create_rig(camera_width=96, camera_height=72, projector_width=120, projector_height=90)
    assert bpy.ops.procam.export_patterns(directory=str(tmp_path / "seq")) == {"FINISHED"}
    photos = tmp_path / "photos"
    photos.mkdir()
    w, h = blender_rig.read_camera(scene).intrinsics.size
    for i, f in enumerate(sorted((tmp_path / "seq").glob("[0-9]*.png"))):
        write_image(photos / f"IMG_{i + 1:04d}.png", cv2.resize(read_image(f), (w, h), interpolation=cv2.INTER_AREA))
    depth = tmp_path / "depth.npy"
    np.save(depth, np.full((h, w), 1500.0, np.float32))  # 1.5 m, in millimetres
    common = dict(sequence_dir=str(tmp_path / "seq"), photos_dir=str(photos), encoding="linear")
    with pytest.raises(RuntimeError, match="depth file .*missing.npy does not exist"):
        bpy.ops.procam.import_captures(out_dir=str(tmp_path / "bad"), depth_file=str(tmp_path / "missing.npy"),
                                       **common)
    with pytest.raises(RuntimeError, match="depth sensor's width and height"):
        bpy.ops.procam.import_captures(out_dir=str(tmp_path / "bad"), depth_file=str(depth), depth_native_width=64,
                                       **common)
    assert not (tmp_path / "bad").exists() and scene.procam_capture_dir == ""
    assert bpy.ops.procam.import_captures(out_dir=str(tmp_path / "set"), depth_file=str(depth), depth_units="mm",
                                          check_exposure=False, **common) == {"FINISHED"}
    cs = CaptureSet.load(tmp_path / "set")
    assert scene.procam_capture_dir == str(tmp_path / "set")
    assert np.allclose(cs.depth(), 1.5)
    assert cs.notes["depth"]["units"] == "millimetres (given)" and "exposure" not in cs.notes
    said = capfd.readouterr()
    assert "depth from depth.npy (mm), exposure not checked" in said.out + said.err
