"""VESA MPCDI export and import: the archive's structure against the standard (v2.0, and the names the reference
library reads), the round trip, a media server's application of it, the sl profile, and bad input."""

from __future__ import annotations

import dataclasses
import math
import re
import struct
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from procam.addon.errors import MpcdiError, ProCamError
from procam.addon.imageio import read_image, write_image
from procam.addon.lab.truth import make_truth
from procam.addon.mpcdi import apply as apply_mpcdi
from procam.addon.mpcdi.derive import grid_centres, trace
from procam.addon.mpcdi.format import Mpcdi, Region, pfm_bytes, read_mpcdi, read_pfm, write_archive
from procam.addon.rig.model import Rig
from procam.addon.stages.calibrate import Calibration
from procam.addon.steps import calibrate as calibrate_step
from procam.addon.steps.mpcdi import ApplyMpcdiOptions, ExportMpcdiOptions, run_apply, run_export

CAMERA, PROJECTOR = (96, 72), (120, 90)


def _calibration(folder: Path, projectors: int = 2, *, sizes: tuple[tuple[int, int], ...] | None = None) -> Path:
    """A calibration folder of the lab's true rig (no warp, no operator, no capture set): side by side on the curve."""
    truth = make_truth("curve", camera_size=CAMERA, projector_size=PROJECTOR, projectors=projectors,
                       layout="side-by-side", overlap=0.3)
    rig = truth.rig
    if sizes is not None:  # each projector at its own resolution, the same lens
        projs = [dataclasses.replace(p, intrinsics=p.intrinsics.scaled(*s), input_size=None, input_offset=None)
                 for p, s in zip(rig.projectors, sizes)]
        rig = Rig(rig.camera, projs[0], tuple(projs[1:]))
    cal = Calibration(rig, truth.surface, None, "", other_warps=(None,) * (projectors - 1))
    folder.mkdir(parents=True)
    calibrate_step.write(folder, cal, {})
    return folder


@pytest.fixture(scope="module")
def two(tmp_path_factory) -> tuple[Path, Path]:
    """A two-projector calibration and its 2d MPCDI file."""
    root = tmp_path_factory.mktemp("mpcdi")
    cal = _calibration(root / "cal")
    done = run_export(ExportMpcdiOptions(cal, root / "show.mpcdi", content_size=(160, 90)))
    return cal, done.path


def _xml(path: Path) -> ET.Element:
    with zipfile.ZipFile(path) as z:
        return ET.fromstring(z.read("mpcdi.xml"))


