"""The live camera: an OpenCV ``VideoCapture`` client read by a thread that stamps every frame on arrival.

A source is a camera index (``0``), a device path (``/dev/video2``) or a URL
(``http://…/stream.mjpg`` from a network camera or a phone used as a webcam,
``rtsp://…``). Network streams and most drivers queue frames; reading only when
a capture is wanted returns whatever waited in the queue, often the previous
pattern. So a thread reads every frame as it arrives and keeps the recent ones
with their arrival time, and a capture asks for frames that *arrived after* a
given moment (:meth:`CameraClient.frames_after`): the live device makes that
moment "shown + measured latency" (``device.py``).

Exposure, gain, white balance and focus are switched to manual where the
backend takes it (:meth:`CameraClient.lock`); whether it took is then checked
from the pictures themselves, because many backends accept a setting and
ignore it and network streams take none.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from pathlib import Path

import cv2
import numpy as np

from ..errors import LiveError

#: Frames kept (at 30 fps, 4 s): more than the slowest latency and averaging need together.
KEPT = 120
#: Seconds to wait for the first frame after opening (network cameras take a while to start streaming).
OPEN_TIMEOUT = 10.0


def parse_source(text: str) -> int | str:
    """A camera index, a device path or a URL, from what the user typed."""
    s = str(text).strip()
    if s.isdigit():
        return int(s)
    if "://" in s:
        return s
    if Path(s).exists():
        return s
    raise LiveError(f"camera {s!r} is neither an index (0, 1 …), a device path that exists (/dev/video0) nor a "
                    "URL (http://…/video.mjpg, rtsp://…)")


class CameraClient:
    """An open camera whose frames a background thread reads and time-stamps (float32 BGR→RGB in [0, 1])."""

    def __init__(self, source: int | str, *, size: tuple[int, int] | None = None) -> None:
        self.source = source
        api = cv2.CAP_FFMPEG if isinstance(source, str) and "://" in source else cv2.CAP_ANY
        self._cap = cv2.VideoCapture(source, api)
        if not self._cap.isOpened():
            self._cap.release()
            hint = ("the URL is reachable from this machine and streams MJPEG/H.264 (try it in a browser or VLC)"
                    if isinstance(source, str) and "://" in source else
                    "the camera exists, no other program uses it, and this user may open it (on Linux: group "
                    "'video')")
            raise LiveError(f"cannot open camera {source!r} through OpenCV VideoCapture: check that {hint}")
        if size is not None:
            self._cap.set(cv2.CAP_PROP_FRAME_WIDTH, int(size[0]))
            self._cap.set(cv2.CAP_PROP_FRAME_HEIGHT, int(size[1]))
        self._frames: deque[tuple[float, np.ndarray]] = deque(maxlen=KEPT)
        self._cond = threading.Condition()
        self._stop = False
        self._failure: str | None = None
        self._thread = threading.Thread(target=self._read, name="procam-camera", daemon=True)
        self._thread.start()
        try:
            first = self.frames_after(time.perf_counter() - 1.0, 1, timeout=OPEN_TIMEOUT)[0]
        except LiveError:
            self.close()
            raise
        self.size = (first.shape[1], first.shape[0])

    def _read(self) -> None:
        failures = 0
        while not self._stop:
            ok, img = self._cap.read()
            stamp = time.perf_counter()
            if not ok or img is None:
                failures += 1
                if failures >= 50:
                    with self._cond:
                        self._failure = "the camera stopped delivering frames"
                        self._cond.notify_all()
                    return
                time.sleep(0.01)
                continue
            failures = 0
            scale = 65535.0 if img.dtype == np.uint16 else 255.0
            f = img.astype(np.float32) / scale
            f = np.repeat(f[..., None], 3, axis=2) if f.ndim == 2 else f[..., 2::-1]
            with self._cond:
                self._frames.append((stamp, np.ascontiguousarray(f)))
                self._cond.notify_all()

    def stamped_after(self, t: float) -> list[tuple[float, np.ndarray]]:
        """``(arrival time, frame)`` of the kept frames that arrived after ``t``, without waiting."""
        with self._cond:
            if self._failure:
                raise LiveError(f"{self._failure} (camera {self.source!r})")
            return [(stamp, f) for stamp, f in self._frames if stamp > t]

    def frames_after(self, t: float, count: int, *, timeout: float = 5.0) -> list[np.ndarray]:
        """The first ``count`` frames that arrived after ``t`` (``time.perf_counter``), waiting for them."""
        deadline = time.perf_counter() + timeout
        with self._cond:
            while True:
                if self._failure:
                    raise LiveError(f"{self._failure} (camera {self.source!r})")
                got = [f for stamp, f in self._frames if stamp > t]
                if len(got) >= count:
                    return got[:count]
                left = deadline - time.perf_counter()
                if left <= 0:
                    raise LiveError(f"camera {self.source!r} delivered {len(got)} of {count} frames within "
                                    f"{timeout:.1f} s: is it still streaming?")
                self._cond.wait(left)

    def frame_period(self, window: int = 30) -> float:
        """Median seconds between the last ``window`` frames (the camera's real rate, not what it claims)."""
        with self._cond:
            stamps = [s for s, _ in list(self._frames)[-window:]]
        if len(stamps) < 3:
            return 1.0 / 30.0
        return float(np.median(np.diff(stamps)))

    def lock(self) -> dict[str, bool]:
        """Ask the backend for manual exposure, white balance and focus; which requests it accepted.

        Accepted is not obeyed: the live device checks the pictures (``device.py``)."""
        wanted = {"exposure": (cv2.CAP_PROP_AUTO_EXPOSURE, (1.0, 0.25)),  # V4L2 manual = 1, DirectShow = 0.25
                  "white balance": (cv2.CAP_PROP_AUTO_WB, (0.0,)),
                  "focus": (cv2.CAP_PROP_AUTOFOCUS, (0.0,))}
        accepted = {}
        for name, (prop, values) in wanted.items():
            accepted[name] = any(self._cap.set(prop, v) for v in values)
        return accepted

    def close(self) -> None:
        self._stop = True
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self._cap.release()


__all__ = ["CameraClient", "parse_source"]
