"""Capture sets: a folder with ``capture.json`` and the images a session captured.

A capture set is what a real session (projector + camera + phone/RGBD depth)
or the virtual lab produces, and what calibration reads. Layout::

    capture.json          models + one entry per image (schema below)
    images/NNNN_name.png  camera captures, 16-bit linear PNG at the camera resolution
    patterns/NNNN_name.png  the native projector frame that was shown for an entry
    depth/name.npy        depth in metres (float32 .npy or .exr), 0 = no measurement

``capture.json`` (format ``procam-capture``, version 1)::

    {"format": "procam-capture", "version": 1, "colour_space": "linear",
     "camera": Camera.to_dict(), "camera_status": "nominal" | "calibrated",
     "projector": Projector.to_dict(), "projector_status": "nominal" | "calibrated",
     "projector_pose_known": false,
     "depth": {"intrinsics": Intrinsics.to_dict() of the depth image as stored,
               "native_size": [256, 192], "units": "metres", "missing": 0} | null,
     "target_area": [x, y, width, height] | null,   # camera pixels, corner convention
     "notes": {...},                                 # free-form provenance
     "camera_lens_removed": {"camera": Intrinsics.to_dict(), "distortion": [k1, k2, p1, p2, k3],
                             "source": "..."},      # only when import took a calibrated lens out
     "images": [{"file": "images/0003_checker_p0.png", "kind": "checker", "name": "checker_p0",
                 "pattern": "patterns/0003_checker_p0.png",
                 "params": {"square": 50, "phase": 0, "area": "input"}}, ...]}

Several projectors, one camera and one surface: ``"projectors": [Projector.to_dict(), ...]`` lists every
projector (``"projector"`` is still the first, so a one-projector reader reads it), and each entry a projector
showed while the others were black says which, ``"projector": 1`` (numbered from 0; written only when not 0, so
a one-projector set is written exactly as before). The surface photo, the depth images and targets are shared by
all projectors and carry no index. :meth:`CaptureSet.for_projector` gives the one-projector view of a projector
that single-projector code reads unchanged.

Kinds and their required ``params``: ``surface`` (projector off), ``black``,
``white``, ``checker`` (square, phase), ``graycode`` (axis, bit, inverted),
``validation`` (pattern, plus its own parameters), ``target`` (a desired
appearance; any size, it is fitted into ``target_area`` later), ``depth``.
``params`` may also carry provenance such as ``source_encoding``.

Captures are never modified in place: :class:`CaptureSetWriter` builds a new
set in a hidden sibling folder and renames it into place only once it is
complete and loads back cleanly.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..colour import srgb_decode, srgb_encode
from ..errors import CaptureError, ImageError, RigError
from ..imageio import known_size, read_image, remember_size, write_atomic_bytes, write_image
from ..outputs import AtomicFolder, holds_manifest, jsonable
from ..rig.model import Camera, Intrinsics, Projector, projectors_from_dict
from ..safepaths import inside

FORMAT = "procam-capture"
VERSION = 1
SUPPORTED_VERSIONS = (1,)
MANIFEST = "capture.json"

KINDS = ("surface", "black", "white", "checker", "graycode", "validation", "target", "depth")
#: Kinds whose image is a camera capture and so must have the camera's size.
CAMERA_KINDS = ("surface", "black", "white", "checker", "graycode", "validation")
#: Kinds shared by every projector of a set (taken once, projectors off or not involved): they carry no index.
SHARED_KINDS = ("surface", "target", "depth")
REQUIRED_PARAMS: dict[str, tuple[str, ...]] = {
    "checker": ("square", "phase"),
    "graycode": ("axis", "bit", "inverted"),
    "validation": ("pattern",),
}
#: Parameter of a ``depth`` entry that makes it the sensor's image of a flat wall at this distance (metres),
#: from which calibration reads the sensor's constant bias; the scene's depth entry has no such parameter.
WALL_PARAM = "wall_distance_m"
#: A depth map with more than this share of missing pixels is refused.
MAX_DEPTH_MISSING = 0.5
IMAGE_SUFFIXES = (".png", ".exr", ".npy")
DEPTH_SUFFIXES = (".npy", ".exr")


def _non_finite(value: Any, at: str = "") -> tuple[str, float] | None:
    """The first number in a JSON document that is NaN or infinite (Python's reader accepts ``NaN``,
    ``Infinity`` and ``1e999``), as its dotted key path and value; None when every number is finite."""
    if isinstance(value, float) and not math.isfinite(value):
        return at or "the document", value
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, item in items:
        found = _non_finite(item, f"{at}.{key}" if at else str(key))
        if found is not None:
            return found
    return None


@dataclass(frozen=True)
class DepthInfo:
    """Intrinsics of the depth image as stored, and the sensor's native resolution."""

    intrinsics: Intrinsics
    native_size: tuple[int, int]

    def to_dict(self) -> dict[str, Any]:
        return {"intrinsics": self.intrinsics.to_dict(), "native_size": [int(v) for v in self.native_size],
                "units": "metres", "missing": 0}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> DepthInfo:
        size = d.get("native_size")
        if (not isinstance(size, (list, tuple)) or len(size) != 2
                or not all(isinstance(v, int) and v > 0 for v in size)):
            raise CaptureError(f"depth native_size must be [width, height] in pixels, got {size!r}")
        if d.get("units", "metres") != "metres":
            raise CaptureError(f"depth units must be metres, got {d.get('units')!r}")
        try:
            intr = Intrinsics.from_dict(d["intrinsics"])
        except (KeyError, TypeError, RigError) as exc:
            raise CaptureError(f"depth intrinsics are invalid: {exc}") from None
        return DepthInfo(intr, (int(size[0]), int(size[1])))


