"""Depth as users have it (formats, units, holes, a shifted map) and phone photographs (EXIF orientation,
exposure or white balance left on auto): each bad input is refused or corrected by name, nothing half written.

Sessions are a small lab set (camera 128×96) played back as photographs of an exported sequence.
"""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from procam.addon.capture.depth_io import (align_depth, find_alignment, project_points, read_depth,
                                           read_ply_points)
from procam.addon.capture.sequence import export_sequence, load_sequence
from procam.addon.capture.exposure import (Shot, capture_set_shots, check_capture_set, check_exposure,
                                           reduce_image)
from procam.addon.capture.format import CaptureSet, linear_to_srgb
from procam.addon.cli.app import main
from procam.addon.errors import CaptureError
from procam.addon.imageio import exif_orientation, read_image, write_image
from procam.addon.steps.capture import ImportOptions, run_import

LAB = dict(scale=0.2, samples=4)
REAL = Path(__file__).resolve().parents[1].parent / "shared" / "realdata" / "kamino410-procam-calibration"


@pytest.fixture(scope="module")
def session(lab_set, tmp_path_factory):
    """A lab capture set, its exported sequence, and the lab's captures saved as that sequence's photographs."""
    captures_dir, _ = lab_set("curve", "", **LAB)
    cs = CaptureSet.load(captures_dir)
    root = tmp_path_factory.mktemp("session")
    seq = export_sequence(cs.projector, root / "seq")
    frames = load_sequence(seq).frames
    images = [e for e in cs.entries if e.kind != "depth"]
    assert [f["name"] for f in frames] == [e.name for e in images]
    return cs, seq, frames, images, root


def shoot(session, out: Path, change=None, suffix: str = ".png") -> Path:
    """Save the lab's captures as photographs of the sequence; ``change(i, image)`` alters the i-th one."""
    cs, _, frames, images, _ = session
    out.mkdir()
    for i, (f, e) in enumerate(zip(frames, images)):
        img = read_image(cs.file(e))
        if change is not None:
            img = np.clip(change(i, img), 0, 1).astype(np.float32)
        path = out / f"{Path(f['file']).stem}{suffix}"
        if suffix == ".jpg":
            ok, buf = cv2.imencode(".jpg", np.round(linear_to_srgb(img)[..., ::-1] * 255).astype(np.uint8),
                                   [cv2.IMWRITE_JPEG_QUALITY, 95])
            path.write_bytes(buf.tobytes())
        else:
            write_image(path, img)
    return out


@pytest.fixture(scope="module")
def photos(session):
    return shoot(session, session[4] / "photos")


def true_depth(session) -> np.ndarray:
    return session[0].depth()


