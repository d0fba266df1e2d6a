"""``procam calibrate-rig``: camera and projector intrinsics and their pose from a chessboard lit by Gray code."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np

from ..stages.rig_calibration import DISTORTION_MODELS, MIN_POSES, RigCalibration
from ..steps.rig import RigOptions, run as calibrate_rig
from .app import command
from .terminal import run_step


def _pair(what: str):
    """An argparse type for ``AxB`` (``x``, ``×`` or ``,`` between two positive whole numbers)."""
    def parse(text: str) -> tuple[int, int]:
        m = re.fullmatch(r"\s*(\d+)\s*[x×X,]\s*(\d+)\s*", text)
        if not m or int(m[1]) <= 0 or int(m[2]) <= 0:
            raise argparse.ArgumentTypeError(f"{what} must look like 9x7 (two positive whole numbers), got {text!r}")
        return int(m[1]), int(m[2])
    parse.__name__ = what  # argparse names the type in its messages
    return parse


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}")
    return value


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("sessions", type=Path, nargs="+", metavar="SESSION_DIR",
                   help=f"one folder per board pose (at least {MIN_POSES}), each holding the camera's images "
                        "PREFIX_00 … in projection order: the Gray code (OpenCV's order), then white, then black "
                        "(e.g. graycode_00..41.png for a 1024x768 projector)")
    p.add_argument("--board", type=_pair("board"), required=True, metavar="COLSxROWS",
                   help="the chessboard's inner corners: per row x rows (9x7 and 7x9 both find the same board)")
    p.add_argument("--square", type=_positive, default=None, metavar="METRES",
                   help="the size of one chessboard square in metres, so that the projector's position is metric "
                        "and import-captures --rig can use it (default: lengths in board squares)")
    p.add_argument("--projector", type=_pair("projector size"), required=True, metavar="WxH",
                   help="the projector's native size the Gray code was made for (required: the image count "
                        "gives only the number of bits, which many sizes share)")
    p.add_argument("--out", type=Path, required=True, metavar="RIG_JSON", help="the rig.json file to write")
    p.add_argument("--window", type=int, default=47, metavar="PIXELS",
                   help="side of the camera-pixel window around each corner whose decoded pixels fit the local "
                        "homography (default 47; about two thirds of a square works well)")
    p.add_argument("--camera-distortion", choices=tuple(DISTORTION_MODELS), default="k1k2p1p2",
                   help="which of OpenCV's k1 k2 p1 p2 k3 to estimate for the camera (default k1k2p1p2: k3 is not "
                        "observable from a few poses)")
    p.add_argument("--projector-distortion", choices=("auto", *DISTORTION_MODELS), default="auto",
                   help="the same for the projector (default auto: none, k1 or k1k2, whichever the corners "
                        "support by the BIC; a distortion fitted where there is none moves the principal point)")
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
    options = RigOptions(tuple(args.sessions), args.out, args.board, args.projector, square=args.square,
                         window=args.window, camera_model=args.camera_distortion,
                         projector_model=args.projector_distortion, force=args.force)
    cal = run_step("calibrate-rig", calibrate_rig, options)
    print_report(cal, args.out)
    return 0
