"""``procam calibrate-rig``: camera and projector intrinsics and their pose from a chessboard lit by Gray code."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..options import add_arguments, from_arguments
from ..stages.rig_calibration import MIN_POSES, RigCalibration
from ..steps.rig import RigOptions, run as calibrate_rig
from .app import command
from .terminal import run_step


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("sessions", type=Path, nargs="+", metavar="SESSION_DIR",
                   help=f"one folder per board pose (at least {MIN_POSES}), each holding the camera's images "
                        "PREFIX_00 … in projection order: the Gray code (OpenCV's order), then white, then black "
                        "(e.g. graycode_00..41.png for a 1024x768 projector)")
    add_arguments(p, RigOptions, exclude=("window", "camera_model", "projector_model"))
    p.add_argument("--out", type=Path, required=True, metavar="RIG_JSON", help="the rig.json file to write")
    add_arguments(p, RigOptions, only=("window", "camera_model", "projector_model"))
    p.add_argument("--force", action="store_true", help="replace an existing rig.json")


def _num(value: float | None, spec: str = ".3f") -> str:
    return "–" if value is None else f"{value:{spec}}"


def print_report(cal: RigCalibration, out: Path) -> None:
    """The calibration as a table on stdout."""
    print(f"rig calibration: {out}")
    square = f"{cal.square:g} m" if cal.metric else "1 (lengths in squares)"
    print(f"  board {cal.board[0]}x{cal.board[1]} inner corners, square {square}; camera "
          f"{cal.camera_size[0]}x{cal.camera_size[1]}, projector {cal.projector_size[0]}x{cal.projector_size[1]}")
    head = f"  {'pose':<24} {'used':<5} {'corners':>7} {'decoded':>7} {'share':>6} {'cam RMS':>8} {'proj RMS':>8}"
    print(head)
    for p in cal.poses:
        share = "–" if p.decoded_share is None else f"{100 * p.decoded_share:.0f} %"
        print(f"  {p.name[-24:]:<24} {'yes' if p.used else 'no':<5} {p.corners_found:>7} {p.corners_decoded:>7} "
              f"{share:>6} {_num(p.camera_rms):>8} {_num(p.projector_rms):>8}")
        if not p.used:
            print(f"    skipped: {p.reason}")
    print(f"  RMS (px): camera {cal.camera_rms:.3f}, projector {cal.projector_rms:.3f}, stereo {cal.stereo_rms:.3f} "
          f"({cal.stereo_flags})")
    for name, K, d, std, model in (("camera", cal.camera_matrix, cal.camera_distortion, cal.camera_std,
                                    cal.camera_model),
                                   ("projector", cal.projector_matrix, cal.projector_distortion, cal.projector_std,
                                    cal.projector_model)):
        print(f"  {name} K (OpenCV, pixel centres): fx {K[0, 0]:.2f} ±{std[0]:.1f}  fy {K[1, 1]:.2f} ±{std[1]:.1f}  "
              f"cx {K[0, 2]:.2f} ±{std[2]:.1f}  cy {K[1, 2]:.2f} ±{std[3]:.1f}")
        print(f"  {name} distortion k1 k2 p1 p2 k3 ({model}): {np.array2string(d, precision=5, suppress_small=True)}")
    choice = cal.projector_model_choice
    if choice:
        print("  projector distortion chosen by " + choice["criterion"] + ": " + ", ".join(
            f"{m} RMS {c['rms']:.3f} BIC {c['bic']:.1f}" for m, c in choice["candidates"].items()))
    print("  R (camera → projector, OpenCV):")
    for row in cal.rotation:
        print("    " + " ".join(f"{v:+.6f}" for v in row))
    print(f"  T (camera → projector, {'m' if cal.metric else 'board squares'}): "
          f"{np.array2string(cal.translation, precision=4)}")
    print(f"  projector position in the camera frame: {np.array2string(cal.camera_from_projector[:3, 3], precision=4)}")
    for w in cal.warnings:
        print(f"  warning: {w}")


@command("calibrate-rig", "Calibrate camera, projector and their pose from a chessboard lit by Gray code.", _configure)
def run(args: argparse.Namespace) -> int:
    options = from_arguments(RigOptions, args, sessions=tuple(args.sessions), out=args.out, force=args.force)
    cal = run_step("calibrate-rig", calibrate_rig, options)
    print_report(cal, args.out)
    return 0
