"""The live show step: frames of a video file, camera or stream compensated and shown as they arrive.

``procam live-show CAL --source SOURCE --device live:display=N[,camera=…]``.
The source is read in its own thread that keeps only its newest frame
(``live/source.py``); this loop, on the caller's thread, takes the newest
frame, solves it with the calibration's real-time solver
(:mod:`.realtime`), draws every projector's frame into its window and flips
them (``live/window.py``, one window per projector: ``display=1+2``), and
records how long the frame took from its arrival to the flip. The loop never
queues: a frame that arrives while the previous one is being solved replaces
it, and is counted as dropped.

Open or closed loop: without a camera in the device (``live:display=1``) the
show runs open loop (θ from the calibration's validation captures, as
``procam show``). With one (``live:camera=0,display=1``) the live device opens
as ``procam capture`` opens it (latency measured with a white flash), and every
:data:`FOLLOW_EVERY` seconds the newest camera frame is given to
:meth:`RealtimeSolver.follow` with the solve it shows (the one on screen a
measured latency before it arrived), which moves θ a small step towards it
(θ settles over seconds, so it does not flicker). A camera that stops
delivering leaves the show open loop, said once.

Bad input: a source that cannot be opened is refused before any window opens.
A source that stalls or ends is held on its last frame for ``hold`` seconds,
then black, and said; a file that ended then stops the run (its report says
so); a stream that comes back resumes. A frame of another size than the
source's first is fitted into the display area like any target, said once.
Esc in a window stops the show (the report says so); a cancel raises
:class:`Cancelled` (:class:`LiveShowCancelled`, with the report so far, once
the loop runs: Blender's Stop Live Show reports it); the windows always close.

A status line every :data:`STATUS_EVERY` second goes to ``progress`` and
``on_status``: frames in, shown, dropped, the solve's milliseconds and the
latency from arrival to flip (medians over the last second), frames per second.
:func:`latency_figures` turns a report into the median and 95th percentile of
that latency and the dropped count (``scripts/bench_live_show.py``, the tests).
"""

from __future__ import annotations

import time
import warnings
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from ..capture.format import srgb_to_linear
from ..errors import Cancelled, LiveError, ProCamError
from ..live.device import LiveDevice, LiveSpec, check_displays, open_windows
from ..live.source import FrameSource, linear_frame
from ..live.window import ProjectorWindow, WindowClosed
from ..options import option, same_option, validate
from ..progress import Cancel, Progress, never, part, quiet
from ..video import VideoReader
from . import calibrate as calibrate_step
from .projectors import JointStage
from .realtime import LEARN_MIN_FRAMES, REFINE_STEPS, RealtimeSolver
from .stage_c import StageC, StageCOptions, camera_lens_of

#: Seconds between two status lines, and between two camera frames given to the solver's θ (closed loop: at 10 a
#: second and the solver's step, θ covers 95 % of a change in about 3 s).
STATUS_EVERY, FOLLOW_EVERY = 1.0, 0.1
#: A source without a new frame for this long is said to stall (the hold starts from its last frame anyway).
STALL_S = 0.5
#: A camera without a new frame for this long is lost (the show goes on open loop).
CAMERA_LOST_S = 3.0
#: ``--range auto`` on a file fits one gain and offset to at most this many frames, evenly spread (as ``show``).
RANGE_SAMPLE = 32

DEVICE_HELP = ("live:display=N[,camera=SOURCE] — the projector window(s) as procam capture opens them (display=N, "
               "position=X:Y; several projectors display=1+2; displays are numbered from 0, as procam live-check "
               "--list-displays lists them); with camera=SOURCE θ follows the camera slowly "
               "(closed loop), without one the show runs open loop")


def _device(text: str) -> None:
    if LiveSpec.parse(text, camera_required=False).shoot:
        raise LiveError("live-show follows a streaming camera (camera=SOURCE) or runs open loop without one; a "
                        "shooting command (shoot=) takes seconds a photograph, too slow for a show")


def _seconds(value: float | None) -> None:
    if value is not None and not value > 0:
        raise LiveError(f"--duration must be a number of seconds > 0, got {value!r}")


