"""The Calibrate / Compensate / Diagnose / Export operators headless through bpy.ops on a tiny lab capture set,
their poll messages, a cancelled job leaving the scene as it was, and the worker-thread path of the UI."""

import json
import time

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")  # before pymeshlab (shared Embree), and the operators need it

from procam.addon import jobs  # noqa: E402
from procam.addon.native import prepare_worker_libraries  # noqa: E402
from procam.addon.steps import calibrate as calibrate_step  # noqa: E402
from procam.addon.steps import compensate as compensate_step  # noqa: E402
from procam.addon.steps import diagnose as diagnose_step  # noqa: E402
from procam.addon.steps.stage_c import StageCOptions  # noqa: E402
from procam.addon.imageio import read_image, write_image  # noqa: E402
from procam.addon.blender import rig as blender_rig  # noqa: E402
from procam.addon.steps.calibrate import read as read_calibration  # noqa: E402

TINY = dict(scale=0.15, samples=4)  # camera 96×72, projector 120×90


@pytest.fixture(scope="module")
def tiny(lab_set):
    return lab_set("vedge", "", **TINY)


@pytest.fixture(scope="module")
def calibrated(tiny, tmp_path_factory):
    """A calibration made the way the UI makes it: run_calibration in a worker thread."""
    out = tmp_path_factory.mktemp("ui") / "calibration"
    prepare_worker_libraries()  # as the Calibrate operator does before its worker starts
    options = calibrate_step.CalibrateOptions(tiny[0], out, with_blend=False)
    job = jobs.Job("calibration", calibrate_step.run_view, options).start()
    seen = set()
    while not job.wait(0.05):
        seen.add(round(job.snapshot().fraction, 1))
    assert job.status == jobs.DONE, job.snapshot().error
    assert len(seen) >= 3  # progress arrived while it ran
    return job.result


@pytest.fixture
def targets(tmp_path):
    rng = np.random.default_rng(1)
    paths = []
    for i in range(2):
        p = tmp_path / "targets" / f"frame{i + 1}.png"
        p.parent.mkdir(exist_ok=True)
        write_image(p, rng.uniform(0.2, 0.8, (30, 40, 3)).astype(np.float32))
        paths.append(p)
    return paths


def _scene_state(scene):
    objs = {o.name: (o.type, tuple(round(v, 9) for row in o.matrix_world for v in row), o.hide_render)
            for o in scene.objects}
    return objs, sorted(i.name for i in bpy.data.images), dict(scene.items()).get("procam_calibration_dir")


def test_threaded_calibration_returns_what_the_scene_shows(calibrated):
    view = calibrated
    assert (view.folder / "calibration.json").is_file() and not (view.folder / "scene.blend").exists()
    assert {"warp_grid", "pose_mask", "warp_compare_after"} <= set(view.images)
    assert view.images["warp_grid"].shape[:2] == tuple(reversed(view.calibration.warp.size))
    summary = calibrate_step.summary(view.folder)
    assert summary.ok and "px" in summary.headline and len(summary.lines) >= 4