def moved(depth: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """A depth map misregistered by (dx, dy) px: the sensor saw the same scene a few pixels off (edges replicate)."""
    return cv2.warpAffine(depth, np.float32([[1, 0, dx], [0, 1, dy]]), (depth.shape[1], depth.shape[0]),
                          flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)


def import_with(session, photos_dir: Path, out: Path, **kw) -> CaptureSet:
    messages: list[str] = []
    cs = run_import(ImportOptions(session[1], photos_dir, out, **kw), lambda m, f: messages.append(m))
    cs.messages = messages  # type: ignore[attr-defined]
    return cs


# -- depth: formats and units ----------------------------------------------------------------------

def test_millimetres_given_as_metres_are_detected_converted_and_warned(session, photos, tmp_path, capsys):
    cs = session[0]
    depth = true_depth(session)
    mm = tmp_path / "depth_mm.npy"
    np.save(mm, np.nan_to_num(depth * 1000.0))
    r = read_depth(mm, cs.camera.intrinsics)
    assert r.scale == 0.001 and "millimetres" in r.scale_reason
    assert len(r.warnings) == 1 and "depth_mm.npy" in r.warnings[0] and "--depth-units" in r.warnings[0]
    assert np.allclose(r.depth[np.isfinite(depth)], depth[np.isfinite(depth)], rtol=1e-5)
    assert np.array_equal(np.isnan(r.depth), np.isnan(depth))
    # the same file said to be metres is refused: 1700 m is no projection-mapping scene
    with pytest.raises(CaptureError, match=r"depth_mm.npy: its median depth is .* outside \[0.05, 50\] m"):
        read_depth(mm, cs.camera.intrinsics, units="m")
    assert read_depth(mm, cs.camera.intrinsics, units="mm").warnings == ()
    # through the CLI: imported in metres, the warning on the terminal and in the notes
    out = tmp_path / "set"
    assert main(["import-captures", str(session[1]), str(photos), "--out", str(out), "--depth", str(mm)]) == 0
    assert "depth_mm.npy: values have a median of" in capsys.readouterr().err
    got = CaptureSet.load(out)
    assert np.nanmax(np.abs(got.depth() - depth)) < 1e-4
    assert main(["import-captures", str(session[1]), str(photos), "--out", str(tmp_path / "m"), "--depth", str(mm),
                 "--depth-units", "m"]) == 2
    assert "its median depth is 1765 m in metres (given)" in capsys.readouterr().err and not (tmp_path / "m").exists()
    assert got.notes["depth"]["scale_to_metres"] == 0.001 and "millimetres" in got.notes["depth"]["warnings"][0]


def test_sixteen_bit_png_in_millimetres_and_float_exr(session, tmp_path):
    cs = session[0]
    depth = true_depth(session)
    png = tmp_path / "depth.png"
    cv2.imwrite(str(png), np.round(np.nan_to_num(depth) * 1000).astype(np.uint16))  # 0 = hole
    r = read_depth(png, cs.camera.intrinsics)
    assert r.source_format == "png 16-bit" and r.scale == 0.001 and r.warnings == ()
    assert np.array_equal(np.isnan(r.depth), np.isnan(depth))
    assert np.nanmax(np.abs(r.depth - depth)) < 0.0006
    exr = tmp_path / "depth.exr"
    cv2.imwrite(str(exr), np.nan_to_num(depth).astype(np.float32))
    assert np.nanmax(np.abs(read_depth(exr, cs.camera.intrinsics).depth - depth)) < 1e-6
    eight = tmp_path / "depth8.png"
    cv2.imwrite(str(eight), np.full((10, 10), 100, np.uint8))
    with pytest.raises(CaptureError, match="depth8.png is an 8-bit image"):
        read_depth(eight, cs.camera.intrinsics)


def _cloud(session) -> np.ndarray:
    """The lab's depth map back-projected through the camera's K: one point per valid pixel, camera frame."""
    k = session[0].camera.intrinsics
    depth = true_depth(session)
    v, u = np.nonzero(np.isfinite(depth))
    z = depth[v, u].astype(np.float64)
    return np.stack([(u + 0.5 - k.cx) / k.fx * z, (v + 0.5 - k.cy) / k.fy * z, z], axis=1)


def write_ply(path: Path, points: np.ndarray, binary: bool) -> Path:
    head = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0", "comment test",
            f"element vertex {len(points)}", "property float x", "property float y", "property float z",
            "property uchar red", "element face 0", "property list uchar int vertex_indices", "end_header"]
    body = (np.zeros(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1")]))
    body["x"], body["y"], body["z"], body["red"] = points[:, 0], points[:, 1], points[:, 2], 200
    data = ("\n".join(head) + "\n").encode()
    if binary:
        data += body.tobytes()
    else:
        data += "".join(f"{p[0]:.6f} {p[1]:.6f} {p[2]:.6f} 200\n" for p in points).encode()
    path.write_bytes(data)
    return path


def test_point_clouds_ascii_and_binary_project_into_the_camera(session, tmp_path):
    cs, depth = session[0], true_depth(session)
    points = _cloud(session)
    for binary in (False, True):
        ply = write_ply(tmp_path / f"cloud{int(binary)}.ply", points, binary)
        pts, fmt = read_ply_points(ply)
        assert fmt == ("ply binary_little_endian" if binary else "ply ascii") and len(pts) == len(points)
        r = read_depth(ply, cs.camera.intrinsics)
        assert r.projected and r.depth.shape == depth.shape
        both = np.isfinite(r.depth) & np.isfinite(depth)
        assert both.sum() > 0.99 * np.isfinite(depth).sum()
        assert np.max(np.abs(r.depth[both] - depth[both])) < 1e-5
    # nearest point wins a pixel
    k = cs.camera.intrinsics
    near_far = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 1.0]])
    assert np.nanmin(project_points(np.vstack([points, near_far]), k)) <= 1.0


def test_point_cloud_behind_the_camera_or_beside_the_image_is_refused(session, tmp_path):
    cs = session[0]
    points = _cloud(session)
    behind = write_ply(tmp_path / "opengl.ply", points * [1, -1, -1], binary=True)  # OpenGL camera axes
    with pytest.raises(CaptureError, match=r"point cloud .*opengl.ply lies behind the camera \(100% .*y and z negated"):
        read_depth(behind, cs.camera.intrinsics)
    corner = points[(points[:, 0] < np.percentile(points[:, 0], 10)) & (points[:, 1] < np.percentile(points[:, 1], 10))]
    small = write_ply(tmp_path / "corner.ply", corner, binary=False)
    with pytest.raises(CaptureError, match=r"corner.ply projects onto only \d+% of the 128×96 image"):
        read_depth(small, cs.camera.intrinsics)


