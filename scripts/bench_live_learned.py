#!/usr/bin/env python3
"""A live show's learned correction: follow the camera on one clip, then play another clip without a camera.

Usage: ``.venv/bin/python scripts/bench_live_learned.py [--other-forms 1] [--scale 0.5] [--follow 24]
[--frames 8] [--timing 0] [--work DIR]``

Renders (or reuses, in ``--work``: the folders ``scripts/bench_closed_loop.py`` makes) a lab of other forms
(``procam lab --other-forms``, sensor noise on) and its calibration, then, with the real-time solver a live show
uses (``--range auto``):

1. **follows** the lab camera on ``--follow`` frames of a panning clip of one photograph (city): every frame
   solved, shown, captured through the lab and given to :meth:`RealtimeSolver.follow`, as ``procam live-show
   --device live:camera=…,display=…`` does; the correction learned (each camera pixel's gain and offset against
   the model) is written as ``procam live-show --correction FILE`` writes it;
2. **plays** ``--frames`` frames of a panning clip of other photographs (forest, then studio) open loop, as a show
   without a camera does, three ways, each answer captured through the lab: today's open loop (θ from the
   validation captures), the θ the follow left in memory (what today's live show keeps, for its own display
   area), and the learned correction read back from the file (``--correction FILE`` without a camera).

Prints the captured PSNR inside the display area of each way (mean over the frames) and the real-time solve's
milliseconds with and without the learned correction; ``--timing N`` also times N solves of each way back to back,
without the lab's renders between them.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from procam.addon.capture.targets import natural_target

sys.path.insert(0, str(Path(__file__).parent))
from bench_closed_loop import lab_and_calibration  # noqa: E402
from bench_live_show import panning  # noqa: E402


def time_solves(ways: dict, images: list[np.ndarray], reps: int) -> dict[str, list[float]]:
    """Each way's solve milliseconds over ``reps`` solves, the ways interleaved frame by frame so that whatever
    else the cores do falls on all of them alike (each way's first solve of a frame's area not counted)."""
    got: dict[str, list[float]] = {name: [] for name in ways}
    for solver in ways.values():
        solver.solve(images[0])
    for k in range(reps):
        image = images[k % len(images)]
        for name, solver in ways.items():
            got[name].append(solver.solve(image).solve_ms)
    return got


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--surface", default="curve")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--other-forms", type=float, default=1.0)
    ap.add_argument("--lab-effects", default="noise=0.4")
    ap.add_argument("--follow", type=int, default=24, help="frames followed with the camera (default 24)")
    ap.add_argument("--frames", type=int, default=8, help="frames played without a camera, per way (default 8)")
    ap.add_argument("--timing", type=int, default=0,
                    help="also time this many solves of each way back to back, without the lab between them (the "
                         "solve's own speed; the quality part's milliseconds share the cores with the lab's renders)")
    ap.add_argument("--timing-only", action="store_true",
                    help="with --timing and --work: reuse the correction learned there, time the solves alone")
    ap.add_argument("--work", type=Path, help="keep the folders here and reuse them")
    args = ap.parse_args()

    from procam.addon.stages.metrics import psnr
    from procam.addon.steps import calibrate as calibrate_step
    from procam.addon.steps.realtime import RealtimeSolver
    from procam.addon.steps.stage_c import StageC, StageCOptions, device_pipeline

    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        truth = lab_and_calibration(work, args.surface, args.lab_effects, args.other_forms, args.scale)
        cal = calibrate_step.read(work / "cal")
        sha = calibrate_step.identity(work / "cal")["sha256"]
        cw, ch = cal.rig.camera.intrinsics.size
        size = (round(1.25 * cw), round(1.25 * ch))
        learn_clip = natural_target("city", size)
        play_clips = [natural_target("forest", size), natural_target("studio", size)]
        device = device_pipeline(f"lab:{truth}", cal)
        assert device is not None

        def shown(frame) -> np.ndarray:
            return device.project(frame.frames[0][..., :3].astype(np.float32) / 255.0)

        learned_file = work / "learned-correction.npz"
        try:
            with StageC(cal, StageCOptions(range="auto")) as stage:
                sample = [panning(learn_clip, i) for i in range(0, args.follow, 6)] + \
                         [panning(c, i) for c in play_clips for i in range(0, args.frames, 4)]
                stage.fix_range(sample)
                today = RealtimeSolver.for_stage(stage)
                followed = RealtimeSolver(stage, today.inverses)
                if args.timing_only and not learned_file.exists():
                    raise SystemExit(f"--timing-only reuses {learned_file}: run once without it first")
                for i in range(0 if args.timing_only else args.follow):
                    out = followed.solve(panning(learn_clip, i))
                    followed.follow(shown(out), out)
                if not args.timing_only:
                    written = followed.save_learned(learned_file, sha)
                    print(f"followed {args.follow} frames; learned correction written to {written}")
                learned = RealtimeSolver(stage, today.inverses)
                learned.load_learned(learned_file, sha)
                ways = {"open loop (validation θ)": today, "θ left by the follow": followed,
                        "learned correction": learned}
                if args.timing_only:
                    del ways["θ left by the follow"]
                scores: dict[str, list[float]] = {k: [] for k in ways}
                ms: dict[str, list[float]] = {k: [] for k in ways}
                for clip in [] if args.timing_only else play_clips:
                    for i in range(args.frames):
                        image = panning(clip, i)
                        for name, solver in ways.items():
                            out = solver.solve(image)
                            area = out.area
                            target = solver._fitted(image, area).reshape(area.height, area.width, 3)
                            seen = area.crop(shown(out))
                            scores[name].append(psnr(np.clip(seen, 0, 1), target))
                            ms[name].append(out.solve_ms)
                if args.timing:
                    timing = time_solves(ways, [panning(c, i) for c in play_clips for i in range(args.frames)],
                                         args.timing)
        finally:
            device.close()
        if not args.timing_only:
            print_quality(args, ways, scores, ms)
        if args.timing:
            print(f"\nsolve alone, {args.timing} solves of each way, interleaved (camera {cw}×{ch}, projector "
                  f"{cal.rig.projector.intrinsics.width}×{cal.rig.projector.intrinsics.height}):\n")
            print("| way | ms (median) | ms (90th percentile) | frames a second (median) |")
            print("|---|---|---|---|")
            for name, got in timing.items():
                print(f"| {name} | {np.median(got):.1f} | {np.percentile(got, 90):.1f} | {1000 / np.median(got):.0f} |")


def print_quality(args: argparse.Namespace, ways: dict, scores: dict[str, list[float]],
                  ms: dict[str, list[float]]) -> None:
    """The quality part's table: each way's captured PSNR and its change against today's open loop."""
    print(f"\nlab --effects {args.lab_effects} --other-forms {args.other_forms}, scale {args.scale}; followed "
          f"{args.follow} frames of city, then {2 * args.frames} frames of forest and studio without a camera, "
          "--range auto\n")
    print("| way | captured PSNR (mean) | change | solve ms (median) |")
    print("|---|---|---|---|")
    base = float(np.mean(scores["open loop (validation θ)"]))
    for name in ways:
        m = float(np.mean(scores[name]))
        print(f"| {name} | {m:.2f} | {m - base:+.2f} | {np.median(ms[name][2:]):.1f} |")


if __name__ == "__main__":
    main()
