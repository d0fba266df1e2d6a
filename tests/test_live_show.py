"""``procam live-show``: a video file, stream or camera compensated frame by frame into a projector window on a
virtual X server (Xvfb), with its latency measured by a marker frame seen on the screen.

The loop's mechanics (dropping, stalls, holds, a lost camera) are timed with a stand-in solver of the real-time
solver's methods, whose speed the test sets."""

from __future__ import annotations

import http.server
import shutil
import threading
import time

import cv2
import numpy as np
import pytest

from procam.addon.cli.app import main
from procam.addon.errors import LiveError
from procam.addon.live.device import LiveSpec
from procam.addon.live.loopback import LoopbackCamera, LoopbackRig
from procam.addon.live.marker import ScreenWatch, marker_latencies, write_marker_clip
from procam.addon.live.source import FrameSource, SourceError, linear_frame
from procam.addon.steps import live_show
from procam.addon.steps.live_show import LiveShowOptions, latency_figures, run_live_show

ORIGIN = (40, 30)
DEVICE = f"live:position={ORIGIN[0]}:{ORIGIN[1]}"


class StandIn:
    """The real-time solver's methods: the frame resized to the projector's native frame, after ``delay`` s."""

    def __init__(self, stage, delay: float = 0.0) -> None:
        self.stage = stage
        proj = stage.calibration.rig.projector
        self.size = tuple(proj.intrinsics.size)
        self.camera_size = tuple(stage.calibration.rig.camera.intrinsics.size)
        self.delay, self.followed, self.solved = delay, [], 0

    def solve(self, image):
        t = time.perf_counter()
        frame = cv2.resize(image, self.size, interpolation=cv2.INTER_AREA)
        if self.delay:
            time.sleep(self.delay)
        self.solved += 1
        return type("Out", (), {"frames": [frame], "solve_ms": (time.perf_counter() - t) * 1000})()

    def follow(self, capture, shown=None):
        assert capture.shape == (self.camera_size[1], self.camera_size[0], 3) and capture.dtype == np.float32
        assert shown is not None and shown.frames[0].shape[:2] == self.size[::-1]
        self.followed.append(capture)


def stand_in(delay: float = 0.0, made: list | None = None):
    def make(stage, refine_steps, say):
        solver = StandIn(stage, delay)
        if made is not None:
            made.append(solver)
        return solver
    return make


@pytest.fixture(scope="module")
def cal(lab_calibration):
    folder, _, _ = lab_calibration(scale=0.1, samples=4)
    return folder


@pytest.fixture(scope="module")
def stored(live_calibration, tmp_path_factory):
    """The calibration of its own with its operator and approximate inverse stored (procam precompute --live)."""
    folder = tmp_path_factory.mktemp("live-show") / "cal"
    shutil.copytree(live_calibration(scale=0.1, samples=4), folder)
    return folder


def _size(cal) -> tuple[int, int]:
    from procam.addon.steps import calibrate
    return tuple(calibrate.read(cal).rig.projector.intrinsics.size)


def _grab(region) -> np.ndarray:
    import mss
    with mss.MSS() as screen:
        left, top, w, h = region
        return np.asarray(screen.grab({"left": left, "top": top, "width": w, "height": h}))[..., 2::-1]


class MjpegServer:
    """A network stream on 127.0.0.1 of numbered grey frames, which can pause (a stall) and resume."""

    def __init__(self, size=(64, 48), fps=30.0) -> None:
        self.size, self.fps = size, fps
        self.paused = threading.Event()
        self.sent = 0
        owner = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                try:
                    while True:
                        if owner.paused.is_set():
                            time.sleep(0.01)
                            continue
                        level = 40 + 8 * (owner.sent % 20)
                        w, h = owner.size
                        ok, jpeg = cv2.imencode(".jpg", np.full((h, w, 3), level, np.uint8))
                        self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n"
                                         % len(jpeg) + jpeg.tobytes() + b"\r\n")
                        self.wfile.flush()
                        owner.sent += 1
                        time.sleep(1.0 / fps)
                except (BrokenPipeError, ConnectionResetError):
                    pass

            def log_message(self, *args):
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/stream.mjpg"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()


