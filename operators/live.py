"""ProCam ▸ Live: the scene's live rig as a ``live:…`` device string, Check Live Rig, Preview Camera and Capture Live.

Threads: SDL wants a window made and used by one thread. On Linux and Windows
that may be any thread, so the check and the capture (and Compensate's Live
mode) open the projector window inside their background job and use it there.
macOS lets only the main thread own windows: there these jobs run in the
foreground (:data:`WINDOW_NEEDS_MAIN_THREAD`), blocking Blender's UI until they
finish, which is the price of a window that opens at all. The camera preview
opens no window and always runs here, on the main thread.
"""

import math
import sys
import time

import bpy
from bpy.props import BoolProperty

from ..addon import jobs
from ..addon.blender import rig as blender_rig
from ..addon.capture.format import srgb_to_linear
from ..addon.errors import ProCamError
from ..addon.live.camera import CameraClient, parse_source
from ..addon.live.device import LiveDevice, LiveReport
from ..addon.live.rig_options import LiveRigOptions
from ..addon.live.window import list_displays
from ..addon.progress import Cancel, Progress
from ..addon.options import from_values, sidebar_names, spec_of
from ..addon.rig.model import Projector
from ..addon.steps.live import LiveCaptureOptions, run_live_capture
from . import paths
from .job_operator import JobOperator, job_running_message
from .messages import sidebar_text

#: macOS (Cocoa) refuses windows outside the main thread; elsewhere the job's worker may own the projector window.
WINDOW_NEEDS_MAIN_THREAD = sys.platform == "darwin"
#: The Blender image Preview Camera writes.
PREVIEW_IMAGE = "ProCam Camera Preview"


def rig_options(scene: bpy.types.Scene) -> LiveRigOptions:
    """The Live panel's rig: its fields as :class:`LiveRigOptions` declares them."""
    return from_values(LiveRigOptions, lambda prop: getattr(scene, prop))


def window_placement(scene: bpy.types.Scene) -> str:
    """The Live panel's projector window(s) as the device string says them (:meth:`LiveRigOptions.window`)."""
    return rig_options(scene).window()


def live_device(scene: bpy.types.Scene) -> str:
    """The scene's Live settings as the ``live:…`` device string (checked: a clear LiveError when it is wrong)."""
    return rig_options(scene).device()


def _live_why_not(scene: bpy.types.Scene) -> str | None:
    if not scene.procam_live_camera.strip():
        return "type the camera's index, device path or URL in the Live panel"
    return None


def _display_line() -> str:
    found = list_displays()
    return "displays: " + ("; ".join(f"{i}: {w}×{h}" + (f" at {hz:.0f} Hz" if hz else "") for i, w, h, hz in found)
                           or "none")


def check_rig(spec: str, projector: Projector, *, progress: Progress, cancel: Cancel,
              check_exposure: bool = True) -> tuple[str, LiveReport]:
    """Open the live device (window, camera, measurements) and close it again: the displays seen and its report.

    Runs as a job: cancelling stops it at the device's next progress report."""
    progress("listing the displays", 0.0)
    displays = _display_line()
    device = LiveDevice(spec, projector, progress=progress, check_exposure=check_exposure)
    device.close()
    return displays, device.report


class _LiveJob(JobOperator):
    def in_foreground(self, context: bpy.types.Context) -> bool:
        return WINDOW_NEEDS_MAIN_THREAD


class PROCAM_OT_live_check(_LiveJob, bpy.types.Operator):
    """Open the projector window and the camera of the Live panel, measure latency, noise and whether the camera's
    exposure is locked, and close them again. Runs in the background, Esc cancels"""

    bl_idname = "procam.live_check"
    bl_label = "Check Live Rig"
    # No UNDO: the check changes no data.
    bl_options = {"REGISTER"}
    step = "live_check"

    @classmethod
    def why_not(cls, scene: bpy.types.Scene) -> str | None:
        why = _live_why_not(scene)
        if why is None and blender_rig.find_rig_objects(scene).projector is None:
            why = "create the rig first: the ProCam Projector gives the window its native size"
        return why

    def make_job(self, context: bpy.types.Context, relay: "jobs.MainThreadRelay | None") -> jobs.Job:
        scene = context.scene
        return jobs.Job("live check", check_rig, live_device(scene), blender_rig.read_projector(scene),
                        check_exposure=scene.procam_live_check_exposure)

    def apply(self, context: bpy.types.Context, result: object) -> str:
        displays, report = result
        return "Live rig: " + "; ".join([*report.lines(), displays])


