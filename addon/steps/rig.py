"""The calibrate-rig step: board poses lit by Gray code → ``rig.json`` (camera, projector, their pose), and readers.

A session folder is one board pose: images named ``PREFIX_NN.EXT`` (``graycode_00.png`` …), numbered from
0 without gaps, in the projector's order: the Gray code for the projector size in OpenCV's order (each bit
followed by its inverse, x bits then y bits), then white, then black — the layout of OpenCV's structured-light
samples and of ``realdata/kamino410-procam-calibration``. Images may be 8- or 16-bit, grey or colour.

The projector size is required: the image count gives only the total number of Gray-code bits
(``2 × (bits_x + bits_y) + 2`` images), which many sizes share (1024×768, 800×600, 2048×384 all use 20 bits),
so it never identifies the size; a count that does not fit the size given is refused.

``rig.json`` (:data:`layout.RIG`) is written under a temporary name and renamed into place; an existing one
is replaced only with ``force``, and a file that is not a rig calibration never. Its intrinsics use the
project's convention (pixel corners at integers) with OpenCV's matrices beside them, and the projector's pose
is a 4×4 ``camera_from_projector`` in the camera's OpenCV frame, in the unit of the square size.
"""

from __future__ import annotations

import dataclasses
import json
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from collections.abc import Callable

import numpy as np

from ..capture.patterns import gray_code_bits
from ..errors import MALFORMED, CalibrationError, CaptureError
from ..imageio import READ_IMAGE_SUFFIXES, read_image
from ..options import Choice, option, validate
from ..outputs import check_file_replaceable, holds_manifest, write_manifest, writer_lock
from ..progress import Cancel, Progress, quiet
from ..stages.rig_calibration import DISTORTION_MODELS, PoseSource, RigCalibration, calibrate_rig
from . import layout
from .summary import Summary, cached, fmt

KIND = layout.RIG

_NUMBERED = re.compile(r"^(?P<prefix>.*?)(?P<number>\d+)$")


def _pair(what: str) -> Callable[[str], tuple[int, int]]:
    """Text ``AxB`` (``x``, ``×`` or ``,`` between two positive whole numbers) → (A, B)."""
    def parse(text: str) -> tuple[int, int]:
        m = re.fullmatch(r"\s*(\d+)\s*[x×X,]\s*(\d+)\s*", text)
        if not m or int(m[1]) <= 0 or int(m[2]) <= 0:
            raise ValueError(f"{what} must look like 9x7 (two positive whole numbers), got {text!r}")
        return int(m[1]), int(m[2])
    return parse


def _positive_square(value: float) -> None:
    if not value > 0:
        raise CalibrationError(f"--square must be a positive number of metres, got {value!r}")


_DISTORTION_HELP = {"none": "No lens distortion", "k1": "Radial k1", "k1k2": "Radial k1 k2",
                    "k1k2p1p2": "Radial k1 k2 and tangential p1 p2",
                    "k1k2p1p2k3": "Radial k1 k2 k3 and tangential p1 p2 (k3 needs many varied poses)"}
_DISTORTION_CHOICES = tuple(Choice(name, name, _DISTORTION_HELP.get(name, name)) for name in DISTORTION_MODELS)


@dataclass(frozen=True)
class RigOptions:
    """What ``procam calibrate-rig`` asks for."""

    sessions: tuple[Path, ...]  # one folder per board pose
    out: Path  # the rig.json to write
    board: tuple[int, int] = option(
        required=True, parse=_pair("board"), metavar="COLSxROWS", label="Inner Corners", own_field=True,
        help="the chessboard's inner corners: per row x rows (9x7 and 7x9 both find the same board)")
    #: None: not given (refused by :func:`run` with what to give)
    projector_size: tuple[int, int] | None = option(
        required=True, flag="--projector", parse=_pair("projector size"), metavar="WxH", label="Projector Size",
        own_field=True,
        help="the projector's native size the Gray code was made for (required: the image count gives only the "
             "number of bits, which many sizes share)")
    square: float | None = option(
        None, metavar="METRES", check=_positive_square, label="Square Size", own_field=True,
        help="the size of one chessboard square in metres, so that the projector's position is metric and "
             "import-captures --rig can use it (default: lengths in board squares)")
    window: int = option(
        47, min=5, soft_max=201, metavar="PIXELS", label="Corner Window", prop="procam_board_window",
        subtype="PIXEL",
        help="side of the camera-pixel window around each corner whose decoded pixels fit the local homography "
             "(default 47; about two thirds of a square works well)")
    camera_model: str = option(
        "k1k2p1p2", flag="--camera-distortion", choices=_DISTORTION_CHOICES, label="Camera Distortion",
        prop="procam_board_camera_distortion",
        help="which of OpenCV's k1 k2 p1 p2 k3 to estimate for the camera (default k1k2p1p2: k3 is not observable "
             "from a few poses)")
    projector_model: str = option(
        "auto", flag="--projector-distortion", label="Projector Distortion",
        prop="procam_board_projector_distortion",
        choices=(Choice("auto", "auto", "None, k1 or k1 k2: whichever the corners support (BIC)"),
                 *_DISTORTION_CHOICES),
        help="which of OpenCV's k1 k2 p1 p2 k3 to estimate for the projector (default auto: none, k1 or k1k2, "
             "whichever the corners support by the BIC; a distortion fitted where there is none moves the principal "
             "point)")
    force: bool = False