def test_calibrate_operator_moves_the_projector_and_shows_the_textured_surface(registered, tiny, tmp_path):
    scene = bpy.context.scene
    with pytest.raises(RuntimeError, match="no capture set"):
        bpy.ops.procam.calibrate()
    bpy.ops.procam.create_rig(camera_width=96, camera_height=72, projector_width=120, projector_height=90,
                              surface="plane")
    user_surface = blender_rig.find_rig_objects(scene).surface
    scene.procam_capture_dir = str(tiny[0])
    with pytest.raises(RuntimeError, match="choose the calibration folder"):
        bpy.ops.procam.calibrate()
    scene.procam_calibration_dir = str(tmp_path / "cal")
    assert bpy.ops.procam.calibrate() == {"FINISHED"}
    cal = read_calibration(tmp_path / "cal")
    objs = blender_rig.find_rig_objects(scene)
    assert np.allclose(blender_rig.read_projector(scene).camera_from_projector,
                       cal.rig.projector.camera_from_projector, atol=1e-6)
    assert objs.surface.name == blender_rig.CALIBRATED_SURFACE_NAME
    assert len(objs.surface.data.polygons) == len(cal.surface.faces)
    tex = [n for n in objs.surface.active_material.node_tree.nodes if n.type == "TEX_IMAGE"][0].image
    assert tuple(tex.size) == (cal.surface.albedo.shape[1], cal.surface.albedo.shape[0])
    assert user_surface.hide_render and user_surface.name in scene.objects  # kept, hidden, no longer the surface
    grid = bpy.data.images["ProCam Calibration warp_grid"]
    assert tuple(grid.size) == tuple(cal.warp.size)
    assert "ProCam Calibration pose_mask" in bpy.data.images
    assert jobs.BOARD.get("calibrate").status == jobs.DONE
    # an existing calibration is kept, and the message names the sidebar's field, not the command's option
    with pytest.raises(RuntimeError, match="never overwritten without ‘Replace Results’$"):
        bpy.ops.procam.calibrate()
    assert jobs.BOARD.get("calibrate").status == jobs.FAILED
    # and the panel's "Failed:" line says it so too
    assert jobs.BOARD.get("calibrate").snapshot().error.endswith("without ‘Replace Results’")


def test_calibrate_one_stage_at_a_time(registered, tiny, tmp_path):
    """Surface, Pose, Warp buttons: the surface alone leaves the artist's projector where it stands; each later
    stage reuses the folder's earlier ones; a depth offset given in the panel replaces the wall image's."""
    scene = bpy.context.scene
    bpy.ops.procam.create_rig(camera_width=96, camera_height=72, projector_width=120, projector_height=90,
                              surface="vedge")
    scene.procam_capture_dir = str(tiny[0])
    scene.procam_calibration_dir = str(tmp_path / "cal")
    with pytest.raises(RuntimeError, match="holds no calibration yet"):
        bpy.ops.procam.calibrate(stage="POSE")
    scene.procam_depth_offset_given, scene.procam_depth_offset = True, 0.003
    assert bpy.ops.procam.calibrate(stage="SURFACE") == {"FINISHED"}
    cal = read_calibration(tmp_path / "cal", complete=False)
    assert cal.missing_stages == ["pose", "warp"]
    assert cal.report["surface_report"]["depth_offset"] == pytest.approx(0.003)
    assert blender_rig.find_rig_objects(scene).surface.name == blender_rig.CALIBRATED_SURFACE_NAME
    projector = blender_rig.find_rig_objects(scene).projector  # the artist moves it; a surface rerun keeps it there
    projector.location.x += 0.1
    bpy.context.view_layer.update()
    placed = blender_rig.read_projector(scene).camera_from_projector
    scene.procam_replace_outputs = True
    assert bpy.ops.procam.calibrate(stage="SURFACE") == {"FINISHED"}
    assert np.allclose(blender_rig.read_projector(scene).camera_from_projector, placed, atol=1e-6)
    assert bpy.ops.procam.calibrate(stage="POSE") == {"FINISHED"}
    cal = read_calibration(tmp_path / "cal", complete=False)
    assert cal.missing_stages == ["warp"]
    assert np.allclose(blender_rig.read_projector(scene).camera_from_projector,
                       cal.rig.projector.camera_from_projector, atol=1e-6)
    assert bpy.ops.procam.calibrate(stage="WARP") == {"FINISHED"}
    assert not read_calibration(tmp_path / "cal").missing_stages
    assert "ProCam Calibration warp_grid" in bpy.data.images


def test_cancelled_calibration_leaves_scene_and_disk_unchanged(registered, tiny, tmp_path, monkeypatch):
    scene = bpy.context.scene
    bpy.ops.procam.create_rig(camera_width=96, camera_height=72, projector_width=120, projector_height=90,
                              surface="vedge")
    scene.procam_capture_dir = str(tiny[0])
    scene.procam_calibration_dir = str(tmp_path / "cal")
    before = _scene_state(scene)
    real = jobs.Job.progress

    def progress(self, message, fraction):  # the user presses Esc once stage A has started
        if fraction >= 0.2:
            self.cancel()
        return real(self, message, fraction)

    monkeypatch.setattr(jobs.Job, "progress", progress)
    assert bpy.ops.procam.calibrate() == {"CANCELLED"}
    assert jobs.BOARD.get("calibrate").status == jobs.CANCELLED
    assert _scene_state(scene) == before
    assert list(tmp_path.iterdir()) == []  # no calibration folder, no temporary leftovers


