"""ProCam ▸ Create Rig: a camera and a projector (optionally a built-in surface) from spec-sheet values."""

# No `from __future__ import annotations`: Blender reads the property annotations as objects at registration.
import math

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty

from ..addon.errors import ProCamError
from ..addon.blender import rig as blender_rig
from ..addon.rig.demo import demo_rig
from ..addon.rig.model import Camera, Intrinsics, Projector, Rig, intrinsics_from_fov, projector_intrinsics_from_throw
from ..addon.surface.shapes import builtin_surface
from .messages import sidebar_text

_SURFACES = [("NONE", "None", "Keep the scene's surface (or set one later with Set Surface)"),
             ("plane", "Plane", "A flat textured wall"),
             ("curve", "Curve", "A concave cylinder section"),
             ("vedge", "Vertical edge", "Two planes meeting at a vertical concave corner"),
             ("hedge", "Horizontal edge", "Two planes meeting at a horizontal concave corner")]


class PROCAM_OT_create_rig(bpy.types.Operator):
    """Create the ProCam camera and projector (replacing previous ones); the projector starts at the demo pose"""

    bl_idname = "procam.create_rig"
    bl_label = "Create Rig"
    bl_options = {"REGISTER", "UNDO"}

    # Hard minimums are 0 (not 1) so that a zero reaches validation and is reported instead of clamped.
    projector_width: IntProperty(name="Projector Width", default=800, min=0, soft_min=1, subtype="PIXEL")
    projector_height: IntProperty(name="Projector Height", default=600, min=0, soft_min=1, subtype="PIXEL")
    throw_ratio: FloatProperty(name="Throw Ratio", description="Distance / image width", default=1.25,
                               soft_min=0.1, soft_max=5.0, precision=3)
    # Real projectors shift their image by more than its own size (the realdata one by 127 % of its height).
    shift_x: FloatProperty(name="Lens Shift X", description="Image centre right of the lens axis, % of the width",
                           default=0.0, soft_min=-200.0, soft_max=200.0, subtype="PERCENTAGE")
    shift_y: FloatProperty(name="Lens Shift Y", description="Image centre above the lens axis, % of the height",
                           default=15.0, soft_min=-200.0, soft_max=200.0, subtype="PERCENTAGE")
    use_explicit_k: BoolProperty(name="Explicit Intrinsics",
                                 description="Give fx, fy, cx, cy in projector pixels instead of throw and shift")
    fx: FloatProperty(name="fx", default=1000.0, subtype="PIXEL")
    fy: FloatProperty(name="fy", default=1000.0, subtype="PIXEL")
    cx: FloatProperty(name="cx", description="Principal point, pixels from the left edge", default=400.0,
                      subtype="PIXEL")
    cy: FloatProperty(name="cy", description="Principal point, pixels from the top edge", default=390.0,
                      subtype="PIXEL")
    input_width: IntProperty(name="Input Width", description="Projector input image width (0: whole frame)",
                             default=0, min=0, subtype="PIXEL")
    input_height: IntProperty(name="Input Height", description="Projector input image height (0: whole frame)",
                              default=0, min=0, subtype="PIXEL")
    intensity: FloatProperty(name="Intensity", description="1 gives an irradiance of π on a plane 1 m in front",
                             default=2.5, soft_min=0.01, soft_max=100.0)
    camera_width: IntProperty(name="Camera Width", default=640, min=0, soft_min=1, subtype="PIXEL")
    camera_height: IntProperty(name="Camera Height", default=480, min=0, soft_min=1, subtype="PIXEL")
    camera_fov: FloatProperty(name="Camera Field of View", description="Horizontal field of view",
                              default=math.radians(58.0), soft_min=math.radians(5.0), soft_max=math.radians(150.0),
                              subtype="ANGLE")
    surface: EnumProperty(name="Surface", items=_SURFACES, default="NONE")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.scene is not None

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        return context.window_manager.invoke_props_dialog(self, width=340)

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        layout.use_property_split = True
        col = layout.column(heading="Projector")
        col.prop(self, "projector_width")
        col.prop(self, "projector_height")
        col.prop(self, "use_explicit_k")
        if self.use_explicit_k:
            for name in ("fx", "fy", "cx", "cy"):
                col.prop(self, name)
        else:
            col.prop(self, "throw_ratio")
            col.prop(self, "shift_x")
            col.prop(self, "shift_y")
        col.prop(self, "input_width")
        col.prop(self, "input_height")
        col.prop(self, "intensity")
        col = layout.column(heading="Camera")
        col.prop(self, "camera_width")
        col.prop(self, "camera_height")
        col.prop(self, "camera_fov")
        layout.prop(self, "surface")

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            camera = Camera(intrinsics_from_fov(self.camera_width, self.camera_height, math.degrees(self.camera_fov)))
            if self.use_explicit_k:
                k = Intrinsics(self.projector_width, self.projector_height, self.fx, self.fy, self.cx, self.cy)
            else:
                k = projector_intrinsics_from_throw(self.projector_width, self.projector_height, self.throw_ratio,
                                                    self.shift_x / 100.0, self.shift_y / 100.0)
            size = (self.input_width or k.width, self.input_height or k.height)
            projector = Projector(k, demo_rig().projector.camera_from_projector, self.intensity, size)
            surface = None if self.surface == "NONE" else builtin_surface(self.surface)
            objs = blender_rig.create_rig(context.scene, Rig(camera, projector), surface)
        except ProCamError as exc:
            self.report({"ERROR"}, sidebar_text(str(exc)))
            return {"CANCELLED"}
        extra = f", surface {objs.surface.name!r}" if surface is not None else ""
        self.report({"INFO"}, f"Created {objs.camera.name!r} and {objs.projector.name!r}{extra}")
        return {"FINISHED"}
