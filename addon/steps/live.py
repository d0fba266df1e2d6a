"""The live capture step: the calibration sequence shown on the projector and captured by the camera, resumable.

A session lives in ``OUT.session/`` beside the capture set it will become:
the exported sequence (``sequence/``, as ``procam patterns`` writes it), one
photograph per frame as it is captured (``photos/NNNN.png``, 16-bit linear,
each written atomically) and ``session.json`` (the settings, and what the live
device measured each time it opened). An interrupted session (Ctrl-C, Esc in
the projector window, a camera that dropped out) keeps its photographs; the
same command resumes at the first missing one. When every frame is captured
the photographs are imported exactly as ``procam import-captures`` imports a
user's own (depth, rig file, exposure check), the capture set is written and
the session folder removed.

Why resume through photographs rather than a half-written capture set: a
capture set is written atomically or not at all (``capture/format.py``), and
the folder workflow's import already checks what a resumed session most
risks — a camera whose exposure or white balance changed in between.

Several projectors (``display=1+2``, one window each): each projector's
sequence is captured while the others show black (``capture.devices.OneProjector``),
projector 1's into ``sequence/`` and ``photos/`` as for one projector,
projector K's into ``sequence_pK/`` and ``photos_pK/``; the session resumes
the same way, at the first missing photograph of any projector. Each
projector's photographs are imported on their own (the depth with projector
1's), and the imports are combined into one multi-projector capture set
(``capture/combine.py``: the surface photo and the depth once). A rig file
(``--rig``) calibrates one projector and is refused for several.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..capture.combine import combine_projector_sets
from ..capture.devices import Device, OneProjector
from ..capture.sequence import export_sequence, load_sequence, sequence_frame
from ..capture.format import CaptureSet, is_capture_set
from ..errors import Cancelled, CaptureError, LiveError
from ..imageio import read_image, write_atomic_bytes, write_image
from ..lab.layouts import MAX_PROJECTORS
from ..live.shoot import check_camera_device, open_camera_device, parse_camera_device
from ..options import option, same_option, validate
from ..outputs import check_replaceable, writer_lock
from ..progress import Cancel, Progress, never, part, quiet
from ..rig.model import Projector, projector_intrinsics_from_throw
from .capture import ImportOptions, PatternsOptions, PhotoSettings, ProjectorSheet, run_import

SESSION_FORMAT = "procam-live-session"
SESSION_MANIFEST = "session.json"


DEVICE_HELP = ("live:camera=SOURCE,display=N — SOURCE a camera index, a device path or a URL (http://…mjpg, "
               "rtsp://…); display=N covers display N (at the projector's native size; displays are numbered "
               "from 0, as procam live-check --list-displays lists them), position=X:Y puts the "
               "window at desktop coordinates instead; several projectors: one display each, display=1+2 (or "
               "position=X:Y+X:Y); options: average=N or noise=σ (frames per capture), encoding=srgb|linear, "
               "latency=auto|SECONDS, size=WxH. A stills camera: shoot='COMMAND … {out} …' instead of camera= "
               "(e.g. shoot='gphoto2 --capture-image-and-download --filename {out}'; the command runs latency "
               "seconds after the frame shows, default 0.25; timeout=SECONDS, encoding=auto|srgb|linear). Other "
               "software that shows and photographs: command:run='TOOL … {frame} … {out}' ({frame}: the 16-bit PNG "
               "to show; several projectors {frame1} … {frameN})")


@dataclass(frozen=True)
class LiveCaptureOptions(PhotoSettings):
    """What ``procam capture`` asks for: the live device, the pattern sequence, and how to import it."""

    device: str = option(required=True, check=parse_camera_device, help=DEVICE_HELP)
    projector: Projector
    out: Path
    # the pattern sequence's options, declared by the patterns step
    checker: int | None = same_option(PatternsOptions, "checker")
    area: str = same_option(PatternsOptions, "area")
    graycode: bool = same_option(PatternsOptions, "graycode")
    validation: bool = same_option(PatternsOptions, "validation")
    seed: int = same_option(PatternsOptions, "seed")
    force: bool = False
    restart: bool = option(False, label="Restart", own_field=True,
                           help="discard an interrupted session of other settings instead of refusing")
    #: projectors 2…N of a rig of several, in rig order (one display each in ``device``)
    others: tuple[Projector, ...] = ()

    @property
    def projectors(self) -> tuple[Projector, ...]:
        """Every projector whose sequence the session captures, the first first."""
        return (self.projector, *self.others)

    @property
    def session(self) -> Path:
        return self.out.with_name(self.out.name + ".session")

    def settings(self) -> dict[str, Any]:
        """What a resumed session must share with the one it continues (the device may differ: a new port…)."""
        return {"projector": self.projector.to_dict(), "checker": self.checker, "area": self.area,
                "graycode": self.graycode, "validation": self.validation, "seed": self.seed,
                # written only for several, so that a one-projector session reads (and resumes) as before
                **({"others": [p.to_dict() for p in self.others]} if self.others else {})}


@dataclass(frozen=True)
class LiveRigSheet:
    """How many projectors ``procam capture`` drives: all of the projector sheet's kind, one display each."""

    projectors: int = option(
        1, min=1, max=MAX_PROJECTORS,
        help="projectors of the rig (default 1), all of the sheet's size and lens, one display each in the "
             "device's display=1+2…; each projector's sequence is captured while the others show black, into one "
             "capture set")

    def others(self, projector: Projector) -> tuple[Projector, ...]:
        """Projectors 2…N: the sheet's projector again (their poses are unknown until calibration)."""
        validate(self, CaptureError)
        return (projector,) * (self.projectors - 1)


