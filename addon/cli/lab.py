"""``procam lab``: render a complete calibration capture set in the virtual lab, truth sealed outside it.

Every argument is checked before the first render (surface, effects, sizes,
output folders), so a bad request fails in about a second with exit code 2
and writes nothing. Progress goes to stderr, the summary to stdout.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..lab.lab import describe_run
from ..options import add_arguments, from_arguments
from ..steps.capture import BoardOptions, LabOptions, run_board, run_lab
from .app import command
from .terminal import progress, run_step


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, required=True, help="capture set folder to create")
    add_arguments(p, LabOptions)
    p.add_argument("--force", action="store_true", help="replace an existing capture set (and truth) at --out")
    p.formatter_class = argparse.RawDescriptionHelpFormatter


@command("lab", "Render a calibration capture set in the virtual lab (Cycles + injected real-world effects).",
         _configure)
def run(args: argparse.Namespace) -> int:
    options = from_arguments(LabOptions, args, out=args.out, force=args.force)
    out, truth_path = options.paths()
    progress(f"lab: {out} ({args.samples} spp)")
    t0 = time.perf_counter()
    cs = run_step("lab", run_lab, options)
    sizes = ", ".join(f"{w}×{h}" for w, h in (p.intrinsics.size for p in cs.projectors))
    print(f"capture set: {out} ({describe_run(cs, time.perf_counter() - t0)}, projector{'s' if cs.others else ''} "
          f"{sizes}, {args.samples} spp)")
    print(f"sealed truth: {truth_path}")
    print(f"effects: {args.effects or 'none'}" + (f"; other forms at {options.other_forms:g} (procam lab --help)"
                                                  if options.other_forms else ""))
    return 0


def _configure_board(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, required=True, help="folder to create, one pose_NN session folder per pose")
    add_arguments(p, BoardOptions)
    p.add_argument("--force", action="store_true", help="replace board sessions made earlier at --out")


@command("lab-board", "Render chessboard sessions of the demo rig in the virtual lab, for procam calibrate-rig.",
         _configure_board)
def run_board_sessions(args: argparse.Namespace) -> int:
    options = from_arguments(BoardOptions, args, out=args.out, force=args.force)
    truth = run_step("lab-board", run_board, options)
    size = truth.rig.projector.intrinsics.size
    print(f"board sessions: {args.out} ({len(truth.poses)} poses of a {args.board[0]}x{args.board[1]} board, "
          f"squares {args.square:g} m)")
    print(f"sealed truth: {args.truth or args.out.with_name(args.out.name + '.truth.json')}")
    print(f"calibrate them: procam calibrate-rig {args.out}/pose_* --board {args.board[0]}x{args.board[1]} "
          f"--square {args.square:g} --projector {size[0]}x{size[1]} --out rig.json")
    return 0
