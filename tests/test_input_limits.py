"""Inputs a user can fix give exit 2, never an internal error or a runaway: the pixel limit on every image, depth
map and video frame read (checked from the header, before decoding), a full disk or a folder we may not write,
malformed numbers in files and on the command line, and unknown effects in a diagnosis."""

from __future__ import annotations

import argparse
import errno
import json
import os
import pathlib
import struct
import zlib

import cv2
import numpy as np
import pytest

from procam.addon.errors import ImageError, ProCamError, RigError


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def png_bomb(width: int, height: int) -> bytes:
    """A valid 16-bit RGB PNG header declaring ``width`` × ``height`` pixels, with a tiny zlib stream of zeros."""
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(b"\0" * 4096, 9))
            + _chunk(b"IEND", b""))


def test_png_declaring_20000x20000_is_refused_at_once_in_little_memory(tmp_path, run_python):
    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(png_bomb(20000, 20000))
    assert bomb.stat().st_size < 200
    # A fresh interpreter under a 3 GiB address-space cap (decoding would need 2.4 GB for the pixels alone): it
    # must refuse with the size and the limit, in well under a second of work and without growing the process's
    # peak memory.
    out = run_python("""
        import json, resource, sys, time
        resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))
        from procam.addon.errors import ProCamError
        from procam.addon.stages.display_area import load_target
        rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        t0 = time.perf_counter()
        try:
            load_target(sys.argv[1])
            code, message = 0, ""
        except ProCamError as exc:
            code, message = exc.exit_code, str(exc)
        print(json.dumps({"code": code, "message": message, "seconds": time.perf_counter() - t0,
                          "grown_mb": (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024}))
        sys.exit(code)
    """, str(bomb), env={"PROCAM_MAX_PIXELS": ""}, timeout=120)
    assert out.returncode == 2, out.stderr[-2000:]
    doc = json.loads(out.stdout.strip().splitlines()[-1])
    assert "20000×20000" in doc["message"] and str(1 << 27) in doc["message"]
    assert "PROCAM_MAX_PIXELS" in doc["message"]
    # The peak memory the refusal adds to what the imports took (those vary with the machine's libraries).
    assert doc["seconds"] < 2.0 and doc["grown_mb"] < 100


@pytest.mark.parametrize("suffix", [".png", ".jpg", ".tif", ".bmp", ".exr", ".hdr"])
def test_declared_size_is_read_from_each_format_header(tmp_path, suffix):
    from procam.addon.imageio import declared_size

    img = np.random.default_rng(0).random((23, 37, 3)).astype(np.float32)
    path = tmp_path / f"x{suffix}"
    data = img if suffix in (".exr", ".hdr") else (img * 255).astype(np.uint8)
    assert cv2.imwrite(str(path), data)
    with open(path, "rb") as fh:
        assert declared_size(fh) == (37, 23)


def test_the_pixel_limit_is_settable_and_named(tmp_path, monkeypatch):
    from procam.addon.imageio import read_image, write_image

    path = write_image(tmp_path / "small.png", np.zeros((23, 37, 3), np.float32))
    monkeypatch.setenv("PROCAM_MAX_PIXELS", "500")
    with pytest.raises(ImageError, match=r"declares 37×23 pixels .* limit of 500"):
        read_image(path)
    monkeypatch.setenv("PROCAM_MAX_PIXELS", "851")
    assert read_image(path).shape == (23, 37, 3)
    monkeypatch.setenv("PROCAM_MAX_PIXELS", "lots")
    with pytest.raises(ImageError, match="PROCAM_MAX_PIXELS must be a positive whole number"):
        read_image(path)


