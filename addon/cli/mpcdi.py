"""``procam export-mpcdi`` and ``procam apply-mpcdi``: a calibration as a VESA MPCDI file for media servers, and an
MPCDI file applied to content frames as a media server would."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..options import add_arguments, from_arguments
from ..steps.mpcdi import ApplyMpcdiOptions, ExportMpcdiOptions, run_apply, run_export
from .app import command
from .terminal import progress, run_step


def _configure_export(p: argparse.ArgumentParser) -> None:
    p.add_argument("calibration", type=Path, help="calibration folder (from procam calibrate), one projector or more")
    p.add_argument("--out", type=Path, required=True, help="the .mpcdi file to write")
    add_arguments(p, ExportMpcdiOptions)
    p.add_argument("--force", action="store_true", help="replace an existing MPCDI file at --out")


@command("export-mpcdi", "Write the calibration as a VESA MPCDI file (warp, blend and black level per projector) "
         "for media servers.", _configure_export)
def export(args: argparse.Namespace) -> int:
    done = run_step("export-mpcdi", run_export, from_arguments(
        ExportMpcdiOptions, args, calibration=args.calibration, out=args.out, force=args.force))
    for line in done.warnings:
        progress(f"warning: {line}")
    print(f"MPCDI file: {done.path} ({done.bytes} bytes, {done.seconds:.1f} s)")
    r = done.report
    print(f"  profile {r['profile']}, content {r['content_size'][0]}x{r['content_size'][1]} in camera area "
          f"{r['area']['x']},{r['area']['y']},{r['area']['width']},{r['area']['height']}")
    print(f"  blend: {r['blend']}")
    print(f"  beta: {r.get('beta')}")
    for p in r["projectors"]:
        print(f"  projector {p['projector']}: region {p['region']} {p['resolution'][0]}x{p['resolution'][1]}, warp "
              f"grid {p['warp_grid'][0]}x{p['warp_grid'][1]}, {100 * p['pixels_showing_content']:.0f} % of its pixels "
              f"show content")
    return 0


def _configure_apply(p: argparse.ArgumentParser) -> None:
    p.add_argument("mpcdi", type=Path, help="the .mpcdi file (2d profile)")
    p.add_argument("content", type=Path, nargs="+", help="content images (the media server's canvas), in order")
    p.add_argument("--out", type=Path, required=True, help="folder to create for projector_K/frame_0001.png … and "
                   "frames.json, one sequence per region")
    add_arguments(p, ApplyMpcdiOptions)
    p.add_argument("--force", action="store_true", help="replace an existing frame sequence at --out")


@command("apply-mpcdi", "Apply an MPCDI file to content images as a media server does (warp, alpha, beta): one frame "
         "sequence per projector.", _configure_apply)
def apply(args: argparse.Namespace) -> int:
    out = run_step("apply-mpcdi", run_apply, from_arguments(
        ApplyMpcdiOptions, args, mpcdi=args.mpcdi, content=tuple(args.content), out=args.out, force=args.force))
    print(f"projector frames: {out}")
    return 0
