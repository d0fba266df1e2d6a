"""View3D ▸ Sidebar ▸ ProCam ▸ Captures ▸ Board Calibration: the chessboard sessions, their settings, and the
rig.json that Calibrate Rig writes (its state and key figures)."""

from pathlib import Path

import bpy
from bpy.props import FloatProperty, IntVectorProperty, StringProperty

from ..addon.options import spec_of
from ..addon.stages.rig_calibration import MIN_POSES
from ..addon.steps import rig as rig_step
from ..addon.steps.summary import Summary
from ..operators import paths
from .properties import declared_properties
from .step_state import draw_state, wrapped

def scene_properties() -> dict[str, object]:
    """Scene properties this panel shows (registered on ``bpy.types.Scene`` by ``blender_registration``)."""
    return {
        "procam_board_sessions_dir": StringProperty(
            name="Board Sessions", subtype="DIR_PATH",
            description="Folder with one subfolder per board pose, each holding the camera's images graycode_00 … "
                        "in projection order: the Gray code (OpenCV's order), then white, then black"),
        "procam_board_sessions_filter": StringProperty(
            name="Name Filter", default="*",
            description="Which subfolders are board poses (a pattern such as pose_* or capture_*); others, like a "
                        "folder of the pattern images themselves, are left out"),
        "procam_board_corners": IntVectorProperty(
            name=spec_of(rig_step.RigOptions, "board").label, size=2, default=(9, 7), min=2, soft_max=40,
            description="The chessboard's inner corners per row and rows (9 × 7 and 7 × 9 find the same board)"),
        "procam_board_square": FloatProperty(
            name=spec_of(rig_step.RigOptions, "square").label, subtype="DISTANCE", unit="LENGTH",
            default=0.0, min=0.0, soft_max=0.2, precision=4,
            description="One chessboard square, measured (makes the projector's position metric, so Import "
                        "Captures can use it); 0: unknown, lengths in board squares"),
        "procam_board_projector_size": IntVectorProperty(
            name=spec_of(rig_step.RigOptions, "projector_size").label, size=2, default=(1920, 1080), min=1,
            description="The projector's native width and height the Gray code was made for (the number of "
                        "images alone does not tell it)"),
        **declared_properties(rig_step.RigOptions),
        "procam_rig_file": StringProperty(
            name="Rig File", subtype="FILE_PATH",
            description="The rig.json that Calibrate Rig writes; Import Captures then uses it"),
    }


_SESSIONS: dict[tuple[str, str], tuple[object, tuple[str, str]]] = {}


def sessions_status(folder: str, pattern: str) -> tuple[str, str]:
    """(icon, text): how many board poses the folder holds, by name, kept until the folder changes (panels redraw
    often; no image is read here)."""
    if not folder:
        return "INFO", "Choose the folder of board sessions (one subfolder per pose)"
    root = Path(bpy.path.abspath(folder))
    try:
        stamp: object = root.stat().st_mtime_ns
    except OSError:
        return "ERROR", f"{root} does not exist"
    key = (str(root), pattern)
    hit = _SESSIONS.get(key)
    if hit is not None and hit[0] == stamp:
        return hit[1]
    found = paths.board_sessions(root, pattern.strip() or "*")
    names = ", ".join(p.name for p in found[:6]) + (" …" if len(found) > 6 else "")
    if len(found) >= MIN_POSES:
        result = ("CHECKMARK", f"{len(found)} board poses: {names}")
    elif paths.holds_numbered_images(root):
        result = ("ERROR", "This folder is one pose: choose the folder above it")
    else:
        result = ("ERROR", f"{len(found)} board poses{': ' + names if found else ''} (at least {MIN_POSES} needed)")
    _SESSIONS[key] = (stamp, result)
    return result


class PROCAM_PT_board(bpy.types.Panel):
    bl_idname = "PROCAM_PT_board"
    bl_label = "Board Calibration"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ProCam"
    bl_parent_id = "PROCAM_PT_captures"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        scene = context.scene
        layout.prop(scene, "procam_board_sessions_dir", text="")
        layout.prop(scene, "procam_board_sessions_filter")
        icon, text = sessions_status(scene.procam_board_sessions_dir, scene.procam_board_sessions_filter)
        wrapped(layout, text, icon=icon)
        col = layout.column(align=True)
        col.prop(scene, "procam_board_corners")
        col.prop(scene, "procam_board_square")
        col.prop(scene, "procam_board_projector_size")
        col = layout.column(align=True)
        col.prop(scene, "procam_board_camera_distortion", text="Camera")
        col.prop(scene, "procam_board_projector_distortion", text="Projector")
        col.prop(scene, "procam_board_window")
        layout.prop(scene, "procam_rig_file", text="")
        path = bpy.path.abspath(scene.procam_rig_file) if scene.procam_rig_file else ""
        if path and Path(path).is_file():
            summary = rig_step.summary(path)
        else:
            summary = Summary(False, "Choose the board sessions and the rig.json to write, then Calibrate Rig")
        draw_state(layout, "calibrate_rig", summary)
        col = layout.column(align=True)
        col.operator("procam.calibrate_rig", icon="PLAY")
        col.prop(scene, "procam_replace_outputs")
