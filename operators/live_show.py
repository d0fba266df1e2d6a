"""ProCam ▸ Live ▸ Start Live Show / Stop Live Show: ``procam live-show`` as a background job of the Live panel.

The show runs as the Live panel's other jobs do (operators/live.py says which
thread may own the projector window): in the job's worker thread on Linux and
Windows, in the foreground on macOS (there only Esc in the projector window or
the Duration stops it, Blender's UI being blocked). Its status line (frames
in, shown, dropped, solve and latency, frames per second) is the job's
progress message each second; the newest :class:`LiveStatus` is kept in
:data:`SHOW_STATUS` for the panel. Stop Live Show and Esc in Blender (the job
operator's modal) cancel the job: the loop then ends as Esc in the projector
window ends it, the windows close, and the show's report is the job's result,
which the panel keeps. A stop before the loop runs (while the calibration and
the solver open) cancels the job: nothing was shown.

The calibration is the scene's (as Compensate reads it), the window the Live
panel's (with its camera when Follow Camera is on: closed loop), and Range,
Effect Models and Display Area the Compensate panel's.
"""

from __future__ import annotations

from dataclasses import dataclass

import bpy

from ..addon import jobs
from ..addon.errors import LiveError
from ..addon.options import from_values, sidebar_names, validate
from ..addon.progress import Cancel, Progress
from ..addon.steps.layout import CALIBRATION
from ..addon.steps.live_show import LiveShowCancelled, LiveShowOptions, LiveShowReport, LiveStatus, run_live_show
from . import paths
from .compensate import effects_diagnosis
from .job_operator import JobOperator
from .live import WINDOW_NEEDS_MAIN_THREAD, live_device, window_placement

#: How a show's report says that Blender stopped it.
STOPPED_IN_BLENDER = "Stop Live Show (or Esc) in Blender"


@dataclass
class ShowStatus:
    """The running live show's newest status: written by the show's thread once a second, read by the panel (one
    attribute set and read whole: no lock needed)."""

    latest: LiveStatus | None = None

    def update(self, status: LiveStatus) -> None:
        self.latest = status


#: The status of the live show that runs (or ran last).
SHOW_STATUS = ShowStatus()


def play_live_show(options: LiveShowOptions, *, progress: Progress, cancel: Cancel) -> LiveShowReport:
    """:func:`run_live_show` as a job runs it: its status kept in :data:`SHOW_STATUS`; a cancel once the loop runs
    ends the show with its report (the module doc)."""
    SHOW_STATUS.latest = None
    try:
        return run_live_show(options, progress, cancel, on_status=SHOW_STATUS.update)
    except LiveShowCancelled as exc:
        exc.report.stopped = STOPPED_IN_BLENDER
        return exc.report


def show_source(scene: bpy.types.Scene) -> str:
    """The Live panel's source: a video file (a path relative to the .blend resolved), a camera index or path, or a
    stream URL as typed."""
    text = scene.procam_live_source.strip()
    if not text:
        raise LiveError("no live show source: type a video file, a camera index (0) or a stream URL in the Live "
                        "panel's Source")
    # The file browser may give a path relative to the .blend (//clip.mp4); an index or a URL is kept as typed.
    return str(paths.resolve(text, "live show source")) if text.startswith("//") else text


def show_device(scene: bpy.types.Scene) -> str:
    """The live show's ``live:…`` device: the Live panel's window, open loop; with Follow Camera its whole rig,
    camera included (θ follows the camera: closed loop)."""
    if scene.procam_live_follow_camera:
        return live_device(scene)
    return "live:" + window_placement(scene)


def show_options(scene: bpy.types.Scene) -> LiveShowOptions:
    """The scene's settings as ``procam live-show`` takes them (checked: a clear ProCamError when one is wrong)."""
    options = from_values(LiveShowOptions, lambda prop: getattr(scene, prop),
                          calibration=paths.resolve(scene.procam_calibration_dir, "calibration folder"),
                          source=show_source(scene), device=show_device(scene), diagnosis=effects_diagnosis(scene))
    validate(options, LiveError)
    return options


def show_running() -> jobs.Job | None:
    """The live show's job while it runs, else None."""
    job = jobs.BOARD.get("live_show")
    return job if job is not None and not job.finished else None


class PROCAM_OT_live_show_start(JobOperator, bpy.types.Operator):
    """Compensate the Live panel's source (a video file, camera or stream) frame by frame with the scene's
    calibration and show it in the projector window as it plays, in the background; Stop Live Show or Esc stops it"""

    bl_idname = "procam.live_show_start"
    bl_label = "Start Live Show"
    # No UNDO: a live show changes no Blender data (its figures stay with its job, for the panel).
    bl_options = {"REGISTER"}
    step = "live_show"
    option_names = {**sidebar_names([LiveShowOptions]), "--device": "the Live panel's window"}
    cancel_note = "it stopped before its first frame; the scene is unchanged"

    def in_foreground(self, context: bpy.types.Context) -> bool:
        return WINDOW_NEEDS_MAIN_THREAD

    @classmethod
    def why_not(cls, scene: bpy.types.Scene) -> str | None:
        if paths.existing(scene.procam_calibration_dir, CALIBRATION.manifest) is None:
            return "no calibration: run Calibrate or choose a calibration folder"
        if not scene.procam_live_source.strip():
            return "type the live show's Source in the Live panel: a video file, a camera index or a stream URL"
        if scene.procam_live_follow_camera and not scene.procam_live_camera.strip():
            return "Follow Camera needs the Live panel's camera (its index, device path or URL)"
        return None

    def make_job(self, context: bpy.types.Context, relay: jobs.MainThreadRelay | None) -> jobs.Job:
        return jobs.Job("live show", play_live_show, show_options(context.scene))

    def apply(self, context: bpy.types.Context, result: object) -> str:
        report: LiveShowReport = result
        first, _, stopped = report.lines()
        return f"{first[:1].upper()}{first[1:]}; {stopped}"


class PROCAM_OT_live_show_stop(bpy.types.Operator):
    """Stop the running live show: its windows close and the Live panel keeps its figures (as Esc)"""

    bl_idname = "procam.live_show_stop"
    bl_label = "Stop Live Show"
    # No UNDO: stopping changes no data.
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        if show_running() is None:
            cls.poll_message_set("no live show is running")
            return False
        return True

    def execute(self, context: bpy.types.Context) -> set[str]:
        job = show_running()
        if job is None:
            self.report({"WARNING"}, "nothing to stop: the live show has already ended")
            return {"CANCELLED"}
        job.cancel()
        self.report({"INFO"}, "Stopping the live show…")
        return {"FINISHED"}
