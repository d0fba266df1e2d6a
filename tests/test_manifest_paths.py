"""A manifest that names a file outside its folder (absolute, ``../``, or through a symlink) is refused by every
reader with exit 2, and nothing outside the folders the user gave is read or copied (issue 37, items 3–5)."""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from procam.addon.cli.app import main
from procam.addon.imageio import write_image
from procam.addon.steps import layout

SECRET = b"not yours to read"
_opened: list[str] | None = None


def _audit(event: str, args: tuple) -> None:
    if event == "open" and _opened is not None and isinstance(args[0], (str, bytes, os.PathLike)):
        _opened.append(os.fsdecode(args[0]))


sys.addaudithook(_audit)  # one hook for the session (hooks cannot be removed); it records only inside opened()


@contextmanager
def opened() -> Iterator[list[str]]:
    """The files opened in this process meanwhile (resolved), from Python's audit events."""
    global _opened
    _opened = []
    seen = _opened
    try:
        yield seen
    finally:
        _opened = None
        seen[:] = [os.path.realpath(p) for p in seen]


def _outside(tmp_path: Path, name: str = "secret.png", shape: tuple[int, int] = (60, 80)) -> Path:
    """An image outside every folder given to the command, that a manifest tries to reach."""
    folder = tmp_path / "elsewhere"
    folder.mkdir(exist_ok=True)
    path = folder / name
    write_image(path, np.full((*shape, 3), 0.5, np.float32))
    return path


def _read_outside(seen: list[str], outside: Path) -> list[str]:
    root = os.path.realpath(outside)
    return [p for p in seen if p == root or p.startswith(root + os.sep)]


# -- item 3: export-frames copies what compensation.json names ------------------------------------------------

def _compensation(folder: Path, frame: str) -> Path:
    """A compensation folder whose one finished target names ``frame`` as its projector frame."""
    folder.mkdir()
    for name in ("a_input.png", "a_frame.png", "a_simulated.png"):
        write_image(folder / name, np.zeros((60, 80, 3), np.float32))
    doc = {"format": layout.COMPENSATION.format, "version": 1,
           "targets": [{"name": "a", "status": "done", "input": "a_input.png", "frame": frame,
                        "simulated": "a_simulated.png", "psnr_simulated": 30.0, "seconds": 1.0, "mode": "forward",
                        "area": {"x": 0, "y": 0, "width": 60, "height": 60}}]}
    (folder / layout.COMPENSATION.manifest).write_text(json.dumps(doc))
    return folder


def test_export_frames_of_an_honest_compensation_copies_its_frame(tmp_path: Path) -> None:
    comp = _compensation(tmp_path / "comp", "a_frame.png")
    assert main(["export-frames", str(comp), "--out", str(tmp_path / "frames")]) == 0
    assert (tmp_path / "frames" / "frame_0001.png").read_bytes() == (comp / "a_frame.png").read_bytes()


@pytest.mark.parametrize("how", ["absolute", "climbing", "symlink", "symlinked folder"])
def test_export_frames_refuses_a_frame_outside_the_compensation(tmp_path: Path, how: str, capsys) -> None:
    secret = _outside(tmp_path)
    secret.write_bytes(SECRET)
    comp = tmp_path / "comp"
    frame = {"absolute": str(secret), "climbing": "../elsewhere/secret.png", "symlink": "link.png",
             "symlinked folder": "frames/secret.png"}[how]
    _compensation(comp, frame)
    if how == "symlink":
        os.symlink(secret, comp / "link.png")
    if how == "symlinked folder":
        os.symlink(secret.parent, comp / "frames")
    out = tmp_path / "frames"
    with opened() as seen:
        assert main(["export-frames", str(comp), "--out", str(out)]) == 2
    assert not out.exists()
    assert _read_outside(seen, secret.parent) == []
    assert "names files inside itself" in capsys.readouterr().err


# -- item 4: import-captures copies a pattern that sequence.json names outside the sequence ----------------------

FRAME = (80, 60)
CAM = (64, 48)


