"""Benchmark of stage A (projector pose) on lab data: each start/strategy, each surface; prints a table.

    .venv/bin/python scripts/bench_pose.py [--scale 0.5] [--surfaces plane,curve,vedge,hedge]
        [--effects realistic] [--samples 16] [--cache DIR] [--strategies pnp,pnp+mask,mask,paper]

For each surface it renders (or reuses, from ``--cache``) a lab capture set
with Gray code, reconstructs the surface from the capture's depth, runs stage
A with each strategy, and compares the pose with the sealed lab truth
(evaluation only). Strategies:

* ``pnp``       the default: Gray-code correspondences + PnP (the mask only checks the result)
* ``pnp+mask``  PnP, then 60 steps of the debiased mask refinement
* ``mask``      the debiased mask refinement alone from the nominal pose (≥ 15 cm, 5° off)
* ``paper``     the paper's stage A from the nominal pose: binary mask, Γ with ε = 0.01 throughout,
                Adam without preconditioning, at full resolution

Errors: position (mm) and the angle between optical axes (degrees).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from procam.addon.capture.format import CaptureSet
from procam.addon.lab.truth import LabTruth, make_truth
from procam.addon.lab.lab import run_lab
from procam.addon.stages.surface import scene_depth
from procam.addon.stages.pose import estimate_pose, pose_error
from procam.addon.surface.reconstruct import reconstruct_surface

STRATEGIES = ("pnp", "pnp+mask", "mask", "paper")


def lab_set(cache: Path, surface: str, effects: str, scale: float, samples: int, seed: int) -> tuple[Path, Path]:
    root = cache / f"{surface}-{effects or 'none'}-s{scale:g}-n{samples}-seed{seed}"
    caps, truth = root / "captures", root / "truth.json"
    if not (caps / "capture.json").is_file() or not truth.is_file():
        root.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        cam = (round(640 * scale), round(480 * scale))
        proj = (round(800 * scale), round(600 * scale))
        lab = make_truth(surface, effects=effects, seed=seed, samples=samples, camera_size=cam, projector_size=proj)
        run_lab(lab, caps, truth_path=truth, graycode=True, force=True)
        print(f"# rendered {surface} lab set at {cam[0]}×{cam[1]} in {time.perf_counter() - t0:.0f} s", flush=True)
    return caps, truth


def run(strategy: str, captures: CaptureSet, surface, seed: int):
    if strategy == "pnp":
        return estimate_pose(captures, surface, init="graycode", seed=seed)
    if strategy == "pnp+mask":
        return estimate_pose(captures, surface, init="graycode", iterations=60, seed=seed)
    if strategy == "mask":
        return estimate_pose(captures, surface, init="nominal", seed=seed)
    if strategy == "paper":
        return estimate_pose(captures, surface, init="nominal", method="paper", seed=seed)
    raise SystemExit(f"unknown strategy {strategy!r}; choose from {', '.join(STRATEGIES)}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scale", type=float, default=1.0, help="share of 640×480 / 800×600 (default full resolution)")
    ap.add_argument("--surfaces", default="plane,curve,vedge,hedge")
    ap.add_argument("--effects", default="realistic")
    ap.add_argument("--samples", type=int, default=16, help="Cycles samples of the lab renders")
    ap.add_argument("--strategies", default=",".join(STRATEGIES))
    ap.add_argument("--cache", type=Path, default=Path("/tmp/procam-bench-pose"))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    rows = []
    header = (f"{'surface':8s} {'strategy':9s} {'pos mm':>8s} {'dir °':>7s} {'seconds':>8s} {'loss':>9s}  "
              "sub-steps (pos mm / dir °)")
    print(header, flush=True)
    for surf_name in args.surfaces.split(","):
        caps_dir, truth_path = lab_set(args.cache, surf_name, args.effects, args.scale, args.samples, args.seed)
        captures = CaptureSet.load(caps_dir)
        truth = LabTruth.load(truth_path).rig.projector.camera_from_projector  # evaluation only
        t0 = time.perf_counter()
        depth, offset, _ = scene_depth(captures)  # as calibrate does: the wall image's sensor bias removed
        surface, _ = reconstruct_surface(depth, captures.depth_info.intrinsics, captures.image("surface"),
                                         depth_offset=offset)
        t_surface = time.perf_counter() - t0
        start = pose_error(captures.projector.camera_from_projector, truth)
        print(f"# {surf_name}: nominal start {1000 * start[0]:.0f} mm / {start[1]:.2f}°, surface "
              f"reconstructed in {t_surface:.1f} s", flush=True)
        for strategy in args.strategies.split(","):
            result = run(strategy, captures, surface, args.seed)
            pos, ang = pose_error(result.camera_from_projector, truth)
            subs = "; ".join(f"{k} {1000 * pose_error(v, truth)[0]:.1f}/{pose_error(v, truth)[1]:.3f}"
                             for k, v in result.steps.items() if k != "initial")
            loss = f"{result.losses[-1]:.2e}" if result.losses else "-"
            line = (f"{surf_name:8s} {strategy:9s} {1000 * pos:8.2f} {ang:7.3f} {result.seconds:8.1f} {loss:>9s}  "
                    f"{subs}")
            print(line, flush=True)
            rows.append((surf_name, strategy, pos, ang, result.seconds))
    print("\n# summary: worst over surfaces")
    for strategy in args.strategies.split(","):
        sel = [r for r in rows if r[1] == strategy]
        if sel:
            print(f"{strategy:9s} pos ≤ {1000 * max(r[2] for r in sel):.2f} mm, dir ≤ {max(r[3] for r in sel):.3f}°, "
                  f"seconds ≤ {max(r[4] for r in sel):.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
