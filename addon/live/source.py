"""A live show's frame source: a video file, a camera or a network stream, read in its own thread, newest frame only.

``SOURCE`` is a video file (played at its own frame rate, not as fast as it
decodes), a camera index (``0``) or device path (``/dev/video2``), or a
network stream URL (``rtsp://…``, ``http://…/stream.mjpg``: what OpenCV's
FFmpeg reads). A thread reads it and keeps **only the newest frame**: a live
show that falls behind must show the present, never work off a queue, so a
frame that arrives before the previous one was taken overwrites it and is
counted as dropped (:attr:`FrameSource.dropped`). Each frame is stamped when it
arrived (``time.perf_counter``), from which the show measures its latency.

Frames are converted here, off the show's thread, to what stage C reads: linear
float H×W×3 in [0, 1]; 8-bit frames are sRGB-encoded (as ``show`` decodes
8-bit video and images; a lookup table, not the curve per pixel), unless the
encoding says linear; 16-bit frames are linear.

A camera or stream that stops delivering is reopened every :data:`RETRY_S`
seconds until it comes back (a stall the show holds through, then resumes); a
file that ends sets :attr:`FrameSource.ended`.
"""

from __future__ import annotations

import stat
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..capture.format import srgb_to_linear
from ..errors import LiveError

#: Seconds to wait for the first frame after opening (network streams take a while to start).
OPEN_TIMEOUT = 10.0
#: Failed reads in a row after which a camera or stream counts as stopped, and is reopened this often (seconds).
FAILED_READS, RETRY_S = 20, 1.0
#: A file whose container gives no usable frame rate plays at this one.
DEFAULT_FPS = 30.0

_SRGB_LUT = srgb_to_linear(np.arange(256, dtype=np.float32) / 255.0)


class SourceError(LiveError):
    """A live show's source that cannot be opened or read."""


@dataclass
class Frame:
    """One frame of the source: its number (1, 2, … in arrival order), when it arrived, and its image as OpenCV
    decoded it, linearised the first time :attr:`image` is asked for: the frames a show drops (a source faster
    than the solve) are never converted, which kept a core's fifth busy at 1280×960 and 30 fps."""

    number: int
    arrived: float
    raw: np.ndarray
    encoding: str = "auto"
    _image: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def image(self) -> np.ndarray:
        """Linear RGB float32 H×W×3 in [0, 1]."""
        if self._image is None:
            self._image = linear_frame(self.raw, self.encoding)
        return self._image


def parse_source(text: str) -> tuple[str, int | str]:
    """``(kind, what OpenCV opens)`` from what the user typed: kind ``file``, ``camera`` or ``stream``."""
    s = str(text).strip()
    if not s:
        raise SourceError("--source is empty: give a video file, a camera index (0), a device path (/dev/video0) "
                          "or a stream URL (rtsp://…, http://…/stream.mjpg)")
    if s.isdigit():
        return "camera", int(s)
    if "://" in s:
        return "stream", s
    p = Path(s)
    try:
        mode = p.stat().st_mode
    except OSError:
        raise SourceError(f"source {s!r} is neither a file that exists, a camera index (0, 1 …) nor a stream URL "
                          "(rtsp://…, http://…/stream.mjpg)") from None
    if stat.S_ISCHR(mode):
        return "camera", s
    if not stat.S_ISREG(mode):
        raise SourceError(f"source {s!r} is a folder or special file, not a video file or camera device")
    return "file", s


