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
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..capture.sequence import export_sequence, load_sequence, sequence_frame
from ..capture.format import CaptureSet, is_capture_set
from ..errors import Cancelled, CaptureError, LiveError
from ..imageio import read_image, write_atomic_bytes, write_image
from ..live.device import LiveDevice, LiveSpec
from ..options import option, same_option, validate
from ..outputs import check_replaceable
from ..progress import Cancel, Progress, never, part, quiet
from ..rig.model import Projector, projector_intrinsics_from_throw
from .capture import ImportOptions, PatternsOptions, PhotoSettings, ProjectorSheet, run_import

SESSION_FORMAT = "procam-live-session"
SESSION_MANIFEST = "session.json"


DEVICE_HELP = ("live:camera=SOURCE,display=N — SOURCE a camera index, a device path or a URL (http://…mjpg, "
               "rtsp://…); display=N covers display N (at the projector's native size), position=X:Y puts the "
               "window at desktop coordinates instead; options: average=N or noise=σ (frames per capture), "
               "encoding=srgb|linear, latency=auto|SECONDS, size=WxH")


@dataclass(frozen=True)
class LiveCaptureOptions(PhotoSettings):
    """What ``procam capture`` asks for: the live device, the pattern sequence, and how to import it."""

    device: str = option(required=True, check=LiveSpec.parse, help=DEVICE_HELP)
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

    @property
    def session(self) -> Path:
        return self.out.with_name(self.out.name + ".session")

    def settings(self) -> dict[str, Any]:
        """What a resumed session must share with the one it continues (the device may differ: a new port…)."""
        return {"projector": self.projector.to_dict(), "checker": self.checker, "area": self.area,
                "graycode": self.graycode, "validation": self.validation, "seed": self.seed}


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


def _photo(session: Path, i: int) -> Path:
    """Where frame ``i``'s photograph is kept in a session folder."""
    return session / "photos" / f"{i:04d}.png"


def _photos_taken(session: Path) -> int:
    return len(list((session / "photos").glob("*.png")))


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
                raise CaptureError(f"{session} holds a live session with other settings (projector, patterns or "
                                   "seed): give the same settings to resume it, or --restart to discard its "
                                   f"{_photos_taken(session)} photographs")
            shutil.rmtree(session)
        elif options.restart:
            shutil.rmtree(session)
    if not _is_session(session):
        session.mkdir(parents=True, exist_ok=True)
        export_sequence(options.projector, session / "sequence", checker_size=options.checker, area=options.area,
                        seed=options.seed, graycode=options.graycode, validation=options.validation)
        (session / "photos").mkdir()
        _write_session(session, {"format": SESSION_FORMAT, "version": 1, "settings": options.settings(),
                                 "opened": []})
    doc = _read_session(session)
    return doc, _photos_taken(session)


def run_live_capture(options: LiveCaptureOptions, progress: Progress | None = None,
                     cancel: Cancel | None = None) -> CaptureSet:
    """Capture the calibration sequence live (resuming a session of the same settings) into a new capture set."""
    say, stop = progress or quiet, cancel or never
    validate(options, CaptureError)  # a bad device string fails before anything is written
    check_replaceable(options.out, force=options.force, what="capture set", replaceable=is_capture_set,
                      inputs=(options.session, options.depth_path, options.rig),
                      error=CaptureError)
    doc, done = open_session(options)
    session = options.session
    sequence = load_sequence(session / "sequence")
    frames = sequence.frames
    if done:
        say(f"resuming the live session in {session}: {done} of {len(frames)} frames already captured", 0.0)
    missing = [(i, f) for i, f in enumerate(frames) if not _photo(session, i).is_file()]
    try:
        if missing:
            with LiveDevice(options.device, options.projector, progress=part(say, 0.0, 0.1, "live device: "),
                            check_exposure=options.check_exposure) as device:
                doc["opened"].append({"device": options.device, **device.report.to_dict()})
                _write_session(session, doc)
                for n, (i, frame) in enumerate(missing):
                    if stop():
                        raise Cancelled("live capture was cancelled")
                    say(f"capturing frame {i + 1}/{len(frames)} ({frame['name']})", 0.1 + 0.8 * n / len(missing))
                    if frame["kind"] == "surface":
                        shot = device.capture_off()
                    else:
                        shot = device.project(read_image(sequence_frame(sequence, frame)))
                    write_image(_photo(session, i), shot)
        say("importing the photographs (depth, exposure check)", 0.9)
        captures = run_import(ImportOptions(session / "sequence", session / "photos", options.out, encoding="linear",
                                            force=options.force, **options.photo_settings()),
                              part(say, 0.9, 1.0))
    except Cancelled as exc:
        # however the stop came (this loop's check, or the job's at a progress report), the photographs taken so
        # far stay in the session folder, and the same command resumes from them
        raise Cancelled(f"{exc}: {_photos_taken(session)} of {len(frames)} frames are captured and kept in "
                        f"{session}; run the same command to resume", kept=True) from None
    shutil.rmtree(session, ignore_errors=True)
    say(f"capture set {options.out}: {len(frames)} frames", 1.0)
    return captures