@dataclass(frozen=True)
class Entry:
    """One image of a capture set: what it shows and where it lies (paths relative to the set)."""

    file: str
    kind: str
    name: str
    params: dict[str, Any] = field(default_factory=dict)
    pattern: str | None = None
    #: which projector showed it (0 = the first); the others showed black
    projector: int = 0

    def matches(self, filters: dict[str, Any]) -> bool:
        for key, value in filters.items():
            have = self.name if key == "name" else self.params.get(key, _MISSING)
            if have is _MISSING or have != value:
                return False
        return True

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"file": self.file, "kind": self.kind, "name": self.name}
        if self.pattern:
            d["pattern"] = self.pattern
        if self.params:
            d["params"] = jsonable(self.params)
        if self.projector:
            d["projector"] = int(self.projector)
        return d


_MISSING = object()

def _check_params(kind: str, params: dict[str, Any], where: str) -> None:
    missing = [p for p in REQUIRED_PARAMS.get(kind, ()) if p not in params]
    if missing:
        raise CaptureError(f"{where}: a {kind!r} entry needs the parameter(s) {', '.join(missing)}")
    if kind == "checker":
        sq, ph = params["square"], params["phase"]
        if not isinstance(sq, int) or isinstance(sq, bool) or sq <= 0:
            raise CaptureError(f"{where}: checker square size must be a positive number of pixels, got {sq!r}")
        if ph not in (0, 1) or isinstance(ph, bool):
            raise CaptureError(f"{where}: checker phase must be 0 or 1, got {ph!r}")
    elif kind == "graycode":
        if params["axis"] not in ("x", "y"):
            raise CaptureError(f"{where}: Gray-code axis must be 'x' or 'y', got {params['axis']!r}")
        bit = params["bit"]
        if not isinstance(bit, int) or isinstance(bit, bool) or bit < 0:
            raise CaptureError(f"{where}: Gray-code bit must be a whole number ≥ 0, got {bit!r}")
        if not isinstance(params["inverted"], bool):
            raise CaptureError(f"{where}: Gray-code 'inverted' must be true or false, got {params['inverted']!r}")
    area = params.get("area")
    if area is not None and area not in ("input", "frame"):
        raise CaptureError(f"{where}: pattern area must be 'input' or 'frame', got {area!r}")


