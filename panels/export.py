"""View3D ▸ Sidebar ▸ ProCam ▸ Export: save the calibration .blend or MPCDI file, export the projector frame
sequence, prepare a show from the image sequence folder."""

import bpy

from ..addon.steps import show as show_step
from .step_state import draw_state


class PROCAM_PT_export(bpy.types.Panel):
    bl_idname = "PROCAM_PT_export"
    bl_label = "Export"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ProCam"
    bl_order = 6

    def draw(self, context: bpy.types.Context) -> None:
        col = self.layout.column(align=True)
        col.operator("procam.export_calibration_blend", icon="FILE_BLEND")
        col.operator("procam.export_frames", icon="SEQUENCE")
        col.operator("procam.export_mpcdi", icon="EXPORT")
        layout = self.layout
        scene = context.scene
        layout.prop(scene, "procam_show_dir")
        draw_state(layout, "show", show_step.summary(bpy.path.abspath(scene.procam_show_dir)))
        layout.operator("procam.prepare_show", icon="SEQUENCE")
