"""``procam diagnose``: where and why the calibrated simulation still differs from the captures."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..options import add_arguments, from_arguments
from ..steps.diagnose import DiagnoseOptions, run as diagnose, summary
from .app import command
from .terminal import print_summary, run_step


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("calibration", type=Path, help="calibration folder (from procam calibrate)")
    p.add_argument("--out", type=Path, required=True, help="diagnosis folder to create (gap.json, maps, summary.md)")
    add_arguments(p, DiagnoseOptions)
    p.add_argument("--force", action="store_true", help="replace an existing diagnosis folder")


@command("diagnose", "Sim-to-real diagnosis: residual maps, regions, and which unmodelled effect explains them.",
         _configure)
def run(args: argparse.Namespace) -> int:
    run_step("diagnose", diagnose, from_arguments(DiagnoseOptions, args, calibration=args.calibration,
                                                  out=args.out, force=args.force))
    print_summary("diagnosis", args.out, summary(args.out))
    return 0
