"""Output folders that appear whole or not at all, and progress reporting on stderr for long work.

A command writes into a hidden temporary sibling of its output folder and
renames it into place only when everything is written, so a crash or a
cancel never leaves a half-written result under the real name, and an
existing result is only replaced with ``force`` — after the new one is complete.

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
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ProCamError
from .imageio import usual_mode


class OutputError(ProCamError):
    """An output folder that cannot be written or already holds results."""


class AtomicFolder:
    """Build a folder in a hidden sibling and rename it into place when complete.

    An existing ``target`` is refused unless ``force``; even then it is only
    renamed to a backup and removed after the new folder is in place, so a
    failure at any point leaves either the old folder or the new one, never
    a mixture. ``replaceable(path)`` says which existing folders ``force``
    may replace (others are refused even with ``force``, to protect user data).
    """

    def __init__(self, target: str | Path, *, force: bool = False, what: str = "folder",
                 replaceable: Callable[[Path], bool] | None = None,
                 error: type[ProCamError] = OutputError) -> None:
        self.target = Path(target)
        self.error = error
        self.force = force
        self.what = what
        if self.target.exists():
            if not self.target.is_dir():
                raise self.error(f"{self.target} exists and is not a folder; choose another output path")
            empty = not any(self.target.iterdir())
            if not empty:
                if replaceable is not None and not replaceable(self.target):
                    raise self.error(f"{self.target} exists, is not empty and is not a {what}; "
                                       "refusing to replace it — choose another output folder")
                if not force:
                    raise self.error(f"{self.target} already holds a {what}; it is never overwritten "
                                       "without --force (force=True)")
        try:
            self.target.parent.mkdir(parents=True, exist_ok=True)
            self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.target.name}.tmp-", dir=self.target.parent))
            usual_mode(self.tmp)
        except OSError as exc:
            raise self.error(f"cannot write {self.what} at {self.target}: {exc.strerror or exc}") from None
        self.done = False

    def commit(self) -> Path:
        if self.done:
            raise self.error(f"{self.what} at {self.target} was already completed")
        backup: Path | None = None
        try:
            if self.target.exists():
                backup = Path(tempfile.mkdtemp(prefix=f".{self.target.name}.old-", dir=self.target.parent))
                backup.rmdir()  # mkdtemp reserves a unique name; rename needs it free
                os.replace(self.target, backup)
            os.replace(self.tmp, self.target)
        except OSError as exc:
            if backup is not None and backup.exists() and not self.target.exists():
                os.replace(backup, self.target)  # put the old one back
            self.abort()
            raise self.error(f"cannot move the new {self.what} into {self.target}: {exc.strerror or exc}") from None
        self.done = True
        if backup is not None:
            shutil.rmtree(backup, ignore_errors=True)
        return self.target

    def abort(self) -> None:
        if not self.done:
            shutil.rmtree(self.tmp, ignore_errors=True)
            self.done = True


@contextlib.contextmanager
def fresh_output_folder(path: str | Path, *, force: bool = False, what: str = "results folder") -> Iterator[Path]:
    """Yield a temporary folder; on success it becomes ``path`` (replacing it only with ``force``)."""
    folder = AtomicFolder(path, force=force, what=what)
    try:
        yield folder.tmp
    except BaseException:
        folder.abort()
        raise
    folder.commit()


def output_names(paths: "Iterable[str | Path]") -> list[str]:
    """Output names from file stems, made unique (a/x.png and b/x.png become x and x_2)."""
    import re

    out: list[str] = []
    for p in paths:
        base = re.sub(r"[^A-Za-z0-9_.-]+", "-", Path(p).stem).strip("-") or "target"
        name, n = base, 1
        while name in out:
            n += 1
            name = f"{base}_{n}"
        out.append(name)
    return out


def jsonable(value: Any) -> Any:
    """Plain JSON types (numpy scalars/arrays become numbers/lists) so manifests are portable."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _stamp(message: str) -> str:
    return f"[procam {time.strftime('%H:%M:%S')}] {message}"


#: The bar currently drawn in place on a terminal, so that :func:`progress` can print above it.
_drawn: "ProgressBar | None" = None


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
        tail = f"{count}/{self.total}{unit} [{_duration(elapsed)}{left}]"
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
        self.done = min(max(float(done), 0.0), float(self.total))
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

    def __enter__(self) -> "ProgressBar":
        return self

    def __exit__(self, *exc: Any) -> None:
        global _drawn
        if self.tty and self._shown:
            self._out.write("\n")  # leave the last state visible above an error message
            self._out.flush()
        self._shown = False
        if _drawn is self:
            _drawn = None
