"""``procam diagnose``: where and why the calibrated simulation still differs from the captures."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..gap.fit import MAX_EFFECTS, MIN_SHARE
from ..gap.models import NAMES
from ..steps.diagnose import DiagnoseOptions, run as diagnose
from .app import command
from .terminal import run_step


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("calibration", type=Path, help="calibration folder (from procam calibrate)")
    p.add_argument("--out", type=Path, required=True, help="diagnosis folder to create (gap.json, maps, summary.md)")
    p.add_argument("--effects", default="all",
                   help=f"candidate effect models, comma-separated, or 'all' (default): {', '.join(NAMES)}")
    p.add_argument("--scale", type=float, default=0.5,
                   help="working resolution as a share of the camera image (default 0.5)")
    p.add_argument("--spp", type=int, default=32, help="samples per pixel of the model renders (default 32)")
    p.add_argument("--min-share", type=float, default=MIN_SHARE,
                   help=f"an effect is selected only if it removes at least this share of the held-out RMSE "
                        f"left (default {MIN_SHARE})")
    p.add_argument("--max-effects", type=int, default=MAX_EFFECTS,
                   help=f"effects selected at most: rounds of the greedy selection, each slower than the last "
                        f"(default {MAX_EFFECTS})")
    p.add_argument("--force", action="store_true", help="replace an existing diagnosis folder")


@command("diagnose", "Sim-to-real diagnosis: residual maps, regions, and which unmodelled effect explains them.",
         _configure)
def run(args: argparse.Namespace) -> int:
    doc = run_step("diagnose", diagnose, DiagnoseOptions(args.calibration, args.out, effects=args.effects,
                                                         scale=args.scale, spp=args.spp,
                                                         min_share=args.min_share, max_effects=args.max_effects,
                                                         force=args.force))
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
