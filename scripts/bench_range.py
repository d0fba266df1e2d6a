#!/usr/bin/env python3
"""Bright content and the projector's range: compensation with ``--range none`` against ``--range auto``.

Usage: ``.venv/bin/python scripts/bench_range.py [--surface curve] [--scale 0.5] [--iterations 60] [--effects auto]
[--diagnose-scale 1] [--lab-effects realistic,defocus=0] [--work DIR]``

Renders a lab capture set (``realistic`` effects, or ``--lab-effects``), calibrates it, and
compensates six natural photographs at full brightness (each scaled so its
99.5th percentile is 1, the case where compensation clips) closed loop through
the lab, once as they are and once with ``--range auto``; then evaluates both.
Prints, per target, the range ceiling (the target clipped per pixel to the
captured [black, white]: what no input can beat), the noise ceiling (that
clipped target as a capture scores it through the camera's noise, measured
from two captures of each compensated input) and the PSNR reached, for both,
and the show's gain and offset, and where the error lies: how much of it is finer than 1.5 camera
pixels, for the capture and for what stage C's own model predicted. ``--effects auto`` diagnoses the
calibration first and compensates with the effects it selected around stage C.
``--work DIR`` keeps and reuses every folder.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from procam.addon.capture.targets import DEFAULT_TARGETS, natural_target
from procam.addon.cli.app import main as procam
from procam.addon.imageio import write_image


def step(args: list[str], done: Path) -> None:
    if done.exists():
        return
    if procam(args) != 0:
        raise SystemExit(f"procam {args[0]} failed")


def full_brightness_targets(folder: Path) -> list[str]:
    """The six natural photographs at 400×300 in ``folder``, each scaled so its 99.5th percentile is 1 (the case
    where compensation clips); their paths."""
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for name in DEFAULT_TARGETS:
        img = natural_target(name, (400, 300))
        img = np.clip(img / max(float(np.percentile(img, 99.5)), 1e-6), 0.0, 1.0)
        out.append(str(write_image(folder / f"{name}.png", img)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--surface", default="curve")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--iterations", type=int, default=60)
    ap.add_argument("--lab-effects", default="realistic",
                    help="the lab's effects (procam lab --effects), e.g. realistic,defocus=0 to withhold one")
    ap.add_argument("--effects", choices=("none", "auto"), default="none",
                    help="auto: run procam diagnose and compensate with the effects it selected")
    ap.add_argument("--diagnose-scale", type=float, default=None,
                    help="with --effects auto: procam diagnose's --scale (default its own); 1 looks at every "
                         "camera pixel, where half scale can miss a projector blur of about a texel")
    ap.add_argument("--camera-rig", type=Path, default=None,
                    help="a rig calibration of the lab's demo rig (procam lab-board, then procam calibrate-rig) at "
                         "any scale: its camera lens is taken out of the lab's capture set (procam "
                         "undistort-captures, K scaled to the set's size) before calibrating, and so out of every "
                         "lab capture after")
    ap.add_argument("--work", type=Path, help="keep the folders here and reuse them")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        lab, truth = work / "lab", work / "lab.truth.json"
        step(["lab", "--surface", args.surface, "--effects", args.lab_effects, "--scale", str(args.scale), "--out",
              str(lab), "--truth", str(truth)], lab)
        if args.camera_rig is not None:
            rig = scaled_rig_file(args.camera_rig, json.loads((lab / "capture.json").read_text())["camera"],
                                  work / "camera-rig.json")
            step(["undistort-captures", str(lab), "--rig", str(rig), "--out", str(work / "lab-undistorted")],
                 work / "lab-undistorted")
            lab = work / "lab-undistorted"
        step(["calibrate", str(lab), "--out", str(work / "cal")], work / "cal")
        targets = full_brightness_targets(work / "targets")
        effects, fx = [], ""
        if args.effects == "auto":
            scale = [] if args.diagnose_scale is None else ["--scale", str(args.diagnose_scale)]
            step(["diagnose", str(work / "cal"), *scale, "--out", str(work / "diagnosis")], work / "diagnosis")
            effects, fx = ["--effects", "auto", "--diagnosis", str(work / "diagnosis")], "-fx"
        rows, sims = {}, {}
        for rng in ("none", "auto"):
            comp, ev = work / f"comp-{rng}{fx}", work / f"eval-{rng}{fx}"
            step(["compensate", str(work / "cal"), *targets, "--device", f"lab:{truth}", "--iterations",
                  str(args.iterations), "--range", rng, *effects, "--out", str(comp)], comp)
            step(["evaluate", str(work / "cal"), "--inputs", str(comp), "--targets", *targets, "--device",
                  f"lab:{truth}", "--out", str(ev)], ev)
            rows[rng] = json.loads((ev / "metrics.json").read_text())
            sims[rng] = json.loads((comp / "compensation.json").read_text())["targets"]
        r = rows["auto"]["range"]
        print(f"\n{args.surface}, lab effects {args.lab_effects}, scale {args.scale}, {args.iterations} iterations, "
              f"closed loop, --effects {args.effects}; --range auto: "
              f"{r['gain']:.3f}·t {r['offset']:+.3f} ({100 * r['clipped_share']:.2f} % of the values clipped)\n")
        print("| Target | none: ceiling / with noise | none: uncompensated → ours | none: gap at the input's limit "
              "| auto: ceiling / with noise | auto: uncompensated → ours |")
        print("|---|---|---|---|---|---|")

        def limit(row: dict) -> str:
            share = row.get("ceiling_gap_at_limit")
            return "–" if share is None else f"{share:.0%}"

        def ceilings(row: dict, prefix: str = "") -> str:
            noise = row.get(f"{prefix}noise_ceiling")  # None: evaluated before the noise ceiling (rerun evaluate)
            return f"{row[prefix + 'range_ceiling']:.2f} / " + ("–" if noise is None else f"{noise:.2f}")

        for a, b in zip(rows["none"]["targets"], rows["auto"]["targets"]):
            print(f"| {a['name']} | {ceilings(a)} | {a['uncompensated']['psnr']:.2f} → {a['psnr']:.2f} | {limit(a)} | "
                  f"{ceilings(b)} | {b['uncompensated']['psnr']:.2f} → {b['psnr']:.2f} |")
        a, b = rows["none"], rows["auto"]
        print(f"| mean | {ceilings(a, 'mean_')} | {a['mean_uncompensated']['psnr']:.2f} → {a['mean']['psnr']:.2f} | | "
              f"{ceilings(b, 'mean_')} | {b['mean_uncompensated']['psnr']:.2f} → {b['mean']['psnr']:.2f} |")
        for name, row in rows.items():
            if row.get("mean_noise_ceiling") is None:
                continue
            done = [t for t in row["targets"] if t.get("status") == "done"]
            noise = np.mean([t["capture_noise_rmse"] for t in done])
            # What stage C's own model (θ included) said each input reaches, through the measured noise: a gap to
            # the noise ceiling that this also shows is the projector's reach as modelled, not the solver's.
            simulated = {t["name"]: t["psnr_simulated"] for t in sims[name]}
            predicted = np.mean([-10 * np.log10(10 ** (-simulated[t["name"]] / 10) + t["capture_noise_rmse"] ** 2)
                                 for t in done])
            print(f"--range {name}: ours {row['mean']['psnr']:.2f} dB, "
                  f"{row['mean_noise_ceiling'] - row['mean']['psnr']:.2f} dB below the noise ceiling, "
                  f"{row['mean_range_ceiling'] - row['mean']['psnr']:.2f} dB below the range ceiling; "
                  f"camera noise RMS {noise:.4f}; stage C's own prediction through that noise {predicted:.2f} dB")
            fx = "-fx" if args.effects == "auto" else ""
            print(f"  squared error ×1e-4 (of it finer than {FINE_PX} camera pixels), capture against target | "
                  f"stage C's prediction against target | capture against prediction; the camera's noise:")
            for t in done:
                parts = error_scales(work / f"comp-{name}{fx}", work / f"eval-{name}{fx}", t)
                print(f"  {t['name']}: " + " | ".join(f"{1e4 * whole:.2f} ({1e4 * fine:.2f})" for whole, fine in parts)
                      + f"; {1e4 * t['capture_noise_rmse'] ** 2:.2f}")


def scaled_rig_file(src: Path, camera: dict, dst: Path) -> Path:
    """``src`` (a rig.json) with its camera and projector K scaled to ``camera``'s size (a capture set's camera,
    as ``capture.json`` holds it; the same aspect): a lab rendered at another scale is the same rig. The
    distortion terms are in normalised coordinates and stay."""
    from procam.addon.rig.model import Camera
    from procam.addon.steps import rig as rig_step

    cal = rig_step.read(src)
    size = Camera.from_dict(camera).intrinsics.size
    s = size[0] / cal.camera_size[0]

    def scaled(k: np.ndarray) -> np.ndarray:  # OpenCV pixel centres: x' = s (x + ½) − ½
        k = np.array(k, float)
        k[:2, :2] *= s
        k[:2, 2] = s * (k[:2, 2] + 0.5) - 0.5
        return k

    out = replace(cal, camera_size=size, camera_matrix=scaled(cal.camera_matrix),
                  projector_size=(round(cal.projector_size[0] * s), round(cal.projector_size[1] * s)),
                  projector_matrix=scaled(cal.projector_matrix))
    dst.write_text(json.dumps({"format": rig_step.KIND.format, "version": rig_step.KIND.version, **out.to_dict()}))
    return dst


#: The scale (σ of a Gaussian, camera pixels) below which :func:`error_scales` calls an error fine: detail the lab
#: projector's blurred lens passes little of (the plane's camera pixel spans 1.76 texels), and the camera's noise.
FINE_PX = 1.5


def area_image(path: Path, area: dict) -> np.ndarray:
    """The image at ``path`` inside the display ``area`` (a record's ``area``): as it is when it has the area's size
    (a target), else cropped to it (a camera image)."""
    from procam.addon.imageio import read_image

    image = np.asarray(read_image(path), np.float32)
    if image.shape[:2] == (area["height"], area["width"]):
        return image
    return image[area["y"]:area["y"] + area["height"], area["x"]:area["x"] + area["width"]]


def error_scales(comp: Path, ev: Path, row: dict) -> list[tuple[float, float]]:
    """Mean squared error inside the display area, and its part finer than :data:`FINE_PX`, of the capture
    against the target, of stage C's prediction against the target, and of the capture against the prediction."""
    import cv2

    a, name = row["area"], row["name"]
    capture, target = area_image(ev / f"{name}_capture.png", a), area_image(comp / f"{name}_target.png", a)
    simulated = area_image(comp / f"{name}_simulated.png", a)
    out = []
    for e in (capture - target, simulated - target, capture - simulated):
        fine = e - cv2.GaussianBlur(e, (0, 0), FINE_PX)
        out.append((float(np.mean(e ** 2)), float(np.mean(fine ** 2))))
    return out


if __name__ == "__main__":
    main()
