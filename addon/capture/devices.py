"""Capture devices: things that show a projector frame and return what the camera saw.

The pipeline talks to a :class:`Device` and never knows which one it has:

* the virtual lab (``addon/lab/``) renders the frame with Cycles;
* the live device (``addon/live/``) shows the frame in a window on the
  projector's display and captures it with a camera client;
* the folder workflow, for users with their own projection/capture tools:
  :func:`export_sequence` writes the numbered pattern frames, the user shows
  and photographs them, :func:`import_captures` turns the photographs into a
  capture set; :class:`FolderDevice` then replays that capture set, answering
  ``project`` for every frame that was captured.

:func:`capture_sequence` runs a pattern sequence through any device into a
new capture set.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import struct
from abc import ABC, abstractmethod
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import CaptureError, ImageError, RigError
from ..imageio import ORIENTATIONS, READ_IMAGE_SUFFIXES, exif_orientation, read_image, write_atomic_bytes, write_image
from ..progress import Progress, quiet
from ..rig.model import Camera, Intrinsics, Projector, intrinsics_from_fov
from ..outputs import AtomicFolder, holds_manifest
from ..safepaths import inside
from .depth_io import MIN_VALID, DepthReading, find_alignment, read_depth, shift_image
from .exposure import Shot, check_exposure, reduce_image
from .format import CAMERA_KINDS, CaptureSet, CaptureSetWriter, DepthInfo, Entry, srgb_to_linear
from .patterns import PatternSpec, calibration_sequence

SEQUENCE_FORMAT = "procam-sequence"
SEQUENCE_VERSION = 1
SEQUENCE_MANIFEST = "sequence.json"
ENCODINGS = ("auto", "srgb", "linear")


class Device(ABC):
    """Shows a native projector frame and returns the camera's image (float32 H×W×3, linear)."""

    projector: Projector

    @abstractmethod
    def project(self, frame: np.ndarray) -> np.ndarray:
        """Show ``frame`` (native projector resolution, float32 H×W×3 in [0, 1]) and capture."""

    def capture_off(self) -> np.ndarray:
        """Capture with the projector off; devices that cannot switch it off show a black frame."""
        w, h = self.projector.intrinsics.size
        return self.project(np.zeros((h, w, 3), dtype=np.float32))

    def close(self) -> None:  # noqa: B027 — a device that holds nothing needs no override
        """Release windows, cameras, renderers."""

    def check_frame(self, frame: np.ndarray) -> np.ndarray:
        f = np.asarray(frame, dtype=np.float32)
        if f.ndim == 2:
            f = np.repeat(f[..., None], 3, axis=2)
        w, h = self.projector.intrinsics.size
        if f.shape != (h, w, 3):
            raise CaptureError(f"a projector frame must be {w}×{h}×3 (the native resolution), got {f.shape}; "
                               "place an input image with Projector.frame_from_input")
        if not np.all(np.isfinite(f)) or f.min() < 0 or f.max() > 1:
            raise CaptureError("a projector frame must hold values in [0, 1]")
        return f

    def __enter__(self) -> "Device":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def capture_sequence(device: Device, sequence: Sequence[PatternSpec], out_dir: str | Path, camera: Camera, *,
                     force: bool = False, depth: np.ndarray | None = None, depth_info: DepthInfo | None = None,
                     notes: dict[str, Any] | None = None, **writer_args: Any) -> CaptureSet:
    """Show each pattern through ``device`` and write the captures as a new capture set."""
    with CaptureSetWriter(out_dir, camera, device.projector, depth_info=depth_info, notes=notes,
                          force=force, inputs=writer_args.pop("inputs", ()), **writer_args) as writer:
        for spec in sequence:
            frame = spec.image
            shot = device.capture_off() if spec.projector_off else device.project(frame)
            writer.add(spec.kind, shot, name=spec.name, frame=None if spec.projector_off else frame, **spec.params)
        if depth is not None:
            writer.add_depth(depth)
    return CaptureSet.load(out_dir, verify_images=False)


# -- folder workflow: export ---------------------------------------------------------------------

