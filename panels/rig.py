"""View3D ▸ Sidebar ▸ ProCam ▸ Rig: what the rig holds, and the buttons that change it."""

import bpy

from ..addon.blender import rig as blender_rig


class PROCAM_PT_rig(bpy.types.Panel):
    bl_idname = "PROCAM_PT_rig"
    bl_label = "Rig"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ProCam"
    bl_order = 0

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        state = blender_rig.rig_summary(context.scene)
        col = layout.column(align=True)
        for key, icon in (("camera", "CAMERA_DATA"), ("projector", "LIGHT_SPOT"), ("surface", "MESH_DATA")):
            col.label(text=f"{key.capitalize()}: {state[key]}", icon=icon)
        if "error" in state:
            layout.label(text=state["error"], icon="ERROR")
        col = layout.column(align=True)
        col.operator("procam.create_rig", icon="ADD")
        col.operator("procam.add_projector", icon="LIGHT_SPOT")
        col.operator("procam.set_surface", icon="MESH_PLANE")
        col.operator("procam.set_projector_image", icon="IMAGE_DATA")
