"""ProCam ▸ Compensate (stage C for every target), Evaluate and Prepare Show (background jobs), the target list,
and Preview on Projector.

The compensated inputs and simulated camera views become Blender images
(``ProCam NAME input`` / ``ProCam NAME simulated``, read from the result
folder); Preview on Projector puts one compensated frame on the ProCam
Projector so that a Cycles render shows it on the surface.
"""

from collections.abc import Callable
from pathlib import Path
from typing import Any

import bpy
from bpy.props import CollectionProperty, StringProperty

from ..addon import jobs
from ..addon.blender import rig as blender_rig
from ..addon.errors import ProCamError
from ..addon.options import from_values
from ..addon.steps import compensate as compensate_step
from ..addon.steps import evaluate as evaluate_step
from ..addon.steps import show as show_step
from ..addon.steps.layout import CALIBRATION, COMPENSATION
from ..addon.steps.stage_c import StageCOptions, device_kind, open_device
from . import paths
from .job_operator import JobOperator
from .live import WINDOW_NEEDS_MAIN_THREAD, live_device
from .messages import sidebar_text


def input_images(target: compensate_step.CompensatedTarget) -> list[tuple[str, Path]]:
    """The Blender names and files of a target's compensated inputs: ``ProCam NAME input`` for one projector,
    ``ProCam NAME input pK`` for each of several (K from 1)."""
    if len(target.input_paths) == 1:
        return [(f"ProCam {target.name} input", target.input_path)]
    return [(f"ProCam {target.name} input p{k + 1}", path) for k, path in enumerate(target.input_paths)]


def scene_device(scene: bpy.types.Scene) -> str | None:
    """The device Compensate's mode names: the Live panel's rig in Live mode, else the Device field (None: empty)."""
    if scene.procam_compensation_mode == "LIVE":
        return live_device(scene)
    return scene.procam_device or None


def effects_diagnosis(scene: bpy.types.Scene) -> Path | None:
    """The diagnosis folder the Compensate panel's Effect Models read (None: no effects chosen)."""
    effects = scene.procam_effects.strip() or "none"
    if effects.lower() == "none":
        return None
    return paths.resolve(scene.procam_diagnosis_dir, "diagnosis folder (for the effect models)")


def stage_c_options(scene: bpy.types.Scene) -> StageCOptions:
    """The scene's Compensate settings as the step's options (what ``procam compensate`` takes as flags)."""
    closed = scene.procam_compensation_mode in ("CLOSED", "LIVE")
    return from_values(StageCOptions, lambda prop: getattr(scene, prop), device=scene_device(scene) if closed else None,
                       diagnosis=effects_diagnosis(scene))


def scene_targets(scene: bpy.types.Scene) -> tuple:
    """The target images of the Compensate list, then those of the image sequence folder."""
    files = [paths.resolve(t.filepath, "target image") for t in scene.procam_targets]
    folder = paths.resolve(scene.procam_target_folder, "image sequence folder") if scene.procam_target_folder else None
    return compensate_step.target_paths(files, folder)


def _stage_c_why_not(scene: bpy.types.Scene, *, device_needed: bool) -> str | None:
    """Why a step that runs or measures stage C cannot start: no calibration, no targets, no device it needs."""
    if paths.existing(scene.procam_calibration_dir, CALIBRATION.manifest) is None:
        return "no calibration: run Calibrate or choose a calibration folder"
    if not (len(scene.procam_targets) or scene.procam_target_folder):
        return "no targets: add target images or choose an image sequence folder"
    if scene.procam_compensation_mode == "LIVE":
        if not scene.procam_live_camera.strip():
            return "Live mode needs the camera of the Live panel (its index, device path or URL)"
    elif (device_needed or scene.procam_compensation_mode == "CLOSED") and not scene.procam_device:
        return "needs a device: lab:TRUTH_FILE or folder:CAPTURE_DIR"
    return None


