"""The diagnosis on real photographs: ``realdata/kamino410-procam-calibration``, each board pose end to end.

    .venv/bin/python scripts/bench_realdata.py --work /tmp/real [--scale 0.25] [--square 0.025]

A real camera photographed a real 1024×768 projector lighting a printed board in front of a wall and a table
(OpenCV's Gray code, white, black; 4 board poses; no depth image, no validation patterns, no surface photo).
For every pose, with the commands a user runs:

1. ``procam calibrate-rig`` on all four poses (``--square``: the board's squares are not stated; the scale only
   sets the units of the pose and the surface, not the diagnosis);
2. ``procam patterns --layout opencv`` (the session's own frames, checked against the published ones) and
   ``procam import-captures --rig --encoding linear`` (a machine-vision camera's raw 8-bit values);
3. ``procam calibrate --init nominal``: the surface triangulated from the Gray code, the projector's pose from
   the rig, stage B from the Gray code (no checkerboard);
4. ``procam diagnose``: every other Gray-code pattern held out.

Prints, per pose, the calibration's figures and what the diagnosis finds: the held-out residual before and after
the selected effects, what they explain, the fitted parameters and the first regions; then the seconds each step
took for each pose (each command in this process, as a user's pipeline in Python runs them). Folders under
``--work`` are reused when complete (``--fresh`` starts again; a reused step prints no seconds).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "realdata" / "kamino410-procam-calibration"
POSES = ("capture_0", "capture_1", "capture_2", "capture_3")


#: seconds of each step run: (pose, step) → s
SECONDS: dict[tuple[str, str], float] = {}


def _cli(argv: list[str], pose: str = "") -> None:
    from procam.addon.cli.app import main

    t0 = time.perf_counter()
    code = main(argv)
    if code != 0:
        raise SystemExit(f"procam {' '.join(argv)} failed with exit code {code}")
    SECONDS[pose, argv[0]] = time.perf_counter() - t0


def _same_frames(sequence: Path, published: Path) -> None:
    """The exported frames are the session's: refuse to go on otherwise (the import matches photos by order)."""
    doc = json.loads((sequence / "sequence.json").read_text())
    for i, frame in enumerate(doc["frames"]):
        ours = cv2.imread(str(sequence / frame["file"]), cv2.IMREAD_UNCHANGED).astype(np.float64)
        ours = (ours.mean(axis=2) if ours.ndim == 3 else ours) / 65535.0
        theirs = cv2.imread(str(published / f"pattern_{i:02d}.png"), cv2.IMREAD_GRAYSCALE).astype(np.float64) / 255.0
        if ours.shape != theirs.shape or float(np.abs(ours - theirs).mean()) > 0.01:
            raise SystemExit(f"frame {i} ({frame['name']}) differs from {published / f'pattern_{i:02d}.png'}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", type=Path, default=REAL, help="the kamino410-procam-calibration folder")
    ap.add_argument("--work", type=Path, required=True, help="folder for the rig, capture sets, calibrations")
    ap.add_argument("--scale", type=float, default=0.25, help="diagnosis working resolution (share of 1280×1024)")
    ap.add_argument("--square", type=float, default=0.025, help="assumed board square (m); the data do not say")
    ap.add_argument("--poses", default=",".join(POSES))
    ap.add_argument("--fresh", action="store_true", help="remove earlier results under --work first")
    args = ap.parse_args(argv)
    if not args.real.is_dir():
        print(f"no real data at {args.real}", file=sys.stderr)
        return 2
    if args.fresh and args.work.exists():
        shutil.rmtree(args.work)
    args.work.mkdir(parents=True, exist_ok=True)
    rig, seq = args.work / "rig.json", args.work / "sequence"
    t0 = time.perf_counter()
    if not rig.is_file():
        _cli(["calibrate-rig", *(str(args.real / p) for p in POSES), "--board", "9x7", "--square", str(args.square),
              "--projector", "1024x768", "--out", str(rig)])
    if not (seq / "sequence.json").is_file():
        _cli(["patterns", "--projector-width", "1024", "--projector-height", "768", "--area", "frame",
              "--no-validation", "--layout", "opencv", "--out", str(seq)])
    _same_frames(seq, args.real / "graycode_pattern")
    rows = []
    for pose in args.poses.split(","):
        captures, cal, gap = (args.work / f"{pose}_{k}" for k in ("captures", "calibration", "diagnosis"))
        if not (captures / "capture.json").is_file():
            _cli(["import-captures", str(seq), str(args.real / pose), "--rig", str(rig), "--encoding", "linear",
                  "--out", str(captures), "--force"], pose)
        if not (cal / "calibration.json").is_file():
            _cli(["calibrate", str(captures), "--out", str(cal), "--init", "nominal", "--no-blend-output",
                  "--no-precompute", "--force"], pose)
        if not (gap / "gap.json").is_file():
            _cli(["diagnose", str(cal), "--out", str(gap), "--scale", str(args.scale), "--force"], pose)
        rows.append((pose, json.loads((cal / "calibration.json").read_text()),
                     json.loads((gap / "gap.json").read_text())))

    print(f"\nreal photographs: {args.real}\nrig: {rig}; diagnosis at scale {args.scale}; "
          f"{time.perf_counter() - t0:.0f} s in all (reused folders not counted)\n")
    print("| pose | surface points (rejected), reprojection | warp from the Gray code, median | held-out RMSE → with "
          "the selected effects | explained | selected | fitted | first regions |")
    print("|---|---|---|---|---|---|---|---|")
    for pose, cal, doc in rows:
        rep = cal.get("report", cal)
        tri = (rep.get("surface_report") or {}).get("triangulation") or {}
        warp = rep.get("warp_report") or {}
        res, after = doc["residual"], doc["residual_after"]
        params = "; ".join(f"{n} " + ", ".join(f"{k} {v:.3g}" for k, v in p.items())
                           for n, p in doc["selected_params"].items())
        regions = "; ".join(f"{r['cause']} {r['share']:.0%}: {r['description']}" for r in doc["regions"][:2])
        print(f"| {pose} | {tri.get('points', '?')} ({tri.get('rejected', '?')}), "
              f"{tri.get('reprojection_rms_px', float('nan')):.2f} px | "
              f"{warp['corners_before_px']['median']:.2f} → {warp['corners_after_px']['median']:.2f} px | "
              f"{res['rmse']:.4f} ({res['psnr']:.1f} dB) → {after['rmse']:.4f} ({after['psnr']:.1f} dB) | "
              f"{doc['unexplained']['explained_share']:.0%} | {', '.join(doc['selected']) or 'none'} | {params} | "
              f"{regions} |")
    steps = ("import-captures", "calibrate", "diagnose")
    if any(key[1] in steps for key in SECONDS):
        print("\n| pose | " + " | ".join(f"{s} (s)" for s in steps) + " |\n|---|" + "---|" * len(steps))
        for pose, _, _ in rows:
            print(f"| {pose} | " + " | ".join(f"{SECONDS[pose, s]:.1f}" if (pose, s) in SECONDS else "reused"
                                               for s in steps) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