def _sequence(tmp_path: Path) -> tuple[Path, Path]:
    """A small exported sequence (no Gray code) and plain photographs of it, one per frame."""
    from procam.addon.capture.sequence import export_sequence
    from procam.addon.rig.model import Projector, projector_intrinsics_from_throw

    proj = Projector(projector_intrinsics_from_throw(FRAME[0], FRAME[1], 1.25, 0.0, 0.15), input_size=(60, 60))
    seq = export_sequence(proj, tmp_path / "seq", checker_size=10, graycode=False, validation=False)
    photos = tmp_path / "photos"
    photos.mkdir()
    frames = json.loads((seq / "sequence.json").read_text())["frames"]
    for i, _ in enumerate(frames):
        write_image(photos / f"IMG_{i:04d}.png", np.full((CAM[1], CAM[0], 3), 0.2 + 0.01 * i, np.float32))
    return seq, photos


def _import(seq: Path, photos: Path, out: Path) -> int:
    return main(["import-captures", str(seq), str(photos), "--out", str(out), "--no-exposure-check"])


def test_import_captures_of_an_honest_sequence(tmp_path: Path) -> None:
    from procam.addon.capture.format import CaptureSet

    seq, photos = _sequence(tmp_path)
    assert _import(seq, photos, tmp_path / "set") == 0
    assert CaptureSet.load(tmp_path / "set").entries_of("white")


@pytest.mark.parametrize("how", ["absolute", "climbing", "symlink"])
def test_import_captures_refuses_a_pattern_outside_the_sequence(tmp_path: Path, how: str, capsys) -> None:
    seq, photos = _sequence(tmp_path)
    secret = _outside(tmp_path)
    manifest = seq / "sequence.json"
    doc = json.loads(manifest.read_text())
    white = next(f for f in doc["frames"] if f["kind"] == "white")
    if how == "symlink":
        (seq / white["file"]).unlink()
        os.symlink(secret, seq / white["file"])
    else:
        white["file"] = str(secret) if how == "absolute" else "../elsewhere/secret.png"
        manifest.write_text(json.dumps(doc))
    out = tmp_path / "set"
    with opened() as seen:
        assert _import(seq, photos, out) == 2
    assert not out.exists()
    assert _read_outside(seen, secret.parent) == []
    assert "names files inside itself" in capsys.readouterr().err


# -- item 5: a capture set whose image, pattern or depth folder is a symlink leaving it ----------------------------

@pytest.mark.parametrize("folder", ["images", "patterns"])
def test_a_capture_set_with_a_symlinked_folder_leaving_it_is_refused(tmp_path: Path, folder: str, capsys) -> None:
    from procam.addon.capture.format import CaptureSet
    from procam.addon.errors import CaptureError

    seq, photos = _sequence(tmp_path)
    assert _import(seq, photos, tmp_path / "set") == 0
    capsys.readouterr()
    moved = tmp_path / "elsewhere" / folder
    moved.parent.mkdir()
    (tmp_path / "set" / folder).rename(moved)
    os.symlink(moved, tmp_path / "set" / folder)
    with pytest.raises(CaptureError, match="outside"):
        CaptureSet.load(tmp_path / "set", verify_images=False)
    with opened() as seen:
        assert main(["calibrate", str(tmp_path / "set"), "--out", str(tmp_path / "cal")]) == 2
    assert not (tmp_path / "cal").exists()
    assert _read_outside(seen, moved.parent) == []
    assert "outside" in capsys.readouterr().err


def test_a_capture_set_whose_depth_file_links_outside_is_refused(tmp_path: Path) -> None:
    from procam.addon.capture.format import CaptureSet, CaptureSetWriter, DepthInfo
    from procam.addon.errors import CaptureError
    from procam.addon.rig.model import Camera, Projector, intrinsics_from_fov, projector_intrinsics_from_throw

    camera = Camera(intrinsics_from_fov(CAM[0], CAM[1], 58.0))
    proj = Projector(projector_intrinsics_from_throw(FRAME[0], FRAME[1], 1.25, 0.0, 0.15), input_size=(60, 60))
    with CaptureSetWriter(tmp_path / "set", camera, proj, depth_info=DepthInfo(camera.intrinsics, CAM)) as w:
        w.add("white", np.full((CAM[1], CAM[0], 3), 0.5, np.float32))
        entry = w.add_depth(np.full((CAM[1], CAM[0]), 2.0, np.float32))
    CaptureSet.load(tmp_path / "set")
    secret = tmp_path / "elsewhere" / "depth.npy"
    secret.parent.mkdir()
    np.save(secret, np.full((CAM[1], CAM[0]), 3.0, np.float32))
    (tmp_path / "set" / entry.file).unlink()
    os.symlink(secret, tmp_path / "set" / entry.file)
    with opened() as seen, pytest.raises(CaptureError, match="outside"):
        CaptureSet.load(tmp_path / "set")
    assert _read_outside(seen, secret.parent) == []


