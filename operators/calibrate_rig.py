"""ProCam ▸ Calibrate Rig: camera and projector lenses and their pose from chessboard sessions, as a background job.

The sessions are the subfolders of one folder (optionally those matching a name pattern), one board pose each,
as ``procam calibrate-rig`` takes them; the result is a ``rig.json`` that Import Captures then uses. The scene
changes only in its rig-file path.
"""

from pathlib import Path

import bpy

from ..addon import jobs
from ..addon.errors import CalibrationError, CaptureError
from ..addon.options import from_values, sidebar_names
from ..addon.stages.rig_calibration import MIN_POSES, RigCalibration
from ..addon.steps import rig as rig_step
from . import paths
from .job_operator import JobOperator

#: The operator whose Rig Calibration a successful run fills in.
IMPORT_CAPTURES = "procam.import_captures"


def find_sessions(scene: bpy.types.Scene) -> list[Path]:
    """The scene's board session folders (absolute), checked: at least MIN_POSES of them, else a clear error."""
    folder = paths.resolve(scene.procam_board_sessions_dir, "board sessions folder")
    pattern = scene.procam_board_sessions_filter.strip() or "*"
    if not folder.is_dir():
        raise CaptureError(f"the board sessions folder {folder} does not exist: choose the folder that holds one "
                           "subfolder per board pose")
    sessions = paths.board_sessions(folder, pattern)
    if not sessions and paths.holds_numbered_images(folder):
        raise CaptureError(f"{folder} holds the images of one pose itself: choose the folder above it, which holds "
                           "one subfolder per board pose")
    if len(sessions) < MIN_POSES:
        found = f" ({', '.join(p.name for p in sessions)})" if sessions else ""
        raise CalibrationError(f"{len(sessions)} board pose folder(s) with numbered images in {folder} match "
                               f"'{pattern}'{found}; rig calibration needs at least {MIN_POSES}: capture more "
                               "poses, or check the folder and the name filter")
    return sessions


def describe(cal: RigCalibration, out: str) -> str:
    """The outcome as one report line: overall and per-pose RMS, skipped poses, warnings."""
    per_pose = ", ".join(f"{p.name} {p.camera_rms:.2f}/{p.projector_rms:.2f}" for p in cal.poses
                         if p.used and p.camera_rms is not None and p.projector_rms is not None)
    text = (f"Rig calibrated from {len(cal.used)} of {len(cal.poses)} poses: RMS camera {cal.camera_rms:.3f} px, "
            f"projector {cal.projector_rms:.3f} px, stereo {cal.stereo_rms:.3f} px; per pose (camera/projector "
            f"px): {per_pose}")
    text += "".join(f"; skipped {name}: {why}" for name, why in cal.skipped.items())
    text += "".join(f"; warning: {w}" for w in cal.warnings)
    if not cal.metric:
        text += "; lengths in board squares (give the square size for a metric projector pose)"
    return f"{text}. Import Captures will use {out}"


class PROCAM_OT_calibrate_rig(JobOperator, bpy.types.Operator):
    """Calibrate the camera, the projector and their pose from photographs of a chessboard lit by Gray code (one
    subfolder per board pose); writes rig.json for Import Captures. Runs in the background, Esc cancels"""

    bl_idname = "procam.calibrate_rig"
    bl_label = "Calibrate Rig"
    bl_options = {"REGISTER", "UNDO"}
    step = "calibrate_rig"
    option_names = {"--out": "‘Rig File’", **sidebar_names([rig_step.RigOptions])}
    _out = None  # the rig.json being written (a Path), for apply(); no annotation: Blender reads those as properties

    @classmethod
    def why_not(cls, scene: bpy.types.Scene) -> str | None:
        if not scene.procam_board_sessions_dir:
            return "choose the folder of board sessions (one subfolder per board pose)"
        if not scene.procam_rig_file:
            return "choose the rig.json file to write"
        return None

    def make_job(self, context: bpy.types.Context, relay: "jobs.MainThreadRelay | None") -> jobs.Job:
        scene = context.scene
        sessions = find_sessions(scene)
        out = paths.resolve(scene.procam_rig_file, "rig file")
        if out.is_dir():  # a folder picked by mistake: write the usual name inside it
            out = out / rig_step.KIND.manifest
        cols, rows = scene.procam_board_corners
        width, height = scene.procam_board_projector_size
        square = float(scene.procam_board_square)
        options = from_values(rig_step.RigOptions, lambda prop: getattr(scene, prop), sessions=tuple(sessions),
                              out=out, board=(int(cols), int(rows)), projector_size=(int(width), int(height)),
                              square=square if square > 0 else None, force=scene.procam_replace_outputs)
        self._out = out
        return jobs.Job("rig calibration", rig_step.run, options)

    def apply(self, context: bpy.types.Context, result: object) -> str:
        out = str(self._out)
        context.scene.procam_rig_file = out
        # The dialog of Import Captures opens with its last-used values: the new rig is then already filled in.
        context.window_manager.operator_properties_last(IMPORT_CAPTURES).rig_file = out
        return describe(result, out)
