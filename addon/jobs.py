"""Background jobs for the Blender UI: an engine function in a worker thread, with progress, cancel and its outcome.

A :class:`Job` calls ``fn(*args, progress=…, cancel=…, **kwargs)``. The engine
reports ``progress(message, fraction)``; the UI polls :meth:`Job.snapshot` from a
timer and asks for a stop with :meth:`Job.cancel`. Engine functions check
``cancel()`` where they can; :meth:`Job.progress` also raises
:class:`~.errors.Cancelled` once a stop was asked for, so a function that only
reports progress still stops at its next report. The outcome is kept: the
result, the :class:`~.errors.Cancelled` (the job is cancelled), or the
:class:`~.errors.ProCamError` (it failed). Anything else is a ProCam bug: the
traceback goes to stderr and the job fails with a message that says so.

bpy is not thread-safe, so a worker must not touch it. Work that has to run on
Blender's main thread (a virtual-lab capture renders with Cycles) goes through
a :class:`MainThreadRelay`: the worker blocks in :meth:`MainThreadRelay.call`
while the UI's timer runs the call in :meth:`MainThreadRelay.pump`.

No bpy here: this module is tested without Blender.
"""

from __future__ import annotations

import queue
import sys
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from .errors import Cancelled, ProCamError

PENDING, RUNNING, DONE, FAILED, CANCELLED = "pending", "running", "done", "failed", "cancelled"
FINISHED_STATES = (DONE, FAILED, CANCELLED)


class JobError(ProCamError):
    """A job that cannot start (another one runs) or whose result was asked for too early."""


@dataclass(frozen=True)
class Snapshot:
    """What the UI shows of a job at one moment."""

    name: str
    status: str
    message: str
    fraction: float
    error: str | None
    seconds: float
    #: a cancel that kept finished work: ``error`` says what and where
    kept: bool = False

    @property
    def finished(self) -> bool:
        return self.status in FINISHED_STATES


