#!/usr/bin/env python3
"""The MPCDI hand-off measured: content through the exported warp + alpha + beta projected in the two-projector lab,
against ProCam's own joint compensation and the linear-ramp baseline; and export time and file size at 1920×1080.

Usage: ``.venv/bin/python scripts/bench_mpcdi.py [--parts lab,timing] [--scale 0.3] [--samples 8] [--targets 3]
[--iterations N] [--work DIR]``

``lab``: two projectors side by side on the curve, 20 % overlap, ``realistic`` effects, projector 2 with a tone
curve of its own (``bench_projectors.py``'s lab and harness), calibrated (so the transport operators are stored and
the blend is the joint blend's). Per natural target: the MPCDI file exported for the target's display area
(``procam export-mpcdi --area``, content = the target fitted to the area), the frame each projector shows for it
as a media server applies the file (``procam apply-mpcdi``: ``Pi·α·(1 − β) + β``), all shown at once through the
lab and scored like ProCam's own answers: PSNR over the area, inside the overlap and outside it, and the seam step;
beside it ProCam's joint compensation (open loop, derived blend) and each projector compensated alone on its linear
edge-blend ramp (open loop), on the same lab. The hand-off shows the content as it is: it keeps the geometry, the
blend and the black floor, and loses every per-pixel correction of the surface (texture, brightness fall-off,
bounce light) and of the projectors' response — the PSNR gap to ProCam's compensation is that; the seam step is
what the blend alone achieves.
``timing``: export time and file size for 2 and 4 projectors at 1920×1080 (camera 640×480, curve, side by side,
warp grid every 4 pixels), from calibrations of the lab's true rig made in memory (no renders: the lab cannot
render 4 projectors at 1920×1080 quickly, and the export does not need them); the blend is the geometric ramps
(there is no light-transport operator at that size) and the beta map is zero (no captures), the content spans the
camera's whole view (``--area 0,0,640,480``): what the timing covers is tracing every pixel, sampling the maps and
writing the archive.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_projectors import Harness, lab, mean, targets_for  # noqa: E402

from procam.addon.lab.truth import make_truth  # noqa: E402
from procam.addon.mpcdi import apply as apply_mpcdi  # noqa: E402
from procam.addon.mpcdi.format import read_mpcdi  # noqa: E402
from procam.addon.stages.calibrate import Calibration  # noqa: E402
from procam.addon.steps import calibrate as calibrate_step  # noqa: E402
from procam.addon.steps.mpcdi import ExportMpcdiOptions, derive, run_export, write  # noqa: E402


def lab_part(work: Path, args: argparse.Namespace) -> None:
    args.effects = "realistic"
    cal_dir, truth_path = lab(work, "curve", "side-by-side", args)
    h = Harness(cal_dir, truth_path, args.iterations)
    rows: dict[str, list[dict[str, Any]]] = {"mpcdi": [], "derived": [], "ramps": []}
    notes = []
    try:
        area0 = h.stage.area_for(np.zeros((300, 400, 3), np.float32))
        for path in targets_for(work, area0, args.targets):
            fitted, area = h.fitted(path)
            out = work / f"{path.stem}.mpcdi"
            done = run_export(ExportMpcdiOptions(cal_dir, out, content_size=area.size,
                                                 area=(area.x, area.y, area.width, area.height), force=True))
            notes.append(f"{path.stem}: {done.report['blend'].split(':')[0]}, {done.report.get('beta')}, "
                         f"beta max {max(p['beta_max'] for p in done.report['projectors']):.3f}, {done.bytes} bytes")
            m = read_mpcdi(out)
            frames = apply_mpcdi.frames(m, fitted)
            rows["mpcdi"].append(h.score(frames, fitted, area))
            for how in ("derived", "ramps"):
                rows[how].append(h.score(h.solve(h.stage.joint, fitted, area, how).x_frames, fitted, area))
    finally:
        h.close()
    print(f"\ncurve, two projectors side by side, 20 % overlap, realistic, scale {args.scale}, {args.targets} "
          "targets, open loop")
    for n in notes:
        print(f"  {n}")
    print("| | PSNR | inside the overlap | outside it | along its edge | seam step |")
    print("|---|---|---|---|---|---|")
    for how, label in (("mpcdi", "MPCDI hand-off (warp + alpha + beta, content as is)"),
                       ("derived", "ProCam joint compensation"), ("ramps", "each alone on linear edge-blend ramps")):
        r = rows[how]
        print(f"| {label} | {mean(r, 'psnr'):.2f} | {mean(r, 'psnr_overlap'):.2f} | {mean(r, 'psnr_outside'):.2f} | "
              f"{mean(r, 'psnr_border'):.2f} | {mean(r, 'seam_step'):.4f} |")


def timing_part(work: Path, args: argparse.Namespace) -> None:
    print("\nexport time and size, 1920×1080 projectors, camera 640×480, curve side by side, warp grid every 4 px")
    print("| projectors | derive (trace + maps) s | write s | total s | file MB | warp grid |")
    print("|---|---|---|---|---|---|")
    for count in (2, 4):
        truth = make_truth("curve", camera_size=(640, 480), projector_size=(1920, 1080), projectors=count,
                           layout="side-by-side", overlap=0.2)
        cal = Calibration(truth.rig, truth.surface, None, "", other_warps=(None,) * (count - 1))
        folder = work / f"cal-{count}"
        if not folder.exists():
            folder.mkdir()
            calibrate_step.write(folder, cal, {})
        out = work / f"show-{count}.mpcdi"
        # The content over the camera's whole view: four projectors side by side reach past the largest 16:9
        # rectangle their union holds, and the timing is of every pixel of every projector.
        options = ExportMpcdiOptions(folder, out, area=(0, 0, 640, 480), force=True)
        t0 = time.perf_counter()
        done, _ = derive(options)
        t1 = time.perf_counter()
        size = write(done.mpcdi, out, force=True)
        t2 = time.perf_counter()
        grid = done.report["projectors"][0]["warp_grid"]
        print(f"| {count} | {t1 - t0:.1f} | {t2 - t1:.1f} | {t2 - t0:.1f} | {size / 1e6:.1f} | {grid[0]}×{grid[1]} |")


PARTS = {"lab": lab_part, "timing": timing_part}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--parts", default="lab,timing")
    ap.add_argument("--scale", type=float, default=0.3)
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--targets", type=int, default=3)
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--work", type=Path, help="keep the folders here and reuse them")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for part in args.parts.split(","):
            PARTS[part](work, args)


if __name__ == "__main__":
    main()
