"""The live loop with real parts: a projector window on a virtual X server (Xvfb), a camera that is a real HTTP
client (OpenCV VideoCapture) of a loopback MJPEG server filming that window, closed-loop compensation through them."""

from __future__ import annotations

import json
import time
from types import SimpleNamespace

import numpy as np
import pytest

from procam.addon.capture.format import CaptureSet
from procam.addon.capture.targets import natural_target
from procam.addon.cli.app import main
from procam.addon.errors import Cancelled, CaptureError, LiveError
from procam.addon.live.rig_options import LiveRigOptions
from procam.addon.imageio import write_image
from procam.addon.live.camera import CameraClient, parse_source
from procam.addon.live.device import LiveDevice, LiveSpec, open_windows
from procam.addon.live.loopback import LoopbackCamera, LoopbackRig, painted_wall
from procam.addon.live.window import ProjectorWindow, list_displays
from procam.addon.rig.model import Projector, projector_intrinsics_from_throw
from procam.addon.steps import stage_c
from procam.addon.steps.live import LiveCaptureOptions, run_live_capture
from tests.conftest import XVFB_SCREEN as SCREEN  # the screen of the shared xvfb fixture

ORIGIN = (40, 30)  # where the projector window sits on the virtual screen
SIZE = (256, 192)  # projector and camera


# -- without a display --------------------------------------------------------------------------------------------

def test_live_spec_parsing():
    spec = LiveSpec.parse("live:camera=http://127.0.0.1:8080/a,b.mjpg,position=40:30,average=4,encoding=linear")
    assert spec.camera == "http://127.0.0.1:8080/a,b.mjpg" and spec.position == (40, 30) and spec.display is None
    assert spec.average == 4 and spec.encoding == "linear" and spec.latency is None
    spec = LiveSpec.parse("live:camera=0,latency=0.2,noise=0.003,size=1280x720")
    assert spec.camera == 0 and spec.display == 0 and spec.latency == 0.2 and spec.noise == 0.003
    assert spec.size == (1280, 720)
    for bad, message in (("live:display=1", "say which camera"), ("live:camera=0,average=0", "average must be"),
                         ("live:camera=0,average=2,noise=0.01", "not both"), ("live:camera=0,encoding=hdr", "srgb"),
                         ("live:camera=0,display=x", "display= takes whole numbers"),
                         ("live:camera=/nonexistent/video9", "neither"),
                         ("live:camera=0,camera=1", "twice"), ("live:bogus", "key=value")):
        with pytest.raises(LiveError, match=message):
            LiveSpec.parse(bad)


