"""``procam lab``: render a complete calibration capture set in the virtual lab, truth sealed outside it."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..cli import command
from ..errors import LabError


def _configure(p: argparse.ArgumentParser) -> None:
    from ..lab.effects import effect_help

    p.add_argument("--surface", default="curve", help="plane, curve, vedge, hedge, or an .obj/.ply file (rig frame, metres)")
    p.add_argument("--out", type=Path, required=True, help="capture set folder to create")
    p.add_argument("--truth", type=Path, default=None,
                   help="sealed truth JSON, outside the capture set (default: OUT.truth.json beside OUT)")
    p.add_argument("--effects", default="", help="NAME=STRENGTH[,NAME.PARAM=VALUE…] or 'realistic'. " + effect_help())
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--samples", type=int, default=16, help="Cycles samples per pixel (default 16)")
    p.add_argument("--scale", type=float, default=1.0,
                   help="resolution scale: 1 = camera 640×480, projector 800×600 (default); 0.5 halves both")
    p.add_argument("--no-graycode", action="store_true", help="skip the Gray-code patterns (faster)")
    p.add_argument("--force", action="store_true", help="replace an existing capture set at --out")
    p.formatter_class = argparse.RawDescriptionHelpFormatter


@command("lab", "Render a calibration capture set in the virtual lab (Cycles + injected real-world effects).", _configure)
def run(args: argparse.Namespace) -> int:
    from ..lab.lab import make_truth, run_lab
    from ..outputs import progress

    if not 0.05 <= args.scale <= 2:
        raise LabError(f"--scale must lie between 0.05 and 2, got {args.scale}")
    cam = (max(8, round(640 * args.scale)), max(6, round(480 * args.scale)))
    proj = (max(8, round(800 * args.scale)), max(6, round(600 * args.scale)))
    truth_path = args.truth or args.out.with_name(args.out.name + ".truth.json")
    truth = make_truth(args.surface, effects=args.effects, seed=args.seed, samples=args.samples,
                       camera_size=cam, projector_size=proj)
    t0 = time.perf_counter()

    def report(seq):
        for i, spec in enumerate(seq):
            progress(f"lab: {i + 1}/{len(seq)} {spec.name}")
            yield spec

    cs = run_lab(truth, args.out, truth_path=truth_path, force=args.force, graycode=not args.no_graycode,
                 progress=report)
    dt = time.perf_counter() - t0
    print(f"capture set: {args.out} ({len(cs.entries)} images, camera {cam[0]}×{cam[1]}, projector {proj[0]}×{proj[1]}, "
          f"{args.samples} spp) in {dt:.0f} s")
    print(f"sealed truth: {truth_path}")
    print(f"effects: {truth.effects.spec or 'none'}")
    return 0

