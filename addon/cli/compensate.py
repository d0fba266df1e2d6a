"""``procam compensate``: stage C for each target image, closed loop through a device or open loop.

The folder it writes is the compensate step's (``addon/steps/compensate.py``); the stage-C options here are
shared with ``procam show``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..stages.compensate import DEFAULT_SCHEDULE, ITERATIONS_JOINT, ITERATIONS_Z, SCHEDULES
from ..stages.display_area import TARGET_ENCODINGS, parse_area
from ..steps.compensate import CompensateOptions, run as compensate
from ..steps.stage_c import StageCOptions
from .app import command
from .terminal import run_step


def add_schedule_options(p: argparse.ArgumentParser) -> None:
    """The stage-C options shared by ``procam compensate`` and ``procam show`` (device, schedule, area, θ)."""
    def counts(name: str) -> str:
        s = SCHEDULES[name]
        start = f"{s.fixed_point} fixed-point steps + " if s.fixed_point else ""
        return (f"{name}: {start}{s.iterations_z}+{s.iterations_joint} iterations, lr {s.lr}, a capture every "
                f"{s.capture_interval}")

    p.add_argument("--device", default=None,
                   help="closed loop through lab:TRUTH_FILE (virtual lab), folder:CAPTURE_DIR or live:camera=SOURCE,display=N; "
                        "without a device θ is estimated from the validation captures (open loop)")
    p.add_argument("--schedule", choices=tuple(SCHEDULES), default=DEFAULT_SCHEDULE,
                   help=f"stage-C schedule (default {DEFAULT_SCHEDULE}; 'paper' = the paper's 200+300 iterations). "
                        "--iterations, --lr and --capture-every override its values: " +
                        "; ".join(counts(n) for n in SCHEDULES))
    p.add_argument("--iterations", type=int, default=None,
                   help="total iterations, split between z alone and z + θ in the schedule's own ratio "
                        f"(paper: {ITERATIONS_Z}:{ITERATIONS_JOINT} Adam steps; fast: all joint Adam steps, after "
                        "its fixed-point steps; transport: solver steps, half of them before the first capture; "
                        "default: the schedule's counts)")
    p.add_argument("--area", default=None,
                   help="display area x,y,width,height in camera pixels (default: the capture set's, else the "
                        "largest rectangle of the target's aspect ratio that the projector covers)")
    p.add_argument("--spp", type=int, default=4, help="samples per pixel inside the loop (default 4)")
    p.add_argument("--bounces", type=int, default=1, help="indirect bounces simulated (default 1)")
    p.add_argument("--capture-every", type=int, default=None,
                   help="closed loop: capture W(z) every K joint iterations (default: the schedule's; "
                        "1 = the paper, for fast real hardware)")
    p.add_argument("--lr", type=float, default=None, help="Adam learning rate on z (default: the schedule's)")
    p.add_argument("--target-encoding", choices=TARGET_ENCODINGS, default="auto",
                   help="auto: 8-bit files are sRGB and are linearised, 16-bit/float are linear")
    p.add_argument("--range", default="none",
                   help="what the targets become before compensation: 'auto' fits one gain and offset to all the "
                        "targets so that at most 1 %% of their values lie outside what the projector shows on this "
                        "surface (its white and black captures), never dimming targets that fit; 'GAIN,OFFSET' "
                        "gives them; 'none' (default) keeps the targets as they are")
    p.add_argument("--no-bias", action="store_true", help="no θ at all (ablation): neither captures nor validation")
    p.add_argument("--seed", type=int, default=0)


def stage_c_options(args: argparse.Namespace) -> StageCOptions:
    """The :class:`StageCOptions` of the command line (checked: a bad value fails here, before any work)."""
    options = StageCOptions(schedule=args.schedule, iterations=args.iterations, lr=args.lr,
                            capture_every=args.capture_every, spp=args.spp, bounces=args.bounces, seed=args.seed,
                            area=parse_area(args.area) if args.area else None, target_encoding=args.target_encoding,
                            use_bias=not args.no_bias, device=args.device, effects=args.effects,
                            diagnosis=args.diagnosis, range=args.range)
    options.check()
    return options


def add_effect_options(p: argparse.ArgumentParser) -> None:
    """``--effects`` / ``--diagnosis``: diagnosed effect models around stage C (addon/gap/compensation.py)."""
    p.add_argument("--effects", default="none",
                   help="effect models around stage C, fitted by procam diagnose: 'auto' (the ones it selected), "
                        "NAME,... or 'none' (default); needs --diagnosis")
    p.add_argument("--diagnosis", type=Path, default=None, help="the procam diagnose folder for --effects")


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("calibration", type=Path, help="calibration folder (from procam calibrate)")
    p.add_argument("targets", type=Path, nargs="+", metavar="TARGET", help="target images (PNG, JPEG, EXR, …)")
    p.add_argument("--out", type=Path, required=True, help="folder to create for the projector inputs")
    add_schedule_options(p)
    add_effect_options(p)
    p.add_argument("--force", action="store_true", help="replace an existing compensation folder at --out")


@command("compensate", "Find the projector input for each target image (stage C).", _configure)
def run(args: argparse.Namespace) -> int:
    options = CompensateOptions(args.calibration, tuple(args.targets), args.out, stage_c_options(args),
                                force=args.force)
    view = run_step("compensate", compensate, options, total=len(options.targets), unit="targets")
    effects = view.doc.get("effects")
    if effects:
        print(f"effect models: {', '.join(effects['used']) or 'none'}"
              + (f"; not inverted: {', '.join(effects['not_inverted'])}" if effects["not_inverted"] else ""))
    for t in view.doc["targets"]:
        if t.get("status") == "done":
            print(f"{t['name']}: {t['mode']}, {t['seconds']:.1f} s, simulated PSNR {t['psnr_simulated_start']:.2f} "
                  f"→ {t['psnr_simulated']:.2f} dB in the display area")
    print(f"compensation: {args.out} ({len(view.targets)}/{len(options.targets)} targets)")
    return 0