def linear_frame(img: np.ndarray, encoding: str = "auto") -> np.ndarray:
    """An OpenCV frame (BGR or grey, 8- or 16-bit) as linear RGB float32 H×W×3 in [0, 1]."""
    import cv2  # not at the top: Blender registers the extension without loading OpenCV

    if img.ndim == 2:
        img = img[..., None]
    if img.dtype == np.uint8 and img.shape[2] in (3, 4):
        # OpenCV's own channel swap and table lookup: 7 ms for a 1280×960 frame where NumPy's indexing of the
        # reversed channels took 34 (the source's thread runs it on every frame the source delivers).
        rgb = cv2.cvtColor(img, cv2.COLOR_BGR2RGB if img.shape[2] == 3 else cv2.COLOR_BGRA2RGB)
        if encoding == "linear":
            return rgb.astype(np.float32) * np.float32(1.0 / 255.0)
        return cv2.LUT(rgb, _SRGB_LUT.reshape(1, 256))
    rgb = img[..., 2::-1] if img.shape[2] >= 3 else np.repeat(img[..., :1], 3, axis=2)
    if rgb.dtype == np.uint8:
        if encoding == "linear":
            return np.ascontiguousarray(rgb, dtype=np.float32) / np.float32(255.0)
        return _SRGB_LUT[rgb]
    if rgb.dtype == np.uint16:
        return np.ascontiguousarray(rgb, dtype=np.float32) / np.float32(65535.0)
    return np.clip(np.ascontiguousarray(rgb, dtype=np.float32), 0.0, 1.0)


