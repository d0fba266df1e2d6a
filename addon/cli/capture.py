"""``procam patterns``, ``import-captures`` and ``undistort-captures``: the folder workflow for users with their own
tools.

``patterns`` writes the numbered calibration frames at the projector's native
resolution; the user shows and photographs them; ``import-captures`` turns the
photographs into a capture set that calibration reads; ``undistort-captures`` takes a
board-calibrated camera lens out of a capture set made before the camera was calibrated.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..capture.devices import load_sequence
from ..capture.patterns import LAYOUTS
from ..errors import CaptureError, RigError
from ..rig.model import Camera, Projector, intrinsics_from_fov, projector_intrinsics_from_throw
from ..steps.capture import (ImportOptions, PatternsOptions, UndistortOptions, run_import, run_patterns,
                             run_undistort)
from .app import command
from .args import finite_float
from .terminal import run_step


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {value}")
    return value


def add_projector_options(p: argparse.ArgumentParser) -> None:
    """The projector as a spec sheet gives it: native size, input area, throw ratio, lens shift."""
    p.add_argument("--projector-width", type=_positive_int, required=True, help="native projector width (px)")
    p.add_argument("--projector-height", type=_positive_int, required=True, help="native projector height (px)")
    p.add_argument("--input-width", type=_positive_int, help="projector input width inside the frame (default: frame)")
    p.add_argument("--input-height", type=_positive_int, help="projector input height (default: frame)")
    p.add_argument("--throw-ratio", type=finite_float, default=1.0,
                   help="nominal throw ratio, distance / width (default 1.0)")
    p.add_argument("--shift-x", type=finite_float, default=0.0, help="nominal lens shift right, fraction of the width")
    p.add_argument("--shift-y", type=finite_float, default=0.0, help="nominal lens shift up, fraction of the height")


def projector_from_args(args: argparse.Namespace) -> Projector:
    intr = projector_intrinsics_from_throw(args.projector_width, args.projector_height, args.throw_ratio,
                                           args.shift_x, args.shift_y)
    if (args.input_width is None) != (args.input_height is None):
        raise RigError("give both --input-width and --input-height, or neither")
    return Projector(intr, input_size=(args.input_width, args.input_height) if args.input_width else None)


def add_pattern_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checker", type=_positive_int, help="checkerboard square size in pixels (default: ~1/12 of the input)")
    p.add_argument("--area", choices=("input", "frame"), default="input",
                   help="draw patterns inside the projector input (default) or over the whole frame")
    p.add_argument("--no-graycode", action="store_true", help="leave out the Gray-code frames")
    p.add_argument("--no-validation", action="store_true", help="leave out the validation frames")
    p.add_argument("--seed", type=int, default=0, help="seed of the random validation patterns")
    p.add_argument("--layout", choices=LAYOUTS, default="procam",
                   help="procam (default): surface photo, black, white, checkerboards, Gray code, validation; opencv: "
                        "OpenCV's structured-light order (Gray code, each bit then its inverse, x then y; then white "
                        "and black; no surface photo or checkerboard), as procam calibrate-rig's board sessions use: "
                        "import such photographs with it")


def _configure_patterns(p: argparse.ArgumentParser) -> None:
    add_projector_options(p)
    add_pattern_options(p)
    p.add_argument("--out", type=Path, required=True, help="new folder for the numbered frames")
    p.add_argument("--force", action="store_true", help="replace an existing sequence folder at --out")


@command("patterns", "Export the numbered calibration pattern sequence for your own projection/capture tools.",
         _configure_patterns)
def patterns(args: argparse.Namespace) -> int:
    projector = projector_from_args(args)
    w, h = projector.intrinsics.size
    out = run_step("patterns", run_patterns, PatternsOptions(
        projector, args.out, checker=args.checker, area=args.area, graycode=not args.no_graycode,
        validation=not args.no_validation, seed=args.seed, layout=args.layout, force=args.force))
    n = len(load_sequence(out).frames)
    print(f"wrote {n} frames ({w}×{h}) and sequence.json to {out}")
    return 0


def add_camera_options(p: argparse.ArgumentParser) -> None:
    """What import-captures and a live capture need beyond the photographs: camera lens, rig file, depth, checks."""
    p.add_argument("--camera-fov", type=finite_float, default=60.0,
                   help="nominal horizontal field of view of the camera in degrees (default 60)")
    p.add_argument("--rig", type=Path, metavar="RIG_JSON",
                   help="a rig calibration from `procam calibrate-rig`: calibrated camera and projector K, the "
                        "camera's lens distortion removed from every photograph (and the depth map), the "
                        "projector's pose when the rig was calibrated with --square in metres")
    p.add_argument("--depth", type=Path, metavar="FILE",
                   help="depth of the scene seen from the camera: .npy/.exr in metres, 16-bit .png/.tif in "
                        "millimetres (0 = no depth; iPhone, RealSense, Azure Kinect), or a .ply point cloud in the "
                        "camera's OpenCV frame (x right, y down, z forward). A shift of a few pixels against the "
                        "photographs is found and corrected (with a warning)")
    p.add_argument("--depth-units", choices=("auto", "m", "mm"), default="auto",
                   help="units of the depth values; auto (default) detects millimetres given as metres and says so")
    p.add_argument("--depth-native-width", type=_positive_int,
                   help="native depth-sensor width (e.g. 256); a .ply point cloud is projected at this size")
    p.add_argument("--depth-native-height", type=_positive_int, help="native depth-sensor height (e.g. 192)")
    p.add_argument("--no-exposure-check", action="store_true",
                   help="import even when the photographs' exposure or white balance seems to change during the "
                        "session (complementary patterns that do not add up to white + black)")


def depth_native_size(args: argparse.Namespace) -> tuple[int, int] | None:
    if not (args.depth_native_width or args.depth_native_height):
        return None
    if not (args.depth_native_width and args.depth_native_height):
        raise CaptureError("give both --depth-native-width and --depth-native-height")
    return (args.depth_native_width, args.depth_native_height)


def _configure_import(p: argparse.ArgumentParser) -> None:
    p.add_argument("sequence_dir", type=Path, help="folder written by `procam patterns`")
    p.add_argument("captures_dir", type=Path, help="folder of numbered captures (png, jpg, tif, exr), one per frame")
    p.add_argument("--out", type=Path, required=True, help="new capture-set folder")
    p.add_argument("--camera-width", type=_positive_int, help="expected capture width (checked)")
    p.add_argument("--camera-height", type=_positive_int, help="expected capture height (checked)")
    p.add_argument("--encoding", choices=("auto", "srgb", "linear"), default="auto",
                   help="how the captures are encoded; auto: 8-bit files are sRGB, 16-bit/float are linear")
    add_camera_options(p)
    p.add_argument("--force", action="store_true", help="replace an existing capture set at --out")


@command("import-captures", "Import numbered captures of an exported pattern sequence as a capture set.",
         _configure_import)
def import_photographs(args: argparse.Namespace) -> int:
    camera = None
    if (args.camera_width is None) != (args.camera_height is None):
        raise CaptureError("give both --camera-width and --camera-height, or neither")
    if args.camera_width:
        camera = Camera(intrinsics_from_fov(args.camera_width, args.camera_height, args.camera_fov))
    native = depth_native_size(args)
    cs = run_step("import-captures", run_import, ImportOptions(
        args.sequence_dir, args.captures_dir, args.out, camera=camera, camera_fov=args.camera_fov,
        encoding=args.encoding, depth_path=args.depth, depth_units=args.depth_units, depth_native_size=native,
        rig=args.rig, check_exposure=not args.no_exposure_check, force=args.force))
    w, h = cs.camera.intrinsics.size
    print(f"wrote capture set {cs.path}: {len(cs)} images, camera {w}×{h}")
    if args.rig is not None:
        print(f"  camera and projector from {args.rig}: lens distortion removed from the photographs; projector "
              f"pose {'from the rig (use calibrate --init nominal to keep it)' if cs.projector_pose_known else 'left to calibrate (the rig is in board squares)'}")
    return 0


def _configure_undistort(p: argparse.ArgumentParser) -> None:
    p.add_argument("captures_dir", type=Path, help="a capture set (procam lab, import-captures or capture)")
    p.add_argument("--rig", type=Path, required=True, metavar="RIG_JSON",
                   help="a rig calibration from `procam calibrate-rig` of the camera that took the set")
    p.add_argument("--out", type=Path, required=True, help="new capture-set folder")
    p.add_argument("--force", action="store_true", help="replace an existing capture set at --out")


@command("undistort-captures", "Take the camera lens of a rig calibration out of an existing capture set.",
         _configure_undistort)
def undistort(args: argparse.Namespace) -> int:
    cs = run_step("undistort-captures", run_undistort, UndistortOptions(args.captures_dir, args.rig, args.out,
                                                                        force=args.force))
    print(f"wrote capture set {cs.path}: {len(cs)} images with the camera's lens from {args.rig} taken out; "
          "calibrate it, and a live camera's frames will go through the same lens")
    return 0
