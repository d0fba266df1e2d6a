"""ProCam ▸ Add Projector: one more projector in the scene's rig, a copy of the active one moved beside it."""

# No `from __future__ import annotations`: Blender reads the property annotations as objects at registration.
from dataclasses import replace

import bpy
import numpy as np
from bpy.props import FloatProperty

from ..addon.errors import ProCamError
from ..addon.blender import rig as blender_rig
from .messages import sidebar_text


class PROCAM_OT_add_projector(bpy.types.Operator):
    """Add another ProCam projector (same lens and resolution as the active one), moved to its right"""

    bl_idname = "procam.add_projector"
    bl_label = "Add Projector"
    bl_options = {"REGISTER", "UNDO"}

    offset: FloatProperty(name="Offset", description="How far to the right of the active projector it goes",
                          default=0.5, soft_min=-5.0, soft_max=5.0, subtype="DISTANCE", unit="LENGTH")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.scene is not None and blender_rig.find_rig_objects(context.scene).projector is not None

    def execute(self, context: bpy.types.Context) -> set[str]:
        scene = context.scene
        try:
            model = blender_rig.read_projector(scene)
            pose = model.camera_from_projector.copy()
            pose[:3, 3] += pose[:3, 0] * float(self.offset)  # along the projector's own x (its image's right)
            obj = blender_rig.add_projector(scene, replace(model, camera_from_projector=np.asarray(pose)))
        except ProCamError as exc:
            self.report({"ERROR"}, sidebar_text(str(exc)))
            return {"CANCELLED"}
        # the new projector becomes the one the panels show and work on
        for other in context.selected_objects:
            other.select_set(False)
        obj.select_set(True)
        context.view_layer.objects.active = obj
        count = len(blender_rig.find_rig_objects(scene).projectors)
        self.report({"INFO"}, f"Added {obj.name!r}: the rig has {count} projectors")
        return {"FINISHED"}