class _DeviceJob(JobOperator):
    """A job that projects through the scene's device: opened here, on the main thread (the lab builds a
    Blender scene and renders with Cycles), and relayed to from the worker. A live device is the exception:
    the step opens it in the job's own thread (the calibrated projector sizes its window, and an SDL window
    stays with the thread that made it; operators/live.py says why macOS runs it in the foreground). The step puts
    the calibration's lens and the effect models after the device it is given (steps/stage_c.device_pipeline), as
    after one it opens itself."""

    def in_foreground(self, context: bpy.types.Context) -> bool:
        return WINDOW_NEEDS_MAIN_THREAD and context.scene.procam_compensation_mode == "LIVE"

    def open_device(self, spec: str | None, relay: "jobs.MainThreadRelay | None"):
        if not spec or device_kind(spec) in ("live", "command"):
            return None
        self._device = device = open_device(spec)
        return jobs.RelayedDevice(device, relay) if relay is not None else device

    def stage_c_job(self, name: str, run: Callable[..., object], options: Any,
                    relay: "jobs.MainThreadRelay | None") -> jobs.Job:
        """The job of a step that runs stage C (compensate, show) with its device, once its options check."""
        options.stage_c.check()  # a bad value fails here, before a device is opened
        return jobs.Job(name, run, options, device=self.open_device(options.stage_c.device_spec, relay))


class PROCAM_OT_compensate(_DeviceJob, bpy.types.Operator):
    """Find the projector input for each target (stage C) in the background, open or closed loop; Esc cancels"""

    bl_idname = "procam.compensate"
    bl_label = "Compensate"
    bl_options = {"REGISTER", "UNDO"}
    step = "compensate"
    option_names = {"--out": "‘Results’ folder"}

    @classmethod
    def why_not(cls, scene: bpy.types.Scene) -> str | None:
        why = _stage_c_why_not(scene, device_needed=False)
        if why is None and not scene.procam_compensation_dir:
            why = "choose the results folder to write"
        return why

    def make_job(self, context: bpy.types.Context, relay: "jobs.MainThreadRelay | None") -> jobs.Job:
        scene = context.scene
        options = compensate_step.CompensateOptions(
            paths.resolve(scene.procam_calibration_dir, "calibration folder"), scene_targets(scene),
            paths.resolve(scene.procam_compensation_dir, "results folder"), stage_c_options(scene),
            force=scene.procam_replace_outputs)
        return self.stage_c_job("compensation", compensate_step.run, options, relay)

    def apply(self, context: bpy.types.Context, result: object) -> str:
        view: compensate_step.CompensationView = result
        for t in view.targets:
            for name, path in input_images(t):
                blender_rig.load_image_file(path, name)
            blender_rig.load_image_file(t.simulated_path, f"ProCam {t.name} simulated")
        context.scene.procam_compensation_dir = str(view.folder)
        count = view.projector_count
        if count == 1:
            return f"Compensated {len(view.targets)} target(s) ({view.mode}) into {view.folder}"
        shown, scene_count = "", len(blender_rig.find_rig_objects(context.scene).projectors)
        if view.targets and scene_count == count:
            # each projector shows its own frame of the first target, as Preview on Projector puts them
            blender_rig.set_projector_frames(context.scene, view.targets[0].frame_paths)
            shown = f"; each projector shows its frame of {view.targets[0].name} (render F12 to preview)"
        elif view.targets:
            shown = (f"; the scene has {scene_count} ProCam projector(s): Load Calibration to see each projector's "
                     "frame")
        return (f"Compensated {len(view.targets)} target(s) on {count} projectors ({view.mode}) into "
                f"{view.folder}{shown}")


