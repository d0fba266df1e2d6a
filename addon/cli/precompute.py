"""``procam precompute``: the light-transport operator of a calibration, for stage C's ``transport`` schedule."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..options import add_arguments, from_arguments
from ..steps.transport import PrecomputeOptions, run
from .app import command
from .terminal import run_step


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("calibration", type=Path, help="calibration folder (from procam calibrate)")
    add_arguments(p, PrecomputeOptions)
    p.add_argument("--force", action="store_true", help="render it again even when one is stored")


@command("precompute", "Precompute the light-transport operator of a calibration (compensate --schedule transport).",
         _configure)
def precompute(args: argparse.Namespace) -> int:
    doc = run_step("precompute", run, from_arguments(
        PrecomputeOptions, args, calibration=args.calibration, force=args.force))
    docs = doc.get("projectors", [doc])  # a calibration of several projectors: each one's operator
    for k, one in enumerate(docs):
        whose = f" (projector {k + 1}, {one.get('file')})" if len(docs) > 1 else ""
        print(f"transport operator in {args.calibration}{whose}: {one['direct_renders']} direct renders (lattice "
              f"every {one['spacing']}th texel), {one['entries_per_pixel']} entries a pixel, indirect "
              f"{one['indirect_blocks'][0]}×{one['indirect_blocks'][1]} blocks; {one['megabytes']} MB, "
              f"{one['seconds']} s")
        inv = one.get("inverse")
        if inv:
            print(f"approximate inverse{whose}: {inv['stencil']} stencil, {inv['megabytes']} MB, {inv['seconds']} s")
    return 0
