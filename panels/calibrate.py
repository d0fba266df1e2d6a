"""View3D ▸ Sidebar ▸ ProCam ▸ Calibrate: the calibration folder, its state and key figures, and its images."""

import bpy

from ..addon.steps import calibrate as calibrate_step
from .step_state import draw_state


class PROCAM_PT_calibrate(bpy.types.Panel):
    bl_idname = "PROCAM_PT_calibrate"
    bl_label = "Calibrate"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ProCam"
    bl_order = 3

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        scene = context.scene
        layout.prop(scene, "procam_calibration_dir", text="")
        row = layout.row()
        row.prop(scene, "procam_calibration_init", text="Start")
        layout.prop(scene, "procam_projector_intrinsics", text="Lens")
        row = layout.row(align=True)
        row.prop(scene, "procam_surface_mesh", text="Mesh")
        row.operator("procam.use_selected_surface_mesh", text="", icon="EYEDROPPER")
        summary = calibrate_step.summary(bpy.path.abspath(scene.procam_calibration_dir))
        done = draw_state(layout, "calibrate", summary)
        row = layout.row(align=True)
        row.prop(scene, "procam_depth_offset_given", text="")
        sub = row.row(align=True)
        sub.enabled = scene.procam_depth_offset_given
        sub.prop(scene, "procam_depth_offset")
        col = layout.column(align=True)
        col.operator("procam.calibrate", icon="PLAY").stage = "ALL"
        row = col.row(align=True)
        for stage, text in (("SURFACE", "Surface"), ("POSE", "Pose"), ("WARP", "Warp")):
            row.operator("procam.calibrate", text=text).stage = stage
        col.operator("procam.load_calibration", icon="IMPORT")
        col.prop(scene, "procam_replace_outputs")
        if done and summary.data.get("diagnostics"):
            sub = layout.column(align=True)
            sub.label(text="Diagnostic images:")
            root = bpy.path.abspath(scene.procam_calibration_dir)
            count = int(summary.data.get("projectors", 1))
            for k, names in enumerate(by_projector(summary.data["diagnostics"], count)):
                if count > 1:  # several projectors: each one's images under its number
                    sub.label(text=f"Projector {k + 1}:", icon="LIGHT_SPOT")
                for name in names:
                    op = sub.operator("procam.show_image", text=name.removesuffix(".png"), icon="IMAGE_DATA")
                    op.filepath = f"{root.rstrip('/')}/diagnostics/{name}"
                    op.name = f"ProCam Calibration {name.removesuffix('.png')}"


def by_projector(names: list[str], count: int) -> list[list[str]]:
    """The diagnostic image names of each projector: projector k ≥ 2's carry the prefix ``pK_``, the first's none."""
    out: list[list[str]] = [[] for _ in range(max(1, count))]
    for name in names:
        head = name.split("_", 1)[0]
        k = int(head[1:]) - 1 if count > 1 and head[:1] == "p" and head[1:].isdigit() else 0
        out[k if 0 <= k < len(out) else 0].append(name)
    return out