def _is_sequence(path: Path) -> bool:
    return holds_manifest(path, SEQUENCE_MANIFEST, SEQUENCE_FORMAT)


def export_sequence(projector: Projector, out_dir: str | Path, *, checker_size: int | None = None,
                    area: str = "input", seed: int = 0, camera: Camera | None = None, graycode: bool = True,
                    validation: bool = True, layout: str = "procam", force: bool = False) -> Path:
    """Write the numbered pattern frames (``0000_surface.png`` …) and ``sequence.json`` into a new folder.

    Frames are native projector resolution, 16-bit PNG, raw projector input
    levels (no sRGB transfer: show them without colour management). An
    existing non-empty folder is replaced only with ``force`` and only if it is
    itself an exported sequence.
    """
    seq = calibration_sequence(projector, checker_size, area=area, graycode=graycode, validation=validation, seed=seed,
                               layout=layout)
    folder = AtomicFolder(out_dir, force=force, what="pattern sequence", replaceable=_is_sequence, inputs=(),
                          error=CaptureError)
    try:
        frames = []
        for i, spec in enumerate(seq):
            file = f"{i:04d}_{spec.name}.png"
            write_image(folder.tmp / file, spec.image)
            frames.append({"index": i, "file": file, "name": spec.name, "kind": spec.kind, "params": spec.params})
        doc = {"format": SEQUENCE_FORMAT, "version": SEQUENCE_VERSION,
               "projector": projector.to_dict(), "camera": camera.to_dict() if camera else None,
               "area": area, "seed": int(seed), "count": len(frames),
               "encoding": "raw projector input levels in [0, 1], 16-bit PNG, no sRGB transfer",
               "instructions": [
                   "Show each frame full-screen on the projector, at its native resolution, without scaling "
                   "or colour management, in the numbered order.",
                   "For 'surface' switch the projector off (or cover the lens) and turn the room lights on, evenly: "
                   "this photo shows the surface's own colours. Take every other frame in the dark.",
                   "Keep camera exposure, white balance and focus fixed for the whole sequence.",
                   "Save one photo per frame; name them so that sorting by the number in the name gives the "
                   "sequence order (e.g. 0000.png, 0001.png …), then run: procam import-captures SEQUENCE CAPTURES --out SET"],
               "frames": frames}
        write_atomic_bytes(folder.tmp / SEQUENCE_MANIFEST, (json.dumps(doc, indent=1) + "\n").encode())
    except BaseException:
        folder.abort()
        raise
    return folder.commit()


@dataclass(frozen=True)
class SequenceInfo:
    """An exported pattern sequence as read back from ``sequence.json``."""

    path: Path
    projector: Projector
    camera: Camera | None
    frames: list[dict[str, Any]]


