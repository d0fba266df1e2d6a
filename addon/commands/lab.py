"""``procam lab``: render a complete calibration capture set in the virtual lab, truth sealed outside it.

Every argument is checked before the first render (surface, effects, sizes,
output folders), so a bad request fails in about a second with exit code 2
and writes nothing. Progress goes to stderr, the summary to stdout.
"""

from __future__ import annotations

import argparse
import os
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
    p.add_argument("--samples", type=int, default=16,
                   help="Cycles samples per pixel (default 16); checker and Gray-code frames, which are only "
                        "binarised, get a quarter (at least 4) unless --full-binary")
    p.add_argument("--full-binary", action="store_true",
                   help="render checker and Gray-code frames with the full --samples too")
    p.add_argument("--scale", type=float, default=1.0,
                   help="resolution scale: 1 = camera 640×480, projector 800×600 (default); 0.5 halves both")
    p.add_argument("--no-graycode", action="store_true", help="skip the Gray-code patterns (faster)")
    p.add_argument("--force", action="store_true", help="replace an existing capture set (and truth) at --out")
    p.formatter_class = argparse.RawDescriptionHelpFormatter


@command("lab", "Render a calibration capture set in the virtual lab (Cycles + injected real-world effects).", _configure)
def run(args: argparse.Namespace) -> int:
    from ..lab.lab import check_lab_outputs, describe_run, make_truth, run_lab
    from ..outputs import progress

    if not 0.05 <= args.scale <= 2:
        raise LabError(f"--scale must lie between 0.05 and 2, got {args.scale}")
    out = Path(os.path.abspath(args.out))  # normalised, so that "." or "../x" get a proper name
    truth_path = Path(os.path.abspath(args.truth)) if args.truth else out.with_name(out.name + ".truth.json")
    check_lab_outputs(out, truth_path, force=args.force)  # before reading any mesh
    truth = make_truth(args.surface, effects=args.effects, seed=args.seed, samples=args.samples, scale=args.scale)
    cam, proj = truth.rig.camera.intrinsics.size, truth.rig.projector.intrinsics.size
    progress(f"lab: surface {truth.surface_source}, effects {truth.effects.spec}, camera {cam[0]}×{cam[1]}, "
             f"projector {proj[0]}×{proj[1]}, {args.samples} spp")
    t0 = time.perf_counter()

    def report(done: int, total: int, message: str) -> None:
        elapsed = time.perf_counter() - t0
        eta = f", ~{elapsed / done * (total - done):.0f} s left" if 2 < done < total else ""
        progress(f"lab: {done}/{total} {message} ({elapsed:.0f} s{eta})")

    cs = run_lab(truth, out, truth_path=truth_path, force=args.force, graycode=not args.no_graycode,
                 fast_binary=not args.full_binary, progress=report)
    dt = time.perf_counter() - t0
    print(f"capture set: {out} ({describe_run(cs, dt)}, projector {proj[0]}×{proj[1]}, {args.samples} spp)")
    print(f"sealed truth: {truth_path}")
    print(f"effects: {truth.effects.spec}")
    return 0
