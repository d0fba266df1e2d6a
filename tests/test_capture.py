"""Capture sets, patterns, devices and the capture CLI (issue 3, items 1–3), at small sizes."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from procam.addon.capture import patterns
from procam.addon.capture.devices import Device, FolderDevice, capture_sequence
from procam.addon.capture.sequence import export_sequence, load_sequence
from procam.addon.capture.photos import import_captures, removed_lens
from procam.addon.capture.format import CaptureSet, DepthInfo, linear_to_srgb, srgb_to_linear
from procam.addon.capture.patterns import (calibration_sequence, checkerboard, decode_gray_code,
                                           decode_gray_code_set, gray_code_bits, gray_code_layout,
                                           gray_code_patterns, smooth_random, validation_patterns)
from procam.addon.cli.app import main
from procam.addon.errors import CaptureError
from procam.addon.imageio import read_image, write_image
from procam.addon.rig.model import (Camera, Intrinsics, Projector, intrinsics_from_fov, look_at_pose,
                                    projector_intrinsics_from_throw)

CAM = (64, 48)
FRAME = (80, 60)
INPUT = (60, 60)


def small_camera(size=CAM) -> Camera:
    return Camera(intrinsics_from_fov(size[0], size[1], 58.0))


def small_projector(frame=FRAME, input_size=INPUT) -> Projector:
    return Projector(projector_intrinsics_from_throw(frame[0], frame[1], 1.25, 0.0, 0.15), input_size=input_size)


def true_mapping(cam_size, frame_size):
    """A smooth, known camera-pixel → projector-frame mapping (corner convention, at camera pixel centres)."""
    w, h = cam_size
    y, x = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    sx, sy = frame_size[0] / w, frame_size[1] / h
    u = 2.0 + 0.9 * sx * x + 0.04 * y + 1.5 * np.sin(y / 9.0)
    v = 1.0 + 0.03 * x + 0.88 * sy * y
    return u, v


class WarpDevice(Device):
    """A synthetic projector + camera: the camera sees the frame through a known warp, with gain and black level."""

    def __init__(self, projector: Projector, cam_size=CAM, noise: float = 0.0, seed: int = 0) -> None:
        self.projector = projector
        self.u, self.v = true_mapping(cam_size, projector.intrinsics.size)
        self.noise = noise
        self.rng = np.random.default_rng(seed)
        self.shots = 0

    def project(self, frame: np.ndarray) -> np.ndarray:
        f = self.check_frame(frame)
        # remap samples at OpenCV pixel centres: corner-convention u maps to u - 0.5.
        seen = cv2.remap(f, (self.u - 0.5).astype(np.float32), (self.v - 0.5).astype(np.float32),
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        img = 0.03 + 0.85 * seen + self.noise * self.rng.standard_normal(seen.shape)
        self.shots += 1
        return np.clip(img, 0, 1).astype(np.float32)


def write_small_set(path: Path, *, with_depth: bool = True, force: bool = False) -> CaptureSet:
    """A capture set with one entry of every kind (random images: only the format is under test)."""
    cam, proj = small_camera(), small_projector()
    rng = np.random.default_rng(1)
    shape = (CAM[1], CAM[0], 3)
    depth_info = DepthInfo(cam.intrinsics.scaled(32, 24), (32, 24)) if with_depth else None
    with CaptureSet.writer(path, cam, proj, depth_info=depth_info, target_area=(4, 4, 50, 40), force=force,
                           notes={"device": "test"}) as w:
        w.add("surface", rng.random(shape))
        w.add("black", np.full(shape, 0.02), frame=proj.frame_from_input(patterns.black(INPUT)), area="input")
        w.add("white", np.full(shape, 0.8), frame=proj.frame_from_input(patterns.white(INPUT)), area="input")
        w.add("checker", rng.random(shape), square=10, phase=0, frame=proj.frame_from_input(checkerboard(INPUT, 10, 0)))
        w.add("checker", rng.random(shape), square=10, phase=1, frame=proj.frame_from_input(checkerboard(INPUT, 10, 1)))
        w.add("graycode", rng.random(shape), axis="x", bit=0, inverted=False)
        w.add("graycode", rng.random(shape), axis="x", bit=0, inverted=True)
        w.add("validation", rng.random(shape), name="val_grey_0.5", frame=np.full((FRAME[1], FRAME[0], 3), 0.5),
              pattern="grey", level=0.5)
        w.add("target", rng.random((30, 40, 3)), name="target_mandrill")
        if with_depth:
            depth = 1.5 + 0.1 * rng.random((24, 32))
            depth[:3] = np.nan  # some missing pixels are fine
            w.add_depth(depth)
    return CaptureSet.load(path)


def siblings(path: Path) -> list[str]:
    """Hidden temporary/backup folders the writers may have left next to ``path``."""
    return sorted(p.name for p in path.parent.iterdir() if p.name.startswith(f".{path.name}."))


def edit_manifest(path: Path, change) -> None:
    doc = json.loads((path / "capture.json").read_text())
    change(doc)
    (path / "capture.json").write_text(json.dumps(doc))


# -- capture sets ---------------------------------------------------------------------------------

def test_round_trip(tmp_path):
    out = tmp_path / "set"
    cs = write_small_set(out)
    assert siblings(out) == []
    again = CaptureSet.load(out)
    assert again.camera == cs.camera and again.projector.input_size == INPUT
    assert again.target_area == (4, 4, 50, 40) and again.notes == {"device": "test"}
    assert again.colour_space == "linear" and again.projector_status == "nominal" and not again.projector_pose_known
    assert [e.kind for e in again] == ["surface", "black", "white", "checker", "checker", "graycode", "graycode",
                                       "validation", "target", "depth"]
    assert np.allclose(again.image("white"), 0.8, atol=1e-4)
    assert again.image("checker", phase=1).shape == (CAM[1], CAM[0], 3)
    assert again.image("graycode", axis="x", bit=0, inverted=True).dtype == np.float32
    assert again.image("validation", pattern="grey", level=0.5).shape == (CAM[1], CAM[0], 3)
    assert again.image("target").shape == (30, 40, 3)
    assert np.array_equal(again.pattern("checker", phase=0),
                          small_projector().frame_from_input(checkerboard(INPUT, 10, 0)))
    assert np.allclose(again.pattern("validation", name="val_grey_0.5"), 0.5, atol=1e-4)
    assert len(again.entries_of("checker")) == 2 and again.entries_of("depth")[0].file.endswith(".npy")
    d = again.depth()
    assert d.shape == (24, 32) and np.isnan(d[:3]).all() and np.nanmin(d) >= 1.5
    assert again.depth_info.native_size == (32, 24)
    with pytest.raises(CaptureError, match="2 checker images"):
        again.image("checker")
    with pytest.raises(CaptureError, match="no graycode with axis='y'"):
        again.image("graycode", axis="y", bit=0, inverted=False)
    manifest = json.loads((out / "capture.json").read_text())
    assert manifest["format"] == "procam-capture" and manifest["version"] == 1
    assert manifest["images"][3]["params"] == {"square": 10, "phase": 0}


def test_outputs_get_the_usual_modes_not_mkstemps_private_ones(tmp_path):
    # A show machine's media server or another crew account must be able to read what we write.
    out = tmp_path / "set"
    write_small_set(out)
    umask = os.umask(0o022)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o777 & ~umask
    assert {p.stat().st_mode & 0o777 for p in out.iterdir() if p.is_file()} == {0o666 & ~umask}


@pytest.fixture
def good_set(tmp_path) -> Path:
    out = tmp_path / "good"
    write_small_set(out)
    return out


def test_missing_manifest(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(CaptureError, match="capture.json is missing"):
        CaptureSet.load(tmp_path / "empty")
    with pytest.raises(CaptureError, match="does not exist"):
        CaptureSet.load(tmp_path / "nowhere")


def test_missing_file(good_set):
    (good_set / CaptureSet.load(good_set).entry("white").file).unlink()
    with pytest.raises(CaptureError, match=r"images/0002_white\.png is missing"):
        CaptureSet.load(good_set)


def test_truncated_image(good_set):
    f = good_set / CaptureSet.load(good_set).entry("checker", phase=0).file
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2])
    with pytest.raises(CaptureError, match=r"0003_checker_s10_p0\.png is unreadable or truncated"):
        CaptureSet.load(good_set)


def test_a_file_damaged_after_a_load_is_decoded_again(good_set):
    """Loading skips images this process already decoded, but only while they are the same file: bytes damaged in
    place (the same size) are read again and refused."""
    f = good_set / CaptureSet.load(good_set).entry("checker", phase=0).file
    data = bytearray(f.read_bytes())
    data[len(data) // 3:] = bytes(len(data) - len(data) // 3)
    f.write_bytes(bytes(data))
    with pytest.raises(CaptureError, match=r"0003_checker_s10_p0\.png is unreadable or truncated"):
        CaptureSet.load(good_set)


def test_wrong_size(good_set):
    e = CaptureSet.load(good_set).entry("black")
    write_image(good_set / e.file, np.zeros((CAM[1] + 2, CAM[0], 3)))
    with pytest.raises(CaptureError,
                       match=r"0001_black\.png: image is 64×50 pixels, but the camera resolution is 64×48"):
        CaptureSet.load(good_set)


def test_wrong_pattern_size(good_set):
    e = CaptureSet.load(good_set).entry("white")
    write_image(good_set / e.pattern, np.zeros((10, 10, 3)))
    with pytest.raises(CaptureError, match=r"0002_white\.png: projected pattern is 10×10"):
        CaptureSet.load(good_set)


def test_depth_mostly_empty(good_set):
    e = CaptureSet.load(good_set).entry("depth")
    d = np.zeros((24, 32), np.float32)
    d[:5] = 2.0
    write_image(good_set / e.file, d)
    with pytest.raises(CaptureError, match=r"depth\.npy: depth map is mostly empty \(79%"):
        CaptureSet.load(good_set)


def test_depth_negative_and_nan(good_set):
    e = CaptureSet.load(good_set).entry("depth")
    d = np.full((24, 32), 2.0, np.float32)
    d[0, 0] = -1.0
    write_image(good_set / e.file, d)
    with pytest.raises(CaptureError, match=r"depth\.npy: depth holds negative values"):
        CaptureSet.load(good_set)
    d[0, 0] = np.nan
    np.save(good_set / e.file, d)
    with pytest.raises(CaptureError, match=r"depth file depth/depth\.npy is unreadable .*store missing depth as 0"):
        CaptureSet.load(good_set)


def test_depth_wrong_size(good_set):
    e = CaptureSet.load(good_set).entry("depth")
    write_image(good_set / e.file, np.full((48, 64), 2.0, np.float32))
    with pytest.raises(CaptureError, match="depth is 64×48 pixels, but the depth intrinsics say 32×24"):
        CaptureSet.load(good_set)


def test_duplicate_entries(good_set):
    edit_manifest(good_set, lambda d: d["images"].append(dict(d["images"][2])))
    with pytest.raises(CaptureError, match=r"duplicate entry for file images/0002_white\.png"):
        CaptureSet.load(good_set)


def test_duplicate_names(good_set):
    def change(d):
        d["images"][1]["name"] = "white"
    edit_manifest(good_set, change)
    with pytest.raises(CaptureError, match=r"0002_white\.png\): duplicate entry name 'white'"):
        CaptureSet.load(good_set)


def test_unknown_kind(good_set):
    def change(d):
        d["images"][0]["kind"] = "sunset"
    edit_manifest(good_set, change)
    with pytest.raises(CaptureError, match=r"images/0000_surface\.png\): unknown kind 'sunset'"):
        CaptureSet.load(good_set)


def test_missing_params(good_set):
    def change(d):
        del d["images"][5]["params"]["bit"]
    edit_manifest(good_set, change)
    with pytest.raises(CaptureError,
                       match=r"0005_graycode_x00\.png\): a 'graycode' entry needs the parameter\(s\) bit"):
        CaptureSet.load(good_set)


def test_unsupported_version_and_bad_json(good_set):
    edit_manifest(good_set, lambda d: d.update(version=99))
    with pytest.raises(CaptureError, match="capture.json: capture-set version 99 is not supported"):
        CaptureSet.load(good_set)
    (good_set / "capture.json").write_text("{not json")
    with pytest.raises(CaptureError, match="capture.json is not valid JSON"):
        CaptureSet.load(good_set)


def test_path_escape_refused(good_set):
    def change(d):
        d["images"][0]["file"] = "../elsewhere.png"
    edit_manifest(good_set, change)
    with pytest.raises(CaptureError, match="file .*must be a relative path inside the folder"):
        CaptureSet.load(good_set)


def test_existing_set_not_overwritten(good_set):
    before = (good_set / "capture.json").read_bytes()
    with pytest.raises(CaptureError, match="never overwritten without --force"):
        write_small_set(good_set)
    assert (good_set / "capture.json").read_bytes() == before and siblings(good_set) == []
    write_small_set(good_set, with_depth=False, force=True)
    assert not CaptureSet.load(good_set).entries_of("depth") and not (good_set / "depth").exists()
    assert siblings(good_set) == []


def test_failed_write_leaves_old_set(good_set):
    cam, proj = small_camera(), small_projector()
    with pytest.raises(CaptureError, match="camera resolution is 64×48"), \
            CaptureSet.writer(good_set, cam, proj, force=True) as w:
        w.add("surface", np.zeros((CAM[1], CAM[0], 3)))
        w.add("white", np.zeros((10, 10, 3)))
    assert len(CaptureSet.load(good_set)) == 10 and siblings(good_set) == []
    with pytest.raises(RuntimeError), CaptureSet.writer(good_set, cam, proj, force=True) as w:
        w.add("surface", np.zeros((CAM[1], CAM[0], 3)))
        raise RuntimeError("renderer crashed")
    assert len(CaptureSet.load(good_set)) == 10 and siblings(good_set) == []


def test_identical_frames_stored_once(tmp_path):
    cam, proj = small_camera(), small_projector()
    grey = np.full((FRAME[1], FRAME[0], 3), 0.25, np.float32)
    with CaptureSet.writer(tmp_path / "set", cam, proj) as w:
        a = w.add("validation", np.zeros((CAM[1], CAM[0], 3)), name="first", frame=grey, pattern="grey", level=0.25)
        b = w.add("validation", np.zeros((CAM[1], CAM[0], 3)), name="again", frame=grey, pattern="grey", level=0.25)
    assert a.pattern == b.pattern and len(list((tmp_path / "set" / "patterns").iterdir())) == 1


def test_writer_refuses_bad_input(tmp_path):
    cam, proj = small_camera(), small_projector()
    other = tmp_path / "photos"
    other.mkdir()
    (other / "holiday.jpg").write_bytes(b"x")
    with pytest.raises(CaptureError, match="is not a capture set; refusing to replace it"):
        CaptureSet.writer(other, cam, proj, force=True)
    w = CaptureSet.writer(tmp_path / "new", cam, proj)
    with pytest.raises(CaptureError, match="values outside"):
        w.add("white", np.full((CAM[1], CAM[0], 3), 1.5))
    with pytest.raises(CaptureError, match="unknown kind 'sunset'"):
        w.add("sunset", np.zeros((CAM[1], CAM[0], 3)))
    with pytest.raises(CaptureError, match="projector frame is 80×60"):
        w.add("white", np.zeros((CAM[1], CAM[0], 3)), frame=np.zeros((60, 60, 3)))
    with pytest.raises(CaptureError, match="depth intrinsics"):
        w.add_depth(np.ones((24, 32)))
    w.abort()
    assert not (tmp_path / "new").exists() and siblings(tmp_path / "new") == []


# -- several projectors ---------------------------------------------------------------------------

FRAME2 = (64, 40)


def write_two_projector_set(path: Path) -> CaptureSet:
    """One camera, one surface photo and depth; projector 0 (80×60) and projector 1 (64×40, elsewhere)."""
    cam, first = small_camera(), small_projector()
    second = Projector(projector_intrinsics_from_throw(*FRAME2, 1.6), look_at_pose((-0.3, 0.1, 0.0), (0, 0, 1.6)))
    rng = np.random.default_rng(2)
    shape = (CAM[1], CAM[0], 3)
    with CaptureSet.writer(path, cam, first, others=(second,), depth_info=DepthInfo(cam.intrinsics, CAM)) as w:
        w.add("surface", rng.random(shape), projector="off")
        for k, proj in enumerate((first, second)):
            for kind, level in (("black", 0.0), ("white", 1.0)):
                w.add(kind, np.full(shape, 0.02 + 0.7 * level * (k + 1) / 2), projector_index=k,
                      frame=np.full((*proj.intrinsics.size[::-1], 3), level), area="frame")
        w.add_depth(np.full((CAM[1], CAM[0]), 1.6))
    return CaptureSet.load(path)


def test_two_projector_set_round_trips_and_gives_one_projector_views(tmp_path):
    cs = write_two_projector_set(tmp_path / "set")
    assert len(cs.projectors) == 2 and cs.projectors[1].intrinsics.size == FRAME2
    doc = json.loads((tmp_path / "set" / "capture.json").read_text())
    assert doc["projector"] == doc["projectors"][0] and len(doc["projectors"]) == 2
    assert [e.get("projector", 0) for e in doc["images"]] == [0, 0, 0, 1, 1, 0]  # written only when not 0
    with pytest.raises(CaptureError, match="captures of 2 projectors"):
        cs.image("white")  # single-projector code must take one projector's view
    for k, level in ((0, 0.37), (1, 0.72)):
        view = cs.for_projector(k)
        assert view.projector is cs.projectors[k] and view.others == () and view.path == cs.path
        assert [e.kind for e in view] == ["surface", "black", "white", "depth"]
        assert {e.projector for e in view} == {0}
        assert np.allclose(view.image("white"), level, atol=1e-3)
        assert view.pattern("white").shape[:2] == cs.projectors[k].intrinsics.size[::-1]
        assert view.depth().shape == (CAM[1], CAM[0])
    # one projector's view is a one-projector set: its manifest has no trace of the others
    assert "projectors" not in cs.for_projector(1).to_dict()
    assert cs.for_projector(0).for_projector(0).projector is cs.projector
    with pytest.raises(CaptureError, match="2 projector.*numbered 0 to 1.*no projector 2"):
        cs.for_projector(2)
    with pytest.raises(CaptureError, match="no projector -1"):
        cs.for_projector(-1)


def test_projectors_of_unknown_pose_may_share_the_placeholder_pose(tmp_path):
    """Imported photographs of projectors not calibrated yet: every pose is the same placeholder."""
    cam, first = small_camera(), small_projector()
    shape = (CAM[1], CAM[0], 3)
    with CaptureSet.writer(tmp_path / "set", cam, first, others=(first,)) as w:
        for k in (0, 1):
            w.add("white", np.full(shape, 0.5), projector_index=k)
    assert len(CaptureSet.load(tmp_path / "set").projectors) == 2


def test_one_projector_manifest_has_no_projector_fields(tmp_path):
    write_small_set(tmp_path / "set")
    doc = json.loads((tmp_path / "set" / "capture.json").read_text())
    assert "projectors" not in doc and not any("projector" in e for e in doc["images"])
    cs = CaptureSet.load(tmp_path / "set")
    assert cs.for_projector(0) is cs and len(cs.projectors) == 1


@pytest.mark.parametrize("change, message", [
    (lambda d: d["images"][3].update(projector=2), "numbered 0 to 1, got 2"),
    (lambda d: d["images"][3].update(projector="1"), "numbered 0 to 1, got '1'"),
    (lambda d: d["images"][0].update(projector=1), "surface image is shared by every projector"),
    (lambda d: [e.pop("projector", None) for e in d["images"]], "no captures of projector\\(s\\) 2 \\(numbered from 1"),
    (lambda d: d["projectors"][0].update(intensity=9.0), "'projector' differs from the first"),
    (lambda d: d.update(projectors=[]), "list of one or more"),
])
def test_bad_projector_indices_and_missing_sequences_are_refused(tmp_path, change, message):
    out = tmp_path / "set"
    write_two_projector_set(out)
    edit_manifest(out, change)
    with pytest.raises(CaptureError, match=message):
        CaptureSet.load(out)


def test_writer_checks_each_projector_frame_and_index(tmp_path):
    cam, first = small_camera(), small_projector()
    second = Projector(projector_intrinsics_from_throw(*FRAME2, 1.6), look_at_pose((-0.3, 0.1, 0.0), (0, 0, 1.6)))
    shape = (CAM[1], CAM[0], 3)
    w = CaptureSet.writer(tmp_path / "new", cam, first, others=(second,))
    with pytest.raises(CaptureError, match="projector 2's frame is 64×40"):
        w.add("white", np.zeros(shape), projector_index=1, frame=np.zeros((60, 80, 3)))
    with pytest.raises(CaptureError, match="numbered 0 to 1, got 2"):
        w.add("white", np.zeros(shape), projector_index=2)
    with pytest.raises(CaptureError, match="target image is shared"):
        w.add("target", np.zeros((8, 8, 3)), projector_index=1)
    w.add("white", np.zeros(shape), frame=np.zeros((60, 80, 3)))
    with pytest.raises(CaptureError, match="no captures of projector\\(s\\) 2"):
        w.commit()  # the second projector's sequence never captured
    assert not (tmp_path / "new").exists() and siblings(tmp_path / "new") == []


def test_srgb_round_trip():
    v = np.linspace(0, 1, 256, dtype=np.float32)
    assert np.allclose(linear_to_srgb(srgb_to_linear(v)), v, atol=1e-5)
    assert abs(float(srgb_to_linear(np.float32(0.5))) - 0.21404) < 1e-4


# -- patterns ---------------------------------------------------------------------------------------

def test_basic_patterns():
    c = checkerboard((40, 30), 10, 0)
    assert c.shape == (30, 40, 3) and c.dtype == np.float32
    assert c[0, 0, 0] == 0 and c[0, 10, 0] == 1 and c[10, 10, 0] == 0
    assert np.array_equal(checkerboard((40, 30), 10, 1), 1 - c)
    a, b = smooth_random((50, 40), 7), smooth_random((50, 40), 7)
    assert np.array_equal(a, b) and not np.array_equal(a, smooth_random((50, 40), 8))
    assert a.min() >= 0.05 and a.max() <= 0.95 and a.std() > 0.05
    vals = validation_patterns((50, 40), seed=3)
    assert [n for n, _, _ in vals] == ["val_grey_0.25", "val_grey_0.5", "val_grey_0.75", "val_ramp_r", "val_ramp_g",
                                       "val_ramp_b", "val_random_3", "val_random_4"]
    ramp = {n: img for n, _, img in vals}["val_ramp_g"]
    assert ramp[..., 0].max() == 0 and np.all(np.diff(ramp[0, :, 1]) > 0)
    with pytest.raises(CaptureError):
        checkerboard((40, 30), 0)


def test_calibration_sequence_order():
    proj = small_projector()
    seq = calibration_sequence(proj, 10)
    nx, ny = gray_code_bits(INPUT)
    kinds = [s.kind for s in seq]
    assert kinds[:5] == ["surface", "black", "white", "checker", "checker"]
    assert kinds[5:5 + 2 * (nx + ny)] == ["graycode"] * (2 * (nx + ny))
    assert kinds[5 + 2 * (nx + ny):] == ["validation"] * 9
    # the session closes with white again, for the diagnosis's check that nothing changed during it
    assert seq[-1].name == "val_white_end" and seq[-1].params["repeat"] == "white"
    np.testing.assert_array_equal(seq[-1].image, seq[2].image)
    assert seq[5].params == {"area": "input", "axis": "x", "bit": 0, "inverted": False, "bits": nx, "grid": [60, 60]}
    for s in seq:
        img = s.image
        assert img.shape == (FRAME[1], FRAME[0], 3) and img.dtype == np.float32
        assert img.min() >= 0 and img.max() <= 1
        # outside the input rectangle the frame stays black
        assert img[:, :proj.input_offset[0]].max() == 0
    assert seq[2].image[:, 10:70].min() == 1.0
    full = calibration_sequence(proj, 10, area="frame", graycode=False, validation=False)
    assert [s.name for s in full] == ["surface", "black", "white", "checker_s10_p0", "checker_s10_p1"]
    assert full[2].image.min() == 1.0


def test_gray_code_matches_opencv_layout():
    size = (37, 23)
    ours = gray_code_patterns(size)
    ok, cv_images = cv2.structured_light.GrayCodePattern_create(*size).generate()
    assert len(ours) == len(cv_images) == len(gray_code_layout(size))
    for (_, _, _, img), ref in zip(ours, cv_images):
        assert np.array_equal((img[..., 0] * 255).astype(np.uint8), ref)
    d = decode_gray_code([img for *_, img in ours], size)
    yy, xx = np.mgrid[0:23, 0:37]
    assert d.valid.all() and np.array_equal(d.coords[..., 0], xx + 0.5) and np.array_equal(d.coords[..., 1], yy + 0.5)


def test_gray_code_decodes_synthetic_warp():
    """Encode → warp with a known smooth mapping (plus gain, black level, noise) → decode: < 0.5 px."""
    frame = (200, 150)
    proj = Projector(projector_intrinsics_from_throw(*frame, 1.2), input_size=frame)
    dev = WarpDevice(proj, cam_size=(160, 120), noise=0.003, seed=4)
    grid = frame
    caps = [dev.project(img) for *_, img in gray_code_patterns(grid)]
    white, black = dev.project(patterns.white(grid)), dev.project(patterns.black(grid))
    d = decode_gray_code(caps, grid, white_capture=white, black_capture=black, white_threshold=0.02)
    inside = (dev.u > 1) & (dev.u < frame[0] - 1) & (dev.v > 1) & (dev.v < frame[1] - 1)
    assert d.valid[inside].mean() > 0.9  # pixels right on a stripe edge are rightly refused
    assert not d.valid[~inside & ((dev.u < -1) | (dev.v > frame[1] + 1))].any()
    ok = d.valid & inside
    err = np.abs(d.coords[ok] - np.stack([dev.u, dev.v], -1)[ok])
    assert err.max() < 0.5 + 0.05 and err.mean() < 0.3
    assert np.quantile(err, 0.99) < 0.5
    # agrees with OpenCV's own per-pixel decoder on 8-bit versions of the same captures
    gen = cv2.structured_light.GrayCodePattern_create(*grid)
    gen.setWhiteThreshold(5)
    caps8 = [np.round(c.mean(axis=2) * 255).astype(np.uint8) for c in caps]
    d8 = decode_gray_code([c.astype(np.float32) / 255 for c in caps8], grid, white_threshold=5 / 255 - 1e-6)
    for y, x in [(10, 20), (60, 80), (100, 140), (33, 7), (90, 150)]:
        err_cv, (px, py) = gen.getProjPixel(caps8, x, y)
        assert err_cv == (not d8.valid[y, x])
        if not err_cv:
            assert (px + 0.5, py + 0.5) == tuple(d8.coords[y, x])


def test_capture_sequence_and_decode_set(tmp_path):
    proj = small_projector()
    seq = calibration_sequence(proj, 10, validation=False)
    dev = WarpDevice(proj)
    cs = capture_sequence(dev, seq, tmp_path / "set", small_camera(), notes={"device": "warp"})
    assert dev.shots == len(seq) and len(CaptureSet.load(cs.path)) == len(seq)
    assert cs.entry("surface").pattern is None and cs.entry("white").pattern
    d = decode_gray_code_set(cs)
    assert d.offset == proj.input_offset and d.grid_size == INPUT
    x0, y0 = proj.input_offset
    # camera pixels that straddle the input's border see it partly lit: their true position is ambiguous
    inside = (dev.u > x0 + 1) & (dev.u < x0 + INPUT[0] - 1) & (dev.v > y0 + 1) & (dev.v < y0 + INPUT[1] - 1)
    ok = d.valid & inside
    err = np.abs(d.coords[ok] - np.stack([dev.u, dev.v], -1)[ok])
    assert ok.sum() > 0.9 * inside.sum() and err.max() < 0.55
    assert not d.valid[(dev.u < x0 - 1) | (dev.u > x0 + INPUT[0] + 1)].any()
    # Decoded once while the files stay the same (a calibration asks up to three times, through capture-set objects
    # of its own), read-only; again with other thresholds, and when a Gray-code image is retaken.
    assert decode_gray_code_set(CaptureSet.load(cs.path)) is d and not d.coords.flags.writeable
    assert decode_gray_code_set(cs, white_threshold=0.1) is not d
    kept = decode_gray_code_set(cs)
    assert decode_gray_code_set(cs) is kept
    first = cs.path / cs.entries_of("graycode")[0].file
    os.utime(first, ns=(first.stat().st_atime_ns, first.stat().st_mtime_ns + 10**9))
    again = decode_gray_code_set(cs)
    assert again is not kept and np.array_equal(again.coords, d.coords, equal_nan=True)


# -- folder workflow --------------------------------------------------------------------------------

def shoot_folder(seq_dir: Path, out: Path, suffix: str = ".png", bits: int = 16,
                 names: str | None = "IMG_{:04d}") -> Path:
    """Play the user's part: show each exported frame to a synthetic camera and save the photos.

    ``names`` None saves each photo under its frame's name.
    """
    info = load_sequence(seq_dir)
    dev = WarpDevice(info.projector)
    out.mkdir()
    for i, f in enumerate(info.frames):
        cap = dev.project(read_image(seq_dir / f["file"]))
        path = out / ((Path(f["file"]).stem if names is None else names.format(i + 100)) + suffix)
        if bits == 8:  # a phone: 8-bit sRGB-encoded
            cv2.imwrite(str(path), np.round(linear_to_srgb(cap)[..., ::-1] * 255).astype(np.uint8))
        else:
            write_image(path, cap)
    return out


def test_export_and_import(tmp_path):
    proj = small_projector()
    seq_dir = export_sequence(proj, tmp_path / "seq", checker_size=10, seed=2)
    info = load_sequence(seq_dir)
    files = sorted(p.name for p in seq_dir.iterdir())
    assert files[0] == "0000_surface.png" and files[1] == "0001_black.png" and files[-1] == "sequence.json"
    assert len(info.frames) == len(calibration_sequence(proj, 10)) == len(files) - 1
    assert read_image(seq_dir / "0002_white.png").shape == (FRAME[1], FRAME[0], 3)
    with pytest.raises(CaptureError, match="never overwritten without --force"):
        export_sequence(proj, seq_dir)

    caps = shoot_folder(seq_dir, tmp_path / "photos16")
    cs = import_captures(seq_dir, caps, None, None, tmp_path / "set16")
    white = cs.entry("white")
    assert white.params["source"] == "IMG_0102.png" and white.params["source_encoding"] == "linear 16-bit"
    assert cs.camera.intrinsics.size == CAM and cs.notes["device"] == "folder"
    assert np.array_equal(cs.pattern("white"), read_image(seq_dir / "0002_white.png"))

    caps8 = shoot_folder(seq_dir, tmp_path / "photos8", suffix=".jpg", bits=8)
    cs8 = import_captures(seq_dir, caps8, None, None, tmp_path / "set8")
    assert cs8.entry("black").params["source_encoding"] == "sRGB-encoded 8-bit, linearised on import"
    # linearised back close to the linear captures (JPEG + 8-bit quantisation aside)
    assert abs(float(cs8.image("white").mean()) - float(cs.image("white").mean())) < 0.01
    assert decode_gray_code_set(cs8).valid.mean() > 0.5

    # FolderDevice replays the imported captures for exactly the frames that were shown
    dev = FolderDevice(cs.path)
    seq = calibration_sequence(proj, 10, seed=2)
    assert np.array_equal(dev.project(seq[3].image), cs.image("checker", phase=0))
    assert np.array_equal(dev.capture_off(), cs.image("surface"))
    with pytest.raises(CaptureError, match="never captured"):
        dev.project(np.full((FRAME[1], FRAME[0], 3), 0.123, np.float32))
    with pytest.raises(CaptureError, match="native resolution"):
        dev.project(np.zeros((10, 10, 3)))


def test_photos_named_after_their_frames_import_in_frame_order(tmp_path):
    # Frame names end in a pattern's own index (…_graycode_x00, …_graycode_x00_inv), which repeats:
    # their last number cannot order them.
    proj = small_projector()
    seq_dir = export_sequence(proj, tmp_path / "seq", checker_size=10, seed=2)
    caps = shoot_folder(seq_dir, tmp_path / "photos", suffix=".jpg", bits=8, names=None)
    assert (caps / "0006_graycode_x00_inv.jpg").is_file()
    cs = import_captures(seq_dir, caps, None, None, tmp_path / "set")
    frames = load_sequence(seq_dir).frames
    assert [e.params["source"] for e in cs.entries] == [Path(f["file"]).stem + ".jpg" for f in frames]
    assert cs.entry("white").params["source"] == "0002_white.jpg"
    assert cs.entry("checker", phase=0).params["source"] == "0003_checker_s10_p0.jpg"


def test_import_truncated_leaves_nothing(tmp_path):
    proj = small_projector()
    seq_dir = export_sequence(proj, tmp_path / "seq", checker_size=10, graycode=False)
    caps = shoot_folder(seq_dir, tmp_path / "photos")
    victim = sorted(caps.iterdir())[4]
    victim.write_bytes(victim.read_bytes()[:-200])
    out = tmp_path / "set"
    with pytest.raises(CaptureError, match=rf"{victim.name} is truncated"):
        import_captures(seq_dir, caps, None, None, out)
    assert not out.exists() and siblings(out) == []
    # a JPEG cut short decodes in OpenCV with a grey tail: we refuse it too
    jpgs = shoot_folder(seq_dir, tmp_path / "jpgs", suffix=".jpg", bits=8)
    victim = sorted(jpgs.iterdir())[2]
    victim.write_bytes(victim.read_bytes()[: victim.stat().st_size // 2])
    with pytest.raises(CaptureError, match=rf"{victim.name} is truncated"):
        import_captures(seq_dir, jpgs, None, None, out)
    assert not out.exists() and siblings(out) == []


def test_import_mismatches(tmp_path):
    proj = small_projector()
    seq_dir = export_sequence(proj, tmp_path / "seq", checker_size=10, graycode=False)
    caps = shoot_folder(seq_dir, tmp_path / "photos")
    sorted(caps.iterdir())[-1].unlink()
    with pytest.raises(CaptureError, match=r"the sequence has 14 frames but .* holds 13 captures"):
        import_captures(seq_dir, caps, None, None, tmp_path / "set")
    caps2 = shoot_folder(seq_dir, tmp_path / "photos2")
    with pytest.raises(CaptureError, match="camera resolution is 32×24"):
        import_captures(seq_dir, caps2, Camera(intrinsics_from_fov(32, 24, 60)), None, tmp_path / "set")
    shutil.copy(sorted(caps2.iterdir())[0], caps2 / "extra.png")
    with pytest.raises(CaptureError, match="without a number in their name: extra.png"):
        import_captures(seq_dir, caps2, None, None, tmp_path / "set")
    with pytest.raises(CaptureError, match="sequence.json is missing"):
        import_captures(caps, caps2, None, None, tmp_path / "set")
    assert not (tmp_path / "set").exists()


# -- CLI --------------------------------------------------------------------------------------------

def test_cli_patterns_and_import(tmp_path, capsys):
    seq = tmp_path / "seq"
    args = ["patterns", "--projector-width", "80", "--projector-height", "60", "--input-width", "60",
            "--input-height", "60", "--checker", "10", "--no-graycode", "--out", str(seq)]
    assert main(args) == 0
    assert "wrote 14 frames" in capsys.readouterr().out
    assert main(args) == 2
    assert "never overwritten without --force" in capsys.readouterr().err
    assert main(args + ["--force"]) == 0
    assert main(["patterns", "--projector-width", "80", "--projector-height", "60", "--input-width", "60",
                 "--out", str(tmp_path / "x")]) == 2
    assert main(["patterns", "--projector-width", "80", "--projector-height", "60", "--checker", "500",
                 "--out", str(tmp_path / "x")]) == 2
    assert "checker size" in capsys.readouterr().err and not (tmp_path / "x").exists()

    caps = shoot_folder(seq, tmp_path / "photos")
    out = tmp_path / "set"
    assert main(["import-captures", str(seq), str(caps), "--out", str(out), "--camera-width", "64",
                 "--camera-height", "48"]) == 0
    assert "14 images, camera 64×48" in capsys.readouterr().out
    assert len(CaptureSet.load(out)) == 14
    assert main(["import-captures", str(seq), str(caps), "--out", str(out)]) == 2
    assert main(["import-captures", str(seq), str(caps), "--out", str(tmp_path / "s2"), "--camera-width", "60",
                 "--camera-height", "48"]) == 2
    assert "camera resolution is 60×48" in capsys.readouterr().err
    assert main(["import-captures", str(tmp_path / "nope"), str(caps), "--out", str(tmp_path / "s3")]) == 2
    depth = tmp_path / "depth.npy"
    np.save(depth, np.full((24, 32), 1.7, np.float32))
    assert main(["import-captures", str(seq), str(caps), "--out", str(tmp_path / "s4"), "--depth", str(depth),
                 "--depth-native-width", "256", "--depth-native-height", "192"]) == 0
    s4 = CaptureSet.load(tmp_path / "s4")
    assert s4.depth().shape == (24, 32) and s4.depth_info.native_size == (256, 192)


def test_cli_lists_commands(capsys):
    from procam.addon.cli.app import build_parser
    text = build_parser().format_help()
    assert "patterns" in text and "import-captures" in text


def _rig_file(path: Path, camera_size, projector_size, distortion, metric=True) -> Path:
    """A rig.json as `procam calibrate-rig` writes it, for known lenses and pose."""
    from procam.addon.stages.rig_calibration import RigCalibration
    from procam.addon.steps.rig import write

    pose = look_at_pose(np.array([0.2, 0.1, 0.0]), np.array([0.0, 0.0, 1.5]))
    cam_k = np.array([[70.0, 0, 31.5], [0, 70.0, 23.5], [0, 0, 1]])
    proj_k = np.array([[100.0, 0, 39.5], [0, 100.0, 80.0], [0, 0, 1]])  # principal point below the frame
    return write(path, RigCalibration.known(camera_size, projector_size, cam_k, distortion, proj_k,
                                            camera_from_projector=pose, metric=metric))


def test_rig_lens_puts_a_point_where_a_pinhole_would(tmp_path):
    """Undistortion moves a dot from where the distorted lens shows it to where the pinhole K puts it."""
    from procam.addon.rig.lens import RigLens

    k = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    dist = np.array([-0.25, 0.08, 0.001, -0.002, 0.0])
    point = np.array([[0.42, -0.3, 1.0]])
    pinhole = (k @ point[0])[:2] / point[0, 2]
    seen = cv2.projectPoints(point, np.zeros(3), np.zeros(3), k, dist)[0].reshape(2)
    assert np.linalg.norm(seen - pinhole) > 10  # the lens really moves it
    ys, xs = np.mgrid[0:480, 0:640]
    blob = np.exp(-((xs - seen[0]) ** 2 + (ys - seen[1]) ** 2) / (2 * 2.0 ** 2)).astype(np.float32)
    lens = RigLens(Intrinsics.from_opencv_matrix(640, 480, k), dist, "test")
    out = lens.image(np.repeat(blob[..., None], 3, 2))[..., 0]
    centre = np.array([(out * xs).sum(), (out * ys).sum()]) / out.sum()
    assert np.linalg.norm(centre - pinhole) < 0.1
    half = lens.image(blob[::2, ::2].copy(), nearest=True)  # a half-size depth map
    assert np.unravel_index(np.argmax(half), half.shape) == pytest.approx(
        (round((pinhole[1] + 0.5) / 2 - 0.5), round((pinhole[0] + 0.5) / 2 - 0.5)), abs=1)


def test_import_with_a_rig_file(tmp_path, capsys):
    seq = export_sequence(small_projector(), tmp_path / "seq", checker_size=10, graycode=False)
    caps = shoot_folder(seq, tmp_path / "photos")
    rig = _rig_file(tmp_path / "rig.json", CAM, FRAME, [-0.2, 0.0, 0.0, 0.0, 0.0])
    assert main(["import-captures", str(seq), str(caps), "--out", str(tmp_path / "set"), "--rig", str(rig)]) == 0
    assert "lens distortion removed" in capsys.readouterr().out
    cs = CaptureSet.load(tmp_path / "set")
    assert (cs.camera_status, cs.projector_status, cs.projector_pose_known) == ("calibrated", "calibrated", True)
    assert (cs.camera.intrinsics.fx, cs.camera.intrinsics.cx, cs.camera.intrinsics.cy) == (70.0, 32.0, 24.0)
    assert cs.projector.intrinsics.cy == 80.5 and cs.projector.input_size == INPUT  # K from the rig, input kept
    assert np.allclose(cs.projector.camera_from_projector, look_at_pose(np.array([0.2, 0.1, 0.0]),
                                                                       np.array([0.0, 0.0, 1.5])))
    plain = import_captures(seq, caps, None, None, tmp_path / "plain")
    assert not np.allclose(cs.image("checker", phase=0), plain.image("checker", phase=0), atol=1e-3)
    # The rig's lengths in board squares: its K is used, the pose is left to calibrate.
    squares = _rig_file(tmp_path / "squares.json", CAM, FRAME, np.zeros(5), metric=False)
    assert main(["import-captures", str(seq), str(caps), "--out", str(tmp_path / "sq"), "--rig", str(squares)]) == 0
    sq = CaptureSet.load(tmp_path / "sq")
    assert not sq.projector_pose_known and np.allclose(sq.projector.camera_from_projector,
                                                       small_projector().camera_from_projector)
    assert np.array_equal(sq.image("white"), plain.image("white"))  # no distortion: the photographs as they were
    capsys.readouterr()
    # The lens taken out is recorded, for a live camera's frames later (test_a_live_camera_sees_through_…).
    assert np.allclose(removed_lens(cs).distortion, [-0.2, 0, 0, 0, 0]) and removed_lens(plain) is None
    assert removed_lens(cs).camera.size == CAM and removed_lens(sq) is not None
    # A rig of another projector or camera resolution is refused, naming the file; nothing is written.
    for name, cam, frame, message in (("p.json", CAM, (160, 120), "calibrates a 160×120 projector"),
                                      ("c.json", (128, 96), FRAME, "camera resolution is 128×96")):
        bad = _rig_file(tmp_path / name, cam, frame, np.zeros(5))
        assert main(["import-captures", str(seq), str(caps), "--out", str(tmp_path / "bad"), "--rig", str(bad)]) == 2
        assert message in capsys.readouterr().err and not (tmp_path / "bad").exists()


def test_a_live_camera_sees_through_the_lens_import_took_out(tmp_path, monkeypatch):
    """Photographs imported with a rig file lose the camera's lens distortion, and their calibration lives in that
    pinhole camera; a live camera still delivers the lens's image. Stage C and evaluation put its frames through
    the same lens (recorded by the capture set and by the calibration), and refuse a set that says a lens was
    taken out without recording which, before the projector window opens, rather than compare them silently."""
    from types import SimpleNamespace

    from procam.addon.capture.devices import LensRemovedDevice
    from procam.addon.rig.lens import RigLens
    from procam.addon.steps import stage_c

    seq = export_sequence(small_projector(), tmp_path / "seq", checker_size=10, graycode=False)
    caps = shoot_folder(seq, tmp_path / "photos")
    rig = _rig_file(tmp_path / "rig.json", CAM, FRAME, [-0.2, 0.05, 0.0, 0.0, 0.0])
    assert main(["import-captures", str(seq), str(caps), "--out", str(tmp_path / "set"), "--rig", str(rig)]) == 0
    lens = removed_lens(CaptureSet.load(tmp_path / "set"))
    rng = np.random.default_rng(0)
    raw = rng.uniform(0.0, 1.0, (CAM[1], CAM[0], 3)).astype(np.float32)

    class Camera_(Device):
        opened = 0

        def __init__(self, spec, projector, progress=None, others=()):
            Camera_.opened += 1
            self.projector, self.camera_size = projector, CAM

        def project(self, frame):
            return raw

    monkeypatch.setattr(stage_c, "open_camera_device", lambda spec, projector, **_: Camera_(spec, projector))
    spec, proj = "live:camera=0,display=0", small_projector()

    def calibration(report, capture_dir):
        return SimpleNamespace(report=report, capture_dir=str(capture_dir),
                               rig=SimpleNamespace(projector=proj, others=(),
                                                   camera=SimpleNamespace(intrinsics=proj.intrinsics)))

    # From the capture set (a calibration made before calibrations recorded it) and from the calibration alone.
    for report, where in (({}, tmp_path / "set"), ({"camera_lens_removed": lens.to_dict()}, tmp_path / "moved")):
        device = stage_c.device_pipeline(spec, calibration(report, where))
        assert isinstance(device, LensRemovedDevice) and device.camera_size == CAM
        seen = device.project(np.zeros((FRAME[1], FRAME[0], 3), np.float32))
        np.testing.assert_array_equal(seen, lens.image(raw))
        assert np.abs(seen - raw).max() > 0.1  # the lens really moves the image
    plain = stage_c.device_pipeline(spec, calibration({}, tmp_path / "x"))
    assert not isinstance(plain, LensRemovedDevice)
    # The lab's camera too (a lab set undistorted with undistort-captures); a replayed capture set is not.
    monkeypatch.setattr(stage_c, "LabTruth", SimpleNamespace(load=lambda path: SimpleNamespace(  # one projector
        rig=SimpleNamespace(projectors=(proj,)))))
    from procam.addon.lab import cycles_device  # where stage C takes the lab's device from when it renders

    monkeypatch.setattr(cycles_device, "LabDevice", lambda truth: Camera_("lab", proj))
    with_lens = calibration({"camera_lens_removed": lens.to_dict()}, "")
    assert isinstance(stage_c.device_pipeline("lab:t.json", with_lens), LensRemovedDevice)
    assert not isinstance(stage_c.device_pipeline(f"folder:{tmp_path / 'set'}", with_lens), LensRemovedDevice)
    # A device opened elsewhere (Blender opens the lab on its main thread and relays to it) gets the same lens.
    relayed = stage_c.device_pipeline("lab:t.json", with_lens, device=Camera_("lab", proj))
    assert isinstance(relayed, LensRemovedDevice)
    np.testing.assert_array_equal(relayed.project(np.zeros((FRAME[1], FRAME[0], 3), np.float32)), lens.image(raw))
    assert RigLens.from_dict(lens.to_dict()).to_dict() == lens.to_dict()
    # A set whose notes say a lens was taken out but which does not record it (an earlier ProCam) is refused.
    doc = json.loads((tmp_path / "set" / "capture.json").read_text())
    del doc["camera_lens_removed"]
    (tmp_path / "set" / "capture.json").write_text(json.dumps(doc))
    opened = Camera_.opened
    with pytest.raises(CaptureError, match="import the photographs again with --rig"):
        stage_c.device_pipeline(spec, calibration({}, tmp_path / "set"))
    assert Camera_.opened == opened


def test_undistorting_a_set_later_gives_what_import_with_the_rig_gives(tmp_path, capsys):
    """A capture set made before the camera was calibrated (or rendered by the lab) gets the board-calibrated lens
    taken out afterwards (undistort-captures): the same images, camera and record as importing the photographs with
    the rig file, the set's own projector kept; a set whose lens is already out, or a lens of another camera size,
    is refused."""
    seq = export_sequence(small_projector(), tmp_path / "seq", checker_size=10, graycode=False)
    caps = shoot_folder(seq, tmp_path / "photos")
    rig = _rig_file(tmp_path / "rig.json", CAM, FRAME, [-0.2, 0.05, 0.0, 0.0, 0.0])
    plain = import_captures(seq, caps, None, None, tmp_path / "plain")
    assert main(["import-captures", str(seq), str(caps), "--out", str(tmp_path / "at_import"), "--rig",
                 str(rig)]) == 0
    assert main(["undistort-captures", str(tmp_path / "plain"), "--rig", str(rig), "--out",
                 str(tmp_path / "later")]) == 0
    assert "taken out" in capsys.readouterr().out
    at_import, later = CaptureSet.load(tmp_path / "at_import"), CaptureSet.load(tmp_path / "later")
    assert later.camera == at_import.camera and later.projector.to_dict() == plain.projector.to_dict()
    assert later.camera_lens["distortion"] == at_import.camera_lens["distortion"]
    assert [e.kind for e in later] == [e.kind for e in plain]
    for kind, params in (("white", {}), ("checker", {"phase": 0})):
        np.testing.assert_allclose(later.image(kind, **params), at_import.image(kind, **params), atol=2 / 65535)
        np.testing.assert_array_equal(later.pattern(kind, **params), plain.pattern(kind, **params))
    assert main(["undistort-captures", str(tmp_path / "later"), "--rig", str(rig), "--out",
                 str(tmp_path / "x")]) == 2
    assert "already taken out" in capsys.readouterr().err and not (tmp_path / "x").exists()
    other = _rig_file(tmp_path / "other.json", (128, 96), FRAME, np.zeros(5))
    assert main(["undistort-captures", str(tmp_path / "plain"), "--rig", str(other), "--out",
                 str(tmp_path / "x")]) == 2
    assert "calibrates a 128×96 camera" in capsys.readouterr().err


# -- showing several projectors at once, and the check that the others were black ------------------

class _TwoSidedDevice(Device):
    """Two projectors of different resolutions: the camera's left half sees the first, its right half the second."""

    def __init__(self, first: Projector, second: Projector) -> None:
        self.projector, self.second = first, second

    @property
    def projectors(self) -> tuple[Projector, ...]:
        return (self.projector, self.second)

    def project(self, frame: np.ndarray) -> np.ndarray:
        raise CaptureError("give both frames")

    def project_all(self, frames) -> np.ndarray:
        a, b = self.check_frames(frames)
        img = np.zeros((CAM[1], CAM[0], 3), np.float32)
        img[:, : CAM[0] // 2] = a.mean()
        img[:, CAM[0] // 2:] = b.mean()
        return img


def test_project_all_takes_one_frame_per_projector_at_its_own_size():
    first = small_projector()
    second = Projector(projector_intrinsics_from_throw(*FRAME2, 1.6), look_at_pose((-0.3, 0.1, 0.0), (0, 0, 1.6)))
    device = _TwoSidedDevice(first, second)
    a = np.ones((FRAME[1], FRAME[0], 3), np.float32)
    b = np.full((FRAME2[1], FRAME2[0], 3), 0.5, np.float32)
    img = device.project_all([a, b])
    assert img[0, 0, 0] == 1.0 and img[0, -1, 0] == 0.5
    with pytest.raises(CaptureError, match="projector 2's frame must be 64×40"):
        device.project_all([a, a])
    with pytest.raises(CaptureError, match="shows 2 projector.*got 3 frame"):
        device.project_all([a, b, b])
    with pytest.raises(CaptureError, match="not one frame"):
        device.project_all(a)
    # a one-projector device shows frames[0] with project; wrappers pass project_all through
    single = WarpDevice(first)
    assert single.projectors == (first,)
    np.testing.assert_array_equal(single.project_all([a]), single.project(a))
    with pytest.raises(CaptureError, match="takes one frame for each, got 2"):
        single.project_all([a, a])

    class _Lens:
        def image(self, img):
            return img * 0.5

    from procam.addon.capture.devices import LensRemovedDevice
    wrapped = LensRemovedDevice(device, _Lens())  # type: ignore[arg-type]
    assert wrapped.projectors == device.projectors
    assert wrapped.project_all([a, b])[0, 0, 0] == 0.5
    # the effect models of a diagnosis are one projector's: several frames are refused, not sent unadapted
    from procam.addon.gap.compensation import AdaptedDevice, EffectAdapter
    adapted = AdaptedDevice(device, EffectAdapter({}, first))
    assert adapted.projectors == device.projectors
    with pytest.raises(CaptureError, match="one projector's; showing 2 projectors at once"):
        adapted.project_all([a, b])
    one = AdaptedDevice(single, EffectAdapter({}, first))
    np.testing.assert_allclose(one.project_all([a]), one.project(a))


def test_a_projector_left_on_during_anothers_captures_is_named(tmp_path):
    from procam.addon.capture.others_black import check_others_black

    cs = write_two_projector_set(tmp_path / "good")
    assert max(check_others_black(cs).values()) < 0.01
    assert check_others_black(cs.for_projector(0)) == {}
    # footprints: projector 1 lights the left half, projector 2 the right; projector 2 stayed on (grey) while
    # projector 1's black was taken
    cam, first = small_camera(), small_projector()
    second = cs.projectors[1]
    shape = (CAM[1], CAM[0], 3)
    left, right = np.zeros(shape), np.zeros(shape)
    left[:, : CAM[0] // 2 + 4], right[:, CAM[0] // 2 - 4:] = 0.6, 0.6
    rng = np.random.default_rng(1)

    def shot(light: np.ndarray) -> np.ndarray:
        return np.clip(0.02 + light + rng.normal(0, 0.01, shape), 0, 1)

    def write(path: Path, leak: float) -> CaptureSet:
        with CaptureSet.writer(path, cam, first, others=(second,)) as w:
            for k, (proj, light) in enumerate(((first, left), (second, right))):
                size = proj.intrinsics.size[::-1]
                w.add("black", shot(leak * right if k == 0 else np.zeros(shape)), projector_index=k,
                      frame=np.zeros((*size, 3)))
                w.add("white", shot(light + (leak * right if k == 0 else 0)), projector_index=k,
                      frame=np.ones((*size, 3)))
        return CaptureSet.load(path)

    assert max(check_others_black(write(tmp_path / "fine", 0.0)).values()) < 0.01
    with pytest.raises(CaptureError, match="projector 2 was not black while projector 1's captures"):
        check_others_black(write(tmp_path / "bad", 0.5))