def test_the_archive_has_the_standards_structure(two):
    _, path = two
    with zipfile.ZipFile(path) as z:
        names = z.namelist()
        assert names[0] == "mpcdi.xml" and all("/" not in n and "\\" not in n for n in names)  # §3.3: flat
        assert z.read("mpcdi.xml").startswith(b'<?xml version="1.0" encoding="utf-8"?>')
        members = {n: z.read(n) for n in names}
    root = _xml(path)
    assert root.tag == "MPCDI"
    a = root.attrib
    # version 1.0: the reference library refuses 2.0 (test_the_reference_library_reads_every_value_written); the
    # v2.0 attributes (geometry, color) are written beside v1.0's level
    assert a["profile"] == "2d" and a["version"] == "1.0" and a["geometry"] in "12" and a["color"] == "2"
    assert a["level"] in "1234" and re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d", a["date"])
    assert [c.tag for c in root] == ["display", "files", "extensionSet"]
    buffers = root.find("display").findall("buffer")
    assert len(buffers) == 1 and buffers[0].get("xResolution") == "160" == buffers[0].get("Xresolution")
    regions = buffers[0].findall("region")
    assert [r.get("id") for r in regions] == ["projector_1", "projector_2"]
    filesets = {f.get("region"): f for f in root.find("files").findall("fileset")}
    assert set(filesets) == {"projector_1", "projector_2"}
    for r in regions:
        for v2, v1 in (("xSize", "xsize"), ("ySize", "ysize"), ("xResolution", "Xresolution"),
                       ("yResolution", "Yresolution")):  # the standard's names and the reference library's
            assert r.get(v2) == r.get(v1) is not None
        x, y, xs, ys = (float(r.get(k)) for k in ("x", "y", "xSize", "ySize"))
        assert 0 <= x <= 1 and 0 <= y <= 1 and 0 < xs <= 1 and 0 < ys <= 1 and x + xs <= 1 + 1e-9
        w, h = int(r.get("xResolution")), int(r.get("yResolution"))
        assert (w, h) == PROJECTOR and r.find("color/decode").get("type") == "gamma"
        fs = filesets[r.get("id")]
        gw = fs.find("geometryWarpFile")
        assert {c.tag for c in gw} == {"path", "geometricUnit", "originOf3DData", "originof3DData", "interpolation"}
        assert gw.findtext("interpolation") == "linear"
        pfm = members[gw.findtext("path")]
        header = re.match(rb"PF\n(\d+) (\d+)\n(-?[\d.]+)\n", pfm)
        assert header and float(header.group(3)) < 0  # little-endian, the scale's sign says so
        cols, rows = int(header.group(1)), int(header.group(2))
        assert len(pfm) == header.end() + cols * rows * 12 and cols >= 2 and rows >= 2
        # The first row stored is the raster's bottom row (netpbm, the reference library's PfmIO).
        first = np.frombuffer(pfm, "<f4", cols * 3, header.end()).reshape(cols, 3)
        np.testing.assert_array_equal(first, read_pfm(pfm)[-1])
        assert a["geometry"] == ("1" if max(cols, rows) <= 32 else "2")
        for tag, children in (("alphaMap", {"path", "componentDepth", "bitDepth", "gammaEmbedded"}),
                              ("betaMap", {"path", "componentDepth", "bitDepth"})):
            el = fs.find(tag)
            assert {c.tag for c in el} == children and el.findtext("bitDepth") == "8"  # all the library holds
            png = members[el.findtext("path")]
            assert png.startswith(b"\x89PNG\r\n\x1a\n")
            width, height, depth, colour = struct.unpack(">IIBB", png[16:26])
            assert (width, height, depth) == (w, h, 8) and colour == 0  # grey: componentDepth 1
            assert el.findtext("componentDepth") == "1"
    ext = root.find("extensionSet/extension")
    assert ext.get("name") == "procam" and "geometric ramps" in ext.find("definitions").get("blend")


def test_a_round_trip_gives_back_what_was_written(two, tmp_path):
    _, path = two
    m = read_mpcdi(path)
    again = tmp_path / "again.mpcdi"
    with open(again, "wb") as fh:
        write_archive(m, fh)
    back = read_mpcdi(again)
    assert back.profile == m.profile == "2d" and back.buffers == m.buffers == {"display": (160, 90)}
    for r, s in zip(m.regions, back.regions):
        assert (r.id, r.x, r.y, r.xsize, r.ysize, r.resolution) == (s.id, s.x, s.y, s.xsize, s.ysize, s.resolution)
        np.testing.assert_array_equal(r.warp, s.warp)  # floats, NaN included
        np.testing.assert_array_equal(r.alpha, s.alpha)  # 8-bit levels read back are written back as they are
        np.testing.assert_array_equal(r.beta, s.beta)
    assert back.map_bits == m.map_bits == 8
    # 16-bit maps, for readers that take them, on request
    fine = tmp_path / "fine.mpcdi"
    with open(fine, "wb") as fh:
        write_archive(dataclasses.replace(m, map_bits=16), fh)
    assert read_mpcdi(fine).map_bits == 16 and _xml(fine).find("files/fileset/alphaMap/bitDepth").text == "16"
    # Unknown samples are NaN with an error of 1; known ones carry no error estimate (NaN), §3.6.2.
    w = m.regions[0].warp
    unknown = np.isnan(w[..., 0])
    assert unknown.any() and (~unknown).any()
    assert np.all(w[unknown][:, 2] == 1.0) and np.all(np.isnan(w[~unknown][:, 2]))