def test_depth_mostly_holes_is_refused_by_name_and_nothing_is_written(session, photos, tmp_path):
    depth = true_depth(session).copy()
    depth[np.random.default_rng(0).random(depth.shape) < 0.9] = np.nan
    holes = tmp_path / "holes.npy"
    np.save(holes, depth)
    out = tmp_path / "set"
    with pytest.raises(CaptureError, match=r"depth file .*holes.npy is mostly holes: only \d+% .*at least 50%"):
        import_with(session, photos, out, depth_path=holes)
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".set")]


# -- depth: alignment -----------------------------------------------------------------------------

def test_misaligned_depth_is_detected_corrected_and_warned(session, photos, tmp_path):
    depth = true_depth(session)
    off = tmp_path / "off.npy"
    np.save(off, np.nan_to_num(moved(depth, 0, 4)))
    cs = import_with(session, photos, tmp_path / "set", depth_path=off)
    note = cs.notes["depth"]
    assert note["alignment"]["shift_px"] == [0, -4] and note["alignment"]["checked"]
    assert any("off.npy was misaligned" in w and "+0, -4" in w for w in note["warnings"])
    assert any(m.startswith("warning:") and "misaligned" in m for m in cs.messages)
    got = cs.depth()
    both = np.isfinite(got) & np.isfinite(depth)
    assert np.mean(np.abs(got[both] - depth[both]) < 1e-4) > 0.99
    # sideways too, straight through the function. The curve's left and right silhouettes run 5 px inside the
    # frame: moved 4 px, one ends at the frame's border, and the other alone leaves half a pixel open: 3 or 4 px.
    fixed, shift, conf = align_depth(moved(depth, -4, 0), [session[0].image("surface")])
    assert shift[1] == 0 and shift[0] in (3, 4) and conf > 0.3
    assert np.isnan(fixed[:, :shift[0]]).all()


def test_aligned_depth_is_left_alone(session, photos, tmp_path):
    depth = true_depth(session)
    aligned = tmp_path / "aligned.npy"
    np.save(aligned, np.nan_to_num(depth))
    cs = import_with(session, photos, tmp_path / "set", depth_path=aligned)
    assert cs.notes["depth"]["alignment"]["shift_px"] == [0, 0] and cs.notes["depth"]["alignment"]["checked"]
    assert not cs.notes["depth"]["warnings"] and not any("warning" in m for m in cs.messages)
    assert np.array_equal(np.isnan(cs.depth()), np.isnan(depth))
    # a flat depth map has no edges to align on: not checked, not shifted, not refused
    a = find_alignment(np.full_like(depth, 1.7), [session[0].image("surface")])
    assert a.shift == (0, 0) and not a.checked


def test_depth_shifted_beyond_the_search_is_refused(session):
    depth = true_depth(session)
    with pytest.raises(CaptureError, match=r"does not line up with the photographs.*misaligned by 8 px or more"):
        find_alignment(moved(depth, 0, 11), [session[0].image("surface")], name="depth file d.npy")


# -- photographs: EXIF orientation ---------------------------------------------------------------

def with_orientation(jpeg: bytes, orientation: int) -> bytes:
    """A JPEG with an EXIF APP1 segment holding one tag, Orientation (0x0112), right after its SOI marker."""
    tiff = (b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 1) + struct.pack("<HHI", 0x0112, 3, 1)
            + struct.pack("<HH", orientation, 0) + struct.pack("<I", 0))
    payload = b"Exif\x00\x00" + tiff
    return jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + jpeg[2:]


