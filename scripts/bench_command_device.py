#!/usr/bin/env python3
"""Closed loop through the command device in the lab against the lab device directly: same targets, same schedule.

Usage: ``.venv/bin/python scripts/bench_command_device.py [--surface vedge] [--scale 0.3] [--samples 8]
[--targets city,forest,interior] [--schedule transport] [--iterations N] [--work DIR]``

Renders a lab capture set, calibrates it (``procam calibrate``), then compensates the same targets twice with the
same schedule: once through ``lab:TRUTH`` (the lab device, in process) and once through
``command:run='python -m procam.addon.lab.shoot --truth TRUTH --frame {frame} --out {out} --shot {n}'`` (a new
process per photograph, the frame handed over as a 16-bit PNG, the photograph read back as a 16-bit PNG, as a rig
driven by other software would). Both sets of inputs are then evaluated through the lab device (same seed), so the
captured PSNR compares the two loops alone. Prints a table (per target: captured PSNR of each, the difference) and
the seconds each loop took; the figure is the largest difference, which should stay within 0.2 dB (the photographs'
noise differs: the command device's shots are numbered after its three opening shots).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
import time
from pathlib import Path

from procam.addon.capture.targets import natural_target
from procam.addon.cli.app import main as procam
from procam.addon.imageio import write_image


def shoot_command(truth: Path, samples: int | None) -> str:
    """The ``command:`` device spec that renders each frame through the lab in a fresh process."""
    parts = [sys.executable, "-m", "procam.addon.lab.shoot", "--truth", str(truth), "--frame", "{frame}",
             "--out", "{out}", "--shot", "{n}"]
    if samples is not None:
        parts += ["--samples", str(samples)]
    return f"command:run={shlex.join(parts)},suffix=png"


def run(args: argparse.Namespace, work: Path) -> list[dict[str, float | str]]:
    truth = work / "lab.truth.json"
    steps = [["lab", "--surface", args.surface, "--scale", str(args.scale), "--samples", str(args.samples),
              "--out", str(work / "lab"), "--truth", str(truth)],
             ["calibrate", str(work / "lab"), "--out", str(work / "cal"), "--no-blend-output"],
             ["precompute", str(work / "cal")]]
    for step in steps:
        if procam(step) != 0:
            raise SystemExit(f"procam {step[0]} failed")
    names = args.targets.split(",")
    targets = [str(write_image(work / f"{n}.png", natural_target(n, (160, 120)))) for n in names]
    schedule = ["--schedule", args.schedule] + (["--iterations", str(args.iterations)] if args.iterations else [])
    seconds = {}
    for label, device in (("lab", f"lab:{truth}"), ("command", shoot_command(truth, None))):
        t0 = time.perf_counter()
        if procam(["compensate", str(work / "cal"), *targets, "--device", device, *schedule,
                   "--out", str(work / f"comp-{label}")]) != 0:
            raise SystemExit(f"compensate through the {label} device failed")
        seconds[label] = time.perf_counter() - t0
        if procam(["evaluate", str(work / "cal"), "--inputs", str(work / f"comp-{label}"), "--targets", *targets,
                   "--device", f"lab:{truth}", "--out", str(work / f"eval-{label}")]) != 0:
            raise SystemExit(f"evaluating the {label} loop's inputs failed")
    rows = []
    scores = {label: {t["name"]: t for t in json.loads((work / f"eval-{label}" / "metrics.json").read_text())
                      ["targets"]} for label in ("lab", "command")}
    for name in scores["lab"]:
        lab, cmd = scores["lab"][name], scores["command"][name]
        rows.append({"target": name, "uncompensated": lab["uncompensated"]["psnr"], "lab": lab["psnr"],
                     "command": cmd["psnr"], "difference": cmd["psnr"] - lab["psnr"]})
    print(f"{args.surface}, scale {args.scale} ({args.samples} spp), schedule {args.schedule}; loops took "
          f"{seconds['lab']:.0f} s (lab device) and {seconds['command']:.0f} s (command device)")
    print("| target | uncompensated | closed loop, lab device | closed loop, command device | difference |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['target']} | {r['uncompensated']:.2f} dB | {r['lab']:.2f} dB | {r['command']:.2f} dB | "
              f"{r['difference']:+.2f} dB |")
    worst = max(abs(float(r["difference"])) for r in rows)
    print(f"largest difference {worst:.3f} dB ({'within' if worst <= 0.2 else 'beyond'} 0.2 dB)")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--surface", default="vedge")
    ap.add_argument("--scale", type=float, default=0.3)
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--targets", default="city,forest,interior")
    ap.add_argument("--schedule", default="transport")
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--work", type=Path, default=None, help="keep the run's folders here (default: a temporary one)")
    args = ap.parse_args()
    if args.work is not None:
        args.work.mkdir(parents=True, exist_ok=True)
        run(args, args.work)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            run(args, Path(tmp))


if __name__ == "__main__":
    main()