def expected_count(projector_size: tuple[int, int]) -> int:
    """Images in a session for this projector: each Gray-code bit and its inverse, then white and black."""
    bx, by = gray_code_bits(projector_size)
    return 2 * (bx + by) + 2


def session_files(folder: str | Path, projector_size: tuple[int, int]) -> list[Path]:
    """A session folder's images in order (Gray code …, white, black), checked for gaps and count."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CaptureError(f"session folder {folder} does not exist (give one folder of images per board pose)")
    groups: dict[str, dict[int, Path]] = {}
    for p in folder.iterdir():
        m = _NUMBERED.match(p.stem)
        if p.is_file() and p.suffix.lower() in READ_IMAGE_SUFFIXES and m:
            groups.setdefault(m["prefix"] + "\0" + p.suffix.lower(), {})[int(m["number"])] = p
    if not groups:
        raise CaptureError(f"{folder} holds no numbered images (expected graycode_00.png, graycode_01.png, …)")
    if len(groups) > 1:
        named = [k for k in groups if k.split("\0")[0].rstrip("_-").lower() == "graycode"]
        if len(named) != 1:
            kinds = ", ".join(sorted(f"{k.split(chr(0))[0]}NN{k.split(chr(0))[1]}" for k in groups))
            raise CaptureError(f"{folder} holds several numbered image series ({kinds}); keep one per folder")
        groups = {named[0]: groups[named[0]]}
    key, numbered = next(iter(groups.items()))
    prefix, suffix = key.split("\0")
    first, last = min(numbered), max(numbered)
    width = len(next(iter(numbered.values())).stem) - len(prefix)
    want = expected_count(projector_size)
    # Numbering may start at 0 or 1; a set with gaps that lacks only some numbers of a complete one is missing them.
    for start in dict.fromkeys((first, 0, 1)):
        span = range(start, start + want)
        missing = [n for n in span if n not in numbered]
        gaps = [n for n in missing if first < n < last]  # trailing ones look the same as a wrong --projector
        if gaps and len(numbered) + len(missing) == want and all(n in span for n in numbered):
            names = ", ".join(f"{prefix}{n:0{width}d}{suffix}" for n in missing[:5])
            raise CaptureError(f"{folder}: missing image(s) {names}{' …' if len(missing) > 5 else ''}; a "
                               f"{projector_size[0]}×{projector_size[1]} projector's session has {want} images")
    if len(numbered) != want or last - first + 1 != want:
        bx, by = gray_code_bits(projector_size)
        raise CaptureError(
            f"{folder} holds {len(numbered)} images ({prefix}{first:0{width}d}{suffix} … "
            f"{prefix}{last:0{width}d}{suffix}), but a {projector_size[0]}×{projector_size[1]} projector's Gray "
            f"code has {2 * (bx + by)} images ({bx} x bits and {by} y bits, each with its inverse) plus white and "
            f"black = {want}; check --projector (the projector's native size the patterns were made for) and that "
            "no image is missing")
    return [numbered[n] for n in sorted(numbered)]


def _read(path: Path, shape: tuple[int, ...] | None) -> np.ndarray:
    img = read_image(path, channels=1)
    if shape is not None and img.shape != shape:
        raise CaptureError(f"{path} is {img.shape[1]}×{img.shape[0]} but the session's white image is "
                           f"{shape[1]}×{shape[0]}; every image of a session must come from the same camera")
    return img


def pose_source(folder: Path, files: list[Path]) -> PoseSource:
    """A pose read on demand; every image checked against the white image's size, naming the file that differs."""
    white_file, black_file, gray_files = files[-2], files[-1], files[:-2]
    shape: dict[str, tuple[int, ...]] = {}

    def white() -> np.ndarray:
        img = _read(white_file, None)
        shape["white"] = img.shape
        return img

    return PoseSource(folder.name or str(folder), white, lambda: _read(black_file, shape.get("white")),
                      lambda: [_read(f, shape.get("white")) for f in gray_files])


def _check_out(out: Path, force: bool, sessions: tuple[Path, ...]) -> None:
    """Refuse an output that must not be replaced, before any work (:func:`..outputs.check_file_replaceable`)."""
    if out.is_dir():
        raise CalibrationError(f"{out} is a folder; give the file to write, e.g. {out / KIND.manifest}")
    check_file_replaceable(out, force=force, what="ProCam rig calibration",
                           replaceable=lambda p: holds_manifest(p.parent, p.name, KIND.format),
                           inputs=(*sessions, *layout.step_folders_around(out)), error=CalibrationError)