# -- without a display --------------------------------------------------------------------------------------------

def test_the_device_of_a_live_show_may_name_no_camera():
    spec = LiveSpec.parse("live:display=1+2", camera_required=False)
    assert spec.camera is None and spec.displays == (1, 2)
    with pytest.raises(LiveError, match="say which camera.*only `procam live-show` runs without one"):
        LiveSpec.parse("live:display=1")
    assert LiveSpec.parse("live:camera=0,display=1", camera_required=False).camera == 0


def test_sources_are_parsed_and_converted(tmp_path):
    with pytest.raises(SourceError, match="neither a file that exists, a camera index"):
        FrameSource(str(tmp_path / "missing.mp4"))
    with pytest.raises(SourceError, match="folder or special file"):
        FrameSource(str(tmp_path))
    (tmp_path / "notes.mp4").write_text("not a video")
    with pytest.raises(SourceError, match="cannot open the source|delivered no frame"):
        FrameSource(str(tmp_path / "notes.mp4"))
    with pytest.raises(SourceError, match="cannot open the source '57'.*camera exists"):
        FrameSource("57")
    grey = np.array([[[0, 128, 255]]], np.uint8)  # BGR
    np.testing.assert_allclose(linear_frame(grey)[0, 0], [1.0, 0.2158605, 0.0], atol=1e-5)
    np.testing.assert_allclose(linear_frame(grey, "linear")[0, 0], [1.0, 128 / 255, 0.0], atol=1e-6)
    bgra = np.array([[[0, 128, 255, 7]]], np.uint8)  # a camera backend's four channels: alpha dropped
    np.testing.assert_allclose(linear_frame(bgra)[0, 0], [1.0, 0.2158605, 0.0], atol=1e-5)
    np.testing.assert_allclose(linear_frame(np.array([[128]], np.uint8))[0, 0], [0.2158605] * 3, atol=1e-5)


def test_a_file_plays_at_its_own_rate_and_only_the_newest_frame_is_kept(tmp_path):
    clip = write_marker_clip(tmp_path / "c.avi", (32, 24), 45, fps=30.0, markers=(44,))
    with FrameSource(str(clip)) as source:
        assert source.kind == "file" and source.fps == 30.0 and source.size == (32, 24)
        time.sleep(0.3)
        assert source.frames_in == 1  # the file waits for the show to start
        source.start()
        t0 = time.perf_counter()
        first = source.take()
        assert first is not None and first.number == 1 and first.arrived >= t0 - 0.01
        time.sleep(0.5)  # the show is busy: the frames of half a second arrive, only the newest is kept
        newest = source.take()
        assert newest is not None and 12 <= newest.number <= 18, newest.number
        assert source.dropped == newest.number - 2 and source.take() is None
        while not source.ended:
            time.sleep(0.02)
        played = time.perf_counter() - t0
        last = source.take()
    assert 1.3 <= played <= 1.9, played  # 45 frames at 30 fps, not as fast as they decode
    assert last is not None and last.number == 45 and last.image.mean() > 0.9  # the marker, linear white
    assert source.frames_in == 45


def test_a_bad_source_is_refused_before_any_window_opens(cal, tmp_path, capsys, monkeypatch):
    opened = []
    monkeypatch.setattr(live_show, "ProjectorWindow", lambda *a, **k: opened.append(a))
    assert main(["live-show", str(cal), "--source", str(tmp_path / "nope.mp4"), "--device", DEVICE]) == 2
    assert "neither a file that exists" in capsys.readouterr().err
    assert main(["live-show", str(cal), "--source", "rtsp://127.0.0.1:9/none", "--device", DEVICE]) == 2
    assert "cannot open the source 'rtsp://127.0.0.1:9/none'" in capsys.readouterr().err
    assert main(["live-show", str(cal), "--source", "0", "--device", "live:position=1:1+9:9"]) == 2
    assert "names 2 displays" in capsys.readouterr().err
    assert main(["live-show", str(cal), "--source", "0", "--device", DEVICE, "--duration", "0"]) == 2
    assert opened == []