class PROCAM_OT_live_preview(bpy.types.Operator):
    """Grab one frame from the Live panel's camera into the image "ProCam Camera Preview" (open it in the Image
    Editor) to check what the camera sees"""

    bl_idname = "procam.live_preview"
    bl_label = "Preview Camera"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        # A running live job holds the camera; a second client of it would fight for the frames.
        why = job_running_message() or (_live_why_not(context.scene) if context.scene is not None else "No scene")
        if why is not None:
            cls.poll_message_set(why)
        return why is None

    def execute(self, context: bpy.types.Context) -> set[str]:
        scene = context.scene
        try:
            camera = CameraClient(parse_source(scene.procam_live_camera))
            try:
                # A frame that arrives from now on: some cameras hand out a stale or dark first frame.
                frame = camera.frames_after(time.perf_counter(), 1)[0]
            finally:
                camera.close()
            linear = srgb_to_linear(frame) if scene.procam_live_encoding == "srgb" else frame
            image = blender_rig.set_image(PREVIEW_IMAGE, linear)
        except ProCamError as exc:
            self.report({"ERROR"}, sidebar_text(str(exc)))
            return {"CANCELLED"}
        shown = 0
        for area in (context.screen.areas if context.screen is not None else ()):
            if area.type == "IMAGE_EDITOR":
                area.spaces.active.image = image
                shown += 1
        where = "shown in the Image Editor" if shown else f"open '{PREVIEW_IMAGE}' in an Image Editor to see it"
        self.report({"INFO"}, f"Camera frame {image.size[0]}×{image.size[1]} ({where})")
        return {"FINISHED"}


class PROCAM_OT_live_capture(_LiveJob, bpy.types.Operator):
    """Show the calibration patterns of the scene's projector on the live projector and capture each with the live
    camera into a new capture set (resumes an interrupted session). Runs in the background, Esc cancels"""

    bl_idname = "procam.live_capture"
    bl_label = "Capture Live"
    bl_options = {"REGISTER", "UNDO"}
    step = "live_capture"
    option_names = {"--out": "‘Live Capture Set’ folder", **sidebar_names([LiveCaptureOptions], only=("restart",))}
    cancel_note = "the photographs so far are kept beside the capture-set folder: Capture Live again resumes"
    _out = None  # the capture set being written (a Path), for apply(); no annotation: Blender reads those as properties

    restart: BoolProperty(name=spec_of(LiveCaptureOptions, "restart").label, default=False,
                          description="Discard an interrupted session of other settings instead of refusing")

    @classmethod
    def why_not(cls, scene: bpy.types.Scene) -> str | None:
        why = _live_why_not(scene)
        objs = blender_rig.find_rig_objects(scene)
        if why is None and (objs.camera is None or objs.projector is None):
            why = "create the rig first (ProCam Camera and ProCam Projector): the patterns are the projector's"
        if why is None and not scene.procam_live_capture_dir:
            why = "choose the new capture-set folder in the Live panel"
        return why

    def make_job(self, context: bpy.types.Context, relay: "jobs.MainThreadRelay | None") -> jobs.Job:
        scene = context.scene
        rig = blender_rig.read_rig(scene)  # as Export Patterns: the patterns are those of the scene's projector
        cam = rig.camera.intrinsics
        # The live camera's lens is unknown until calibrated; the scene's ProCam Camera gives its field of view.
        fov = math.degrees(2.0 * math.atan(cam.width / (2.0 * cam.fx)))
        out = paths.resolve(scene.procam_live_capture_dir, "live capture set")
        depth = paths.resolve(scene.procam_live_depth_file, "depth file") if scene.procam_live_depth_file else None
        options = LiveCaptureOptions(live_device(scene), rig.projector, out, camera_fov=fov, depth_path=depth,
                                     check_exposure=scene.procam_live_check_exposure,
                                     force=scene.procam_replace_outputs, restart=self.restart)
        self._out = out
        return jobs.Job("live capture", run_live_capture, options)

    def apply(self, context: bpy.types.Context, result: object) -> str:
        w, h = result.camera.intrinsics.size
        context.scene.procam_capture_dir = str(self._out)  # calibration reads it next
        return f"Live capture set {self._out}: {len(result)} images, camera {w}×{h}; Calibrate uses it"