def _npy_header_only(path: pathlib.Path, shape: tuple[int, ...]) -> None:
    with open(path, "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "<f4", "fortran_order": False, "shape": shape})


def test_npy_depth_whose_header_claims_a_million_squared_is_refused(tmp_path):
    from procam.addon.capture.depth_io import read_depth
    from procam.addon.rig.model import intrinsics_from_fov

    path = tmp_path / "depth.npy"
    _npy_header_only(path, (10 ** 6, 10 ** 6))
    with pytest.raises(ProCamError, match=r"depth file .* declares 1000000×1000000 pixels") as info:
        read_depth(path, intrinsics_from_fov(64, 48, 60.0))
    assert info.value.exit_code == 2


def test_one_dimensional_npy_target_is_refused(tmp_path):
    from procam.addon.stages.display_area import load_target

    path = tmp_path / "target.npy"
    np.save(path, np.linspace(0, 1, 50, dtype=np.float32))
    with pytest.raises(ImageError, match=r"shape \(50,\), not an image"):
        load_target(path)


def test_video_frames_over_the_limit_are_refused_before_decoding(tmp_path, monkeypatch):
    from procam.addon.video import VideoReader, frame_count

    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    for i in range(3):
        writer.write(np.full((48, 64, 3), 40 * i, np.uint8))
    writer.release()
    assert frame_count(path) == 3
    monkeypatch.setenv("PROCAM_MAX_PIXELS", "1000")
    with pytest.raises(ImageError, match=r"video .* declares 64×48 pixels .* limit of 1000"):
        VideoReader(path).read(0)


def test_warm_start_frame_bytes_are_checked(monkeypatch):
    from procam.addon.steps.show_work import decode_png16

    with pytest.raises(ImageError, match="declares 20000×20000"):
        decode_png16(png_bomb(20000, 20000))


def test_a_full_disk_while_a_manifest_is_written_says_so(tmp_path, monkeypatch):
    from procam.addon.imageio import write_image
    from procam.addon.outputs import write_manifest
    from procam.addon.steps.show import ShowFolder

    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    folder = ShowFolder(tmp_path / "show")
    folder.path.mkdir()
    folder.doc = {"format": "procam-show", "frames": {}}
    monkeypatch.setattr(pathlib.Path, "write_bytes", full)
    with pytest.raises(ProCamError, match="the disk is full") as info:
        folder.write()
    assert info.value.exit_code == 2 and type(info.value).__name__ == "WriteError"
    with pytest.raises(ProCamError, match="the disk is full"):
        write_manifest(tmp_path / "x.json", {"a": 1})
    monkeypatch.undo()
    monkeypatch.setattr(np, "save", full)
    with pytest.raises(ProCamError, match="the disk is full"):
        write_image(tmp_path / "x.npy", np.zeros((4, 4), np.float32))
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == []  # no temporary file left


def test_an_out_folder_we_may_not_look_into_is_a_clear_error(tmp_path, monkeypatch):
    from procam.addon.outputs import AtomicFolder, OutputError, folder_in_place
    from procam.addon.steps.show import ShowFolder

    out = tmp_path / "out"
    out.mkdir()
    (out / "f").write_text("x")
    if os.geteuid() != 0:  # root reads any folder: there the refusal is simulated below
        out.chmod(0)
        try:
            with pytest.raises(OutputError, match="cannot look into"):
                AtomicFolder(out, force=True, replaceable=lambda p: True, inputs=())
        finally:
            out.chmod(0o755)
    real = pathlib.Path.iterdir

    def denied(self):
        if self == out or self == out.absolute():
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(self))
        return real(self)

    monkeypatch.setattr(pathlib.Path, "iterdir", denied)
    with pytest.raises(OutputError, match="cannot look into .*Permission denied"):
        AtomicFolder(out, force=True, replaceable=lambda p: True, inputs=())
    with pytest.raises(OutputError, match="cannot look into"), \
            folder_in_place(out, force=True, replaceable=lambda p: True, inputs=()):
        pass
    with pytest.raises(ProCamError, match="cannot write the show folder") as info:
        ShowFolder(out).open()
    assert info.value.exit_code == 2


def test_unknown_or_malformed_effects_in_a_diagnosis_are_refused():
    from procam.addon.gap.compensation import adapter_from_options, load_adapter
    from procam.addon.rig.model import Projector, intrinsics_from_fov

    projector = Projector(intrinsics_from_fov(40, 30, 50.0))
    doc = {"selected_params": {"wobble": {"a": 1.0}}}
    with pytest.raises(ProCamError, match="names the effect 'wobble', which this ProCam does not know"):
        adapter_from_options("auto", doc, projector, where="the diagnosis in d")
    with pytest.raises(ProCamError, match="parameters of the effect 'defocus' are malformed"):
        load_adapter({"selected_params": {"defocus": {"sigma": "wide"}}}, projector)
    with pytest.raises(ProCamError, match="malformed"):
        load_adapter({"selected_params": ["defocus"]}, projector)


def test_no_command_line_number_accepts_nan():
    from procam.addon.cli.app import build_parser, main

    parser = build_parser()
    floats = []
    for sub in parser._subparsers._group_actions[0].choices.values():
        for action in sub._actions:
            assert action.type is not float, f"{sub.prog} {action.option_strings} takes NaN and infinity"
            if action.type is not None and getattr(action.type, "__name__", "") == "float":
                floats.append(action)  # a declared number option's parser (addon/options.py), not float itself
    assert floats  # the checked type is in use
    assert main(["diagnose", "cal", "--out", "x", "--min-share", "nan"]) == 2
    assert main(["lab", "--out", "x", "--scale", "inf"]) == 2
    with pytest.raises(argparse.ArgumentTypeError):
        floats[0].type("nan")


def test_a_resolution_that_is_not_whole_is_refused():
    from procam.addon.rig.model import Intrinsics, Projector

    k = {"width": 128, "height": 96, "fx": 100.0, "fy": 100.0, "cx": 64.0, "cy": 48.0}
    assert Intrinsics.from_dict({**k, "width": 128.0}).width == 128
    with pytest.raises(RigError, match="resolution width must be a whole number of pixels, got 128.9"):
        Intrinsics.from_dict({**k, "width": 128.9})
    with pytest.raises(RigError, match="whole number"):
        Intrinsics.from_dict({**k, "height": float("nan")})
    with pytest.raises(RigError, match="input size must be"):
        Projector.from_dict({"intrinsics": k, "camera_from_projector": np.eye(4).tolist(),
                             "input_size": [100.5, 96]})
