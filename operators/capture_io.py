"""ProCam ▸ Export Patterns / Import Captures: a capture session with the user's own projector and camera.

Export writes the numbered pattern frames of the scene's projector (show them
full screen, photograph each); Import turns those photographs into a capture set
and makes it the scene's. Both only write new folders; the scene changes only in
its capture-set path.

Several projectors, one at a time, as ``procam patterns --projector-number K``
and ``procam import-captures … --add-to SET`` do: Export Patterns writes
projector K's sequence (its own size and lens; K defaults to the active
projector), and Import Captures with "Add to Capture Set" makes a new set of
that set's projectors and this one, leaving that set as it was.
"""

# No `from __future__ import annotations`: Blender reads the property annotations as objects at registration.
import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty

from ..addon.blender import rig as blender_rig
from ..addon.errors import ProCamError
from ..addon.options import sidebar_names, spec_of
from ..addon.steps.capture import DepthSensorSize, ImportOptions, PatternsOptions, run_import, run_patterns
from . import paths
from .messages import REPLACE_BOX, sidebar_text

ENCODING_ITEMS = [("auto", "Auto", "8-bit files are sRGB, 16-bit and float files are linear"),
                  ("srgb", "sRGB", "The photographs are sRGB-encoded (most cameras' JPEG and 8-bit PNG)"),
                  ("linear", "Linear", "The photographs hold linear light (RAW developed linear, EXR)")]
DEPTH_UNITS_ITEMS = [("auto", "Auto", "Detect millimetres given as metres from the values (with a warning when "
                                      "it converts)"),
                     ("m", "Metres", "The depth values are metres"),
                     ("mm", "Millimetres", "The depth values are millimetres")]


def _label(name: str) -> str:
    """The import dialog's label of an option, as ImportOptions declares it (and messages name it)."""
    return spec_of(ImportOptions, name).label


def _sensor_label(side: str) -> str:
    return spec_of(DepthSensorSize, f"depth_native_{side}").label


#: the import's options as its dialog names them in messages
_IMPORT_NAMES = (REPLACE_BOX | {"--out": "‘New Capture Set’ folder"}
                 | sidebar_names([ImportOptions, DepthSensorSize]))
#: the export's options as its dialog names them in messages
_EXPORT_NAMES = (REPLACE_BOX | {"--out": "‘Folder’"}
                 | sidebar_names([PatternsOptions], only=("projector_number", "layout")))


def _number(name: str) -> dict[str, object]:
    """An integer option's label and limits, as PatternsOptions declares them, for a dialog's own field of it."""
    spec = spec_of(PatternsOptions, name)
    return {"name": spec.label, "min": int(spec.min or 0), "max": int(spec.max or 2 ** 31 - 1)}


def _rig_missing(context: bpy.types.Context) -> str:
    objs = blender_rig.find_rig_objects(context.scene)
    if objs.camera is None or objs.projector is None:
        return "Create the rig first (ProCam Camera and ProCam Projector)"
    return ""


