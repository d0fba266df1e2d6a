"""ProCam ▸ Run Virtual Lab: render a calibration capture set of the scene's rig with Cycles and injected effects.

The lab renders in a scratch scene of its own and removes it afterwards, so
the user's scene is left as it was; only the scene's capture-set path changes
(it then shows in the Captures panel). The run is synchronous (Blender waits,
the progress shows on the cursor/status bar); headless runs work the same way.
"""

# No `from __future__ import annotations`: Blender reads the property annotations as objects at registration.
import time
from pathlib import Path

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty

from ..addon.blender import rig as blender_rig
from ..addon.errors import ProCamError
from ..addon.lab.lab import describe_run
from ..addon.options import sidebar_names, spec_of
from ..addon.steps.capture import LabOptions, run_lab
from .messages import REPLACE_BOX, sidebar_text

#: The command's options as this operator's dialog names them (its messages come from the shared lab step): the
#: labels LabOptions declares, which the dialog's fields below show.
_OPTION_NAMES = REPLACE_BOX | {"--out": "‘Capture Set’ folder"} | sidebar_names([LabOptions])

def _label(name: str) -> str:
    """The dialog's label of a lab option, as LabOptions declares it (and messages name it)."""
    return spec_of(LabOptions, name).label


_SURFACES = [("SCENE", "Scene Surface", "The scene's ProCam Surface (set it with Set Surface)"),
             ("plane", "Plane", "A flat textured wall"),
             ("curve", "Curve", "A concave cylinder section"),
             ("vedge", "Vertical edge", "Two planes meeting at a vertical concave corner"),
             ("hedge", "Horizontal edge", "Two planes meeting at a horizontal concave corner")]


class PROCAM_OT_run_lab(bpy.types.Operator):
    """Render a calibration capture set (surface, black, white, checkers, Gray code, validation, depth) in the
    virtual lab; the true rig and effects are sealed in a truth file outside the set"""

    bl_idname = "procam.run_lab"
    bl_label = "Run Virtual Lab"
    bl_options = {"REGISTER", "UNDO"}

    surface: EnumProperty(name=_label("surface"), items=_SURFACES, default="SCENE")
    use_scene_rig: BoolProperty(name="Scene Rig", default=True,
                                description="Use the scene's ProCam camera and projector when it has them "
                                            "(else the demo rig: camera 640×480, projector 800×600)")
    effects: StringProperty(name=_label("effects"), default="",
                            description="NAME=STRENGTH,… (strengths in [0, 1]) or 'realistic'; empty: none")
    samples: IntProperty(name=_label("samples"), description="Cycles samples per pixel", default=16, min=0, soft_min=1,
                         soft_max=256)
    scale: FloatProperty(name=_label("scale"), description="Scale of the camera and projector resolutions",
                         default=1.0, soft_min=0.05, soft_max=2.0)
    seed: IntProperty(name=_label("seed"), default=0, min=0)
    graycode: BoolProperty(name=_label("graycode"), description="Include the Gray-code patterns", default=True)
    out_dir: StringProperty(name="Capture Set", subtype="DIR_PATH",
                            description="Folder of the new capture set (default: the scene's capture set)")
    truth_path: StringProperty(name=_label("truth"), subtype="FILE_PATH",
                               description="Sealed truth JSON outside the capture set (default: beside it)")
    force: BoolProperty(name="Replace", description="Replace an existing capture set (and truth file)")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.scene is not None

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        if not self.out_dir:
            self.out_dir = context.scene.procam_capture_dir or "//procam_lab"
        return context.window_manager.invoke_props_dialog(self, width=360)

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        layout.use_property_split = True
        for name in ("surface", "use_scene_rig", "effects", "samples", "scale", "seed", "graycode", "out_dir",
                     "truth_path", "force"):
            layout.prop(self, name)

    def _paths(self, context: bpy.types.Context) -> tuple[Path, Path]:
        raw = self.out_dir or context.scene.procam_capture_dir
        if not raw:
            raise ProCamError("no capture-set folder given: choose where the lab writes its captures")
        resolved = [bpy.path.abspath(p) if p else "" for p in (raw, self.truth_path)]
        if any(p.startswith("//") for p in resolved):
            raise ProCamError("a path relative to the .blend file needs a saved file: save it or give an absolute path")
        out = Path(resolved[0]).absolute()
        truth = Path(resolved[1]).absolute() if resolved[1] else out.with_name(out.name + ".truth.json")
        return out, truth

    def execute(self, context: bpy.types.Context) -> set[str]:
        scene, wm = context.scene, context.window_manager
        t0 = time.perf_counter()
        wm.progress_begin(0, 100)
        try:
            out, truth_path = self._paths(context)
            objs = blender_rig.find_rig_objects(scene)
            rig = (blender_rig.read_rig(scene)
                   if self.use_scene_rig and objs.camera is not None and objs.projector is not None else None)
            if self.surface == "SCENE":
                surface, source = blender_rig.read_surface(scene), f"Blender object {objs.surface.name!r}"
            else:
                surface, source = self.surface, None
            options = LabOptions(out, surface=surface, effects=self.effects, seed=self.seed, samples=self.samples,
                                 scale=self.scale, graycode=self.graycode, truth=truth_path, rig=rig,
                                 surface_source=source, force=self.force)
            cs = run_lab(options, lambda message, fraction: wm.progress_update(int(100 * fraction)))
        except ProCamError as exc:
            self.report({"ERROR"}, sidebar_text(str(exc), _OPTION_NAMES))
            return {"CANCELLED"}
        finally:
            wm.progress_end()
        scene.procam_capture_dir = str(out)
        self.report({"INFO"}, f"Virtual lab: {describe_run(cs, time.perf_counter() - t0)} in {out}; "
                              f"truth sealed in {truth_path.name}")
        return {"FINISHED"}
