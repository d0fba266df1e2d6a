#!/usr/bin/env python3
"""Stage C on the precomputed light-transport operator against the ``fast`` schedule, closed and open loop.

Usage: ``.venv/bin/python scripts/bench_transport.py [--surface curve] [--scale 1] [--targets 6] [--work DIR]``

Renders a lab capture set (``realistic`` effects), calibrates it, precomputes
the operator (seconds, MB), measures how well ``T z`` reproduces Mitsuba's
``f̂(z)`` on held-out inputs (PSNR against a 256-spp render, next to a 16-spp
render's), then compensates each natural target with ``fast`` and with
``transport``, closed loop through the lab and open loop, and evaluates every
result through the lab. Prints the compute seconds per target (without the
lab's own capture time) and the captured PSNR. ``--work DIR`` keeps and
reuses every folder.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from procam.addon.capture.targets import DEFAULT_TARGETS, natural_target
from procam.addon.cli.app import main as procam
from procam.addon.imageio import write_image
from procam.addon.render.forward import ForwardModel
from procam.addon.stages.metrics import psnr
from procam.addon.steps import calibrate as calibrate_step
from procam.addon.steps import transport as transport_step


def step(args: list[str], done: Path) -> None:
    if done.exists():
        return
    if procam(args) != 0:
        raise SystemExit(f"procam {args[0]} failed")


def accuracy(cal_dir: Path) -> list[tuple[str, float, float]]:
    cal = calibrate_step.read(cal_dir)
    op = transport_step.load(cal, bounces=1, seed=0)
    iw, ih = cal.rig.projector.input_size
    reference = ForwardModel(cal.rig, cal.surface, bounces=1, spp=256, smoothing_eps=0.0, clamp=False, seed=991)
    quick = ForwardModel(cal.rig, cal.surface, bounces=1, spp=16, smoothing_eps=0.0, clamp=False, seed=992)
    rows = []
    for name in ("courtyard", "sunrise", "studio"):  # inputs the operator was not built from (it saw lattices)
        z = natural_target(name, (iw, ih))
        ref = reference.render_input(z, seed=991)
        rows.append((name, psnr(np.clip(op.apply(z), 0, 1), np.clip(ref, 0, 1)),
                     psnr(np.clip(quick.render_input(z, seed=992), 0, 1), np.clip(ref, 0, 1))))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--surface", default="curve")
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--targets", type=int, default=6)
    ap.add_argument("--work", type=Path, help="keep the folders here and reuse them")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        lab, truth, cal = work / "lab", work / "lab.truth.json", work / "cal"
        step(["lab", "--surface", args.surface, "--effects", "realistic", "--scale", str(args.scale), "--out",
              str(lab), "--truth", str(truth)], lab)
        step(["calibrate", str(lab), "--out", str(cal)], cal)
        t0 = time.perf_counter()
        step(["precompute", str(cal)], cal / transport_step.REPORT_FILE)
        pre = json.loads((cal / transport_step.REPORT_FILE).read_text())
        print(f"\noperator: {pre['seconds']} s to precompute ({time.perf_counter() - t0:.0f} s this run), "
              f"{pre['megabytes']} MB, lattice every {pre['spacing']}th texel ({pre['direct_renders']} renders), "
              f"{pre['entries_per_pixel']} entries a pixel, indirect {pre['indirect_blocks']} blocks")
        print("\n| Held-out input | T z vs 256 spp | 16-spp Mitsuba vs 256 spp |\n|---|---|---|")
        for name, a, b in accuracy(cal):
            print(f"| {name} | {a:.2f} dB | {b:.2f} dB |")
        (work / "targets").mkdir(exist_ok=True)
        targets = [str(write_image(work / "targets" / f"{n}.png", natural_target(n, (400, 300))))
                   for n in DEFAULT_TARGETS[:args.targets]]
        results = {}
        for loop in ("closed", "open"):
            for schedule in ("fast", "transport"):
                key = f"{schedule}-{loop}"
                comp, ev = work / f"comp-{key}", work / f"eval-{key}"
                device = ["--device", f"lab:{truth}"] if loop == "closed" else []
                step(["compensate", str(cal), *targets, "--schedule", schedule, *device, "--out", str(comp)], comp)
                step(["evaluate", str(cal), "--inputs", str(comp), "--targets", *targets, "--device",
                      f"lab:{truth}", "--out", str(ev)], ev)
                manifest = json.loads((comp / "compensation.json").read_text())
                metrics = json.loads((ev / "metrics.json").read_text())
                compute = {t["name"]: t["seconds_compute"] for t in manifest["targets"]}
                results[key] = {r["name"]: (r["psnr"], compute[r["name"]]) for r in metrics["targets"]}
                results[key]["_ssim"] = float(np.mean([r["ssim"] for r in metrics["targets"]]))
                first = manifest["targets"][0]
                results[key]["_first"] = (first["name"], first.get("seconds_verify") or 0.0,
                                          first.get("operator_vs_mitsuba_psnr"))
                with open(comp / "compensation.json") as fh:
                    reports = json.load(fh)["targets"]
                results[key]["_captures"] = sum(t.get("captures", 0) for t in reports)
        for loop in ("closed", "open"):
            f, t = results[f"fast-{loop}"], results[f"transport-{loop}"]
            print(f"\n{loop} loop, {args.surface}, scale {args.scale}; compute seconds per target, without the lab's "
                  f"captures ({f['_captures']} for fast, {t['_captures']} for transport)\n")
            print("| Target | fast: PSNR | fast: s | transport: PSNR | transport: s | Δ PSNR |\n"
                  "|---|---|---|---|---|---|")
            names = [n for n in f if not n.startswith("_")]
            for n in names:
                print(f"| {n} | {f[n][0]:.2f} | {f[n][1]:.1f} | {t[n][0]:.2f} | {t[n][1]:.2f} | "
                      f"{t[n][0] - f[n][0]:+.2f} |")
            mf, mt = np.mean([f[n][0] for n in names]), np.mean([t[n][0] for n in names])
            print(f"| mean | {mf:.2f} | {np.mean([f[n][1] for n in names]):.1f} | {mt:.2f} | "
                  f"{np.mean([t[n][1] for n in names]):.2f} | {mt - mf:+.2f} |")
            print(f"\nmean SSIM: fast {f['_ssim']:.4f}, transport {t['_ssim']:.4f}")
            name, verify, agree = t["_first"]
            rest = [t[n][1] for n in names if n != name]
            print(f"\ntransport: {np.mean(rest):.2f} s a target after the first (max {max(rest):.2f} s); the first, "
                  f"{name}, {t[name][1]:.2f} s, includes building the area's operator view and the Mitsuba render "
                  f"that checks the operator once per run ({verify:.2f} s; operator vs Mitsuba {agree} dB)")


if __name__ == "__main__":
    main()
