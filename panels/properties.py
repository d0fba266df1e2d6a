"""Scene properties of the Calibrate, Compensate, Diagnose and Export steps (registered by ``blender_registration``)."""

import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty,
                       StringProperty)

from ..addon.gap.fit import MAX_EFFECTS
from ..addon.stages.compensate import DEFAULT_SCHEDULE


class PROCAM_PG_target(bpy.types.PropertyGroup):
    """One target image of the Compensate step."""

    filepath: StringProperty(name="Target", subtype="FILE_PATH", description="Target image file")


INIT_ITEMS = [("graycode", "Gray Code", "Start stage A from Gray-code correspondences + PnP"),
              ("nominal", "Nominal", "Start stage A from the capture set's nominal projector pose"),
              ("blender", "Scene Projector", "Start stage A from where the ProCam Projector stands in the scene")]
INTRINSICS_ITEMS = [("spec", "Spec Sheet", "The projector's focal length and principal point as the capture set gives "
                                         "them (throw ratio and lens shift, or a rig calibration)"),
                    ("fit", "Fit to Gray Code", "Fit the projector's focal length and principal point to the Gray "
                                                "code on a curved or edged surface before finding its pose (kept at "
                                                "the spec where the surface cannot tell, e.g. a flat wall)")]
SCHEDULE_ITEMS = [("transport", "Transport", "Solve on the calibration's precomputed light-transport operator: "
                                             "no renders, under a second a target, 3 captures in closed loop"),
                  ("fast", "Fast", "Fixed-point start, 150 joint iterations, 15 captures: renders every step; "
                                   "no operator needed"),
                  ("paper", "Paper", "The paper's 200 iterations on z, then 300 on z and θ")]
MODE_ITEMS = [("OPEN", "Open Loop", "No device: the bias θ comes from the calibration's validation captures"),
              ("CLOSED", "Closed Loop", "θ from captures of the projector input through the device (lab or folder)"),
              ("LIVE", "Live", "Closed loop through the real projector and camera of the Live panel")]


def scene_properties() -> dict[str, object]:
    """Properties set on ``bpy.types.Scene``; PROCAM_PG_target must be registered first."""
    return {
        "procam_calibration_dir": StringProperty(
            name="Calibration", subtype="DIR_PATH",
            description="Calibration folder: Calibrate writes it, Compensate and Diagnose read it"),
        "procam_calibration_init": EnumProperty(name="Start Pose", items=INIT_ITEMS, default="graycode"),
        "procam_projector_intrinsics": EnumProperty(name="Projector Lens", items=INTRINSICS_ITEMS, default="spec"),
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
        "procam_device": StringProperty(
            name="Device", description="lab:TRUTH_FILE (virtual lab) or folder:CAPTURE_DIR: the closed loop "
                                       "captures through it, and Evaluate projects through it"),
        "procam_area": StringProperty(
            name="Display Area", description="x,y,width,height in camera pixels; empty: the largest rectangle of "
                                             "each target's aspect ratio that the projector covers"),
        "procam_effects": StringProperty(
            name="Effect Models", default="none",
            description="Diagnosed effect models around stage C: 'auto' (those the diagnosis found compensation "
                        "can invert), NAME,... or 'none'; their parameters come from the Diagnosis folder"),
        "procam_range": StringProperty(
            name="Range", default="none",
            description="What the targets become before compensation: 'auto' (one gain and offset for all the "
                        "targets so at most 1 % of their values lie outside what the projector shows on this surface; "
                        "targets that fit are never dimmed), 'GAIN,OFFSET', or 'none' (as they are)"),
        "procam_use_bias": BoolProperty(
            name="Bias θ", default=True,
            description="Estimate the per-pixel bias θ (off: the no-θ ablation, neither captures nor validation)"),
        "procam_seed": IntProperty(name="Seed", default=0, min=0,
                                   description="Seed of every random stream; the same seed repeats the result"),
        "procam_evaluation_dir": StringProperty(
            name="Evaluation", subtype="DIR_PATH", description="Evaluation folder: metrics.json and side-by-sides"),
        "procam_show_dir": StringProperty(
            name="Show", subtype="DIR_PATH",
            description="Show folder: numbered projector frames of the image sequence, resumable"),
        "procam_schedule": EnumProperty(name="Schedule", items=SCHEDULE_ITEMS, default=DEFAULT_SCHEDULE),
        "procam_iterations": IntProperty(
            name="Iterations", description="Total stage-C Adam iterations (0 = the schedule's own: fast 60, paper "
                                           "200 + 300)", default=0, min=0, soft_max=1000),
        "procam_compensation_dir": StringProperty(
            name="Results", subtype="DIR_PATH", description="Compensation folder: projector inputs and frames"),
        "procam_diagnosis_dir": StringProperty(
            name="Diagnosis", subtype="DIR_PATH", description="Diagnosis folder (gap.json and residual maps)"),
        "procam_diagnosis_scale": FloatProperty(
            name="Working Scale", default=0.5, min=0.05, max=1.0,
            description="The diagnosis's working resolution as a share of the camera image: 1 sees a projector blur "
                        "of about a texel that 0.5 can miss (slower)"),
        "procam_max_effects": IntProperty(
            name="Max Effects", default=MAX_EFFECTS, min=1, soft_max=8,
            description="Effects the diagnosis selects at most: rounds of its greedy selection, each slower than "
                        "the last"),
    }
