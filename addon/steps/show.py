"""The show step: compensate every frame of a folder or numbered image sequence into a growing, resumable folder.

A show is a folder that grows one finished frame at a time::

    frame_0001.png …   the projector input of each target frame in the native projector frame
                       (full resolution, 16-bit PNG), numbered like the input frames
    show.json          the manifest, rewritten atomically after every frame
    open_loop_bias.npz θ estimated once from the validation captures (open loop only), reused on resume

Why a growing folder and not one atomic folder like ``procam compensate``: a
clip has hundreds of frames and hours of work, and a crash at frame 412 must
not lose frames 1–411. Each frame file is written under a temporary name and
renamed into place, and only then entered in the manifest, so:

* a frame counts as finished only when the manifest says so *and* the file on
  disk has the recorded size and SHA-256 — a frame file without an entry (a
  crash between the rename and the manifest update) or a damaged one is redone;
* a rerun with the same settings skips the finished frames and does the rest;
* a rerun with other settings (calibration content, device, schedule, area, …),
  or after a target image changed, is refused unless ``force``, which redoes
  every frame: a finished frame is never overwritten silently;
* a target that cannot be read or compensated is recorded as a failure in the
  manifest and the next frames go on (unless ``fail_fast``); a rerun retries it.

One :class:`.stage_c.StageC` (scene loaded, kernels compiled) serves every
frame, as it serves the compensate step's targets. Two runs on one folder at once are refused (every writer's lock,
:func:`..outputs.writer_lock`, which the OS lets go of when a process dies).

The targets are image files or the frames of one video file (numbered 1…N;
its size and SHA-256 are recorded, so a changed video is noticed like a
changed image). **Warm start** (default): stage C for a frame starts from the
previous frame's correction (its answer minus its usual start, added to this
frame's usual start), read back from that frame's 16-bit PNG (the bytes the
folder keeps, so a resumed show computes exactly what a fresh one does;
:mod:`.show_work`). The sequence is cut into **chunks** of ``chunk`` frames by
frame number (1–24, 25–48, … by default); the first frame of a chunk starts
cold, so the chunks are independent and can run side by side on a cluster
(:mod:`.show_cluster`, ``workers``/``cluster``), and a single process cuts
them the same way: the frames are byte-identical either way. The process
running the show is the only writer of the folder.

**Several projectors** (a calibration with ``projector_count`` N > 1): stage C
solves every projector's input at once (:class:`.projectors.JointStage`, the
joint solve of ``stages/joint.py``) and the folder holds one sequence per
projector, each numbered as one projector's show is, so that each folder is
what a media server plays on that projector's output::

    projector_1/frame_0001.png …   projector 1's frames (K counted from 1)
    projector_2/frame_0001.png …
    show.json                      each frame's entry lists every projector's file, size and SHA-256 under
                                   ``projectors`` (projector 1's also under the one-projector keys)
    open_loop_bias_p1.npz …        each projector's θ model, estimated once (open loop), reused on resume

A frame counts as finished only when every projector's file is there and
matches its entry; the files are written one by one under temporary names,
and the entry only after the last, so a crash in between redoes the frame.
Each projector's warm start reads back its own previous 16-bit frame and
undoes its own warp. A show folder resumed with a calibration of another
number of projectors, other projector sizes or other contents is refused,
naming what changed (``--force`` redoes it). On a cluster
(``--workers``/``--cluster``) each task solves one frame of every projector
and returns every projector's PNG bytes, written here as above. Not yet for
several projectors: what ``JointStage`` refuses (render schedules; of the
diagnosed effect models, the camera's and the surface's). Each projector's
effect models are in the settings.
"""

from __future__ import annotations

import hashlib
import io
import json
from importlib import metadata
import os
import re
import socket
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..capture.devices import Device
from ..errors import Cancelled, ProCamError
from ..imageio import DAMAGED_ARRAYS, READ_IMAGE_SUFFIXES, write_atomic_bytes
from ..options import option, validate
from ..outputs import (check_apart_from_inputs, file_sha256, hold_writer, jsonable, natural_key, release_writer,
                       write_manifest, writer_lock)
from ..progress import Cancel, Progress, check, quiet
from ..safepaths import inside
from ..stages.compensate import BiasModel, Compensator
from ..stages.display_area import DisplayArea
from ..stages.range import RangeMap, parse_range, range_line
from ..video import VideoReader, frame_count, is_video, load_video_frame
from . import calibrate as calibrate_step
from . import layout
from .show_cluster import CONNECT_TIMEOUT, Cluster, WorkerContext
from .projectors import JointStage
from .show_work import FrameJob, FrameOutcome, compute_frame, source_record
from .stage_c import StageC, StageCOptions, check_device_fits, measure_radiometry, stage_c_inputs
from .summary import Summary, cached, fmt

KIND = layout.SHOW
FORMAT, VERSION, MANIFEST = KIND.format, KIND.version, KIND.manifest
BIAS_FILE = layout.OPEN_LOOP_BIAS
FRAME_PREFIX = layout.FRAME_PREFIX
#: ``--range auto`` fits the show's gain and offset to at most this many frames, evenly spread.
RANGE_SAMPLE = 32
#: Frames per warm-start chunk (by frame number: 1–24, 25–48, …): one second at 24 fps.
CHUNK = 24

class SequenceError(ProCamError):
    """A target sequence or show folder that cannot be used as asked."""


# -- the input sequence ----------------------------------------------------------------------------

@dataclass(frozen=True)
class SourceFrame:
    """One target of the sequence and the frame number its output carries: an image file, or frame ``index``
    (0-based) of the video file ``path``."""

    number: int
    path: Path
    index: int | None = None


_HASHES = re.compile(r"#+")
_PRINTF = re.compile(r"%(0?)(\d*)d")
_TRAILING_DIGITS = re.compile(r"(\d+)$")


def _pattern_regex(name: str) -> re.Pattern[str] | None:
    """A regex for a file-name pattern with one run of ``#`` (Blender) or one ``%0Nd`` (printf); else None."""
    hashes, printf = list(_HASHES.finditer(name)), list(_PRINTF.finditer(name))
    if not hashes and not printf:
        return None
    if len(hashes) + len(printf) > 1:
        raise SequenceError(f"the sequence pattern {name!r} has more than one frame-number field; "
                            "use one run of # (shot_####.png) or one %04d")
    m = (hashes or printf)[0]
    width = len(m.group(0)) if hashes else int(m.group(2) or 1)
    # #### pads to 4 digits; frame 12345 simply has 5.
    digits = rf"(\d{{{width},}})" if hashes or m.group(1) else r"(\d+)"
    return re.compile(re.escape(name[:m.start()]) + digits + re.escape(name[m.end():]) + r"\Z")