def test_live_rig_of_several_projectors_is_refused_before_any_window_opens(monkeypatch):
    spec = LiveSpec.parse("live:camera=0,display=1+2")
    assert spec.display == 1 and spec.displays == (1, 2) and spec.windows == 2
    assert spec.placements() == [(1, None), (2, None)]
    assert LiveSpec.parse("live:camera=0,display=1").displays == ()
    spec = LiveSpec.parse("live:camera=0,position=40:30+300:30")
    assert spec.position == (40, 30) and spec.positions == ((40, 30), (300, 30))
    assert spec.placements() == [(None, (40, 30)), (None, (300, 30))]
    assert LiveSpec.parse("live:camera=0,position=4:3").placements() == [(None, (4, 3))]
    proj = Projector(projector_intrinsics_from_throw(*SIZE, 1.2))
    beside = proj.camera_from_projector.copy()
    beside[0, 3] += 0.4
    other = Projector(proj.intrinsics, beside)
    with pytest.raises(LiveError, match="rig has 2 projectors but the live device names 1 display.*display=1\\+2"):
        LiveDevice("live:camera=57,display=1", proj, others=(other,))  # camera 57 would fail later: not reached
    with pytest.raises(LiveError, match="rig has 3 projectors but the live device names 2 display"):
        LiveDevice("live:camera=57,position=1:1+300:1", proj, others=(other, other))
    with pytest.raises(LiveError, match="2 displays .* for a rig of one projector"):
        LiveDevice("live:camera=57,display=1+2", proj)
    with pytest.raises(LiveError, match="3 displays \\(0\\+1\\+2\\) for a rig of 2 projectors"):
        LiveDevice("live:camera=57,display=0+1+2", proj, others=(other,))
    with pytest.raises(LiveError, match="not both"):
        LiveSpec.parse("live:camera=0,display=1+2,position=3:4")
    assert main(["live-check", "--device", "live:camera=57,display=1", "--projector-width", "64",
                 "--projector-height", "48", "--projectors", "2"]) == 2
    # Stage C and evaluation open a live device of every projector of the calibration's rig.
    monkeypatch.setattr(stage_c, "camera_lens_of", lambda calibration: None)
    calibration = SimpleNamespace(rig=SimpleNamespace(projector=proj, others=(other,),
                                                   camera=SimpleNamespace(intrinsics=proj.intrinsics)))
    with pytest.raises(LiveError, match="rig has 2 projectors but the live device names 1 display"):
        stage_c.device_pipeline("live:camera=57,display=1", calibration)
    with pytest.raises(LiveError, match="display 1 is named twice"):
        LiveSpec.parse("live:camera=0,display=1+1")
    with pytest.raises(LiveError, match="position 3:4 is named twice"):
        LiveSpec.parse("live:camera=0,position=3:4+3:4")
    with pytest.raises(LiveError, match="position is X:Y"):
        LiveSpec.parse("live:camera=0,position=3:4+5")


def test_sources():
    assert parse_source("2") == 2 and parse_source("rtsp://cam/stream") == "rtsp://cam/stream"
    with pytest.raises(LiveError, match="cannot open camera 57"):
        CameraClient(57)


def test_no_display_is_a_clear_error(run_python):
    proc = run_python("""
        from procam.addon.cli.app import main
        raise SystemExit(main(["live-check", "--device", "live:camera=0,display=0", "--projector-width", "64",
                               "--projector-height", "48"]))
    """, env={"DISPLAY": "", "WAYLAND_DISPLAY": "", "SDL_VIDEODRIVER": "x11"})
    assert proc.returncode == 2, proc.stderr
    assert "no display to open the projector window on" in proc.stderr and "Traceback" not in proc.stderr


def test_stage_c_names_the_live_device():
    from procam.addon.steps.stage_c import device_kind
    assert device_kind("live:camera=0,display=1") == "live"
    with pytest.raises(CaptureError, match="live:camera=SOURCE,display=N"):
        device_kind("webcam:0")


# -- on a virtual X server ----------------------------------------------------------------------------------------

def _grab(region: tuple[int, int, int, int]) -> np.ndarray:
    import mss
    with mss.MSS() as screen:
        left, top, w, h = region
        return np.asarray(screen.grab({"left": left, "top": top, "width": w, "height": h}))[..., 2::-1]


def test_window_shows_frames_pixel_for_pixel(xvfb):
    assert list_displays()[0][1:3] == SCREEN
    frame = np.random.default_rng(1).random((48, 64, 3)).astype(np.float32)
    window = ProjectorWindow((64, 48), position=(100, 70))
    try:
        window.show(frame)
        time.sleep(0.1)
        assert window.position == (100, 70)
        shown = _grab((100, 70, 64, 48))
        np.testing.assert_array_equal(shown, np.rint(frame * 255).astype(np.uint8))
    finally:
        window.close()
    with pytest.raises(LiveError, match="native resolution"):
        ProjectorWindow((64, 48), display=0)
    with pytest.raises(LiveError, match="there is no display 3"):
        ProjectorWindow(SCREEN, display=3)
    window = ProjectorWindow(SCREEN, display=0)  # a display of the native size is covered exactly
    try:
        assert window.position == (0, 0)
    finally:
        window.close()
    # With several projectors the message names the one whose display does not fit, and no window stays open.
    fits, small = (SimpleNamespace(intrinsics=SimpleNamespace(size=size)) for size in (SCREEN, (64, 48)))
    with pytest.raises(LiveError, match=r"display 0 is \d+×\d+ but projector 2's native frame is 64×48"):
        open_windows(LiveSpec(camera=None, display=0, displays=(0, 0)), [fits, small], lambda *a: None)