class PROCAM_OT_export_patterns(bpy.types.Operator):
    """Write the calibration pattern sequence of the scene's projector as numbered 16-bit PNG frames"""

    bl_idname = "procam.export_patterns"
    bl_label = "Export Patterns"
    bl_options = {"REGISTER"}

    directory: StringProperty(name="Folder", subtype="DIR_PATH",
                              description="New folder for the numbered frames and sequence.json")
    force: BoolProperty(name="Replace", default=False, description="Replace an existing exported sequence there")
    projector_number: IntProperty(default=1, **_number("projector_number"),
                                  description="Several projectors: the sequence of projector K (its own size and "
                                              "lens; default the active projector); 2 and above leave out the "
                                              "surface photo, taken once with projector 1's")
    order: EnumProperty(name=spec_of(PatternsOptions, "layout").label, default="procam", items=[
        ("procam", "ProCam", "Surface photo, black, white, checkerboards, Gray code, validation patterns"),
        ("opencv", "OpenCV Structured Light", "Gray code (each bit then its inverse, x then y), white, black, then "
                   "the validation patterns: the order of OpenCV's structured-light sessions and of board sessions "
                   "for Calibrate Rig; import photographs taken that way with this sequence")])

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        why = _rig_missing(context) if context.scene is not None else "No scene"
        if why:
            cls.poll_message_set(why)
        return not why

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        if not self.properties.is_property_set("projector_number"):
            # the projector the panels work on: the active one of several
            objs = blender_rig.find_rig_objects(context.scene)
            if objs.projector in objs.projectors:
                self.projector_number = objs.projectors.index(objs.projector) + 1
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        if not self.directory:
            self.report({"ERROR"}, "Choose a folder for the pattern frames")
            return {"CANCELLED"}
        k = int(self.projector_number)
        count = len(blender_rig.find_rig_objects(context.scene).projectors)
        if k > count:
            label = spec_of(PatternsOptions, "projector_number").label
            self.report({"ERROR"}, f"the scene has {count} ProCam projector(s): choose a ‘{label}’ from 1 to "
                                   f"{count}, or add projector {k} first (Add Projector)")
            return {"CANCELLED"}
        try:
            rig = blender_rig.read_rig(context.scene)
            out = run_patterns(PatternsOptions(rig.projectors[k - 1], paths.resolve(self.directory, "pattern folder"),
                                               camera=rig.camera, layout=self.order, projector_number=k,
                                               force=self.force))
        except ProCamError as exc:
            self.report({"ERROR"}, sidebar_text(str(exc), _EXPORT_NAMES))
            return {"CANCELLED"}
        frames = len(list(out.glob("[0-9]*.png")))
        if count == 1:
            self.report({"INFO"}, f"{frames} pattern frames in {out}: show each full screen on the projector, "
                                  "photograph it, then Import Captures")
        else:
            then = (f"Import Captures with ‘{_label('add_to')}’ set to the capture set of projectors 1–{k - 1}"
                    if k > 1 else "Import Captures")
            self.report({"INFO"}, f"{frames} pattern frames of projector {k} in {out}: show each full screen on "
                                  f"projector {k} while the others show black, photograph it, then {then}")
        return {"FINISHED"}