def _numbered(paths: list[Path]) -> list[SourceFrame]:
    """Frames numbered by the trailing digits of their names when all have distinct ones, else 1, 2, …"""
    paths = sorted(paths, key=natural_key)
    numbers = [_TRAILING_DIGITS.search(p.stem) for p in paths]
    if all(numbers) and len({int(m.group(1)) for m in numbers}) == len(paths):
        frames = [SourceFrame(int(m.group(1)), p) for m, p in zip(numbers, paths)]
        return sorted(frames, key=lambda f: f.number)
    return [SourceFrame(i + 1, p) for i, p in enumerate(paths)]


def list_frames(inputs: Sequence[str | Path]) -> list[SourceFrame]:
    """The target frames named by ``inputs``, in frame order.

    ``inputs`` is one folder (every image in it: numbered by the digits that end
    their names when those are distinct, else 1, 2, … in natural order), one
    numbered pattern (``frames/shot_####.png`` or ``frames/shot_%04d.png``:
    numbered by the file names), a list of image files (numbered like a folder),
    or one video file (its frames numbered 1…N).
    """
    items = [Path(p) for p in inputs]
    if not items:
        raise SequenceError("no target frames given; name a folder, a pattern like frames/shot_####.png, files, "
                            "or a video")
    videos = [p for p in items if is_video(p)]
    if videos:
        if len(items) > 1:
            raise SequenceError("give one video file alone (not with other videos or images); join videos first")
        if not videos[0].is_file():
            raise SequenceError(f"video {videos[0]} not found")
        try:
            n = frame_count(videos[0])
        except ProCamError as exc:
            raise SequenceError(str(exc)) from None
        return [SourceFrame(i + 1, videos[0], i) for i in range(n)]
    if len(items) == 1 and items[0].is_dir():
        folder = items[0]
        paths = [p for p in folder.iterdir()
                 if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in READ_IMAGE_SUFFIXES]
        if not paths:
            raise SequenceError(f"the folder {folder} holds no images ({', '.join(READ_IMAGE_SUFFIXES)})")
        return _numbered(paths)
    if len(items) == 1 and not items[0].exists():
        regex = _pattern_regex(items[0].name)
        folder = items[0].parent
        if regex is None:
            raise SequenceError(f"target {items[0]} not found (give a folder, an image, or a numbered pattern "
                                "like shot_####.png)")
        if not folder.is_dir():
            raise SequenceError(f"the folder of the sequence pattern {items[0]} does not exist: {folder}")
        found: dict[int, Path] = {}
        for p in sorted(folder.iterdir(), key=natural_key):
            m = regex.match(p.name)
            if m and p.is_file():
                n = int(m.group(1))
                if n in found:
                    raise SequenceError(f"{found[n].name} and {p.name} both match {items[0].name} as frame {n}; "
                                        "keep one of them")
                found[n] = p
        if not found:
            raise SequenceError(f"no file in {folder} matches the sequence pattern {items[0].name}")
        return [SourceFrame(n, found[n]) for n in sorted(found)]
    for p in items:
        if p.is_dir():
            raise SequenceError(f"{p} is a folder; give either one folder or a list of image files, not both")
        if not p.is_file():
            raise SequenceError(f"target {p} not found")
    if len({p.resolve() for p in items}) != len(items):
        raise SequenceError("the same target file is named twice")
    return _numbered(items)


def frame_digits(frames: Sequence[SourceFrame]) -> int:
    """Zero padding for the output names: 4, or more when the frame numbers need it."""
    return max(4, *(len(str(f.number)) for f in frames)) if frames else 4


def frame_files(number: int, digits: int, count: int = 1) -> list[str]:
    """The file(s) of frame ``number``: ``frame_0001.png`` for one projector, else one per projector
    (``projector_1/frame_0001.png``, …)."""
    if count == 1:
        return [layout.frame_name(number, digits)]
    return [layout.projector_frame_name(number, digits, k) for k in range(count)]


def bias_files(count: int) -> list[str]:
    """The open-loop θ file(s) of a show of ``count`` projectors."""
    return [BIAS_FILE] if count == 1 else [f"open_loop_bias_p{k + 1}.npz" for k in range(count)]


#: the files a show of several projectors keeps in its folders (what --force may remove)
_FRAME_FILE = re.compile(rf"(projector_\d+/)?{FRAME_PREFIX}\d+\.png")
_PROJECTOR_DIR = re.compile(r"projector_\d+")


# -- settings and manifest -----------------------------------------------------------------------

def _seconds(value: float) -> None:
    if not value > 0:
        raise SequenceError(f"--connect-timeout must be a number of seconds > 0, got {value!r}")


@dataclass(frozen=True)
class ShowOptions:
    """What ``procam show`` and the Prepare Show button ask for.

    ``targets``: one folder, one numbered pattern, or image files (:func:`list_frames`).
    """

    calibration: Path
    targets: tuple[str | Path, ...]
    out: Path
    stage_c: StageCOptions = field(default_factory=StageCOptions)
    force: bool = False
    fail_fast: bool = option(False, help="stop at the first frame that fails instead of going on with the next ones")
    warm_start: bool = option(
        True, negate="--cold-start",
        help="start each frame's stage C from the previous frame's answer (within its chunk); off: every frame "
             "starts from its target alone")
    chunk: int = option(
        CHUNK, min=1, metavar="N",
        help=f"frames per warm-start chunk, by frame number (default {CHUNK}); the first frame of each chunk starts "
             "cold, and chunks run side by side with --workers/--cluster")
    #: Renders with several samples per pixel add them in an order that depends on the thread count, so runs
    #: are byte-identical between one process and a cluster when both use the same count.
    threads: int | None = option(
        None, min=1, metavar="N",
        help="Dr.Jit threads of this process, or of each worker (default: all cores; cores over workers on a local "
             "cluster); frames are byte-identical across runs with the same count")
    workers: int | None = option(
        None, min=1, metavar="N",
        help="compute the frames on a local cluster of N worker processes (Dask distributed)")
    cluster: str | None = option(
        None, metavar="ADDRESS",
        help="compute the frames on the Dask cluster whose scheduler is at ADDRESS (tcp://host:8786)")
    connect_timeout: float = option(
        CONNECT_TIMEOUT, metavar="SECONDS", check=_seconds,
        help=f"with --cluster: seconds to wait for its scheduler to answer (default {CONNECT_TIMEOUT:g})")

    def check(self, mode: str) -> None:
        """Refuse a warm-start or cluster request that cannot run, before anything is loaded."""
        validate(self, SequenceError)
        if self.workers is not None and self.cluster:
            raise SequenceError("give either --workers (a local cluster) or --cluster ADDRESS, not both")
        if (self.workers is not None or self.cluster) and mode == "closed-loop":
            raise SequenceError("the closed loop runs through one physical device (one projector and camera), "
                                "whose frames cannot be shared out: drop --workers/--cluster, or drop --device "
                                "for the open loop")

    def warm(self) -> dict[str, Any] | None:
        """The warm start as the settings record it (it decides the pixels): None for cold starts."""
        return ({"from": "previous frame's correction (its 16-bit PNG minus its own start)", "chunk": self.chunk}
                if self.warm_start else None)