def _reference_read(path: Path) -> dict[str, dict]:
    """What the reference C++ library (github.com/scaredyfish/MPCDI, ``src/IO/mpcdiReaderIntern.cpp``,
    ``mpcdiPfmIO.cpp``, ``mpcdiPNGReadWrite.cpp``) reads of a file, done its way, failing where it fails: names matched
    exactly (tinyxml2), the root's ``version`` major at most 1 (``Read`` refuses "MPACS Version 2.0" with error 16
    unless the caller turns CheckVersionSupported off, and nDisplay does not), every child of ``display`` a
    ``buffer`` and of a buffer a ``region``, every ``fileset`` carrying ``region``, the required texts of
    geometryWarpFile, alphaMap and betaMap; a PFM read as "PF", width, height, scale, one byte, then the rows
    bottom-first in the host's (little-endian) order whatever the scale's sign; a PNG read into one byte per
    component (``DataMap`` holds ``unsigned char``: a 16-bit PNG's two bytes become two samples). Per region: its
    attributes, the warp as the library indexes it ((x, y) → [y, x], y = 0 the file's last row) and the maps'
    bytes."""
    def need(el, name):
        assert el is not None and el.get(name) is not None, f"the reference reader needs attribute {name!r}"
        return el.get(name)

    def text(el, name):
        c = el.find(name)  # ElementTree's find is exact, as tinyxml2's FirstChildElement
        assert c is not None and (c.text or "").strip(), f"the reference reader needs <{name}> in <{el.tag}>"
        return c.text.strip()

    with zipfile.ZipFile(path) as z:
        members = {n: z.read(n) for n in z.namelist()}
    root = ET.fromstring(members["mpcdi.xml"])
    assert root.tag == "MPCDI"
    version = need(root, "version")
    assert "." in version and int(version.split(".")[0]) <= 1, \
        f"version {version!r}: the reference reader supports 1.0 only and refuses a later major version"
    for a in ("profile", "date"):
        need(root, a)
    int(need(root, "level"))
    out: dict[str, dict] = {}
    display = root.find("display")
    assert display is not None
    for b in display:
        assert b.tag == "buffer", f"<display> holds <{b.tag}>; the reference reader expects only <buffer>"
        need(b, "id")
        for r in b:
            assert r.tag == "region", f"<buffer> holds <{r.tag}>; the reference reader expects only <region>"
            rid = need(r, "id")
            got = {k: float(need(r, k)) for k in ("x", "y", "xsize", "ysize")}
            got.update({k: int(need(r, k)) for k in ("Xresolution", "Yresolution")})
            filesets = [f for f in root.find("files") if need(f, "region") == rid]
            assert len(filesets) == 1
            fs = filesets[0]
            gw, am = fs.find("geometryWarpFile"), fs.find("alphaMap")
            assert gw is not None and am is not None
            for t in ("geometricUnit", "interpolation", "originof3DData"):
                text(gw, t)
            pfm = members[text(gw, "path")]
            assert pfm[:2] == b"PF"
            head = re.match(rb"PF.\s*(\d+)\s+(\d+)\s+(\S+)\s", pfm, re.S)  # istream >> sizeX >> sizeY >> scale
            assert head is not None
            cols, rows = int(head.group(1)), int(head.group(2))
            data = np.frombuffer(pfm, "<f4", rows * cols * 3, head.end()).reshape(rows, cols, 3)
            got["warp"] = data[::-1]  # the library's row y = the file's row rows-1-y
            maps = {"alpha": am, "beta": fs.find("betaMap")}
            for kind, el in maps.items():
                if el is None:
                    continue
                for t in ("componentDepth", "bitDepth"):
                    int(text(el, t))
                if kind == "alpha":
                    float(text(el, "gammaEmbedded"))
                png = members[text(el, "path")]
                raw = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
                # libpng's rows as bytes, one byte a sample: 16-bit samples are big-endian pairs of bytes
                width, comps = raw.shape[1], (1 if raw.ndim == 2 else 3)
                rgb = raw if raw.ndim == 2 else raw[..., ::-1]
                rowbytes = rgb.astype(">u2").view(np.uint8) if raw.dtype == np.uint16 else rgb.astype(np.uint8)
                got[kind] = rowbytes.reshape(raw.shape[0], -1)[:, :width * comps].reshape(raw.shape[0], width, comps)
            out[rid] = got
    return out


