"""ProCam ▸ Calibrate (surface, pose, warp as a background job) and ProCam ▸ Load Calibration (an existing folder).

Both end the same way: the projector moves to the calibrated pose, the
reconstructed surface appears textured, and the warp's deformed grid and the
diagnostic images become Blender images (``ProCam …``).
"""

import bpy
from bpy.props import EnumProperty

from ..addon import jobs
from ..addon.options import from_values
from ..addon.blender import rig as blender_rig
from ..addon.errors import CalibrationError, ProCamError
from ..addon.native import prepare_worker_libraries
from ..addon.steps import calibrate as calibrate_step
from ..addon.steps.calibrate import CalibrateOptions, CalibrationView
from ..addon.steps.layout import CALIBRATION, CAPTURES
from . import paths
from .job_operator import JobOperator
from .messages import sidebar_text

IMAGE_PREFIX = "ProCam Calibration "


STAGE_ITEMS = [("ALL", "All", "Surface, then the projector pose (stage A), then the warp (stage B)"),
               ("SURFACE", "Surface", "Only the surface from the depth image; pose and warp must be rerun after it"),
               ("POSE", "Pose", "Only the projector pose (stage A) on the calibration's surface; the warp must be "
                                "rerun after it"),
               ("WARP", "Warp", "Only the warp (stage B) on the calibration's surface and pose")]


def apply_view(context: bpy.types.Context, view: CalibrationView) -> str:
    """Write a calibration into the scene; returns the report."""
    cal = view.calibration
    posed = cal.stages["pose"] != "not run"
    objs = blender_rig.apply_calibration(context.scene, cal.rig, cal.surface, source=str(view.folder),
                                         move_projector=posed)
    for name, image in view.images.items():
        blender_rig.set_image(IMAGE_PREFIX + name, image)
    context.scene.procam_calibration_dir = str(view.folder)
    todo = f"; still to run: {', '.join(cal.missing_stages)}" if cal.missing_stages else ""
    todo += "".join(f"; warning: {w}" for w in cal.warnings)
    # every projector of the calibration, in rig order (one: the scene's only one)
    placed = ", ".join(f"{o.name!r} {'at' if posed else 'left at'} "
                       f"({o.matrix_world.translation[0]:+.3f}, {o.matrix_world.translation[1]:+.3f}, "
                       f"{o.matrix_world.translation[2]:+.3f})" for o in objs.projectors)
    return (f"Calibration {view.folder.name}: {placed}, surface "
            f"{len(cal.surface.faces)} faces, {len(view.images)} images{todo}")


class PROCAM_OT_calibrate(JobOperator, bpy.types.Operator):
    """Estimate the surface, the projector pose (stage A) and the warp (stage B) from the scene's capture set,
    in the background; Esc cancels"""

    bl_idname = "procam.calibrate"
    bl_label = "Calibrate"
    bl_options = {"REGISTER", "UNDO"}
    step = "calibrate"
    option_names = {"--out": "‘Calibration’ folder", "--stages": "‘Stage’"}

    stage: EnumProperty(name="Stage", items=STAGE_ITEMS, default="ALL",
                        description="Which stage to run; a single later stage reuses the earlier ones from the "
                                    "calibration folder")

    @classmethod
    def description(cls, context: bpy.types.Context, properties: bpy.types.OperatorProperties) -> str:
        return next(d for k, _, d in STAGE_ITEMS if k == properties.stage) + "; Esc cancels"

    @classmethod
    def why_not(cls, scene: bpy.types.Scene) -> str | None:
        if paths.existing(scene.procam_capture_dir, CAPTURES.manifest) is None:
            return "no capture set: run the virtual lab or choose a capture-set folder in Captures"
        if not scene.procam_calibration_dir:
            return "choose the calibration folder to write"
        if scene.procam_calibration_init == "blender" and blender_rig.find_rig_objects(scene).projector is None:
            return "start pose 'Scene Projector' needs a ProCam Projector in the scene"
        return None

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
        stages = None if self.stage == "ALL" else self.stage.lower()
        if stages in ("pose", "warp") and paths.existing(scene.procam_calibration_dir, CALIBRATION.manifest) is None:
            raise CalibrationError(f"the {stages} stage reuses the calibration folder's earlier stages, but it "
                                   "holds no calibration yet; run Surface (or All) first")
        offset = float(scene.procam_depth_offset) if scene.procam_depth_offset_given else None
        # Read in the main thread: bpy must not run in the worker.
        mesh = blender_rig.read_mesh_object(scene, scene.procam_surface_mesh) if scene.procam_surface_mesh else None
        # No scene.blend: the open scene is the .blend here, and bpy must not run in the worker (Export saves one).
        options = from_values(CalibrateOptions, lambda prop: getattr(scene, prop), capture_dir=captures, out=out,
                              init=init, initial_pose=initial, stages=stages or "all", depth_offset=offset,
                              surface_mesh=mesh, with_blend=False, force=scene.procam_replace_outputs)
        return jobs.Job("calibration", calibrate_step.run_view, options)

    def apply(self, context: bpy.types.Context, result: object) -> str:
        return apply_view(context, result)


class PROCAM_OT_use_selected_surface_mesh(bpy.types.Operator):
    """Use the selected mesh (a scan or CAD model of the object) as the surface: Calibrate registers it to the
    measured points"""

    bl_idname = "procam.use_selected_surface_mesh"
    bl_label = "Use Selected Mesh as Surface"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        obj = context.active_object
        if obj is None or obj.type != "MESH" or blender_rig.role(obj) is not None:
            cls.poll_message_set("select a mesh of the object (not a ProCam rig object)")
            return False
        return True

    def execute(self, context: bpy.types.Context) -> set[str]:
        context.scene.procam_surface_mesh = context.active_object
        self.report({"INFO"}, f"Calibrate will register {context.active_object.name!r} as the surface")
        return {"FINISHED"}


class PROCAM_OT_load_calibration(bpy.types.Operator):
    """Bring the calibration folder into the scene: projector pose, textured surface, warp grid, diagnostics"""

    bl_idname = "procam.load_calibration"
    bl_label = "Load Calibration"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        if paths.existing(context.scene.procam_calibration_dir, CALIBRATION.manifest) is None:
            cls.poll_message_set("no calibration folder (with calibration.json): run Calibrate or choose one")
            return False
        return True

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            folder = paths.resolve(context.scene.procam_calibration_dir, "calibration folder")
            view = calibrate_step.read_view(folder)
            message = apply_view(context, view)
        except ProCamError as exc:
            self.report({"ERROR"}, sidebar_text(str(exc)))
            return {"CANCELLED"}
        self.report({"INFO"}, message)
        return {"FINISHED"}