# -- on a virtual X server ----------------------------------------------------------------------------------------

def test_a_clip_is_shown_frame_by_frame_and_a_marker_measures_the_latency(xvfb, cal, tmp_path):
    size = _size(cal)
    markers = (20, 50, 80)
    clip = write_marker_clip(tmp_path / "m.avi", (96, 72), 100, fps=30.0, markers=markers)
    statuses, said = [], []
    with ScreenWatch((*ORIGIN, *size)) as watch:
        report = run_live_show(LiveShowOptions(cal, str(clip), DEVICE, hold=0.3),
                               lambda m, f: said.append(m), on_status=statuses.append, solver_for=stand_in())
    assert report.stopped == "the video ended" and report.frames_in == 100
    assert report.shown + report.dropped == 100 and report.dropped <= 15, report.lines()
    assert any(m.startswith("the video ended: holding its last frame for 0.3 s") for m in report.said)
    assert 2 <= len(statuses) <= 5 and statuses[-1].line.startswith("in ") and "latency" in statuses[-1].line
    assert any(m.startswith("in ") and "dropped" in m for m in said)
    # Each marker frame was flipped, and then seen on the screen (within a few refreshes of its flip).
    by_number = {f.number: f for f in report.frames}
    shown = [by_number[n + 1] for n in markers if n + 1 in by_number]  # a dropped marker never reaches the screen
    assert len(shown) >= 2
    seen = marker_latencies([f.arrived for f in shown], watch.onsets)
    assert len(seen) == len(shown) == len(watch.onsets), (watch.onsets, shown)
    for onset, f in zip(watch.onsets, shown):
        assert f.flipped - 0.002 <= onset <= f.flipped + 0.15, (onset, f)
    figures = latency_figures(report)
    assert figures.median_ms is not None and 0 < figures.median_ms < 50 and figures.p95_ms < 100, figures
    assert max(seen) < 0.15


def test_a_solver_slower_than_the_source_drops_frames_and_never_queues(xvfb, cal, tmp_path):
    clip = write_marker_clip(tmp_path / "d.avi", (64, 48), 60, fps=30.0)
    made: list = []
    said: list = []
    report = run_live_show(LiveShowOptions(cal, str(clip), DEVICE, hold=0.0, range="auto"),
                           lambda m, f: said.append(m), solver_for=stand_in(0.1, made))
    assert "range: fitting the show's map to 30 frames of the source" in said  # every 2nd of 60, as show
    assert made[0].stage.range_map is not None
    # 2 s of video at 30 fps, a solve of 0.1 s: about 20 shown, the rest dropped
    assert report.frames_in == 60 and 10 <= report.shown <= 22 and report.dropped == 60 - report.shown
    lat_median, lat_p95 = report.latency_ms
    # Never a queue: a frame waits at most one solve before its own solve starts.
    assert lat_p95 < 250 and lat_median < 200, report.lines()
    assert made[0].solved == report.shown


def test_a_stream_that_stalls_is_held_then_black_and_resumes(xvfb, cal):
    size = _size(cal)
    server = MjpegServer()
    try:
        said = []

        def stall(message, fraction):
            said.append(message)
            if message.startswith("in ") and not server.paused.is_set() and len(said) < 8:
                server.paused.set()  # after the first status line, the stream stops for 1.5 s
                threading.Timer(1.5, server.paused.clear).start()

        grabs = []

        def watch(status):
            grabs.append((status.elapsed, float(_grab((*ORIGIN, *size)).mean())))

        report = run_live_show(LiveShowOptions(cal, server.url, DEVICE, hold=0.5, duration=4.5), stall,
                               on_status=watch, solver_for=stand_in())
    finally:
        server.close()
    assert report.stopped == "after 4.5 s (--duration)"
    assert "the source stalls (no new frame): holding its last frame for 0.5 s, then black" in report.said
    assert "the source stalled for 0.5 s: black until it resumes" in report.said
    assert any(m.startswith("the source resumed after 1.") for m in report.said), report.said
    assert report.shown > 60  # it went on after the stall
    assert any(level == 0.0 for _, level in grabs), grabs  # black during the stall
    assert grabs[-1][1] > 10  # and a picture again after it