@pytest.mark.parametrize("profile", ["2d", "sl"])
def test_the_reference_library_reads_every_value_written(tmp_path, profile):
    """The reference reader (emulated as :func:`_reference_read`; ``scripts/check_mpcdi_reference.sh`` runs the real
    one) reads the file and gets back ProCam's values: the version it accepts, its names, the warp bit for bit in
    ProCam's orientation, and the blend maps as 8-bit values (the only depth it holds)."""
    cal = _calibration(tmp_path / "cal")
    path = run_export(ExportMpcdiOptions(cal, tmp_path / "show.mpcdi", profile=profile,
                                         content_size=(160, 90))).path
    ref, m = _reference_read(path), read_mpcdi(path)
    assert sorted(ref) == sorted(r.id for r in m.regions)
    for r in m.regions:
        got = ref[r.id]
        assert (got["Xresolution"], got["Yresolution"]) == r.resolution
        np.testing.assert_allclose([got[k] for k in ("x", "y", "xsize", "ysize")], [r.x, r.y, r.xsize, r.ysize])
        np.testing.assert_array_equal(got["warp"], r.warp)
        for kind, img in (("alpha", r.alpha), ("beta", r.beta)):
            want = np.round(np.clip(img, 0, 1) * 255).astype(np.uint8).reshape(got[kind].shape)
            np.testing.assert_array_equal(got[kind], want, err_msg=f"{r.id}'s {kind} map as the library reads it")
        assert np.count_nonzero((r.alpha > 0) & (r.alpha < 1)) > 0  # the overlap's ramp is in what was compared


def test_pfm_either_endianness_and_a_cut_file():
    a = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
    little = pfm_bytes(a)
    np.testing.assert_array_equal(read_pfm(little), a)
    big = b"PF\n3 2\n1.0\n" + a[::-1].astype(">f4").tobytes()
    np.testing.assert_array_equal(read_pfm(big), a)
    with pytest.raises(MpcdiError, match="cut or damaged"):
        read_pfm(little[:-4])
    with pytest.raises(MpcdiError, match="not a PFM"):
        read_pfm(b"P6\n3 2\n255\n" + bytes(18))


def test_the_warp_sends_each_pixel_to_where_its_light_lands(two):
    """Applied to a content frame that holds its own coordinates, each projector pixel shows the content coordinate
    of the camera pixel its light reaches (the calibrated model's ray cast)."""
    cal_dir, path = two
    m = read_mpcdi(path)
    cal = calibrate_step.read(cal_dir)
    ch, cw = 90, 160
    t, s = np.mgrid[0:ch, 0:cw] + 0.5
    content = np.stack([s / cw, t / ch, np.zeros_like(s)], axis=2).astype(np.float32)
    area = [int(v) for v in m.extension["contentArea"].split(",")]
    for k, region in enumerate(m.regions):
        frame = apply_mpcdi.region_frame(m, region, content)
        alpha = apply_mpcdi.stretch(region.alpha, region.resolution)
        hit = trace(cal.for_projector(k), grid_centres(region.resolution, region.resolution))
        want = np.stack([(hit.camera[:, 0] - area[0]) / area[2], (hit.camera[:, 1] - area[1]) / area[3]], axis=1)
        shown = (frame[..., :2] / np.maximum(alpha, 1e-6)[..., None]).reshape(-1, 2)
        sure = (alpha.reshape(-1) > 0.2) & np.all((want > 0.05) & (want < 0.95), axis=1)
        assert sure.sum() > 500
        err = np.abs(shown[sure] - want[sure])
        # a warp grid 4 px apart, interpolated, and the content's own pixels: well under a content pixel's width ×3
        assert np.median(err) < 0.01 and np.percentile(err, 95) < 0.03


