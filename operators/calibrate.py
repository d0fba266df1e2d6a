"""ProCam ▸ Calibrate (surface, pose, warp as a background job) and ProCam ▸ Load Calibration (an existing folder).

Both end the same way: the projector moves to the calibrated pose, the
reconstructed surface appears textured, and the warp's deformed grid and the
diagnostic images become Blender images (``ProCam …``).
"""

import bpy

from ..addon import jobs
from ..addon.errors import ProCamError
from ..addon.rig import blender_rig
from ..addon.workflow import (CALIBRATION_MANIFEST, CalibrationView, load_calibration_view,
                              prepare_worker_libraries, run_calibration)
from . import paths
from .job_operator import JobOperator, job_running_message

IMAGE_PREFIX = "ProCam Calibration "


def apply_view(context: bpy.types.Context, view: CalibrationView) -> str:
    """Write a calibration into the scene; returns the report."""
    cal = view.calibration
    objs = blender_rig.apply_calibration(context.scene, cal.rig, cal.surface, source=str(view.folder))
    for name, image in view.images.items():
        blender_rig.set_image(IMAGE_PREFIX + name, image)
    context.scene.procam_calibration_dir = str(view.folder)
    pos = cal.rig.projector.position
    return (f"Calibration {view.folder.name}: {objs.projector.name!r} at ({pos[0]:+.3f}, {pos[1]:+.3f}, "
            f"{pos[2]:+.3f}) m, surface {len(cal.surface.faces)} faces, {len(view.images)} images")


class PROCAM_OT_calibrate(JobOperator, bpy.types.Operator):
    """Estimate the surface, the projector pose (stage A) and the warp (stage B) from the scene's capture set,
    in the background; Esc cancels"""

    bl_idname = "procam.calibrate"
    bl_label = "Calibrate"
    bl_options = {"REGISTER", "UNDO"}
    step = "calibrate"

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        scene = context.scene
        why = job_running_message()
        if why is None and paths.existing(scene.procam_capture_dir, "capture.json") is None:
            why = "no capture set: run the virtual lab or choose a capture-set folder in Captures"
        if why is None and not scene.procam_calibration_dir:
            why = "choose the calibration folder to write"
        if why is None and scene.procam_calibration_init == "blender" and \
                blender_rig.find_rig_objects(scene).projector is None:
            why = "start pose 'Scene Projector' needs a ProCam Projector in the scene"
        if why is not None:
            cls.poll_message_set(why)
        return why is None

    def make_job(self, context: bpy.types.Context, relay: "jobs.MainThreadRelay | None") -> jobs.Job:
        scene = context.scene
        captures = paths.resolve(scene.procam_capture_dir, "capture set")
        out = paths.resolve(scene.procam_calibration_dir, "calibration folder")
        if relay is not None:
            prepare_worker_libraries()
        init, initial = scene.procam_calibration_init, None
        if init == "blender":
            initial = blender_rig.read_projector(scene).camera_from_projector
            init = "given"
        return jobs.Job("calibration", run_calibration, captures, out, init=init, initial_pose=initial,
                        force=scene.procam_replace_outputs)

    def apply(self, context: bpy.types.Context, result: object) -> str:
        return apply_view(context, result)


class PROCAM_OT_load_calibration(bpy.types.Operator):
    """Bring the calibration folder into the scene: projector pose, textured surface, warp grid, diagnostics"""

    bl_idname = "procam.load_calibration"
    bl_label = "Load Calibration"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        if paths.existing(context.scene.procam_calibration_dir, CALIBRATION_MANIFEST) is None:
            cls.poll_message_set("no calibration folder (with calibration.json): run Calibrate or choose one")
            return False
        return True

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            folder = paths.resolve(context.scene.procam_calibration_dir, "calibration folder")
            view = load_calibration_view(folder)
            message = apply_view(context, view)
        except ProCamError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, message)
        return {"FINISHED"}
