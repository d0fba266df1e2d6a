"""Calibration that knows what it cannot tell: the intrinsics fit on phone-like depth with a bias and a
misregistration, as it was (the covariance's verdict), with the judged rule, and with the nominal intrinsics.

    .venv/bin/python scripts/bench_calibration_uncertainty.py [--surfaces plane,curve,vedge,hedge] [--scale 0.25]
        [--cases 5:1:0,8:0:2,10:2.1:2.1] [--samples 4] [--other-forms 0] [--cache DIR]

Each case is BIAS_MM:SHIFT_X:SHIFT_Y (the depth map's misregistration in pixels of a 640-wide camera). The lab set
has the realistic effects, the spec 1.2 % long in projector focal length and 2 % of the height off in lens shift,
the camera's field of view 0.75° wide (focal length 1.6 % short), and no wall depth image (the bias is not
measured). ``--other-forms S`` renders each set through the lab of other forms as well (``procam lab
--other-forms``: a response and colour mixing that drift over the frame, a disk blur, another vignetting law, a
camera tone curve with a knee and JPEG photographs), forms no model of the calibration has. For each surface and
case: the projector's position (cm) and axis (°) error against the sealed truth,
with ``--projector-intrinsics spec``, the old fit rule (all of the covariance-determined values fitted), and the
judged rule; and whether each reported uncertainty covers the true error (within COVER_SIGMAS of its σ): the
judged values (projector focal length, principal point, camera focal length where judged) and the pose, the judged
rule's and the one the calibration with the nominal intrinsics states (``pose_uncertainty``).

A second table gives, for the same calibrations, where the projector's pixels land, which is what a show sees and
what the axis alone does not say (a principal point moved and the axis turned with it can leave every pixel where it
was): the angle between each fitted and true pixel ray over the whole projector image, mean and largest, and the
distance between where the fitted and the true ray of each pixel meet the true surface (mm), mean and largest.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np

from procam.addon.lab.lab import run_lab
from procam.addon.lab.truth import LabTruth, make_truth, projector_depth
from procam.addon.rig.model import Projector
from procam.addon.stages import intrinsics
from procam.addon.steps import calibrate


def lab_set(cache: Path, surface: str, case: tuple[float, float, float], scale: float, samples: int,
            other_forms: float = 0.0) -> Path:
    bias, sx, sy = case
    root = cache / (f"{surface}-b{bias:g}-x{sx:g}-y{sy:g}-s{scale:g}-n{samples}" +
                    (f"-o{other_forms:g}" if other_forms else ""))
    if not (root / "truth.json").is_file():
        effects = f"realistic,depth_noise.bias={bias / 1000},depth_noise.shift_x={sx},depth_noise.shift_y={sy}"
        lab = make_truth(surface, effects=effects, seed=0, samples=samples, scale=scale,
                         nominal_error=(-0.012, 0.02), camera_fov_error=0.75, other_forms=other_forms)
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


def landing(fitted: Projector, true: Projector, truth: LabTruth) -> tuple[float, float, float, float]:
    """Ray angle mean and max (degrees) and landing distance on the true surface mean and max (mm) over the
    projector's pixels that meet the surface, of the calibrated projector against the true one."""
    w, h = true.intrinsics.size
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    px = np.stack([xs.ravel(), ys.ravel()], axis=1)
    rays, hits = [], []
    for p in (true, fitted):
        pose = np.asarray(p.camera_from_projector, float)
        d = p.intrinsics.rays(px) @ pose[:3, :3].T  # z = 1 in the projector's frame, so depth × d is the point
        hits.append(d * projector_depth(truth.surface, p).reshape(-1, 1) + pose[:3, 3])
        rays.append(d / np.linalg.norm(d, axis=1, keepdims=True))
    angle = np.degrees(np.arccos(np.clip(np.sum(rays[0] * rays[1], axis=1), -1.0, 1.0)))
    dist = 1000 * np.linalg.norm(hits[1] - hits[0], axis=1)
    dist = dist[np.isfinite(dist)]
    return float(angle.mean()), float(angle.max()), float(dist.mean()), float(dist.max())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--surfaces", default="plane,curve,vedge,hedge")
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--cases", default="5:1:0,8:0:2,10:2.1:2.1")
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--other-forms", type=float, default=0.0, help="as procam lab's (0: off)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/procam-bench-calunc"))
    args = ap.parse_args(argv)
    cases = [tuple(float(v) for v in c.split(":")) for c in args.cases.split(",")]
    k = intrinsics.COVER_SIGMAS
    print(f"lab scale {args.scale:g}, {args.samples} spp, realistic effects"
          f"{f', other forms {args.other_forms:g}' if args.other_forms else ''}, no wall depth image; "
          f"spec focal -1.2 %, shift +2 % of the height, camera focal -1.6 %; 'covered': true error ≤ {k:g} σ reported")
    print("| surface | bias mm | shift px | nominal cm / ° | old fit cm / ° | judged cm / ° | judged kept | "
          "values covered (judged) | pose covered (judged) | values covered (old σ) | nominal pose ± cm / ° | "
          "nominal pose covered |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    totals = {"values": [0, 0], "pose": [0, 0], "old": [0, 0], "nominal pose": [0, 0]}
    worst = [-np.inf, -np.inf]
    lands = []
    t0 = time.perf_counter()
    for surface in args.surfaces.split(","):
        for case in cases:
            root = lab_set(args.cache, surface, case, args.scale, args.samples, args.other_forms)
            truth = LabTruth.load(root / "truth.json")
            tp, tc = truth.rig.projector, truth.rig.camera.intrinsics
            errs, cals, land = {}, {}, {}
            for mode in ("nominal", "old", "judged"):
                cal = cals[mode] = calibrate_with(root, mode)
                p = cal.rig.projector
                errs[mode] = (100 * float(np.linalg.norm(p.position - tp.position)),
                              float(np.degrees(np.arccos(np.clip(p.direction @ tp.direction, -1, 1)))))
                land[mode] = landing(p, tp, truth)
            worst = [max(worst[i], errs["judged"][i] - errs["nominal"][i]) for i in range(2)]
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
            nu = cals["nominal"].report["pose_uncertainty"]
            nominal_ok = (errs["nominal"][0] / 100 <= k * nu["position_std_m"] and
                          errs["nominal"][1] <= k * nu["axis_std_deg"])
            totals["nominal pose"][0] += int(nominal_ok)
            totals["nominal pose"][1] += 1
            kept = ", ".join(n.replace("projector_", "") for n, v in u["values"].items() if v["kept"] == "fit")
            print(f"| {surface} | {case[0]:g} | {np.hypot(case[1], case[2]):.1f} | {errs['nominal'][0]:.2f} / "
                  f"{errs['nominal'][1]:.3f} | {errs['old'][0]:.2f} / {errs['old'][1]:.3f} | "
                  f"{errs['judged'][0]:.2f} / {errs['judged'][1]:.3f} | {kept or 'spec'} | "
                  f"{sum(covered)}/{len(covered)} | {'yes' if pose_ok else 'no'} | "
                  f"{sum(old_covered)}/{len(old_covered)} | {100 * nu['position_std_m']:.2f} / "
                  f"{nu['axis_std_deg']:.3f} | {'yes' if nominal_ok else 'no'} |", flush=True)
            lands.append(f"| {surface} | {case[0]:g} | {np.hypot(case[1], case[2]):.1f} | " + " | ".join(
                f"{land[m][0]:.3f} / {land[m][1]:.3f} | {land[m][2]:.1f} / {land[m][3]:.1f}"
                for m in ("nominal", "old", "judged")) + " |")
    share = {n: a / max(b, 1) for n, (a, b) in totals.items()}
    print(f"\nreported uncertainty covers the true error: values {totals['values'][0]}/{totals['values'][1]} "
          f"({share['values']:.0%}), pose {totals['pose'][0]}/{totals['pose'][1]} ({share['pose']:.0%}), the pose "
          f"with the nominal intrinsics {totals['nominal pose'][0]}/{totals['nominal pose'][1]} "
          f"({share['nominal pose']:.0%}); the old "
          f"covariance σ of the values it fitted: {totals['old'][0]}/{totals['old'][1]} ({share['old']:.0%})")
    print(f"judged rule's error minus nominal's, worst case: position {worst[0]:+.2f} cm, axis {worst[1]:+.3f}°")
    print("\nwhere the projector's pixels land: angle between fitted and true pixel rays over the projector image "
          "(mean / max °), distance between where they meet the true surface (mean / max mm)")
    print("| surface | bias mm | shift px | nominal ray ° | nominal mm | old fit ray ° | old fit mm | judged ray ° | "
          "judged mm |")
    print("|---|---|---|---|---|---|---|---|---|")
    print("\n".join(lands))
    print(f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
