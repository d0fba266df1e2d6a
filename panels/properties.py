"""Scene properties of the Calibrate, Compensate, Diagnose and Export steps (registered by ``blender_registration``)."""

import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty,
                       StringProperty)

from ..addon.options import Declared, prop_name, sidebar_fields
from ..addon.steps.calibrate import CalibrateOptions
from ..addon.steps.diagnose import DiagnoseOptions
from ..addon.steps.stage_c import StageCOptions
from ..operators.messages import sidebar_text


class PROCAM_PG_target(bpy.types.PropertyGroup):
    """One target image of the Compensate step."""

    filepath: StringProperty(name="Target", subtype="FILE_PATH", description="Target image file")


MODE_ITEMS = [("OPEN", "Open Loop", "No device: the bias θ comes from the calibration's validation captures"),
              ("CLOSED", "Closed Loop", "θ from captures of the projector input through the device (lab or folder)"),
              ("LIVE", "Live", "Closed loop through the real projector and camera of the Live panel")]


def declared_property(d: Declared) -> object:
    """The scene property of one option as its ``Options`` field declares it (addon/options.py): label, help,
    default, limits and choices come from there; a value the sidebar leaves blank (0, empty) stands for None."""
    spec = d.spec
    text = sidebar_text(spec.help)
    common = {"name": spec.label, "description": text[:1].upper() + text[1:]}
    if spec.choices:
        return EnumProperty(items=[(c.value, c.label or c.value, c.description) for c in spec.offered],
                            default=d.default, **common)
    if d.kind is bool:
        return BoolProperty(default=bool(d.default), **common)
    limits = {k: v for k, v in (("min", spec.min), ("max", spec.max), ("soft_max", spec.soft_max)) if v is not None}
    if d.kind is int:
        pixel = {"subtype": spec.subtype} if spec.subtype else {}
        return IntProperty(default=spec.blank if d.default is None else d.default, **limits, **pixel, **common)
    if d.kind is float:
        return FloatProperty(default=spec.blank if d.default is None else d.default, **limits, **common)
    extra = {"subtype": spec.subtype} if spec.subtype else {}
    return StringProperty(default="" if d.default is None or spec.parse else str(d.default), **extra, **common)


def declared_properties(*classes: type) -> dict[str, object]:
    """The sidebar fields of the steps' ``Options`` classes, by their scene property names."""
    return {prop_name(d): declared_property(d) for cls in classes for d in sidebar_fields(cls)}


def scene_properties() -> dict[str, object]:
    """Properties set on ``bpy.types.Scene``; PROCAM_PG_target must be registered first."""
    return {
        **declared_properties(CalibrateOptions, StageCOptions, DiagnoseOptions),
        "procam_calibration_dir": StringProperty(
            name="Calibration", subtype="DIR_PATH",
            description="Calibration folder: Calibrate writes it, Compensate and Diagnose read it"),
        "procam_surface_mesh": PointerProperty(
            name="Surface Mesh", type=bpy.types.Object, poll=lambda _, obj: obj.type == "MESH",
            description="A mesh of the object (scan or CAD, anywhere in the scene) to register to the measured "
                        "points and use as the surface; empty: the surface is made from the depth image or the "
                        "triangulated Gray code"),
        "procam_depth_offset_given": BoolProperty(
            name="Set Depth Offset",
            description="Give the depth sensor's bias by hand instead of reading it from the capture set's wall "
                        "depth image (a flat wall at a tape-measured distance)"),
        "procam_depth_offset": FloatProperty(
            name="Depth Offset", subtype="DISTANCE", unit="LENGTH", default=0.0, min=-0.5, max=0.5,
            description="The depth sensor's constant bias (+ = it reads too far), subtracted from the depth"),
        "procam_replace_outputs": BoolProperty(
            name="Replace Results", description="Let a step replace its existing output folder (never otherwise)"),
        "procam_targets": CollectionProperty(type=PROCAM_PG_target, name="Targets"),
        "procam_target_index": IntProperty(name="Active Target", default=0, min=0),
        "procam_target_folder": StringProperty(
            name="Image Sequence", subtype="DIR_PATH",
            description="Folder of target images (e.g. the frames of a clip), compensated in numbered order"),
        "procam_compensation_mode": EnumProperty(name="Mode", items=MODE_ITEMS, default="OPEN"),
        "procam_evaluation_dir": StringProperty(
            name="Evaluation", subtype="DIR_PATH", description="Evaluation folder: metrics.json and side-by-sides"),
        "procam_show_dir": StringProperty(
            name="Show", subtype="DIR_PATH",
            description="Show folder: numbered projector frames of the image sequence, resumable"),
        "procam_compensation_dir": StringProperty(
            name="Results", subtype="DIR_PATH", description="Compensation folder: projector inputs and frames"),
        "procam_diagnosis_dir": StringProperty(
            name="Diagnosis", subtype="DIR_PATH", description="Diagnosis folder (gap.json and residual maps)"),
    }
