"""Show preparation: compensate every frame of a folder or numbered image sequence, resumably.

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

One :class:`~.compensate.Compensator` (scene loaded, kernels compiled) serves
every frame. Two runs on one folder at once are refused (an OS lock on the
folder, released by the OS when a process dies).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import Cancelled, ProCamError
from .compensate import DEFAULT_SCHEDULE, BiasModel, Schedule, get_schedule

FORMAT = "procam-show"
VERSION = 1
MANIFEST = "show.json"
BIAS_FILE = "open_loop_bias.npz"
FRAME_PREFIX = "frame_"
#: Files taken as frames when a folder is given.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp", ".npy")

#: ``on_progress(done, total, message, finished)``: ``done`` of the ``total`` frames this run computes
#: (fractional while one is under way); ``finished`` is true when a frame has just been written or has failed.
OnProgress = Callable[[float, int, str, bool], None]


class SequenceError(ProCamError):
    """A target sequence or show folder that cannot be used as asked."""


# -- the input sequence ----------------------------------------------------------------------------

@dataclass(frozen=True)
class SourceFrame:
    """One target image of the sequence and the frame number its output carries."""

    number: int
    path: Path


_HASHES = re.compile(r"#+")
_PRINTF = re.compile(r"%(0?)(\d*)d")
_TRAILING_DIGITS = re.compile(r"(\d+)$")


def _natural_key(path: Path) -> list[Any]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]


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
    paths = sorted(paths, key=_natural_key)
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
    numbered by the file names), or a list of image files (numbered like a folder).
    """
    items = [Path(p) for p in inputs]
    if not items:
        raise SequenceError("no target frames given; name a folder, a pattern like frames/shot_####.png, or files")
    if len(items) == 1 and items[0].is_dir():
        folder = items[0]
        paths = [p for p in folder.iterdir()
                 if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in IMAGE_SUFFIXES]
        if not paths:
            raise SequenceError(f"the folder {folder} holds no images ({', '.join(IMAGE_SUFFIXES)})")
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
        for p in sorted(folder.iterdir(), key=_natural_key):
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


def frame_name(number: int, digits: int) -> str:
    """The output file name of frame ``number`` (``frame_0001.png``): zero-padded like media servers expect."""
    return f"{FRAME_PREFIX}{number:0{digits}d}.png"


def frame_digits(frames: Sequence[SourceFrame]) -> int:
    """Zero padding for the output names: 4, or more when the frame numbers need it."""
    return max(4, *(len(str(f.number)) for f in frames)) if frames else 4


def file_sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


# -- settings and manifest -----------------------------------------------------------------------

