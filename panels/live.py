"""View3D ▸ Sidebar ▸ ProCam ▸ Live: the real projector and camera (the ``live:…`` device), a check of the rig, a
camera preview, the calibration set captured live, where Compensate's Live mode gets its device, and the live show
(Start/Stop Live Show, its measured frame rate while it runs and its report after)."""

from pathlib import Path

import bpy
from bpy.props import BoolProperty, StringProperty

from ..addon import jobs
from ..addon.options import prop_name, sidebar_fields
from ..addon.live.rig_options import LiveRigOptions
from ..addon.steps.live import SESSION_MANIFEST
from ..addon.steps.live_show import LiveShowOptions
from ..addon.steps.stage_c import StageCOptions
from ..addon.steps.summary import Summary
from ..operators.live_show import SHOW_STATUS, show_running
from .captures import capture_set_status
from .properties import declared_properties, declared_property
from .step_state import draw_state, wrapped

def _show_properties() -> dict[str, object]:
    """The live show's own fields as ``LiveShowOptions`` declares them; Range, Effect Models and Display Area are
    the Compensate panel's (the same options of stage C), not made twice."""
    compensate = {prop_name(d) for d in sidebar_fields(StageCOptions)}
    return {prop_name(d): declared_property(d) for d in sidebar_fields(LiveShowOptions)
            if prop_name(d) not in compensate}


def scene_properties() -> dict[str, object]:
    """Scene properties this panel shows (registered on ``bpy.types.Scene`` by ``blender_registration``)."""
    return {
        **_show_properties(),
        "procam_live_follow_camera": BoolProperty(
            name="Follow Camera", default=False,
            description="Closed loop: the camera above (with its averaging, encoding and latency) films the show "
                        "and the compensation follows it slowly; off: open loop, the window alone"),
        **declared_properties(LiveRigOptions),
        "procam_live_depth_file": StringProperty(
            name="Depth", subtype="FILE_PATH",
            description="Optional depth of the scene seen from the camera (as Import Captures takes it), for "
                        "calibration's surface"),
        "procam_live_capture_dir": StringProperty(
            name="Live Capture Set", subtype="DIR_PATH",
            description="New capture-set folder for Capture Live (an interrupted session waits beside it, in "
                        "FOLDER.session, and Capture Live resumes it)"),
    }


def check_summary() -> Summary:
    """The last Check Live Rig's findings (kept on the job board), or what it would tell."""
    job = jobs.BOARD.get("live_check")
    if job is not None and job.status == jobs.DONE:
        displays, report = job.result
        return Summary(True, "Live rig checked", (displays, *report.lines()))
    return Summary(False, "Check Live Rig measures latency, noise and the exposure lock")


def _ms(value: float | None) -> str:
    return "–" if value is None else f"{value:.0f} ms"


def show_summary() -> Summary:
    """The live show: the last second's figures while it runs (frame rate, frames shown and dropped, latency),
    the last report's after it stopped; ``data`` holds the figures."""
    if show_running() is not None:
        s = SHOW_STATUS.latest
        if s is None:
            return Summary(False, "Live show starting: opening the source, the solver and the window")
        return Summary(False, f"{s.fps:.1f} fps: shown {s.shown}, dropped {s.dropped}",
                       (f"latency {_ms(s.latency_ms)}, solve {_ms(s.solve_ms)}", f"{s.frames_in} frames in, "
                        f"{s.elapsed:.0f} s"),
                       {"fps": s.fps, "shown": s.shown, "dropped": s.dropped, "latency_ms": s.latency_ms})
    job = jobs.BOARD.get("live_show")
    if job is not None and job.status == jobs.DONE:
        r = job.result
        first, *rest = r.lines()
        return Summary(True, first[:1].upper() + first[1:], (*rest, *r.said[:3]),
                       {"fps": r.fps, "shown": r.shown, "dropped": r.dropped, "latency_ms": r.latency_ms[0]})
    return Summary(False, "Start Live Show compensates the source as it plays, in the window above")


def capture_summary(folder: str) -> Summary:
    """What the live capture folder holds: a capture set, an interrupted session, or nothing yet."""
    if not folder:
        return Summary(False, "Choose the new capture-set folder, then Capture Live")
    root = Path(bpy.path.abspath(folder).rstrip("/\\"))
    if (root.with_name(root.name + ".session") / SESSION_MANIFEST).is_file():
        return Summary(False, f"An interrupted session waits in {root.name}.session: Capture Live resumes it")
    icon, text = capture_set_status(folder)
    if icon == "CHECKMARK":
        return Summary(True, f"Captured: {text}")
    return Summary(False, "Capture Live shows the calibration patterns and captures each")


def draw_show(layout: bpy.types.UILayout, scene: bpy.types.Scene) -> None:
    """The live show's source and settings, Start or Stop Live Show, and its figures."""
    layout.separator()
    layout.label(text="Live Show", icon="PLAY")
    layout.prop(scene, "procam_live_source")
    col = layout.column(align=True)
    col.prop(scene, "procam_live_follow_camera")
    col.prop(scene, "procam_live_refine_steps")
    col.prop(scene, "procam_live_hold")
    col.prop(scene, "procam_live_duration")
    layout.prop(scene, "procam_live_correction")  # written while following the camera, read without one
    summary = show_summary()
    if show_running() is not None:  # the measured figures in place of a progress bar: a show has no end
        box = layout.box()
        wrapped(box, summary.headline, icon="TIME")
        for line in summary.lines:
            wrapped(box, line)
        layout.operator("procam.live_show_stop", icon="PAUSE")
        return
    draw_state(layout, "live_show", summary)
    layout.operator("procam.live_show_start", icon="PLAY")
    wrapped(layout, "Calibration, Range, Effect Models and Display Area: Compensate's", icon="INFO")


class PROCAM_PT_live(bpy.types.Panel):
    bl_idname = "PROCAM_PT_live"
    bl_label = "Live"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ProCam"
    bl_order = 2
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        scene = context.scene
        layout.prop(scene, "procam_live_camera")
        layout.prop(scene, "procam_live_placement", expand=True)
        if scene.procam_live_placement == "DISPLAY":
            layout.prop(scene, "procam_live_display")
        else:
            layout.prop(scene, "procam_live_position")
        col = layout.column(align=True)
        col.prop(scene, "procam_live_average")
        col.prop(scene, "procam_live_encoding", text="")
        row = col.row(align=True)
        row.prop(scene, "procam_live_latency_auto")
        sub = row.row(align=True)
        sub.enabled = not scene.procam_live_latency_auto
        sub.prop(scene, "procam_live_latency", text="")
        col.prop(scene, "procam_live_check_exposure")
        row = layout.row(align=True)
        row.operator("procam.live_check", icon="VIEWZOOM")
        row.operator("procam.live_preview", icon="CAMERA_DATA")
        draw_state(layout, "live_check", check_summary())
        layout.separator()
        layout.prop(scene, "procam_live_capture_dir")
        layout.prop(scene, "procam_live_depth_file")
        summary = capture_summary(scene.procam_live_capture_dir)
        draw_state(layout, "live_capture", summary)
        job = jobs.BOARD.get("live_capture")
        if job is not None and job.finished and not summary.ok:
            # After Esc or a failure the photographs so far are kept: say that a rerun resumes them.
            wrapped(layout, summary.headline, icon="INFO")
        col = layout.column(align=True)
        col.operator("procam.live_capture", icon="REC")
        col.prop(scene, "procam_replace_outputs")
        wrapped(layout, "Compensate ▸ Live runs the closed loop through this rig", icon="INFO")
        draw_show(layout, scene)
