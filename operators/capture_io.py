"""ProCam ▸ Export Patterns / Import Captures: a capture session with the user's own projector and camera.

Export writes the numbered pattern frames of the scene's projector (show them
full screen, photograph each); Import turns those photographs into a capture set
and makes it the scene's. Both only write new folders; the scene changes only in
its capture-set path.
"""

# No `from __future__ import annotations`: Blender reads the property annotations as objects at registration.
import bpy
from bpy.props import BoolProperty, StringProperty

from ..addon.blender import rig as blender_rig
from ..addon.errors import ProCamError
from ..addon.steps.capture import ImportOptions, PatternsOptions, run_import, run_patterns
from . import paths


def _rig_missing(context: bpy.types.Context) -> str:
    objs = blender_rig.find_rig_objects(context.scene)
    if objs.camera is None or objs.projector is None:
        return "Create the rig first (ProCam Camera and ProCam Projector)"
    return ""


class PROCAM_OT_export_patterns(bpy.types.Operator):
    """Write the calibration pattern sequence of the scene's projector as numbered 16-bit PNG frames"""

    bl_idname = "procam.export_patterns"
    bl_label = "Export Patterns"
    bl_options = {"REGISTER"}

    directory: StringProperty(name="Folder", subtype="DIR_PATH",
                              description="New folder for the numbered frames and sequence.json")
    force: BoolProperty(name="Replace", default=False, description="Replace an existing exported sequence there")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        why = _rig_missing(context) if context.scene is not None else "No scene"
        if why:
            cls.poll_message_set(why)
        return not why

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        if not self.directory:
            self.report({"ERROR"}, "Choose a folder for the pattern frames")
            return {"CANCELLED"}
        try:
            rig = blender_rig.read_rig(context.scene)
            out = run_patterns(PatternsOptions(rig.projector, paths.resolve(self.directory, "pattern folder"),
                                               camera=rig.camera, force=self.force))
        except ProCamError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        frames = len(list(out.glob("[0-9]*.png")))
        self.report({"INFO"}, f"{frames} pattern frames in {out}: show each full screen on the projector, "
                              "photograph it, then Import Captures")
        return {"FINISHED"}


class PROCAM_OT_import_captures(bpy.types.Operator):
    """Turn photographs of an exported pattern sequence into a capture set and use it in this scene"""

    bl_idname = "procam.import_captures"
    bl_label = "Import Captures"
    bl_options = {"REGISTER", "UNDO"}

    sequence_dir: StringProperty(name="Pattern Sequence", subtype="DIR_PATH",
                                 description="The folder Export Patterns wrote")
    photos_dir: StringProperty(name="Photographs", subtype="DIR_PATH",
                               description="One photograph per frame, numbered in the same order")
    out_dir: StringProperty(name="New Capture Set", subtype="DIR_PATH", description="Folder to create")
    rig_file: StringProperty(name="Rig Calibration", subtype="FILE_PATH",
                             description="Optional rig.json from procam calibrate-rig: calibrated camera and projector "
                                         "lenses (the camera's distortion is removed from the photographs) and, "
                                         "when calibrated in metres, the projector's pose")
    force: BoolProperty(name="Replace", default=False, description="Replace an existing capture set there")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.scene is not None

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        return context.window_manager.invoke_props_dialog(self, width=420)

    def execute(self, context: bpy.types.Context) -> set[str]:
        missing = [n for n, v in (("pattern sequence", self.sequence_dir), ("photographs", self.photos_dir),
                                  ("new capture set", self.out_dir)) if not v]
        if missing:
            self.report({"ERROR"}, "Choose the " + ", ".join(missing) + " folder(s)")
            return {"CANCELLED"}
        objs = blender_rig.find_rig_objects(context.scene)
        try:
            rig = paths.resolve(self.rig_file, "rig calibration") if self.rig_file else None
            # A rig calibration brings its own camera; the scene's (nominal) one is only used without it.
            camera = blender_rig.read_camera(context.scene) if objs.camera is not None and rig is None else None
            out = paths.resolve(self.out_dir, "new capture set")
            captures = run_import(ImportOptions(paths.resolve(self.sequence_dir, "pattern sequence"),
                                                paths.resolve(self.photos_dir, "photographs"), out, camera=camera,
                                                rig=rig, force=self.force))
        except ProCamError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        context.scene.procam_capture_dir = str(out)
        lens = f", calibrated camera and projector from {rig.name}" if rig is not None else ""
        self.report({"INFO"}, f"capture set {out}: {len(captures)} images{lens}")
        return {"FINISHED"}