class Job:
    """One engine call, run in a worker thread (:meth:`start`) or in the caller's thread (:meth:`run`)."""

    def __init__(self, name: str, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> None:
        self.name = name
        self._fn, self._args, self._kwargs = fn, args, kwargs
        self._lock = threading.Lock()
        self._cancel = threading.Event()
        self._done = threading.Event()
        self._status = PENDING
        self._message = "waiting"
        self._fraction = 0.0
        self._result: Any = None
        self._error: ProCamError | Cancelled | None = None
        self._t0: float | None = None
        self._t1: float | None = None
        self._thread: threading.Thread | None = None
        self.traceback: str | None = None
        #: How the UI words the engine's progress and error messages (the sidebar names the command's options by
        #: its own fields); as they are by default.
        self.wording: Callable[[str], str] = str

    # -- called by the engine (any thread)

    def progress(self, message: str, fraction: float) -> None:
        """Record progress; raises :class:`Cancelled` once a stop was asked for."""
        with self._lock:
            self._message = self.wording(str(message))
            if fraction == fraction and fraction >= 0:  # NaN or a negative value: fraction unknown, keep the last
                self._fraction = min(1.0, float(fraction))
        if self._cancel.is_set():
            # Not "nothing was written": a resumable step (live capture, a show) keeps what it finished, and says so
            # when it passes this on; an atomic one writes nothing by construction.
            raise Cancelled(f"{self.name} was cancelled")

    def cancelled(self) -> bool:
        """True once a stop was asked for (the engine's ``cancel`` callable)."""
        return self._cancel.is_set()

    # -- called by the UI

    def cancel(self) -> None:
        """Ask the job to stop at its next progress report or cancel check."""
        self._cancel.set()
        with self._lock:
            if self._status in (PENDING, RUNNING):
                self._message = "cancelling…"

    def start(self) -> Job:
        """Run in a daemon worker thread; returns at once."""
        self._begin()
        self._thread = threading.Thread(target=self._run, name=f"procam-{self.name}", daemon=True)
        self._thread.start()
        return self

    def run(self) -> Job:
        """Run in the calling thread (Blender in background mode has no event loop to poll a worker)."""
        self._begin()
        self._run()
        return self

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the job has finished (True) or ``timeout`` seconds passed (False)."""
        return self._done.wait(timeout)

    def snapshot(self) -> Snapshot:
        with self._lock:
            end = self._t1 if self._t1 is not None else time.perf_counter()
            seconds = 0.0 if self._t0 is None else end - self._t0
            error = self.wording(str(self._error)) if self._error is not None else None
            kept = isinstance(self._error, Cancelled) and self._error.kept
            return Snapshot(self.name, self._status, self._message, self._fraction, error, seconds, kept)

    def mark_failed(self, error: ProCamError) -> None:
        """A finished job whose result could not be used (e.g. applying it to the scene failed)."""
        with self._lock:
            self._status, self._error, self._message = FAILED, error, "failed"

    @property
    def status(self) -> str:
        with self._lock:
            return self._status

    @property
    def finished(self) -> bool:
        return self._done.is_set()

    @property
    def error(self) -> ProCamError | Cancelled | None:
        with self._lock:
            return self._error

    @property
    def result(self) -> Any:
        """The engine function's return value; :class:`JobError` unless the job is done."""
        with self._lock:
            if self._status != DONE:
                raise JobError(f"{self.name} has no result: it is {self._status}")
            return self._result

    # -- internals

    def _begin(self) -> None:
        with self._lock:
            if self._status != PENDING:
                raise JobError(f"{self.name} was already started")
            self._status = RUNNING
            self._message = "starting"
            self._t0 = time.perf_counter()

    def _run(self) -> None:
        status, result = DONE, None
        error: ProCamError | None = None
        try:
            if self._cancel.is_set():
                raise Cancelled(f"{self.name} was cancelled before it started; nothing was written")
            result = self._fn(*self._args, progress=self.progress, cancel=self.cancelled, **self._kwargs)
        except Cancelled as exc:
            status, error = CANCELLED, exc
        except ProCamError as exc:
            status, error = FAILED, exc
        except Exception as exc:  # noqa: BLE001 — a bug: keep the traceback for the console, fail the job cleanly
            self.traceback = traceback.format_exc()
            print(self.traceback, file=sys.stderr, flush=True)
            status, error = FAILED, ProCamError(f"{self.name} stopped on a ProCam bug ({type(exc).__name__}: {exc}); "
                                                "the traceback is in the console — please report it")
        with self._lock:
            self._status, self._result, self._error = status, result, error
            self._t1 = time.perf_counter()
            if status == DONE:
                self._fraction, self._message = 1.0, "done"
            elif status == CANCELLED:
                self._message = "cancelled"
            else:
                self._message = "failed"
        self._done.set()


class JobBoard:
    """The jobs of the UI by step name: at most one runs at a time (they share the CPU and the renderer)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._jobs: dict[str, Job] = {}

    def running(self) -> Job | None:
        with self._lock:
            return next((j for j in self._jobs.values() if j.status in (PENDING, RUNNING)), None)

    def add(self, step: str, job: Job) -> Job:
        """Record ``job`` as the step's current job; refuses while another job runs."""
        with self._lock:
            busy = next((j for j in self._jobs.values() if j.status in (PENDING, RUNNING)), None)
            if busy is not None:
                raise JobError(f"{busy.name} is still running: wait for it or cancel it first")
            self._jobs[step] = job
        return job

    def get(self, step: str) -> Job | None:
        with self._lock:
            return self._jobs.get(step)

    def forget(self, step: str) -> None:
        with self._lock:
            job = self._jobs.get(step)
            if job is not None and job.finished:
                del self._jobs[step]

    def clear(self) -> None:
        """Cancel whatever runs and forget every job (on unregister)."""
        with self._lock:
            jobs = list(self._jobs.values())
            self._jobs.clear()
        for job in jobs:
            job.cancel()


#: The board the Blender UI uses.
BOARD = JobBoard()


class MainThreadRelay:
    """Runs calls from a worker on the main thread: the worker waits in :meth:`call`, the UI runs :meth:`pump`."""

    def __init__(self, cancel: Callable[[], bool] | None = None, poll_s: float = 0.05) -> None:
        self._queue: queue.Queue[tuple[Callable[[], Any], dict[str, Any], threading.Event]] = queue.Queue()
        self._cancel = cancel or (lambda: False)
        self._poll_s = poll_s

    def call(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """From a worker: run ``fn`` on the main thread and return its value (or raise its exception)."""
        box: dict[str, Any] = {}
        done = threading.Event()
        self._queue.put((lambda: fn(*args, **kwargs), box, done))
        while not done.wait(self._poll_s):
            if self._cancel():
                box["abandoned"] = True
                raise Cancelled("cancelled while waiting for the main thread; nothing was written")
        if "error" in box:
            raise box["error"]
        return box.get("value")

    def pump(self, max_calls: int = 1) -> int:
        """On the main thread: run up to ``max_calls`` waiting calls; returns how many ran."""
        ran = 0
        while ran < max_calls:
            try:
                fn, box, done = self._queue.get_nowait()
            except queue.Empty:
                break
            if not box.get("abandoned"):
                try:
                    box["value"] = fn()
                except BaseException as exc:  # noqa: BLE001 — handed to the worker, which raises it
                    box["error"] = exc
            done.set()
            ran += 1
        return ran


class RelayedDevice:
    """A capture device whose ``project`` runs on the main thread through a relay (the lab renders with bpy)."""

    def __init__(self, device: Any, relay: MainThreadRelay) -> None:
        self._device, self._relay = device, relay
        self.projector = device.projector

    def project(self, frame: Any) -> Any:
        return self._relay.call(self._device.project, frame)

    def project_all(self, frames: Any) -> Any:
        return self._relay.call(self._device.project_all, frames)

    def capture_off(self) -> Any:
        return self._relay.call(self._device.capture_off)

    def check_frame(self, frame: Any, index: int = 0) -> Any:
        return self._device.check_frame(frame, index)

    def close(self) -> None:
        """The owner closes the real device on the main thread."""

    def __getattr__(self, name: str) -> Any:
        return getattr(self._device, name)


__all__ = ["BOARD", "CANCELLED", "DONE", "FAILED", "FINISHED_STATES", "Job", "JobBoard", "JobError",
           "MainThreadRelay", "PENDING", "RUNNING", "RelayedDevice", "Snapshot"]
