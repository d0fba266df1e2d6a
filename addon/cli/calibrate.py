"""``procam calibrate``: surface, projector pose (stage A) and warp (stage B) from a capture set."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import CalibrationError
from ..options import add_arguments, from_arguments
from ..steps.calibrate import BlendWriter, CalibrateOptions, run as calibrate, summary
from .app import command
from .terminal import print_summary, run_step


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture_dir", type=Path, help="capture set folder (from procam lab or import-captures)")
    p.add_argument("--out", type=Path, required=True, help="calibration folder to create")
    add_arguments(p, CalibrateOptions, exclude=("with_blend",))
    p.add_argument("--blend", type=Path, help="with --init blender: the .blend holding the ProCam Projector")
    p.add_argument("--no-blend-output", action="store_true", help="do not write scene.blend")
    p.add_argument("--force", action="store_true", help="replace an existing calibration folder")


def blend_writer() -> BlendWriter:
    """Blender's writer of a calibration's scene.blend: bpy is imported here, by the command, never by the steps."""
    from ..blender.blend_file import save_calibration_blend

    return save_calibration_blend


@command("calibrate", "Estimate surface, projector pose and warp from a capture set.", _configure)
def run(args: argparse.Namespace) -> int:
    initial = None
    if args.init == "blender":
        if args.blend is None:
            raise CalibrationError("--init blender needs --blend FILE.blend with a ProCam Projector in it")
        # bpy only for --init blender: opening a .blend is the one thing here that needs Blender.
        from ..blender.blend_file import projector_pose_from_blend

        initial = projector_pose_from_blend(args.blend)
    options = from_arguments(CalibrateOptions, args, capture_dir=args.capture_dir, out=args.out,
                             init="given" if initial is not None else args.init, initial_pose=initial,
                             with_blend=not args.no_blend_output, force=args.force)
    run_step("calibrate", calibrate, options, blend_writer=blend_writer() if options.with_blend else None)
    print_summary("calibration", args.out, summary(args.out))
    return 0