def test_compensate_preview_and_export(registered, calibrated, targets, tmp_path):
    scene = bpy.context.scene
    with pytest.raises(RuntimeError, match="no calibration"):
        bpy.ops.procam.compensate()
    scene.procam_calibration_dir = str(calibrated.folder)
    assert bpy.ops.procam.load_calibration() == {"FINISHED"}
    with pytest.raises(RuntimeError, match="no targets"):
        bpy.ops.procam.compensate()
    bpy.ops.procam.add_targets(directory=str(targets[0].parent), files=[{"name": p.name} for p in targets])
    assert [t.filepath for t in scene.procam_targets] == [str(p) for p in targets]
    scene.procam_target_index = 0
    assert bpy.ops.procam.remove_target() == {"FINISHED"} and len(scene.procam_targets) == 1
    scene.procam_compensation_mode = "CLOSED"
    with pytest.raises(RuntimeError, match="needs a device"):
        bpy.ops.procam.compensate()
    scene.procam_compensation_mode = "OPEN"
    scene.procam_iterations = 6
    scene.procam_compensation_dir = str(tmp_path / "comp")
    assert bpy.ops.procam.compensate() == {"FINISHED"}
    view = compensate_step.read(tmp_path / "comp")
    assert [t.name for t in view.targets] == ["frame2"] and view.mode == "open-loop"
    assert "ProCam frame2 input" in bpy.data.images and "ProCam frame2 simulated" in bpy.data.images
    assert compensate_step.summary(tmp_path / "comp").ok

    assert bpy.ops.procam.preview_compensated(target="frame2") == {"FINISHED"}
    shown = blender_rig.projector_image(blender_rig.find_rig_objects(scene).projector)
    assert np.allclose(shown, read_image(view.targets[0].frame_path), atol=1e-4)
    with pytest.raises(RuntimeError, match="no compensated target 'nope'"):
        bpy.ops.procam.preview_compensated(target="nope")

    assert bpy.ops.procam.export_frames(directory=str(tmp_path / "show")) == {"FINISHED"}
    doc = json.loads((tmp_path / "show" / "frames.json").read_text())
    assert [f["file"] for f in doc["frames"]] == ["frame_0001.png"]
    assert (tmp_path / "show" / "frame_0001.png").read_bytes() == view.targets[0].frame_path.read_bytes()
    with pytest.raises(RuntimeError, match="already holds .* without ‘Replace’$"):
        bpy.ops.procam.export_frames(directory=str(tmp_path / "show"))

    blend = tmp_path / "cal.blend"
    assert bpy.ops.procam.export_calibration_blend(filepath=str(blend)) == {"FINISHED"}
    assert blend.stat().st_size > 0 and [p.name for p in tmp_path.glob(".cal*")] == []
    with pytest.raises(RuntimeError, match="exists"):
        bpy.ops.procam.export_calibration_blend(filepath=str(blend))

    image = tmp_path / "show" / "frame_0001.png"
    assert bpy.ops.procam.show_image(filepath=str(image), name="ProCam check") == {"FINISHED"}
    assert tuple(bpy.data.images["ProCam check"].size) == calibrated.calibration.rig.projector.intrinsics.size


