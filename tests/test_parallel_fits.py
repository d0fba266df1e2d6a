"""Independent fits on threads (addon/gap/parallel.py) and numpy's BLAS held to one thread (addon/native.py).

The selection itself, run with these threads, is checked against its known answers in tests/test_gap.py and
tests/test_projectors_camera.py; here: order, errors, cancel, and the BLAS setting restored.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from procam.addon import native
from procam.addon.errors import Cancelled
from procam.addon.gap.parallel import run_fits


def test_results_come_in_the_jobs_order_whatever_order_they_start_and_end_in():
    started, ends = [], []

    def job(i: int):
        def run():
            started.append(i)
            time.sleep(0.02 * (4 - i))  # the first ends last
            ends.append(i)
            return i * i
        return run

    seen = []
    out = run_fits([job(i) for i in range(4)], order=[3, 2, 1, 0], threads=2,
                   done=lambda i, n: seen.append((i, n)))
    assert out == [0, 1, 4, 9]
    assert set(started[:2]) == {2, 3}  # the first two asked for start first
    assert sorted(i for i, _ in seen) == [0, 1, 2, 3] and [n for _, n in seen] == [1, 2, 3, 4]
    with pytest.raises(ValueError, match="every job once"):
        run_fits([job(0), job(1)], order=[0, 0])


def test_two_threads_run_at_once_and_one_thread_runs_in_turn():
    both = threading.Barrier(2, timeout=5)

    def meet():
        both.wait()  # returns only when the other job is running too
        return threading.current_thread().name

    names = run_fits([meet, meet], threads=2)
    assert len(set(names)) == 2 and all(n.startswith("procam-fit") for n in names)
    assert run_fits([threading.current_thread, threading.current_thread], threads=1) == \
        [threading.current_thread()] * 2


def test_a_jobs_error_is_raised_once_the_running_jobs_end():
    finished = []

    def slow():
        time.sleep(0.2)
        finished.append("slow")
        return 1

    def broken():
        raise FloatingPointError("parameters became NaN")

    with pytest.raises(FloatingPointError, match="NaN"):
        run_fits([slow, broken], threads=2)
    assert finished == ["slow"]  # nothing still runs once the error is raised


def test_cancel_stops_before_the_jobs_not_started():
    ran = []

    def job(i: int):
        def run():
            ran.append(i)
            time.sleep(0.05)
            return i
        return run

    flag = threading.Event()

    def done(i: int, n: int) -> None:
        flag.set()

    with pytest.raises(Cancelled):
        run_fits([job(i) for i in range(20)], threads=2, cancel=flag.is_set, done=done)
    assert len(ran) < 20
    with pytest.raises(Cancelled):
        run_fits([job(0)], threads=1, cancel=lambda: True)


def test_blas_threads_holds_openblas_to_one_thread_and_sets_it_back():
    found = native._openblas()
    if not found:
        pytest.skip("numpy here uses no OpenBLAS this module finds")
    _, getter = found[0]
    before = getter()
    with native.blas_threads(1):
        assert getter() == 1
        with native.blas_threads(1):
            assert getter() == 1
        assert getter() == 1  # the inner block does not restore while the outer one holds it
        a = np.random.default_rng(0).random((200, 200))
        np.testing.assert_allclose(a @ np.eye(200), a)
    assert getter() == before