def test_exif_orientation_is_read_and_applied_as_opencv_does(tmp_path):
    img = (np.random.default_rng(0).random((12, 20, 3)) * 255).astype(np.uint8)
    jpeg = cv2.imencode(".jpg", img)[1].tobytes()
    for o in range(1, 9):
        path = tmp_path / f"o{o}.jpg"
        path.write_bytes(with_orientation(jpeg, o))
        assert exif_orientation(path) == o
        ours = read_image(path)
        theirs = cv2.imread(str(path), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255.0
        assert np.array_equal(ours, theirs), o


def test_a_photograph_turned_against_the_others_is_refused(session, tmp_path):
    jpgs = shoot(session, tmp_path / "jpgs", suffix=".jpg")
    victim = sorted(jpgs.iterdir())[7]
    victim.write_bytes(with_orientation(victim.read_bytes(), 6))
    out = tmp_path / "set"
    with pytest.raises(CaptureError, match=rf"photograph .*{victim.name} is rotated 90° .* camera was turned"):
        import_with(session, jpgs, out)
    assert not out.exists()
    # every photograph with the same tag: all turned upright alike, and imported
    for p in jpgs.iterdir():
        if p != victim:
            p.write_bytes(with_orientation(p.read_bytes(), 6))
    cs = import_with(session, jpgs, out)
    assert cs.camera.intrinsics.size == (96, 128) and "EXIF orientation 6" in cs.notes["orientation"]


# -- photographs: exposure and white balance -------------------------------------------------------

def test_clean_session_passes_the_exposure_check(session, photos, tmp_path):
    cs = import_with(session, photos, tmp_path / "set")
    note = cs.notes["exposure"]
    assert note["checked"] and note["pairs_checked"] >= 8
    assert note["max_exposure_drift_log"] < 0.02 and note["max_colour_drift_log"] < 0.01
    assert check_capture_set(session[0]).checked  # an existing capture set, too


def test_auto_exposure_is_refused_naming_the_first_brighter_photograph(session, tmp_path):
    frames = session[2]
    start = next(i for i, f in enumerate(frames) if f["name"] == "graycode_x03")
    drifted = shoot(session, tmp_path / "drift", lambda i, img: img * 1.3 if i >= start else img)
    first = sorted(drifted.iterdir())[start].name
    out = tmp_path / "set"
    with pytest.raises(CaptureError, match=rf"exposure changed during the session, from {first} on: it is "
                                           r"brighter: .* 1\.30× white \+ black.*lock the camera's exposure"):
        import_with(session, drifted, out)
    assert not out.exists()
    # the change between a Gray-code image and its inverse names the inverse
    mid = shoot(session, tmp_path / "mid", lambda i, img: img * 1.3 if i > start else img)
    with pytest.raises(CaptureError, match=rf"from {sorted(mid.iterdir())[start + 1].name} on"):
        import_with(session, mid, out)
    # the user may still import it, knowingly
    assert import_with(session, mid, out, check_exposure=False).notes.get("exposure") is None


@pytest.mark.skipif(not REAL.is_dir(), reason=f"real captures not found at {REAL}")
def test_real_photographs_with_a_locked_exposure_pass():
    """Real photographs (a linear machine-vision camera, 8-bit): no false alarm. Frames 0–39 are Gray-code bit,
    inverse pairs (x then y), 40 white, 41 black; white and black come last here."""
    shots = []
    for i in range(42):
        kind = "white" if i == 40 else "black" if i == 41 else "graycode"
        params = {"axis": "x" if i < 20 else "y", "bit": (i % 20) // 2, "inverted": i % 2 == 1}
        shots.append(Shot(kind, params, reduce_image(read_image(REAL / "capture_0" / f"graycode_{i:02d}.png")),
                          f"graycode_{i:02d}.png"))
    report = check_exposure(shots)
    assert report.checked and len(report.pairs) >= 10 and report.max_exposure_drift < 0.03
    # the same session 20 % darker from x bit 2 on; from x bit 6 on, whose stripes are too fine to check
    for start, named in ((4, r"graycode_04.png on"), (12, r"graycode_20.png \(or from as early as graycode_12.png")):
        darker = [Shot(s.kind, s.params, s.image * (0.8 if start <= i < 40 else 1.0), s.source)
                  for i, s in enumerate(shots)]
        with pytest.raises(CaptureError, match=f"exposure changed during the session, from {named}"):
            check_exposure(darker)


def test_white_balance_change_is_refused_naming_the_photograph(session, tmp_path):
    frames = session[2]
    start = next(i for i, f in enumerate(frames) if f["name"] == "graycode_y01")
    warm = np.array([1.12, 1.0, 1.0], np.float32)
    drifted = shoot(session, tmp_path / "wb", lambda i, img: img * warm if i >= start else img)
    with pytest.raises(CaptureError, match=rf"white balance changed during the session, from "
                                           rf"{sorted(drifted.iterdir())[start].name} on: .* the R channel"):
        import_with(session, drifted, tmp_path / "set")
    # the same check on an existing capture set's shots
    shots = [Shot(s.kind, s.params, s.image * warm if "y01" in s.source or "y02" in s.source else s.image, s.source)
             for s in capture_set_shots(session[0])]
    with pytest.raises(CaptureError, match="white balance changed"):
        check_exposure(shots)
