"""``procam demo``: the built-in demo end to end — lab → calibration → compensation → evaluation → diagnosis —
made of the real steps (``addon/steps/demo.py``), with its folders under ``--out`` and a summary on screen.

Default: half resolution (camera 320×240, projector 400×300) so it runs in minutes on 2 cores;
``--full`` uses the paper's 640×480 / 800×600.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..options import add_arguments, from_arguments
from ..steps.demo import DemoOptions, run as demo
from ..steps.summary import fmt
from .app import command
from .calibrate import blend_writer
from .terminal import run_step


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="results folder (default: out/demo)")
    add_arguments(p, DemoOptions)
    p.add_argument("--force", action="store_true", help="replace an existing results folder")


@command("demo", "Run the built-in demo end to end (lab, calibration, compensation, evaluation, diagnosis).",
         _configure)
def run(args: argparse.Namespace) -> int:
    options = from_arguments(DemoOptions, args, out=args.out, force=args.force)
    summary = run_step("demo", demo, options, blend_writer=blend_writer())
    cam, proj = summary["resolution"]["camera"], summary["resolution"]["projector"]
    c = summary["calibration"]
    x = summary["cross_renderer"]
    m = summary["compensation"]["mean"]
    print(f"ProCam demo — results in {args.out}/")
    print(f"  rig: camera {cam[0]}×{cam[1]}, projector {proj[0]}×{proj[1]} (lens shift 15 % up), "
          f"surface {args.surface}, lab effects: {args.effects}")
    for k, p in enumerate(c.get("projectors") or [c]):
        which = f"projector {k + 1}" if c.get("projectors") else "projector"
        print(f"  calibration: {which} position error {p['position_error_cm']:.2f} cm, direction error "
              f"{p['direction_error_deg']:.3f}° (against the sealed lab truth)")
    wc = c["warp_corners"] or {}
    if wc.get("corners_before_px") and wc.get("corners_after_px"):
        print(f"  warp: checkerboard corners median {wc['corners_before_px']['median']:.2f} px → "
              f"{wc['corners_after_px']['median']:.2f} px")
    print(f"  Cycles vs Mitsuba (direct): corners median {x['corner_offset_median_px']:.3f} px, "
          f"intensity mean |diff| {x['intensity_mean_abs_diff_pct']:.2f} %")
    for r in summary["compensation"]["targets"]:
        print(f"  target {r['name']:10s}: PSNR {r['uncompensated_psnr']:.2f} → {r['psnr']:.2f} dB, "
              f"SSIM {r['uncompensated_ssim']:.3f} → {r['ssim']:.3f} ({r['mode']}, {r['seconds']} s)")
    print(f"  mean: PSNR {m['uncompensated_psnr']:.2f} → {m['psnr']:.2f} dB (uncompensated → compensated); "
          f"{args.out}/evaluation/ holds the side-by-side images")
    overlap = summary["compensation"].get("overlap")
    if overlap:
        o, u = overlap["mean"], overlap["mean_uncompensated"]
        print(f"  overlap of the projectors: PSNR {fmt(u.get('psnr_overlap'), '.2f')} → "
              f"{fmt(o.get('psnr_overlap'), '.2f')} dB inside it, {fmt(u.get('psnr_outside'), '.2f')} → "
              f"{fmt(o.get('psnr_outside'), '.2f')} dB outside it; seam step {fmt(u.get('seam_step'), '.4f')} → "
              f"{fmt(o.get('seam_step'), '.4f')}")
    g = summary["diagnosis"]
    if g.get("headline"):
        print(f"  diagnosis says: {g['headline']}")
    if "projectors" in g:
        for k, p in enumerate(g["projectors"]):
            print(f"    projector {k + 1}: selected {', '.join(p.get('selected') or []) or 'none'} "
                  f"(see {args.out}/diagnosis/projector_{k + 1}/summary.md)")
        print("  seconds: " + ", ".join(f"{k} {v}" for k, v in summary["seconds"].items())
              + f", total {summary['seconds_total']}")
        _print_report(args.out, summary)
        return 0
    print(f"  diagnosis: held-out residual RMSE {g['residual']['rmse']:.4f} → {g['residual_after']['rmse']:.4f} "
          f"({g['residual']['psnr']:.1f} → {g['residual_after']['psnr']:.1f} dB) with the selected effects: "
          f"{', '.join(g['selected']) or 'none'} (see {args.out}/diagnosis/summary.md)")
    if g["absorbed"]:
        print(f"    absorbed by calibration, found from its inputs: {', '.join(g['absorbed'])}; "
              f"--effects auto would invert: {', '.join(g['compensation']) or 'none'}")
    for w in g.get("warnings", []):
        print(f"    warning: {w}")
    for k, r in enumerate(g["regions"]):
        print(f"    region {k + 1} ({r.get('cause', '?')}): {r['share']:.0%} of the error, {r['description']}")
    fx = summary.get("with_effects")
    if fx:
        print(f"  compensated again with {', '.join(fx['effects'])} inverted (--effects auto): PSNR "
              f"{m['psnr']:.2f} → {fx['mean']['psnr']:.2f} dB, SSIM {m['ssim']:.3f} → {fx['mean']['ssim']:.3f} "
              f"({args.out}/evaluation-effects/)")
    print("  seconds: " + ", ".join(f"{k} {v}" for k, v in summary["seconds"].items())
          + f", total {summary['seconds_total']}")
    _print_report(args.out, summary)
    return 0


def _print_report(out: Path, summary: dict) -> None:
    made = summary.get("report") or {}
    if made.get("skipped"):
        print(f"  report: not built ({made['skipped']})")
    elif made:
        print(f"  report: {out / made['html']} ({made['bytes'] / 1e6:.2f} MB, {made['seconds']} s) — open it in a "
              "browser")
