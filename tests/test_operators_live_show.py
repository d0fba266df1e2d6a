"""Start/Stop Live Show through bpy.ops on a virtual X server: a short clip compensated by the real-time solver of a
small calibration with its approximate inverse stored, the Live panel's measured figures while the show runs and
its report after; Stop Live Show and Esc in Blender ending the show with its report and its window closed; a bad
source reported as an error, not a traceback; and the reasons the buttons are greyed out."""

import shutil
import time
from types import SimpleNamespace

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from procam.addon import jobs  # noqa: E402
from procam.addon.cli.app import main  # noqa: E402
from procam.addon.live.marker import write_marker_clip  # noqa: E402

ORIGIN = (40, 30)  # the projector window on the virtual screen


@pytest.fixture(scope="module")
def stored(live_calibration, tmp_path_factory):
    """A small calibration (projector 80×60) of its own with its operator and approximate inverse stored."""
    folder = tmp_path_factory.mktemp("live-show-ops") / "cal"
    shutil.copytree(live_calibration(scale=0.1, samples=4), folder)
    return folder


def _window(folder) -> tuple[int, int, int, int]:
    from procam.addon.steps import calibrate

    return (*ORIGIN, *calibrate.read(folder).rig.projector.intrinsics.size)


def _grab(region) -> np.ndarray:
    import mss

    with mss.MSS() as screen:
        left, top, w, h = region
        return np.asarray(screen.grab({"left": left, "top": top, "width": w, "height": h}))[..., 2::-1]


def _scene(calibration, source):
    scene = bpy.context.scene
    scene.procam_calibration_dir = str(calibration)
    scene.procam_live_source = str(source)
    scene.procam_live_placement = "POSITION"
    scene.procam_live_position = f"{ORIGIN[0]}:{ORIGIN[1]}"
    scene.procam_live_hold = 0.0
    return scene


def _wait_for_status(job, timeout=60.0):
    from procam.operators.live_show import SHOW_STATUS

    end = time.perf_counter() + timeout
    while SHOW_STATUS.latest is None or SHOW_STATUS.latest.shown == 0:
        assert not job.finished, job.snapshot().error
        assert time.perf_counter() < end, "no status line from the live show"
        time.sleep(0.05)
    return SHOW_STATUS.latest


def test_the_buttons_say_why_they_are_greyed_out(registered, tmp_path):
    from procam.operators.live_show import PROCAM_OT_live_show_start as start
    from procam.operators.live_show import show_device

    scene = bpy.context.scene
    assert "no calibration" in start.why_not(scene) and not bpy.ops.procam.live_show_start.poll()
    (tmp_path / "calibration.json").write_text("{}")  # enough for the poll's "is there a calibration" check
    scene.procam_calibration_dir = str(tmp_path)
    assert "Source" in start.why_not(scene)
    scene.procam_live_source = "0"
    assert start.why_not(scene) is None and bpy.ops.procam.live_show_start.poll()
    assert show_device(scene) == "live:display=1"  # open loop: the Live panel's window alone
    scene.procam_live_follow_camera, scene.procam_live_camera = True, ""
    assert "Follow Camera needs the Live panel's camera" in start.why_not(scene)
    scene.procam_live_camera = "2"
    assert show_device(scene) == "live:camera=2,display=1,average=1,encoding=srgb,latency=auto"
    assert not bpy.ops.procam.live_show_stop.poll()  # nothing runs
    gate = jobs.Job("capture", lambda *, progress, cancel: None)
    jobs.BOARD.add("capture", gate)
    assert not bpy.ops.procam.live_show_start.poll()  # another job runs
    gate.run()
    assert bpy.ops.procam.live_show_start.poll()


def test_a_bad_source_is_an_error_not_a_traceback(registered, stored, tmp_path):
    from procam.panels.live import show_summary

    _scene(stored, tmp_path / "nope.mp4")
    with pytest.raises(RuntimeError, match="neither a file that exists") as err:
        bpy.ops.procam.live_show_start()
    assert "Traceback" not in str(err.value)
    assert jobs.BOARD.get("live_show").status == jobs.FAILED and not show_summary().ok