def _projector(size=SIZE) -> Projector:
    return Projector(projector_intrinsics_from_throw(size[0], size[1], 1.25, 0.0, 0.15))


@pytest.mark.parametrize("delay", [0.15])
def test_latency_is_measured_and_no_capture_shows_the_previous_frame(xvfb, delay):
    loop, _, _ = painted_wall(SIZE, ORIGIN, delay_s=delay)
    loop.noise = 0.0
    with LoopbackCamera(loop) as cam:  # noqa: SIM117 (the device is opened on the camera's URL)
        with LiveDevice(f"live:camera={cam.url},position={ORIGIN[0]}:{ORIGIN[1]},encoding=linear",
                        _projector()) as device:
            frame = device.report.camera_frame_s
            measured = sorted(device.report.latencies_s)
            # The first frame grabbed after the flip is up to one camera frame later; transport adds a little.
            assert delay <= measured[1] <= delay + frame + 0.03, device.report.lines()
            lit = loop.gain[..., 1] > 0  # every camera pixel; compare the picture's mean with the level's
            levels = [0.1, 0.9, 0.2, 0.8, 0.3, 0.7, 0.15, 0.95]
            seen = []
            for level in levels:
                shot = device.project(np.full((SIZE[1], SIZE[0], 3), level, np.float32))
                seen.append(float(shot[lit].mean()))
    # The footprint covers a fixed share of the picture: the mean is an affine function of the level, and a
    # capture that held the previous frame would break the order of these strongly alternating levels.
    slope, icpt = np.polyfit(levels, seen, 1)
    residual = np.abs(np.asarray(seen) - (slope * np.asarray(levels) + icpt))
    assert slope > 0.1 and residual.max() < 0.05 * slope, (levels, seen)


def test_auto_exposure_is_refused(xvfb):
    loop, _, _ = painted_wall(SIZE, ORIGIN, auto_exposure=True)
    with LoopbackCamera(loop) as cam, pytest.raises(LiveError, match="exposure is not locked"):
        LiveDevice(f"live:camera={cam.url},position={ORIGIN[0]}:{ORIGIN[1]},encoding=linear", _projector())


def test_camera_that_sees_nothing_is_refused(xvfb):
    loop, _, _ = painted_wall(SIZE, ORIGIN)
    loop.region = (520, 380, *SIZE)  # films a part of the screen where the window is not
    with LoopbackCamera(loop) as cam, pytest.raises(LiveError, match="did not see the projector"):
        LiveDevice(f"live:camera={cam.url},position={ORIGIN[0]}:{ORIGIN[1]},encoding=linear", _projector())


