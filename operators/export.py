"""ProCam ▸ Export: save the calibration as a .blend or as a VESA MPCDI file for media servers, or the compensated
frames as a numbered 16-bit PNG sequence."""

import bpy
from bpy.props import BoolProperty, EnumProperty, StringProperty

from ..addon.blender.blend_file import save_calibration_blend_atomic
from ..addon.errors import ProCamError
from ..addon.options import spec_of
from ..addon.steps import export as export_step
from ..addon.steps import mpcdi as mpcdi_step
from ..addon.steps.mpcdi import ExportMpcdiOptions
from ..addon.steps.layout import CALIBRATION, COMPENSATION
from . import paths
from .messages import REPLACE_BOX, sidebar_text


def _has_calibration(cls: type, context: bpy.types.Context) -> bool:
    """The poll of an export from the calibration folder: there is one."""
    if paths.existing(context.scene.procam_calibration_dir, CALIBRATION.manifest) is None:
        cls.poll_message_set("no calibration folder: run Calibrate or choose one")  # type: ignore[attr-defined]
        return False
    return True


class PROCAM_OT_export_calibration_blend(bpy.types.Operator):
    """Save the calibration (rig, textured surface, diagnostic images) as a .blend file; the open file is untouched"""

    bl_idname = "procam.export_calibration_blend"
    bl_label = "Save Calibration .blend"
    bl_options = {"REGISTER"}  # writes a file, changes no data in this one

    filepath: StringProperty(name="File", subtype="FILE_PATH")
    filter_blender: BoolProperty(default=True, options={"HIDDEN", "SKIP_SAVE"})
    force: BoolProperty(name="Replace", description="Replace an existing file")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return _has_calibration(cls, context)

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        if not self.filepath:
            self.filepath = str(paths.existing(context.scene.procam_calibration_dir, CALIBRATION.manifest)
                                / "scene.blend")
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            out = export_step.run_blend(export_step.ExportBlendOptions(
                paths.resolve(context.scene.procam_calibration_dir, "calibration folder"),
                paths.resolve(self.filepath, ".blend file"), force=self.force),
                writer=save_calibration_blend_atomic)
        except ProCamError as exc:
            self.report({"ERROR"}, sidebar_text(str(exc), REPLACE_BOX | {"--out": "‘File’"}))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Saved the calibration as {out}")
        return {"FINISHED"}


class PROCAM_OT_export_frames(bpy.types.Operator):
    """Write the compensated projector frames as a numbered 16-bit PNG sequence (one per projector) for media servers"""

    bl_idname = "procam.export_frames"
    bl_label = "Export Projector Frames"
    bl_options = {"REGISTER"}  # writes files, changes no data

    directory: StringProperty(name="Folder", subtype="DIR_PATH")
    filter_folder: BoolProperty(default=True, options={"HIDDEN", "SKIP_SAVE"})
    force: BoolProperty(name="Replace", description="Replace an existing frame sequence")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        if paths.existing(context.scene.procam_compensation_dir, COMPENSATION.manifest) is None:
            cls.poll_message_set("no compensation results: run Compensate or choose a results folder")
            return False
        return True

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            out = export_step.run_frames(export_step.ExportFramesOptions(
                paths.resolve(context.scene.procam_compensation_dir, "results folder"),
                paths.resolve(self.directory, "frame folder"), force=self.force))
        except ProCamError as exc:
            self.report({"ERROR"}, sidebar_text(str(exc), REPLACE_BOX | {"--out": "‘Folder’"}))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Projector frames written to {out}")
        return {"FINISHED"}


def _profile_items() -> list[tuple[str, str, str]]:
    return [(c.value, c.label, c.description) for c in spec_of(ExportMpcdiOptions, "profile").offered]


class PROCAM_OT_export_mpcdi(bpy.types.Operator):
    """Write the calibration as a VESA MPCDI file (warp, blend and black level per projector) for media servers"""

    bl_idname = "procam.export_mpcdi"
    bl_label = "Export MPCDI"
    bl_options = {"REGISTER"}  # writes a file, changes no data

    filepath: StringProperty(name="File", subtype="FILE_PATH")
    filter_glob: StringProperty(default="*.mpcdi", options={"HIDDEN", "SKIP_SAVE"})
    profile: EnumProperty(name="Profile", items=_profile_items())
    force: BoolProperty(name="Replace", description="Replace an existing MPCDI file")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return _has_calibration(cls, context)

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        if not self.filepath:
            folder = paths.existing(context.scene.procam_calibration_dir, CALIBRATION.manifest)
            self.filepath = str(folder.parent / f"{folder.name}.mpcdi")
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            done = mpcdi_step.run_export(mpcdi_step.ExportMpcdiOptions(
                paths.resolve(context.scene.procam_calibration_dir, "calibration folder"),
                paths.resolve(self.filepath, ".mpcdi file"), profile=self.profile, force=self.force))
        except ProCamError as exc:
            self.report({"ERROR"}, sidebar_text(str(exc), REPLACE_BOX | {"--out": "‘File’"}))
            return {"CANCELLED"}
        for line in done.warnings:
            self.report({"WARNING"}, line)
        self.report({"INFO"}, f"Wrote the MPCDI file {done.path} ({len(done.report['projectors'])} projector(s), "
                              f"{done.bytes // 1024} KiB)")
        return {"FINISHED"}
