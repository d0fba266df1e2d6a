"""The Live panel's operators through bpy.ops on a virtual X server: the scene's live device string, Preview Camera
and Capture Live against a loopback camera filming the projector window, Check Live Rig in a worker thread, bad
cameras reported as errors, and Compensate's Live mode handing the live string to stage C."""

import time

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from procam.addon import jobs  # noqa: E402
from procam.addon.capture.format import CaptureSet  # noqa: E402
from procam.addon.errors import LiveError  # noqa: E402
from procam.addon.live.device import LiveSpec  # noqa: E402
from procam.addon.live.loopback import LoopbackCamera, painted_wall  # noqa: E402
from procam.addon.rig.model import Projector, projector_intrinsics_from_throw  # noqa: E402

SIZE = (160, 120)  # projector and camera: small, so a whole calibration sequence is captured in seconds
ORIGIN = (40, 30)  # the projector window on the virtual screen
#: Nothing listens on the discard port: the camera cannot open.
DEAD_URL = "http://127.0.0.1:9/stream.mjpg"


def _live_scene(scene, url: str) -> None:
    scene.procam_live_camera = url
    scene.procam_live_placement = "POSITION"
    scene.procam_live_position = f"{ORIGIN[0]}:{ORIGIN[1]}"
    scene.procam_live_encoding = "linear"  # the loopback camera streams linear values


def test_live_device_string(registered):
    from procam.operators.live import live_device

    scene = bpy.context.scene
    assert live_device(scene) == "live:camera=0,display=1,average=1,encoding=srgb,latency=auto"
    scene.procam_live_camera = " http://10.0.0.5:8080/video?a=1,b=2 "
    scene.procam_live_placement, scene.procam_live_position = "POSITION", "1920:-40"
    scene.procam_live_average, scene.procam_live_encoding = 8, "linear"
    scene.procam_live_latency_auto, scene.procam_live_latency = False, 0.125
    text = live_device(scene)
    assert text == "live:camera=http://10.0.0.5:8080/video?a=1,b=2,position=1920:-40,average=8,encoding=linear,latency=0.125"
    spec = LiveSpec.parse(text)
    assert (spec.camera, spec.position, spec.display, spec.average, spec.encoding, spec.latency) == \
        ("http://10.0.0.5:8080/video?a=1,b=2", (1920, -40), None, 8, "linear", 0.125)
    scene.procam_live_camera = "/nonexistent/video9"
    with pytest.raises(LiveError, match="neither an index"):
        live_device(scene)
    scene.procam_live_camera = ""
    with pytest.raises(LiveError, match="no live camera"):
        live_device(scene)
    assert not bpy.ops.procam.live_preview.poll() and not bpy.ops.procam.live_check.poll()


def test_the_window_fields_take_one_placement_per_projector(registered):
    """Display and Position take one window per projector of the rig, joined by + as in the device string; a value
    that is not one is refused saying the form, and no other key slips into the device string."""
    from procam.operators.live import live_device, window_placement

    scene = bpy.context.scene
    scene.procam_live_display = "1 + 2"
    assert window_placement(scene) == "display=1+2"
    assert LiveSpec.parse(live_device(scene)).displays == (1, 2)
    scene.procam_live_placement, scene.procam_live_position = "POSITION", "40:30+300:-30"
    assert window_placement(scene) == "position=40:30+300:-30"
    for bad in ("", "40", "40:30+40:30", "1,camera=3", "40:30+x:1"):
        scene.procam_live_position = bad
        with pytest.raises(LiveError, match=r"Live panel's Position must be X:Y in desktop pixels \(40:30\), or one "
                                            r"per projector joined by \+"):
            window_placement(scene)
    scene.procam_live_placement, scene.procam_live_display = "DISPLAY", "1+two"
    with pytest.raises(LiveError, match="Live panel's Display must be a display index"):
        window_placement(scene)


def test_compensate_live_mode_passes_the_live_string(registered, tmp_path):
    from procam.operators.compensate import PROCAM_OT_compensate, PROCAM_OT_evaluate, stage_c_options

    scene = bpy.context.scene
    scene.procam_compensation_mode = "LIVE"
    scene.procam_live_camera = ""
    (tmp_path / "calibration.json").write_text("{}")  # enough for the poll's "is there a calibration" check
    scene.procam_calibration_dir = str(tmp_path)
    scene.procam_target_folder = str(tmp_path)
    assert "Live panel" in PROCAM_OT_compensate.why_not(scene)
    scene.procam_live_camera, scene.procam_live_display = "2", "1"
    scene.procam_compensation_dir = str(tmp_path / "comp")
    assert PROCAM_OT_compensate.why_not(scene) is None
    options = stage_c_options(scene)
    assert options.device == "live:camera=2,display=1,average=1,encoding=srgb,latency=auto"
    assert options.mode == "closed-loop" and options.device_spec == options.device
    assert "no compensation results" in PROCAM_OT_evaluate.why_not(scene)  # not "needs a device": Live is one
    scene.procam_compensation_mode = "OPEN"
    assert stage_c_options(scene).device is None


