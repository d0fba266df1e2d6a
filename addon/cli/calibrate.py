"""``procam calibrate``: surface, projector pose (stage A) and warp (stage B) from a capture set."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..errors import CalibrationError
from ..options import add_arguments, from_arguments
from ..steps.calibrate import BlendWriter, CalibrateOptions, run as calibrate
from ..steps.layout import TRANSPORT_JSON
from .app import command
from .terminal import run_step


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture_dir", type=Path, help="capture set folder (from procam lab or import-captures)")
    p.add_argument("--out", type=Path, required=True, help="calibration folder to create")
    add_arguments(p, CalibrateOptions, exclude=("with_blend",))
    p.add_argument("--blend", type=Path, help="with --init blender: the .blend holding the ProCam Projector")
    p.add_argument("--no-blend-output", action="store_true", help="do not write scene.blend")
    p.add_argument("--force", action="store_true", help="replace an existing calibration folder")


def blend_writer() -> "BlendWriter":
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
    cal = run_step("calibrate", calibrate, options, blend_writer=blend_writer() if options.with_blend else None)
    r = cal.report
    print(f"calibration: {args.out}")
    sr = r["surface_report"]
    source = sr.get("source", "depth")
    print(f"  surface: {sr['vertices']} vertices, {sr['faces']} faces, from {source}, depth offset "
          f"{100 * sr.get('depth_offset', 0.0):+.2f} cm ({sr.get('depth_offset_source', 'none')})")
    if "triangulation" in sr:
        t = sr["triangulation"]
        print(f"  triangulated Gray code: {t['points']} points ({t['rejected']} rejected), reprojection "
              f"{t['reprojection_rms_px']:.2f} px rms, {t['triangulation_angle_deg']:.1f}° between the rays")
    if "registration" in sr:
        g = sr["registration"]
        print(f"  mesh {sr['mesh_file']} registered to the {sr['measured']} points: residual {g['rms_mm']:.2f} mm "
              f"rms, {g['median_mm']:.2f} mm median, overlap {g['overlap']:.0%}, {g['iterations']} iterations "
              f"(start: {g['start']})")
    p = cal.rig.projector
    if "init" in r:
        print(f"  projector position (m): {np.array2string(p.position, precision=4)}, "
              f"direction: {np.array2string(p.direction, precision=4)} (init: {r['init']}, stage A: "
              f"{r.get('pose', {}).get('info', {}).get('method', 'ours')})")
    if "projector_intrinsics" in r:
        print(f"  projector intrinsics (fitted to the Gray code): {r['projector_intrinsics']['summary']}")
    print("  stages: " + ", ".join(f"{k} {v}" for k, v in cal.stages.items()))
    for w in cal.warnings:
        print(f"  warning: {w}")
    b, a = (r.get("warp_report") or {}).get("corners_before_px"), (r.get("warp_report") or {}).get("corners_after_px")
    if b and a:
        what = ("decoded Gray code against the model, median" if r["warp_report"].get("source") == "graycode"
                else "checker corners median")
        print(f"  warp: {what} {b.get('median', float('nan')):.2f} px → {a.get('median', float('nan')):.2f} px")
    print("  seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in r["seconds"].items()))
    operator = Path(args.out) / TRANSPORT_JSON
    if operator.is_file():
        doc = json.loads(operator.read_text())
        print(f"  transport operator: {doc['megabytes']} MB in {doc['seconds']:.0f} s")
    return 0
