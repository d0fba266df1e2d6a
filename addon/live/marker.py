"""The marker measurement of a live show without hardware: a dark clip with bright marker frames, and a watcher
that films the projector window off the screen to see when each marker appears.

A live show's report says when each source frame arrived and when its frame
was flipped (``steps/live_show.py``). What reached the screen is what the
watcher sees: it grabs the window's screen area as fast as it can (``mss``, a
dev requirement, as the loopback camera's) and notes when the area's mean
first rises above :data:`SEEN_LEVEL` after being dark. With the marker frames'
arrival times this gives the latency from the source to the screen
(:func:`marker_latencies`), which the tests and ``scripts/bench_live_show.py``
compare with the report's arrival → flip figures.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..errors import LiveError

#: The window's mean 8-bit level above which a marker is seen, and below which the screen is dark again.
SEEN_LEVEL, DARK_LEVEL = 100.0, 40.0


def write_marker_clip(path: Path, size: tuple[int, int], frames: int, *, fps: float = 30.0,
                      markers: Sequence[int] = (), dark: int = 12, bright: int = 255) -> Path:
    """An MJPEG ``.avi`` of ``frames`` dark frames (8-bit level ``dark``) where the frames numbered in ``markers``
    (0-based) are ``bright`` white."""
    import cv2

    w, h = size
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), float(fps), (int(w), int(h)))
    if not writer.isOpened():
        raise LiveError(f"cannot write the marker clip {path} (OpenCV's MJPG writer)")
    try:
        wanted = set(markers)
        for i in range(frames):
            level = bright if i in wanted else dark
            writer.write(np.full((h, w, 3), level, np.uint8))
    finally:
        writer.release()
    return path


class ScreenWatch:
    """Grabs a screen area in a thread and stamps each time its mean 8-bit level rises above ``seen`` after being
    below ``dark`` (``time.perf_counter``). A context manager."""

    def __init__(self, region: tuple[int, int, int, int], *, seen: float = SEEN_LEVEL,
                 dark: float = DARK_LEVEL) -> None:
        try:
            import mss  # a dev requirement, as the loopback camera's
        except ImportError:
            raise LiveError("the screen watch needs the mss package (pip install mss)") from None
        self._mss = mss
        self.region, self.seen, self.dark = region, seen, dark
        self.onsets: list[float] = []
        self.grabs = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="procam-screen-watch", daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        left, top, w, h = self.region
        area = {"left": int(left), "top": int(top), "width": int(w), "height": int(h)}
        bright = False
        with self._mss.MSS() as screen:
            while not self._stop.is_set():
                level = float(np.asarray(screen.grab(area))[..., :3].mean())
                stamp = time.perf_counter()
                self.grabs += 1
                if not bright and level > self.seen:
                    bright = True
                    self.onsets.append(stamp)
                elif bright and level < self.dark:
                    bright = False
                time.sleep(0.001)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)

    def __enter__(self) -> ScreenWatch:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def marker_latencies(arrivals: Sequence[float], onsets: Sequence[float], *, within: float = 1.0) -> list[float]:
    """For each marker's arrival time, seconds until the first screen onset after it (within ``within`` s);
    markers never seen are left out."""
    out = []
    for a in arrivals:
        seen = [t for t in onsets if a <= t <= a + within]
        if seen:
            out.append(seen[0] - a)
    return out


__all__ = ["ScreenWatch", "marker_latencies", "write_marker_clip"]