def test_bad_camera_is_an_error_not_a_traceback(registered):
    scene = bpy.context.scene
    scene.procam_live_camera = DEAD_URL
    t0 = time.perf_counter()
    with pytest.raises(RuntimeError, match="cannot open camera") as err:
        bpy.ops.procam.live_preview()
    assert "Traceback" not in str(err.value) and time.perf_counter() - t0 < 15
    assert "ProCam Camera Preview" not in bpy.data.images
    scene.procam_live_camera = "/nonexistent/video9"
    bpy.ops.procam.create_rig(camera_width=SIZE[0], camera_height=SIZE[1], projector_width=SIZE[0],
                              projector_height=SIZE[1], surface="plane")
    scene.procam_live_capture_dir = "/tmp/procam-never-written"
    with pytest.raises(RuntimeError, match="neither an index") as err:
        bpy.ops.procam.live_capture()
    assert "Traceback" not in str(err.value)


def test_preview_camera_makes_an_image_of_the_camera_size(registered, xvfb):
    loop, _, _ = painted_wall(SIZE, ORIGIN)
    with LoopbackCamera(loop) as cam:
        _live_scene(bpy.context.scene, cam.url)
        assert bpy.ops.procam.live_preview() == {"FINISHED"}
    image = bpy.data.images["ProCam Camera Preview"]
    assert tuple(image.size) == SIZE
    pixels = np.empty(SIZE[0] * SIZE[1] * 4, np.float32)
    image.pixels.foreach_get(pixels)
    assert np.isfinite(pixels).all() and pixels.reshape(-1, 4)[:, :3].max() > 0.0  # the wall's stray light


def test_check_live_rig_in_a_worker_thread_and_a_dead_camera(registered, xvfb):
    """The window is made and used by the job's worker thread, as in the UI; a dead camera fails the job with
    LiveError's message, after the window has opened and closed again."""
    from procam.operators.live import check_rig

    projector = Projector(projector_intrinsics_from_throw(SIZE[0], SIZE[1], 1.25, 0.0, 0.15))
    loop, _, _ = painted_wall(SIZE, ORIGIN, delay_s=0.1)
    with LoopbackCamera(loop) as cam:
        spec = f"live:camera={cam.url},position={ORIGIN[0]}:{ORIGIN[1]},encoding=linear"
        job = jobs.Job("live check", check_rig, spec, projector).start()
        assert job.wait(60) and job.status == jobs.DONE, job.snapshot().error
    displays, report = job.result
    assert displays == "displays: 0: 800×600" and 0.1 <= report.latency_s < 0.4
    job = jobs.Job("live check", check_rig, f"live:camera={DEAD_URL},position=40:30", projector).start()
    assert job.wait(60) and job.status == jobs.FAILED and "cannot open camera" in job.snapshot().error


def test_capture_live_cancelled_resumes_into_a_capture_set(registered, xvfb, tmp_path, monkeypatch):
    """Check Live Rig, then Capture Live stopped (Esc) after 10 frames: the photographs stay in the session and the
    panel says so; Capture Live again resumes and writes the capture set, which becomes the scene's."""
    from procam.panels.live import capture_summary, check_summary

    scene = bpy.context.scene
    bpy.ops.procam.create_rig(camera_width=SIZE[0], camera_height=SIZE[1], projector_width=SIZE[0],
                              projector_height=SIZE[1], surface="plane")
    loop, _, _ = painted_wall(SIZE, ORIGIN)
    with LoopbackCamera(loop) as cam:
        _live_scene(scene, cam.url)
        assert bpy.ops.procam.live_check() == {"FINISHED"}
        assert check_summary().ok and any("latency" in line for line in check_summary().lines)
        with pytest.raises(RuntimeError, match="choose the new capture-set folder"):
            bpy.ops.procam.live_capture()
        scene.procam_live_capture_dir = str(tmp_path / "set")
        real = jobs.Job.progress

        def progress(self, message, fraction):  # the user presses Esc as frame 11 comes up
            if message.startswith("capturing frame 11/"):
                self.cancel()
            return real(self, message, fraction)

        monkeypatch.setattr(jobs.Job, "progress", progress)
        t0 = time.perf_counter()
        assert bpy.ops.procam.live_capture() == {"CANCELLED"}
        assert jobs.BOARD.get("live_capture").status == jobs.CANCELLED
        assert len(list((tmp_path / "set.session" / "photos").glob("*.png"))) == 10
        assert "interrupted session" in capture_summary(scene.procam_live_capture_dir).headline
        assert scene.procam_capture_dir == ""
        monkeypatch.setattr(jobs.Job, "progress", real)
        assert bpy.ops.procam.live_capture() == {"FINISHED"}
        seconds = time.perf_counter() - t0
    captures = CaptureSet.load(tmp_path / "set")
    assert captures.camera.intrinsics.size == SIZE and len(captures) > 20
    assert scene.procam_capture_dir == str(tmp_path / "set") and not (tmp_path / "set.session").exists()
    assert jobs.BOARD.get("live_capture").status == jobs.DONE
    assert capture_summary(scene.procam_live_capture_dir).headline.startswith("Captured:")
    print(f"live capture of {len(captures)} images at {SIZE[0]}×{SIZE[1]}, cancelled and resumed: {seconds:.1f} s")