def chunk_of(number: int, chunk: int) -> int:
    """The chunk of a frame number: frames 1…chunk are chunk 0, and so on."""
    return (number - 1) // chunk


def warm_from(frames: Sequence[SourceFrame], options: ShowOptions) -> dict[int, int]:
    """For each frame that is warm-started, the number of the frame it starts from: the one before it in the
    sequence, when both lie in the same chunk."""
    if not options.warm_start:
        return {}
    return {f.number: p.number for p, f in zip(frames, frames[1:])
            if chunk_of(p.number, options.chunk) == chunk_of(f.number, options.chunk)}


def settings_of(options: StageCOptions, *, calibration: dict[str, str], mode: str, digits: int,
                effects: dict[str, Any] | None, range_map: RangeMap | None = None,
                warm: dict[str, Any] | None = None, radiometry: dict[str, Any] | None = None) -> dict[str, Any]:
    """What decides the frames' pixels: two runs with equal settings write the same frames."""
    schedule = asdict(options.resolved())
    if mode != "closed-loop":  # θ's update rule and the capture interval only act in the closed loop
        schedule.update(alpha=None, capture_every=None, reference_spp=None)
    return {"calibration_sha256": calibration["sha256"], "surface_sha256": calibration["surface_sha256"],
            "device": options.device_spec, "mode": mode, "schedule": schedule, "spp": options.spp,
            "bounces": options.bounces, "seed": options.seed, "area": list(options.area) if options.area else "auto",
            "target_encoding": options.target_encoding, "digits": digits, "effects": effects,
            "range": None if range_map is None else range_map.to_dict(), "warm_start": warm,
            # a surround other than black (the default, which earlier shows held too) changes the frames
            **({"surround": list(options.surround)} if options.surround and any(options.surround) else {}),
            # and so does each camera pixel's own radiometry (``radiometry``, the stage's choice; shows made before
            # it was recorded worked through the global models, which leave no key, so they still resume)
            **({"radiometry": "pixel"} if (radiometry or {}).get("used") == "pixel" else {})}


def _differences(old: dict[str, Any], new: dict[str, Any], prefix: str = "") -> list[str]:
    """``key: old → new`` for each setting that differs (nested settings as ``schedule.lr``)."""
    out = []
    for k in sorted(set(old) | set(new)):
        a, b = old.get(k), new.get(k)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differences(a, b, f"{prefix}{k}.")
        elif a != b:
            out.append(f"{prefix}{k}: {a!r} → {b!r}")
    return out


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


class ShowFolder:
    """The output folder and its manifest: locking, verification of finished frames, atomic updates."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.doc: dict[str, Any] | None = None
        self._lock: Path | None = None

    # locking: every writer's lock (outputs.writer_lock), which a dead process lets go of
    def lock(self) -> None:
        self._lock = hold_writer(self.path)

    @property
    def locked(self) -> bool:
        """Whether this object holds the folder's lock."""
        return self._lock is not None

    def unlock(self) -> None:
        if self._lock is not None:
            release_writer(self._lock)
            self._lock = None

    def open(self, *, force: bool = False) -> dict[str, Any] | None:
        """Create or check the folder, and lock it; return the existing manifest (None for a new show).

        With ``force`` a damaged manifest, or one of another format version, starts a new show.
        """
        p = self.path
        if p.exists() and not p.is_dir():
            raise SequenceError(f"{p} exists and is not a folder; choose another --out")
        manifest = p / MANIFEST
        try:
            if p.is_dir() and not manifest.is_file() and any(not q.name.startswith(".") for q in p.iterdir()):
                raise SequenceError(f"{p} is not empty and holds no {MANIFEST}: it is not a show folder; "
                                    "refusing to write frames into it — choose another --out")
            p.mkdir(parents=True, exist_ok=True)
            self.lock()
        except OSError as exc:  # a folder we may not look into or write (permissions)
            raise SequenceError(f"cannot write the show folder {p}: {exc.strerror or exc}; choose another --out "
                                "or change its permissions") from None
        try:
            return self._read(manifest, force)
        except BaseException:
            self.unlock()  # flock conflicts even within one process: never keep it after a refusal
            raise

    def _read(self, manifest: Path, force: bool) -> dict[str, Any] | None:
        # Temporary files of a run that died mid-write (frames and manifest are written as .NAME.*.suffix).
        for q in self.path.iterdir():
            if q.name.startswith((f".{FRAME_PREFIX}", ".show.", ".open_loop_bias.", ".open_loop_bias_p")) \
                    and q.is_file():
                q.unlink(missing_ok=True)
            elif _PROJECTOR_DIR.fullmatch(q.name) and q.is_dir():
                for t in q.iterdir():
                    if t.name.startswith(f".{FRAME_PREFIX}") and t.is_file():
                        t.unlink(missing_ok=True)
        if not manifest.is_file():
            return None
        try:
            doc = json.loads(manifest.read_text())
        except (OSError, ValueError) as exc:
            if force:
                return None
            raise SequenceError(f"the manifest {manifest} is damaged ({exc}); rerun with --force to redo the "
                                "whole show") from None
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise SequenceError(f"{manifest} is not a ProCam show manifest; choose another --out")
        if doc.get("version") != VERSION:
            if force:
                return None
            raise SequenceError(f"{manifest} was written by another version of ProCam (format version "
                                f"{doc.get('version')}); rerun with --force to redo the show, or choose another --out")
        return doc

    def write(self) -> None:
        assert self.doc is not None
        write_manifest(self.path / MANIFEST, self.doc)

    def verified(self, entry: dict[str, Any] | None, name: str | None = None) -> str | None:
        """None when ``entry`` is a finished frame whose file is intact, else why it must be redone. ``name``: the
        file the frame must be in (an entry naming another file, inside the folder or not, is not finished)."""
        if not entry or entry.get("status") != "done":
            return "not finished" if not entry else f"{entry.get('status')} before"
        # An entry naming a file elsewhere (edited, or copied from another show) is redone into its own name
        # rather than refused: the file it names is never read, and the rerun gives the complete show asked for.
        if name is not None and entry.get("file") != name:
            return f"its manifest entry names {entry.get('file')!r}, not {name}"
        return self._intact(entry)

    def verified_all(self, entry: dict[str, Any] | None, names: list[str]) -> str | None:
        """:meth:`verified` for a frame of ``len(names)`` projectors: every projector's file must be the one
        named, there and intact (one missing or damaged file redoes the frame)."""
        if len(names) == 1:
            return self.verified(entry, names[0])
        if not entry or entry.get("status") != "done":
            return "not finished" if not entry else f"{entry.get('status')} before"
        files = entry.get("projectors")
        if not isinstance(files, list) or len(files) != len(names):
            return f"its manifest entry does not list the files of {len(names)} projectors"
        for k, (f, name) in enumerate(zip(files, names)):
            if not isinstance(f, dict) or f.get("file") != name:
                return f"its manifest entry names {f.get('file') if isinstance(f, dict) else f!r} for projector " \
                       f"{k + 1}, not {name}"
            why = self._intact(f)
            if why is not None:
                return f"projector {k + 1}: {why}"
        return None

    def _intact(self, entry: dict[str, Any]) -> str | None:
        """None when the file an entry names is in this folder with its recorded size and SHA-256."""
        try:
            path = inside(self.path, entry.get("file"), what="a finished frame", error=SequenceError)
        except SequenceError:
            return f"its manifest entry names {entry.get('file')!r}, outside the show folder"
        if not path.is_file():
            return f"{path.name} is missing"
        if path.stat().st_size != entry.get("bytes"):
            return f"{path.name} has {path.stat().st_size} bytes, the manifest says {entry.get('bytes')}"
        if file_sha256(path) != entry.get("sha256"):
            return f"{path.name} does not match its checksum (damaged or replaced)"
        return None