def test_a_frame_of_another_size_is_said_once(xvfb, cal, tmp_path, monkeypatch):
    from procam.addon.live import source as source_module

    clip = write_marker_clip(tmp_path / "s.avi", (64, 48), 60, fps=30.0, dark=90)
    convert, count = source_module.linear_frame, []

    def narrower_after_20(img, encoding):  # a camera backend that changes its frame size mid-stream
        count.append(1)
        out = convert(img, encoding)
        return out[:, :40] if len(count) > 20 else out

    monkeypatch.setattr(source_module, "linear_frame", narrower_after_20)
    report = run_live_show(LiveShowOptions(cal, str(clip), DEVICE, hold=0.0), solver_for=stand_in())
    said = [m for m in report.said if "scaled into the display area" in m]
    assert said == ["the source's frames are now 40×48 (they were 64×48): scaled into the display area"]
    assert report.shown >= 55


def test_esc_stops_the_show_and_the_window_closes(xvfb, cal, tmp_path):
    import pygame

    clip = write_marker_clip(tmp_path / "e.avi", (64, 48), 300, fps=30.0, bright=200, dark=200)
    size = _size(cal)

    def esc(message, fraction):
        if message.startswith("in "):
            pygame.event.post(pygame.event.Event(pygame.KEYDOWN, key=pygame.K_ESCAPE))

    report = run_live_show(LiveShowOptions(cal, str(clip), DEVICE), esc, solver_for=stand_in())
    assert report.stopped == "Esc in the projector window" and 20 <= report.shown < 60
    time.sleep(0.1)
    assert _grab((*ORIGIN, *size)).max() == 0  # the window is gone


def test_a_camera_that_goes_away_leaves_the_show_open_loop(xvfb, cal, tmp_path):
    from procam.addon.steps import calibrate

    rig = calibrate.read(cal).rig
    size, cam_size = tuple(rig.projector.intrinsics.size), tuple(rig.camera.intrinsics.size)
    clip = write_marker_clip(tmp_path / "f.avi", (64, 48), 240, fps=30.0, dark=120, markers=())
    made: list = []
    camera = LoopbackCamera(LoopbackRig((*ORIGIN, *size), cam_size))
    try:
        def lose(message, fraction):
            if message.startswith("in ") and len(made[0].followed) >= 2:
                camera.close()

        report = run_live_show(LiveShowOptions(cal, str(clip), f"{DEVICE},camera={camera.url},encoding=linear",
                                               hold=0.0), lose, solver_for=stand_in(made=made))
    finally:
        camera.close()
    assert report.closed_loop and report.follows == len(made[0].followed) >= 2
    assert any(m.startswith("the camera was lost") and m.endswith("the show goes on open loop")
               for m in report.said), report.said
    assert report.stopped == "the video ended" and report.shown > 150  # it went on to the end