def test_the_blend_shares_the_overlap_and_sums_to_one(two):
    """Where both projectors light the same camera pixel their alphas add up to 1; each has all of its own area."""
    cal_dir, path = two
    m = read_mpcdi(path)
    cal = calibrate_step.read(cal_dir)
    cw, ch = CAMERA
    for region in m.regions:
        assert region.alpha.max() > 0.99 and region.alpha.min() == 0.0
    # every camera pixel gets the average alpha of the pixels landing there, per projector, summed over projectors
    per = np.zeros((2, ch, cw))
    for k, region in enumerate(m.regions):
        hit = trace(cal.for_projector(k), grid_centres(region.resolution, region.resolution))
        a = region.alpha.reshape(-1)
        ok = hit.valid & (a > 0)
        ix = np.clip(hit.camera[ok].astype(int), 0, [cw - 1, ch - 1])
        s_, n_ = np.zeros((ch, cw)), np.zeros((ch, cw))
        np.add.at(s_, (ix[:, 1], ix[:, 0]), a[ok])
        np.add.at(n_, (ix[:, 1], ix[:, 0]), 1)
        per[k] = np.where(n_ > 0, s_ / np.maximum(n_, 1), 0)
    both = (per > 0).all(axis=0)
    inner = both & np.roll(both, 1, 1) & np.roll(both, -1, 1) & np.roll(both, 1, 0) & np.roll(both, -1, 0)
    assert inner.sum() > 20
    np.testing.assert_allclose(per.sum(axis=0)[inner], 1.0, atol=0.08)


def test_a_media_server_shows_pi_alpha_one_minus_beta_plus_beta():
    """§2.4 on a region that spans the buffer with the identity warp (v up): content rows land the right way up."""
    rows, cols = 4, 5
    x, y = np.meshgrid((np.arange(cols) + 0.5) / cols, (np.arange(rows) + 0.5) / rows)
    warp = np.stack([x, 1.0 - y, np.full_like(x, np.nan)], axis=2).astype(np.float32)  # row 0 at the top: v = 1
    region = Region("p", 0.0, 0.0, 1.0, 1.0, (cols, rows), warp, np.full((rows, cols), 0.5, np.float32),
                    np.full((rows, cols), 0.1, np.float32))
    m = Mpcdi("2d", {"display": (cols, rows)}, [region])
    content = np.zeros((rows, cols, 3), np.float32)
    content[0] = 1.0  # the top row white
    frame = apply_mpcdi.region_frame(m, region, content)
    np.testing.assert_allclose(frame[0], 1.0 * 0.5 * 0.9 + 0.1, atol=1e-5)
    np.testing.assert_allclose(frame[1:], 0.1, atol=1e-5)
    region.alpha_gamma = 2.2  # an alpha stored with a gamma is linearised first
    np.testing.assert_allclose(apply_mpcdi.region_frame(m, region, content)[0], 0.5 ** 2.2 * 0.9 + 0.1, atol=1e-5)


