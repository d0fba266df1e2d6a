"""Lens shift anywhere: Cycles vs Mitsuba, and lab → calibration, as the projector's principal point leaves the frame.

    .venv/bin/python scripts/bench_lens_shift.py [--shifts 0,0 0,60 0,127 0,200 60,0 -60,-200]
        [--surface curve] [--scale 0.5] [--samples 16] [--effects realistic]

For each shift (RIGHT,UP in % of the projector image; the demo projector, aimed so its image lands on the
surface, as ``procam lab --projector-shift`` makes it):

* Cycles vs Mitsuba on the true rig, direct light, camera 320×240 / projector 400×300: checkerboard corner
  offsets (median, max, px) and the white render's mean |difference| (% of the mean), no fitted scale;
* the symmetric frustum Mitsuba's projector needs (degrees) and its texture (always the frame + a 1-texel border);
* a lab capture set (``--scale`` of 640×480 / 800×600, ``--effects``) calibrated by ``procam calibrate``'s step:
  projector position (mm) and axis (°) errors against the sealed truth, and the warp's corner median.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from procam.addon.lab.crosscheck import run_cross_check
from procam.addon.lab.truth import LabTruth
from procam.addon.render.scene import projector_frustum
from procam.addon.rig.demo import demo_projector, demo_rig
from procam.addon.rig.model import Rig
from procam.addon.steps import calibrate, capture
from procam.addon.surface.shapes import builtin_surface


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shifts", nargs="+", default=["0,0", "0,60", "0,127", "0,200", "60,0", "-60,-200"])
    ap.add_argument("--surface", default="curve")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--effects", default="realistic")
    args = ap.parse_args(argv)
    rows = []
    for text in args.shifts:
        shift = tuple(float(v) / 100 for v in text.split(","))
        rig = Rig(demo_rig((320, 240), (400, 300)).camera, demo_projector(400, 300, shift=shift))
        k = rig.projector.intrinsics
        frustum = projector_frustum(k)
        t0 = time.perf_counter()
        check = run_cross_check(rig, builtin_surface(args.surface), bounces=0, samples=64, spp=64).summary()
        t_check = time.perf_counter() - t0
        with tempfile.TemporaryDirectory() as tmp:
            caps, truth_path = Path(tmp) / "captures", Path(tmp) / "truth.json"
            t0 = time.perf_counter()
            capture.run_lab(capture.LabOptions(caps, surface=args.surface, effects=args.effects,
                                               samples=args.samples, scale=args.scale, truth=truth_path,
                                               projector_shift=shift))
            cal = calibrate.run(calibrate.CalibrateOptions(caps, Path(tmp) / "calibration", with_blend=False))
            t_cal = time.perf_counter() - t0
            truth = LabTruth.load(truth_path).rig.projector
        est = cal.rig.projector
        pos_mm = 1000 * float(np.linalg.norm(est.position - truth.position))
        ang = float(np.degrees(np.arccos(np.clip(est.direction @ truth.direction, -1, 1))))
        warp = (cal.report.get("warp_report") or {}).get("corners_after_px") or {}
        rows.append((text, k.cy / k.height, frustum.fov_x_deg, frustum.padded_size, check, t_check, pos_mm, ang,
                     warp.get("median", float("nan")), t_cal))
    print(f"surface {args.surface}; cross-check at 320×240 / 400×300 (direct, 64 spp); calibration at scale "
          f"{args.scale:g}, effects {args.effects or 'none'}, {args.samples} spp")
    print("| shift R,U % | cy / H | frustum ° | texture | corners median / max px | intensity |diff| % "
          "| pose mm | axis ° | warp corners px | s (check, lab+cal) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for text, cy, fov, tex, c, tc, pos, ang, wc, tcal in rows:
        print(f"| {text} | {cy:.2f} | {fov:.1f} | {tex[0]}×{tex[1]} | {c['corner_offset_median_px']:.3f} / "
              f"{c['corner_offset_max_px']:.3f} | {c['intensity_mean_abs_diff_pct']:.2f} | {pos:.1f} | {ang:.3f} "
              f"| {wc:.2f} | {tc:.0f}, {tcal:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
