"""Photographs into a capture set: the import of a photographed pattern sequence, and the camera lens taken out.

:func:`import_captures` checks the photographs (numbering, sizes, bit depth,
orientation, exposure), reads the depth and aligns it, and writes a capture
set; with a rig calibration's lens it takes the camera's distortion out of
every photograph and records the lens (:data:`LENS_REMOVED`);
:func:`undistort_captures` does the same for a set imported before, and
:func:`removed_lens` says which lens a set had taken out. :func:`add_projector_captures` makes a new set of
several projectors: an existing set's captures and one more projector's photographs, taken by the same camera
while the other projectors showed black.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import CaptureError, ImageError
from ..imageio import ORIENTATIONS, READ_IMAGE_SUFFIXES, exif_orientation, read_image
from ..progress import Progress, quiet
from ..rig.model import Camera, Projector, intrinsics_from_fov
from .depth_io import MIN_VALID, DepthReading, find_alignment, read_depth, shift_image
from .exposure import Shot, check_exposure, reduce_image
from .others_black import check_projector_captures
from .format import CAMERA_KINDS, SHARED_KINDS, CaptureSet, CaptureSetWriter, DepthInfo, Entry, srgb_to_linear
from ..rig.lens import RigLens
from .sequence import SequenceInfo, load_sequence, sequence_frame

ENCODINGS = ("auto", "srgb", "linear")



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


def load_capture(path: Path, encoding: str) -> tuple[np.ndarray, str]:
    """One photograph as import reads it (linear float32; complete-file check, EXIF orientation), and how it was
    encoded: ``encoding`` auto takes 8-bit files as sRGB, 16-bit and float ones as linear."""
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
    why = ("; the photograph is turned by 90° against the others (rotated after it was taken, or the camera was "
           "turned): every photograph of a session must be taken, and saved, the same way up") if turned else ""
    return f"capture {path} is {img.shape[1]}×{img.shape[0]} pixels, but the camera resolution is {cw}×{ch}" + why


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
    if seq.projector_index:
        number = seq.projector_index + 1
        raise CaptureError(f"{sequence_dir} is projector {number}'s sequence (exported with --projector-number "
                           f"{number}, without the surface photo): add its photographs to the capture set of "
                           f"projectors 1 to {number - 1}, `procam import-captures {sequence_dir} {captures_dir} "
                           "--add-to SET --out NEW_SET`")
    projector = projector or seq.projector
    camera = camera or seq.camera
    files, orientation, first, first_enc = _photographs(seq, captures_dir, encoding)
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
        notes["orientation"] = (f"EXIF orientation {orientation} ({ORIENTATIONS[orientation]}) applied to every "
                                "photograph")
    status: dict[str, Any] = {}
    if undistort is not None:
        notes["camera"] = f"{LENS_REMOVED}: {undistort.source}"
        status = {"camera_status": "calibrated", "projector_status": "calibrated",
                  "projector_pose_known": undistort.pose_known}
    with CaptureSetWriter(out_capture_dir, camera, projector, depth_info=depth_info, notes=notes, force=force,
                          inputs=(sequence_dir, captures_dir, depth_path, *inputs),
                          camera_lens=None if undistort is None else undistort.to_dict(),
                          **status) as writer:
        shots, kept = _add_photographs(writer, seq, files, (first, first_enc), encoding, undistort, say,
                                       keep=depth is not None)
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


def _photographs(seq: SequenceInfo, captures_dir: str | Path, encoding: str
                 ) -> tuple[list[Path], int, np.ndarray, str]:
    """The photographs of ``seq``'s frames in ``captures_dir``, in frame order, checked one per frame and all
    the same way up; with their EXIF orientation, and the first one read (with how it was encoded)."""
    files = list_captures(captures_dir, [f["file"] for f in seq.frames])
    if len(files) != len(seq.frames):
        raise CaptureError(f"the sequence has {len(seq.frames)} frames but {captures_dir} holds {len(files)} "
                           f"captures ({files[0].name} … {files[-1].name}); one capture per frame is needed")
    orientation = check_orientations(files)
    first, first_enc = load_capture(files[0], encoding)
    return files, orientation, first, first_enc


def _add_photographs(writer: CaptureSetWriter, seq: SequenceInfo, files: list[Path], first: tuple[np.ndarray, str],
                     encoding: str, undistort: RigLens | None, say: Progress, *, projector_index: int = 0,
                     keep: bool = False) -> tuple[list[Shot], dict[str, np.ndarray]]:
    """Each photograph into ``writer`` as the capture of its frame, shown by projector ``projector_index`` (its
    entries named ``NAME_pK`` after the first projector's, as the lab names them; the surface frame of a
    sequence added to a set that has its surface photo already is left out). Returns the shots of the exposure
    check and, with ``keep``, the first white, black and surface photographs, for the depth's alignment."""
    shots: list[Shot] = []
    kept: dict[str, np.ndarray] = {}
    camera = writer.camera
    for i, (frame, path) in enumerate(zip(seq.frames, files)):
        say(f"importing {path.name}", i / len(files))
        if projector_index and frame["kind"] in SHARED_KINDS:
            continue
        img, enc = first if i == 0 else load_capture(path, encoding)
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
        name = f"{frame['name']}_p{projector_index}" if projector_index else frame["name"]
        writer.add(frame["kind"], img, name=name, frame=pattern, source=path.name, source_encoding=enc,
                   projector_index=projector_index, **params)
        if frame["kind"] in ("white", "black", "checker", "graycode"):
            shots.append(Shot(frame["kind"], params, reduce_image(img), path.name))
        if frame["kind"] in ("white", "black", "surface") and keep:
            kept.setdefault(frame["kind"], img)
    return shots, kept