def test_the_real_time_solver_shows_a_clip_end_to_end(xvfb, stored, tmp_path, capsys):
    """The real solver: every frame compensated and flipped, the marker frames seen on the screen after their
    flips, the latency measured; then the command prints its report and exits 0."""
    size = _size(stored)
    markers = (15, 45)
    clip = write_marker_clip(tmp_path / "m.avi", (96, 72), 60, fps=30.0, markers=markers)
    with ScreenWatch((*ORIGIN, *size), seen=40.0, dark=20.0) as watch:
        report = run_live_show(LiveShowOptions(stored, str(clip), DEVICE, hold=0.2))
    assert report.stopped == "the video ended" and report.frames_in == 60
    assert report.shown >= 50 and report.shown + report.dropped == 60, report.lines()
    by_number = {f.number: f for f in report.frames}
    shown = [by_number[n + 1] for n in markers if n + 1 in by_number]
    assert shown and len(watch.onsets) == len(shown), (watch.onsets, shown)
    for onset, f in zip(watch.onsets, shown):
        assert f.flipped - 0.002 <= onset <= f.flipped + 0.15, (onset, f)
    seen = marker_latencies([f.arrived for f in shown], watch.onsets)
    figures = latency_figures(report)
    solve_median, _ = report.solve_ms
    with capsys.disabled():
        print(f"real solver under Xvfb: solve {solve_median:.1f} ms median; latency source → flip "
              f"{figures.median_ms:.1f} ms median, {figures.p95_ms:.1f} ms p95; source → screen (markers) "
              f"{', '.join(f'{v * 1000:.0f}' for v in seen)} ms; {figures.dropped} dropped of {figures.frames_in}")
    assert figures.median_ms < 200 and len(seen) == len(shown)
    # A picture of another aspect than the display area given: stretched into it, said once.
    wide = run_live_show(LiveShowOptions(stored, str(clip), DEVICE, hold=0.0, duration=1.0, area=(8, 8, 48, 24)))
    said = [m for m in wide.said if "stretched to the display area" in m]
    assert len(said) == 1 and said[0].startswith("warning: the live source's frame (96×72"), wide.said
    # Closed loop: θ follows a loopback camera filming the window, each camera frame with the solve it shows.
    from procam.addon.steps import calibrate
    cam_size = tuple(calibrate.read(stored).rig.camera.intrinsics.size)
    with LoopbackCamera(LoopbackRig((*ORIGIN, *size), cam_size)) as camera:
        closed = run_live_show(LiveShowOptions(stored, str(clip), f"{DEVICE},camera={camera.url},encoding=linear",
                                               hold=0.0, correction=tmp_path / "learned.npz"))
    assert closed.closed_loop and closed.follows >= 10 and closed.stopped == "the video ended", closed.lines()
    # What it learned while following is kept, and a show without a camera starts from it.
    assert (tmp_path / "learned.npz").is_file() and any("learned while following" in m for m in closed.said)
    said: list[str] = []
    run_live_show(LiveShowOptions(stored, str(clip), DEVICE, hold=0.0, duration=0.5,
                                  correction=tmp_path / "learned.npz"), lambda m, f: said.append(m))
    assert any(m.startswith("using the correction learned in") for m in said), said
    capsys.readouterr()
    assert main(["live-show", str(stored), "--source", str(clip), "--device", DEVICE, "--hold", "0",
                 "--duration", "1", "--surround", "0.2,0.2,0.2"]) == 0  # (the surround's frames: test_realtime.py)
    out = capsys.readouterr().out
    assert out.startswith("live show: ") and "frames shown of" in out and "stopped: after 1 s (--duration)" in out


# -- several projectors -------------------------------------------------------------------------------------------

TWO_AT = (ORIGIN, (300, 30))
TWO = "live:position=" + "+".join(f"{x}:{y}" for x, y in TWO_AT)


@pytest.fixture(scope="module")
def two_stored(two_projector_lab):
    """The two-projector calibration (projectors 160×120 side by side, 20 % overlap) with both inverses stored."""
    folder = two_projector_lab / "cal"
    assert main(["precompute", str(folder), "--live"]) == 0
    return folder


def _gradient_clip(path, size=(96, 72), frames=60, fps=30.0):
    """A clip dark on the left and bright on the right, so that each projector's share is a picture of its own."""
    w, h = size
    ramp = np.linspace(30, 230, w).astype(np.uint8)
    frame = np.repeat(np.repeat(ramp[None, :, None], h, axis=0), 3, axis=2)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    for _ in range(frames):
        writer.write(frame)
    writer.release()
    return path


