"""ProCam ▸ Open Report: the HTML report of the scene's step folders (``procam report``), opened in the system
browser — rebuilt first where this Python can build it, else the one last built."""

import webbrowser
from pathlib import Path

import bpy

from ..addon.errors import ProCamError
from ..addon.steps import report as report_step
from ..addon.steps.layout import CALIBRATION, COMPENSATION, DIAGNOSIS, EVALUATION, SHOW
from . import paths
from .messages import sidebar_text

#: the scene's folder properties, each with the kind of step folder it names, in the workflow's order
FOLDERS = (("procam_calibration_dir", CALIBRATION), ("procam_compensation_dir", COMPENSATION),
           ("procam_evaluation_dir", EVALUATION), ("procam_show_dir", SHOW), ("procam_diagnosis_dir", DIAGNOSIS))


def scene_folders(scene: bpy.types.Scene) -> list[Path]:
    """The scene's step folders that hold their step's manifest."""
    found = (paths.existing(getattr(scene, prop, ""), kind.manifest) for prop, kind in FOLDERS)
    return [p.absolute() for p in found if p is not None]


class PROCAM_OT_open_report(bpy.types.Operator):
    """Open one HTML page of the scene's step folders (calibration, evaluation, diagnosis, show) in the web
    browser, built again from what the folders hold now"""

    bl_idname = "procam.open_report"
    bl_label = "Open Report"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        if context.scene is None or not scene_folders(context.scene):
            cls.poll_message_set("no step folder yet: run a step, or choose its folder")
            return False
        return True

    def execute(self, context: bpy.types.Context) -> set[str]:
        folders = scene_folders(context.scene)
        try:
            out = report_step.place_for(folders)
            missing = report_step.missing_libraries()
            note = ""
            if missing:
                if not out.is_file():
                    raise ProCamError(f"building the report needs {' and '.join(missing)}, which Blender's Python "
                                      f"lacks: run `procam report {' '.join(map(str, folders))} --out {out}` in "
                                      "ProCam's environment (scripts/setup.sh makes it), then press Open Report "
                                      "again to open it")
                note = f" (as last built: rebuilding it needs {' and '.join(missing)}, which Blender lacks)"
            else:
                result = report_step.run(report_step.ReportOptions(tuple(folders), out, force=True))
                if result.skipped:
                    note = f"; {len(result.skipped)} thing(s) skipped, listed at its end"
        except ProCamError as exc:
            self.report({"ERROR"}, sidebar_text(str(exc)))
            return {"CANCELLED"}
        opened = webbrowser.open(out.as_uri())
        where = "opened in the web browser" if opened else "no web browser answered: open it yourself"
        self.report({"WARNING" if missing or not opened else "INFO"}, f"Report {out}: {where}{note}")
        return {"FINISHED"}