def run(options: RigOptions, progress: Progress | None = None, cancel: Cancel | None = None) -> RigCalibration:
    """Calibrate the rig from the session folders and write ``options.out``; returns the calibration written."""
    say = progress or quiet
    started = time.monotonic()
    out = Path(options.out)
    if options.projector_size is None:  # a missing argument is named first, before anything on disk
        raise CalibrationError("give the projector's native size (--projector WIDTHxHEIGHT): the number of images "
                               "fixes only the total number of Gray-code bits, which many sizes share")
    validate(options, CalibrationError)
    _check_out(out, options.force, tuple(options.sessions))
    with writer_lock(out):  # another run writing this file is refused before any work
        return _run(options, out, say, cancel, started)


def _run(options: RigOptions, out: Path, say: Progress, cancel: Cancel | None, started: float) -> RigCalibration:
    assert options.projector_size is not None
    size = (int(options.projector_size[0]), int(options.projector_size[1]))
    if len({Path(s).resolve() for s in options.sessions}) != len(options.sessions):
        raise CaptureError("the same session folder is given twice; give each board pose once")
    # Every folder's listing is checked before any image is read: a missing image fails in a second, not after
    # minutes of decoding.
    sources = [pose_source(Path(s), session_files(s, size)) for s in options.sessions]
    names = [s.name for s in sources]
    if len(set(names)) != len(names):  # a/capture_0 and b/capture_0: name poses by their full path
        sources = [dataclasses.replace(s, name=str(Path(p))) for s, p in zip(sources, options.sessions)]
    cal = calibrate_rig(sources, options.board, options.square or 1.0, size, say, cancel, window=options.window,
                        camera_model=options.camera_model, projector_model=options.projector_model)
    cal = dataclasses.replace(cal, metric=options.square is not None)
    write(out, cal, sessions=[str(Path(s).absolute()) for s in options.sessions],
          seconds=round(time.monotonic() - started, 2))
    return cal


def write(path: str | Path, cal: RigCalibration, **extra: Any) -> Path:
    """``cal`` as a ``rig.json`` at ``path`` (``extra``: more top-level fields), written to a temporary name and
    renamed into place; the path."""
    out = Path(path)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        write_manifest(out, {"format": KIND.format, "version": KIND.version, **extra, **cal.to_dict()})
    except OSError as exc:
        raise CalibrationError(f"cannot write {out}: {exc.strerror or exc}") from None
    return out


def _path(path: str | Path) -> Path:
    p = Path(path)
    return p / KIND.manifest if p.is_dir() else p


def read(path: str | Path) -> RigCalibration:
    """A ``rig.json`` (or the folder holding one)."""
    p = _path(path)
    if not p.is_file():
        raise CalibrationError(f"{p} does not exist; run {KIND.made_by}")
    try:
        doc = json.loads(p.read_text())
        if not isinstance(doc, dict) or doc.get("format") != KIND.format:
            raise CalibrationError(f"{p} is not a ProCam rig calibration; run {KIND.made_by}")
        if int(doc.get("version", 0)) > KIND.version:
            raise CalibrationError(f"{p} was written by a newer ProCam (version {doc['version']}); update ProCam")
        return RigCalibration.from_dict(doc)
    except (OSError, *MALFORMED) as exc:
        raise CalibrationError(f"cannot read rig calibration {p}: {exc}") from None


def _summary(root: Path, doc: dict[str, Any]) -> Summary:
    rms = doc.get("rms", {})
    cam, proj = doc.get("camera", {}), doc.get("projector", {})
    poses = doc.get("poses", [])
    used = [p["name"] for p in poses if p.get("used")]
    skipped = [f"{p['name']} ({p.get('reason', '')})" for p in poses if not p.get("used")]
    position = np.asarray(doc["camera_from_projector"], dtype=float)[:3, 3]
    lines = (
        f"Poses: {len(used)} used" + (f", skipped: {'; '.join(skipped)}" if skipped else ""),
        f"Camera: fx {fmt(cam.get('fx'), '.1f')} fy {fmt(cam.get('fy'), '.1f')} cx {fmt(cam.get('cx'), '.1f')} "
        f"cy {fmt(cam.get('cy'), '.1f')}, RMS {fmt(rms.get('camera'), '.3f', ' px')}",
        f"Projector: fx {fmt(proj.get('fx'), '.1f')} fy {fmt(proj.get('fy'), '.1f')} cx {fmt(proj.get('cx'), '.1f')} "
        f"cy {fmt(proj.get('cy'), '.1f')}, RMS {fmt(rms.get('projector'), '.3f', ' px')}",
        f"Projector at ({position[0]:+.3f}, {position[1]:+.3f}, {position[2]:+.3f}) "
        f"(× square {fmt(doc.get('board', {}).get('square'), '.4g')})",
    )
    return Summary(True, f"Rig calibrated: stereo RMS {fmt(rms.get('stereo'), '.3f', ' px')}", lines,
                   {"used": used, "skipped": skipped})


def summary(path: str | Path) -> Summary:
    """Key figures of a ``rig.json``: poses used and skipped, both devices' K and RMS, the projector's position."""
    p = _path(path)
    kind = dataclasses.replace(KIND, manifest=p.name)  # any file name, not only rig.json
    return cached(kind, p.parent, _summary, f"run {KIND.made_by} or choose a rig.json")


__all__ = ["KIND", "RigOptions", "expected_count", "pose_source", "read", "run", "session_files", "summary"]