def load_sequence(sequence_dir: str | Path) -> SequenceInfo:
    root = Path(sequence_dir)
    manifest = root / SEQUENCE_MANIFEST
    if not manifest.is_file():
        raise CaptureError(f"{root} is not an exported pattern sequence: {SEQUENCE_MANIFEST} is missing "
                           "(create one with `procam patterns`)")
    try:
        doc = json.loads(manifest.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CaptureError(f"cannot read {manifest}: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != SEQUENCE_FORMAT:
        raise CaptureError(f"{manifest} is not a ProCam pattern sequence")
    if doc.get("version") != SEQUENCE_VERSION:
        raise CaptureError(f"{manifest}: sequence version {doc.get('version')!r} is not supported")
    try:
        projector = Projector.from_dict(doc["projector"])
        camera = Camera.from_dict(doc["camera"]) if doc.get("camera") else None
    except (KeyError, TypeError, ValueError, RigError) as exc:
        raise CaptureError(f"{manifest}: invalid projector or camera model: {exc}") from None
    frames = doc.get("frames")
    if not isinstance(frames, list) or not frames:
        raise CaptureError(f"{manifest}: no frames listed")
    for i, f in enumerate(frames):
        if not isinstance(f, dict) or not {"file", "name", "kind"} <= f.keys():
            raise CaptureError(f"{manifest}: frame {i} needs file, name and kind")
        # A frame is a file of the sequence: a name leading out of it would be copied into the capture set.
        inside(root, f["file"], what=f"{manifest.name}: frame {i}", error=CaptureError)
        if not isinstance(f.get("params") or {}, dict):
            raise CaptureError(f"{manifest}: frame {i}'s params must be an object, not {f['params']!r}; export the "
                               "sequence again with `procam patterns`")
    return SequenceInfo(root, projector, camera, frames)


def sequence_frame(seq: SequenceInfo, frame: dict[str, Any]) -> Path:
    """The file of one of ``seq``'s frames, inside the sequence folder."""
    return inside(seq.path, frame["file"], what="pattern frame", error=CaptureError)


# -- folder workflow: import ---------------------------------------------------------------------

def _png_bit_depth(head: bytes) -> int | None:
    if head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return head[24]


def _tiff_bit_depth(path: Path) -> int | None:
    """BitsPerSample (tag 258) of the first IFD of a classic TIFF; None when it cannot be told."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(8)
            if head[:2] not in (b"II", b"MM"):
                return None
            e = "<" if head[:2] == b"II" else ">"
            if struct.unpack(e + "H", head[2:4])[0] != 42:
                return None  # BigTIFF: not parsed here
            fh.seek(struct.unpack(e + "I", head[4:8])[0])
            (n,) = struct.unpack(e + "H", fh.read(2))
            for _ in range(n):
                tag, typ, count, value = struct.unpack(e + "HHI4s", fh.read(12))
                if tag == 258:
                    if count <= 2:
                        return struct.unpack(e + "H", value[:2])[0]
                    fh.seek(struct.unpack(e + "I", value)[0])
                    return struct.unpack(e + "H", fh.read(2))[0]
            return 1  # the TIFF default when the tag is absent
    except (OSError, struct.error):
        return None


def stored_bit_depth(path: str | Path) -> int | None:
    """Bits per channel of an image file (8, 16, 32 for float) read from its header; None if unknown."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".jpg", ".jpeg"):
        return 8
    if suffix == ".exr":
        return 32
    if suffix in (".tif", ".tiff"):
        return _tiff_bit_depth(path)
    if suffix == ".png":
        with open(path, "rb") as fh:
            return _png_bit_depth(fh.read(26))
    return None


def check_complete(path: str | Path) -> None:
    """Refuse files cut short. OpenCV rejects a truncated PNG but decodes a truncated JPEG with a grey tail."""
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            fh.seek(max(0, size - 4096))
            tail = fh.read()
    except OSError as exc:
        raise CaptureError(f"cannot read capture {path}: {exc.strerror or exc}") from None
    if size == 0:
        raise CaptureError(f"capture {path} is empty")
    if suffix == ".png" and b"IEND" not in tail[-16:]:
        raise CaptureError(f"capture {path} is truncated (no PNG end marker); copy it again from the camera")
    if suffix in (".jpg", ".jpeg") and not tail.rstrip(b"\x00\r\n ").endswith(b"\xff\xd9"):
        raise CaptureError(f"capture {path} is truncated (no JPEG end marker); copy it again from the camera")


def _number(path: Path) -> int | None:
    digits = re.findall(r"\d+", path.stem)
    return int(digits[-1]) if digits else None


def list_captures(captures_dir: str | Path, frame_files: list[str] | None = None) -> list[Path]:
    """The capture files of a folder in sequence order.

    Photographs saved under their frames' names (``0006_graycode_x00_inv.jpg``
    for ``0006_graycode_x00_inv.png``) are ordered as ``frame_files``; any
    other names by the last number in each (``IMG_0051.JPG``), as cameras
    number them. Frame names need the first rule: their last number is a
    pattern's own index, which repeats (``…_x00``, ``…_x00_inv``).
    """
    root = Path(captures_dir)
    if not root.is_dir():
        raise CaptureError(f"captures folder {root} does not exist")
    files = [p for p in root.iterdir() if p.is_file() and not p.name.startswith(".")
             and p.suffix.lower() in READ_IMAGE_SUFFIXES]
    if not files:
        raise CaptureError(f"no captures in {root} (expected numbered {', '.join(READ_IMAGE_SUFFIXES)} files)")
    order = {Path(f).stem: i for i, f in enumerate(frame_files or [])}
    if order and all(p.stem in order for p in files):
        return sorted(files, key=lambda p: order[p.stem])
    unnumbered = [p.name for p in files if _number(p) is None]
    if unnumbered:
        raise CaptureError(f"captures without a number in their name: {', '.join(sorted(unnumbered)[:5])}; "
                           "name them so the number gives the sequence order")
    by_number: dict[int, Path] = {}
    for p in files:
        n = _number(p)
        if n in by_number:
            raise CaptureError(f"captures {by_number[n].name} and {p.name} carry the same number {n}")
        by_number[n] = p
    return [by_number[n] for n in sorted(by_number)]


def _load_capture(path: Path, encoding: str) -> tuple[np.ndarray, str]:
    check_complete(path)
    bits = stored_bit_depth(path)
    try:
        img = read_image(path)
    except ImageError as exc:
        raise CaptureError(f"capture {path} is unreadable or damaged: {exc}") from None
    if encoding == "auto":
        if bits is None:
            raise CaptureError(f"cannot tell the bit depth of {path}; pass encoding='srgb' or 'linear' (--encoding)")
        encoding = "srgb" if bits <= 8 else "linear"
    if encoding == "srgb":
        if bits == 32:
            raise CaptureError(f"{path} is a float image; float captures are linear, not sRGB")
        return srgb_to_linear(img), f"sRGB-encoded {bits}-bit, linearised on import"
    return img, f"linear {bits}-bit" if bits else "linear"


def check_orientations(files: Sequence[Path]) -> int:
    """The photographs' common EXIF orientation; a photograph turned against the first one is refused by name.

    Phones store pixels as the sensor saw them and record how the phone was
    held in the EXIF orientation tag, which :func:`read_image` applies. One
    photograph whose tag differs from the others' was taken with the phone
    turned (or its orientation sensor flipped): imported as it is, it would lie
    sideways against the rest of the session.
    """
    first = exif_orientation(files[0])
    for path in files[1:]:
        o = exif_orientation(path)
        if o != first:
            raise CaptureError(
                f"photograph {path} is {ORIENTATIONS[o]} according to its EXIF orientation, but {files[0].name} is "
                f"{ORIENTATIONS[first]}: the camera was turned during the session (or its orientation sensor "
                "flipped). The camera must not move between shots: lock the screen rotation and capture again. If "
                "the camera did not move and only the tag changed, remove the orientation tag from every photograph "
                "(e.g. `exiftool -Orientation= -n *.jpg`) and import again")
    return first


def _size_message(path: Path, img: np.ndarray, camera: Camera) -> str:
    cw, ch = camera.intrinsics.size
    turned = (img.shape[1], img.shape[0]) == (ch, cw)
    return (f"capture {path} is {img.shape[1]}×{img.shape[0]} pixels, but the camera resolution is {cw}×{ch}"
            + ("; the photograph is turned by 90° against the others (rotated after it was taken, or the camera "
               "was turned): every photograph of a session must be taken, and saved, the same way up" if turned else ""))


def _depth_reference(white: np.ndarray | None, black: np.ndarray | None,
                     surface: np.ndarray | None) -> list[np.ndarray]:
    """Captures that show the surface's silhouette, for :func:`~.depth_io.find_alignment` to choose from."""
    refs = []
    if surface is not None:
        refs.append(surface)
    if white is not None:
        refs.append(np.maximum(white - (black if black is not None else 0.0), 0.0))
    return refs


#: How a capture set's notes begin (``notes["camera"]``) when a calibrated camera lens was taken out of its
#: photographs; sets from before ``camera_lens_removed`` recorded the lens are known by it.
LENS_REMOVED = "calibrated, lens distortion removed"


def import_captures(sequence_dir: str | Path, captures_dir: str | Path, camera: Camera | None,
                    projector: Projector | None, out_capture_dir: str | Path, *, encoding: str = "auto",
                    camera_fov: float = 60.0, depth: np.ndarray | None = None,
                    depth_native_size: tuple[int, int] | None = None, depth_path: str | Path | None = None,
                    depth_units: str = "auto", undistort: RigLens | None = None, check_session: bool = True,
                    progress: Progress | None = None, force: bool = False,
                    inputs: Iterable[str | Path | None] = ()) -> CaptureSet:
    """Turn photographs of an exported sequence into a new capture set (``inputs``: other files the run reads,
    never replaced, besides the sequence, the photographs and the depth file).

    Captures are matched to frames by name, or else by the number in their names (``list_captures``).
    ``encoding='auto'`` treats 8-bit files (JPEG, 8-bit PNG/TIFF) as sRGB and
    linearises them, 16-bit and float files as linear; the choice is recorded
    per image (``params.source_encoding``). A JPEG's EXIF orientation is
    applied, and a photograph turned against the others is refused
    (:func:`check_orientations`). ``camera`` None builds a nominal camera with
    ``camera_fov`` at the captures' size; ``projector`` None takes the one in
    ``sequence.json``.

    Depth: ``depth`` (an array in metres) or ``depth_path`` (any format
    :func:`~.depth_io.read_depth` reads: .npy/.exr metres, 16-bit PNG/TIFF
    millimetres, a PLY point cloud in the camera frame, projected at
    ``depth_native_size`` or the camera's size; ``depth_units`` auto/m/mm) is
    stored with the camera intrinsics scaled to its size. It is checked against
    the photographs for a shift of a few pixels (:func:`~.depth_io.find_alignment`),
    which is corrected with a warning or, when ambiguous, refused.

    ``undistort`` (a calibrated rig's camera lens) removes the camera's lens
    distortion from every photograph and the depth map (not from a projected
    point cloud, which is a pinhole view already), keeping its K, so the
    capture set is a pinhole camera's; it also marks the camera and projector
    as calibrated. ``check_session`` refuses a session whose exposure or white
    balance changed (:func:`~.exposure.check_exposure`). Warnings go to
    ``progress`` and into the capture set's notes. Any bad file raises a
    :class:`CaptureError` naming it, and nothing is written.
    """
    say = progress or quiet
    if encoding not in ENCODINGS:
        raise CaptureError(f"encoding must be one of {', '.join(ENCODINGS)}, got {encoding!r}")
    if depth is not None and depth_path is not None:
        raise CaptureError("give a depth array or a depth file, not both")
    seq = load_sequence(sequence_dir)
    projector = projector or seq.projector
    camera = camera or seq.camera
    files = list_captures(captures_dir, [f["file"] for f in seq.frames])
    if len(files) != len(seq.frames):
        raise CaptureError(f"the sequence has {len(seq.frames)} frames but {captures_dir} holds {len(files)} "
                           f"captures ({files[0].name} … {files[-1].name}); one capture per frame is needed")
    orientation = check_orientations(files)
    first, first_enc = _load_capture(files[0], encoding)
    size = (first.shape[1], first.shape[0])
    if camera is None:
        camera = Camera(intrinsics_from_fov(size[0], size[1], camera_fov))
        camera_note = f"nominal: {camera_fov}° horizontal field of view, centred principal point"
    else:
        camera_note = "given"
    depth_name = "the depth map"
    reading: DepthReading | None = None
    if depth_path is not None:
        reading = read_depth(depth_path, camera.intrinsics, units=depth_units, size=depth_native_size)
        depth_name = f"depth file {reading.path}"
        for warning in reading.warnings:
            say(f"warning: {warning}", 0.0)
        depth = reading.depth
    depth_info = None
    if depth is not None:
        dh, dw = np.asarray(depth).shape[:2]
        depth_info = DepthInfo(camera.intrinsics.scaled(dw, dh), tuple(depth_native_size or (dw, dh)))
    notes: dict[str, Any] = {"device": "folder", "sequence": str(Path(sequence_dir).resolve()),
                             "captures": str(Path(captures_dir).resolve()), "encoding": encoding,
                             "camera": camera_note}
    if orientation != 1:
        notes["orientation"] = f"EXIF orientation {orientation} ({ORIENTATIONS[orientation]}) applied to every photograph"
    status: dict[str, Any] = {}
    if undistort is not None:
        notes["camera"] = f"{LENS_REMOVED}: {undistort.source}"
        status = {"camera_status": "calibrated", "projector_status": "calibrated",
                  "projector_pose_known": undistort.pose_known}
    shots: list[Shot] = []
    kept: dict[str, np.ndarray] = {}  # the first white, black and surface photographs, for the depth's alignment
    with CaptureSetWriter(out_capture_dir, camera, projector, depth_info=depth_info, notes=notes, force=force,
                          inputs=(sequence_dir, captures_dir, depth_path, *inputs),
                          camera_lens=None if undistort is None else undistort.to_dict(),
                          **status) as writer:
        for i, (frame, path) in enumerate(zip(seq.frames, files)):
            say(f"importing {path.name}", i / len(files))
            img, enc = (first, first_enc) if i == 0 else _load_capture(path, encoding)
            if (img.shape[1], img.shape[0]) != camera.intrinsics.size:
                raise CaptureError(_size_message(path, img, camera))
            if undistort is not None:
                img = undistort.image(img)
            pattern = None
            if frame["kind"] != "surface":
                try:
                    pattern = read_image(sequence_frame(seq, frame))
                except ImageError as exc:
                    raise CaptureError(f"pattern frame {frame['file']} of the sequence is unreadable: {exc}") from None
            params = dict(frame.get("params") or {})
            writer.add(frame["kind"], img, name=frame["name"], frame=pattern, source=path.name,
                       source_encoding=enc, **params)
            if frame["kind"] in ("white", "black", "checker", "graycode"):
                shots.append(Shot(frame["kind"], params, reduce_image(img), path.name))
            if frame["kind"] in ("white", "black", "surface") and depth is not None:
                kept.setdefault(frame["kind"], img)
        if depth is not None:
            d = np.asarray(depth, dtype=np.float32)
            if undistort is not None and not (reading is not None and reading.projected):
                d = undistort.image(d, nearest=True)
            d = _align(d, kept, depth_name, reading, writer.notes, say)
            writer.add_depth(d)
        if check_session:
            say("checking that exposure and white balance stayed fixed", 1.0)
            report = check_exposure(shots, where=f"photographs in {Path(captures_dir)}")
            writer.notes["exposure"] = report.notes()
    return CaptureSet.load(out_capture_dir, verify_images=False)


def undistort_captures(captures: CaptureSet, lens: "RigLens", out: str | Path, *, force: bool = False,
                       inputs: Iterable[str | Path | None] = (), progress: Progress | None = None) -> CaptureSet:
    """A new capture set: ``captures`` with the calibrated camera ``lens`` taken out of every camera image and
    depth map, as ``import-captures --rig`` does at import, for a set captured (or rendered by the lab) before
    the camera was calibrated. The camera becomes the lens's pinhole and the set records the lens, so a live
    camera's frames go through it too; the projector, the patterns and the targets are kept as they are."""
    say = progress or quiet
    size = captures.camera.intrinsics.size
    if captures.camera_lens is not None:
        raise CaptureError(f"the camera's lens was already taken out of {captures.path} "
                           f"({captures.camera_lens.get('source')}); undistort the set it was made from")
    if lens.camera.size != size:
        raise CaptureError(f"the lens is calibrated for a {lens.camera.size[0]}×{lens.camera.size[1]} camera, but "
                           f"the capture set {captures.path} is {size[0]}×{size[1]}")
    depth_info = captures.depth_info
    if depth_info is not None:
        depth_info = replace(depth_info, intrinsics=lens.pinhole.scaled(*depth_info.intrinsics.size))
    notes = {**captures.notes, "camera": f"{LENS_REMOVED}: {lens.source}",
             "undistorted_from": str(Path(captures.path).resolve())}
    with CaptureSetWriter(out, Camera(lens.pinhole), captures.projector, depth_info=depth_info,
                          target_area=captures.target_area, camera_status="calibrated",
                          projector_status=captures.projector_status,
                          projector_pose_known=captures.projector_pose_known, notes=notes,
                          camera_lens=lens.to_dict(), force=force, inputs=(captures.path, *inputs)) as writer:
        for i, e in enumerate(captures.entries):
            say(f"undistorting {e.name}", i / max(len(captures.entries), 1))
            if e.kind == "depth":
                writer.add_depth(lens.image(captures._read_depth(e), nearest=True), name=e.name,
                                 suffix=Path(e.file).suffix, **e.params)
                continue
            image = captures._read(e.file)
            if e.kind in CAMERA_KINDS:
                image = np.clip(lens.image(image), 0.0, 1.0)
            pattern = captures._read(e.pattern) if e.pattern else None
            writer.add(e.kind, image, name=e.name, frame=pattern, **e.params)
    return CaptureSet.load(out, verify_images=False)


def _align(depth: np.ndarray, kept: dict[str, np.ndarray], name: str, reading: DepthReading | None,
           notes: dict[str, Any], say: Progress) -> np.ndarray:
    """The depth map checked (and corrected) for a shift against the photographs; notes["depth"] says what."""
    info: dict[str, Any] = reading.notes() if reading is not None else {"file": None, "format": "array (metres)"}
    warnings = list(info.get("warnings", []))
    refs = _depth_reference(kept.get("white"), kept.get("black"), kept.get("surface"))
    if refs:
        found = find_alignment(depth, refs, name=name)
        info["alignment"] = found.notes()
        if found.shift != (0, 0):
            depth = shift_image(depth, found.shift[0], found.shift[1], np.nan)
            warning = (f"{name} was misaligned with the photographs: shifted by {found.shift[0]:+d}, "
                       f"{found.shift[1]:+d} depth pixels to match the surface's edges (confidence "
                       f"{found.confidence:.2f}); register depth to colour in the capture app to avoid this")
            say(f"warning: {warning}", 1.0)
            warnings.append(warning)
        elif not found.checked:
            warnings.append(f"{name}: alignment with the photographs not checked: {found.reason}")
    valid = float(np.mean(np.isfinite(depth) & (depth > 0)))
    if valid < MIN_VALID:
        raise CaptureError(f"{name} is mostly holes: only {valid:.0%} of its pixels hold a depth (at least "
                           f"{MIN_VALID:.0%} needed); capture the depth again, or import without it")
    info["warnings"] = warnings
    notes["depth"] = info
    return depth


def _frame_key(frame: np.ndarray) -> str:
    # The 16-bit quantisation the capture set stores, so a frame matches its stored pattern file exactly.
    q = np.round(np.clip(np.asarray(frame, dtype=np.float32), 0, 1) * 65535.0).astype(np.uint16)
    return hashlib.sha1(q.tobytes() + str(q.shape).encode()).hexdigest()


class FolderDevice(Device):
    """Replays a capture set: ``project(frame)`` returns the capture recorded for exactly that frame.

    It lets the pipeline run offline on captures made with the user's own
    tools. A frame that was never captured raises a :class:`CaptureError`
    (export it, capture it, import again).
    """

    def __init__(self, capture_dir: str | Path) -> None:
        self.captures = CaptureSet.load(capture_dir)
        self.projector = self.captures.projector
        self.camera = self.captures.camera
        self._by_frame: dict[str, Entry] = {}
        keys: dict[str, str] = {}  # pattern file → key: patterns shown twice are stored once
        for e in self.captures.entries:
            if e.pattern:
                if e.pattern not in keys:
                    keys[e.pattern] = _frame_key(read_image(self.captures.pattern_file(e)))
                self._by_frame.setdefault(keys[e.pattern], e)

    def project(self, frame: np.ndarray) -> np.ndarray:
        f = self.check_frame(frame)
        entry = self._by_frame.get(_frame_key(f))
        if entry is None:
            raise CaptureError(f"this frame was never captured in {self.captures.path}; export it with the "
                               "sequence, capture it with your tools and import the captures again")
        return read_image(self.captures.file(entry))

    def capture_off(self) -> np.ndarray:
        if self.captures.entries_of("surface"):
            return self.captures.image("surface")
        return super().capture_off()


__all__ = ["Device", "FolderDevice", "LensRemovedDevice", "RigLens", "SequenceInfo", "capture_sequence",
           "check_complete", "check_orientations", "export_sequence", "import_captures", "list_captures",
           "load_sequence", "removed_lens", "stored_bit_depth", "undistort_captures"]


@dataclass(frozen=True)
class RigLens:
    """A calibrated camera lens to take out of photographs: its pinhole intrinsics and OpenCV's k1 k2 p1 p2 k3."""

    camera: Intrinsics
    distortion: np.ndarray
    source: str  # where it comes from, for the capture set's notes
    pose_known: bool = False  # the rig file also gives the projector's metric pose

    @property
    def pinhole(self) -> Intrinsics:
        """The pinhole camera the photographs become: the lens's K with square pixels (f = √(fx·fy)), because the
        renderer's camera has them; a calibrated fx and fy differ a little (0.05 % on the real board photos)."""
        f = math.sqrt(self.camera.fx * self.camera.fy)
        return replace(self.camera, fx=f, fy=f)

    def image(self, img: np.ndarray, *, nearest: bool = False) -> np.ndarray:
        """``img`` as the :attr:`pinhole` camera would see it (pixels from outside the frame are 0).

        A depth map smaller than the photographs (same lens, aligned) gets K scaled to its size."""
        a = np.asarray(img, dtype=np.float32)
        h, w = a.shape[:2]
        k = self.camera.scaled(w, h).opencv_matrix()
        mx, my = cv2.initUndistortRectifyMap(k, self.distortion, None, self.pinhole.scaled(w, h).opencv_matrix(),
                                             (w, h), cv2.CV_32FC1)
        out = cv2.remap(a, mx, my, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return out.reshape(a.shape)

    def to_dict(self) -> dict[str, Any]:
        """As a capture set records it (``camera_lens_removed``)."""
        return {"camera": self.camera.to_dict(), "distortion": [float(v) for v in np.ravel(self.distortion)],
                "source": self.source}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> "RigLens":
        return RigLens(Intrinsics.from_dict(d["camera"]), np.asarray(d["distortion"], np.float64), str(d["source"]))


def removed_lens(captures: CaptureSet) -> RigLens | None:
    """The calibrated camera lens import took out of ``captures``' photographs (None: it took none out).

    A capture set made by an earlier ProCam says in its notes that a lens was taken out but does not record
    which: a live camera's frames could then not be put through the same, and are refused."""
    if captures.camera_lens is not None:
        return RigLens.from_dict(captures.camera_lens)
    if LENS_REMOVED in str(captures.notes.get("camera", "")):
        raise CaptureError(f"the photographs of {captures.path} had the camera's lens distortion taken out at "
                           "import, but the capture set does not record that lens (made by an earlier ProCam), so a "
                           "live camera's frames cannot be undistorted the same way; import the photographs again "
                           "with --rig, then calibrate")
    return None


class LensRemovedDevice(Device):
    """A device whose camera images go through the lens taken out of the calibration's photographs.

    A capture set imported with a rig file (``import-captures --rig``, ``capture --rig``) or undistorted after
    (``undistort-captures``) holds photographs with the camera's lens distortion taken out, and its calibration
    lives in that pinhole camera; a live camera (or the lab's) still delivers the lens's image, which would sit
    up to the lens's displacement off the calibration, silently."""

    def __init__(self, device: Device, lens: RigLens) -> None:
        self.device, self.lens = device, lens
        self.projector = device.projector

    def __getattr__(self, name: str) -> Any:  # the live device's report, camera_size, …
        return getattr(self.device, name)

    def project(self, frame: np.ndarray) -> np.ndarray:
        return self.lens.image(self.device.project(frame))

    def capture_off(self) -> np.ndarray:
        return self.lens.image(self.device.capture_off())

    def close(self) -> None:
        self.device.close()
