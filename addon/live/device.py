"""The live device: the projector window and the camera client, with the latency between them measured.

``--device live:camera=SOURCE,display=N`` (or ``position=X:Y``) and options:

* ``average=N`` frames per capture, or ``noise=σ``: as many frames as bring the
  camera's measured per-frame noise down to σ (linear units), at most 64;
* ``encoding=srgb|linear``: how the camera encodes 8-bit frames (webcams and
  network cameras: sRGB);
* ``latency=auto|SECONDS``: measured at start by default;
* ``size=WxH``: ask the camera for a resolution.

Several projectors: ``display=1+2`` names one display per projector, in rig order. Showing several projector
windows at once is not implemented yet: a rig of several projectors is refused with what to do (fewer displays
than projectors first), and so is a list of displays for a rig of one.

Latency: the window shows black, then white, and the time from the flip to the
first frame that arrives brighter is one measurement; the largest of three is
kept. Every capture then waits for frames that arrived later than the flip plus
that latency plus one camera frame (the frame being exposed while the image
changed is a mix of both), so a capture never holds the previous pattern.

Locked exposure: the camera is asked for manual exposure, white balance and
focus; then white is captured right after it shows and again after
:data:`ADAPT_S` seconds. A camera still on auto moves between the two (it
adapts to the new brightness); any change beyond the capture check's tolerance
(``capture/exposure.py``) refuses the device with a message to lock exposure.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..capture.devices import Device
from ..capture.exposure import COLOUR_TOLERANCE, GAIN_TOLERANCE
from ..capture.format import srgb_to_linear
from ..errors import LiveError
from ..progress import Progress, quiet
from ..rig.model import Projector
from .camera import CameraClient, parse_source
from .window import ProjectorWindow

#: The most frames one capture averages.
MAX_AVERAGE = 64
#: Seconds between the two white captures of the exposure-lock check (auto exposure settles in about one second).
ADAPT_S = 1.0
#: A latency measurement gives up after this many seconds without seeing the white frame.
LATENCY_TIMEOUT = 5.0
#: The camera "sees" the white frame once its picture's mean rises this much above black's (linear units).
SEEN_STEP = 0.02


@dataclass(frozen=True)
class LiveSpec:
    """What ``live:…`` asks for."""

    camera: int | str
    display: int | None = None
    position: tuple[int, int] | None = None
    average: int | None = None
    noise: float | None = None
    encoding: str = "srgb"
    latency: float | None = None  # None: measured
    size: tuple[int, int] | None = None
    #: every display of ``display=1+2`` (one per projector, in rig order); () when one display or a position
    displays: tuple[int, ...] = ()

    @staticmethod
    def parse(text: str) -> "LiveSpec":
        """``camera=SOURCE,display=N|position=X:Y[,average=N|noise=σ][,encoding=…][,latency=…][,size=WxH]``."""
        body = text[5:] if text.startswith("live:") else text
        known = ("camera", "display", "position", "average", "noise", "encoding", "latency", "size")
        values: dict[str, str] = {}
        last = None
        for token in body.split(","):
            key, eq, value = token.partition("=")
            if eq and key.strip() in known:
                last = key.strip()
                if last in values:
                    raise LiveError(f"live device: {last} is given twice in {text!r}")
                values[last] = value.strip()
            elif last is not None:  # a comma inside the previous value (URLs may hold one)
                values[last] += "," + token
            else:
                raise LiveError(f"live device: expected key=value, got {token!r} in {text!r}; the form is "
                                "live:camera=SOURCE,display=N (see `procam live-check --help`)")
        if "camera" not in values:
            raise LiveError(f"live device: say which camera, e.g. live:camera=0,display=1 (got {text!r})")
        try:
            displays = tuple(int(v) for v in values["display"].split("+")) if "display" in values else ()
            display = displays[0] if displays else None
            position = tuple(int(v) for v in values["position"].split(":")) if "position" in values else None
            average = int(values["average"]) if "average" in values else None
            noise = float(values["noise"]) if "noise" in values else None
            latency = None if values.get("latency", "auto") == "auto" else float(values["latency"])
            size = tuple(int(v) for v in values["size"].lower().split("x")) if "size" in values else None
        except ValueError as exc:
            raise LiveError(f"live device: a value in {text!r} is not a number ({exc})") from None
        if display is None and position is None:
            display = 0
        if position is not None and len(position) != 2 or size is not None and len(size) != 2:
            raise LiveError("live device: position is X:Y and size is WIDTHxHEIGHT")
        if average is not None and noise is not None:
            raise LiveError("live device: give average=N or noise=σ, not both")
        if average is not None and not 1 <= average <= MAX_AVERAGE:
            raise LiveError(f"live device: average must be 1 … {MAX_AVERAGE} frames, got {average}")
        if noise is not None and not noise > 0:
            raise LiveError(f"live device: noise must be a positive level (linear units), got {noise}")
        if latency is not None and not 0 <= latency < 10:
            raise LiveError(f"live device: latency must be 0 … 10 s or auto, got {latency}")
        encoding = values.get("encoding", "srgb")
        if encoding not in ("srgb", "linear"):
            raise LiveError(f"live device: encoding must be srgb or linear, got {encoding!r}")
        if len(displays) > 1 and position is not None:
            raise LiveError("live device: give several displays (display=1+2) or one position, not both")
        return LiveSpec(parse_source(values["camera"]), display, position, average, noise, encoding, latency, size,
                        displays if len(displays) > 1 else ())


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
    """Refuse, before any window opens, a live rig whose displays do not fit its projectors: one display per
    projector, and (not implemented yet) more than one projector."""
    displays = len(spec.displays) or 1
    if projectors > 1 and displays < projectors:
        raise LiveError(f"this rig has {projectors} projectors but the live device names {displays} display(s); "
                        f"give one display per projector in rig order, e.g. display="
                        f"{'+'.join(str(k + 1) for k in range(projectors))}")
    if projectors > 1:
        raise LiveError(f"showing {projectors} projectors at once through the live device (one window per display) "
                        "is not implemented yet: capture each projector's sequence on its own, the others showing "
                        "black, and import the captures (procam import-captures)")
    if displays > 1:
        raise LiveError(f"the live device names {displays} displays (display={'+'.join(map(str, spec.displays))}) "
                        "for a rig of one projector; give its one display")


class LiveDevice(Device):
    """A real projector (a :class:`ProjectorWindow`) and a real camera (a :class:`CameraClient`)."""

    def __init__(self, spec: LiveSpec | str, projector: Projector, *, others: Sequence[Projector] = (),
                 progress: Progress | None = None, check_exposure: bool = True) -> None:
        say = progress or quiet
        self.spec = spec if isinstance(spec, LiveSpec) else LiveSpec.parse(spec)
        check_displays(self.spec, 1 + len(others))
        self.projector = projector
        self.window: ProjectorWindow | None = None
        self.camera: CameraClient | None = None
        try:
            say("opening the projector window", 0.0)
            self.window = ProjectorWindow(projector.intrinsics.size, display=self.spec.display,
                                          position=self.spec.position)
            say("opening the camera", 0.1)
            self.camera = CameraClient(self.spec.camera, size=self.spec.size)
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

    def _show(self, frame: np.ndarray) -> float:
        assert self.window is not None
        return self.window.show(frame)

    def _settled_after(self, shown: float) -> float:
        """The moment after which every camera frame shows what the window flipped at ``shown``."""
        assert self.camera is not None
        return shown + self.latency_s + self.camera.frame_period()

    def _linear(self, frames: list[np.ndarray]) -> np.ndarray:
        mean = np.mean(frames, axis=0, dtype=np.float64).astype(np.float32)
        return srgb_to_linear(mean) if self.spec.encoding == "srgb" else mean

    def project(self, frame: np.ndarray) -> np.ndarray:
        assert self.camera is not None
        shown = self._show(self.check_frame(frame))
        return self._linear(self.camera.frames_after(self._settled_after(shown), self.average,
                                                     timeout=self.latency_s + 5.0))

    # -- measurements at start -----------------------------------------------------------------------------------

    def _flat(self, value: float) -> np.ndarray:
        w, h = self.projector.intrinsics.size
        return np.full((h, w, 3), value, dtype=np.float32)

    def _latency(self, say: Progress) -> tuple[float, tuple[float, ...]]:
        assert self.camera is not None
        if self.spec.latency is not None:
            return float(self.spec.latency), (float(self.spec.latency),)
        found: list[float] = []
        for k in range(3):
            say(f"measuring the camera latency ({k + 1}/3)", 0.2 + 0.1 * k)
            self._show(self._flat(0.0))
            time.sleep(0.3 + 1.5 * (max(found) if found else 0.5))  # until black has surely come through
            dark = float(np.mean(self.camera.frames_after(time.perf_counter() - 0.05, 1)[0]))
            t_white = self._show(self._flat(1.0))
            seen, t = None, t_white
            while seen is None and time.perf_counter() < t_white + LATENCY_TIMEOUT:
                for stamp, img in self.camera.stamped_after(t):
                    t = stamp
                    if float(np.mean(img)) > dark + SEEN_STEP:
                        seen = stamp
                        break
                time.sleep(0.002)
            if seen is None:
                raise LiveError(f"the camera did not see the projector: a full white frame raised its picture's "
                                f"mean by less than 2 % within {LATENCY_TIMEOUT:.0f} s. Point the camera at the "
                                "projected image, check that the projector shows the window (display index), and "
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
        first = self.project(self._flat(1.0))
        time.sleep(ADAPT_S)
        second = self.project(self._flat(1.0))
        lit = first.mean(axis=2) > 0.05 * max(float(first.mean(axis=2).max()), 1e-6)
        if lit.sum() < 16:
            return 0.0, 0.0
        a = first[lit].mean(axis=0).astype(np.float64) + 1e-6
        b = second[lit].mean(axis=0).astype(np.float64) + 1e-6
        ratio = np.log(b / a)
        return float(abs(ratio.mean())), float(np.max(np.abs(ratio - ratio.mean())))

    def close(self) -> None:
        camera, self.camera = getattr(self, "camera", None), None
        window, self.window = getattr(self, "window", None), None
        if camera is not None:
            camera.close()
        if window is not None:
            window.close()


__all__ = ["LiveDevice", "LiveReport", "LiveSpec", "check_displays"]