def _source_changed(entry: dict[str, Any], frame: SourceFrame) -> bool:
    """Whether the target of a finished frame changed since (size/time first, the hash only when those differ)."""
    try:
        st = frame.path.stat()
    except OSError:
        return False  # a vanished target is reported when it is read, not here
    if entry.get("source") == str(frame.path.absolute()) and entry.get("source_bytes") == st.st_size \
            and entry.get("source_mtime_ns") == st.st_mtime_ns:
        return False
    return source_record(frame.path)["source_sha256"] != entry.get("source_sha256")  # a video: hashed once


# -- the run ---------------------------------------------------------------------------------------

@dataclass
class ShowResult:
    """What one run did; ``manifest`` is the manifest as written at the end."""

    folder: Path
    done: list[int] = field(default_factory=list)
    skipped: list[int] = field(default_factory=list)
    failed: dict[int, str] = field(default_factory=dict)
    total: int = 0
    seconds: float = 0.0
    manifest: dict[str, Any] = field(default_factory=dict)

    @property
    def complete(self) -> bool:
        return not self.failed and len(self.done) + len(self.skipped) == self.total


def _save_bias(path: Path, bias: BiasModel) -> None:
    buf = io.BytesIO()
    arrays = {"theta": bias.theta} if bias.gain is None else {"theta": bias.theta, "gain": bias.gain}
    np.savez(buf, **arrays, kind=np.array(bias.kind), report=np.array(json.dumps(jsonable(bias.report))))
    write_atomic_bytes(path, buf.getvalue())


def _load_bias(path: Path) -> BiasModel | None:
    try:
        with np.load(path, allow_pickle=False) as data:
            return BiasModel(data["theta"].astype(np.float32),
                             data["gain"].astype(np.float32) if "gain" in data.files else None,
                             str(data["kind"]), json.loads(str(data["report"])))
    except (*DAMAGED_ARRAYS, TypeError):  # TypeError: a lone array (.npy), not an archive
        return None  # damaged: estimated again


def run(options: ShowOptions, progress: Progress | None = None, cancel: Cancel | None = None, *,
        device: Device | None = None, compensator: Compensator | None = None) -> ShowResult:
    """Compensate every frame into ``options.out`` (module doc); resumes a show made with the same settings.

    ``device``: an open device to use for ``options.stage_c.device`` (else it is
    opened here). ``compensator``: a loaded :class:`Compensator` to reuse (its
    spp, bounces and seed must equal the options'). Progress runs over the
    frames this run computes. Per-frame failures are recorded and reported in
    the result (the caller decides the exit code);
    :class:`~procam.addon.errors.Cancelled` or any unexpected error is
    recorded in the manifest and raised.
    """
    say = progress or quiet
    frames = list_frames(options.targets)
    if len({f.number for f in frames}) != len(frames):
        raise SequenceError("two target frames carry the same frame number")
    sc = options.stage_c
    sc.check()
    mode = sc.mode
    options.check(mode)
    # what the show reads: the calibration, the targets (a numbered pattern reads its folder), the device's files
    targets = [Path(t) for t in options.targets]
    check_apart_from_inputs(options.out, (options.calibration, calibrate_step.capture_set_of(options.calibration),
                                          *targets, *(t.parent for t in targets if not t.exists()),
                                          *stage_c_inputs(sc)), error=SequenceError)
    with writer_lock(options.out):  # another run of this show is refused before any work
        return _locked(options, frames, sc, mode, say, cancel, device, compensator)


def _locked(options: ShowOptions, frames: list[SourceFrame], sc: StageCOptions, mode: str, say: Progress,
            cancel: Cancel | None, device: Device | None, compensator: Compensator | None) -> ShowResult:
    cal = calibrate_step.read(options.calibration)  # says how to make one when the folder is not a calibration
    check_device_fits(sc.device, cal, device=device)  # a device of another rig: refused before any frame
    ident = calibrate_step.identity(options.calibration)
    digits = frame_digits(frames)
    say(f"show: {len(frames)} frame(s) {frames[0].number}…{frames[-1].number} → {options.out}", 0.0)
    if options.threads is not None and options.workers is None and not options.cluster:
        import drjit as dr

        before = dr.thread_count()
        dr.set_thread_count(options.threads)
        try:
            return _prepare(options, frames, sc, mode, cal, ident, digits, say, cancel, device, compensator)
        finally:
            dr.set_thread_count(before)
    return _prepare(options, frames, sc, mode, cal, ident, digits, say, cancel, device, compensator)


def _prepare(options: ShowOptions, frames: list[SourceFrame], sc: StageCOptions, mode: str, cal: Any,
             ident: dict[str, str], digits: int, say: Progress, cancel: Cancel | None, device: Device | None,
             compensator: Compensator | None) -> ShowResult:
    """:func:`run` once the request is checked: stage C loaded, the range fixed, the settings made."""
    if cal.projector_count > 1:
        # Every projector solved at once; a one-projector compensator given to reuse does not apply.
        with JointStage(cal, sc, device=device, progress=say) as joint:
            _fix_range(joint, frames, say)
            settings = settings_of(sc, calibration=ident, mode=mode, digits=digits, effects=joint.effects(),
                                   range_map=joint.range_map, warm=options.warm(),
                                   radiometry=measure_radiometry(joint, say))
            settings["blend"] = "derived"  # the joint solve's blend prior (stages/joint.py)
            return _run(options, frames, joint, cal, ident, settings, digits, say, cancel)
    with StageC(cal, sc, device=device, compensator=compensator) as stage:
        effects = stage.adapter.params if stage.adapter is not None else None
        _fix_range(stage, frames, say)
        settings = settings_of(sc, calibration=ident, mode=mode, digits=digits, effects=effects,
                               range_map=stage.range_map, warm=options.warm(),
                               radiometry=measure_radiometry(stage, say))
        return _run(options, frames, stage, cal, ident, settings, digits, say, cancel)


