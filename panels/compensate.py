"""View3D ▸ Sidebar ▸ ProCam ▸ Compensate: targets, how stage C runs (what ``procam compensate`` offers), state,
results, Preview on Projector, and Evaluate."""

from pathlib import Path

import bpy

from ..addon.steps import compensate as compensate_step
from ..addon.steps import evaluate as evaluate_step
from .step_state import draw_state


class PROCAM_UL_targets(bpy.types.UIList):
    """The target images, one per row (file name; the full path in the tooltip of the property)."""

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index=0):
        layout.label(text=Path(item.filepath).name or "(no file)", icon="IMAGE_DATA")


class PROCAM_PT_compensate(bpy.types.Panel):
    bl_idname = "PROCAM_PT_compensate"
    bl_label = "Compensate"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ProCam"
    bl_order = 4

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        scene = context.scene
        layout.label(text="Targets:")
        row = layout.row()
        row.template_list("PROCAM_UL_targets", "", scene, "procam_targets", scene, "procam_target_index", rows=3)
        col = row.column(align=True)
        col.operator("procam.add_targets", text="", icon="ADD")
        col.operator("procam.remove_target", text="", icon="REMOVE")
        layout.prop(scene, "procam_target_folder")
        layout.prop(scene, "procam_compensation_mode", expand=True)
        if scene.procam_compensation_mode == "LIVE":  # the closed loop and Evaluate go through the Live panel's rig
            layout.label(text="Device: the Live panel's projector and camera", icon="LINKED")
        else:
            layout.prop(scene, "procam_device")
        if scene.procam_compensation_mode != "OPEN":  # the rule a closed loop follows its captures by
            layout.prop(scene, "procam_loop", expand=True)
        row = layout.row(align=True)
        row.prop(scene, "procam_schedule", text="")
        row.prop(scene, "procam_iterations")
        col = layout.column(align=True)
        col.prop(scene, "procam_area")
        col.prop(scene, "procam_surround")
        col.prop(scene, "procam_effects")
        col.prop(scene, "procam_radiometry")
        col.prop(scene, "procam_range")
        row = col.row(align=True)
        row.prop(scene, "procam_use_bias")
        row.prop(scene, "procam_seed")
        layout.prop(scene, "procam_compensation_dir")
        summary = compensate_step.summary(bpy.path.abspath(scene.procam_compensation_dir))
        done = draw_state(layout, "compensate", summary)
        layout.operator("procam.compensate", icon="PLAY")
        if not done:
            return
        root = bpy.path.abspath(scene.procam_compensation_dir).rstrip("/")
        col = layout.column(align=True)
        count = int(summary.data.get("projector_count", 1))
        if count > 1:  # every projector has its own input: one button each, numbered as the rig counts them
            col.label(text=f"Inputs of projectors 1–{count}; Preview puts each on its projector", icon="LIGHT_SPOT")
        for t in summary.data.get("targets", []):
            row = col.row(align=True)
            row.label(text=t["name"])
            several = t.get("projectors") if count > 1 and isinstance(t.get("projectors"), list) else None
            if several is None:
                op = row.operator("procam.show_image", text="", icon="IMAGE_DATA")
                op.filepath, op.name = f"{root}/{t['input']}", f"ProCam {t['name']} input"
            for k, p in enumerate(several or []):
                op = row.operator("procam.show_image", text=str(k + 1), icon="IMAGE_DATA")
                op.filepath, op.name = f"{root}/{p.get('input', '')}", f"ProCam {t['name']} input p{k + 1}"
            op = row.operator("procam.show_image", text="", icon="CAMERA_DATA")
            op.filepath, op.name = f"{root}/{t['simulated']}", f"ProCam {t['name']} simulated"
            row.operator("procam.preview_compensated", text="", icon="LIGHT_SPOT").target = t["name"]
        layout.operator("procam.preview_compensated", icon="LIGHT_SPOT")
        layout.prop(scene, "procam_evaluation_dir")
        evaluation = evaluate_step.summary(bpy.path.abspath(scene.procam_evaluation_dir))
        draw_state(layout, "evaluate", evaluation)
        layout.operator("procam.evaluate", icon="GRAPH")
