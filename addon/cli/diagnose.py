"""``procam diagnose``: where and why the calibrated simulation still differs from the captures."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..options import add_arguments, from_arguments
from ..steps.diagnose import DiagnoseOptions, run as diagnose
from .app import command
from .terminal import run_step


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("calibration", type=Path, help="calibration folder (from procam calibrate)")
    p.add_argument("--out", type=Path, required=True, help="diagnosis folder to create (gap.json, maps, summary.md)")
    add_arguments(p, DiagnoseOptions)
    p.add_argument("--force", action="store_true", help="replace an existing diagnosis folder")


@command("diagnose", "Sim-to-real diagnosis: residual maps, regions, and which unmodelled effect explains them.",
         _configure)
def run(args: argparse.Namespace) -> int:
    doc = run_step("diagnose", diagnose, from_arguments(DiagnoseOptions, args, calibration=args.calibration,
                                                        out=args.out, force=args.force))
    res, after = doc["residual"], doc["residual_after"]
    print(f"diagnosis: {args.out}")
    print(f"  {doc['headline']}")
    for w in doc.get("warnings", []):
        print(f"  warning: {w}")
    print(f"  held-out residual: RMSE {res['rmse']:.4f} ({res['psnr']:.1f} dB)"
          f" → {after['rmse']:.4f} ({after['psnr']:.1f} dB) with the selected effects; without pixel noise "
          f"{res['rmse_structured']:.4f} → {after['rmse_structured']:.4f}")
    absorbed = f" ({', '.join(doc['absorbed'])} absorbed by calibration, found from its inputs)" if doc["absorbed"] else ""
    print("  selected: " + (", ".join(doc["selected"]) or "none") + absorbed)
    if doc["session"]["changed"]:
        print(f"  the rig changed during the session: {doc['session']['sentence']}")
    u = doc["unexplained"]
    if u["detected"]:
        print(f"  unexplained: the selected effects explain {u['explained_share']:.0%} of the residual above the "
              f"captures' noise; RMSE {u['unexplained_rmse']:.4f} is left" + (f", most of it {u['where']}"
                                                                               if u["where"] else ""))
    elif doc["modelled"]:
        print(f"  explained: {u['explained_share']:.0%} of the residual above the captures' noise")
    else:
        print(f"  left: RMSE {u['unexplained_rmse']:.4f} above the captures' noise, too little to model")
    for e in doc["effects"][:3]:
        if e.get("error"):
            continue
        print(f"  {e['name']:<16} alone: RMSE {e['heldout_rmse_after']:.4f} ({e['reduction']:.0%} less), "
              f"confidence {e['confidence']['level']}")
    for k, r in enumerate(doc["regions"][:3]):
        print(f"  region {k + 1} ({r.get('cause', '?')}): {r['share']:.0%} of the error, {r['description']}")
    print(f"  summary: {Path(args.out) / 'summary.md'}")
    return 0