@dataclass(frozen=True)
class LiveShowOptions:
    """What ``procam live-show`` asks for: the calibration, the source, the windows, and stage C's choices."""

    calibration: Path
    source: str = option(
        required=True, metavar="SOURCE", label="Source", prop="procam_live_source", subtype="FILE_PATH",
        help="a video file (played at its own frame rate), a camera index (0) or device path (/dev/video0), or a "
             "network stream URL (rtsp://…, http://…/stream.mjpg)")
    device: str = option(required=True, check=_device, help=DEVICE_HELP)
    range: str = same_option(StageCOptions, "range",
                             help="what the frames become before compensation: 'auto' fits one gain and offset, "
                                  "'bright' (or bright:PCT) an offset and a smooth gain field (to an even sample of "
                                  "a file's frames, or a camera's or stream's frames of the first second), "
                                  "'GAIN,OFFSET' gives them, 'none' (default) keeps them")
    effects: str = same_option(StageCOptions, "effects")
    diagnosis: Path | None = same_option(StageCOptions, "diagnosis")
    area: tuple[int, int, int, int] | None = same_option(StageCOptions, "area")
    surround: tuple[float, float, float] | None = same_option(StageCOptions, "surround")
    target_encoding: str = same_option(StageCOptions, "target_encoding",
                                       help="auto: 8-bit frames are sRGB and are linearised, 16-bit are linear")
    refine_steps: int = option(REFINE_STEPS, min=0, max=50, metavar="N", label="Refine Steps",
                               prop="procam_live_refine_steps",
                               help=f"refinement steps per frame after the approximate inverse (default "
                                    f"{REFINE_STEPS}: within 0.1 dB of the transport schedule's in the lab)")
    hold: float = option(2.0, min=0.0, max=3600.0, metavar="SECONDS", label="Hold", prop="procam_live_hold",
                         help="a source that stalls or ends: hold its last frame this long, then black (default 2)")
    # The sidebar's 0 stands for no limit (its blank); the command line refuses 0 (_seconds).
    correction: Path | None = option(
        None, metavar="FILE", label="Learned Correction", prop="procam_live_correction", subtype="FILE_PATH",
        blank="",
        help="with camera=: write the per-pixel correction learned while following the camera (each camera "
             "pixel's gain and offset against the model, from the frames shown) to FILE when the show ends (a file "
             "there is replaced); "
             "without a camera: start from the correction in FILE, learned so by an earlier show of this "
             "calibration and display area, instead of the validation captures' θ (default none)")
    duration: float | None = option(None, check=_seconds, metavar="SECONDS", label="Duration",
                                    prop="procam_live_duration", blank=0.0, min=0.0,
                                    help="stop after this many seconds (default: until the source ends, Esc in the "
                                         "window or Ctrl-C)")

    def stage_options(self) -> StageCOptions:
        """Stage C as ``procam show`` opens it for this show: open loop (the camera, if any, is this step's)."""
        return StageCOptions(range=self.range, effects=self.effects, diagnosis=self.diagnosis, area=self.area,
                             surround=self.surround, target_encoding=self.target_encoding)


@dataclass(frozen=True)
class ShownFrame:
    """One source frame that reached the windows: its number, when it arrived and was flipped, its solve's ms."""

    number: int
    arrived: float
    flipped: float
    solve_ms: float

    @property
    def latency_ms(self) -> float:
        return (self.flipped - self.arrived) * 1000.0


@dataclass(frozen=True)
class LiveStatus:
    """The status of the last second (counts since the start; milliseconds: medians over the last second)."""

    elapsed: float
    frames_in: int
    shown: int
    dropped: int
    solve_ms: float | None
    latency_ms: float | None
    fps: float

    @property
    def line(self) -> str:
        ms = lambda v: "–" if v is None else f"{v:.0f} ms"  # noqa: E731
        return (f"in {self.frames_in}, shown {self.shown}, dropped {self.dropped}, solve {ms(self.solve_ms)}, "
                f"latency {ms(self.latency_ms)}, {self.fps:.1f} fps")


def _median_p95(values: Sequence[float]) -> tuple[float | None, float | None]:
    if not values:
        return None, None
    a = np.asarray(values, dtype=np.float64)
    return float(np.median(a)), float(np.percentile(a, 95))


