"""Benchmark stage B (warp): checkerboard corner agreement before/after and seconds, per built-in surface.

For each surface it renders a lab capture set with the ``realistic`` effects
(Cycles, 16 samples, no Gray code or validation patterns: stage B needs only
white, black and the two checkerboards, plus depth for the surface), builds the
surface from the set's depth (``reconstruct_surface``, as calibration does),
and runs :func:`procam.addon.stages.warp.estimate_warp` with the projector pose
of the lab truth moved by 5 mm and turned by 0.2° — the residual stage A
leaves, which the warp is there to absorb. ``--pose truth`` uses the true pose,
``--surface truth`` the true mesh. A benchmark may read the lab truth; the
pipeline never does.

    .venv/bin/python scripts/bench_warp.py --scale 0.5
    .venv/bin/python scripts/bench_warp.py --scale 1 --surfaces vedge

Prints one row per surface: corner distances capture ↔ simulation (camera px;
median / max / count) before (M = identity) and after the warp, how well W
inverts M, and seconds for the lab render, the surface and stage B (wall clock, and
the CPU time of all threads: on a shared machine the wall clock says more about
the neighbours than about stage B).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

def perturbed(pose: np.ndarray, offset_m: float, angle_deg: float, seed: int) -> np.ndarray:
    """``pose`` moved by ``offset_m`` and turned by ``angle_deg`` about a random axis (seeded)."""
    from procam.addon.lab.truth import rough_pose

    return rough_pose(pose, np.random.default_rng(seed), offset_m, angle_deg)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scale", type=float, default=0.5, help="resolution scale (1 = camera 640×480, projector 800×600)")
    p.add_argument("--surfaces", default="plane,curve,vedge,hedge")
    p.add_argument("--effects", default="realistic")
    p.add_argument("--samples", type=int, default=16, help="Cycles samples of the lab captures")
    p.add_argument("--pose", choices=("perturbed", "truth"), default="perturbed")
    p.add_argument("--surface", choices=("reconstructed", "truth"), default="reconstructed")
    p.add_argument("--offset-mm", type=float, default=5.0)
    p.add_argument("--angle-deg", type=float, default=0.2)
    p.add_argument("--iterations", type=int, default=None)
    p.add_argument("--spp", type=int, default=None)
    p.add_argument("--work", type=Path, default=None, help="keep the lab sets here (default: a temporary folder)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    from procam.addon.capture.format import CaptureSet
    from procam.addon.lab.truth import LabTruth, make_truth
    from procam.addon.lab.lab import run_lab
    from procam.addon.rig.model import Rig
    from procam.addon.stages.surface import scene_depth
    from procam.addon.stages.warp import estimate_warp
    from procam.addon.surface.reconstruct import reconstruct_surface

    kwargs = {k: v for k, v in (("iterations", args.iterations), ("spp", args.spp)) if v is not None}
    work = args.work or Path(tempfile.mkdtemp(prefix="procam-bench-warp-"))
    work.mkdir(parents=True, exist_ok=True)
    cam = (round(640 * args.scale), round(480 * args.scale))
    proj = (round(800 * args.scale), round(600 * args.scale))
    print(f"stage B bench: camera {cam[0]}×{cam[1]}, projector {proj[0]}×{proj[1]}, effects {args.effects!r}, "
          f"pose {args.pose}" + (f" ({args.offset_mm} mm, {args.angle_deg}°)" if args.pose == "perturbed" else "")
          + f", surface {args.surface}, {kwargs or 'default settings'}", flush=True)
    names = [s.strip() for s in args.surfaces.split(",") if s.strip()]
    # Render every lab set before any reconstruction: once pymeshlab is loaded, bpy no longer imports
    # (both bundle Embree; bpy then misses a symbol), so all Cycles work comes first.
    lab_seconds: dict[str, float] = {}
    for name in names:
        root = work / f"{name}_{args.scale:g}"
        t0 = time.perf_counter()
        if not (root / "captures" / "capture.json").is_file():
            root.mkdir(parents=True, exist_ok=True)
            truth = make_truth(name, effects=args.effects, seed=args.seed, samples=args.samples, camera_size=cam,
                               projector_size=proj)
            run_lab(truth, root / "captures", truth_path=root / "truth.json", graycode=False, validation=False,
                    force=True)
        lab_seconds[name] = time.perf_counter() - t0

    header = (f"{'surface':8} {'before med/max px':>18} {'after med/max px':>17} {'n':>4} {'W∘M px':>7} "
              f"{'lab s':>6} {'surf s':>6} {'B s':>6} {'B cpu s':>7} {'loss':>13}")
    print(header, flush=True)
    for name in names:
        root = work / f"{name}_{args.scale:g}"
        captures = CaptureSet.load(root / "captures")
        truth = LabTruth.load(root / "truth.json")
        t0 = time.perf_counter()
        if args.surface == "truth":
            surface = truth.surface
        else:
            depth, offset, _ = scene_depth(captures)  # as calibrate does: the wall image's sensor bias removed
            surface, _ = reconstruct_surface(depth, captures.camera.intrinsics, captures.image("surface"),
                                             depth_offset=offset)
        t_surf = time.perf_counter() - t0
        pose = truth.rig.projector.camera_from_projector
        if args.pose == "perturbed":
            pose = perturbed(pose, args.offset_mm / 1000, args.angle_deg, args.seed + 17)
        rig = Rig(captures.camera, captures.projector.with_pose(pose))
        cpu0 = time.process_time()
        result = estimate_warp(captures, surface, rig, seed=args.seed, **kwargs)
        cpu = time.process_time() - cpu0
        b, a = result.corners_before_px, result.corners_after_px
        row = (f"{name:8} {b['median']:8.2f} /{b['max']:6.2f}   {a['median']:7.2f} /{a['max']:6.2f} {a['n']:4d} "
               f"{result.inverse_error_px:7.3f} {lab_seconds[name]:6.0f} {t_surf:6.1f} {result.seconds:6.1f} "
               f"{cpu:7.1f} {result.losses[0]:.4f}→{result.losses[-1]:.4f}")
        print(row, flush=True)
    print(f"\nlab sets in {work}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
