"""``procam report``: one self-contained HTML page of step folders or a whole tree of them (``steps/report.py``)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..options import add_arguments, from_arguments
from ..steps.report import ReportOptions, run as report
from .app import command
from .terminal import run_step


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("folders", type=Path, nargs="+", metavar="FOLDER",
                   help="step folders, or folders holding them (a demo's, a project's): each is walked")
    add_arguments(p, ReportOptions)


@command("report", "One HTML page of step folders (calibration, evaluation, diagnosis, show), pictures embedded.",
         _configure)
def run(args: argparse.Namespace) -> int:
    result = run_step("report", report, from_arguments(ReportOptions, args, folders=tuple(args.folders)))
    print(f"report: {result.path}")
    print(f"  {len(result.sections)} step folder(s) shown, {len(result.skipped)} thing(s) skipped; "
          f"{result.bytes / 1e6:.2f} MB, built in {result.seconds:.1f} s")
    for path, reason in result.skipped:
        print(f"  skipped {path}: {reason}")
    return 0
