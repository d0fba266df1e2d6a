"""The projector window and a shooting command: ``live:display=N,shoot='gphoto2 … --filename {out}'``.

For stills cameras that cannot stream (a DSLR or mirrorless camera over gphoto2, a phone app that saves a file):
each capture shows the frame in the projector window(s) (``window.py``, as the live device does), waits for the
display to settle, then runs the command (``capture/command.py``: no shell, ``{out}`` a new path in a private
folder, a timeout, the command's error output in the message) and reads the photograph it wrote.

Latency-safe ordering: the command starts only after every window has flipped and ``latency`` seconds have passed
(default :data:`SETTLE_S`; a projector's input lag is 16–150 ms, more with frame interpolation on). A stills
camera's latency cannot be measured as a stream's is (a photograph takes seconds), so it is given, not measured;
and because ``{out}`` never names a file that existed before the command started, a photograph read was taken by a
command that started after the frame was on the projector. The windows are polled while the command runs (Esc
still stops the session).

Exposure: at open, black, white and white again after :data:`~.device.ADAPT_S` s are photographed; a camera that
does not see the projector, or whose exposure or white balance moved, is refused; every later photograph's EXIF
exposure is compared with the first one's (``capture/command.py``).

:func:`open_camera_device` opens whichever device a spec names: the live device with a streaming camera, this one
with a shooting command, or the command device that shows and photographs (``command:run=…``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from ..capture.command import CommandDevice, CommandSpec, PhotoCommand, ShotReport, check_shots
from ..capture.devices import ShownTogether
from ..errors import CaptureError, LiveError
from ..progress import Progress, quiet
from ..rig.model import Projector
from .device import ADAPT_S, LiveDevice, LiveSpec, check_displays, open_windows
from .window import ProjectorWindow

#: Seconds between the last window's flip and the shooting command's start, when ``latency=`` is not given.
SETTLE_S = 0.25


class ShootDevice(ShownTogether):
    """Projector windows (one per projector) and a command that takes each photograph."""

    error, what = LiveError, "this live device"

    def __init__(self, spec: LiveSpec | str, projector: Projector, *, others: Sequence[Projector] = (),
                 progress: Progress | None = None, check_exposure: bool = True) -> None:
        say = progress or quiet
        self.spec = spec if isinstance(spec, LiveSpec) else LiveSpec.parse(spec)
        if not self.spec.shoot:
            raise LiveError("this device takes photographs with a command: live:display=N,shoot='… {out} …'")
        check_displays(self.spec, 1 + len(others))
        self.projector, self.others = projector, tuple(others)
        self.latency_s = SETTLE_S if self.spec.latency is None else float(self.spec.latency)
        self.average = self.spec.average or 1
        self.windows: list[ProjectorWindow] = []
        self._command: PhotoCommand | None = PhotoCommand(self.spec.shoot, timeout=self.spec.timeout,
                                                          encoding=self.spec.encoding, suffix=self.spec.suffix,
                                                          what="the shooting command")
        try:
            self.windows = open_windows(self.spec, self.projectors, say)
            white, contrast, noise, *drift = check_shots(lambda v: self._capture(self._flat(v)),
                                                         check_exposure=check_exposure, adapt_s=ADAPT_S, say=say)
            seconds = float(np.median(self._command.seconds)) if self._command.seconds else 0.0
            self.report = ShotReport(self.latency_s, seconds, contrast, noise, self.average, *drift)
        except BaseException:
            self.close()
            raise

    def _settle(self, shown: float) -> None:
        """Wait until ``latency_s`` after the flip at ``shown``, handling the windows' events meanwhile."""
        while True:
            for window in self.windows:
                window.poll()
            left = shown + self.latency_s - time.perf_counter()
            if left <= 0:
                return
            time.sleep(min(left, 0.02))

    def _capture(self, frames: Sequence[np.ndarray]) -> np.ndarray:
        if not self.windows or self._command is None:
            raise LiveError("the live device is closed")
        for window, frame in zip(self.windows, frames):
            window.put(frame)
        shown = max(window.flip() for window in self.windows)
        shots = []
        for _ in range(self.average):
            self._settle(shown)
            shots.append(self._command.take())
        image = np.mean(shots, axis=0).astype(np.float32) if len(shots) > 1 else shots[0]
        return self._same_size(image, self._command.shots - 1)

    def close(self) -> None:
        command, self._command = getattr(self, "_command", None), None
        windows, self.windows = getattr(self, "windows", []), []
        if command is not None:
            command.close()
        for window in windows:
            window.close()


CAMERA_DEVICE_FORM = ("live:camera=SOURCE,display=N (a streaming camera), live:display=N,shoot='COMMAND … {out}' "
                      "(a command takes each photograph) or command:run='COMMAND … {frame} … {out}' (a command shows "
                      "and photographs each frame)")


def parse_camera_device(text: str) -> LiveSpec | CommandSpec:
    """A live or command device spec, checked before any window opens or command runs."""
    if text.startswith("command:"):
        return CommandSpec.parse(text)
    if text.startswith("live:"):
        return LiveSpec.parse(text)
    raise CaptureError(f"the device must be {CAMERA_DEVICE_FORM}; got {text!r}")


def check_camera_device(text: str, projectors: int) -> None:
    """Refuse, before anything opens, a spec whose windows or frame files do not fit ``projectors``."""
    spec = parse_camera_device(text)
    if isinstance(spec, CommandSpec):
        spec.check_projectors(projectors)
    else:
        check_displays(spec, projectors)


def open_camera_device(text: str, projector: Projector, *, others: Sequence[Projector] = (),
                       progress: Progress | None = None, check_exposure: bool = True,
                       camera_size: tuple[int, int] | None = None) -> LiveDevice | ShootDevice | CommandDevice:
    """The device ``text`` names: :class:`LiveDevice` (``camera=``), :class:`ShootDevice` (``shoot=``) or
    :class:`CommandDevice` (``command:``). Each has a ``report`` (``lines()``, ``to_dict()``) and ``camera_size``.
    ``camera_size``: the calibration's camera, which a live camera is checked against as soon as it connects (the
    others deliver their first frame only when they capture)."""
    spec = parse_camera_device(text)
    if isinstance(spec, CommandSpec):
        return CommandDevice(spec, projector, others=others, progress=progress, check_exposure=check_exposure)
    if spec.shoot:
        return ShootDevice(spec, projector, others=others, progress=progress, check_exposure=check_exposure)
    return LiveDevice(spec, projector, others=others, progress=progress, check_exposure=check_exposure,
                      camera_size=camera_size)


__all__ = ["CAMERA_DEVICE_FORM", "SETTLE_S", "ShootDevice", "check_camera_device", "open_camera_device",
           "parse_camera_device"]
