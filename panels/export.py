"""View3D ▸ Sidebar ▸ ProCam ▸ Export: save the calibration .blend, export the projector frame sequence."""

import bpy


class PROCAM_PT_export(bpy.types.Panel):
    bl_idname = "PROCAM_PT_export"
    bl_label = "Export"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ProCam"
    bl_order = 5

    def draw(self, context: bpy.types.Context) -> None:
        col = self.layout.column(align=True)
        col.operator("procam.export_calibration_blend", icon="FILE_BLEND")
        col.operator("procam.export_frames", icon="SEQUENCE")