def _fix_range(stage: StageC | JointStage, frames: list[SourceFrame], say: Progress) -> None:
    """``--range auto`` or ``bright``: one map for the whole show, from an even sample of its frames (a per-frame
    fit would flicker)."""
    rule = parse_range(stage.options.range)
    if not isinstance(rule, str) or rule == "none":
        return
    sample = frames[::max(1, -(-len(frames) // RANGE_SAMPLE))]
    say(f"range: fitting the show's map to {len(sample)} of the {len(frames)} frames", 0.0)
    readers: dict[Path, VideoReader] = {}
    try:
        stage.fix_range([_load(stage, f, readers)[0] for f in sample])
    finally:
        for r in readers.values():
            r.close()
    if stage.range_map is not None:
        say(f"range: frames mapped to {stage.range_map.describe()}", 0.0)


def _load(stage: StageC | JointStage, frame: SourceFrame, readers: dict[Path, VideoReader]
          ) -> tuple[np.ndarray, str]:
    """A target as stage C reads it: an image file, or a frame of a video (readers kept open by path)."""
    if frame.index is None:
        return stage.load(frame.path)
    reader = readers.get(frame.path) or readers.setdefault(frame.path, VideoReader(frame.path))
    return load_video_frame(reader, frame.index, encoding=stage.options.target_encoding)


def projector_fingerprints(cal: Any) -> list[str]:
    """Each projector's calibration in short (SHA-256 of its calibrated description and warp): a show of several
    projectors records them (``projectors_calibrated``), so a resume after one was calibrated again names it."""
    out = []
    for projector, warp in zip(cal.rig.projectors, cal.warps):
        doc = {"projector": projector.to_dict(), "warp": warp.to_dict() if warp is not None else None}
        out.append(hashlib.sha256(json.dumps(jsonable(doc), sort_keys=True).encode()).hexdigest()[:16])
    return out


def _rig_changes(old: dict[str, Any], rig: dict[str, Any]) -> list[str]:
    """What differs between the projectors a show's manifest was made for and ``rig`` (a stage's rig record):
    projectors added or removed, a projector's frame or input size or offset, or its calibration."""
    def listed(doc: dict[str, Any]) -> list[Any]:
        return list(doc["projectors"]) if isinstance(doc.get("projectors"), list) else [doc.get("projector")]

    before, after = listed(old), listed(rig)
    out = []
    if len(before) != len(after):
        n, m = len(before), len(after)
        which = ", ".join(f"projector {k + 1}" for k in range(min(n, m), max(n, m)))
        out.append(f"{which} {'added' if m > n else 'removed'}: the show was made for {n} projector"
                   f"{'s' if n > 1 else ''}, the calibration has {m}")
    for k, (a, b) in enumerate(zip(before, after)):
        if not isinstance(a, dict):
            continue  # an older manifest that recorded no rig: the calibration's checksum says the rest
        for key in ("frame_size", "input_size", "input_offset"):
            if a.get(key) is not None and list(a[key]) != list(b[key]):
                out.append(f"projector {k + 1}'s {key.replace('_', ' ')} {a[key]} → {b[key]}")
    then, now = old.get("projectors_calibrated"), rig.get("projectors_calibrated")
    if isinstance(then, list) and isinstance(now, list):
        out += [f"projector {k + 1} calibrated again (its pose, lens, response or warp changed)"
                for k, (a, b) in enumerate(zip(then, now)) if a != b]
    return out


def _remove_frames(folder: Path, entries: Sequence[dict[str, Any]]) -> None:
    """--force: the frames (every projector's) and θ files of an earlier show, so the folder never mixes two."""
    for e in entries:
        files = [e.get("file")] + [p.get("file") for p in e.get("projectors") or [] if isinstance(p, dict)]
        for name in files:
            if isinstance(name, str) and _FRAME_FILE.fullmatch(name):
                (folder / name).unlink(missing_ok=True)
    for q in folder.iterdir():
        if q.name == BIAS_FILE or re.fullmatch(r"open_loop_bias_p\d+\.npz", q.name):
            q.unlink(missing_ok=True)
        elif _PROJECTOR_DIR.fullmatch(q.name) and q.is_dir() and not any(q.iterdir()):
            q.rmdir()


def _run(options: ShowOptions, frames: list[SourceFrame], stage: StageC | JointStage, cal: Any,
         ident: dict[str, str], settings: dict[str, Any], digits: int, say: Progress,
         cancel: Cancel | None) -> ShowResult:
    """:func:`run` once the frames, the settings and stage C are ready. With ``workers``/``cluster`` the cluster is
    started or reached first: one that cannot be leaves the show folder as it was (none is created)."""
    if options.workers is None and not options.cluster:
        return _run_folder(options, frames, stage, cal, ident, settings, digits, say, cancel, None)
    where = (f"the cluster at {options.cluster}" if options.cluster
             else f"a local cluster of {options.workers} worker(s)")
    say(f"starting {where}", 0.0)
    cluster = Cluster(workers=options.workers, address=options.cluster, threads=options.threads,
                      connect_timeout=options.connect_timeout, beside=Path(options.out),
                      poll=lambda: check(cancel, f"show cancelled while reaching {where}"))
    try:
        say(f"{where}: {cluster.describe}", 0.0)
        return _run_folder(options, frames, stage, cal, ident, settings, digits, say, cancel, cluster)
    finally:
        cluster.close()


def _run_folder(options: ShowOptions, frames: list[SourceFrame], stage: StageC | JointStage, cal: Any,
                ident: dict[str, str], settings: dict[str, Any], digits: int, say: Progress,
                cancel: Cancel | None, cluster: Cluster | None) -> ShowResult:
    """:func:`run` once the frames, the settings, stage C (and the cluster) are ready: the folder's bookkeeping."""
    force, mode = options.force, stage.options.mode
    effects = stage.adapter if isinstance(stage, StageC) else None
    count = stage.count if isinstance(stage, JointStage) else 1
    rig = stage.rig_record()
    if isinstance(stage, JointStage):
        rig = {**rig, "projectors_calibrated": projector_fingerprints(cal)}
    schedule = stage.schedule
    log = lambda msg: say(msg, 0.0)  # noqa: E731 — a message between frames, before the frame progress
    folder = ShowFolder(options.out)
    old = folder.open(force=force)
    t_run = time.perf_counter()
    try:
        history: dict[str, Any] = {"runs": [], "failures": []}
        frames_doc: dict[str, Any] = {}
        areas: dict[str, Any] = {}
        if old is not None:
            history = {"runs": list(old.get("runs", [])), "failures": list(old.get("failures", []))}
            for r in history["runs"]:
                # This process holds the folder's lock, so no run recorded as running is still alive (where locks
                # are not available, its recorded process is asked).
                if isinstance(r, dict) and r.get("status") == "running" and (folder.locked or owner_gone(r)):
                    r["status"] = "interrupted"
                    log(f"run {r.get('run')} (started {r.get('started')}) was interrupted before it finished "
                        "(its process ended: killed, or the machine stopped); resuming it")
            diffs = _rig_changes(old, rig) + _differences(old.get("settings", {}), settings)
            current = {str(f.number): f for f in frames}
            # An entry that is not a record (a damaged or hand-edited show.json) is no finished frame: redone.
            listed = old.get("frames")
            old_frames = {str(n): e for n, e in listed.items() if isinstance(e, dict)} \
                if isinstance(listed, dict) else {}
            changed = [n for n, e in old_frames.items()
                       if n in current and e.get("status") == "done" and _source_changed(e, current[n])]
            if not force:
                if diffs:
                    raise SequenceError(f"{folder.path} holds a show made with other settings ("
                                        + "; ".join(diffs) + "); its finished frames are never overwritten "
                                        "silently: rerun with --force to redo every frame, or choose another --out")
                if changed and frames[0].index is not None:
                    raise SequenceError(f"the video {frames[0].path} changed since its frames were compensated into "
                                        f"{folder.path}; rerun with --force to redo every frame, or choose another "
                                        "--out")
                if changed:
                    raise SequenceError(f"the target image of frame(s) {', '.join(sorted(changed, key=int))} changed "
                                        f"since they were compensated into {folder.path}; rerun with --force to "
                                        "redo every frame, or choose another --out")
                frames_doc = dict(old_frames)
                areas = dict(old.get("areas", {}))
            else:
                # --force: every frame is redone; remove the old ones so the folder never mixes two settings.
                _remove_frames(folder.path, list(old_frames.values()))
                if diffs:
                    log("--force: redoing every frame (settings changed: " + "; ".join(diffs) + ")")
                else:
                    log("--force: redoing every frame")
        run_no = len(history["runs"]) + 1
        run = {"run": run_no, "started": _now(), "status": "running", "frames": len(frames),
               "done": 0, "skipped": 0, "failed": 0,
               "where": (f"cluster {options.cluster}" if options.cluster else
                         f"local cluster, {options.workers} worker(s)" if options.workers else "this process"),
               "threads": options.threads, "pid": os.getpid(), "host": socket.gethostname()}
        history["runs"].append(run)
        folder.doc = {
            "format": FORMAT, "version": VERSION, "procam_version": _procam_version(),
            "calibration": {"path": ident["path"], "sha256": ident["sha256"], "surface_sha256": ident["surface_sha256"],
                            "capture_set": cal.capture_dir},
            "device": stage.options.device_spec, "mode": mode,
            "schedule": {"iterations": schedule.iterations_z + schedule.iterations_joint, **settings["schedule"],
                         "spp": stage.options.spp, "seed": stage.options.seed},
            # What the simulation f̂ models, and the diagnosed effect models around it (addon/gap).
            "effects": {"direct_light": True,
                        "interreflection_bounces": stage.bounces if isinstance(stage, StageC) else
                        stage.options.bounces,
                        "bias": mode if mode != "open-loop" else "open-loop (see open_loop_bias)",
                        "warp": cal.warp is not None if isinstance(stage, StageC) else
                        [v.warp is not None for v in stage.views],
                        "effect_models": effects.used if effects is not None else [],
                        "not_inverted": effects.not_used if effects is not None else {},
                        "params": effects.params if effects is not None else {},
                        **({"projectors": (stage.effects() or {}).get("projectors")}
                           if isinstance(stage, JointStage) else {})},
            **rig, "projector_count": count,
            "frame_pattern": (f"{FRAME_PREFIX}{'#' * digits}.png" if count == 1 else
                              f"{layout.PROJECTOR_FOLDER.format(k='K')}/{FRAME_PREFIX}{'#' * digits}.png"),
            "frame_format": "PNG, 16-bit RGB, linear",
            "settings": settings, "areas": areas, "frames": frames_doc, "complete": False, **history}
        if frames[0].index is not None:  # the video's identity: a changed video is noticed like a changed image
            folder.doc["video"] = {**source_record(frames[0].path), "frames": len(frames)}
        folder.write()

        result = ShowResult(folder.path, total=len(frames))
        todo: list[SourceFrame] = []
        prev_of = warm_from(frames, options)
        # Frames whose redone answer differs from the one their successor started from: that successor is redone
        # too. A frame redone only because its file went missing comes back byte-identical, so it is not here.
        changes: set[int] = set()
        for f in frames:
            entry = frames_doc.get(str(f.number))
            prev = prev_of.get(f.number)
            changed = not entry or entry.get("status") != "done"  # no answer yet: whoever started from it, didn't
            why = folder.verified_all(entry, frame_files(f.number, digits, count))
            if why is None and entry.get("warm_start") != prev:
                # Computed cold while its predecessor had no answer (it had failed), or started from a frame that
                # no longer precedes it: a fresh run starts it from its predecessor, so it is redone to match.
                why = (f"computed cold, without frame {prev}'s answer to start from" if prev is not None else
                       f"warm-started from frame {entry.get('warm_start')}, which no longer precedes it")
                changed = True
            elif why is None and prev in changes:
                why, changed = f"warm-started from frame {prev}, which is redone with another answer", True
            if why is None:
                result.skipped.append(f.number)
                continue
            if changed:
                changes.add(f.number)
            if entry and entry.get("status") == "done":
                log(f"frame {f.number}: redoing it ({why})")
                frames_doc[str(f.number)] = {**entry, "status": "invalid", "reason": why}
            todo.append(f)
        run["skipped"] = len(result.skipped)
        if result.skipped:
            log(f"{len(result.skipped)} of {len(frames)} frames already finished in {folder.path}; skipping them")
        kept = set(frames_doc) - {str(f.number) for f in frames}
        if kept:
            log(f"{len(kept)} frame(s) of an earlier run are not in this input; kept as they are")

        try:
            if todo:
                _run_frames(todo, frames, folder, result, run, stage, digits, options=options, ident=ident,
                            say=say, cancel=cancel, count=count, cluster=cluster)
            run["status"] = "complete" if not result.failed else "incomplete"
        except Cancelled as exc:
            run["status"] = "cancelled"
            kept = sum(1 for e in frames_doc.values() if isinstance(e, dict) and e.get("status") == "done")
            raise Cancelled(f"{exc}; {kept} finished frame(s) kept in {folder.path}: rerun the same command to "
                            "resume", kept=True) from None
        except KeyboardInterrupt:
            run["status"] = "cancelled"
            raise
        except ProCamError as exc:
            run["status"] = f"stopped: {exc}"
            raise
        except BaseException as exc:
            run["status"] = f"crashed: {type(exc).__name__}: {exc}"
            raise
        finally:
            run["finished"] = _now()
            run["seconds"] = round(time.perf_counter() - t_run, 2)
            folder.doc["complete"] = len(result.done) + len(result.skipped) == len(frames)
            try:
                folder.write()
            except ProCamError:
                pass  # the original error matters more; the manifest of the last finished frame stands
        result.seconds = time.perf_counter() - t_run
        result.manifest = folder.doc
        return result
    finally:
        folder.unlock()


def _procam_version() -> str:
    try:
        return metadata.version("procam")
    except metadata.PackageNotFoundError:  # inside Blender the extension is not a pip distribution
        return "unknown"


def _open_loop_bias(stage: StageC | JointStage, folder: ShowFolder, say: Progress) -> dict[str, Any] | list[Any]:
    """The open loop's θ: read back from the show folder when an earlier run estimated it, else estimated once
    and kept there (one file per projector with several); its manifest record."""
    if isinstance(stage, StageC):
        bias_path = folder.path / BIAS_FILE
        stage.bias = _load_bias(bias_path) if bias_path.is_file() else None
        if stage.bias is None:
            say("estimating θ from the validation captures (open loop, once for the whole show)", 0.0)
            _save_bias(bias_path, stage.estimate_bias())
        bias = stage.bias
        return {"file": BIAS_FILE, "kind": bias.kind, **bias.report}
    files = bias_files(stage.count)
    kept = [_load_bias(folder.path / f) if (folder.path / f).is_file() else None for f in files]
    if all(b is not None for b in kept):
        stage.use_biases([b for b in kept if b is not None])
    else:
        say(f"estimating θ of each of the {stage.count} projectors from its validation captures (open loop, once "
            "for the whole show)", 0.0)
        for f, b in zip(files, stage.estimate_bias()):
            _save_bias(folder.path / f, b)
    assert stage.biases is not None
    return [{"projector": k + 1, "file": f, "kind": b.kind, **b.report}
            for k, (f, b) in enumerate(zip(files, stage.biases))]


def _run_frames(todo: list[SourceFrame], frames: list[SourceFrame], folder: ShowFolder, result: ShowResult,
                run: dict[str, Any], stage: StageC | JointStage, digits: int, *, options: ShowOptions,
                ident: dict[str, str], say: Progress, cancel: Cancel | None, count: int = 1,
                cluster: Cluster | None = None) -> None:
    """The frame loop of :func:`run` (split out to keep the bookkeeping above readable): in this process, or as
    tasks on a cluster; either way this process alone writes the frames and the manifest, as they finish."""
    doc = folder.doc
    frames_doc, areas = doc["frames"], doc["areas"]
    stage.areas.update({k: DisplayArea.from_dict(v) for k, v in areas.items()})
    if stage.options.mode == "open-loop":
        doc["open_loop_bias"] = _open_loop_bias(stage, folder, say)

    prev_of = warm_from(frames, options)
    by_number = {f.number: f for f in frames}
    jobs = []
    for f in todo:
        p = by_number.get(prev_of.get(f.number, -1))
        jobs.append(FrameJob(f.number, f.path, frame_files(f.number, digits, count)[0], f.index,
                             p.number if p else None, p.path if p else None, p.index if p else None))
    # A frame warm-started from one finished in an earlier run starts from that frame's file(s), as verified.
    numbers = {j.number for j in jobs}
    starts: dict[int, list[bytes]] = {}
    for j in jobs:
        if j.prev is not None and j.prev not in numbers:
            entry = frames_doc[str(j.prev)]
            files = entry["projectors"] if count > 1 else [entry]
            starts[j.number] = []
            for f in files:
                data = inside(folder.path, f["file"], what="a finished frame", error=SequenceError).read_bytes()
                if hashlib.sha256(data).hexdigest() != f["sha256"]:
                    raise SequenceError(f"{f['file']} changed while the show ran; rerun to redo it")
                starts[j.number].append(data)

    n = len(jobs)
    finished = 0

    def record(out: FrameOutcome) -> None:
        nonlocal finished
        number, now = out.number, _now()
        source = str(next(j.path for j in jobs if j.number == number).absolute())
        if out.error is not None:
            result.failed[number] = out.error
            run["failed"] = len(result.failed)
            frames_doc[str(number)] = {**out.entry, "run": run["run"], "time": now}
            doc["failures"].append({"frame": number, "source": source, "error": out.error, "run": run["run"],
                                    "time": now})
            folder.write()
            finished += 1
            say(f"frame {number}: failed: {out.error}", finished / n)
            if options.fail_fast:
                raise SequenceError(f"frame {number} failed ({out.error}); stopped (--fail-fast). Finished frames "
                                    "are kept; fix it and rerun to resume") from None
            return
        # A full or vanished disk fails every frame alike: stop here rather than record failures.
        try:
            if count == 1:
                write_atomic_bytes(folder.path / out.entry["file"], out.png)
            else:
                # Every projector's file first, the entry after the last: a crash in between redoes the frame.
                for k, (f, png) in enumerate(zip(out.entry["projectors"], out.pngs)):
                    (folder.path / layout.PROJECTOR_FOLDER.format(k=k + 1)).mkdir(exist_ok=True)
                    write_atomic_bytes(folder.path / f["file"], png)
        except (OSError, ProCamError) as exc:
            raise SequenceError(f"cannot write frame {number} into {folder.path}: {exc}; the finished frames "
                                "are kept, rerun to resume") from None
        areas.update(out.areas)
        finished += 1
        for w in out.warnings:
            say(f"frame {number}: warning: {w}", finished / n)
        frames_doc[str(number)] = {**out.entry, "run": run["run"], "time": now}
        result.done.append(number)
        run["done"] = len(result.done)
        folder.write()  # the frame counts as finished from here on
        warm = f", warm from {out.entry['warm_start']}" if out.entry.get("warm_start") is not None else ""
        say(f"frame {number}: {out.entry['psnr_model']:.2f} dB (model), {out.entry['seconds']:.1f} s{warm}",
            finished / n)

    if cluster is not None:
        _run_on_cluster(cluster, jobs, starts, stage, digits, ident, areas, record, cancel)
        return
    readers: dict[Path, VideoReader] = {}
    last: FrameOutcome | None = None
    try:
        for i, job in enumerate(jobs):
            check(cancel, f"show cancelled before frame {job.number} ({len(result.done)} frame(s) finished in "
                          "this run)")
            say(f"frame {job.number}: {job.path.name}" + (f" #{job.index + 1}" if job.index is not None else ""),
                i / n)
            start: list[bytes] | None
            if last is not None and last.number == job.prev:  # computed just now (None: it failed)
                start = (last.pngs or [last.png]) if last.png is not None else None
            else:
                start = starts.pop(job.number, None)
            step = lambda msg, frac, i=i: say(msg, (i + min(max(frac, 0.0), 0.999)) / n)  # noqa: E731
            last = compute_frame(stage, job, start or None, digits=digits, readers=readers, cancel=cancel,
                                 progress=step)
            record(last)
    finally:
        for r in readers.values():
            r.close()


def _run_on_cluster(cluster: Cluster, jobs: list[FrameJob], starts: dict[int, list[bytes]],
                    stage: StageC | JointStage, digits: int, ident: dict[str, str], areas: dict[str, Any],
                    record: Any, cancel: Cancel | None) -> None:
    """The frames as tasks on a Dask cluster (:mod:`.show_cluster`); ``record`` writes each as it comes back."""
    key = hashlib.sha256(json.dumps([ident["sha256"], ident["surface_sha256"], repr(stage.options)])
                         .encode()).hexdigest()
    bias, biases = (None, stage.biases) if isinstance(stage, JointStage) else (stage.bias, None)
    ctx = WorkerContext(key, Path(ident["path"]), stage.options, bias, stage.range_map, dict(areas), cluster.threads,
                        biases=biases, digits=digits)
    outcomes = cluster.run(ctx, jobs, starts, poll=lambda: check(cancel, "show cancelled"))
    try:
        for out in outcomes:
            record(out)
    finally:
        outcomes.close()  # cancels what is still queued


# -- reading ---------------------------------------------------------------------------------------

@dataclass
class ShowView:
    """A show folder: its manifest, with each run as a reader should see it (:func:`read`)."""

    folder: Path
    doc: dict[str, Any]

    @property
    def complete(self) -> bool:
        """Whether every frame of the sequence is finished."""
        return bool(self.doc.get("complete"))

    @property
    def frames(self) -> dict[str, dict[str, Any]]:
        """Each frame's record by its number (as text): ``status`` done or failed, its ``file``, figures."""
        return {str(k): e for k, e in (self.doc.get("frames") or {}).items() if isinstance(e, dict)}

    @property
    def runs(self) -> list[dict[str, Any]]:
        """Every run that wrote the folder, oldest first; one whose process is gone reads ``interrupted``."""
        return [r for r in self.doc.get("runs") or [] if isinstance(r, dict)]

    @property
    def status(self) -> str | None:
        """The last run's status: running, complete, incomplete, cancelled, interrupted, … (None: no run)."""
        return str(self.runs[-1].get("status")) if self.runs else None


def read(folder: str | Path) -> ShowView:
    """A show folder and its manifest; a clear error when the folder holds no show. A run recorded as running
    whose process is gone reads as ``"interrupted"``."""
    doc = KIND.read(folder, SequenceError)
    if isinstance(doc.get("runs"), list):
        doc["runs"] = _runs_shown(doc)
    return ShowView(Path(folder), doc)


def owner_gone(run: dict[str, Any]) -> bool:
    """Whether the process that recorded ``run`` is known to have ended: it ran on this host under a process id
    that is no longer alive. False when it lives or cannot be asked (another host, no id recorded)."""
    pid, host = run.get("pid"), run.get("host")
    if isinstance(pid, bool) or not isinstance(pid, int) or pid <= 0 or host != socket.gethostname():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except (PermissionError, OSError):
        return False  # alive under another user (or the OS will not say)
    return False


def _runs_shown(doc: dict[str, Any]) -> list[dict[str, Any]]:
    """The manifest's runs as a reader should see them: a run still marked running whose process is gone was
    interrupted (SIGKILL, power loss) — it never had the chance to say so."""
    out = []
    for r in doc.get("runs") or []:
        if isinstance(r, dict) and r.get("status") == "running" and owner_gone(r):
            r = {**r, "status": "interrupted"}
        out.append(r)
    return out


def _summary(root: Path, doc: dict[str, Any]) -> Summary:
    frames = [e for e in (doc.get("frames") or {}).values() if isinstance(e, dict)]
    done = [e for e in frames if e.get("status") == "done"]
    failed = [e for e in frames if e.get("status") == "failed"]
    psnr = [float(e["psnr_model"]) for e in done if e.get("psnr_model") is not None]
    head = (f"{len(done)}/{len(frames)} frames finished ({doc.get('mode')})"
            + (f", model PSNR {fmt(sum(psnr) / len(psnr), '.2f')} dB mean" if psnr else ""))
    runs = [r for r in doc.get("runs") or [] if isinstance(r, dict)]
    last = runs[-1] if runs else {}
    ran = ([f"run {last.get('run')}: {last.get('done', 0)} frame(s) compensated, {last.get('skipped', 0)} already "
            f"finished, {last.get('failed', 0)} failed, {fmt(last.get('seconds'), '.1f', ' s')} "
            f"({last.get('where', 'this process')})"] if last else [])
    lines = (*ran, *(f"frame {e.get('number')}: failed — {e.get('error', '')}" for e in failed),
             *range_line((doc.get("settings") or {}).get("range")))
    return Summary(True, head, lines, {"done": len(done), "failed": len(failed), "complete": doc.get("complete"),
                                       "status": last.get("status"), "run": last})


def summary(folder: str | Path) -> Summary:
    """A show folder: frames finished and failed, mean model PSNR, and whether its last run is still running or
    was interrupted."""
    s = cached(KIND, folder, _summary, "run Prepare Show or choose a show folder")
    run = s.data.get("run") if s.ok else None
    if not run or run.get("status") != "running":
        return s
    # Asked on every call, not cached: the manifest of a killed run does not change when its process dies.
    if owner_gone(run):
        return replace(s, headline=s.headline + ", interrupted",
                       lines=(f"run {run.get('run')} was interrupted before it finished (process {run.get('pid')} "
                              f"on {run.get('host')} is gone); rerun the same command to resume",) + s.lines,
                       data={**s.data, "status": "interrupted"})
    owner = f" (process {run.get('pid')} on {run.get('host')})" if run.get("pid") else ""
    return replace(s, headline=s.headline + ", running",
                   lines=(f"run {run.get('run')} is marked running{owner}",) + s.lines)