# -- item 5: calibration.json's surface mesh and diagnostics ----------------------------------------------------

def _mesh_file(path: Path) -> Path:
    np.savez(path, vertices=np.array([[0, 0, 2], [1, 0, 2], [0, 1, 2]], np.float64), faces=np.array([[0, 1, 2]]),
             uvs=np.zeros((3, 2)), albedo=np.full((4, 4, 3), 0.5, np.float32))
    return path


def _calibration(folder: Path, mesh: object) -> Path:
    """A calibration folder (every stage run) whose manifest names ``mesh`` as its surface."""
    from procam.addon.rig.model import Camera, Projector, Rig, intrinsics_from_fov, projector_intrinsics_from_throw

    rig = Rig(Camera(intrinsics_from_fov(CAM[0], CAM[1], 58.0)),
              Projector(projector_intrinsics_from_throw(FRAME[0], FRAME[1], 1.25, 0.0, 0.15), input_size=(60, 60)))
    folder.mkdir()
    _mesh_file(folder / "surface.npz")
    doc = {"format": layout.CALIBRATION.format, "version": 1, "rig": rig.to_dict(), "capture_set": "",
           "surface": {"mesh": mesh}}
    (folder / layout.CALIBRATION.manifest).write_text(json.dumps(doc))
    return folder


def test_an_honest_calibration_reads_its_own_mesh(tmp_path: Path) -> None:
    from procam.addon.steps import calibrate

    cal = _calibration(tmp_path / "cal", "surface.npz")
    assert calibrate.read(cal).surface.vertices.shape == (3, 3)
    assert calibrate.identity(cal)["surface_sha256"]


@pytest.mark.parametrize("how", ["absolute", "climbing", "symlink", "not a name"])
def test_a_calibration_mesh_outside_its_folder_is_refused(tmp_path: Path, how: str) -> None:
    from procam.addon.errors import CalibrationError
    from procam.addon.steps import calibrate

    (tmp_path / "elsewhere").mkdir()
    secret = _mesh_file(tmp_path / "elsewhere" / "mesh.npz")
    mesh = {"absolute": str(secret), "climbing": "../elsewhere/mesh.npz", "symlink": "linked.npz",
            "not a name": ["surface.npz"]}[how]
    cal = _calibration(tmp_path / "cal", mesh)
    if how == "symlink":
        os.symlink(secret, cal / "linked.npz")
    with opened() as seen:
        with pytest.raises(CalibrationError):
            calibrate.read(cal)
        with pytest.raises(CalibrationError):
            calibrate.identity(cal)
        assert main(["precompute", str(cal)]) == 2
    assert _read_outside(seen, secret.parent) == []


def test_calibration_diagnostics_linked_outside_are_refused(tmp_path: Path) -> None:
    from procam.addon.errors import CalibrationError
    from procam.addon.steps import calibrate

    cal = _calibration(tmp_path / "cal", "surface.npz")
    secret = _outside(tmp_path, "warp.png")
    os.symlink(secret.parent, cal / layout.DIAGNOSTICS_DIR)
    with opened() as seen, pytest.raises(CalibrationError, match="outside"):
        calibrate.read_view(cal)
    assert _read_outside(seen, secret.parent) == []


# -- the rule, other readers: evaluate's inputs (a compensation or a show folder) --------------------------------

AREA = {"x": 0, "y": 0, "width": 60, "height": 60}