def test_start_shows_the_clip_and_the_panel_its_frame_rate(registered, xvfb, stored, tmp_path, monkeypatch):
    """Start Live Show as the operator runs it (here in the foreground: no event loop in background mode): the
    clip compensated and shown; while it runs the panel's figures are the last second's, after it the report's."""
    from procam.panels.live import show_summary

    clip = write_marker_clip(tmp_path / "c.avi", (96, 72), 75, fps=30.0, dark=120)
    _scene(stored, clip)
    seen, real = [], jobs.Job.progress

    def progress(self, message, fraction):  # each status line: what the panel and the screen show then
        if message.startswith("in "):
            seen.append((show_summary(), float(_grab(_window(stored)).max())))
        return real(self, message, fraction)

    monkeypatch.setattr(jobs.Job, "progress", progress)
    assert bpy.ops.procam.live_show_start() == {"FINISHED"}
    report = jobs.BOARD.get("live_show").result
    assert report.stopped == "the video ended" and report.shown > 30 and report.frames_in == 75, report.lines()
    running = [s for s, _ in seen if s.data]  # the first status line comes before its figures are kept
    assert running and all(s.data["fps"] > 0 and s.data["shown"] > 0 for s in running), seen
    assert running[-1].headline.endswith(f"fps: shown {running[-1].data['shown']}, dropped "
                                         f"{running[-1].data['dropped']}")
    assert max(level for _, level in seen) > 0  # the window showed the compensated clip
    after = show_summary()
    assert after.ok and after.headline.startswith(f"Live show: {report.shown} frames shown of 75 in")
    assert after.data["fps"] == pytest.approx(report.fps) and after.data["fps"] > 5
    assert after.data["latency_ms"] is not None and after.data["latency_ms"] > 0
    assert "stopped: the video ended" in after.lines
    print(f"Start Live Show, 80×60 under Xvfb: {after.headline}; {after.lines[0]}")
    time.sleep(0.1)
    assert _grab(_window(stored)).max() == 0  # the window closed


@pytest.mark.parametrize("how", ["stop", "esc"])
def test_stop_or_esc_ends_the_show_with_its_report_and_the_window_closes(registered, xvfb, stored, tmp_path, how):
    """The show in a worker thread, as in the UI: Stop Live Show (or Esc, through the job operator's modal) ends it
    with its report, not a cancel, and the window is gone."""
    from procam.operators.live_show import (STOPPED_IN_BLENDER, PROCAM_OT_live_show_start, play_live_show,
                                            show_options)
    from procam.panels.live import show_summary

    clip = write_marker_clip(tmp_path / "s.avi", (64, 48), 600, fps=30.0, dark=120)  # 20 s: it never ends alone
    scene = _scene(stored, clip)
    job = jobs.BOARD.add("live_show", jobs.Job("live show", play_live_show, show_options(scene))).start()
    try:
        status = _wait_for_status(job)
        assert status.fps > 0 and _grab(_window(stored)).max() > 0
        assert not bpy.ops.procam.live_show_start.poll() and bpy.ops.procam.live_show_stop.poll()
        assert not show_summary().ok and show_summary().data["shown"] > 0
        if how == "stop":
            assert bpy.ops.procam.live_show_stop() == {"FINISHED"}
        else:
            modal = PROCAM_OT_live_show_start.modal(SimpleNamespace(_job=job), bpy.context,
                                                    SimpleNamespace(type="ESC", value="PRESS"))
            assert modal == {"RUNNING_MODAL"}
        assert job.wait(15)
    finally:
        job.cancel()
        job.wait(15)
    assert job.status == jobs.DONE, job.snapshot().error
    report = job.result
    assert report.stopped == STOPPED_IN_BLENDER and report.shown >= status.shown and report.seconds < 15
    assert show_summary().ok and f"stopped: {STOPPED_IN_BLENDER}" in show_summary().lines
    time.sleep(0.1)
    assert _grab(_window(stored)).max() == 0  # the window closed
    assert not bpy.ops.procam.live_show_stop.poll()


def test_start_shows_a_rig_of_two_projectors_in_two_windows(registered, xvfb, two_projector_lab, tmp_path,
                                                             monkeypatch):
    """Start Live Show on a two-projector calibration: the Position field's two windows become the device string,
    and each window shows its projector's frame; the field's one window for two projectors is refused, saying how
    to give two."""
    from procam.addon.steps import calibrate
    from procam.operators.live_show import show_device

    cal = two_projector_lab / "cal"
    assert main(["precompute", str(cal), "--live"]) == 0
    at = (ORIGIN, (300, 30))
    regions = [(*xy, *p.intrinsics.size) for xy, p in zip(at, calibrate.read(cal).rig.projectors)]
    scene = _scene(cal, write_marker_clip(tmp_path / "c.avi", (96, 72), 45, fps=30.0, dark=120))
    with pytest.raises(RuntimeError, match="this rig has 2 projectors but the live device names 1 display"):
        bpy.ops.procam.live_show_start()
    scene.procam_live_position = "40:30 + 300:30"
    assert show_device(scene) == "live:position=40:30+300:30"
    seen, real = [], jobs.Job.progress

    def progress(self, message, fraction):  # each status line: what the two windows show then
        if message.startswith("in "):
            seen.append([_grab(r) for r in regions])
        return real(self, message, fraction)

    monkeypatch.setattr(jobs.Job, "progress", progress)
    assert bpy.ops.procam.live_show_start() == {"FINISHED"}
    report = jobs.BOARD.get("live_show").result
    assert report.stopped == "the video ended" and report.shown > 20 and report.frames_in == 45, report.lines()
    assert seen, report.lines()
    first, second = seen[-1]
    assert first.mean() > 5 and second.mean() > 5 and np.abs(first.astype(np.int16) - second).mean() > 1
