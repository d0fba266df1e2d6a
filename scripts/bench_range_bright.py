#!/usr/bin/env python3
"""How bright a show stays: ``--range none``, ``auto`` and ``bright`` on the four lab surfaces.

Usage: ``.venv/bin/python scripts/bench_range_bright.py [--surfaces plane,curve,vedge,hedge] [--scale 0.3]
[--iterations 20] [--full] [--work DIR]``

For each surface: renders a lab capture set (``realistic`` effects), calibrates it, and compensates six natural
photographs at full brightness (each scaled so its 99.5th percentile is 1, as ``bench_range.py``) closed loop
through the lab with each range rule, then evaluates. Prints per surface and rule the brightness kept (the mean
mapped white over the display area as a share of the targets' white), the plain PSNR (against the mapped targets,
what the README's older tables give) and the PSNR relative to the mapped white (the capture read back through the
map against the targets as given: comparable across rules), each the mean over the six photographs, and the
share of the targets' values the map clips. ``--scale 0.3`` (default) runs in minutes on two cores; ``--full``
is the lab's full scale (1) with 60 iterations. ``--work DIR`` keeps and reuses every folder.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

from procam.addon.capture.targets import DEFAULT_TARGETS, natural_target
from procam.addon.cli.app import main as procam
from procam.addon.imageio import write_image

RULES = ("none", "auto", "bright")


def step(args: list[str], done: Path) -> None:
    if done.exists():
        return
    if procam(args) != 0:
        raise SystemExit(f"procam {args[0]} failed")


def surface_rows(surface: str, work: Path, scale: float, iterations: int) -> dict[str, dict]:
    """The metrics.json of each rule's evaluation on one surface."""
    work.mkdir(parents=True, exist_ok=True)
    lab, truth = work / "lab", work / "lab.truth.json"
    step(["lab", "--surface", surface, "--effects", "realistic", "--scale", str(scale), "--out", str(lab),
          "--truth", str(truth)], lab)
    step(["calibrate", str(lab), "--out", str(work / "cal")], work / "cal")
    (work / "targets").mkdir(exist_ok=True)
    targets = []
    for name in DEFAULT_TARGETS:
        img = natural_target(name, (400, 300))
        img = np.clip(img / max(float(np.percentile(img, 99.5)), 1e-6), 0.0, 1.0)
        targets.append(str(write_image(work / "targets" / f"{name}.png", img)))
    rows = {}
    for rule in RULES:
        comp, ev = work / f"comp-{rule}", work / f"eval-{rule}"
        step(["compensate", str(work / "cal"), *targets, "--device", f"lab:{truth}", "--iterations", str(iterations),
              "--range", rule, "--out", str(comp)], comp)
        step(["evaluate", str(work / "cal"), "--inputs", str(comp), "--targets", *targets, "--device",
              f"lab:{truth}", "--no-repeat", "--out", str(ev)], ev)
        rows[rule] = json.loads((ev / "metrics.json").read_text())
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--surfaces", default="plane,curve,vedge,hedge")
    ap.add_argument("--scale", type=float, default=0.3)
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--full", action="store_true", help="the lab's full scale (1) and 60 iterations")
    ap.add_argument("--work", type=Path, help="keep the folders here and reuse them")
    args = ap.parse_args()
    scale, iterations = (1.0, 60) if args.full else (args.scale, args.iterations)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        table = []
        for surface in args.surfaces.split(","):
            rows = surface_rows(surface, work / surface, scale, iterations)
            for rule in RULES:
                doc = rows[rule]
                r = doc.get("range") or {}
                kept = doc.get("brightness_kept")
                clipped = r.get("clipped_share")
                table.append(f"| {surface} | `{rule}` | {100 * kept:.0f} % | {doc['mean']['psnr']:.2f} | "
                             f"{doc['mean_psnr_relative']:.2f} | "
                             + ("–" if clipped is None else f"{100 * clipped:.2f} %") + " |")
            print(f"{surface}: done", flush=True)
        print(f"\nlab `realistic` effects, scale {scale}, {iterations} iterations, closed loop, six photographs at "
              "full brightness (means over the six)\n")
        print("| Surface | `--range` | brightness kept | PSNR vs mapped target (dB) | PSNR relative to the mapped "
              "white (dB) | values clipped by the map |")
        print("|---|---|---|---|---|---|")
        print("\n".join(table))


if __name__ == "__main__":
    main()