def test_live_capture_calibrate_and_closed_loop_compensation(xvfb, tmp_path, capsys, monkeypatch):
    """A whole calibration set captured live (interrupted and resumed), calibrated, and compensated closed loop."""
    # a short delay: the latency's own test weighs longer ones; every capture of the set waits it out
    loop, depth, truth = painted_wall(SIZE, ORIGIN, delay_s=0.05)
    np.save(tmp_path / "depth.npy", depth)
    target = write_image(tmp_path / "city.png", natural_target("city", (160, 160)))
    with LoopbackCamera(loop) as cam:
        device = f"live:camera={cam.url},position={ORIGIN[0]}:{ORIGIN[1]},encoding=linear,average=2"
        projector = Projector(truth.intrinsics, input_size=truth.input_size)
        options = LiveCaptureOptions(device, projector, tmp_path / "set", camera_fov=58.0,
                                     depth_path=tmp_path / "depth.npy")
        calls = []
        stopped = r"11 of \d+ frames are captured and kept in .*run the same command to resume"
        with pytest.raises(Cancelled, match=stopped):
            run_live_capture(options, cancel=lambda: len(calls) > 10,
                             progress=lambda m, f: calls.append(m) if m.startswith("capturing") else None)
        kept = sorted((tmp_path / "set.session" / "photos").glob("*.png"))
        assert len(kept) == 11 and not (tmp_path / "set").exists()
        args = ["--device", device, "--projector-width", str(SIZE[0]), "--projector-height", str(SIZE[1]),
                "--input-width", str(truth.input_size[0]), "--input-height", str(truth.input_size[1]),
                "--throw-ratio", "1.25", "--shift-y", "0.15"]
        assert main(["capture", *args, "--seed", "3", "--camera-fov", "58", "--depth", str(tmp_path / "depth.npy"),
                     "--out", str(tmp_path / "set")]) == 2  # other settings than the session's: refused
        assert "other settings" in capsys.readouterr().err
        assert main(["capture", *args, "--camera-fov", "58", "--depth", str(tmp_path / "depth.npy"),
                     "--out", str(tmp_path / "set")]) == 0
        err = capsys.readouterr().err
        assert "resuming the live session" in err and "11 of" in err
        assert not (tmp_path / "set.session").exists()
        captures = CaptureSet.load(tmp_path / "set")
        assert captures.camera.intrinsics.size == SIZE and "exposure" in captures.notes

        assert main(["calibrate", str(tmp_path / "set"), "--out", str(tmp_path / "cal")]) == 0
        cal = json.loads((tmp_path / "cal" / "calibration.json").read_text())
        pose = np.asarray(cal["camera_from_projector"])
        assert np.linalg.norm(pose[:3, 3] - truth.camera_from_projector[:3, 3]) < 0.01

        # the capture measured the latency; later steps are given it, as a crew gives what it measured once
        known = f"{device},latency=0.1"
        assert main(["compensate", str(tmp_path / "cal"), str(target), "--device", known, "--iterations", "40",
                     "--out", str(tmp_path / "comp")]) == 0
        assert main(["evaluate", str(tmp_path / "cal"), "--inputs", str(tmp_path / "comp"), "--targets", str(target),
                     "--device", known, "--out", str(tmp_path / "eval")]) == 0
        # A camera at another resolution than the calibration's is refused before any work, as soon as it connects
        # (before the seconds of measuring its latency).
        other = LoopbackRig((*ORIGIN, *SIZE), (SIZE[0] // 2, SIZE[1] // 2))
        monkeypatch.setattr(LiveDevice, "_latency", lambda *a: pytest.fail("latency measured before the size check"))
        with LoopbackCamera(other) as small:
            assert main(["compensate", str(tmp_path / "cal"), str(target), "--device",
                         f"live:camera={small.url},position={ORIGIN[0]}:{ORIGIN[1]},encoding=linear",
                         "--out", str(tmp_path / "comp2")]) == 2
        assert "camera delivers 128×96 frames but the calibration's camera is 256×192" in capsys.readouterr().err
    metrics = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    city = metrics["targets"][0]
    assert city["psnr"] >= city["uncompensated"]["psnr"] + 6.0, city


def test_a_stream_that_stops_keeps_the_session_and_resumes(xvfb, tmp_path):
    size = (160, 120)
    loop, _, truth = painted_wall(size, ORIGIN)
    projector = Projector(truth.intrinsics, input_size=truth.input_size)

    def options(url: str) -> LiveCaptureOptions:
        return LiveCaptureOptions(f"live:camera={url},position={ORIGIN[0]}:{ORIGIN[1]},encoding=linear", projector,
                                  tmp_path / "set", validation=False, camera_fov=58.0)

    cam = LoopbackCamera(loop)
    try:
        def stop_at_sixth(message: str, fraction: float) -> None:
            if message.startswith("capturing frame 6/"):
                cam.close()  # the network camera goes away mid-session

        with pytest.raises(LiveError, match="stopped delivering frames|delivered 0 of"):
            run_live_capture(options(cam.url), progress=stop_at_sixth)
    finally:
        cam.close()
    assert len(list((tmp_path / "set.session" / "photos").glob("*.png"))) == 5
    assert not (tmp_path / "set").exists()
    with LoopbackCamera(loop) as again:  # back, on another port: the session resumes at frame 6
        said = []
        captures = run_live_capture(options(again.url), progress=lambda m, f: said.append(m))
    assert any("5 of" in m and "already captured" in m for m in said)
    assert sum(m.startswith("capturing") for m in said) == len(captures) - 5


def test_esc_in_the_projector_window_stops_and_the_window_is_given_back(xvfb):
    import pygame

    window = ProjectorWindow((64, 48), position=(100, 70))
    try:
        window.show(np.zeros((48, 64, 3), np.float32))
        pygame.event.post(pygame.event.Event(pygame.KEYDOWN, key=pygame.K_ESCAPE))
        with pytest.raises(LiveError, match="Esc"):
            window.show(np.ones((48, 64, 3), np.float32))
    finally:
        window.close()
    time.sleep(0.1)
    # The screen area is the X root's again (black), not the last white frame.
    assert _grab((100, 70, 64, 48)).max() == 0


def test_the_live_panels_rig_is_one_device_string_checked_field_by_field():
    rig = LiveRigOptions(camera=" http://10.0.0.5:8080/video ", placement="POSITION", position="1920:-40 + 0:0",
                         average=8, encoding="linear", latency_auto=False, latency=0.125)
    assert rig.device() == ("live:camera=http://10.0.0.5:8080/video,position=1920:-40+0:0,average=8,"
                            "encoding=linear,latency=0.125")
    assert LiveRigOptions().device() == "live:camera=0,display=1,average=1,encoding=srgb,latency=auto"
    with pytest.raises(LiveError, match="Live panel's Display must be a display index"):
        LiveRigOptions(display="1,camera=2").device()
    with pytest.raises(LiveError, match="no live camera"):
        LiveRigOptions(camera=" ").device()


def test_no_display_is_refused_even_where_sdl_falls_back_to_drawing_off_screen(run_python):
    """With no X server, SDL falls back to its off-screen driver, which "shows" frames nobody sees (issue 53, item
    4): listing the displays, a check and a show all refuse, exit 2, as with no driver at all."""
    proc = run_python("""
        import os
        os.environ.pop("SDL_VIDEODRIVER", None)
        from procam.addon.cli.app import main
        codes = [main(["live-check", "--list-displays"]),
                 main(["live-check", "--device", "live:camera=0,display=0", "--projector-width", "1024",
                       "--projector-height", "768"])]
        import pygame
        print("driver tried:", pygame.display.get_init() and pygame.display.get_driver())
        raise SystemExit(max(codes) if min(codes) == 2 else 1)
    """, env={"DISPLAY": "", "WAYLAND_DISPLAY": ""})
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stderr.count("no display to open the projector window on") == 2, proc.stderr
    assert "display 0:" not in proc.stdout and "Traceback" not in proc.stderr
    assert "driver tried: False" in proc.stdout  # SDL's video was let go again


@pytest.mark.parametrize("where", [(5000, 5000), (-64, 10), (10, SCREEN[1]), (-5000, -5000)])
def test_a_window_placed_entirely_off_the_desktop_is_refused(xvfb, where):
    """A window nobody sees shows nothing on the projector (issue 53, item 4): refused, saying where the desktop is."""
    with pytest.raises(LiveError, match=rf"at {where[0]}:{where[1]} lies entirely off the desktop"):
        ProjectorWindow((64, 48), position=where)
    window = ProjectorWindow((64, 48), position=(SCREEN[0] - 10, SCREEN[1] - 10))  # partly on: the user's choice
    window.close()


def test_the_help_says_displays_are_numbered_from_0():
    """SDL numbers displays from 0, and so do --list-displays and display=N: the help says so (issue 53)."""
    from procam.addon.steps import live, live_show

    for text in (live.DEVICE_HELP, live_show.DEVICE_HELP):
        assert "numbered from 0, as procam live-check --list-displays lists them" in text
