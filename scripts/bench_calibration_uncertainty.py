"""Calibration that knows what it cannot tell: the intrinsics fit on phone-like depth with a bias and a
misregistration, as it was (the covariance's verdict), with the judged rule, and with the nominal intrinsics.

    .venv/bin/python scripts/bench_calibration_uncertainty.py [--surfaces plane,curve,vedge,hedge] [--scale 0.25]
        [--cases 5:1:0,8:0:2,10:2.1:2.1] [--samples 4] [--cache DIR]

Each case is BIAS_MM:SHIFT_X:SHIFT_Y (the depth map's misregistration in pixels of a 640-wide camera). The lab set
has the realistic effects, the spec 1.2 % long in projector focal length and 2 % of the height off in lens shift,
the camera's field of view 0.75° wide (focal length 1.6 % short), and no wall depth image (the bias is not
measured). For each surface and case: the projector's position (cm) and axis (°) error against the sealed truth,
with ``--projector-intrinsics spec``, the old fit rule (all of the covariance-determined values fitted), and the
judged rule; and whether each reported uncertainty covers the true error (within COVER_SIGMAS of its σ): the
judged values (projector focal length, principal point, camera focal length where judged) and the pose.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np

from procam.addon.lab.lab import run_lab
from procam.addon.lab.truth import LabTruth, make_truth
from procam.addon.stages import intrinsics
from procam.addon.steps import calibrate


def lab_set(cache: Path, surface: str, case: tuple[float, float, float], scale: float, samples: int) -> Path:
    bias, sx, sy = case
    root = cache / f"{surface}-b{bias:g}-x{sx:g}-y{sy:g}-s{scale:g}-n{samples}"
    if not (root / "truth.json").is_file():
        effects = f"realistic,depth_noise.bias={bias / 1000},depth_noise.shift_x={sx},depth_noise.shift_y={sy}"
        lab = make_truth(surface, effects=effects, seed=0, samples=samples, scale=scale,
                         nominal_error=(-0.012, 0.02), camera_fov_error=0.75)
        run_lab(lab, root / "captures", truth_path=root / "truth.json", depth_wall=False, validation=False,
                force=True)
    return root


def calibrate_with(root: Path, mode: str) -> calibrate.Calibration:
    out = root / f"cal-{mode}"
    options = calibrate.CalibrateOptions(root / "captures", out, with_blend=False, precompute=False, force=True,
                                         stages="surface,pose",
                                         projector_intrinsics="spec" if mode == "nominal" else "fit")
    if mode != "old":
        return calibrate.run(options)
    with mock.patch.object(intrinsics, "JUDGE", False):
        return calibrate.run(options)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--surfaces", default="plane,curve,vedge,hedge")
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--cases", default="5:1:0,8:0:2,10:2.1:2.1")
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/procam-bench-calunc"))
    args = ap.parse_args(argv)
    cases = [tuple(float(v) for v in c.split(":")) for c in args.cases.split(",")]
    k = intrinsics.COVER_SIGMAS
    print(f"lab scale {args.scale:g}, {args.samples} spp, realistic effects, no wall depth image; spec focal -1.2 %, "
          f"shift +2 % of the height, camera focal -1.6 %; 'covered': true error ≤ {k:g} σ reported")
    print("| surface | bias mm | shift px | nominal cm / ° | old fit cm / ° | judged cm / ° | judged kept | "
          "values covered (judged) | pose covered (judged) | values covered (old σ) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    totals = {"values": [0, 0], "pose": [0, 0], "old": [0, 0]}
    worst = 0.0
    t0 = time.perf_counter()
    for surface in args.surfaces.split(","):
        for case in cases:
            root = lab_set(args.cache, surface, case, args.scale, args.samples)
            truth = LabTruth.load(root / "truth.json")
            tp, tc = truth.rig.projector, truth.rig.camera.intrinsics
            errs, cals = {}, {}
            for mode in ("nominal", "old", "judged"):
                cal = cals[mode] = calibrate_with(root, mode)
                p = cal.rig.projector
                errs[mode] = (100 * float(np.linalg.norm(p.position - tp.position)),
                              float(np.degrees(np.arccos(np.clip(p.direction @ tp.direction, -1, 1)))))
            worst = max(worst, errs["judged"][0] - errs["nominal"][0])
            u = cals["judged"].report["projector_intrinsics"]["uncertainty"]
            true = {"projector_focal": tp.intrinsics.fx, "projector_cx": tp.intrinsics.cx,
                    "projector_cy": tp.intrinsics.cy, "camera_focal": tc.fx}
            covered, old_covered = [], []
            old = cals["old"].report["projector_intrinsics"]["uncertainty"]["values"]
            for name, v in u["values"].items():
                share = name == "camera_focal"
                err = abs(v["value"] - true[name]) / (v["spec"] if share else 1.0)
                covered.append(err <= k * v["std"])
                if name in old and old[name]["kept"] == "fit":
                    o = old[name]
                    old_covered.append(abs(o["value"] - true[name]) / (o["spec"] if share else 1.0)
                                       <= k * o["covariance_std"])
            pose_ok = (errs["judged"][0] / 100 <= k * u["pose"]["position_std_m"] and
                       errs["judged"][1] <= k * u["pose"]["axis_std_deg"])
            totals["values"][0] += sum(covered)
            totals["values"][1] += len(covered)
            totals["pose"][0] += int(pose_ok)
            totals["pose"][1] += 1
            totals["old"][0] += sum(old_covered)
            totals["old"][1] += len(old_covered)
            kept = ", ".join(n.replace("projector_", "") for n, v in u["values"].items() if v["kept"] == "fit")
            print(f"| {surface} | {case[0]:g} | {np.hypot(case[1], case[2]):.1f} | {errs['nominal'][0]:.2f} / "
                  f"{errs['nominal'][1]:.3f} | {errs['old'][0]:.2f} / {errs['old'][1]:.3f} | "
                  f"{errs['judged'][0]:.2f} / {errs['judged'][1]:.3f} | {kept or 'spec'} | "
                  f"{sum(covered)}/{len(covered)} | {'yes' if pose_ok else 'no'} | "
                  f"{sum(old_covered)}/{len(old_covered)} |", flush=True)
    share = {n: a / max(b, 1) for n, (a, b) in totals.items()}
    print(f"\nreported uncertainty covers the true error: values {totals['values'][0]}/{totals['values'][1]} "
          f"({share['values']:.0%}), pose {totals['pose'][0]}/{totals['pose'][1]} ({share['pose']:.0%}); the old "
          f"covariance σ of the values it fitted: {totals['old'][0]}/{totals['old'][1]} ({share['old']:.0%})")
    print(f"judged rule's position error minus nominal's, worst case: {worst:+.2f} cm "
          f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