def _projector_index(value: Any, kind: str, count: int, where: str) -> int:
    """An entry's projector number, checked: a whole number naming one of the set's ``count`` projectors, and 0 for
    the kinds every projector shares."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < count:
        raise CaptureError(f"{where}: 'projector' must be a projector of the set, numbered 0 to {count - 1}, got "
                           f"{value!r}")
    if value and kind in SHARED_KINDS:
        raise CaptureError(f"{where}: a {kind} image is shared by every projector and names none, got projector "
                           f"{value}")
    return value


def _check_sequences(entries: list[Entry], count: int, where: str) -> None:
    """Each projector of a multi-projector set has captures of its own: a projector listed without them is a
    sequence that was never captured (or got lost), refused before calibration meets it."""
    shown = {e.projector for e in entries if e.kind not in SHARED_KINDS}
    # named from 1 as every message names projectors; the manifest's "projector" field counts from 0
    missing = [str(k + 1) for k in range(count) if k not in shown]
    if missing:
        raise CaptureError(f"{where}: the set lists {count} projectors, but holds no captures of projector(s) "
                           f"{', '.join(missing)} (numbered from 1; an entry's \"projector\" is that number less 1); "
                           "capture each projector's sequence (while the others show black)")


def _lens_removed(value: Any, where: str) -> dict[str, Any] | None:
    """The ``camera_lens_removed`` entry, checked: a camera's intrinsics and OpenCV's 4 to 8 distortion terms."""
    if value is None:
        return None
    try:
        Intrinsics.from_dict(value["camera"])
        terms = [float(v) for v in value["distortion"]]
        if not 4 <= len(terms) <= 8 or not all(math.isfinite(v) for v in terms):
            raise ValueError(f"{len(terms)} distortion terms, or one not finite")
    except (KeyError, TypeError, ValueError, RigError) as exc:
        raise CaptureError(f"{where}: invalid camera_lens_removed (the lens import took out): {exc}") from None
    return {"camera": value["camera"], "distortion": terms, "source": str(value.get("source", ""))}


def _size(img: np.ndarray) -> tuple[int, int]:
    return (int(img.shape[1]), int(img.shape[0]))


def validate_depth(depth: np.ndarray, where: str) -> np.ndarray:
    """Check a depth map (metres, 0/NaN = missing); return it as float32 with NaN for missing."""
    d = np.asarray(depth, dtype=np.float32)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[..., 0]
    if d.ndim == 3:
        # A depth image saved with repeated channels: accept only if they agree.
        if not np.allclose(d, d[..., :1], equal_nan=True):
            raise CaptureError(f"{where}: depth must have one channel, got {d.shape[2]} different ones")
        d = d[..., 0]
    if d.ndim != 2:
        raise CaptureError(f"{where}: depth must be an H×W array, got shape {d.shape}")
    finite = np.isfinite(d)
    if np.any(np.isinf(d)):
        raise CaptureError(f"{where}: depth holds infinite values; store missing depth as 0")
    if np.any(d[finite] < 0):
        raise CaptureError(f"{where}: depth holds negative values (min {float(np.nanmin(d)):.3f} m); "
                           "depth is a distance in metres and must be positive")
    valid = finite & (d > 0)
    missing = 1.0 - float(valid.mean()) if d.size else 1.0
    if missing > MAX_DEPTH_MISSING:
        raise CaptureError(f"{where}: depth map is mostly empty ({missing:.0%} of pixels are 0 or NaN, "
                           f"at most {MAX_DEPTH_MISSING:.0%} allowed); re-capture the depth or check its units")
    return np.where(valid, d, np.nan).astype(np.float32)


@dataclass
class CaptureSet:
    """A loaded, validated capture set. Images are read from disk on demand (never cached, never written)."""

    path: Path
    camera: Camera
    projector: Projector
    entries: list[Entry]
    depth_info: DepthInfo | None = None
    target_area: tuple[int, int, int, int] | None = None
    camera_status: str = "nominal"
    projector_status: str = "nominal"
    projector_pose_known: bool = False
    colour_space: str = "linear"
    notes: dict[str, Any] = field(default_factory=dict)
    version: int = VERSION
    #: the calibrated camera lens import took out of every photograph (``RigLens.to_dict``), None when it took
    #: none: a live camera's frames must go through the same before they meet this set's calibration
    camera_lens: dict[str, Any] | None = None
    #: projectors 2…N of a multi-projector set (``projector`` is the first); empty for one projector
    others: tuple[Projector, ...] = ()

    @property
    def projectors(self) -> tuple[Projector, ...]:
        """Every projector of the set, the first (``projector``) first."""
        return (self.projector, *self.others)

    # -- loading ---------------------------------------------------------------------------------

    @staticmethod
    def load(path: str | Path, *, verify_images: bool = True) -> CaptureSet:
        """Read and validate a capture set; every problem is a :class:`CaptureError` naming the file.

        With ``verify_images`` (default) every image is decoded once to check it
        is readable, complete and of the right size; images are not kept.
        """
        root = Path(path)
        if not root.is_dir():
            raise CaptureError(f"no capture set at {root}: folder does not exist")
        manifest = root / MANIFEST
        if not manifest.is_file():
            raise CaptureError(f"{root} is not a capture set: {MANIFEST} is missing")
        try:
            doc = json.loads(manifest.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError) as exc:
            raise CaptureError(f"cannot read {manifest}: {exc}") from None
        except json.JSONDecodeError as exc:
            raise CaptureError(f"{manifest} is not valid JSON (line {exc.lineno}, column {exc.colno}): "
                               f"{exc.msg}") from None
        cs = CaptureSet._from_doc(root, doc, str(manifest))
        if verify_images:
            cs.verify()
        return cs

    @staticmethod
    def _from_doc(root: Path, doc: Any, where: str) -> CaptureSet:
        if not isinstance(doc, dict):
            raise CaptureError(f"{where}: expected a JSON object")
        # capture.json is standard JSON (its writer refuses NaN and infinities): a value that is not, which only a
        # hand edit or another program makes, is refused here, before any work, rather than carried into the
        # capture sets made from this one, whose manifest could then not be written.
        odd = _non_finite(doc)
        if odd is not None:
            raise CaptureError(f"{where}: {odd[0]} is {odd[1]}, which standard JSON cannot hold; give a finite number "
                               "or remove it")
        if doc.get("format") != FORMAT:
            raise CaptureError(f"{where}: not a ProCam capture set (format {doc.get('format')!r}, expected {FORMAT!r})")
        version = doc.get("version")
        if version not in SUPPORTED_VERSIONS:
            raise CaptureError(f"{where}: capture-set version {version!r} is not supported by this ProCam "
                               f"(supported: {', '.join(map(str, SUPPORTED_VERSIONS))}); update ProCam")
        colour = doc.get("colour_space", "linear")
        if colour != "linear":
            raise CaptureError(f"{where}: colour space {colour!r} is not supported; captures must be stored linear")
        try:
            camera = Camera.from_dict(doc["camera"])
            # the poses of a capture set's projectors may all be unknown placeholders, so unlike a rig's they may
            # coincide (projector_pose_known)
            projector, others = projectors_from_dict({"projector": doc["projector"],
                                                      **({"projectors": doc["projectors"]} if "projectors" in doc
                                                         else {})})
        except KeyError as exc:
            raise CaptureError(f"{where}: missing {exc} model") from None
        except (RigError, TypeError, ValueError) as exc:
            raise CaptureError(f"{where}: invalid camera or projector model: {exc}") from None
        count = 1 + len(others)
        for key in ("depth", "notes"):
            if doc.get(key) and not isinstance(doc[key], dict):
                raise CaptureError(f"{where}: '{key}' must be an object, not {doc[key]!r}; remake the capture set")
        depth_info = DepthInfo.from_dict(doc["depth"]) if doc.get("depth") else None
        target_area = doc.get("target_area")
        if target_area is not None:
            ok = (isinstance(target_area, (list, tuple)) and len(target_area) == 4
                  and all(isinstance(v, int) and not isinstance(v, bool) for v in target_area))
            if ok:
                x, y, w, h = target_area
                cw, ch = camera.intrinsics.size
                ok = w > 0 and h > 0 and x >= 0 and y >= 0 and x + w <= cw and y + h <= ch
            if not ok:
                raise CaptureError(f"{where}: target_area must be [x, y, width, height] of whole camera pixels "
                                   f"inside the {camera.intrinsics.width}×{camera.intrinsics.height} image, "
                                   f"got {target_area!r}")
            target_area = tuple(target_area)
        images = doc.get("images")
        if not isinstance(images, list):
            raise CaptureError(f"{where}: 'images' must be a list of entries")
        entries: list[Entry] = []
        files: set[str] = set()
        names: set[str] = set()
        for i, raw in enumerate(images):
            here = f"{where}, image entry {i}"
            if not isinstance(raw, dict) or "file" not in raw or "kind" not in raw:
                raise CaptureError(f"{here}: each entry needs at least 'file' and 'kind'")
            kind, rel = raw["kind"], raw["file"]
            if kind not in KINDS:
                raise CaptureError(f"{here} ({rel}): unknown kind {kind!r}; known kinds: {', '.join(KINDS)}")
            inside(root, rel, what=f"{here}: file", error=CaptureError)
            params = raw.get("params", {})
            if not isinstance(params, dict):
                raise CaptureError(f"{here} ({rel}): 'params' must be an object")
            _check_params(kind, params, f"{here} ({rel})")
            name = raw.get("name") or Path(rel).stem
            if not isinstance(name, str):
                raise CaptureError(f"{here} ({rel}): 'name' must be a string, not {name!r}")
            if rel in files:
                raise CaptureError(f"{here}: duplicate entry for file {rel}")
            if name in names:
                raise CaptureError(f"{here} ({rel}): duplicate entry name {name!r}")
            suffixes = DEPTH_SUFFIXES if kind == "depth" else IMAGE_SUFFIXES
            if Path(rel).suffix.lower() not in suffixes:
                raise CaptureError(f"{here}: {rel} has an unsupported type for a {kind} image "
                                   f"(use {', '.join(suffixes)})")
            pattern = raw.get("pattern")
            if pattern is not None:
                inside(root, pattern, what=f"{here}: pattern", error=CaptureError)
            if kind == "depth" and depth_info is None:
                raise CaptureError(f"{here} ({rel}): a depth image needs the 'depth' section (its intrinsics)")
            index = _projector_index(raw.get("projector", 0), kind, count, f"{here} ({rel})")
            files.add(rel)
            names.add(name)
            entries.append(Entry(rel, kind, str(name), dict(params), pattern, index))
        if count > 1:
            _check_sequences(entries, count, where)
        return CaptureSet(root, camera, projector, entries, depth_info, target_area,
                          str(doc.get("camera_status", "nominal")), str(doc.get("projector_status", "nominal")),
                          bool(doc.get("projector_pose_known", False)), colour, dict(doc.get("notes") or {}), version,
                          _lens_removed(doc.get("camera_lens_removed"), where), others)

    def verify(self) -> None:
        """Decode every file once: exists, readable, complete, right size, sane depth.

        A file this process wrote or already decoded and found so, unchanged since
        (:func:`~procam.addon.imageio.file_version`), is not decoded again: one process that runs several steps on
        one set (the demo: calibrate, compensate, diagnose; a pipeline in Python) read each photograph three times
        for the same answer (real sessions: 11 of 70 s), and a set it had just written (import, the lab) once more."""
        cam = self.camera.intrinsics.size
        for e in self.entries:
            frame = self.projectors[e.projector].intrinsics.size
            if e.kind == "depth":
                self._read_depth(e)
                continue
            size = self._verified_size(e.file)
            if e.kind in CAMERA_KINDS and size != cam:
                raise CaptureError(f"{self.path / e.file}: image is {size[0]}×{size[1]} pixels, "
                                   f"but the camera resolution is {cam[0]}×{cam[1]}")
            if e.pattern:
                size = self._verified_size(e.pattern, keep=False)
                if size != frame:
                    whose = f"projector {e.projector + 1}'s" if self.others else "the projector"
                    raise CaptureError(f"{self.path / e.pattern}: projected pattern is {size[0]}×{size[1]}, "
                                       f"but {whose} frame is {frame[0]}×{frame[1]}")

    def _verified_size(self, rel: str, keep: bool = True) -> tuple[int, int]:
        """The size of the image ``rel``, decoded whole unless this process wrote or decoded this version of it
        before (:func:`~procam.addon.imageio.known_size`); ``keep``: see :func:`~procam.addon.imageio.read_image`."""
        path = self._file(rel)
        size = known_size(path)
        if size is None:
            size = _size(self._read(rel, keep))
            remember_size(path, size)
        return size

    def _file(self, rel: str) -> Path:
        # Checked at load too; resolved again at each read, so a link put in after loading is not followed.
        return inside(self.path, rel, what="capture set file", error=CaptureError)

    def _read(self, rel: str, keep: bool = True) -> np.ndarray:
        path = self._file(rel)
        if not path.is_file():
            raise CaptureError(f"capture set {self.path}: file {rel} is missing")
        try:
            return read_image(path, keep=keep)
        except ImageError as exc:
            raise CaptureError(f"capture set {self.path}: {rel} is unreadable or truncated ({exc})") from None

    def _read_depth(self, e: Entry) -> np.ndarray:
        path = self._file(e.file)
        if not path.is_file():
            raise CaptureError(f"capture set {self.path}: depth file {e.file} is missing")
        try:
            raw = read_image(path, channels=None)
        except ImageError as exc:
            # read_image refuses NaN: our writer stores missing depth as 0, so say so.
            raise CaptureError(f"capture set {self.path}: depth file {e.file} is unreadable ({exc}); "
                               "store missing depth as 0, not NaN") from None
        d = validate_depth(raw, f"{self.path / e.file}")
        want = self.depth_info.intrinsics.size if self.depth_info else None
        if want and _size(d) != want:
            raise CaptureError(f"{self.path / e.file}: depth is {_size(d)[0]}×{_size(d)[1]} pixels, but the depth "
                               f"intrinsics say {want[0]}×{want[1]}")
        return d

    # -- access ----------------------------------------------------------------------------------

    def entries_of(self, kind: str) -> list[Entry]:
        if kind not in KINDS:
            raise CaptureError(f"unknown kind {kind!r}; known kinds: {', '.join(KINDS)}")
        return [e for e in self.entries if e.kind == kind]

    def entry(self, kind: str, **filters: Any) -> Entry:
        """The one entry of ``kind`` whose params (or ``name``) equal ``filters``."""
        found = [e for e in self.entries_of(kind) if e.matches(filters)]
        what = f"{kind}" + (f" with {', '.join(f'{k}={v!r}' for k, v in filters.items())}" if filters else "")
        if not found:
            raise CaptureError(f"capture set {self.path} has no {what} image")
        if len(found) > 1 and len({e.projector for e in found}) > 1:
            raise CaptureError(f"capture set {self.path} holds the captures of {len(self.projectors)} projectors "
                               f"({len(found)} {what} images); this step reads one projector's captures at a time: "
                               "give it a capture set of one projector")
        if len(found) > 1:
            raise CaptureError(f"capture set {self.path} has {len(found)} {what} images "
                               f"({', '.join(e.name for e in found)}); say which one, e.g. name=…")
        return found[0]

    def image(self, kind: str, **filters: Any) -> np.ndarray:
        """The capture (float32 H×W×3, linear) of the one entry matching ``kind`` and ``filters``; a set read
        without verifying its images still gets each one checked against the camera's size here."""
        e = self.entry(kind, **filters)
        img = self._read(e.file)
        cam = self.camera.intrinsics.size
        if e.kind in CAMERA_KINDS and _size(img) != cam:
            raise CaptureError(f"{self.path / e.file}: image is {_size(img)[0]}×{_size(img)[1]} pixels, but the "
                               f"camera resolution is {cam[0]}×{cam[1]}; capture it again at the camera's size")
        return img

    def pattern(self, kind: str, **filters: Any) -> np.ndarray:
        """The native projector frame that was shown for that entry."""
        e = self.entry(kind, **filters)
        if not e.pattern:
            raise CaptureError(f"capture set {self.path}: {e.file} records no projected pattern")
        return self._read(e.pattern)

    def depth(self, **filters: Any) -> np.ndarray:
        """Depth in metres (float32 H×W at the depth intrinsics' size), NaN where missing.

        Without filters: the one depth image of the scene (not a wall image, :meth:`depth_walls`).
        """
        if filters:
            return self._read_depth(self.entry("depth", **filters))
        scene = [e for e in self.entries_of("depth") if WALL_PARAM not in e.params]
        if len(scene) != 1:
            raise CaptureError(f"capture set {self.path} needs exactly one depth image of the scene, has "
                               f"{len(scene)} ({', '.join(e.file for e in scene) or 'none'}); capture the surface "
                               "with the depth camera from the RGB camera's position")
        return self._read_depth(scene[0])

    def depth_walls(self) -> list[tuple[Entry, float]]:
        """The depth sensor's images of a flat wall facing it, with the wall's tape-measured distance (metres)."""
        return [(e, e.params[WALL_PARAM]) for e in self.entries_of("depth") if WALL_PARAM in e.params]

    def file(self, entry: Entry) -> Path:
        """The image file of ``entry``, inside the set."""
        return self._file(entry.file)

    def pattern_file(self, entry: Entry) -> Path:
        """The projected pattern file of ``entry``, inside the set."""
        if not entry.pattern:
            raise CaptureError(f"capture set {self.path}: {entry.file} records no projected pattern")
        return self._file(entry.pattern)

    def for_projector(self, index: int) -> CaptureSet:
        """The one-projector set of projector ``index`` (0 = the first): the camera, that projector, its captures
        and the shared ones (surface photo, depth, targets), as single-projector code reads any set.

        Same folder, nothing copied; the entries keep their files and names and are numbered 0 in the view.
        """
        count = len(self.projectors)
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index < count:
            raise CaptureError(f"capture set {self.path} has {count} projector(s), numbered 0 to {count - 1}; "
                               f"there is no projector {index!r}")
        index = int(index)
        if count == 1:
            return self
        if not any(e.projector == index and e.kind not in SHARED_KINDS for e in self.entries):
            raise CaptureError(f"capture set {self.path} holds no captures of projector {index + 1}; capture its "
                               "sequence (while the other projectors show black) and make the set again")
        return CaptureSet(self.path, self.camera, self.projectors[index],
                          [replace(e, projector=0) for e in self.entries if e.projector == index or
                           e.kind in SHARED_KINDS], self.depth_info, self.target_area, self.camera_status,
                          self.projector_status, self.projector_pose_known, self.colour_space, dict(self.notes),
                          self.version, self.camera_lens)

    def __iter__(self) -> Iterator[Entry]:
        return iter(self.entries)

    def __len__(self) -> int:
        return len(self.entries)

    def to_dict(self) -> dict[str, Any]:
        return {"format": FORMAT, "version": VERSION, "colour_space": "linear",
                "camera": self.camera.to_dict(), "camera_status": self.camera_status,
                "projector": self.projector.to_dict(), "projector_status": self.projector_status,
                "projector_pose_known": self.projector_pose_known,
                **({"projectors": [p.to_dict() for p in self.projectors]} if self.others else {}),
                "depth": self.depth_info.to_dict() if self.depth_info else None,
                "target_area": list(self.target_area) if self.target_area else None,
                "notes": jsonable(self.notes),
                **({"camera_lens_removed": jsonable(self.camera_lens)} if self.camera_lens else {}),
                "images": [e.to_dict() for e in self.entries]}

    @staticmethod
    def writer(path: str | Path, camera: Camera, projector: Projector, **kwargs: Any) -> CaptureSetWriter:
        """Start a new capture set at ``path``; see :class:`CaptureSetWriter`."""
        return CaptureSetWriter(path, camera, projector, **kwargs)


