"""A show's frames over many processes or machines, on Dask distributed.

Why Dask distributed (not Ray): pure-Python wheels on every platform the
project runs on, a ``LocalCluster`` of worker processes started from Python
with no daemon to install, ``Client(address)`` for a real cluster
(``dask scheduler`` / ``dask worker`` on the machines), and task dependencies
by passing futures — which is exactly how a warm-started frame waits for the
one before it.

* Frames are tasks. Frame n's task takes frame n−1's outcome as an argument
  when it is warm-started from it, so a chunk of frames is a chain and chunks
  run side by side (the show step cuts the sequence into chunks the same way
  with or without a cluster, so the frames are byte-identical).
* Each worker process loads the calibration and the Mitsuba scene once: a
  worker-side cache of :class:`.stage_c.StageC` keyed by the calibration's
  hashes and the settings.
* Workers write nothing; they return each frame's 16-bit PNG bytes and its
  manifest entry, and the process running ``procam show`` writes them (it
  alone holds the show folder's lock), so the folder stays atomic and
  resumable, and no frame is computed twice.
* Dr.Jit's (and OpenCV's) threads per worker are limited so that workers ×
  threads does not exceed the machine's cores (or set with ``threads``).
  Renders with several samples per pixel add them in an order that depends on
  Dr.Jit's thread count (measured: up to 3/65535 apart between 1 and 2
  threads), so a cluster's frames are byte-identical to one process's when
  both run the same number of threads (``procam show --threads``).
* Workers read the calibration and the targets by the paths the show names:
  on a real cluster they must see the same paths (a shared disk).
* A calibration of several projectors runs :class:`.projectors.JointStage` on
  the workers: a task returns every projector's PNG bytes at once (one frame is
  one joint solve, so it is not split across workers), warm-started from every
  projector's previous frame; the open-loop θ models the driver estimated (or
  read back from the show folder) travel with the context.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import threading
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import ProCamError
from ..outputs import hidden_sibling
from ..stages.compensate import BiasModel
from ..stages.display_area import DisplayArea
from ..stages.range import RangeMap
from ..video import VideoReader
from . import calibrate as calibrate_step
from .projectors import JointStage
from .show_work import FrameJob, FrameOutcome, compute_frame
from .stage_c import StageC, StageCOptions


class ClusterError(ProCamError):
    """A cluster that cannot be started, reached or used."""


@dataclass(frozen=True)
class WorkerContext:
    """What every frame task shares: how to build the worker's stage C, and what the driver fixed for the show."""

    key: str  # calibration hashes and settings: the worker cache's key
    calibration: Path
    options: StageCOptions
    bias: BiasModel | None
    range_map: RangeMap | None
    areas: dict[str, Any] = field(default_factory=dict)
    #: Dr.Jit threads per worker (None: the worker's cores over its task slots)
    threads: int | None = None
    #: with several projectors: each projector's open-loop θ model (None: the closed loop or --no-bias)
    biases: list[BiasModel] | None = None
    #: zero padding of the frame numbers (several projectors: the entries name each projector's file)
    digits: int = 4


_STAGES: dict[str, StageC | JointStage] = {}
_READERS: dict[Path, VideoReader] = {}


