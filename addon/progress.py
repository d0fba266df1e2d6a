"""The one progress and cancel protocol of long work, shared by every stage, step and front-end.

A step reports ``progress(message, fraction)`` (``fraction`` of its own work in
[0, 1]) and polls ``cancel()`` between units of work; when it returns true the
step raises :class:`~.errors.Cancelled` and leaves nothing half written. The
CLI turns reports into a bar on stderr (``cli/terminal.py``), Blender into the
job board and the status bar (``jobs.py``). A step that calls another gives it
:func:`part`: the callee's 0…1 lands in a slice of the caller's.
"""

from __future__ import annotations

from collections.abc import Callable

from .errors import Cancelled

#: ``progress(message, fraction)``: what runs now, and how much of this piece of work is done (0…1).
Progress = Callable[[str, float], None]
#: ``cancel()``: true once the user asked to stop.
Cancel = Callable[[], bool]


def quiet(message: str, fraction: float) -> None:
    """The progress sink when the caller gives none."""


def never() -> bool:
    """The cancel test when the caller gives none."""
    return False


def part(progress: Progress | None, start: float, end: float, prefix: str = "") -> Progress:
    """A progress for one slice ``[start, end]`` of the caller's work, each message prefixed with ``prefix``."""
    say = progress or quiet
    span = end - start

    def report(message: str, fraction: float) -> None:
        say(f"{prefix}{message}", start + span * min(max(float(fraction), 0.0), 1.0))

    return report


def check(cancel: Cancel | None, what: str) -> None:
    """Raise :class:`Cancelled` (saying ``what`` was cancelled) when the user asked to stop."""
    if cancel is not None and cancel():
        raise Cancelled(what)
