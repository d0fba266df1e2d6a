"""Background jobs without Blender: progress, cancel, errors, one job at a time, main-thread relay."""

import threading
import time

import pytest

from procam.addon import jobs
from procam.addon.errors import Cancelled, ImageError


def _steps(n, *, progress, cancel, gate=None, fail_at=None):
    for i in range(n):
        if isinstance(gate, threading.Semaphore):
            gate.acquire(timeout=5)  # one release per step: the test decides when each step runs
        elif gate is not None:
            gate.wait(5)
        if fail_at == i:
            raise ImageError("target 3 is unreadable: choose another file")
        progress(f"step {i + 1}/{n}", (i + 1) / n)
    return n * 10


def test_job_runs_in_a_thread_reports_progress_and_keeps_the_result():
    gate = threading.Semaphore(0)
    job = jobs.Job("count", _steps, 3, gate=gate).start()
    assert job.snapshot().status == jobs.RUNNING and not job.finished
    gate.release()
    for _ in range(200):
        if job.snapshot().fraction > 0.3:
            break
        time.sleep(0.01)
    snap = job.snapshot()
    assert snap.status == jobs.RUNNING and snap.fraction == pytest.approx(1 / 3) and snap.message == "step 1/3"
    with pytest.raises(jobs.JobError, match="running"):
        job.result  # noqa: B018 — the property raises
    gate.release()
    gate.release()
    assert job.wait(5)
    snap = job.snapshot()
    assert snap.status == jobs.DONE and snap.fraction == 1.0 and snap.finished and snap.error is None
    assert job.result == 30
    with pytest.raises(jobs.JobError, match="already started"):
        job.start()


def test_cancel_stops_at_the_next_progress_report_and_counts_as_cancelled():
    gate = threading.Semaphore(0)
    job = jobs.Job("count", _steps, 5, gate=gate).start()
    gate.release()
    job.cancel()
    assert job.cancelled()
    for _ in range(5):
        gate.release()
    assert job.wait(5)
    snap = job.snapshot()
    assert snap.status == jobs.CANCELLED and "cancelled" in snap.error
    assert isinstance(job.error, Cancelled)
    with pytest.raises(jobs.JobError):
        job.result  # noqa: B018 — the property raises


def test_engine_cancel_check_is_the_jobs_flag():
    seen = []

    def engine(*, progress, cancel):
        seen.append(cancel())
        return "ran"

    job = jobs.Job("x", engine)
    job.cancel()
    job.run()  # cancelled before it started: the engine is never called
    assert job.status == jobs.CANCELLED and seen == []
    job2 = jobs.Job("x", engine).run()
    assert job2.result == "ran" and seen == [False]


def test_procam_error_fails_the_job_with_its_message():
    job = jobs.Job("count", _steps, 5, fail_at=2).run()
    snap = job.snapshot()
    assert snap.status == jobs.FAILED and snap.error == "target 3 is unreadable: choose another file"
    assert snap.fraction == pytest.approx(0.4)


def test_the_ui_words_a_jobs_progress_and_error_its_own_way():
    """The sidebar names the command's options by its fields (operators/messages.py) in progress lines too."""
    seen = []

    def step(*, progress, cancel):
        progress("the operator is already there (--force renders it again)", 0.5)
        seen.append(job.snapshot().message)
        raise ImageError("x exists; rerun with --force")

    job = jobs.Job("precompute", step)
    job.wording = lambda text: text.replace("--force", "‘Replace Results’")
    job.run()
    assert seen == ["the operator is already there (‘Replace Results’ renders it again)"]
    assert job.snapshot().error == "x exists; rerun with ‘Replace Results’"


def test_a_bug_fails_the_job_with_a_message_and_keeps_the_traceback(capsys):
    def buggy(*, progress, cancel):
        return {}["missing"]

    job = jobs.Job("buggy", buggy).run()
    assert job.status == jobs.FAILED and "ProCam bug (KeyError" in job.snapshot().error
    assert "Traceback" in job.traceback and "Traceback" in capsys.readouterr().err


def test_board_runs_one_job_at_a_time_and_remembers_the_last_per_step():
    board = jobs.JobBoard()
    gate = threading.Event()
    first = board.add("calibrate", jobs.Job("calibration", _steps, 1, gate=gate)).start()
    with pytest.raises(jobs.JobError, match="calibration is still running"):
        board.add("compensate", jobs.Job("compensation", _steps, 1))
    assert board.running() is first
    gate.set()
    assert first.wait(5)
    assert board.running() is None and board.get("calibrate") is first
    second = board.add("compensate", jobs.Job("compensation", _steps, 1)).run()
    assert board.get("compensate") is second and second.status == jobs.DONE
    board.forget("calibrate")
    assert board.get("calibrate") is None
    gate2 = threading.Event()
    third = board.add("diagnose", jobs.Job("diagnosis", _steps, 3, gate=gate2)).start()
    board.clear()  # cancels what runs
    gate2.set()
    assert third.wait(5) and third.status == jobs.CANCELLED and board.get("diagnose") is None


def test_relay_runs_worker_calls_on_the_pumping_thread():
    main = threading.get_ident()
    relay = jobs.MainThreadRelay()

    class Device:
        projector = "P"

        def project(self, frame):
            assert threading.get_ident() == main, "project must run on the main thread"
            if frame is None:
                raise ImageError("bad frame")
            return frame * 2

    dev = jobs.RelayedDevice(Device(), relay)

    def engine(*, progress, cancel):
        out = [dev.project(i) for i in range(3)]
        with pytest.raises(ImageError):
            dev.project(None)
        return out, dev.projector

    job = jobs.Job("relay", engine).start()
    deadline = time.monotonic() + 5
    while not job.finished and time.monotonic() < deadline:
        relay.pump()
        time.sleep(0.005)
    assert job.result == ([0, 2, 4], "P")


def test_relay_wait_ends_when_the_job_is_cancelled():
    holder = []
    relay = jobs.MainThreadRelay(cancel=lambda: holder[0].cancelled(), poll_s=0.01)
    job = jobs.Job("waits", lambda *, progress, cancel: relay.call(lambda: 1))
    holder.append(job)
    job.start()
    time.sleep(0.05)
    job.cancel()  # nobody pumps: the worker must still stop
    assert job.wait(5) and job.status == jobs.CANCELLED
    assert relay.pump() == 1  # the abandoned call is dropped, not run


def test_a_cancel_that_kept_finished_work_says_so():
    """A step that keeps what it finished (a partial compensation, photographs, a show's frames) raises a cancel that
    says so; the snapshot carries it, so the sidebar reports what was kept instead of 'nothing was changed'."""
    def keeps(*, progress, cancel):
        raise Cancelled("compensation was cancelled after 1 of 2 target(s); the finished ones are kept", kept=True)

    def writes_nothing(*, progress, cancel):
        raise Cancelled("stage B (warp) was cancelled; no warp was stored")

    kept = jobs.Job("compensation", keeps).run().snapshot()
    assert kept.status == jobs.CANCELLED and kept.kept and "kept" in (kept.error or "")
    plain = jobs.Job("calibration", writes_nothing).run().snapshot()
    assert plain.status == jobs.CANCELLED and not plain.kept