def test_compensate_bad_input_changes_nothing(registered, calibrated, tmp_path):
    scene = bpy.context.scene
    scene.procam_calibration_dir = str(calibrated.folder)
    scene.procam_compensation_dir = str(tmp_path / "comp")
    scene.procam_targets.add().filepath = str(tmp_path / "missing.png")
    before = _scene_state(scene)
    with pytest.raises(RuntimeError, match="not found"):
        bpy.ops.procam.compensate()
    scene.procam_targets.clear()
    scene.procam_target_folder = str(tmp_path)
    with pytest.raises(RuntimeError, match="holds no images"):
        bpy.ops.procam.compensate()
    (tmp_path / "t.png").write_bytes(b"")
    scene.procam_compensation_mode, scene.procam_device = "CLOSED", "usb:0"
    with pytest.raises(RuntimeError, match="the device must be"):
        bpy.ops.procam.compensate()
    assert _scene_state(scene) == before and not (tmp_path / "comp").exists()


def test_closed_loop_in_a_worker_renders_the_lab_on_the_main_thread(bpy_scene, tiny, calibrated, targets, tmp_path):
    from procam.addon.lab.truth import LabTruth
    from procam.addon.lab.cycles_device import LabDevice

    device = LabDevice(LabTruth.load(tiny[1]))
    holder = []
    relay = jobs.MainThreadRelay(cancel=lambda: holder[0].cancelled())
    try:
        options = compensate_step.CompensateOptions(calibrated.folder, tuple(targets[:1]), tmp_path / "c",
                                                    StageCOptions(iterations=4, device=f"lab:{tiny[1]}"))
        job = jobs.Job("compensation", compensate_step.run, options, device=jobs.RelayedDevice(device, relay))
        holder.append(job)
        job.start()
        pumped, deadline = 0, time.monotonic() + 240
        while not job.finished and time.monotonic() < deadline:  # the modal operator's timer does this
            pumped += relay.pump()
            time.sleep(0.01)
    finally:
        device.close()
    assert job.status == jobs.DONE, job.snapshot().error
    assert pumped >= 1 and job.result.mode == "closed-loop"


def test_diagnose_operator_and_cancel_button(registered, calibrated, tmp_path, monkeypatch):
    scene = bpy.context.scene
    scene.procam_calibration_dir = str(calibrated.folder)
    scene.procam_diagnosis_dir = str(tmp_path / "gap")

    def diagnose(options, progress, cancel):  # the step's interface, a tiny folder
        progress("fitting effects", 0.5)
        out_dir = options.out
        out_dir.mkdir()
        write_image(out_dir / "residual.png", np.zeros((4, 4, 3), np.float32))
        (out_dir / "gap.json").write_text(json.dumps({
            "format": "procam-gap", "version": 1, "residual": {"rmse": 0.03, "psnr": 30.5},
            "regions": [{"bbox": [1, 2, 3, 4], "share": 0.6, "description": "concave corner"}],
            "effects": [{"name": "response", "params": {}, "heldout_rmse_before": 0.03,
                         "heldout_rmse_after": 0.02, "confidence": 0.9}],
            "selected": ["response"]}))

    monkeypatch.setattr(diagnose_step, "run", diagnose)
    assert bpy.ops.procam.diagnose() == {"FINISHED"}
    summary = diagnose_step.summary(tmp_path / "gap")
    assert summary.ok and summary.data["selected"] == ["response"] and summary.data["maps"] == ["residual.png"]

    with pytest.raises(RuntimeError, match="no ProCam job is running"):
        bpy.ops.procam.cancel_job()
    import threading

    gate = threading.Event()
    job = jobs.BOARD.add("diagnose", jobs.Job("diagnosis",
                                              lambda *, progress, cancel: (gate.wait(5), progress("x", 1))))
    job.start()
    try:
        with pytest.raises(RuntimeError, match="diagnosis is running"):
            bpy.ops.procam.calibrate()
        assert bpy.ops.procam.cancel_job(step="diagnose") == {"FINISHED"}
    finally:
        gate.set()
    assert job.wait(5) and job.status == jobs.CANCELLED


