"""``procam lab``: render a complete calibration capture set in the virtual lab, truth sealed outside it.

Every argument is checked before the first render (surface, effects, sizes,
output folders), so a bad request fails in about a second with exit code 2
and writes nothing. Progress goes to stderr, the summary to stdout.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..lab.effects import effect_help
from ..lab.lab import describe_run
from ..steps.capture import BoardOptions, LabOptions, run_board, run_lab
from .app import command
from .args import finite_float
from .terminal import progress, run_step


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--surface", default="curve", help="plane, curve, vedge, hedge, or an .obj/.ply file (rig frame, metres)")
    p.add_argument("--out", type=Path, required=True, help="capture set folder to create")
    p.add_argument("--truth", type=Path, default=None,
                   help="sealed truth JSON, outside the capture set (default: OUT.truth.json beside OUT)")
    p.add_argument("--effects", default="", help="NAME=STRENGTH[,NAME.PARAM=VALUE…] or 'realistic'. " + effect_help())
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--samples", type=int, default=16,
                   help="Cycles samples per pixel (default 16); checker and Gray-code frames, which are only "
                        "binarised, get a quarter (at least 4) unless --full-binary")
    p.add_argument("--full-binary", action="store_true",
                   help="render checker and Gray-code frames with the full --samples too")
    p.add_argument("--scale", type=finite_float, default=1.0,
                   help="resolution scale: 1 = camera 640×480, projector 800×600 (default); 0.5 halves both")
    p.add_argument("--projector-shift", type=_pair, default=None, metavar="RIGHT,UP",
                   help="the demo projector's lens shift in %% of its image (default 0,15; a real projector may sit "
                        "far below its image, e.g. 0,127)")
    p.add_argument("--nominal-error", type=_pair, default=(0.0, 0.0), metavar="FOCAL,SHIFT",
                   help="give the pipeline a projector spec that is wrong by FOCAL %% in focal length (throw ratio) "
                        "and SHIFT %% of the height in vertical lens shift, as a data sheet may be (default 0,0)")
    p.add_argument("--camera-fov-error", type=finite_float, default=0.0, metavar="DEGREES",
                   help="give the pipeline a camera whose horizontal field of view is DEGREES off, as a guessed or "
                        "spec-sheet FoV may be (default 0)")
    p.add_argument("--supersample", type=int, default=1, metavar="N",
                   help="render the camera at N times its resolution and average down, so that lens distortion "
                        "resamples finer pixels than the camera's, as a real lens does (default 1; 2 costs 4×)")
    p.add_argument("--no-graycode", action="store_true", help="skip the Gray-code patterns (faster)")
    p.add_argument("--force", action="store_true", help="replace an existing capture set (and truth) at --out")
    p.formatter_class = argparse.RawDescriptionHelpFormatter


def _pair(text: str) -> tuple[float, float]:
    try:
        a, b = (finite_float(v) / 100.0 for v in text.split(","))
    except (ValueError, argparse.ArgumentTypeError):
        raise argparse.ArgumentTypeError(f"expected two percentages A,B (e.g. 0,127), got {text!r}") from None
    return a, b


@command("lab", "Render a calibration capture set in the virtual lab (Cycles + injected real-world effects).", _configure)
def run(args: argparse.Namespace) -> int:
    options = LabOptions(args.out, surface=args.surface, effects=args.effects, seed=args.seed, samples=args.samples,
                         scale=args.scale, graycode=not args.no_graycode, full_binary=args.full_binary,
                         truth=args.truth, projector_shift=args.projector_shift,
                         nominal_error=args.nominal_error,
                         camera_fov_error=args.camera_fov_error, supersample=args.supersample, force=args.force)
    out, truth_path = options.paths()
    progress(f"lab: {out} ({args.samples} spp)")
    t0 = time.perf_counter()
    cs = run_step("lab", run_lab, options)
    proj = cs.projector.intrinsics.size
    print(f"capture set: {out} ({describe_run(cs, time.perf_counter() - t0)}, projector {proj[0]}×{proj[1]}, "
          f"{args.samples} spp)")
    print(f"sealed truth: {truth_path}")
    print(f"effects: {args.effects or 'none'}")
    return 0


def _configure_board(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, required=True, help="folder to create, one pose_NN session folder per pose")
    p.add_argument("--truth", type=Path, default=None, help="sealed truth file (default: OUT.truth.json beside OUT)")
    p.add_argument("--board", type=_board, default=(9, 7), metavar="COLSxROWS", help="inner corners (default 9x7)")
    p.add_argument("--square", type=finite_float, default=0.06, metavar="METRES", help="square size (default 0.06)")
    p.add_argument("--poses", type=int, default=6, help="board poses (default 6; at least 3)")
    p.add_argument("--effects", default="", help="lab effects, e.g. distortion=0.5,noise=0.3 (default none)")
    p.add_argument("--samples", type=int, default=4, help="Cycles samples per pixel (default 4)")
    p.add_argument("--scale", type=finite_float, default=1.0,
                   help="resolution scale: 1 = camera 640×480, projector 800×600")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--supersample", type=int, default=None, metavar="N",
                   help="render the camera at N times its resolution and average down, so that lens distortion "
                        "resamples finer pixels than the camera's, as a real lens does (default 2 when --effects "
                        "distort the camera's lens, which costs 4× the rendering; else 1)")
    p.add_argument("--force", action="store_true", help="replace board sessions made earlier at --out")


def _board(text: str) -> tuple[int, int]:
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"board must be COLSxROWS inner corners, e.g. 9x7; got {text!r}") from None
    return cols, rows


@command("lab-board", "Render chessboard sessions of the demo rig in the virtual lab, for procam calibrate-rig.",
         _configure_board)
def run_board_sessions(args: argparse.Namespace) -> int:
    options = BoardOptions(args.out, board=args.board, square=args.square, poses=args.poses, effects=args.effects,
                           samples=args.samples, scale=args.scale, seed=args.seed, truth=args.truth, force=args.force,
                           supersample=args.supersample)
    truth = run_step("lab-board", run_board, options)
    size = truth.rig.projector.intrinsics.size
    print(f"board sessions: {args.out} ({len(truth.poses)} poses of a {args.board[0]}x{args.board[1]} board, "
          f"squares {args.square:g} m)")
    print(f"sealed truth: {args.truth or args.out.with_name(args.out.name + '.truth.json')}")
    print(f"calibrate them: procam calibrate-rig {args.out}/pose_* --board {args.board[0]}x{args.board[1]} "
          f"--square {args.square:g} --projector {size[0]}x{size[1]} --out rig.json")
    return 0