@dataclass(frozen=True)
class LiveCheckOptions:
    """What ``procam live-check`` asks for: the live device and the projector window's size, or the displays."""

    device: str | None = same_option(LiveCaptureOptions, "device", None, required=False)
    projector_width: int | None = same_option(ProjectorSheet, "projector_width", None, required=False,
                                              help="native projector width (px): the window's width")
    projector_height: int | None = same_option(ProjectorSheet, "projector_height", None, required=False)
    list_displays: bool = option(False, help="list the displays and their sizes, then stop")
    check_exposure: bool = option(True, negate="--no-exposure-check", help="check that the exposure is locked")

    def projector(self) -> Projector:
        """The projector whose window the check opens (its native size; the throw ratio does not matter here)."""
        validate(self, LiveError)
        if not (self.device and self.projector_width and self.projector_height):
            raise LiveError("live-check needs --device, --projector-width and --projector-height (or "
                            "--list-displays)")
        return Projector(projector_intrinsics_from_throw(self.projector_width, self.projector_height, 1.0))


def _is_session(path: Path) -> bool:
    return (path / SESSION_MANIFEST).is_file()


def _read_session(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads((path / SESSION_MANIFEST).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CaptureError(f"cannot read the live session {path / SESSION_MANIFEST}: {exc}; remove {path} or give "
                           "--restart") from None
    if not isinstance(doc, dict) or doc.get("format") != SESSION_FORMAT:
        raise CaptureError(f"{path} is not a live capture session; choose another --out")
    return doc


def _write_session(path: Path, doc: dict[str, Any]) -> None:
    write_atomic_bytes(path / SESSION_MANIFEST, (json.dumps(doc, indent=1) + "\n").encode())


def _sequence_dir(session: Path, k: int = 0) -> Path:
    """Projector ``k``'s exported sequence in a session folder (projector 1's where a one-projector session
    keeps its one)."""
    return session / ("sequence" if k == 0 else f"sequence_p{k + 1}")


def _photos_dir(session: Path, k: int = 0) -> Path:
    return session / ("photos" if k == 0 else f"photos_p{k + 1}")


def _photo(session: Path, i: int, k: int = 0) -> Path:
    """Where frame ``i``'s photograph of projector ``k``'s sequence is kept in a session folder."""
    return _photos_dir(session, k) / f"{i:04d}.png"


def _photos_taken(session: Path) -> int:
    return sum(len(list(d.glob("*.png"))) for d in session.glob("photos*") if d.is_dir())


def open_session(options: LiveCaptureOptions) -> tuple[dict[str, Any], int]:
    """The session folder for ``options``: resumed when it holds the same settings, else made anew.

    Returns its manifest and how many photographs it already holds."""
    session = options.session
    if session.exists() and not _is_session(session) and any(session.iterdir()):
        raise CaptureError(f"{session} exists and is not a live capture session; move it away first")
    if _is_session(session):
        doc = _read_session(session)
        if doc.get("settings") != json.loads(json.dumps(options.settings())):
            if not options.restart:
                raise CaptureError(f"{session} holds a live session with other settings (projectors, patterns or "
                                   "seed): give the same settings to resume it, or --restart to discard its "
                                   f"{_photos_taken(session)} photographs")
            shutil.rmtree(session)
        elif options.restart:
            shutil.rmtree(session)
    if not _is_session(session):
        session.mkdir(parents=True, exist_ok=True)
        for k, projector in enumerate(options.projectors):
            export_sequence(projector, _sequence_dir(session, k), checker_size=options.checker, area=options.area,
                            seed=options.seed, graycode=options.graycode, validation=options.validation)
            _photos_dir(session, k).mkdir()
        _write_session(session, {"format": SESSION_FORMAT, "version": 1, "settings": options.settings(),
                                 "opened": []})
    doc = _read_session(session)
    return doc, _photos_taken(session)


def run_live_capture(options: LiveCaptureOptions, progress: Progress | None = None,
                     cancel: Cancel | None = None) -> CaptureSet:
    """Capture the calibration sequence live (resuming a session of the same settings) into a new capture set;
    with several projectors, each projector's sequence while the others show black, into one set."""
    say, stop = progress or quiet, cancel or never
    validate(options, CaptureError)  # a bad device string fails before anything is written
    count = len(options.projectors)
    check_camera_device(options.device, count)  # so does a window (or frame file) per projector that is not there
    if count > 1 and options.rig is not None:
        raise CaptureError(f"a rig calibration (--rig) calibrates one projector; this rig has {count}: capture "
                           "without it and calibrate the capture set")
    check_replaceable(options.out, force=options.force, what="capture set", replaceable=is_capture_set,
                      inputs=(options.session, options.depth_path, options.rig),
                      error=CaptureError)
    with writer_lock(options.out):  # another run of this capture set (and its session) is refused before any work
        return _capture(options, say, stop, count)


def _capture(options: LiveCaptureOptions, say: Progress, stop: Cancel, count: int) -> CaptureSet:
    doc, done = open_session(options)
    session = options.session
    sequences = [load_sequence(_sequence_dir(session, k)) for k in range(count)]
    total = sum(len(seq.frames) for seq in sequences)
    if done:
        say(f"resuming the live session in {session}: {done} of {total} frames already captured", 0.0)
    missing = [(k, i, f) for k, seq in enumerate(sequences) for i, f in enumerate(seq.frames)
               if not _photo(session, i, k).is_file()]
    try:
        if missing:
            with open_camera_device(options.device, options.projector, others=options.others,
                                    progress=part(say, 0.0, 0.1, "live device: "),
                                    check_exposure=options.check_exposure) as device:
                doc["opened"].append({"device": options.device, **device.report.to_dict()})
                _write_session(session, doc)
                shown: list[Device] = [device] if count == 1 else [OneProjector(device, k) for k in range(count)]
                for n, (k, i, frame) in enumerate(missing):
                    if stop():
                        raise Cancelled("live capture was cancelled")
                    whose = f"projector {k + 1}'s " if count > 1 else ""
                    say(f"capturing {whose}frame {i + 1}/{len(sequences[k].frames)} ({frame['name']})",
                        0.1 + 0.8 * n / len(missing))
                    if frame["kind"] == "surface":
                        shot = device.capture_off()  # every projector black
                    else:
                        shot = shown[k].project(read_image(sequence_frame(sequences[k], frame)))
                    write_image(_photo(session, i, k), shot)
        say("importing the photographs (depth, exposure check)", 0.9)
        if count == 1:
            captures = run_import(ImportOptions(session / "sequence", session / "photos", options.out,
                                                encoding="linear", force=options.force, **options.photo_settings()),
                                  part(say, 0.9, 1.0))
        else:
            captures = _import_projectors(options, count, say)
    except Cancelled as exc:
        # however the stop came (this loop's check, or the job's at a progress report), the photographs taken so
        # far stay in the session folder, and the same command resumes from them
        raise Cancelled(f"{exc}: {_photos_taken(session)} of {total} frames are captured and kept in "
                        f"{session}; run the same command to resume", kept=True) from None
    shutil.rmtree(session, ignore_errors=True)
    say(f"capture set {options.out}: {total} frames" + (f" of {count} projectors" if count > 1 else ""), 1.0)
    return captures


def _import_projectors(options: LiveCaptureOptions, count: int, say: Progress) -> CaptureSet:
    """Each projector's photographs imported on its own (into the session folder; the depth with projector 1's),
    then combined into one capture set at ``options.out``."""
    session = options.session
    sets = []
    for k in range(count):
        settings = options.photo_settings()
        if k:
            settings["depth_path"] = None  # the depth is taken once, and stored once
        sets.append(run_import(ImportOptions(_sequence_dir(session, k), _photos_dir(session, k),
                                             session / f"imported_p{k + 1}", encoding="linear", force=True,
                                             **settings),
                               part(say, 0.9 + 0.08 * k / count, 0.9 + 0.08 * (k + 1) / count,
                                    f"projector {k + 1}: ")))
    return combine_projector_sets(sets, options.out, force=options.force,
                                  notes={"other_projectors": [cs.notes for cs in sets[1:]]},
                                  inputs=(options.depth_path,), progress=part(say, 0.98, 1.0, "combining: "))
