"""ProCam ▸ Set Projector Image: load an image file as the frame the projector shows."""

# No `from __future__ import annotations`: Blender reads the property annotations as objects at registration.
import bpy
from bpy.props import BoolProperty, StringProperty

from ..addon.errors import ProCamError
from ..addon.blender import rig as blender_rig
from .messages import sidebar_text


class PROCAM_OT_set_projector_image(bpy.types.Operator):
    """Show an image file on the ProCam projector (native or input size; read as linear values)"""

    bl_idname = "procam.set_projector_image"
    bl_label = "Set Projector Image"
    bl_options = {"REGISTER", "UNDO"}

    filepath: StringProperty(name="Image", description="Image file (PNG, EXR, .npy…)", subtype="FILE_PATH")
    filter_image: BoolProperty(default=True, options={"HIDDEN", "SKIP_SAVE"})
    filter_folder: BoolProperty(default=True, options={"HIDDEN", "SKIP_SAVE"})

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.scene is not None and blender_rig.find_rig_objects(context.scene).projector is not None

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        if not self.filepath:
            self.report({"ERROR"}, "no image chosen: give the path of the image to project")
            return {"CANCELLED"}
        path = bpy.path.abspath(self.filepath)
        projector = blender_rig.find_rig_objects(context.scene).projector
        try:
            image = blender_rig.set_projector_image(projector, path)
        except ProCamError as exc:
            self.report({"ERROR"}, sidebar_text(str(exc)))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Projector shows {bpy.path.basename(path)} ({image.size[0]}×{image.size[1]})")
        return {"FINISHED"}