def test_export_patterns_then_import_captures(registered, tmp_path):
    """A session with one's own hardware: export the frames, 'photograph' them (here: the frames themselves),
    import; the scene then points at the new capture set. Without a rig, export is disabled and says why."""
    scene = bpy.context.scene
    assert not bpy.ops.procam.export_patterns.poll()
    assert bpy.ops.procam.create_rig() == {"FINISHED"}
    assert bpy.ops.procam.export_patterns(directory=str(tmp_path / "seq")) == {"FINISHED"}
    frames = sorted((tmp_path / "seq").glob("[0-9]*.png"))
    assert len(frames) > 10 and (tmp_path / "seq" / "sequence.json").is_file()
    # OpenCV's structured-light order, for sessions captured that way: Gray code first, white and black last
    assert bpy.ops.procam.export_patterns(directory=str(tmp_path / "seq-cv"), order="opencv") == {"FINISHED"}
    kinds = [f["kind"] for f in json.loads((tmp_path / "seq-cv" / "sequence.json").read_text())["frames"]]
    assert kinds[0] == "graycode" and "checker" not in kinds and "surface" not in kinds
    assert kinds[kinds.index("white") + 1] == "black" and kinds.index("white") > kinds.index("graycode")
    photos = tmp_path / "photos"
    photos.mkdir()
    import cv2

    w, h = blender_rig.read_camera(scene).intrinsics.size
    for i, f in enumerate(frames):  # the camera's size, named the way cameras name photographs
        write_image(photos / f"IMG_{i + 1:04d}.png", cv2.resize(read_image(f), (w, h), interpolation=cv2.INTER_AREA))
    with pytest.raises(RuntimeError, match="Choose the"):
        bpy.ops.procam.import_captures(sequence_dir=str(tmp_path / "seq"))
    assert bpy.ops.procam.import_captures(sequence_dir=str(tmp_path / "seq"), photos_dir=str(photos),
                                          out_dir=str(tmp_path / "set")) == {"FINISHED"}
    assert scene.procam_capture_dir == str(tmp_path / "set")
    assert (tmp_path / "set" / "capture.json").is_file()
    # With a rig calibration: its lenses and pose, the photographs undistorted.
    from tests.test_capture import _rig_file

    frame = blender_rig.read_projector(scene).intrinsics.size
    rig = _rig_file(tmp_path / "rig.json", (w, h), frame, [-0.1, 0.0, 0.0, 0.0, 0.0])
    assert bpy.ops.procam.import_captures(sequence_dir=str(tmp_path / "seq"), photos_dir=str(photos),
                                          out_dir=str(tmp_path / "rigged"), rig_file=str(rig)) == {"FINISHED"}
    from procam.addon.capture.format import CaptureSet

    rigged = CaptureSet.load(tmp_path / "rigged")
    assert rigged.camera_status == "calibrated" and rigged.projector_pose_known
    assert rigged.camera.intrinsics.fx == 70.0


def test_calibrate_registers_the_selected_mesh_as_the_surface(registered, tiny, tmp_path):
    """An artist's model of the object, placed by eye (5 cm and 3° off): Use Selected Mesh, then Calibrate
    registers it to the measured points and uses it as the surface."""
    from procam.addon.lab.truth import LabTruth
    from procam.addon.rig import frames

    scene = bpy.context.scene
    bpy.ops.procam.create_rig(camera_width=96, camera_height=72, projector_width=120, projector_height=90,
                              surface="vedge")
    true = LabTruth.load(tiny[1]).surface
    a = np.radians(3.0)
    turn = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    centre = true.vertices.mean(axis=0)
    placed = (true.vertices - centre) @ turn.T + centre + (0.05, 0.0, 0.0)
    mesh = bpy.data.meshes.new("scan")
    mesh.from_pydata(frames.blender_points(placed).tolist(), [], true.faces.tolist())
    obj = bpy.data.objects.new("scan", mesh)
    scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.procam.use_selected_surface_mesh() == {"FINISHED"} and scene.procam_surface_mesh == obj
    scene.procam_capture_dir = str(tiny[0])
    scene.procam_calibration_dir = str(tmp_path / "cal")
    assert bpy.ops.procam.calibrate(stage="SURFACE") == {"FINISHED"}
    report = read_calibration(tmp_path / "cal", complete=False).report["surface_report"]
    assert report["source"] == "mesh" and report["measured"] == "depth"
    assert report["registration"]["rms_mm"] < 5.0
    scene.procam_surface_mesh = None