@dataclass
class LiveShowReport:
    """What a live show did: counts, the solve's and the latency's median and 95th percentile, the loop's rate,
    why it stopped and what it said (stalls, sizes, a lost camera)."""

    frames_in: int = 0
    dropped: int = 0
    seconds: float = 0.0
    stopped: str = ""
    closed_loop: bool = False
    follows: int = 0
    said: list[str] = field(default_factory=list)
    frames: list[ShownFrame] = field(default_factory=list)

    @property
    def shown(self) -> int:
        return len(self.frames)

    @property
    def solve_ms(self) -> tuple[float | None, float | None]:
        """Median and 95th percentile of the solve's milliseconds."""
        return _median_p95([f.solve_ms for f in self.frames])

    @property
    def latency_ms(self) -> tuple[float | None, float | None]:
        """Median and 95th percentile of the milliseconds from a frame's arrival to its flip."""
        return _median_p95([f.latency_ms for f in self.frames])

    @property
    def fps(self) -> float:
        """Frames shown per second, from the first flip to the last."""
        if len(self.frames) < 2:
            return 0.0
        span = self.frames[-1].flipped - self.frames[0].flipped
        return (len(self.frames) - 1) / span if span > 0 else 0.0

    def lines(self) -> list[str]:
        fmt = lambda v: "–" if v is None else f"{v:.1f}"  # noqa: E731
        (sm, sp), (lm, lp) = self.solve_ms, self.latency_ms
        loop = f"closed loop, θ followed the camera {self.follows} times" if self.closed_loop else "open loop"
        return [f"live show: {self.shown} frames shown of {self.frames_in} in, {self.dropped} dropped, "
                f"{self.seconds:.1f} s, {self.fps:.1f} fps ({loop})",
                f"solve {fmt(sm)} ms median, {fmt(sp)} ms p95; latency source → flip {fmt(lm)} ms median, "
                f"{fmt(lp)} ms p95",
                f"stopped: {self.stopped}"]


class LiveShowCancelled(Cancelled):
    """A live show cancelled while its loop ran: the report of what it showed until then."""

    def __init__(self, message: str, report: LiveShowReport) -> None:
        super().__init__(message)
        self.report = report


@dataclass(frozen=True)
class LatencyFigures:
    """Source → flip latency over a clip, for benchmarks: median and 95th percentile (ms), frames dropped."""

    median_ms: float | None
    p95_ms: float | None
    dropped: int
    shown: int
    frames_in: int
    fps: float


def latency_figures(report: LiveShowReport) -> LatencyFigures:
    """The latency figures of a live show's report (``scripts/bench_live_show.py``, the tests)."""
    med, p95 = report.latency_ms
    return LatencyFigures(med, p95, report.dropped, report.shown, report.frames_in, report.fps)


def clip_latency(calibration: Path, clip: Path, device: str, *, duration: float | None = None,
                 progress: Progress | None = None, **options: Any) -> tuple[LatencyFigures, LiveShowReport]:
    """Play ``clip`` live through ``calibration`` in the windows of ``device`` until it ends (or ``duration``):
    its latency figures and the whole report."""
    report = run_live_show(LiveShowOptions(calibration, str(clip), device, duration=duration, **options), progress)
    return latency_figures(report), report


# -- the solver the loop needs (steps/realtime.py) --------------------------------------------------------------

class Solved(Protocol):
    frames: list[np.ndarray]
    solve_ms: float


class Solver(Protocol):
    """What the loop asks of the real-time solver (:class:`.realtime.RealtimeSolver`)."""

    @property
    def camera_size(self) -> tuple[int, int]: ...

    def solve(self, image: np.ndarray) -> Any: ...

    def follow(self, capture: np.ndarray, shown: Any = None) -> None: ...

    def load_learned(self, path: Path, calibration_sha256: str) -> int: ...

    def save_learned(self, path: Path, calibration_sha256: str) -> Path | None: ...


def open_solver(stage: StageC | JointStage, refine_steps: int, say: Progress) -> Solver:
    """The calibration's real-time solver for ``stage`` (its stored approximate inverse, or built in memory)."""
    return RealtimeSolver.for_stage(stage, refine_steps=refine_steps, progress=say)


# -- the run ------------------------------------------------------------------------------------------------------