@dataclass(frozen=True)
class ShowOptions:
    """How each frame is compensated: the stage-C schedule (by name, with the values given over it) and choices.

    A schedule value left None is the named schedule's (:data:`~.compensate.SCHEDULES`).
    """

    schedule: str = DEFAULT_SCHEDULE
    iterations_z: int | None = None
    iterations_joint: int | None = None
    lr: float | None = None
    alpha: float | None = None
    capture_every: int | None = None
    spp: int = 4
    bounces: int = 1
    seed: int = 0
    area: tuple[int, int, int, int] | None = None  # camera pixels; None: chosen per aspect ratio
    target_encoding: str = "auto"
    use_bias: bool = True

    def run_arguments(self) -> dict[str, Any]:
        """The schedule keywords of :meth:`Compensator.run`."""
        given = {"iterations_z": self.iterations_z, "iterations_joint": self.iterations_joint, "lr": self.lr,
                 "alpha": self.alpha, "capture_every": self.capture_every}
        return {"schedule": self.schedule, **{k: v for k, v in given.items() if v is not None}}

    def resolved(self) -> Schedule:
        """The schedule every frame runs (a bad value fails here, before any work)."""
        args = self.run_arguments()
        return replace(get_schedule(args.pop("schedule")), **args).check()

    def check(self) -> Schedule:
        for what, v, lo in (("spp", self.spp, 1), ("bounces", self.bounces, 0)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise SequenceError(f"{what} must be a whole number ≥ {lo}, got {v!r}")
        return self.resolved()


def settings_of(options: ShowOptions, *, calibration: dict[str, str], device: str | None, mode: str,
                digits: int) -> dict[str, Any]:
    """What decides the frames' pixels: two runs with equal settings write the same frames."""
    schedule = asdict(options.resolved())
    if mode != "closed-loop":  # θ's update rule and the capture interval only act in the closed loop
        schedule.update(alpha=None, capture_every=None, reference_spp=None)
    return {"calibration_sha256": calibration["sha256"], "surface_sha256": calibration["surface_sha256"],
            "device": device, "mode": mode, "schedule": schedule, "spp": options.spp, "bounces": options.bounces,
            "seed": options.seed, "area": list(options.area) if options.area else "auto",
            "target_encoding": options.target_encoding, "digits": digits}


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


def calibration_identity(folder: str | Path) -> dict[str, str]:
    """Path and content hashes of a calibration folder (calibration.json and its surface mesh)."""
    folder = Path(folder)
    doc_path = folder / "calibration.json"
    try:
        mesh = json.loads(doc_path.read_text()).get("surface", {}).get("mesh", "surface.npz")
        return {"path": str(folder.absolute()), "sha256": file_sha256(doc_path),
                "surface_sha256": file_sha256(folder / mesh)}
    except (OSError, ValueError, AttributeError) as exc:
        raise SequenceError(f"cannot read the calibration {folder}: {exc}") from None


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


class ShowFolder:
    """The output folder and its manifest: locking, verification of finished frames, atomic updates."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.doc: dict[str, Any] | None = None
        self._lock_fd: int | None = None

    # locking: flock on the folder itself, so no lock file is left behind and a dead process frees it
    def lock(self) -> None:
        try:
            import fcntl
        except ImportError:  # Windows: no advisory locks here; two runs on one folder are the user's to avoid
            return
        fd = os.open(self.path, os.O_RDONLY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise SequenceError(f"another procam run is writing to {self.path}; wait for it to finish or "
                                "choose another --out") from None
        self._lock_fd = fd

    def unlock(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # closing releases the flock
            self._lock_fd = None

    def open(self, *, force: bool = False) -> dict[str, Any] | None:
        """Create or check the folder, and lock it; return the existing manifest (None for a new show).

        With ``force`` a damaged manifest, or one of another format version, starts a new show.
        """
        p = self.path
        if p.exists() and not p.is_dir():
            raise SequenceError(f"{p} exists and is not a folder; choose another --out")
        manifest = p / MANIFEST
        if p.is_dir() and not manifest.is_file() and any(not q.name.startswith(".") for q in p.iterdir()):
            raise SequenceError(f"{p} is not empty and holds no {MANIFEST}: it is not a show folder; "
                                "refusing to write frames into it — choose another --out")
        try:
            p.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SequenceError(f"cannot create the show folder {p}: {exc.strerror or exc}") from None
        self.lock()
        try:
            return self._read(manifest, force)
        except BaseException:
            self.unlock()  # flock conflicts even within one process: never keep it after a refusal
            raise

    def _read(self, manifest: Path, force: bool) -> dict[str, Any] | None:
        # Temporary files of a run that died mid-write (frames and manifest are written as .NAME.*.suffix).
        for q in self.path.iterdir():
            if q.name.startswith((f".{FRAME_PREFIX}", ".show.", ".open_loop_bias.")) and q.is_file():
                q.unlink(missing_ok=True)
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
        from ..imageio import write_atomic_bytes
        from ..outputs import jsonable

        assert self.doc is not None
        write_atomic_bytes(self.path / MANIFEST, (json.dumps(jsonable(self.doc), indent=1) + "\n").encode())

    def verified(self, entry: dict[str, Any] | None) -> str | None:
        """None when ``entry`` is a finished frame whose file is intact, else why it must be redone."""
        if not entry or entry.get("status") != "done":
            return "not finished" if not entry else f"{entry.get('status')} before"
        path = self.path / str(entry.get("file", ""))
        if not path.is_file():
            return f"{path.name} is missing"
        if path.stat().st_size != entry.get("bytes"):
            return f"{path.name} has {path.stat().st_size} bytes, the manifest says {entry.get('bytes')}"
        if file_sha256(path) != entry.get("sha256"):
            return f"{path.name} does not match its checksum (damaged or replaced)"
        return None


def _source_record(path: Path) -> dict[str, Any]:
    st = path.stat()
    return {"source": str(path.absolute()), "source_bytes": st.st_size, "source_mtime_ns": st.st_mtime_ns}


def _source_changed(entry: dict[str, Any], frame: SourceFrame) -> bool:
    """Whether the target of a finished frame changed since (size/time first, the hash only when those differ)."""
    try:
        st = frame.path.stat()
    except OSError:
        return False  # a vanished target is reported when it is read, not here
    if entry.get("source") == str(frame.path.absolute()) and entry.get("source_bytes") == st.st_size \
            and entry.get("source_mtime_ns") == st.st_mtime_ns:
        return False
    return file_sha256(frame.path) != entry.get("source_sha256")


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
    import io

    from ..imageio import write_atomic_bytes
    from ..outputs import jsonable

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
    except (OSError, ValueError, KeyError):
        return None  # damaged: estimated again


def prepare_show(calibration_dir: str | Path, frames: Sequence[SourceFrame], out_dir: str | Path,
                 options: ShowOptions, *, device: Any = None, device_spec: str | None = None, force: bool = False,
                 fail_fast: bool = False, on_progress: OnProgress | None = None,
                 log: Callable[[str], None] | None = None, cancel: Callable[[], bool] | None = None,
                 compensator: Any = None, effects: Any = None) -> ShowResult:
    """Compensate every frame into ``out_dir`` (module doc); resumes a show made with the same settings.

    ``device``: closed loop through it (``device_spec`` names it in the
    manifest); none: open loop, or no θ with ``options.use_bias=False``.
    ``compensator``: a loaded :class:`~.compensate.Compensator` to reuse (its
    spp, bounces and seed must equal the options'). Per-frame failures are
    recorded and reported in the result (the caller decides the exit code);
    :class:`~procam.addon.errors.Cancelled` or any unexpected error is recorded
    in the manifest and raised. ``effects``: a :class:`~..gap.compensation.EffectAdapter` whose diagnosed
    effect models sit around stage C (part of the settings: a rerun with other effects needs ``force``).
    """
    from .calibrate import Calibration
    from .display_area import choose_area

    say = log or (lambda msg: None)
    tick = on_progress or (lambda done, total, msg, finished: None)
    frames = list(frames)
    if not frames:
        raise SequenceError("no target frames to compensate")
    if len({f.number for f in frames}) != len(frames):
        raise SequenceError("two target frames carry the same frame number")
    schedule = options.check()
    if device is not None and not device_spec:
        raise SequenceError("a device needs a name (device_spec) for the manifest")
    mode = "closed-loop" if device is not None and options.use_bias else "open-loop" if options.use_bias else "none"
    cal = Calibration.load(calibration_dir)  # says how to make one when the folder is not a calibration
    ident = calibration_identity(calibration_dir)
    digits = frame_digits(frames)
    settings = settings_of(options, calibration=ident, device=device_spec if mode == "closed-loop" else None,
                           mode=mode, digits=digits)
    settings["effects"] = effects.params if effects is not None else None
    if effects is not None and compensator is not None:
        raise SequenceError("a show with effect models builds its own compensator (its scene moves with them)")
    user_area = None
    if options.area is not None:
        user_area = choose_area(cal, aspect=1.0, user=options.area)  # fails now if outside the camera image

    folder = ShowFolder(out_dir)
    old = folder.open(force=force)
    t_run = time.perf_counter()
    try:
        history: dict[str, Any] = {"runs": [], "failures": []}
        frames_doc: dict[str, Any] = {}
        areas: dict[str, Any] = {}
        if old is not None:
            history = {"runs": list(old.get("runs", [])), "failures": list(old.get("failures", []))}
            diffs = _differences(old.get("settings", {}), settings)
            current = {str(f.number): f for f in frames}
            changed = [n for n, e in old.get("frames", {}).items()
                       if n in current and e.get("status") == "done" and _source_changed(e, current[n])]
            if not force:
                if diffs:
                    raise SequenceError(f"{folder.path} holds a show made with other settings ("
                                        + "; ".join(diffs) + "); its finished frames are never overwritten "
                                        "silently: rerun with --force to redo every frame, or choose another --out")
                if changed:
                    raise SequenceError(f"the target image of frame(s) {', '.join(sorted(changed, key=int))} changed "
                                        f"since they were compensated into {folder.path}; rerun with --force to "
                                        "redo every frame, or choose another --out")
                frames_doc = dict(old.get("frames", {}))
                areas = dict(old.get("areas", {}))
            else:
                # --force: every frame is redone; remove the old ones so the folder never mixes two settings.
                for e in old.get("frames", {}).values():
                    name = str(e.get("file", ""))
                    if re.fullmatch(rf"{FRAME_PREFIX}\d+\.png", name):
                        (folder.path / name).unlink(missing_ok=True)
                (folder.path / BIAS_FILE).unlink(missing_ok=True)
                if diffs:
                    say("--force: redoing every frame (settings changed: " + "; ".join(diffs) + ")")
                else:
                    say("--force: redoing every frame")
        run_no = len(history["runs"]) + 1
        run = {"run": run_no, "started": _now(), "status": "running", "frames": len(frames),
               "done": 0, "skipped": 0, "failed": 0}
        history["runs"].append(run)
        proj = cal.rig.projector
        folder.doc = {
            "format": FORMAT, "version": VERSION, "procam_version": _procam_version(),
            "calibration": {"path": ident["path"], "sha256": ident["sha256"], "surface_sha256": ident["surface_sha256"],
                            "capture_set": cal.capture_dir},
            "device": device_spec if mode == "closed-loop" else None, "mode": mode,
            "schedule": {"iterations": schedule.iterations_z + schedule.iterations_joint, **settings["schedule"],
                         "spp": options.spp, "seed": options.seed},
            # What the simulation f̂ models, and the diagnosed effect models around it (addon/gap).
            "effects": {"direct_light": True,
                        "interreflection_bounces": effects.bounces if effects is not None and effects.bounces
                        is not None else options.bounces,
                        "bias": mode if mode != "open-loop" else "open-loop (see open_loop_bias)",
                        "warp": cal.warp is not None,
                        "effect_models": effects.used if effects is not None else [],
                        "not_inverted": effects.not_used if effects is not None else {},
                        "params": effects.params if effects is not None else {}},
            "projector": {"frame_size": list(proj.intrinsics.size), "input_size": list(proj.input_size),
                          "input_offset": list(proj.input_offset)},
            "camera_size": list(cal.rig.camera.intrinsics.size),
            "frame_pattern": f"{FRAME_PREFIX}{'#' * digits}.png", "frame_format": "PNG, 16-bit RGB, linear",
            "settings": settings, "areas": areas, "frames": frames_doc, "complete": False, **history}
        folder.write()

        result = ShowResult(folder.path, total=len(frames))
        todo: list[SourceFrame] = []
        for f in frames:
            why = folder.verified(frames_doc.get(str(f.number)))
            if why is None:
                result.skipped.append(f.number)
            else:
                entry = frames_doc.get(str(f.number))
                if entry and entry.get("status") == "done":
                    say(f"frame {f.number}: redoing it ({why})")
                    frames_doc[str(f.number)] = {**entry, "status": "invalid", "reason": why}
                todo.append(f)
        run["skipped"] = len(result.skipped)
        if result.skipped:
            say(f"{len(result.skipped)} of {len(frames)} frames already finished in {folder.path}; skipping them")
        kept = set(frames_doc) - {str(f.number) for f in frames}
        if kept:
            say(f"{len(kept)} frame(s) of an earlier run are not in this input; kept as they are")

        try:
            if todo:
                _run_frames(todo, folder, result, run, options, cal, mode, digits, user_area, device=device,
                            compensator=compensator, fail_fast=fail_fast, tick=tick, say=say, cancel=cancel,
                            effects=effects)
            run["status"] = "complete" if not result.failed else "incomplete"
        except Cancelled as exc:
            run["status"] = "cancelled"
            raise Cancelled(f"{exc}; the finished frames are kept in {folder.path}: rerun the same command to "
                            "resume") from None
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
        from importlib.metadata import version

        return version("procam")
    except Exception:  # inside Blender the extension is not a pip distribution
        return "unknown"


def _run_frames(todo: list[SourceFrame], folder: ShowFolder, result: ShowResult, run: dict[str, Any],
                options: ShowOptions, cal: Any, mode: str, digits: int, user_area: Any, *, device: Any,
                compensator: Any, fail_fast: bool, tick: OnProgress, say: Callable[[str], None],
                cancel: Callable[[], bool] | None, effects: Any = None) -> None:
    """The frame loop of :func:`prepare_show` (split out to keep the bookkeeping above readable)."""
    from ..capture.format import CaptureSet
    from ..imageio import write_image
    from .compensate import Compensator
    from .display_area import DisplayArea, TargetAspectWarning, choose_area, fit_target, load_target

    doc = folder.doc
    frames_doc, areas = doc["frames"], doc["areas"]
    comp = compensator
    if comp is None:
        say(f"loading the calibrated scene ({mode})")
        if effects is None:
            comp = Compensator(cal, bounces=options.bounces, spp=options.spp, seed=options.seed)
        else:
            from ..gap.compensation import AdaptedDevice

            comp = effects.compensator(cal, bounces=options.bounces, spp=options.spp, seed=options.seed)
            device = AdaptedDevice(device, effects) if device is not None else None
    elif (comp.bounces, comp.spp, comp.seed) != (options.bounces, options.spp, options.seed):
        raise SequenceError("the compensator given was made with other bounces/spp/seed than the show's options")
    try:
        captures = CaptureSet.load(cal.capture_dir, verify_images=False) if cal.capture_dir else None
    except ProCamError:
        captures = None  # a moved capture set: areas then come from --area or the model alone
    bias = None
    if mode == "open-loop":
        bias_path = folder.path / BIAS_FILE
        bias = _load_bias(bias_path) if bias_path.is_file() else None
        if bias is None:
            say("estimating θ from the validation captures (open loop, once for the whole show)")
            if effects is not None and captures is not None:
                from ..gap.compensation import AdaptedCaptures

                bias = comp.estimate_bias(AdaptedCaptures(captures, effects))
            else:
                bias = comp.estimate_bias(captures)
            _save_bias(bias_path, bias)
        doc["open_loop_bias"] = {"file": BIAS_FILE, "kind": bias.kind, **bias.report}

    def area_for(img: np.ndarray) -> Any:
        if user_area is not None:
            return user_area
        key = f"{img.shape[1] / img.shape[0]:.4f}"
        if key not in areas:
            areas[key] = choose_area(cal, aspect=img.shape[1] / img.shape[0], captures=captures).to_dict()
        return DisplayArea.from_dict(areas[key])

    for i, f in enumerate(todo):
        if cancel is not None and cancel():
            raise Cancelled(f"show cancelled before frame {f.number} ({len(result.done)} frame(s) finished in this run)")
        name = frame_name(f.number, digits)
        tick(i, len(todo), f"frame {f.number}: {f.path.name}", False)
        t0 = time.perf_counter()
        try:
            try:
                source = _source_record(f.path)
                source["source_sha256"] = file_sha256(f.path)
            except OSError as exc:  # vanished or unreadable since the sequence was listed
                raise SequenceError(f"cannot read the target {f.path}: {exc.strerror or exc}") from None
            img, note = load_target(f.path, encoding=options.target_encoding)
            area = area_for(img)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", TargetAspectWarning)
                fitted = fit_target(img, area, what=f"target {f.path.name}")
                if effects is not None:
                    fitted = effects.model_target(fitted, area)
                res = comp.run(fitted, area, device=device, **options.run_arguments(), open_loop_theta=bias,
                               use_bias=options.use_bias, cancel=cancel, name=f"frame {f.number}",
                               progress=lambda msg, frac, i=i: tick(i + min(max(frac, 0.0), 0.999), len(todo), msg,
                                                                     False))
        except Cancelled:
            raise
        except ProCamError as exc:
            result.failed[f.number] = str(exc)
            run["failed"] = len(result.failed)
            frames_doc[str(f.number)] = {"number": f.number, "source": str(f.path.absolute()), "status": "failed",
                                         "error": str(exc), "run": run["run"], "time": _now()}
            doc["failures"].append({"frame": f.number, "source": str(f.path.absolute()), "error": str(exc),
                                    "run": run["run"], "time": _now()})
            folder.write()
            say(f"frame {f.number} failed: {exc}")
            tick(i + 1, len(todo), f"frame {f.number}: failed", True)
            if fail_fast:
                raise SequenceError(f"frame {f.number} failed ({exc}); stopped (--fail-fast). Finished frames are "
                                    "kept; fix it and rerun to resume") from None
            continue
        # Outside the per-frame handling above: a full or vanished disk fails every frame alike, so stop here.
        try:
            frame = res.x_frame if effects is None else effects.frame_to_send(res.x_input)
            out = write_image(folder.path / name, frame)
        except (OSError, ProCamError) as exc:
            raise SequenceError(f"cannot write frame {f.number} into {folder.path}: {exc}; the finished frames "
                                "are kept, rerun to resume") from None
        notes = [str(w.message) for w in caught]
        for n in notes:
            say(f"frame {f.number}: warning: {n}")
        entry = {"number": f.number, "file": name, **source, "status": "done",
                 "bytes": out.stat().st_size, "sha256": file_sha256(out),
                 "mode": res.mode, "area": area.to_dict(), "encoding": note, "warnings": notes,
                 "psnr_model_start": round(res.report["psnr_simulated_start"], 3),
                 "psnr_model": round(res.report["psnr_simulated"], 3),
                 "loss_first": res.losses[0] if res.losses else None,
                 "loss_last": res.losses[-1] if res.losses else None, "captures": res.captures,
                 "seconds": round(res.seconds, 2), "seconds_total": round(time.perf_counter() - t0, 2),
                 "run": run["run"], "time": _now()}
        frames_doc[str(f.number)] = entry
        result.done.append(f.number)
        run["done"] = len(result.done)
        folder.write()  # the frame counts as finished from here on
        tick(i + 1, len(todo), f"frame {f.number}: {res.report['psnr_simulated']:.2f} dB (model), "
                                   f"{res.seconds:.1f} s", True)


__all__ = ["FORMAT", "MANIFEST", "OnProgress", "SequenceError", "ShowFolder", "ShowOptions", "ShowResult",
           "SourceFrame", "calibration_identity", "file_sha256", "frame_digits", "frame_name", "list_frames",
           "prepare_show", "settings_of"]
