"""``procam export-frames``: the compensated projector frames as a numbered 16-bit PNG sequence for a media server."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..options import add_arguments, from_arguments
from ..steps.export import ExportFramesOptions, run_frames
from .app import command
from .terminal import run_step


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("compensation", type=Path, help="compensation folder (from procam compensate)")
    p.add_argument("--out", type=Path, required=True, help="folder to create for frame_0001.png … and frames.json "
                   "(several projectors: projector_K/frame_0001.png …, one sequence per projector)")
    add_arguments(p, ExportFramesOptions)
    p.add_argument("--force", action="store_true", help="replace an existing frame sequence at --out")


@command("export-frames",
         "Write the compensated projector frames as a numbered 16-bit PNG sequence (one per projector).", _configure)
def run(args: argparse.Namespace) -> int:
    out = run_step("export-frames", run_frames, from_arguments(
        ExportFramesOptions, args, compensation=args.compensation, out=args.out, force=args.force))
    print(f"projector frames: {out}")
    return 0