class PROCAM_OT_evaluate(_DeviceJob, bpy.types.Operator):
    """Project the compensated inputs and the uncompensated targets through the device and measure PSNR/SSIM in
    the display area, in the background; Esc cancels"""

    bl_idname = "procam.evaluate"
    bl_label = "Evaluate"
    bl_options = {"REGISTER", "UNDO"}
    step = "evaluate"
    option_names = {"--out": "‘Evaluation’ folder"}

    @classmethod
    def why_not(cls, scene: bpy.types.Scene) -> str | None:
        why = _stage_c_why_not(scene, device_needed=True)
        if why is None and paths.existing(scene.procam_compensation_dir, COMPENSATION.manifest) is None:
            why = "no compensation results: run Compensate or choose a results folder"
        if why is None and not scene.procam_evaluation_dir:
            why = "choose the evaluation folder to write"
        return why

    def make_job(self, context: bpy.types.Context, relay: "jobs.MainThreadRelay | None") -> jobs.Job:
        scene = context.scene
        options = evaluate_step.EvaluateOptions(
            paths.resolve(scene.procam_calibration_dir, "calibration folder"),
            paths.resolve(scene.procam_compensation_dir, "results folder"), scene_targets(scene),
            scene_device(scene), paths.resolve(scene.procam_evaluation_dir, "evaluation folder"),
            force=scene.procam_replace_outputs)
        return jobs.Job("evaluation", evaluate_step.run, options, device=self.open_device(options.device, relay))

    def apply(self, context: bpy.types.Context, result: object) -> str:
        folder = paths.resolve(context.scene.procam_evaluation_dir, "evaluation folder")
        for name, image in evaluate_step.read(folder).comparisons():
            blender_rig.load_image_file(image, f"ProCam {name} comparison")
        summary = evaluate_step.summary(folder)
        # several projectors: the figures inside and outside their overlap, not only the area's mean
        overlap = [line for line in summary.lines if line.endswith("(uncompensated → compensated)")
                   and " projectors: " in line]
        return f"Evaluation: {summary.headline}" + "".join(f"; {line}" for line in overlap)


class PROCAM_OT_prepare_show(_DeviceJob, bpy.types.Operator):
    """Compensate every frame of the image sequence folder into numbered 16-bit projector frames, resumably
    (a rerun finishes what is left), in the background; Esc cancels and keeps the finished frames"""

    bl_idname = "procam.prepare_show"
    bl_label = "Prepare Show"
    bl_options = {"REGISTER", "UNDO"}
    step = "show"
    option_names = {"--out": "‘Show’ folder", "--targets": "‘Image Sequence’"}

    @classmethod
    def why_not(cls, scene: bpy.types.Scene) -> str | None:
        why = _stage_c_why_not(scene, device_needed=False)
        if why is None and not scene.procam_target_folder:
            why = "choose the image sequence folder of the show"
        if why is None and not scene.procam_show_dir:
            why = "choose the show folder to write (or resume)"
        return why

    def make_job(self, context: bpy.types.Context, relay: "jobs.MainThreadRelay | None") -> jobs.Job:
        scene = context.scene
        options = show_step.ShowOptions(
            paths.resolve(scene.procam_calibration_dir, "calibration folder"),
            (paths.resolve(scene.procam_target_folder, "image sequence folder"),),
            paths.resolve(scene.procam_show_dir, "show folder"), stage_c_options(scene),
            force=scene.procam_replace_outputs)
        return self.stage_c_job("show", show_step.run, options, relay)

    def apply(self, context: bpy.types.Context, result: object) -> str:
        r: show_step.ShowResult = result
        failed = f", {len(r.failed)} failed (see show.json; rerun to retry)" if r.failed else ""
        return f"Show: {len(r.done)} frame(s) compensated, {len(r.skipped)} already finished{failed} in {r.folder}"


