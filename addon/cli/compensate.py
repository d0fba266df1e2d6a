"""``procam compensate``: stage C for each target image, closed loop through a device or open loop.

The folder it writes is the compensate step's (``addon/steps/compensate.py``); the stage-C options here are
shared with ``procam show``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..options import add_arguments, from_arguments
from ..steps.compensate import CompensateOptions, run as compensate, summary
from ..steps.stage_c import StageCOptions
from .app import command
from .terminal import print_summary, run_step


def add_schedule_options(p: argparse.ArgumentParser) -> None:
    """The stage-C options shared by ``procam compensate`` and ``procam show`` (device, schedule, area, θ), as
    :class:`StageCOptions` declares them."""
    add_arguments(p, StageCOptions, exclude=EFFECT_OPTIONS)


def stage_c_options(args: argparse.Namespace) -> StageCOptions:
    """The :class:`StageCOptions` of the command line (checked: a bad value fails here, before any work)."""
    options = from_arguments(StageCOptions, args)
    options.check()
    return options


#: the options of the diagnosed effect models around stage C (addon/gap/compensation.py)
EFFECT_OPTIONS = ("effects", "diagnosis")


def add_effect_options(p: argparse.ArgumentParser) -> None:
    """``--effects`` / ``--diagnosis``: diagnosed effect models around stage C (addon/gap/compensation.py)."""
    add_arguments(p, StageCOptions, only=EFFECT_OPTIONS)


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("calibration", type=Path, help="calibration folder (from procam calibrate)")
    p.add_argument("targets", type=Path, nargs="+", metavar="TARGET", help="target images (PNG, JPEG, EXR, …)")
    p.add_argument("--out", type=Path, required=True, help="folder to create for the projector inputs")
    add_schedule_options(p)
    add_effect_options(p)
    p.add_argument("--force", action="store_true",
                   help="replace an existing compensation folder at --out (one a failed or cancelled run left, marked "
                        "incomplete, is replaced without it)")


@command("compensate", "Find the projector input for each target image (stage C).", _configure)
def run(args: argparse.Namespace) -> int:
    options = CompensateOptions(args.calibration, tuple(args.targets), args.out, stage_c_options(args),
                                force=args.force)
    view = run_step("compensate", compensate, options, total=len(options.targets), unit="targets")
    print_summary("compensation", view.folder, summary(view.folder))
    return 0