class FrameSource:
    """An open source whose newest frame a thread keeps (module doc). Use as a context manager, or close it."""

    def __init__(self, text: str, *, encoding: str = "auto", open_timeout: float = OPEN_TIMEOUT) -> None:
        self.text = str(text)
        self.kind, self._what = parse_source(text)
        self.encoding = encoding
        self._cond = threading.Condition()
        self._newest: Frame | None = None
        self._taken = 0  # the number of the last frame handed out
        self._count = 0  # frames delivered since the source opened (their numbers)
        self.frames_in = 0
        self.dropped = 0
        self.ended = False
        self.failure: str | None = None
        self.reopened = 0
        self._stop = threading.Event()
        self._go = threading.Event()  # a file waits after its first frame until the show starts playing it
        self._cap = self._open()
        fps = float(self._cap.get(self._cv2.CAP_PROP_FPS) or 0.0)
        #: the file's own frame rate (None for cameras and streams: they deliver at theirs)
        self.fps: float | None = (fps if 1.0 <= fps <= 1000.0 else DEFAULT_FPS) if self.kind == "file" else None
        count = int(self._cap.get(self._cv2.CAP_PROP_FRAME_COUNT) or 0)
        #: a file's frame count as its container lists it (an estimate for some containers); None: not a file
        self.length: int | None = count if self.kind == "file" and count > 0 else None
        self._thread = threading.Thread(target=self._read, name="procam-source", daemon=True)
        self._thread.start()
        first = self.wait(0, open_timeout)
        if first is None:
            why = self.failure or f"no frame within {open_timeout:.0f} s"
            self.close()
            raise SourceError(f"source {self.text!r} opened but delivered no frame ({why}): "
                              + ("the file holds no frame FFmpeg decodes; convert it to .mp4 (H.264)"
                                 if self.kind == "file" else "is it streaming?"))
        self._taken = 0  # the first frame stays to be taken by the show
        #: the first frame's size (width, height)
        self.size = (first.image.shape[1], first.image.shape[0])

    def start(self) -> None:
        """The show starts: a file plays from its first frame on, and the counts start from zero (a camera's or
        stream's frames that arrived while the show was loading are not counted as dropped)."""
        with self._cond:
            waiting = self._newest is not None and self._newest.number > self._taken
            if waiting:
                assert self._newest is not None
                # it arrives for the show now: its latency counts from here, not from the source's opening
                self._newest = replace(self._newest, arrived=time.perf_counter())
            self.frames_in, self.dropped = int(waiting), 0
        self._go.set()

    @property
    def _cv2(self) -> Any:
        import cv2

        return cv2

    def _open(self) -> Any:
        cv2 = self._cv2
        api = cv2.CAP_FFMPEG if self.kind in ("file", "stream") else cv2.CAP_ANY
        cap = cv2.VideoCapture(self._what, api)
        if not cap.isOpened():
            cap.release()
            hint = {"file": "it is a video FFmpeg in OpenCV reads (.mp4 H.264, .avi, .mkv …) and not damaged",
                    "stream": "the URL is reachable from this machine and streams (try it in a browser or VLC)",
                    "camera": "the camera exists, no other program uses it, and this user may open it (on Linux: "
                              "group 'video')"}[self.kind]
            raise SourceError(f"cannot open the source {self.text!r} through OpenCV VideoCapture: check that {hint}")
        return cap

    # -- the reading thread ----------------------------------------------------------------------------------------

    def _publish(self, image: np.ndarray) -> None:
        with self._cond:
            self._count += 1
            self.frames_in += 1
            if self._newest is not None and self._newest.number > self._taken:
                self.dropped += 1  # overwritten before the show took it
            self._newest = Frame(self._count, time.perf_counter(), image, self.encoding)
            self._cond.notify_all()

    def _read(self) -> None:
        period = 1.0 / self.fps if self.fps else 0.0
        due = 0.0
        failures = 0
        while not self._stop.is_set():
            cap = self._cap
            if cap is None:  # a camera or stream being reopened
                if self._stop.wait(RETRY_S):
                    return
                try:
                    self._cap = self._open()
                    self.reopened += 1
                except SourceError:
                    pass
                continue
            try:
                ok, img = cap.read()
            except self._cv2.error as exc:  # on some broken streams
                ok, img = False, None
                self.failure = f"{type(exc).__name__}: {exc}"
            if not ok or img is None:
                if self.kind == "file":
                    with self._cond:
                        self.ended = True
                        self._cond.notify_all()
                    return
                failures += 1
                if failures >= FAILED_READS:
                    self.failure = self.failure or "it stopped delivering frames"
                    cap.release()
                    self._cap, failures = None, 0
                else:
                    time.sleep(0.01)
                continue
            failures = 0
            image = img  # linearised when the show takes it (Frame.image)
            if period:  # a file plays at its own rate: each frame arrives when it is due
                if not self._count:
                    self._publish(image)  # the first frame at once, checked when the source opens
                    while not self._go.wait(0.05):
                        if self._stop.is_set():
                            return
                    due = time.perf_counter()
                    continue
                due += period
                wait = due - time.perf_counter()
                if wait > 0 and self._stop.wait(wait):
                    return
                if wait < -1.0:
                    due = time.perf_counter()  # decoding fell far behind: play on from now, not catch up
            self._publish(image)

    # -- the show's side -------------------------------------------------------------------------------------------

    def take(self) -> Frame | None:
        """The newest frame if it was not taken yet, else None (never waits)."""
        with self._cond:
            return self._take()

    def _take(self) -> Frame | None:
        f = self._newest
        if f is None or f.number <= self._taken:
            return None
        self._taken = f.number
        return f

    def wait(self, after: int, timeout: float) -> Frame | None:
        """The newest frame once one newer than number ``after`` (and not taken) arrived, waiting up to
        ``timeout`` seconds; None when none came (or the file ended)."""
        deadline = time.perf_counter() + timeout
        with self._cond:
            while True:
                f = self._newest
                if f is not None and f.number > max(after, self._taken):
                    return self._take()
                left = deadline - time.perf_counter()
                if left <= 0 or self.ended:
                    return None
                self._cond.wait(left)

    def close(self) -> None:
        self._stop.set()
        self._go.set()
        with self._cond:
            self._cond.notify_all()
        thread = getattr(self, "_thread", None)
        if thread is not None and thread.is_alive():
            thread.join(timeout=2.0)
        cap, self._cap = self._cap, None
        if cap is not None and (thread is None or not thread.is_alive()):
            cap.release()  # a thread stuck in a blocking read keeps its capture; it is a daemon

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["Frame", "FrameSource", "SourceError", "linear_frame", "parse_source"]
