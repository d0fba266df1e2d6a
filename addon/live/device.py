"""The live device: the projector window and the camera client, with the latency between them measured.

``--device live:camera=SOURCE,display=N`` (or ``position=X:Y``) and options:

* ``average=N`` frames per capture, or ``noise=σ``: as many frames as bring the
  camera's measured per-frame noise down to σ (linear units), at most 64;
* ``encoding=srgb|linear``: how the camera encodes 8-bit frames (webcams and
  network cameras: sRGB);
* ``latency=auto|SECONDS``: measured at start by default;
* ``size=WxH``: ask the camera for a resolution;
* ``shoot='COMMAND … {out} …'`` instead of ``camera=``: a command takes each photograph (a stills camera over
  gphoto2, a phone app's tool; ``live/shoot.py``), with ``timeout=SECONDS`` (default 60), ``encoding=auto`` (8-bit
  files sRGB, 16-bit and float linear, as import reads photographs) and ``suffix=jpg`` (what ``{out}`` ends with).

Several projectors: ``display=1+2`` names one display per projector, in rig order (or ``position=X:Y+X:Y``, one
desktop position per projector). Each projector gets its own borderless window of its native size, all open at
once in this process (``window.py``); :meth:`LiveDevice.project_all` draws every window, flips them one after the
other and captures once, after the last flip plus the latency. Fewer displays than projectors, more displays
than projectors, or one display named twice is refused before any window opens. ``project`` (one frame) is
refused on a device of several projectors, as the lab's device refuses it: which projector it would mean, and
what the others show, is for the caller to say (``capture.devices.OneProjector``: one projector, the others
black).

Latency: the window shows black, then white, and the time from the flip to the
first frame that arrives brighter is one measurement; the largest of three is
kept. With several projectors each measurement lights one projector (the others
black), in turn, at least once each, so the wait covers the slowest of them.
Every capture then waits for frames that arrived later than the (last) flip
plus that latency plus one camera frame (the frame being exposed while the
image changed is a mix of both), so a capture never holds the previous pattern.

Locked exposure: the camera is asked for manual exposure, white balance and
focus; then white is captured right after it shows and again after
:data:`ADAPT_S` seconds. A camera still on auto moves between the two (it
adapts to the new brightness); any change beyond the capture check's tolerance
(``capture/exposure.py``) refuses the device with a message to lock exposure.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..capture.command import DEFAULT_TIMEOUT, check_suffix, parse_command, split_spec
from ..capture.devices import ShownTogether
from ..capture.exposure import ADAPT_S, COLOUR_TOLERANCE, GAIN_TOLERANCE, SEEN_STEP
from ..capture.format import srgb_to_linear
from ..errors import LiveError
from ..progress import Progress, quiet
from ..rig.model import Projector
from .camera import CameraClient, parse_source
from .window import ProjectorWindow

#: The most frames one capture averages.
MAX_AVERAGE = 64
#: A latency measurement gives up after this many seconds without seeing the white frame.
LATENCY_TIMEOUT = 5.0


@dataclass(frozen=True)
class LiveSpec:
    """What ``live:…`` asks for."""

    #: None only where the command runs without a camera (``procam live-show``, open loop)
    camera: int | str | None
    display: int | None = None
    position: tuple[int, int] | None = None
    average: int | None = None
    noise: float | None = None
    encoding: str = "srgb"
    latency: float | None = None  # None: measured
    size: tuple[int, int] | None = None
    #: every display of ``display=1+2`` (one per projector, in rig order); () when one display or a position
    displays: tuple[int, ...] = ()
    #: every position of ``position=X:Y+X:Y`` (one per projector, in rig order); () when one position or a display
    positions: tuple[tuple[int, int], ...] = ()
    #: ``shoot='…'``: the command that takes a photograph, split into arguments (``live/shoot.py``); () with a camera
    shoot: tuple[str, ...] = ()
    #: seconds the shooting command may take
    timeout: float = DEFAULT_TIMEOUT
    #: the file type of the shooting command's photograph (what ``{out}`` ends with)
    suffix: str = "jpg"

    @property
    def windows(self) -> int:
        """How many projector windows this names (one per display or position)."""
        return len(self.displays) or len(self.positions) or 1

    def placements(self) -> list[tuple[int | None, tuple[int, int] | None]]:
        """``(display, position)`` of each window, in rig order (one of the two None)."""
        if self.displays:
            return [(d, None) for d in self.displays]
        if self.positions:
            return [(None, p) for p in self.positions]
        return [(self.display, self.position)]

    @staticmethod
    def parse(text: str, *, camera_required: bool = True) -> LiveSpec:
        """``camera=SOURCE,display=N|position=X:Y[,average=N|noise=σ][,encoding=…][,latency=…][,size=WxH]``;
        several projectors: ``display=N+N…`` or ``position=X:Y+X:Y…``. ``camera_required=False``: a spec without
        a camera is taken (``procam live-show``'s open loop)."""
        known = ("camera", "display", "position", "average", "noise", "encoding", "latency", "size", "shoot",
                 "timeout", "suffix")
        values = split_spec(text, "live:", known, "live:camera=SOURCE,display=N (see `procam live-check --help`)",
                            error=LiveError)
        shoot = parse_command(values["shoot"], "live device: shoot", ("{out}",), error=LiveError) \
            if "shoot" in values else ()
        if shoot and "camera" in values:
            raise LiveError("live device: give a streaming camera (camera=SOURCE) or a shooting command "
                            "(shoot='…{out}…'), not both")
        if shoot:
            for key, why in (("noise", "give average=N photographs instead"),
                             ("size", "the camera's own settings decide a photograph's size")):
                if key in values:
                    raise LiveError(f"live device: {key}= is for a streaming camera, not a shooting command; {why}")
        else:
            for key in ("timeout", "suffix"):
                if key in values:
                    raise LiveError(f"live device: {key}= is the shooting command's (shoot='…'); a streaming camera "
                                    "has none")
        camera_required = camera_required and not shoot
        if "camera" not in values and camera_required:
            raise LiveError(f"live device: say which camera, e.g. live:camera=0,display=1 (got {text!r}); only "
                            "`procam live-show` runs without one (open loop)")
        def number(key: str, read: Callable[[str], Any], what: str) -> Any:
            try:
                return read(values[key]) if key in values else None
            except ValueError:
                raise LiveError(f"live device: {key}= takes {what}, got {values[key]!r}") from None

        displays = number("display", lambda v: tuple(int(n) for n in v.split("+")), "whole numbers (display=1+2)") \
            or ()
        display = displays[0] if displays else None
        positions = number("position", lambda v: tuple(tuple(int(n) for n in one.split(":")) for one in v.split("+")),
                           "whole numbers (position=X:Y, several as X:Y+X:Y)") or ()
        position = positions[0] if positions else None
        average = number("average", int, "a whole number of frames")
        noise = number("noise", float, "a number (linear units)")
        latency = None if values.get("latency", "auto") == "auto" else \
            number("latency", float, "a number of seconds or auto")
        size = number("size", lambda v: tuple(int(n) for n in v.lower().split("x")), "whole numbers (WIDTHxHEIGHT)")
        if display is None and position is None:
            display = 0
        if any(len(p) != 2 for p in positions) or size is not None and len(size) != 2:
            raise LiveError("live device: position is X:Y and size is WIDTHxHEIGHT")
        if average is not None and noise is not None:
            raise LiveError("live device: give average=N or noise=σ, not both")
        if average is not None and not 1 <= average <= MAX_AVERAGE:
            raise LiveError(f"live device: average must be 1 … {MAX_AVERAGE} frames, got {average}")
        if noise is not None and not noise > 0:
            raise LiveError(f"live device: noise must be a positive level (linear units), got {noise}")
        if latency is not None and not 0 <= latency < 10:
            raise LiveError(f"live device: latency must be 0 … 10 s or auto, got {latency}")
        encoding = values.get("encoding", "auto" if shoot else "srgb")
        if encoding not in (("auto", "srgb", "linear") if shoot else ("srgb", "linear")):
            raise LiveError(f"live device: encoding must be {'auto, ' if shoot else ''}srgb or linear, got "
                            f"{encoding!r}")
        timeout = number("timeout", float, "a number of seconds")
        timeout = DEFAULT_TIMEOUT if timeout is None else timeout
        if not 0 < timeout <= 3600:
            raise LiveError(f"live device: timeout must be 0 … 3600 s, got {timeout:g}")
        if displays and positions:
            raise LiveError("live device: give displays (display=1+2) or desktop positions (position=X:Y+X:Y), "
                            "not both")
        for named, what in ((displays, "display"), (positions, "position")):
            twice = sorted({":".join(map(str, v)) if isinstance(v, tuple) else str(v)
                            for v in named if named.count(v) > 1})
            if twice:
                raise LiveError(f"live device: {what} {', '.join(twice)} is named twice in {text!r}; give each "
                                f"projector its own {what}")
        camera = parse_source(values["camera"]) if "camera" in values else None
        return LiveSpec(camera, display, position, average, noise, encoding, latency, size,
                        displays if len(displays) > 1 else (),
                        tuple((int(x), int(y)) for x, y in positions) if len(positions) > 1 else (),
                        shoot, timeout, check_suffix(values.get("suffix", "jpg"), "live device", LiveError))


@dataclass(frozen=True)
class LiveReport:
    """What the live device measured when it opened."""

    latency_s: float
    latencies_s: tuple[float, ...]
    camera_frame_s: float
    noise: float
    average: int
    locked: dict[str, bool]
    exposure_drift: float
    colour_drift: float

    def lines(self) -> list[str]:
        took = ", ".join(k for k, v in self.locked.items() if v) or "none"
        measured = ", ".join(f"{v * 1000:.0f}" for v in self.latencies_s)
        return [f"latency {self.latency_s * 1000:.0f} ms (measured {measured} ms)",
                f"camera frame {self.camera_frame_s * 1000:.1f} ms; noise {self.noise:.4f} per frame, "
                f"{self.average} frame(s) averaged per capture",
                f"manual settings accepted by the camera backend: {took}; white drift after {ADAPT_S:.0f} s: "
                f"exposure {self.exposure_drift * 100:.1f} %, colour {self.colour_drift * 100:.1f} %"]

    def to_dict(self) -> dict[str, object]:
        return {"latency_s": self.latency_s, "latencies_s": list(self.latencies_s),
                "camera_frame_s": self.camera_frame_s, "noise_per_frame": self.noise, "average": self.average,
                "manual_settings_accepted": self.locked, "exposure_drift": self.exposure_drift,
                "colour_drift": self.colour_drift}


def check_displays(spec: LiveSpec, projectors: int) -> None:
    """Refuse, before any window opens, a live rig whose windows do not fit its projectors: one display (or
    position) per projector, in rig order."""
    windows = spec.windows
    if windows < projectors:
        raise LiveError(f"this rig has {projectors} projectors but the live device names {windows} display(s); "
                        f"give one display per projector in rig order, e.g. display="
                        f"{'+'.join(str(k + 1) for k in range(projectors))} (or one desktop position each, "
                        "position=X:Y+X:Y)")
    if windows > projectors:
        named = "+".join(map(str, spec.displays)) if spec.displays else \
            "+".join(f"{x}:{y}" for x, y in spec.positions)
        rig = "a rig of one projector" if projectors == 1 else f"a rig of {projectors} projectors"
        raise LiveError(f"the live device names {windows} displays ({named}) for {rig}; give one display per "
                        "projector")


def open_windows(spec: LiveSpec, projectors: Sequence[Projector], say: Progress,
                 title: str = "ProCam projector") -> list[ProjectorWindow]:
    """One projector window per projector, placed as ``spec`` says (all closed again if one cannot open)."""
    windows: list[ProjectorWindow] = []
    many = len(projectors) > 1
    try:
        for k, (proj, (display, position)) in enumerate(zip(projectors, spec.placements())):
            say(f"opening projector {k + 1}'s window" if many else "opening the projector window", 0.0)
            windows.append(ProjectorWindow(proj.intrinsics.size, display=display, position=position,
                                           title=f"{title} {k + 1}" if many else title,
                                           who=f"projector {k + 1}" if many else "the projector"))
    except BaseException:
        for window in windows:
            window.close()
        raise
    return windows


class LiveDevice(ShownTogether):
    """Real projectors (one :class:`ProjectorWindow` each) and a real camera (a :class:`CameraClient`).

    ``others``: projectors 2…N of a rig of several, each shown in the window of its own display (``spec``'s
    ``display=1+2``); :meth:`project_all` shows them all at once and captures once, when all of them have been
    shown for the measured latency."""

    error, what = LiveError, "this live device"

    def __init__(self, spec: LiveSpec | str, projector: Projector, *, others: Sequence[Projector] = (),
                 progress: Progress | None = None, check_exposure: bool = True,
                 camera_size: tuple[int, int] | None = None) -> None:
        """``camera_size``: the calibration's camera; a camera delivering frames of another size is refused as
        soon as it connects, before the latency and exposure are measured (seconds)."""
        say = progress or quiet
        self.spec = spec if isinstance(spec, LiveSpec) else LiveSpec.parse(spec)
        check_displays(self.spec, 1 + len(others))
        if self.spec.camera is None:
            raise LiveError("the live device needs a camera: live:camera=SOURCE,display=N")
        self.projector = projector
        self.others = tuple(others)
        self.windows: list[ProjectorWindow] = []
        self.camera: CameraClient | None = None
        try:
            self.windows = open_windows(self.spec, self.projectors, say)
            say("opening the camera", 0.1)
            self.camera = CameraClient(self.spec.camera, size=self.spec.size)
            got = self.camera.size
            if camera_size is not None and tuple(got) != tuple(camera_size):
                raise LiveError(f"the device's camera delivers {got[0]}×{got[1]} frames but the calibration's camera "
                                f"is {camera_size[0]}×{camera_size[1]}: set the camera to the resolution the capture "
                                "set was taken at (live: size=WxH), or calibrate with captures from this camera")
            locked = self.camera.lock()
            self.latency_s, latencies = self._latency(say)
            self.average, noise = self._averaging()
            drift = self._exposure_drift(say) if check_exposure else (0.0, 0.0)
            self.report = LiveReport(self.latency_s, latencies, self.camera.frame_period(), noise, self.average,
                                     locked, *drift)
            if check_exposure and (drift[0] > GAIN_TOLERANCE or drift[1] > COLOUR_TOLERANCE):
                what = "exposure" if drift[0] > GAIN_TOLERANCE else "white balance"
                raise LiveError(f"the camera's {what} is not locked: the same white frame captured {ADAPT_S:.0f} s "
                                f"later differs by {max(drift) * 100:.0f} %. Switch the camera to manual exposure, "
                                "gain and white balance (its own app or web page for network cameras), then start "
                                "again")
        except BaseException:
            self.close()
            raise

    @property
    def camera_size(self) -> tuple[int, int] | None:
        """The camera's frame size (width, height), checked against a calibration before stage C starts."""
        return self.camera.size if self.camera is not None else None

    # -- capture -------------------------------------------------------------------------------------------------

    def _show(self, frames: Sequence[np.ndarray]) -> float:
        """Every window's frame drawn, then the windows flipped one after the other: the last flip's time, after
        which every window shows its frame."""
        if not self.windows:
            raise LiveError("the live device is closed")
        for window, frame in zip(self.windows, frames):
            window.put(frame)
        return max(window.flip() for window in self.windows)

    def _settled_after(self, shown: float) -> float:
        """The moment after which every camera frame shows what the windows flipped at ``shown``."""
        assert self.camera is not None
        return shown + self.latency_s + self.camera.frame_period()

    def _linear(self, frames: list[np.ndarray]) -> np.ndarray:
        mean = np.mean(frames, axis=0, dtype=np.float64).astype(np.float32)
        return srgb_to_linear(mean) if self.spec.encoding == "srgb" else mean

    def _capture(self, frames: Sequence[np.ndarray]) -> np.ndarray:
        assert self.camera is not None
        shown = self._show(frames)
        return self._linear(self.camera.frames_after(self._settled_after(shown), self.average,
                                                     timeout=self.latency_s + 5.0))

    # -- measurements at start -----------------------------------------------------------------------------------

    def _latency(self, say: Progress) -> tuple[float, tuple[float, ...]]:
        assert self.camera is not None
        if self.spec.latency is not None:
            return float(self.spec.latency), (float(self.spec.latency),)
        found: list[float] = []
        count = len(self.projectors)
        rounds = max(3, count)  # every projector lit at least once: the slowest one's latency is waited out
        for k in range(rounds):
            lit = k % count
            say(f"measuring the camera latency ({k + 1}/{rounds})", 0.2 + 0.3 * k / rounds)
            self._show(self._flat(0.0))
            time.sleep(0.3 + 1.5 * (max(found) if found else 0.5))  # until black has surely come through
            dark = float(np.mean(self.camera.frames_after(time.perf_counter() - 0.05, 1)[0]))
            t_white = self._show(self._flat(1.0, lit))
            seen, t = None, t_white
            while seen is None and time.perf_counter() < t_white + LATENCY_TIMEOUT:
                for stamp, img in self.camera.stamped_after(t):
                    t = stamp
                    if float(np.mean(img)) > dark + SEEN_STEP:
                        seen = stamp
                        break
                time.sleep(0.002)
            if seen is None:
                which = f"projector {lit + 1}" if count > 1 else "the projector"
                window = f"projector {lit + 1}'s window" if count > 1 else "the window"
                raise LiveError(f"the camera did not see {which}: a full white frame raised its picture's "
                                f"mean by less than 2 % within {LATENCY_TIMEOUT:.0f} s. Point the camera at the "
                                f"projected image, check that the projector shows {window} (display index), and "
                                "open the lens")
            found.append(seen - t_white)
        return max(found), tuple(found)

    def _averaging(self) -> tuple[int, float]:
        """Frames per capture, and the per-frame noise (from two runs of frames of the same white image)."""
        assert self.camera is not None
        shown = self._show(self._flat(1.0))
        frames = self.camera.frames_after(self._settled_after(shown), 8, timeout=self.latency_s + 5.0)
        stack = np.asarray(frames, dtype=np.float64)
        # Temporal standard deviation per pixel, median over the picture: the shot and read noise of one frame.
        noise = float(np.median(stack.std(axis=0, ddof=1)))
        if self.spec.average is not None:
            return self.spec.average, noise
        if self.spec.noise is not None:
            return min(MAX_AVERAGE, max(1, math.ceil((noise / self.spec.noise) ** 2))), noise
        return 1, noise

    def _exposure_drift(self, say: Progress) -> tuple[float, float]:
        say("checking that the camera's exposure and white balance are locked", 0.8)
        first = self._capture(self._flat(1.0))
        time.sleep(ADAPT_S)
        second = self._capture(self._flat(1.0))
        lit = first.mean(axis=2) > 0.05 * max(float(first.mean(axis=2).max()), 1e-6)
        if lit.sum() < 16:
            return 0.0, 0.0
        a = first[lit].mean(axis=0).astype(np.float64) + 1e-6
        b = second[lit].mean(axis=0).astype(np.float64) + 1e-6
        ratio = np.log(b / a)
        return float(abs(ratio.mean())), float(np.max(np.abs(ratio - ratio.mean())))

    def close(self) -> None:
        camera, self.camera = getattr(self, "camera", None), None
        windows, self.windows = getattr(self, "windows", []), []
        if camera is not None:
            camera.close()
        for window in windows:
            window.close()


__all__ = ["LiveDevice", "LiveReport", "LiveSpec", "check_displays", "open_windows"]