def _check_new_projector(base: CaptureSet, seq: SequenceInfo, captures_dir: Path) -> None:
    """Refuse a sequence, or photographs, that are not a new projector's: each projector is added once, in order,
    and a sequence without a projector number only when its size tells it from every projector of ``base``."""
    index = len(base.projectors)
    number = seq.projector_index + 1
    if seq.projector_index and seq.projector_index < index:
        raise CaptureError(f"{seq.path} is projector {number}'s sequence, and {base.path} holds projector {number}'s "
                           f"captures already: each projector is added once. Add projector {index + 1}'s (its "
                           f"patterns exported with --projector-number {index + 1})")
    if seq.projector_index > index:
        raise CaptureError(f"{seq.path} is projector {number}'s sequence, but {base.path} holds {index} "
                           f"projector(s): add projector {index + 1} first, the projectors in their order")
    size = seq.projector.intrinsics.size
    if not seq.projector_index:
        same = [k for k, p in enumerate(base.projectors) if p.intrinsics.size == size]
        if same:
            raise CaptureError(
                f"{seq.path} was exported without a projector number, for a {size[0]}×{size[1]} projector as "
                f"projector {same[0] + 1} of {base.path} is: it may be that projector's sequence again. Export "
                f"projector {index + 1}'s patterns with `procam patterns … --projector-number {index + 1}`, "
                "photograph them while the other projectors show black, and add those")
    here = Path(captures_dir).resolve()
    imported = [base.notes.get("captures"), *(a.get("captures") for a in _added(base.notes))]
    for k, folder in enumerate(imported):
        if folder and Path(str(folder)) == here:
            raise CaptureError(f"the photographs in {captures_dir} are in {base.path} already (projector "
                               f"{k + 1}'s); give the photographs of projector {index + 1}'s sequence")


def _added(notes: dict[str, Any]) -> list[dict[str, Any]]:
    """The records of the projectors added to a set after its first (``notes["added_projectors"]``)."""
    added = notes.get("added_projectors")
    return [a for a in added if isinstance(a, dict)] if isinstance(added, list) else []


def _check_same_lens(base: CaptureSet, undistort: RigLens | None) -> None:
    """Refuse photographs of a new projector that would not become the pinhole camera of ``base``'s: the same
    calibrated lens taken out of them (a rig file whose camera is the same), or none out of either."""
    have = removed_lens(base)
    if have is None and undistort is None:
        return
    if have is not None and undistort is None:
        raise CaptureError(f"the camera's lens distortion was taken out of the photographs of {base.path} "
                           f"({have.source}); take the same lens out of this projector's: give --rig, a rig "
                           "calibration of this projector with that same camera calibration")
    if have is None or undistort is None:
        raise CaptureError(f"the photographs of {base.path} kept the camera's lens distortion (imported without "
                           "--rig), but --rig would take it out of this projector's, and one camera must see every "
                           "projector: add them without --rig (`procam undistort-captures` takes the lens out of the "
                           "whole set afterwards), or import every projector's photographs with --rig")
    if (have.camera.to_dict() != undistort.camera.to_dict()
            or np.shape(have.distortion) != np.shape(undistort.distortion)
            or not np.array_equal(np.asarray(have.distortion, float), np.asarray(undistort.distortion, float))):
        raise CaptureError(f"the rig calibration {undistort.source} has another camera lens than the one taken out "
                           f"of the photographs of {base.path} ({have.source}): every projector's photographs must go "
                           "through one camera calibration. Use rig files that share it, or add the photographs "
                           "without --rig to a set imported without it and take the lens out of the whole set with "
                           "`procam undistort-captures SET --rig RIG`")