class PROCAM_OT_add_targets(bpy.types.Operator):
    """Add target images to the Compensate list"""

    bl_idname = "procam.add_targets"
    bl_label = "Add Targets"
    bl_options = {"REGISTER", "UNDO"}

    filepath: StringProperty(name="Image", subtype="FILE_PATH")
    directory: StringProperty(subtype="DIR_PATH", options={"HIDDEN", "SKIP_SAVE"})
    files: CollectionProperty(type=bpy.types.OperatorFileListElement, options={"HIDDEN", "SKIP_SAVE"})
    filter_image: bpy.props.BoolProperty(default=True, options={"HIDDEN", "SKIP_SAVE"})
    filter_folder: bpy.props.BoolProperty(default=True, options={"HIDDEN", "SKIP_SAVE"})

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.scene is not None

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        chosen = [str(Path(self.directory) / f.name) for f in self.files if f.name] if self.directory else []
        if not chosen and self.filepath:
            chosen = [self.filepath]
        missing = [p for p in chosen if not Path(bpy.path.abspath(p)).is_file()]
        if not chosen or missing:
            self.report({"ERROR"}, f"target image not found: {missing[0]}" if missing else
                        "no image chosen: pick one or more target images")
            return {"CANCELLED"}
        targets = context.scene.procam_targets
        known = {t.filepath for t in targets}
        added = 0
        for path in chosen:
            if path not in known:
                targets.add().filepath = path
                added += 1
        context.scene.procam_target_index = len(targets) - 1
        self.report({"INFO"}, f"Added {added} target(s); {len(targets)} in the list")
        return {"FINISHED"}


class PROCAM_OT_remove_target(bpy.types.Operator):
    """Remove the active target from the Compensate list"""

    bl_idname = "procam.remove_target"
    bl_label = "Remove Target"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        scene = context.scene
        if scene is None or not 0 <= scene.procam_target_index < len(scene.procam_targets):
            cls.poll_message_set("no target selected in the list")
            return False
        return True

    def execute(self, context: bpy.types.Context) -> set[str]:
        scene = context.scene
        name = Path(scene.procam_targets[scene.procam_target_index].filepath).name
        scene.procam_targets.remove(scene.procam_target_index)
        scene.procam_target_index = max(0, min(scene.procam_target_index, len(scene.procam_targets) - 1))
        self.report({"INFO"}, f"Removed {name}")
        return {"FINISHED"}


class PROCAM_OT_preview_compensated(bpy.types.Operator):
    """Put a compensated projector frame on the ProCam Projector (each projector its own, with several); render
    (F12) to preview it on the surface"""

    bl_idname = "procam.preview_compensated"
    bl_label = "Preview on Projector"
    bl_options = {"REGISTER", "UNDO"}

    target: StringProperty(name="Target", description="Name of the compensated target (default: the first)")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        scene = context.scene
        why = None
        if blender_rig.find_rig_objects(scene).projector is None:
            why = "the scene has no ProCam Projector: create the rig or load the calibration"
        elif paths.existing(scene.procam_compensation_dir, COMPENSATION.manifest) is None:
            why = "no compensation results: run Compensate or choose a results folder"
        if why is not None:
            cls.poll_message_set(why)
        return why is None

    def execute(self, context: bpy.types.Context) -> set[str]:
        scene = context.scene
        try:
            view = compensate_step.read(paths.resolve(scene.procam_compensation_dir, "results folder"))
            chosen = [t for t in view.targets if not self.target or t.name == self.target]
            if not chosen:
                names = ", ".join(t.name for t in view.targets) or "none"
                raise ProCamError(f"no compensated target {self.target!r} in {view.folder} (finished: {names})")
            t = chosen[0]
            if len(t.frame_paths) > 1:  # several projectors: each shows its own frame, or none changes
                images = blender_rig.set_projector_frames(scene, t.frame_paths)
            else:
                projector = blender_rig.find_rig_objects(scene).projector
                images = [blender_rig.set_projector_image(projector, t.frame_path)]
        except ProCamError as exc:
            self.report({"ERROR"}, sidebar_text(str(exc)))
            return {"CANCELLED"}
        sizes = ", ".join(f"{i.size[0]}×{i.size[1]}" for i in images)
        who = "Projector shows" if len(images) == 1 else f"Each of the {len(images)} projectors shows its frame of"
        self.report({"INFO"}, f"{who} the compensated {t.name} ({sizes}); render (F12) to preview it on the surface")
        return {"FINISHED"}
