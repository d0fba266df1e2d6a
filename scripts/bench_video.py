#!/usr/bin/env python3
"""A small lab show: warm against cold start (seconds per frame, model PSNR, flicker), and a local cluster.

Usage: ``.venv/bin/python scripts/bench_video.py [--frames 8] [--chunk 4] [--iterations 40] [--workers 2]
[--scale 0.3] [--threads 1] [--schedule fast] [--runs warm,cold,cluster] [--no-evaluate] [--work DIR]``

Renders a small lab capture set (``vedge``) and takes its true calibration
(as the tests do, so only stage C is timed), makes a panning sequence of a
natural photograph (a slow camera move: consecutive frames differ little),
and compensates it open loop with ``procam show`` three times: warm start in
this process, ``--cold-start`` in this process, and warm start on a local
cluster of ``--workers`` processes (whose frames must be byte-identical to the
first run's: every run uses ``--threads`` Dr.Jit threads per process). Then
``procam evaluate`` projects the warm and cold shows through the lab and
reports their flicker. Prints one Markdown row per run,
with frames per second (wall, whole ``procam show``). ``--schedule transport``
precomputes the calibration's light-transport operator first (its seconds are
printed apart). ``--runs`` picks the runs and ``--no-evaluate`` skips the lab
evaluation, for throughput on long clips (``--frames 300``).
``--work DIR`` keeps the folders (and reuses the lab and the targets).
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from procam.addon.capture.targets import natural_target
from procam.addon.cli.app import main as procam
from procam.addon.imageio import write_image


def _lab(work: Path, scale: float) -> tuple[Path, Path]:
    """The lab capture set and a calibration folder holding its truth (true rig, surface, identity warp)."""
    from procam.addon.lab.truth import LabTruth, make_truth
    from procam.addon.lab.lab import run_lab
    from procam.addon.stages.calibrate import Calibration
    from procam.addon.stages.warp_model import Warp
    from procam.addon.steps import calibrate as calibrate_step

    captures, truth_path, cal_dir = work / "captures", work / "truth.json", work / "cal"
    if not truth_path.is_file():
        truth = make_truth("vedge", samples=8, camera_size=(round(640 * scale), round(480 * scale)),
                           projector_size=(round(800 * scale), round(600 * scale)))
        run_lab(truth, captures, truth_path=truth_path, graycode=True)
    if not cal_dir.is_dir():
        truth = LabTruth.load(truth_path)
        cal_dir.mkdir()
        calibrate_step.write(cal_dir, Calibration(truth.rig, truth.surface,
                                                  Warp.identity(truth.rig.projector.input_size), str(captures)),
                             {})
    return cal_dir, truth_path


def _targets(folder: Path, frames: int) -> list[str]:
    """A slow pan over a photograph: frame i is a 320×240 window moved 4 pixels right per frame."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = [folder / f"pan_{i + 1:04d}.png" for i in range(frames)]
    if not all(p.is_file() for p in paths):
        wide = natural_target("city", (320 + 4 * frames, 240))
        for i, p in enumerate(paths):
            write_image(p, wide[:, 4 * i:4 * i + 320])
    return [str(p) for p in paths]


def _show(args: list[str], out: Path) -> tuple[float, dict]:
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    if procam(["show", *args, "--out", str(out)]) != 0:
        raise SystemExit("procam show failed")
    return time.perf_counter() - t0, json.loads((out / "show.json").read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--chunk", type=int, default=4)
    ap.add_argument("--iterations", type=int, help="stage C's iterations per frame (default: the schedule's)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--scale", type=float, default=0.3)
    ap.add_argument("--threads", type=int, default=1, help="Dr.Jit threads per process, the same in every run")
    ap.add_argument("--schedule", default="fast", help="stage C's schedule (fast, transport, paper)")
    ap.add_argument("--runs", default="warm,cold,cluster", help="which runs: warm, cold, cluster")
    ap.add_argument("--no-evaluate", action="store_true", help="skip projecting the shows through the lab")
    ap.add_argument("--work", type=Path, help="keep the folders here and reuse the lab and targets")
    args = ap.parse_args()
    wanted = set(args.runs.split(","))
    if not wanted or wanted - {"warm", "cold", "cluster"}:
        raise SystemExit("--runs takes warm, cold and cluster, separated by commas")
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        cal, truth = _lab(work, args.scale)
        targets = _targets(work / "targets", args.frames)
        if args.schedule == "transport":
            t0 = time.perf_counter()
            if procam(["precompute", str(cal)]) != 0:
                raise SystemExit("procam precompute failed")
            doc = json.loads((cal / "transport.json").read_text())
            print(f"\noperator: {doc['seconds']} s to precompute, {doc['megabytes']} MB "
                  f"({time.perf_counter() - t0:.1f} s this run, 0 when it was there)")
        common = [str(cal), str(work / "targets"), "--schedule", args.schedule, "--chunk", str(args.chunk),
                  "--threads", str(args.threads)]
        if args.iterations is not None:
            common += ["--iterations", str(args.iterations)]
        runs = {}
        if "warm" in wanted:
            runs["warm"] = _show(common, work / "warm")
        if "cold" in wanted:
            runs["cold"] = _show([*common, "--cold-start"], work / "cold")
        if "cluster" in wanted:
            runs[f"warm, {args.workers} workers"] = _show([*common, "--workers", str(args.workers)], work / "cluster")
        same = all((work / "warm" / p.name).read_bytes() == p.read_bytes() for p in (work / "cluster").glob("frame_*")
                   ) if "warm" in runs and "cluster" in wanted else "not compared"
        flicker = {}
        for name in () if args.no_evaluate else [r for r in ("warm", "cold") if r in runs]:
            ev = work / f"eval-{name}"
            shutil.rmtree(ev, ignore_errors=True)
            if procam(["evaluate", str(cal), "--inputs", str(work / name), "--targets", *targets, "--device",
                       f"lab:{truth}", "--out", str(ev)]) != 0:
                raise SystemExit("procam evaluate failed")
            flicker[name] = json.loads((ev / "metrics.json").read_text())
        iterations = args.iterations if args.iterations is not None else "the schedule's"
        print(f"\n{args.frames} frames (a 4 px/frame pan), schedule {args.schedule}, chunks of {args.chunk}, "
              f"{iterations} iterations, open loop, lab scale {args.scale}, {args.threads} Dr.Jit thread(s) per "
              f"process; cluster frames byte-identical to the warm run: {same}\n")
        print("| Run | wall s | frames/s | stage C s/frame | model PSNR start → end (dB) | captured PSNR (dB) | "
              "flicker captured / targets / excess |")
        print("|---|---|---|---|---|---|---|")
        for name, (wall, doc) in runs.items():
            done = [e for e in doc["frames"].values() if e["status"] == "done"]
            sec = np.mean([e["seconds"] for e in done])
            start, end = np.mean([e["psnr_model_start"] for e in done]), np.mean([e["psnr_model"] for e in done])
            m = flicker.get(name.split(",")[0]) if "workers" not in name else None
            extra = (f"{m['mean']['psnr']:.2f} | {m['flicker']['captured']:.4f} / {m['flicker']['targets']:.4f} / "
                     f"{m['flicker']['excess']:+.4f}") if m else \
                ("(same frames as warm) | " if "workers" in name and same is True else "not evaluated | ")
            print(f"| {name} | {wall:.1f} | {len(done) / wall:.2f} | {sec:.2f} | {start:.2f} → {end:.2f} | {extra} |")


if __name__ == "__main__":
    main()