def _recording(made: list):
    def make(stage, refine_steps, say):
        solver = live_show.open_solver(stage, refine_steps, say)
        made.append(solver)
        return solver
    return make


def test_a_rig_of_two_projectors_shows_each_ones_frame_in_its_own_window(xvfb, two_stored, tmp_path, capsys,
                                                                          monkeypatch):
    """The real solver on a two-projector calibration: two windows at their positions, each showing the frame the
    solver returned for its projector (different pictures, neither black); the command exits 0 with its report;
    a device of one window is refused before any window opens; a projector dark in the display area shows black."""
    from procam.addon.steps import calibrate

    sizes = [tuple(p.intrinsics.size) for p in calibrate.read(two_stored).rig.projectors]
    regions = [(*at, *size) for at, size in zip(TWO_AT, sizes)]
    clip = _gradient_clip(tmp_path / "g.avi")
    made: list = []
    seen: list = []

    def grab(status):  # on the loop's thread, after its last flip: the windows show the solver's last frames
        seen.append(([_grab(r) for r in regions], [f[..., :3].copy() for f in made[0].last.frames]))  # RGB(X)

    report = run_live_show(LiveShowOptions(two_stored, str(clip), TWO, hold=0.0), on_status=grab,
                           solver_for=_recording(made))
    assert report.stopped == "the video ended" and report.frames_in == 60
    assert report.shown >= 30 and report.shown + report.dropped == 60, report.lines()
    assert seen, report.lines()
    screens, frames = seen[-1]
    for screen, frame in zip(screens, frames):
        assert screen.shape == frame.shape and frame.mean() > 10
        assert abs(float(screen.mean()) - float(frame.mean())) < 1.0, (screen.mean(), frame.mean())
        assert np.abs(screen.astype(np.int16) - frame).mean() < 1.0
    assert np.abs(frames[0].astype(np.int16) - frames[1]).mean() > 10  # each projector its own picture
    with capsys.disabled():
        print(f"two projectors under Xvfb: {report.shown} of {report.frames_in} shown, solve "
              f"{report.solve_ms[0]:.1f} ms median, latency {report.latency_ms[0]:.1f} ms median; windows' mean "
              f"levels {', '.join(f'{s.mean():.1f}' for s in screens)} (solver "
              f"{', '.join(f'{f.mean():.1f}' for f in frames)})")
    # The command: its report, exit 0.
    capsys.readouterr()
    assert main(["live-show", str(two_stored), "--source", str(clip), "--device", TWO, "--hold", "0",
                 "--duration", "1"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("live show: ") and "frames shown of" in out and "stopped: after 1 s (--duration)" in out
    # One window for two projectors: refused before any window opens.
    opened: list = []
    with monkeypatch.context() as m:
        m.setattr(live_show, "ProjectorWindow", lambda *a, **k: opened.append(a))
        assert main(["live-show", str(two_stored), "--source", str(clip), "--device", DEVICE]) == 2
    assert "this rig has 2 projectors but the live device names 1 display(s)" in capsys.readouterr().err
    assert opened == []
    # A display area only projector 1 reaches (camera columns 20–50): projector 2's window stays black.
    dark: list = []
    # 2 s: a status comes every STATUS_EVERY (1 s), and a show of exactly 1 s could end before its first one
    report = run_live_show(LiveShowOptions(two_stored, str(clip), TWO, hold=0.0, duration=2.0, area=(20, 30, 30, 30)),
                           on_status=lambda s: dark.append([_grab(r) for r in regions]))
    assert "warning: projector 2 lights nothing inside the display area: its frame is black" in report.said
    assert report.shown >= 10 and dark, report.lines()
    assert dark[-1][0].mean() > 10 and dark[-1][1].max() == 0
