"""ProCam ▸ Diagnose: the sim-to-real diagnosis of the calibration as a background job."""

import bpy

from ..addon import jobs
from ..addon.options import from_values
from ..addon.steps import diagnose as diagnose_step
from ..addon.steps.layout import CALIBRATION
from . import paths
from .job_operator import JobOperator
from .messages import DIAGNOSE_FIELDS


class PROCAM_OT_diagnose(JobOperator, bpy.types.Operator):
    """Explain where and why the simulation still differs from the captures (ranked effects, regions, maps);
    runs in the background, Esc cancels"""

    bl_idname = "procam.diagnose"
    bl_label = "Diagnose"
    bl_options = {"REGISTER", "UNDO"}
    step = "diagnose"
    option_names = DIAGNOSE_FIELDS

    @classmethod
    def why_not(cls, scene: bpy.types.Scene) -> str | None:
        if paths.existing(scene.procam_calibration_dir, CALIBRATION.manifest) is None:
            return "no calibration: run Calibrate or choose a calibration folder"
        if not scene.procam_diagnosis_dir:
            return "choose the diagnosis folder to write"
        return None

    def make_job(self, context: bpy.types.Context, relay: "jobs.MainThreadRelay | None") -> jobs.Job:
        scene = context.scene
        cal = paths.resolve(scene.procam_calibration_dir, "calibration folder")
        out = paths.resolve(scene.procam_diagnosis_dir, "diagnosis folder")
        options = from_values(diagnose_step.DiagnoseOptions, lambda prop: getattr(scene, prop), calibration=cal,
                              out=out, force=scene.procam_replace_outputs)
        return jobs.Job("diagnosis", diagnose_step.run, options)

    def apply(self, context: bpy.types.Context, result: object) -> str:
        summary = diagnose_step.summary(paths.resolve(context.scene.procam_diagnosis_dir, "diagnosis folder"))
        return f"Diagnosis: {summary.headline}"