class PROCAM_OT_import_captures(bpy.types.Operator):
    """Turn photographs of an exported pattern sequence into a capture set and use it in this scene"""

    bl_idname = "procam.import_captures"
    bl_label = "Import Captures"
    bl_options = {"REGISTER", "UNDO"}

    sequence_dir: StringProperty(name="Pattern Sequence", subtype="DIR_PATH",
                                 description="The folder Export Patterns wrote")
    photos_dir: StringProperty(name="Photographs", subtype="DIR_PATH",
                               description="One photograph per frame, numbered in the same order")
    out_dir: StringProperty(name="New Capture Set", subtype="DIR_PATH", description="Folder to create")
    add_to_dir: StringProperty(name=_label("add_to"), subtype="DIR_PATH",
                               description="Several projectors: the capture set of the projectors photographed "
                                           "so far; the new set holds its captures and this projector's (the next "
                                           "one). That set is read, never changed; the depth and surface photo are "
                                           "its own")
    rig_file: StringProperty(name=_label("rig"), subtype="FILE_PATH",
                             description="Optional rig.json from procam calibrate-rig: calibrated camera and projector "
                                         "lenses (the camera's distortion is removed from the photographs) and, "
                                         "when calibrated in metres, the projector's pose")
    depth_file: StringProperty(name=_label("depth_path"), subtype="FILE_PATH",
                               description="Optional depth of the scene seen from the camera: .npy/.exr in metres, "
                                           "16-bit .png/.tif in millimetres (0 = no depth), or a .ply point cloud "
                                           "in the camera's OpenCV frame; a shift of a few pixels against the "
                                           "photographs is found and corrected (with a warning)")
    depth_units: EnumProperty(name=_label("depth_units"), items=DEPTH_UNITS_ITEMS, default="auto")
    depth_native_width: IntProperty(name=_sensor_label("width"), default=0, min=0, subtype="PIXEL",
                                    description="Native depth-sensor width (e.g. 256): a .ply point cloud is "
                                                "projected at this size; 0: the camera's")
    depth_native_height: IntProperty(name=_sensor_label("height"), default=0, min=0, subtype="PIXEL",
                                     description="Native depth-sensor height (e.g. 192); 0: the camera's")
    encoding: EnumProperty(name=_label("encoding"), items=ENCODING_ITEMS, default="auto",
                           description="How the photographs are encoded")
    camera_fov: FloatProperty(name=_label("camera_fov"), default=60.0, min=1.0, max=179.0,
                              description="Nominal horizontal field of view in degrees, used only without a rig "
                                          "calibration and without a ProCam Camera in the scene")
    check_exposure: BoolProperty(name=_label("check_exposure"), default=True,
                                 description="Refuse a session whose exposure or white balance changed between "
                                             "photographs (complementary patterns that do not add up to white + "
                                             "black); off: import anyway")
    force: BoolProperty(name="Replace", default=False, description="Replace an existing capture set there")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.scene is not None

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        return context.window_manager.invoke_props_dialog(self, width=420)

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        layout.use_property_split = True
        for name in ("sequence_dir", "photos_dir", "out_dir", "add_to_dir", "rig_file"):
            layout.prop(self, name)
        col = layout.column(align=True)
        col.enabled = not self.add_to_dir  # the depth is taken once, with the first projector's photographs
        col.prop(self, "depth_file")
        sub = col.column(align=True)
        sub.enabled = bool(self.depth_file)
        sub.prop(self, "depth_units")
        sub.prop(self, "depth_native_width")
        sub.prop(self, "depth_native_height")
        col = layout.column()
        col.prop(self, "encoding")
        sub = col.column()
        sub.enabled = not self.rig_file  # a rig calibration brings its own camera lens
        sub.prop(self, "camera_fov")
        col.prop(self, "check_exposure")
        col.prop(self, "force")

    def execute(self, context: bpy.types.Context) -> set[str]:
        missing = [n for n, v in (("pattern sequence", self.sequence_dir), ("photographs", self.photos_dir),
                                  ("new capture set", self.out_dir)) if not v]
        if missing:
            self.report({"ERROR"}, "Choose the " + ", ".join(missing) + " folder(s)")
            return {"CANCELLED"}
        objs = blender_rig.find_rig_objects(context.scene)
        warnings: list[str] = []

        def progress(message: str, fraction: float) -> None:
            # The step says what it corrected or converted (depth units, a shifted depth map) as warnings.
            if message.startswith("warning:"):
                warnings.append(message.removeprefix("warning:").strip())

        try:
            rig = paths.resolve(self.rig_file, "rig calibration") if self.rig_file else None
            # A rig calibration brings its own camera; the scene's (nominal) one is only used without it.
            camera = blender_rig.read_camera(context.scene) if objs.camera is not None and rig is None else None
            out = paths.resolve(self.out_dir, "new capture set")
            depth = paths.resolve(self.depth_file, "depth file") if self.depth_file else None
            add_to = paths.resolve(self.add_to_dir, "capture set to add to") if self.add_to_dir else None
            native = DepthSensorSize(self.depth_native_width or None, self.depth_native_height or None).size()
            captures = run_import(ImportOptions(paths.resolve(self.sequence_dir, "pattern sequence"),
                                                paths.resolve(self.photos_dir, "photographs"), out, camera=camera,
                                                camera_fov=self.camera_fov, encoding=self.encoding,
                                                depth_path=depth, depth_units=self.depth_units,
                                                depth_native_size=native, rig=rig, add_to=add_to,
                                                check_exposure=self.check_exposure, force=self.force),
                                  progress)
        except ProCamError as exc:
            self.report({"ERROR"}, sidebar_text(str(exc), _IMPORT_NAMES))
            return {"CANCELLED"}
        context.scene.procam_capture_dir = str(out)
        lens = f", calibrated camera and projector from {rig.name}" if rig is not None else ""
        extra = f", depth from {depth.name} ({self.depth_units})" if depth is not None else ""
        if not self.check_exposure:
            extra += ", exposure not checked"
        for warning in warnings:
            self.report({"WARNING"}, warning)
        if add_to is not None:
            extra += (f", {len(captures.projectors)} projectors: {add_to.name}'s and projector "
                      f"{len(captures.projectors)}'s ({add_to.name} left as it was)")
        self.report({"INFO"}, f"capture set {out}: {len(captures)} images{lens}{extra}")
        return {"FINISHED"}
