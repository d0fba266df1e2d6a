"""ProCam ▸ Set Surface: the active mesh object becomes the projection surface."""

import bpy

from ..addon.errors import ProCamError
from ..addon.blender import rig as blender_rig
from .messages import sidebar_text


class PROCAM_OT_set_surface(bpy.types.Operator):
    """Use the active mesh object as the ProCam projection surface"""

    bl_idname = "procam.set_surface"
    bl_label = "Set Surface"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        # Any active object passes, so that a non-mesh gets a message rather than a greyed-out button.
        return context.scene is not None and context.active_object is not None

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            obj = blender_rig.set_surface(context.scene, context.active_object)
        except ProCamError as exc:
            self.report({"ERROR"}, sidebar_text(str(exc)))
            return {"CANCELLED"}
        self.report({"INFO"}, f"{obj.name!r} is now the ProCam surface ({len(obj.data.polygons)} faces)")
        return {"FINISHED"}