@pytest.mark.parametrize("how", ["absolute", "climbing", "symlink"])
def test_evaluate_refuses_compensated_inputs_outside_their_folder(tmp_path: Path, how: str) -> None:
    from procam.addon.steps.evaluate import CompensationInputs, InputsError

    secret = _outside(tmp_path)
    comp = tmp_path / "comp"
    frame = {"absolute": str(secret), "climbing": "../elsewhere/secret.png", "symlink": "link.png"}[how]
    _compensation(comp, "a_frame.png")
    doc = json.loads((comp / layout.COMPENSATION.manifest).read_text())
    assert CompensationInputs.load(comp).records["a"].frame == comp / "a_frame.png"
    doc["targets"][0]["frame"] = frame
    (comp / layout.COMPENSATION.manifest).write_text(json.dumps(doc))
    if how == "symlink":
        os.symlink(secret, comp / "link.png")
    with pytest.raises(InputsError, match="names files inside itself"):
        CompensationInputs.load(comp)


@pytest.mark.parametrize("how", ["absolute", "climbing", "symlink"])
def test_evaluate_refuses_show_frames_outside_the_show(tmp_path: Path, how: str) -> None:
    from procam.addon.steps.evaluate import CompensationInputs, InputsError

    secret = _outside(tmp_path)
    show = tmp_path / "show"
    show.mkdir()
    write_image(show / "frame_0001.png", np.zeros((60, 80, 3), np.float32))
    entry = {"number": 1, "status": "done", "file": "frame_0001.png", "source": str(tmp_path / "a.png"),
             "area": AREA}
    doc = {"format": layout.SHOW.format, "version": 1, "frames": {"1": entry}}
    (show / layout.SHOW.manifest).write_text(json.dumps(doc))
    assert CompensationInputs.load(show).records["a"].frame == show / "frame_0001.png"
    entry["file"] = {"absolute": str(secret), "climbing": "../elsewhere/secret.png", "symlink": "frame_0002.png"}[how]
    if how == "symlink":
        os.symlink(secret, show / "frame_0002.png")
    (show / layout.SHOW.manifest).write_text(json.dumps(doc))
    with pytest.raises(InputsError, match="names files inside itself"):
        CompensationInputs.load(show)


# -- the rule, fixed names too: a link in a folder never takes ProCam outside it ------------------------------

def test_a_transport_operator_linked_from_another_folder_is_refused(tmp_path: Path) -> None:
    from procam.addon.stages.transport import TransportError
    from procam.addon.steps import calibrate, transport

    cal_dir = _calibration(tmp_path / "cal", "surface.npz")
    ident = calibrate.identity(cal_dir)
    (tmp_path / "elsewhere").mkdir()
    np.savez(tmp_path / "elsewhere" / "transport.npz", matrix=np.zeros(3))
    os.symlink(tmp_path / "elsewhere" / "transport.npz", cal_dir / layout.TRANSPORT_NPZ)
    (cal_dir / layout.TRANSPORT_JSON).write_text(json.dumps(
        {"calibration_sha256": ident["sha256"], "surface_sha256": ident["surface_sha256"], "bounces": 1, "seed": 0}))
    cal = calibrate.read(cal_dir)
    with opened() as seen, pytest.raises(TransportError, match="outside"):
        transport.load(cal, bounces=1, seed=0)
    assert _read_outside(seen, tmp_path / "elsewhere") == []


def test_a_lab_truth_mesh_linked_outside_is_refused(tmp_path: Path) -> None:
    from procam.addon.errors import LabError
    from procam.addon.lab.truth import TRUTH_FORMAT, LabTruth

    (tmp_path / "elsewhere").mkdir()
    secret = _mesh_file(tmp_path / "elsewhere" / "mesh.npz")
    (tmp_path / "set").mkdir()
    os.symlink(secret, tmp_path / "set" / "truth_mesh.npz")
    truth = tmp_path / "set" / "truth.json"
    truth.write_text(json.dumps({"format": TRUTH_FORMAT, "surface": {"mesh": "truth_mesh.npz"}}))
    with opened() as seen, pytest.raises(LabError):
        LabTruth.load(truth)
    assert _read_outside(seen, secret.parent) == []
