"""procam calibrate-rig against the lab's truth: board sessions rendered with Cycles, calibrated, compared.

    .venv/bin/python scripts/bench_board_lab.py [--poses 6] [--scale 1] [--effects distortion=0.5,noise=0.3]
        [--samples 4] [--square 0.06] [--window 19] [--camera-distortion k1k2p1p2] [--projector-distortion auto]
        [--sessions DIR] [--supersample N]

``--sessions`` calibrates sessions rendered earlier (``procam lab-board --out DIR``, truth in DIR.truth.json; the
first ``--poses`` of them) instead of rendering new ones.

Renders ``--poses`` sessions of a 9×7 chessboard (squares of ``--square`` m) through the demo rig (camera
640×480 and projector 800×600 at ``--scale`` 1) with the lab's effects, runs the calibrate-rig step on them and
prints each device's focal-length (%) and principal-point (px) errors, the projector's position (mm) and axis (°)
errors against the truth, and the reprojection RMS.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from procam.addon.lab.board import BoardTruth, default_supersample, render_board_sessions
from procam.addon.lab.truth import scaled_rig
from procam.addon.rig.demo import demo_rig
from procam.addon.steps import rig as rig_step


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--poses", type=int, default=6)
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--effects", default="distortion=0.5,noise=0.3")
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--square", type=float, default=0.06)
    ap.add_argument("--window", type=int, default=19)
    ap.add_argument("--camera-distortion", default="k1k2p1p2")
    ap.add_argument("--projector-distortion", default="auto")
    ap.add_argument("--sessions", type=Path, default=None)
    ap.add_argument("--supersample", type=int, default=None,
                    help="as procam lab-board's (default: 2 when the effects distort the camera's lens)")
    args = ap.parse_args(argv)
    rig = scaled_rig(demo_rig(), args.scale)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        folder = args.sessions or Path(tmp) / "sessions"
        if args.sessions is None:
            ss = args.supersample if args.supersample is not None else default_supersample(args.effects)
            truth = render_board_sessions(rig, folder, poses=args.poses, effects=args.effects,
                                          samples=args.samples, square=args.square, supersample=ss)
        else:
            truth = BoardTruth.load(folder.with_name(folder.name + ".truth.json"))
            rig = truth.rig
        t_render = time.perf_counter() - t0
        t0 = time.perf_counter()
        sessions = tuple(sorted(folder.glob("pose_*")))[:args.poses]
        cal = rig_step.run(rig_step.RigOptions(sessions, Path(tmp) / "rig.json", (9, 7), rig.projector.intrinsics.size,
                                               square=args.square, window=args.window,
                                               camera_model=args.camera_distortion,
                                               projector_model=args.projector_distortion))
        t_cal = time.perf_counter() - t0
    effects = truth.effects if args.sessions else args.effects
    print(f"{len(sessions)} board poses, camera {rig.camera.intrinsics.size}, "
          f"projector {rig.projector.intrinsics.size}, "
          f"effects {effects or 'none'}, {args.samples} spp; distortion models camera {args.camera_distortion}, "
          f"projector {args.projector_distortion}; render {t_render:.0f} s, calibrate-rig {t_cal:.1f} s")
    print("| device | fx error | fy error | cx error | cy error | RMS |")
    print("|---|---|---|---|---|---|")
    for name, km, true, rms in (("camera", cal.camera_matrix, truth.rig.camera.intrinsics, cal.camera_rms),
                                ("projector", cal.projector_matrix, truth.rig.projector.intrinsics, cal.projector_rms)):
        print(f"| {name} | {100 * (km[0, 0] / true.fx - 1):+.3f} % | {100 * (km[1, 1] / true.fy - 1):+.3f} % | "
              f"{km[0, 2] + 0.5 - true.cx:+.2f} px | {km[1, 2] + 0.5 - true.cy:+.2f} px | {rms:.3f} px |")
    p, t = cal.camera_from_projector, truth.rig.projector.camera_from_projector
    axis = np.degrees(np.arccos(np.clip(p[:3, 2] @ t[:3, 2], -1, 1)))
    print(f"projector pose: position {1000 * np.linalg.norm(p[:3, 3] - t[:3, 3]):.2f} mm, axis {axis:.3f}°; "
          f"stereo RMS {cal.stereo_rms:.3f} px; camera distortion k1 k2 {np.round(cal.camera_distortion[:2], 4)}")
    print(f"projector distortion model: {cal.projector_model}" + "".join(
        f"; {m} RMS {c['rms']:.4f} BIC {c['bic']:.1f}"
        for m, c in cal.projector_model_choice.get("candidates", {}).items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
