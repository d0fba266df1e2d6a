"""ProCam ▸ Compensate (stage C for every target, as a background job), the target list, and Preview on Projector.

The compensated inputs and simulated camera views become Blender images
(``ProCam NAME input`` / ``ProCam NAME simulated``, read from the result
folder); Preview on Projector puts one compensated frame on the ProCam
Projector so that a Cycles render shows it on the surface.
"""

from pathlib import Path

import bpy
from bpy.props import CollectionProperty, StringProperty

from ..addon import jobs
from ..addon.errors import ProCamError
from ..addon.rig import blender_rig
from ..addon.workflow import (CALIBRATION_MANIFEST, COMPENSATION_MANIFEST, CompensationView, read_compensation,
                              run_compensation, target_paths)
from . import paths
from .job_operator import JobOperator, job_running_message


def _open_device(spec: str):
    from ..addon.commands.compensate import open_device

    return open_device(spec)


class PROCAM_OT_compensate(JobOperator, bpy.types.Operator):
    """Find the projector input for each target (stage C) in the background, open or closed loop; Esc cancels"""

    bl_idname = "procam.compensate"
    bl_label = "Compensate"
    bl_options = {"REGISTER", "UNDO"}
    step = "compensate"

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        scene = context.scene
        why = job_running_message()
        if why is None and paths.existing(scene.procam_calibration_dir, CALIBRATION_MANIFEST) is None:
            why = "no calibration: run Calibrate or choose a calibration folder"
        if why is None and not (len(scene.procam_targets) or scene.procam_target_folder):
            why = "no targets: add target images or choose an image sequence folder"
        if why is None and scene.procam_compensation_mode == "CLOSED" and not scene.procam_device:
            why = "closed loop needs a device: lab:TRUTH_FILE or folder:CAPTURE_DIR"
        if why is None and not scene.procam_compensation_dir:
            why = "choose the results folder to write"
        if why is not None:
            cls.poll_message_set(why)
        return why is None

    def make_job(self, context: bpy.types.Context, relay: "jobs.MainThreadRelay | None") -> jobs.Job:
        scene = context.scene
        cal = paths.resolve(scene.procam_calibration_dir, "calibration folder")
        files = [paths.resolve(t.filepath, "target image") for t in scene.procam_targets]
        folder = paths.resolve(scene.procam_target_folder, "image sequence folder") if scene.procam_target_folder else None
        targets = target_paths(files, folder)
        out = paths.resolve(scene.procam_compensation_dir, "results folder")
        device, spec = None, None
        if scene.procam_compensation_mode == "CLOSED":
            spec = scene.procam_device
            # Opened here, on the main thread: the lab builds a Blender scene and renders with Cycles.
            self._device = device = _open_device(spec)
            if relay is not None:
                device = jobs.RelayedDevice(device, relay)
        return jobs.Job("compensation", run_compensation, cal, targets, out, device=device, device_spec=spec,
                        schedule=scene.procam_schedule, iterations=scene.procam_iterations or None,
                        force=scene.procam_replace_outputs)

    def apply(self, context: bpy.types.Context, result: object) -> str:
        view: CompensationView = result
        for t in view.targets:
            blender_rig.load_image_file(t.input_path, f"ProCam {t.name} input")
            blender_rig.load_image_file(t.simulated_path, f"ProCam {t.name} simulated")
        context.scene.procam_compensation_dir = str(view.folder)
        return f"Compensated {len(view.targets)} target(s) ({view.mode}) into {view.folder}"


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
    """Put a compensated projector frame on the ProCam Projector; render (F12) to preview it on the surface"""

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
        elif paths.existing(scene.procam_compensation_dir, COMPENSATION_MANIFEST) is None:
            why = "no compensation results: run Compensate or choose a results folder"
        if why is not None:
            cls.poll_message_set(why)
        return why is None

    def execute(self, context: bpy.types.Context) -> set[str]:
        scene = context.scene
        try:
            view = read_compensation(paths.resolve(scene.procam_compensation_dir, "results folder"))
            chosen = [t for t in view.targets if not self.target or t.name == self.target]
            if not chosen:
                names = ", ".join(t.name for t in view.targets) or "none"
                raise ProCamError(f"no compensated target {self.target!r} in {view.folder} (finished: {names})")
            t = chosen[0]
            projector = blender_rig.find_rig_objects(scene).projector
            image = blender_rig.set_projector_image(projector, t.frame_path)
        except ProCamError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Projector shows the compensated {t.name} ({image.size[0]}×{image.size[1]}); "
                              "render (F12) to preview it on the surface")
        return {"FINISHED"}
