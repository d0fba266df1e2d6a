"""The terminal side of long work: progress on stderr (a bar redrawn in place, or time-stamped log lines) and Ctrl-C.

Progress goes to stderr (stdout stays for results). :func:`progress` prints
one time-stamped line. :class:`ProgressBar` tracks a count of work units: on a
terminal it redraws one line in place (carriage return), elsewhere (a log
file, a pipe, a CI job) it prints plain time-stamped lines, at most one every
few seconds, so logs stay readable and greppable. Lines printed with
:func:`progress` while a bar is drawn appear above the bar.
"""

from __future__ import annotations

import contextlib
import math
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

from ..progress import Cancel
from ..steps.summary import Summary

T = TypeVar("T")


def _stamp(message: str) -> str:
    return f"[procam {time.strftime('%H:%M:%S')}] {message}"


#: The bar currently drawn in place on a terminal, so that :func:`progress` can print above it.
_drawn: ProgressBar | None = None


def progress(message: str) -> None:
    """One progress line on stderr (stdout stays for results)."""
    bar = _drawn
    if bar is not None:
        bar._clear()
    print(_stamp(message), file=sys.stderr, flush=True)
    if bar is not None:
        bar._draw()


def _duration(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    h, rest = divmod(seconds, 3600)
    return f"{h}:{rest // 60:02d}:{rest % 60:02d}" if h else f"{rest // 60:02d}:{rest % 60:02d}"


class ProgressBar:
    """Progress over ``total`` units (frames, targets) on stderr: a bar redrawn in place on a terminal,
    time-stamped lines elsewhere.

    ``update(done, message)`` takes a fractional ``done`` (3.4 = three units
    finished and 40 % of the fourth). Updates are throttled (``interval``
    seconds; default 0.1 on a terminal, 2 elsewhere) unless ``force`` is true,
    which callers use when a unit finishes so that every finished unit is logged.
    ``stream`` defaults to ``sys.stderr``; ``tty`` overrides the terminal test.
    """

    def __init__(self, total: int, label: str, *, unit: str = "", stream: Any = None,
                 tty: bool | None = None, interval: float | None = None) -> None:
        self.total = max(int(total), 0)
        self.label = label
        self.unit = unit
        self.stream = stream
        if tty is None:
            isatty = getattr(self._out, "isatty", None)
            tty = bool(isatty and isatty())
        self.tty = tty
        self.interval = interval if interval is not None else (0.1 if tty else 2.0)
        self.started = time.monotonic()
        self.done = 0.0
        self.message = ""
        self._last = float("-inf")
        self._shown = False
        self._logged = ""

    @property
    def _out(self) -> Any:
        return self.stream if self.stream is not None else sys.stderr

    def text(self, *, width: int | None = None) -> str:
        """The current state as one line (without time stamp or carriage return)."""
        elapsed = time.monotonic() - self.started
        frac = min(self.done / self.total, 1.0) if self.total else 1.0
        # One decimal, rounded down: 0.999 of a frame is not "1" frame done.
        count = f"{math.floor(self.done * 10) / 10:.1f}".removesuffix(".0")
        unit = f" {self.unit}" if self.unit else ""
        left = ""
        if 0 < self.done < self.total:
            left = f"<{_duration(elapsed / self.done * (self.total - self.done))}"
        head = f"{self.label} {math.floor(100 * frac):3d}%"
        tail = f"[{_duration(elapsed)}{left}]" if self.unit == "%" else \
            f"{count}/{self.total}{unit} [{_duration(elapsed)}{left}]"
        if self.tty:
            cells = 20
            filled = int(round(frac * cells))
            line = f"{head} |{'#' * filled}{'.' * (cells - filled)}| {tail}"
        else:
            line = f"{head} {tail}"
        if self.message:
            line += f" {self.message}"
        if width is not None and len(line) > width:
            line = line[:max(width - 1, 0)] + "…"
        return line

    def update(self, done: float, message: str = "", *, force: bool = False) -> None:
        done = min(max(float(done), 0.0), float(self.total))
        if self.unit != "%" and math.floor(done) > math.floor(self.done):
            force = True  # a unit (frame, target) finished: always logged
        self.done = done
        if message:
            self.message = message
        now = time.monotonic()
        if not force and now - self._last < self.interval:
            return
        self._last = now
        if self.tty:
            self._draw()
        else:
            self._line()

    def _line(self) -> None:
        text = self.text()
        if text != self._logged:  # close() after a forced final update does not repeat it
            print(_stamp(text), file=self._out, flush=True)
            self._logged = text

    def _draw(self) -> None:
        global _drawn
        width = shutil.get_terminal_size((100, 20)).columns - 1
        self._out.write("\r" + self.text(width=width) + "\x1b[K")
        self._out.flush()
        self._shown = True
        if self._out is sys.stderr:
            _drawn = self

    def _clear(self) -> None:
        if self._shown:
            self._out.write("\r\x1b[K")
            self._out.flush()

    def close(self, message: str = "") -> None:
        """Print the final state once, and end the terminal line."""
        global _drawn
        if message:
            self.message = message
        if self.tty:
            self._draw()
            self._out.write("\n")
            self._out.flush()
        else:
            self._line()
        self._shown = False
        if _drawn is self:
            _drawn = None

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, *exc: Any) -> None:
        global _drawn
        if self.tty and self._shown:
            self._out.write("\n")  # leave the last state visible above an error message
            self._out.flush()
        self._shown = False
        if _drawn is self:
            _drawn = None


@contextlib.contextmanager
def cancel_on_interrupt() -> Iterator[Cancel]:
    """Yield ``cancel()`` for stage loops: the first Ctrl-C makes it true, so the running stage stops
    cleanly at its next step (and raises :class:`Cancelled`); a second Ctrl-C interrupts at once.

    Outside the main thread (a Blender worker) signals cannot be caught: ``cancel()`` stays false there.
    """
    hits = [0]

    def handler(signum: int, frame: object) -> None:
        hits[0] += 1
        if hits[0] > 1:
            raise KeyboardInterrupt
        print("procam: cancelling after the current step (Ctrl-C again to stop at once)", file=sys.stderr,
              flush=True)

    previous = None
    if threading.current_thread() is threading.main_thread():
        try:
            previous = signal.signal(signal.SIGINT, handler)
        except ValueError:
            previous = None
    try:
        yield lambda: hits[0] > 0
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)


def run_step(label: str, step: Callable[..., T], options: Any, *, total: int = 100, unit: str = "%",
             **keywords: Any) -> T:
    """``step(options, progress, cancel, **keywords)`` with a bar on stderr over ``total`` units (the step's
    fraction scaled; a percentage by default) and Ctrl-C as a clean cancel."""
    with cancel_on_interrupt() as cancel, ProgressBar(total, label, unit=unit) as bar:
        def report(message: str, fraction: float) -> None:
            if "warning:" in message or "note:" in message:
                progress(message)  # never throttled away
            bar.update(fraction * total, message)

        result = step(options, report, cancel, **keywords)
        bar.close()
    return result


def print_summary(what: str, folder: str | Path, summary: Summary) -> None:
    """A step's result on stdout: the folder it wrote, then its summary (headline and lines) as the sidebar shows
    it, so both front doors report the same figures in the same words."""
    print(f"{what}: {folder}")
    for line in (summary.headline, *summary.lines):
        print(f"  {line}")