def run_live_show(options: LiveShowOptions, progress: Progress | None = None, cancel: Cancel | None = None, *,
                  on_status: Callable[[LiveStatus], None] | None = None,
                  solver_for: Callable[[StageC | JointStage, int, Progress], Solver] = open_solver
                  ) -> LiveShowReport:
    """Show ``options.source`` compensated in the projector window(s) as it arrives (module doc); the report.

    ``solver_for``: how the solver is made from the opened stage (the real-time solver; tests give a stand-in to
    time the loop's own mechanics)."""
    say = progress or quiet
    validate(options, LiveError)
    spec = LiveSpec.parse(options.device, camera_required=False)
    cal = calibrate_step.read(options.calibration)
    count = cal.projector_count
    check_displays(spec, count)
    sc = options.stage_options()
    sc.check()
    say(f"opening the source {options.source}", 0.0)
    source = FrameSource(options.source, encoding=options.target_encoding)  # refused before any window opens
    said: list[str] = []

    def noted(message: str, fraction: float) -> None:  # the solver's warnings (a frame's aspect) in the report
        if message.startswith("warning:") and message not in said:
            said.append(message)
        say(message, fraction)

    try:
        stage: StageC | JointStage = (JointStage(cal, sc, progress=part(say, 0.0, 0.0)) if count > 1 else
                                      StageC(cal, sc, progress=part(say, 0.0, 0.0)))
        with stage:
            if options.range == "auto" or str(options.range).strip().lower().startswith("bright"):
                _fix_range(stage, source, say)
            solver = solver_for(stage, options.refine_steps, noted)
            # a learned correction belongs to this calibration: its hash goes with it (hashed only when used)
            sha = calibrate_step.identity(options.calibration)["sha256"] if options.correction is not None else ""
            if options.correction is not None and spec.camera is None:
                areas = solver.load_learned(options.correction, sha)
                say(f"using the correction learned in {options.correction} ({areas} display area(s))", 0.0)
            report = _show(options, spec, cal, stage, solver, source, say, cancel or never, on_status, said)
            if options.correction is not None and spec.camera is not None:
                written = solver.save_learned(options.correction, sha)
                report.said.append(f"the correction learned while following the camera is in {written}" if written
                                   else f"too few camera frames were followed to learn a correction (at least "
                                        f"{LEARN_MIN_FRAMES}); nothing written to {options.correction}")
                say(report.said[-1], 1.0)
            return report
    finally:
        source.close()