# -- writing -------------------------------------------------------------------------------------

def is_capture_set(path: str | Path) -> bool:
    """Whether ``path`` holds a capture set's manifest with its format tag (one ProCam wrote)."""
    return holds_manifest(path, MANIFEST, FORMAT)


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", text).strip("-") or "image"


def default_name(kind: str, params: dict[str, Any]) -> str:
    """A readable unique-ish entry name from kind and parameters (``graycode_x03_inv``)."""
    if kind == "checker":
        return f"checker_s{params['square']}_p{params['phase']}"
    if kind == "graycode":
        return f"graycode_{params['axis']}{params['bit']:02d}" + ("_inv" if params["inverted"] else "")
    return kind


class CaptureSetWriter:
    """Creates a NEW capture set atomically; use as a context manager or call :meth:`commit`.

    Images are checked as they are added (size, finite values), so a bad
    capture fails before anything is moved into place. On an exception inside
    the ``with`` block nothing is written. Missing depth may be NaN or 0; it is
    stored as 0 (``read_image`` refuses NaN) and loaded back as NaN.
    ``inputs``: what the run reads, never replaced (:func:`..outputs.check_replaceable`).
    ``others``: projectors 2…N of a multi-projector set; :meth:`add`'s ``projector_index`` says which projector
    showed a capture. ``check``: a check of the finished set (loaded from the hidden folder it was written in)
    before it is moved into place; what it raises leaves nothing behind.
    """

    def __init__(self, path: str | Path, camera: Camera, projector: Projector, *, others: Iterable[Projector] = (),
                 depth_info: DepthInfo | None = None, target_area: tuple[int, int, int, int] | None = None,
                 camera_status: str = "nominal", projector_status: str = "nominal",
                 projector_pose_known: bool = False, notes: dict[str, Any] | None = None,
                 camera_lens: dict[str, Any] | None = None, force: bool = False,
                 inputs: Iterable[str | Path | None] = (), check: Callable[[CaptureSet], Any] | None = None) -> None:
        self.others = tuple(others)
        self._check = check
        self._folder = AtomicFolder(path, force=force, what="capture set", replaceable=is_capture_set, inputs=inputs,
                                    error=CaptureError)
        self.path = Path(path)
        self.camera, self.projector = camera, projector
        self.depth_info = depth_info
        self.target_area = tuple(int(v) for v in target_area) if target_area is not None else None
        self.camera_status, self.projector_status = camera_status, projector_status
        self.projector_pose_known = projector_pose_known
        self.notes = dict(notes or {})
        self.camera_lens = camera_lens
        self.entries: list[Entry] = []
        self._names: set[str] = set()
        self._patterns: dict[str, str] = {}  # content hash → file, so a frame shown twice is stored once
        (self._folder.tmp / "images").mkdir()

    @property
    def _tmp(self) -> Path:
        return self._folder.tmp

    def _unique(self, name: str) -> str:
        base, n = _slug(name), 1
        out = base
        while out in self._names:
            n += 1
            out = f"{base}_{n}"
        return out

    @property
    def projectors(self) -> tuple[Projector, ...]:
        """Every projector of the set being written, the first first."""
        return (self.projector, *self.others)

    def add(self, kind: str, image: np.ndarray, *, name: str | None = None, frame: np.ndarray | None = None,
            projector_index: int = 0, **params: Any) -> Entry:
        """Add one capture. ``frame`` is the native projector frame that was shown (stored under patterns/);
        ``projector_index`` the projector that showed it while the others showed black (0 = the first; not a
        parameter named ``projector``, which the surface photo's ``projector="off"`` already is)."""
        if kind not in KINDS or kind == "depth":
            if kind == "depth":
                raise CaptureError("use add_depth() for depth images")
            raise CaptureError(f"unknown kind {kind!r}; known kinds: {', '.join(KINDS)}")
        index = _projector_index(projector_index, kind, len(self.projectors), f"new {kind} image")
        params = jsonable(params)
        _check_params(kind, params, f"new {kind} image")
        img = np.asarray(image, dtype=np.float32)
        label = name or default_name(kind, params)
        if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3)):
            raise CaptureError(f"{label}: expected an H×W×3 image, got shape {img.shape}")
        cam = self.camera.intrinsics.size
        if kind in CAMERA_KINDS and _size(img) != cam:
            raise CaptureError(f"{label}: image is {_size(img)[0]}×{_size(img)[1]} pixels, "
                               f"but the camera resolution is {cam[0]}×{cam[1]}")
        if not np.all(np.isfinite(img)):
            raise CaptureError(f"{label}: image holds NaN or infinite values")
        if img.min(initial=0.0) < 0.0 or img.max(initial=0.0) > 1.0:
            # 16-bit PNG clips; say so instead of silently losing highlights.
            raise CaptureError(f"{label}: values outside [0, 1] (min {img.min():.3g}, max {img.max():.3g}); "
                               "scale the capture (e.g. exposure) before storing it")
        name, projector = self._unique(label), index
        index = len(self.entries)
        rel = f"images/{index:04d}_{name}.png"
        write_image(self._tmp / rel, img)
        pattern_rel = self._store_pattern(frame, index, name, projector) if frame is not None else None
        entry = Entry(rel, kind, name, dict(params), pattern_rel, projector)
        self.entries.append(entry)
        self._names.add(name)
        return entry

    def _store_pattern(self, pattern: np.ndarray, index: int, name: str, projector: int) -> str:
        pat = np.asarray(pattern, dtype=np.float32)
        frame = self.projectors[projector].intrinsics.size
        if _size(pat) != frame:
            whose = f"projector {projector + 1}'s" if self.others else "the projector"
            raise CaptureError(f"{name}: projected pattern is {_size(pat)[0]}×{_size(pat)[1]}, "
                               f"but {whose} frame is {frame[0]}×{frame[1]}; pass the native frame "
                               "(Projector.frame_from_input)")
        if not np.all(np.isfinite(pat)) or pat.min(initial=0.0) < 0 or pat.max(initial=0.0) > 1:
            raise CaptureError(f"{name}: projected pattern must hold values in [0, 1]")
        # Hash the 16-bit quantised frame: that is exactly what the file will hold.
        q = np.round(pat * 65535.0).astype(np.uint16)
        key = hashlib.sha1(q.tobytes() + str(q.shape).encode()).hexdigest()
        if key not in self._patterns:
            (self._tmp / "patterns").mkdir(exist_ok=True)
            rel = f"patterns/{index:04d}_{name}.png"
            write_image(self._tmp / rel, pat)
            self._patterns[key] = rel
        return self._patterns[key]

    def add_depth(self, depth: np.ndarray, *, name: str = "depth", suffix: str = ".npy", **params: Any) -> Entry:
        """Add a depth map in metres (H×W at the depth intrinsics' size; 0 or NaN = missing)."""
        if self.depth_info is None:
            raise CaptureError("a depth image needs depth intrinsics: pass depth_info= to the writer")
        if suffix not in DEPTH_SUFFIXES:
            raise CaptureError(f"depth is stored as {' or '.join(DEPTH_SUFFIXES)}, not {suffix!r}")
        d = validate_depth(depth, f"depth {name!r}")
        want = self.depth_info.intrinsics.size
        if _size(d) != want:
            raise CaptureError(f"depth {name!r} is {_size(d)[0]}×{_size(d)[1]} pixels, but the depth intrinsics "
                               f"say {want[0]}×{want[1]}")
        name = self._unique(name)
        (self._tmp / "depth").mkdir(exist_ok=True)
        rel = f"depth/{name}{suffix}"
        write_image(self._tmp / rel, np.nan_to_num(d, nan=0.0))
        entry = Entry(rel, "depth", name, dict(jsonable(params)))
        self.entries.append(entry)
        self._names.add(name)
        return entry

    def copy(self, source: CaptureSet, entry: Entry, *, name: str | None = None, projector_index: int | None = None,
             image: Callable[[Entry, np.ndarray], np.ndarray] | None = None) -> Entry:
        """Add ``entry`` of the set ``source``: its image (through ``image(entry, pixels)`` when given; a depth
        map's too), projected pattern and parameters, under ``name`` (default its own) and as projector
        ``projector_index``'s (default its own)."""
        if entry.kind == "depth":
            depth = source._read_depth(entry)
            return self.add_depth(depth if image is None else image(entry, depth), name=name or entry.name,
                                  suffix=Path(entry.file).suffix, **entry.params)
        pixels = source._read(entry.file)
        pattern = source._read(entry.pattern) if entry.pattern else None
        return self.add(entry.kind, pixels if image is None else image(entry, pixels), name=name or entry.name,
                        frame=pattern, projector_index=entry.projector if projector_index is None else projector_index,
                        **entry.params)

    def to_dict(self) -> dict[str, Any]:
        return CaptureSet(self.path, self.camera, self.projector, self.entries, self.depth_info, self.target_area,
                          self.camera_status, self.projector_status, self.projector_pose_known, "linear",
                          self.notes, camera_lens=self.camera_lens, others=self.others).to_dict()

    def commit(self) -> CaptureSet:
        """Write capture.json, check the new set loads cleanly, then move it into place."""
        try:
            doc = self.to_dict()
            write_atomic_bytes(self._tmp / MANIFEST, (json.dumps(doc, indent=1, allow_nan=False) + "\n").encode())
            # Reading back everything we wrote is the cheapest proof the set is complete.
            written = CaptureSet.load(self._tmp)
            if self._check is not None:
                self._check(written)
        except BaseException:
            self._folder.abort()
            raise
        self._folder.commit()
        return CaptureSet.load(self.path, verify_images=False)

    def abort(self) -> None:
        self._folder.abort()

    def __enter__(self) -> CaptureSetWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is not None:
            self.abort()
        elif not self._folder.done:
            self.commit()


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """The sRGB transfer inverted (IEC 61966-2-1), for 8-bit captures that cameras store sRGB-encoded."""
    return srgb_decode(np.asarray(values, dtype=np.float32)).astype(np.float32)


def linear_to_srgb(values: np.ndarray) -> np.ndarray:
    """Linear light → the sRGB transfer (clipped to [0, 1]), float32."""
    return srgb_encode(np.asarray(values, dtype=np.float32)).astype(np.float32)


__all__ = ["AtomicFolder", "CaptureSet", "CaptureSetWriter", "DepthInfo", "Entry", "KINDS", "FORMAT", "VERSION",
           "is_capture_set", "srgb_to_linear", "linear_to_srgb", "validate_depth", "default_name"]