def _stage(ctx: WorkerContext) -> StageC | JointStage:
    """This worker's stage C for ``ctx`` (built once per worker process and show settings): a
    :class:`.projectors.JointStage` for a calibration of several projectors."""
    if ctx.key not in _STAGES:
        import cv2
        import drjit as dr

        threads = ctx.threads
        if threads is None:
            try:
                from distributed import get_worker

                slots = get_worker().state.nthreads
            except (ImportError, ValueError, AttributeError):
                slots = 1
            threads = max(1, (os.cpu_count() or 1) // max(1, slots))
        dr.set_thread_count(threads)
        cv2.setNumThreads(threads)
        for old in _STAGES.values():  # one show at a time per worker: free the last one's scene
            old.close()
        _STAGES.clear()
        cal = calibrate_step.read(ctx.calibration)
        stage: StageC | JointStage
        if cal.projector_count > 1:
            stage = JointStage(cal, ctx.options)
            if ctx.biases is not None:
                stage.use_biases(ctx.biases)
        else:
            stage = StageC(cal, ctx.options)
            stage.bias = ctx.bias
        stage.range_map = ctx.range_map
        _STAGES[ctx.key] = stage
    stage = _STAGES[ctx.key]
    stage.areas.update({k: DisplayArea.from_dict(v) for k, v in ctx.areas.items() if k not in stage.areas})
    return stage


def remote_frame(ctx: WorkerContext, job: FrameJob, prev: FrameOutcome | list[bytes] | None) -> FrameOutcome:
    """A frame task: ``prev`` is the outcome of the frame it warm-starts from, that frame's PNG bytes read from
    the show folder (one per projector, in projector order), or None (a cold start)."""
    stage = _stage(ctx)
    starts: list[bytes] | None
    if isinstance(prev, FrameOutcome):
        starts = (prev.pngs or [prev.png]) if prev.png is not None else None  # a failed predecessor: no answer
    else:
        starts = prev
    return compute_frame(stage, job, starts or None, digits=ctx.digits, readers=_READERS)


#: A worker preload (the text of a script, run in each worker process as it starts): its own process group.
_OWN_GROUP = "import os\nos.setpgid(0, 0)\n"


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """SIGINT ignored while the block runs (in the main thread; elsewhere signals cannot be set, nor are they
    delivered to Python), for the processes it starts to inherit."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


#: Seconds to wait for a cluster's scheduler to answer (``procam show --connect-timeout``).
CONNECT_TIMEOUT = 15.0


def _reach(address: str, timeout: float, poll: Callable[[], None]) -> None:
    """Connect to the scheduler at ``address`` and exchange Dask's handshake, within ``timeout`` seconds, calling
    ``poll`` every tenth of a second (it raises to cancel).

    Why before ``Client(address, timeout=…)``: distributed bounds the TCP connect but not the handshake read after
    it (``distributed.comm.core.connect`` awaits ``comm.read()`` with no limit), so a host that accepts the
    connection and never answers — a wrong port, a firewall, a stopped process — holds the client forever, and
    its wait in another thread does not see Ctrl-C. A scheduler sends its handshake at once on connecting."""
    import asyncio
    import time

    from distributed.comm import connect

    async def attempt() -> None:
        task = asyncio.ensure_future(connect(address, timeout=timeout))
        deadline = time.monotonic() + timeout
        try:
            while not task.done():
                await asyncio.wait({task}, timeout=0.1)
                if not task.done():
                    poll()
                    if time.monotonic() > deadline:
                        raise ClusterError(f"the cluster at {address} accepted the connection but did not answer "
                                           f"within {timeout:g} s (no Dask scheduler there?); check the address and "
                                           "port (dask scheduler prints it), or give more time with "
                                           "--connect-timeout")
            comm = task.result()
        finally:
            if not task.done():
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
        await comm.close()

    try:
        asyncio.run(attempt())
    except (OSError, TimeoutError, ValueError) as exc:
        raise ClusterError(f"cannot reach the cluster at {address}: {exc}; check the address and port, and that "
                           "its scheduler runs (dask scheduler)") from None


class Cluster:
    """A Dask client: on a local cluster of ``workers`` processes started here, or attached to ``address``."""

    def __init__(self, *, workers: int | None = None, address: str | None = None, threads: int | None = None,
                 connect_timeout: float = CONNECT_TIMEOUT, poll: Callable[[], None] = lambda: None,
                 beside: Path | None = None) -> None:
        """``poll`` is called while waiting for a cluster at ``address`` (it raises to cancel). A local cluster's
        workers keep their scratch space (Dask's ``global.lock``, ``purge.lock``, spilled data) in a hidden folder
        beside ``beside`` (the show folder), removed when the cluster closes; without it, in Dask's temporary
        directory."""
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise ClusterError("--workers and --cluster need Dask distributed (pip install -r requirements.txt); "
                               "it is not installed in this Python") from None
        self.local = None
        self.client = None
        self.scratch: Path | None = None
        self.threads: int | None = threads
        try:
            if address:
                _reach(address, connect_timeout, poll)
                self.client = Client(address, timeout=f"{connect_timeout}s")
            else:
                n = max(1, int(workers or 1))
                self.threads = threads or max(1, (os.cpu_count() or 1) // n)
                if beside is not None:  # no write outside the folders the user gave
                    self.scratch = hidden_sibling(Path(beside), "tmp")
                # Ctrl-C in a terminal reaches every process of its group, the workers too: they would die with
                # tracebacks mid-frame and the show would end as a bug. So only this process hears it and cancels
                # the show cleanly: the workers start with SIGINT ignored (inherited through exec), then leave the
                # terminal's process group (ignoring alone does not last: Dr.Jit installs its own SIGINT handler
                # while kernels run). They still exit with this process (Dask watches their parent).
                import dask

                # the scheduler's scratch space too (it takes Dask's temporary directory, not local_directory)
                where = contextlib.nullcontext() if self.scratch is None else \
                    dask.config.set({"temporary-directory": str(self.scratch)})
                # Only CRITICAL records of Dask's own loggers reach the terminal: a task's error comes back through
                # its future (and is reported as ProCam's), while a worker whose heartbeat meets the scheduler
                # already closed by a cancel logs an ERROR with a traceback (seen under load on Ctrl-C).
                with _sigint_ignored(), where:
                    self.local = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                              dashboard_address=None, silence_logs=logging.CRITICAL,
                                              local_directory=None if self.scratch is None else str(self.scratch),
                                              preload=[_OWN_GROUP] if hasattr(os, "setpgid") else None)
                self.client = Client(self.local)
        except (OSError, TimeoutError, ValueError) as exc:
            self.close()
            where = f"the cluster at {address}" if address else "a local cluster"
            raise ClusterError(f"cannot start or reach {where}: {exc}") from None

    @property
    def describe(self) -> str:
        info = self.client.scheduler_info()
        workers = info.get("workers", {})
        slots = sum(int(w.get("nthreads", 1)) for w in workers.values())
        return f"{len(workers)} worker(s), {slots} task slot(s)" + ("" if self.local else f" at {info.get('address')}")

    def run(self, ctx: WorkerContext, jobs: list[FrameJob], starts: dict[int, list[bytes]],
            poll: Callable[[], None]) -> Iterator[FrameOutcome]:
        """Submit every job (each after the job it warm-starts from, when that one is in ``jobs``) and yield the
        outcomes as they finish. ``starts``: each projector's PNG bytes for jobs whose ``prev`` is not in
        ``jobs``. ``poll`` is
        called while waiting (it raises to cancel); on any error the remaining tasks are cancelled."""
        from distributed import wait

        client = self.client
        ctx_future = client.scatter(ctx, broadcast=True, hash=False)
        futures: dict[int, Any] = {}
        run_id = uuid.uuid4().hex  # keys of this run's tasks: never one of an earlier run still on the cluster
        for i, job in enumerate(jobs):
            prev = futures.get(job.prev) if job.prev is not None else None
            if prev is None:
                prev = starts.get(job.number)
            # Earlier frames first: the order a single process would take, and chains never wait on later ones.
            futures[job.number] = client.submit(remote_frame, ctx_future, job, prev, pure=False,
                                                key=f"procam-frame-{job.number}-{run_id}",
                                                priority=len(jobs) - i, retries=0)
        pending = set(futures.values())
        try:
            while pending:
                poll()
                try:
                    done, pending = wait(pending, timeout=0.5, return_when="FIRST_COMPLETED")
                except TimeoutError:  # nothing finished yet: poll again (a cancel is seen within half a second)
                    continue
                for fut in sorted(done, key=lambda f: f.key):
                    yield fut.result()
        finally:
            if pending:
                client.cancel(list(pending), force=True)

    def close(self) -> None:
        client = getattr(self, "client", None)
        if client is not None:
            client.close()
            self.client = None
        if self.local is not None:
            self.local.close()
            self.local = None
        if self.scratch is not None:
            shutil.rmtree(self.scratch, ignore_errors=True)
            self.scratch = None
