"""Benchmark stage C: seconds per target and quality, the paper's schedule against the faster levers.

Builds (or reuses, ``--lab-dir``) a lab capture set of the demo rig with the
``realistic`` effects and its calibration (lab → ``calibrate``, as the demo
does), then compensates natural targets closed loop through the lab device
with the paper's 500-step schedule and with each lever of the fast schedule
added cumulatively (:data:`procam.addon.stages.compensate.LEVERS`). Each
result is measured by projecting it in the lab: PSNR inside the display area
of the capture (and of the model's own prediction, ``clip(f̂(z) − θ)``).

Seconds: ``compute`` is stage C without the time spent waiting for the device
(the Cycles lab needs ~10 CPU-s per capture at full resolution, a real camera
~0.1 s); ``wall`` includes it. ``compute CPU-s`` is the CPU time of all
threads without the device's: on a shared machine the wall clock says as much
about the neighbours as about stage C, and on 2 idle cores compute wall ≈
CPU-s / 2. The first target of a schedule also pays the
kernel compilation unless an earlier run warmed it: all schedules run in one
process with one Compensator, and a warm-up run at the start compiles the
kernels of both resolutions so that no row carries them.

    .venv/bin/python scripts/bench_stage_c.py --scale 0.5 --targets city --lab-dir /tmp/stage-c-0.5
    .venv/bin/python scripts/bench_stage_c.py --scale 1 --targets city,forest --lab-dir /tmp/stage-c-1 \\
        --out stage_c.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from procam.addon.stages.compensate import Schedule


def prepare(lab_dir: Path, surface: str, scale: float, samples: int, seed: int) -> tuple[Path, Path, Path, dict]:
    """The lab capture set, its truth and its calibration under ``lab_dir`` (built when missing)."""
    import bpy  # noqa: F401  (bpy before pymeshlab: both bundle Embree, see scripts/bench_warp.py)

    from procam.addon.lab.truth import make_truth
    from procam.addon.lab.lab import run_lab
    from procam.addon.steps.calibrate import CalibrateOptions
    from procam.addon.steps.calibrate import run as run_calibration

    captures, truth_path, cal_dir = lab_dir / "captures", lab_dir / "truth.json", lab_dir / "calibration"
    seconds: dict[str, float] = {}
    if not (captures / "capture.json").is_file() or not truth_path.is_file():
        t0 = time.perf_counter()
        cam = (round(640 * scale), round(480 * scale))
        proj = (round(800 * scale), round(600 * scale))
        print(f"lab: rendering {surface}, realistic, camera {cam[0]}×{cam[1]}, projector {proj[0]}×{proj[1]} "
              f"into {lab_dir}", flush=True)
        truth = make_truth(surface, effects="realistic", seed=seed, samples=samples, camera_size=cam,
                           projector_size=proj)
        run_lab(truth, captures, truth_path=truth_path, force=True)
        seconds["lab"] = time.perf_counter() - t0
    if not (cal_dir / "calibration.json").is_file():
        t0 = time.perf_counter()
        print("calibrate: surface, stage A, stage B", flush=True)
        run_calibration(CalibrateOptions(captures, cal_dir, seed=seed, with_blend=False, force=True))
        seconds["calibrate"] = time.perf_counter() - t0
    return captures, truth_path, cal_dir, seconds


class TimedDevice:
    """A device wrapper that adds up the CPU time of its captures (the lab renders with Cycles in this process,
    so the process's CPU time holds both; stage C's own CPU time is the difference)."""

    def __init__(self, device: object) -> None:
        self.device = device
        self.projector = device.projector
        self.cpu = 0.0

    def project(self, frame: np.ndarray) -> np.ndarray:
        c = time.process_time()
        try:
            return self.device.project(frame)
        finally:
            self.cpu += time.process_time() - c

    def close(self) -> None:
        self.device.close()


def levers() -> list[tuple[str, Schedule]]:
    """The paper's schedule, then each lever of the fast one added on top of the previous row (the last row is
    ``fast``), then the earlier fast schedule (coarse-to-fine z, plateau stop, 1 spp, cosine lr) for comparison."""
    from procam.addon.stages.compensate import SCHEDULES, Schedule

    paper, fast = SCHEDULES["paper"], SCHEDULES["fast"]
    rows = [("paper (200 z + 300 joint)", paper)]
    s = replace(paper, name="fixed-point", iterations_z=fast.iterations_z, fixed_point=fast.fixed_point,
                fixed_point_spp=fast.fixed_point_spp)
    rows.append((f"+ {fast.fixed_point} fixed-point steps ({fast.fixed_point_spp}-spp forward renders) instead of "
                 f"{paper.iterations_z} Adam z iterations", s))
    s = replace(s, name="crop", crop=fast.crop)
    rows.append(("+ render only the display area", s))
    s = replace(s, name="captures", iterations_joint=fast.iterations_joint, capture_every=fast.capture_every,
                captures=fast.captures, alpha=fast.alpha)
    rows.append((f"+ joint {fast.iterations_joint} its, {fast.captures} captures, one every {fast.capture_interval} "
                 "(α matched)", s))
    s = replace(s, name="fast", fixed_point_joint=fast.fixed_point_joint, reference_spp=fast.reference_spp)
    rows.append((f"+ {fast.fixed_point_joint} fixed-point steps after each capture (= fast)", s))
    assert s == fast, "the last cumulative row must be the fast schedule"
    rows.append(("earlier fast: coarse z at 0.5×, plateau stop, 1 spp z, cosine lr, 9-spp references",
                 Schedule("coarse", iterations_z=60, iterations_joint=45, lr_end=0.001, alpha=None, capture_every=3,
                          captures=15, plateau=5, plateau_tol=0.02, spp_z=1, coarse=0.5, iterations_coarse=40,
                          reference_spp=9)))
    return rows


def summarise(results: list[dict], rows: list[tuple[str, Schedule]]) -> list[dict]:
    """One row per schedule (in lever order): means over the targets it ran on."""
    table = []
    for label, sched in (r for r in levers() if r in rows):
        mine = [r for r in results if r["schedule"] == sched.name]
        if not mine:
            continue
        table.append({"schedule": sched.name, "label": label, "targets": len(mine),
                      "iterations": float(np.mean([r["iterations"]["total"] for r in mine])),
                      "fixed_point": float(np.mean([r["iterations"].get("fixed_point", 0) for r in mine])),
                      "captures": float(np.mean([r["captures"] for r in mine])),
                      **{k: float(np.mean([r[k] for r in mine]))
                         for k in ("compute_s", "compute_cpu_s", "wall_s", "model_psnr", "captured_psnr",
                                   "captured_ssim")}})
    return table


def markdown(table: list[dict]) -> str:
    lines = ["| schedule | targets | Adam iterations | fixed-point steps | captures | compute s/target "
             "| compute CPU-s/target | wall s/target (lab) | model PSNR | captured PSNR | captured SSIM |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for t in table:
        lines.append(f"| {t['label']} | {t['targets']} | {t['iterations']:.0f} | {t['fixed_point']:.0f} | "
                     f"{t['captures']:.0f} | "
                     f"{t['compute_s']:.1f} | {t['compute_cpu_s']:.1f} | {t['wall_s']:.1f} | {t['model_psnr']:.2f} | "
                     f"{t['captured_psnr']:.2f} | {t['captured_ssim']:.3f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scale", type=float, default=1.0,
                   help="resolution scale (1 = camera 640×480, projector 800×600)")
    p.add_argument("--surface", default="vedge", choices=("plane", "curve", "vedge", "hedge"))
    p.add_argument("--targets", default="city,forest", help="built-in natural targets, comma-separated")
    p.add_argument("--schedules", default=None,
                   help="rows to run, comma-separated, run in this order (default: all; names: paper, "
                        "fixed-point, crop, captures, fast, coarse)")
    p.add_argument("--lab-dir", type=Path, default=None,
                   help="folder of the lab set + calibration (reused when present; default: /tmp/procam-bench-stage-c-"
                        "SURFACE-SCALE)")
    p.add_argument("--samples", type=int, default=16, help="Cycles samples of the lab")
    p.add_argument("--prepare-only", action="store_true", help="build the lab set and calibration, then stop")
    p.add_argument("--out", type=Path, default=None, help="write the table as JSON here")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    lab_dir = args.lab_dir or Path(f"/tmp/procam-bench-stage-c-{args.surface}-{args.scale:g}")
    lab_dir.mkdir(parents=True, exist_ok=True)
    captures, truth_path, cal_dir, prep_seconds = prepare(lab_dir, args.surface, args.scale, args.samples, args.seed)
    for k, v in prep_seconds.items():
        print(f"{k}: {v:.0f} s", flush=True)
    if args.prepare_only:
        return 0

    from procam.addon.capture.targets import natural_target
    from procam.addon.imageio import write_atomic_bytes
    from procam.addon.lab.truth import LabTruth
    from procam.addon.lab.cycles_device import LabDevice
    from procam.addon.steps.calibrate import read as read_calibration
    from procam.addon.stages.compensate import Compensator, area_psnr
    from procam.addon.stages.display_area import choose_area, fit_target
    from procam.addon.stages.metrics import ssim

    rows = levers()
    if args.schedules:
        wanted = [w.strip() for w in args.schedules.split(",") if w.strip()]
        by_name = {r[1].name: r for r in rows}
        rows = [by_name[w] for w in wanted if w in by_name]  # in the order asked (the table keeps lever order)
        if not rows:
            raise SystemExit(f"no schedule among {wanted}; names: {', '.join(s.name for _, s in levers())}")
    cal = read_calibration(cal_dir)
    truth = LabTruth.load(truth_path)  # the bench may read the truth (for the lab device); the pipeline never does
    area = choose_area(cal, aspect=4 / 3)
    names = [n.strip() for n in args.targets.split(",") if n.strip()]
    targets = {n: fit_target(natural_target(n, area.size), area) for n in names}
    cam = cal.rig.camera.intrinsics.size
    print(f"stage C bench: {args.surface}, camera {cam[0]}×{cam[1]}, bounces 1, 4 spp, closed loop through the lab "
          f"({truth.samples} Cycles samples), area {area.width}×{area.height}, targets {', '.join(names)}; "
          f"load: {os.getloadavg()[0]:.1f} {os.getloadavg()[1]:.1f} {os.getloadavg()[2]:.1f}", flush=True)
    def save(path: Path, results: list[dict], rows: list) -> None:
        """The table so far as JSON (after every run, so an interrupted bench keeps what it measured)."""
        doc = {"surface": args.surface, "scale": args.scale, "camera": list(cam), "targets": names,
               "area": area.to_dict(), "bounces": 1, "spp": 4, "lab_samples": truth.samples,
               "uncompensated_psnr": plain, "scene_load_s": t_load, "warm_up_s": t_warm,
               "load_average": os.getloadavg(), "table": summarise(results, rows), "runs": results}
        write_atomic_bytes(path, (json.dumps(doc, indent=1) + "\n").encode())

    plain: dict[str, float] = {}
    t_load = t_warm = 0.0
    device = TimedDevice(LabDevice(truth))
    results: list[dict] = []
    try:
        t0 = time.perf_counter()
        comp = Compensator(cal, bounces=1, spp=4, seed=args.seed)
        t_load = time.perf_counter() - t0
        # Warm-up: build the coarse model and compile every kernel the rows use (spp 1/4/9/16, both sizes),
        # and the per-compensator caches (white image, ray-cast correspondence), so no row carries them.
        t0 = time.perf_counter()
        first = targets[names[0]]
        for _, sched in rows:
            comp.run(first, area, schedule=replace(sched, iterations_z=min(2, sched.iterations_z),
                                                   iterations_coarse=min(1, sched.iterations_coarse),
                                                   iterations_joint=0, fixed_point=min(1, sched.fixed_point)),
                     use_bias=False, name="warm-up")
        comp.simulate(np.zeros((comp.ih, comp.iw, 3), np.float32), spp=9)
        t_warm = time.perf_counter() - t0
        print(f"scene load {t_load:.1f} s, warm-up (kernels, caches) {t_warm:.1f} s", flush=True)
        for n, target in targets.items():
            placed = area.place(target, comp.camera_size)
            x = comp.warp_w(comp.initial_input(placed, how="geometric"))
            plain[n] = area_psnr(device.project(cal.rig.projector.frame_from_input(x)), placed, area)
            print(f"{n}: uncompensated (geometry only) captured PSNR {plain[n]:.2f} dB", flush=True)
        for label, sched in rows:
            for n, target in targets.items():
                cpu0, dev0 = time.process_time(), device.cpu
                res = comp.run(target, area, device=device, schedule=sched, name=n)
                cpu = time.process_time() - cpu0 - (device.cpu - dev0)
                shot = device.project(res.x_frame)
                row = {"schedule": sched.name, "label": label, "target": n, "iterations": res.report["iterations"],
                       "phases": res.report["phases"], "captures": res.captures,
                       "compute_s": res.report["seconds_compute"], "compute_cpu_s": round(cpu, 2),
                       "wall_s": round(res.seconds, 2),
                       "device_s": res.report["seconds_device"], "model_psnr": res.report["psnr_simulated"],
                       "captured_psnr": area_psnr(shot, res.target, area),
                       "captured_ssim": ssim(area.crop(shot), area.crop(res.target)),
                       "uncompensated_psnr": plain[n]}
                results.append(row)
                if args.out:
                    save(args.out, results, rows)
                print(f"{sched.name:11s} {n:10s} its {row['iterations']['total']:4d} "
                      f"(+{row['iterations'].get('fixed_point', 0)} fixed-point) captures {row['captures']:3d} "
                      f"compute {row['compute_s']:6.1f} s ({row['compute_cpu_s']:6.1f} CPU-s) "
                      f"wall {row['wall_s']:6.1f} s model {row['model_psnr']:6.2f} "
                      f"captured {row['captured_psnr']:6.2f} dB", flush=True)
    finally:
        device.close()

    table = summarise(results, rows)
    print(f"\nuncompensated captured PSNR: {float(np.mean(list(plain.values()))):.2f} dB (mean); "
          f"load at the end: {os.getloadavg()[0]:.1f} {os.getloadavg()[1]:.1f} {os.getloadavg()[2]:.1f}")
    print(markdown(table))
    if args.out:
        save(args.out, results, rows)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