def _fix_range(stage: StageC | JointStage, source: FrameSource, say: Progress) -> None:
    """``--range auto``: one map for the whole show (a per-frame fit would flicker), from an even sample of a
    file's frames, or from a camera's or stream's frames of the first second."""
    images: list[np.ndarray] = []
    if source.kind == "file":
        length = source.length or RANGE_SAMPLE
        picks = set(range(0, length, max(1, -(-length // RANGE_SAMPLE))))
        with VideoReader(source.text) as reader:
            for i in sorted(picks):
                try:
                    rgb = reader.read(i)
                except ProCamError:
                    break  # the container's count was an estimate
                images.append(linear_frame(np.ascontiguousarray(rgb[..., ::-1]), source.encoding))  # RGB → BGR
    else:
        end, last = time.perf_counter() + 1.0, 0
        while time.perf_counter() < end and len(images) < RANGE_SAMPLE:
            f = source.wait(last, 0.1)
            if f is not None:
                images.append(f.image)
                last = f.number
    say(f"range: fitting the show's map to {len(images)} frames of the source", 0.0)
    if stage.fix_range(images) is not None and stage.range_map is not None:
        say(f"range: frames mapped to {stage.range_map.describe()}", 0.0)


def _camera_image(spec: LiveSpec, image: np.ndarray, lens: Any, adapter: Any) -> np.ndarray:
    """A camera frame as the solver's θ reads it: linear, the calibration's lens taken out, the effect models'
    camera undone (as stage C's device pipeline does to a capture)."""
    img = srgb_to_linear(image) if spec.encoding == "srgb" else np.asarray(image, np.float32)
    if lens is not None:
        img = lens.image(img)
    if adapter is not None:
        img = adapter.camera_to_light(img)
    return np.asarray(img, np.float32)


def _show(options: LiveShowOptions, spec: LiveSpec, cal: Any, stage: StageC | JointStage, solver: Solver,
          source: FrameSource, say: Progress, cancel: Cancel, on_status: Callable[[LiveStatus], None] | None,
          said: list[str]) -> LiveShowReport:
    """The windows (and camera) opened, the loop run, the windows closed whatever happens."""
    device: LiveDevice | None = None
    windows: list[ProjectorWindow] = []
    try:
        if spec.camera is not None:
            device = LiveDevice(spec, cal.rig.projector, others=cal.rig.others, check_exposure=False,
                                progress=part(say, 0.0, 0.0, "live device: "))
            windows = device.windows
            want = tuple(cal.rig.camera.intrinsics.size)
            if device.camera_size != want:
                raise LiveError(f"the camera delivers {device.camera_size[0]}×{device.camera_size[1]} frames but "
                                f"the calibration's camera is {want[0]}×{want[1]}: set the camera to that size "
                                f"(size={want[0]}x{want[1]} in the device) or drop camera= for the open loop")
        else:
            windows = open_windows(spec, (cal.rig.projector, *cal.rig.others), say, title="ProCam live show")
        loop = _Loop(options, spec, stage, solver, source, windows, device, say, on_status,
                     lens=camera_lens_of(cal) if device is not None else None, said=said)
        return loop.run(cancel)
    finally:
        if device is not None:
            device.close()  # its windows with it
        else:
            for w in windows:
                w.close()


class _Loop:
    """The frame loop of one live show (module doc), with its counts."""

    def __init__(self, options: LiveShowOptions, spec: LiveSpec, stage: StageC | JointStage, solver: Solver,
                 source: FrameSource, windows: list[ProjectorWindow], device: LiveDevice | None, say: Progress,
                 on_status: Callable[[LiveStatus], None] | None, *, lens: Any, said: list[str]) -> None:
        self.options, self.spec, self.solver, self.source = options, spec, solver, source
        self.windows, self.device, self.say, self.on_status = windows, device, say, on_status
        self.lens = lens
        self.adapter = stage.adapter if isinstance(stage, StageC) else None
        self.report = LiveShowReport(closed_loop=device is not None, said=said)
        self._said: set[str] = set(said)
        #: (flip time, solve) of the last seconds: which solve a camera frame shows
        self.flips: deque[tuple[float, Any]] = deque(maxlen=256)
        self.black = [np.zeros((w.size[1], w.size[0], 3), np.float32) for w in windows]

    def tell(self, message: str, fraction: float = 0.0) -> None:
        """Say ``message`` once (a stall, a size, a lost camera): the report keeps it."""
        if message in self._said:
            return
        self._said.add(message)
        self.report.said.append(message)
        self.say(message, fraction)

    def _flip(self, frames: Sequence[np.ndarray]) -> float:
        for window, frame in zip(self.windows, frames):
            window.put(frame)
        return max(window.flip() for window in self.windows)

    def run(self, cancel: Cancel) -> LiveShowReport:
        o, source, report = self.options, self.source, self.report
        t0 = time.perf_counter()
        source.start()
        last_arrival, last_status, last_follow = t0, t0, t0
        status_from = 0  # the first frame of the current second in report.frames
        first_size, stalled, black = source.size, False, False
        first_flip: float | None = None
        camera_seen = t0
        try:
            while True:
                now = time.perf_counter()
                if cancel():
                    raise Cancelled(f"live show cancelled after {report.shown} frames shown")
                if o.duration is not None and now - t0 >= o.duration:
                    report.stopped = f"after {o.duration:g} s (--duration)"
                    break
                frame = source.wait(0, 0.01)
                now = time.perf_counter()
                if frame is None:
                    idle = now - last_arrival
                    if not stalled and (source.ended or idle >= STALL_S):
                        stalled = True
                        what = "the video ended" if source.ended else "the source stalls (no new frame)"
                        self.tell(f"{what}: holding its last frame for {o.hold:g} s, then black")
                    if stalled and not black and idle >= o.hold:
                        self._flip(self.black)
                        self.flips.append((time.perf_counter(), None))  # black: no solve to follow
                        black = True
                        self.tell("the video ended: black after the hold" if source.ended else
                                  f"the source stalled for {o.hold:g} s: black until it resumes")
                    if source.ended and black:
                        report.stopped = "the video ended"
                        break
                    for window in self.windows:
                        window.poll()
                else:
                    if stalled:
                        self.say(f"the source resumed after {now - last_arrival:.1f} s", 0.0)
                        report.said.append(f"the source resumed after {now - last_arrival:.1f} s")
                        stalled = black = False
                    size = (frame.image.shape[1], frame.image.shape[0])
                    if size != first_size:
                        self.tell(f"the source's frames are now {size[0]}×{size[1]} (they were {first_size[0]}×"
                                  f"{first_size[1]}): scaled into the display area")
                    with warnings.catch_warnings(record=True) as caught:
                        warnings.simplefilter("always")
                        out = self.solver.solve(frame.image)
                    for w in caught:
                        self.tell(f"warning: {w.message}")
                    flipped = self._flip(out.frames)
                    first_flip = first_flip or flipped
                    self.flips.append((flipped, out))
                    report.frames.append(ShownFrame(frame.number, frame.arrived, flipped, float(out.solve_ms)))
                    last_arrival = frame.arrived
                    now = time.perf_counter()
                if self.device is not None and self.device.camera is not None and first_flip is not None \
                        and now - last_follow >= FOLLOW_EVERY:
                    last_follow = now
                    camera_seen = self._follow(first_flip, camera_seen, now)
                if now - last_status >= STATUS_EVERY:
                    recent = report.frames[status_from:]
                    status = LiveStatus(now - t0, source.frames_in, report.shown, source.dropped,
                                        _median_p95([f.solve_ms for f in recent])[0],
                                        _median_p95([f.latency_ms for f in recent])[0],
                                        len(recent) / (now - last_status))
                    status_from, last_status = report.shown, now
                    self.say(status.line, min(1.0, (now - t0) / o.duration) if o.duration else 0.0)
                    if self.on_status is not None:
                        self.on_status(status)
        except WindowClosed:
            report.stopped = "Esc in the projector window"
        except Cancelled as exc:  # the report so far goes with it (completed by the finally below)
            raise LiveShowCancelled(str(exc), report) from exc
        finally:
            report.seconds = time.perf_counter() - t0
            report.frames_in, report.dropped = source.frames_in, source.dropped
        self.say(f"live show stopped: {report.stopped}", 1.0)
        return report

    def _shown_at(self, moment: float) -> Any:
        """The solve on screen at ``moment`` (None: none yet, or black)."""
        before = [out for t, out in self.flips if t <= moment]
        return before[-1] if before else None

    def _follow(self, first_flip: float, camera_seen: float, now: float) -> float:
        """Give the solver's θ the newest camera frame that shows one solve alone, with that solve; a camera that
        stopped delivering is closed and the show goes on open loop. Returns when the camera last delivered."""
        device = self.device
        assert device is not None and device.camera is not None
        wait = device.latency_s + device.camera.frame_period()  # a frame arriving this long after a flip shows it
        try:
            got = device.camera.stamped_after(max(first_flip + wait, camera_seen))
        except LiveError as exc:
            got, lost = [], str(exc)
        else:
            lost = f"no frame for {CAMERA_LOST_S:.0f} s" if not got and now - camera_seen > CAMERA_LOST_S else ""
        if lost:
            self.tell(f"the camera was lost ({lost}): the show goes on open loop")
            device.camera.close()
            device.camera = None
            return camera_seen
        for stamp, image in reversed(got):
            # The camera sees the screen one latency late: the frame shows the solve on screen then (with a video
            # the next one may mix in over one camera frame; consecutive frames are close and θ's step small).
            shown = self._shown_at(stamp - device.latency_s)
            if shown is not None:
                self.solver.follow(_camera_image(self.spec, image, self.lens, self.adapter), shown)
                self.report.follows += 1
                break
        return got[-1][0] if got else camera_seen


__all__ = ["LatencyFigures", "LiveShowCancelled", "LiveShowOptions", "LiveShowReport", "LiveStatus", "ShownFrame",
           "clip_latency", "latency_figures", "run_live_show"]