def add_projector_captures(base: CaptureSet, sequence_dir: str | Path, captures_dir: str | Path,
                           out_capture_dir: str | Path, *, projector: Projector | None = None,
                           encoding: str = "auto", undistort: RigLens | None = None, check_session: bool = True,
                           progress: Progress | None = None, force: bool = False,
                           inputs: Iterable[str | Path | None] = ()) -> CaptureSet:
    """A NEW capture set: every capture of ``base`` and one more projector's, the photographs in ``captures_dir``
    of the sequence in ``sequence_dir``, taken by ``base``'s camera while every other projector showed black.

    ``base`` is an input: it is read, never changed or replaced (``out_capture_dir`` may not be it). The new
    projector is projector ``len(base.projectors)`` (numbered from 0): the sequence must be its own
    (:func:`_check_new_projector`), photographed at ``base``'s camera size, through the same calibrated lens
    as ``base``'s photographs (``undistort``) or none (:func:`_check_same_lens`). ``projector`` (default the
    sequence's) is its model, e.g. from its rig file. The surface photo, the depth and the targets are
    ``base``'s; a surface frame in the sequence is left out. The finished set must pass
    :func:`.others_black.check_projector_captures` (no projector's photographs another's; the others black)
    before it is moved into place; any problem raises a
    :class:`CaptureError` and nothing is written.
    """
    say = progress or quiet
    if encoding not in ENCODINGS:
        raise CaptureError(f"encoding must be one of {', '.join(ENCODINGS)}, got {encoding!r}")
    seq = load_sequence(sequence_dir)
    index = len(base.projectors)
    _check_new_projector(base, seq, Path(captures_dir))
    _check_same_lens(base, undistort)
    files, orientation, first, first_enc = _photographs(seq, captures_dir, encoding)
    size, cam = (first.shape[1], first.shape[0]), base.camera.intrinsics.size
    if size != cam:
        turned = " (turned by 90°)" if size == cam[::-1] else ""
        raise CaptureError(f"the photographs in {captures_dir} are {size[0]}×{size[1]} pixels{turned} "
                           f"({files[0].name}), but {base.path}'s camera took {cam[0]}×{cam[1]}: every projector's "
                           "sequence must be photographed by the same camera, unmoved, at the same size and the "
                           "same way up")
    pose_known = base.projector_pose_known and undistort is not None and undistort.pose_known
    record: dict[str, Any] = {"projector": index, "sequence": str(Path(sequence_dir).resolve()),
                              "captures": str(Path(captures_dir).resolve()), "encoding": encoding,
                              "added_to": str(Path(base.path).resolve())}
    if orientation != 1:
        record["orientation"] = f"EXIF orientation {orientation} ({ORIENTATIONS[orientation]}) applied"
    if base.projector_pose_known and not pose_known:
        warning = (f"projector {index + 1}'s pose is not known (no metric rig file), so the set no longer knows "
                   "any projector's pose: calibration finds every pose")
        say(f"warning: {warning}", 0.0)
        record["warning"] = warning
    notes = {**base.notes, "added_projectors": [*_added(base.notes), record]}
    out = Path(out_capture_dir)
    with CaptureSetWriter(out, base.camera, base.projector, others=(*base.others, projector or seq.projector),
                          depth_info=base.depth_info, target_area=base.target_area,
                          camera_status=base.camera_status,
                          projector_status=("calibrated" if base.projector_status == "calibrated"
                                            and undistort is not None else "nominal"),
                          projector_pose_known=pose_known, notes=notes, camera_lens=base.camera_lens, force=force,
                          inputs=(base.path, sequence_dir, captures_dir, *inputs),
                          check=lambda written: check_projector_captures(written, where=str(out))) as writer:
        say(f"copying the {len(base.entries)} images of {base.path}", 0.0)
        for e in base.entries:
            writer.copy(base, e)
        shots, _ = _add_photographs(writer, seq, files, (first, first_enc), encoding, undistort, say,
                                    projector_index=index)
        if check_session:
            say("checking that exposure and white balance stayed fixed", 1.0)
            record["exposure"] = check_exposure(shots, where=f"photographs in {Path(captures_dir)}").notes()
    return CaptureSet.load(out, verify_images=False)


def undistort_captures(captures: CaptureSet, lens: RigLens, out: str | Path, *, force: bool = False,
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
    with CaptureSetWriter(out, Camera(lens.pinhole), captures.projector, others=captures.others, depth_info=depth_info,
                          target_area=captures.target_area, camera_status="calibrated",
                          projector_status=captures.projector_status,
                          projector_pose_known=captures.projector_pose_known, notes=notes,
                          camera_lens=lens.to_dict(), force=force, inputs=(captures.path, *inputs)) as writer:
        def undistorted(e: Entry, image: np.ndarray) -> np.ndarray:
            if e.kind == "depth":
                return lens.image(image, nearest=True)
            return np.clip(lens.image(image), 0.0, 1.0) if e.kind in CAMERA_KINDS else image

        for i, e in enumerate(captures.entries):
            say(f"undistorting {e.name}", i / max(len(captures.entries), 1))
            writer.copy(captures, e, image=undistorted)
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
