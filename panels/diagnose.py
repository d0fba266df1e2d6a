"""View3D ▸ Sidebar ▸ ProCam ▸ Diagnose: ranked effects, regions and residual maps of a diagnosis folder."""

from dataclasses import replace

import bpy

from ..addon.steps import diagnose as diagnose_step
from ..addon.steps.summary import Summary
from ..addon.steps.summary import fmt as _num
from ..operators.messages import DIAGNOSE_FIELDS, sidebar_text
from .step_state import draw_state, wrapped


class PROCAM_PT_diagnose(bpy.types.Panel):
    bl_idname = "PROCAM_PT_diagnose"
    bl_label = "Diagnose"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ProCam"
    bl_order = 5

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        scene = context.scene
        layout.prop(scene, "procam_diagnosis_dir", text="")
        summary = diagnose_step.summary(bpy.path.abspath(scene.procam_diagnosis_dir))
        # The diagnosis's advice names the command's options: here, the sidebar's fields; the effects and regions
        # the command lists after it are drawn below, all of them, in boxes of their own.
        brief = summary.lines[:summary.data.get("brief", len(summary.lines))]
        shown = replace(summary, lines=tuple(sidebar_text(line, DIAGNOSE_FIELDS) for line in brief))
        done = draw_state(layout, "diagnose", shown)
        row = layout.row(align=True)
        row.prop(scene, "procam_diagnosis_scale")
        row.prop(scene, "procam_max_effects")
        layout.operator("procam.diagnose", icon="VIEWZOOM")
        # every step's folder on one page, in the web browser (after the last step of the workflow)
        layout.operator("procam.open_report", icon="URL")
        if not done:
            return
        if summary.data.get("projector_count", 1) > 1:
            # several projectors: the headline names the one that differs, a line per projector is drawn above;
            # each projector's effects and regions are in its own folder (its maps below, its summary in Open)
            draw_files(layout, scene, summary)
            return
        selected = set(summary.data["selected"])
        box = layout.box()
        box.label(text="Effects (selected first, as the diagnosis ranks them):")
        for e in summary.data["effects"]:
            row = box.row()
            row.label(text=e["name"], icon="CHECKBOX_HLT" if e["name"] in selected else "CHECKBOX_DEHLT")
            conf = e.get("confidence")
            level = conf.get("level", "–") if isinstance(conf, dict) else _num(conf, ".2f")
            row.label(text=f"removes {_num(100 * float(e.get('reduction') or 0), '.0f')}%, "
                           f"RMSE {_num(e.get('heldout_rmse_before'), '.4f')} → "
                           f"{_num(e.get('heldout_rmse_after'), '.4f')}, {level}")
        box = layout.box()
        box.label(text="Regions (by share of the error):")
        for r in summary.data["regions"]:
            wrapped(box, f"{100 * float(r.get('share', 0) or 0):.0f}% {r.get('description', '')} "
                         f"{tuple(r.get('bbox', ()))}", icon="SELECT_SET")
        draw_files(layout, scene, summary)


def draw_files(layout: bpy.types.UILayout, scene: bpy.types.Scene, summary: Summary) -> None:
    """The summary text and the residual maps (with several projectors, under each projector's number)."""
    root = bpy.path.abspath(scene.procam_diagnosis_dir).rstrip("/")
    if summary.data.get("summary"):
        op = layout.operator("procam.show_text", text="Open Summary", icon="TEXT")
        op.filepath, op.name = f"{root}/{summary.data['summary']}", "ProCam diagnosis summary"
    if summary.data["maps"]:
        col = layout.column(align=True)
        col.label(text="Residual maps:")
        folder = None
        for rel in summary.data["maps"]:
            if "/" in rel and rel.split("/", 1)[0] != folder:  # projector_K/…: a heading per projector
                folder = rel.split("/", 1)[0]
                col.label(text=folder.replace("projector_", "Projector ") + ":", icon="LIGHT_SPOT")
            op = col.operator("procam.show_image", text=rel.removesuffix(".png").split("/")[-1],
                              icon="IMAGE_DATA")
            op.filepath, op.name = f"{root}/{rel}", f"ProCam diagnosis {rel.removesuffix('.png')}"
