"""Independent model fits of the diagnosis on a few threads at once.

A greedy round fits every candidate beside the same selected effects, and the attribution of several projectors
fits each effect on no projector, on each alone and on all: fits that share nothing but their read-only data. Most
of a fit's time is numpy on arrays of ~10⁵ values and OpenCV, which let go of the interpreter's lock, so two
threads on two cores ran the demo's selection in 9.9 s instead of 14.2, with the same fits bit for bit (each fit
reads only its own inputs and its composite's own caches). numpy's OpenBLAS is held to one thread meanwhile
(:func:`..native.blas_threads`): its spinning threads would take the core the second fit runs on.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from typing import TypeVar

from ..errors import Cancelled
from ..native import blas_threads
from ..progress import Cancel

T = TypeVar("T")

#: How often (seconds) a wait for the running fits looks at the cancel flag.
CANCEL_POLL = 0.2


def fit_threads() -> int:
    """Threads for independent fits: this machine's cores (the process's share of them where it is limited)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def run_fits(jobs: Sequence[Callable[[], T]], *, cancel: Cancel | None = None,
             done: Callable[[int, int], None] | None = None, order: Sequence[int] | None = None,
             threads: int | None = None) -> list[T]:
    """Each of ``jobs`` run once, at most ``threads`` (default :func:`fit_threads`) at a time; their results in
    ``jobs``' order. ``order``: the order to start them in (the longest first keeps both cores busy to the end);
    ``done(index, count finished)`` on the calling thread as each ends. A job's exception is raised here, and
    ``cancel`` raises :class:`Cancelled`, once the jobs running then have ended (nothing runs after a return)."""
    count = len(jobs)
    todo = list(order) if order is not None else list(range(count))
    if sorted(todo) != list(range(count)):
        raise ValueError("order must name every job once")
    workers = min(count, threads or fit_threads())
    if workers <= 1:
        out: dict[int, T] = {}
        for n, i in enumerate(todo):
            if cancel is not None and cancel():
                raise Cancelled("diagnosis cancelled")
            out[i] = jobs[i]()
            if done is not None:
                done(i, n + 1)
        return [out[i] for i in range(count)]
    with blas_threads(1):
        pool = ThreadPoolExecutor(workers, thread_name_prefix="procam-fit")
        try:
            futures: dict[Future[T], int] = {pool.submit(jobs[i]): i for i in todo}
            pending, finished = set(futures), 0
            while pending:
                ended, pending = wait(pending, timeout=CANCEL_POLL, return_when=FIRST_COMPLETED)
                if cancel is not None and cancel():
                    raise Cancelled("diagnosis cancelled")
                for f in ended:
                    f.result()  # a job's exception, here
                    finished += 1
                    if done is not None:
                        done(futures[f], finished)
            by_index = {i: f.result() for f, i in futures.items()}
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
    return [by_index[i] for i in range(count)]