def test_apply_mpcdi_writes_one_sequence_per_projector(two, tmp_path):
    _, path = two
    img = np.full((90, 160, 3), 0.5, np.float32)
    content = write_image(tmp_path / "c.png", img)
    out = run_apply(ApplyMpcdiOptions(path, (content,), tmp_path / "frames"))
    for k in (1, 2):
        frame = read_image(out / f"projector_{k}" / "frame_0001.png")
        assert frame.shape == (PROJECTOR[1], PROJECTOR[0], 3) and 0.2 < frame.max() <= 0.5 + 1e-3
    with pytest.raises(ProCamError, match="never overwritten without --force"):
        run_apply(ApplyMpcdiOptions(path, (content,), tmp_path / "frames"))
    run_apply(ApplyMpcdiOptions(path, (content,), tmp_path / "frames", force=True))


def test_the_sl_profile_carries_frustum_pose_and_surface(tmp_path):
    cal = _calibration(tmp_path / "cal")
    done = run_export(ExportMpcdiOptions(cal, tmp_path / "sl.mpcdi", profile="sl"))
    root = _xml(done.path)
    assert root.get("profile") == "sl"
    buffers = root.find("display").findall("buffer")
    assert len(buffers) == 2 and all(len(b.findall("region")) == 1 for b in buffers)  # §3.5.2: one region a buffer
    for fs in root.find("files").findall("fileset"):
        assert fs.find("geometryWarpFile/geometricUnit").text == "m"
        assert fs.find("geometryWarpFile/originOf3DData").text == "centerOfMass"
        assert fs.find("distortionMap/path") is not None
    m = read_mpcdi(done.path)
    truth_cal = calibrate_step.read(cal)
    for k, r in enumerate(m.regions):
        f, cf = r.frustum, r.frame
        assert f is not None and cf is not None and f.left_angle < 0 < f.right_angle and f.down_angle < f.up_angle
        axes = np.array([cf.yaw_axis, cf.pitch_axis, cf.roll_axis])
        np.testing.assert_allclose(axes @ axes.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(axes[[1, 0, 2]]) > 0  # left, up, forward: right-handed (§3.6.3's X left, Y up, Z fwd)
        # yaw right and pitch up give the forward (roll) axis back (§2.2.1's order: yaw first)
        yaw, pitch = math.radians(f.yaw), math.radians(f.pitch)
        fwd = np.array([-math.sin(yaw) * math.cos(pitch), math.sin(pitch), math.cos(yaw) * math.cos(pitch)])
        np.testing.assert_allclose(fwd, cf.roll_axis, atol=1e-9)
        # the 3D points lie on the surface: in the rig frame again, they are where the projector's rays hit
        pts = r.warp.reshape(-1, 3)
        ok = np.all(np.isfinite(pts), axis=1)
        assert ok.mean() > 0.3
        centre = np.asarray(truth_cal.surface.vertices).mean(axis=0)
        rig = pts[ok] * [-1, -1, 1] + centre
        pos = truth_cal.rig.projectors[k].position
        np.testing.assert_allclose(np.array(cf.position) * [-1, -1, 1] + centre, pos, atol=1e-6)
        assert np.all(np.linalg.norm(rig - pos, axis=1) > 0.1)
    with pytest.raises(MpcdiError, match="2d profile"):
        run_apply(ApplyMpcdiOptions(done.path, (write_image(tmp_path / "c.png", np.zeros((4, 4, 3))),),
                                    tmp_path / "frames"))


# -- bad input -----------------------------------------------------------------------------------------------------

def test_one_projector_gives_a_valid_one_region_file(tmp_path):
    cal = _calibration(tmp_path / "cal", projectors=1)
    done = run_export(ExportMpcdiOptions(cal, tmp_path / "one.mpcdi"))
    m = read_mpcdi(done.path)
    assert len(m.regions) == 1 and m.regions[0].alpha.max() == pytest.approx(1.0)
    assert not any("ramps" in w for w in done.warnings)  # one projector blends with nobody: nothing to say


def test_projectors_of_different_sizes_each_get_their_own_resolution(tmp_path):
    cal = _calibration(tmp_path / "cal", sizes=((120, 90), (80, 60)))
    done = run_export(ExportMpcdiOptions(cal, tmp_path / "mixed.mpcdi"))
    m = read_mpcdi(done.path)
    assert [r.resolution for r in m.regions] == [(120, 90), (80, 60)]
    assert [r.alpha.shape for r in m.regions] == [(90, 120), (60, 80)]
    frames = apply_mpcdi.frames(m, np.ones((90, 160, 3), np.float32))
    assert [f.shape for f in frames] == [(90, 120, 3), (60, 80, 3)]


def test_a_calibration_without_a_blend_gets_ramps_and_says_so(tmp_path):
    cal = _calibration(tmp_path / "cal")
    done = run_export(ExportMpcdiOptions(cal, tmp_path / "r.mpcdi"))
    assert any("geometric ramps" in w for w in done.warnings) and "geometric ramps" in done.report["blend"]
    assert any("beta is 0" in w for w in done.warnings)


def test_an_existing_output_is_replaced_only_with_force_and_never_half_written(two, tmp_path, monkeypatch):
    cal, _ = two
    out = tmp_path / "show.mpcdi"
    run_export(ExportMpcdiOptions(cal, out))
    before = out.read_bytes()
    with pytest.raises(MpcdiError, match="never overwritten without --force"):
        run_export(ExportMpcdiOptions(cal, out))
    assert out.read_bytes() == before

    from procam.addon.steps import mpcdi as step

    def broken(m, fh):
        fh.write(b"PK half")
        raise MpcdiError("the disk broke")

    monkeypatch.setattr(step, "write_archive", broken)
    with pytest.raises(MpcdiError, match="disk broke"):
        run_export(ExportMpcdiOptions(cal, out, force=True))
    assert out.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["show.mpcdi"]
    monkeypatch.undo()
    run_export(ExportMpcdiOptions(cal, out, force=True))
    other = tmp_path / "notes.mpcdi"
    other.write_text("mine")
    with pytest.raises(MpcdiError, match="not a MPCDI file|is not a MPCDI"):
        run_export(ExportMpcdiOptions(cal, other, force=True))
    assert other.read_text() == "mine"
    with pytest.raises(MpcdiError, match="ends in .mpcdi"):
        run_export(ExportMpcdiOptions(cal, tmp_path / "show.zip"))
    with pytest.raises(MpcdiError, match="leave as it is"):
        run_export(ExportMpcdiOptions(cal, cal / "inside.mpcdi"))


def test_the_command_line_exits_2_with_a_message(two, tmp_path, capsys):
    from procam.addon.cli.app import main

    cal, path = two
    out = tmp_path / "cli.mpcdi"
    assert main(["export-mpcdi", str(cal), "--out", str(out), "--content-size", "320x180", "--warp-step", "8"]) == 0
    printed = capsys.readouterr()
    assert "MPCDI file:" in printed.out and "geometric ramps" in printed.err
    assert main(["export-mpcdi", str(cal), "--out", str(out)]) == 2
    assert "--force" in capsys.readouterr().err
    assert main(["export-mpcdi", str(cal), "--out", str(out), "--force", "--profile", "sl"]) == 0
    bad = tmp_path / "bad.mpcdi"
    bad.write_bytes(b"PK\x03\x04 not really")
    content = write_image(tmp_path / "c.png", np.zeros((8, 8, 3)))
    assert main(["apply-mpcdi", str(bad), str(content), "--out", str(tmp_path / "f")]) == 2
    assert "not an MPCDI file" in capsys.readouterr().err
    with zipfile.ZipFile(path) as z, zipfile.ZipFile(tmp_path / "cut.mpcdi", "w") as cut:
        for n in z.namelist():
            if not n.startswith("AlphaMap-projector_2"):
                cut.writestr(n, z.read(n))
    assert main(["apply-mpcdi", str(tmp_path / "cut.mpcdi"), str(content), "--out", str(tmp_path / "f")]) == 2
    assert "not in the archive" in capsys.readouterr().err
    assert not (tmp_path / "f").exists()
