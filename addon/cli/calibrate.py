"""``procam calibrate``: surface, projector pose (stage A) and warp (stage B) from a capture set."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..errors import CalibrationError
from ..steps.calibrate import BlendWriter, CalibrateOptions, run as calibrate
from ..steps.layout import TRANSPORT_JSON
from .app import command
from .terminal import run_step


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture_dir", type=Path, help="capture set folder (from procam lab or import-captures)")
    p.add_argument("--out", type=Path, required=True, help="calibration folder to create")
    p.add_argument("--init", choices=("graycode", "nominal", "blender"), default="graycode",
                   help="starting pose for stage A: Gray-code correspondences + PnP (default), the capture set's "
                        "nominal projector (kept as it is when it came from a metric rig calibration), or the "
                        "ProCam Projector placed in a .blend (--blend)")
    p.add_argument("--stage-a", choices=("ours", "paper"), default="ours",
                   help="stage A's mask refinement: ours (debiased soft mask, annealed border smoothing) or the "
                        "paper's (binary mask, Γ with ε = 0.01, 200 Adam steps), from the start --init gives "
                        "(--init nominal --stage-a paper reproduces the paper's pipeline)")
    p.add_argument("--projector-intrinsics", choices=("spec", "fit"), default="spec",
                   help="the projector's focal length and principal point: as the capture set gives them (spec "
                        "sheet or rig file; default), or fitted to the Gray code on a curved or edged surface "
                        "(kept at the spec where the surface cannot tell, e.g. a flat wall)")
    p.add_argument("--blend", type=Path, help="with --init blender: the .blend holding the ProCam Projector")
    p.add_argument("--no-blend-output", action="store_true", help="do not write scene.blend")
    p.add_argument("--stages", default="all", metavar="STAGES",
                   help="run these stages only, comma-separated from surface,pose,warp (a contiguous run): "
                        "earlier ones come from the calibration already in --out, later ones are left to run "
                        "(default: all)")
    p.add_argument("--depth-offset", type=float, default=None, metavar="METRES",
                   help="the depth sensor's constant bias (+ = it reads too far), subtracted from the depth; "
                        "default: read from the capture set's wall depth image (a flat wall at a tape-measured "
                        "distance), else 0")
    p.add_argument("--surface-from", choices=("auto", "depth", "graycode", "mesh"), default="auto",
                   help="where the surface comes from: the capture set's depth image, the Gray code triangulated with "
                        "a calibrated rig (import-captures --rig with a metric rig file), or the mesh of "
                        "--surface-mesh registered to either (default auto: the mesh if given, else depth if "
                        "present, else the Gray code when the projector's pose is known)")
    p.add_argument("--surface-mesh", type=Path, default=None, metavar="FILE",
                   help="the object's mesh (.obj/.ply, a scan or CAD model in its own frame, metres or "
                        "millimetres), registered by ICP to the depth or triangulated points and used as the surface")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--precompute", action=argparse.BooleanOptionalAction, default=True,
                   help="also precompute the light-transport operator into the folder (procam precompute; ~25 s "
                        "at 640×480), which stage C's default schedule solves on (default on)")
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
    options = CalibrateOptions(args.capture_dir, args.out, init="given" if initial is not None else args.init,
                               initial_pose=initial, stage_a=args.stage_a, stages=args.stages,
                               projector_intrinsics=args.projector_intrinsics,
                               depth_offset=args.depth_offset, surface_from=args.surface_from,
                               surface_mesh=args.surface_mesh, with_blend=not args.no_blend_output, seed=args.seed,
                               precompute=args.precompute, force=args.force)
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
