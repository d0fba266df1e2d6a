#!/usr/bin/env python3
"""Where the open-loop seam step of two projectors side by side comes from: the joint solve with the blend's reach
capped and without, against the edge-blend ramps, each projected through the lab and scored.

Usage: ``.venv/bin/python scripts/bench_seam.py LAB_FOLDER [--targets forest,courtyard,city]`` where LAB_FOLDER is a
folder ``scripts/bench_projectors.py --parts side --work DIR`` made (``DIR/curve-side-by-side``: ``lab``,
``lab.truth.json``, ``cal``, ``targets``). Per way: PSNR over the area, inside the overlap, outside it, the seam
step of the capture, of the solve's own prediction (against the target: what the solve asks for) and of the
capture against that prediction (what the model misses); and the seam step of the range ceiling itself.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_projectors import Harness  # noqa: E402

from procam.addon.stages.joint import JointCompensator  # noqa: E402
from procam.addon.steps import calibrate as calibrate_step  # noqa: E402
from procam.addon.steps import projectors  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--targets", default="forest,courtyard,city")
    args = ap.parse_args()
    work = args.folder
    h = Harness(work / "cal", work / "lab.truth.json", None)
    captures = calibrate_step.captures_of(h.cal)
    assert captures is not None
    black, white = projectors.combined_black_white(captures)
    cover = h.stage.coverage()
    ways = {"ours, reach capped": JointCompensator(h.stage.compensators),
            "ours, reach not capped": JointCompensator(h.stage.compensators, cap_reach=False), "ramps": None}
    rows: dict[str, list[list[float]]] = {w: [] for w in ways}
    ceiling = []
    try:
        for name in args.targets.split(","):
            fitted, area = h.fitted(work / "targets" / f"{name}.png")
            masks = projectors.overlap_masks(cover, area)
            ceiling.append(projectors.seam_step(np.clip(fitted, area.crop(black), area.crop(white)), fitted,
                                                masks["overlap"]))
            for way, joint in ways.items():
                res = h.solve(h.stage.joint, fitted, area, "ramps") if joint is None else \
                    h.solve(joint, fitted, area, "derived")
                capture = projectors.project_all(h.device, res.x_frames, h.cam)
                s = projectors.score(capture, fitted, area, masks)
                predicted = area.crop(res.simulated)
                rows[way].append([s["psnr"], s["psnr_overlap"], s["psnr_outside"], s["seam_step"],
                                  projectors.seam_step(predicted, fitted, masks["overlap"]),
                                  projectors.seam_step(area.crop(capture), predicted, masks["overlap"])])
    finally:
        h.close()
    print(f"{work}, open loop, targets {args.targets}; range ceiling's own seam step {np.mean(ceiling):.4f}")
    print("| | PSNR | inside the overlap | outside it | seam step | of the prediction | capture vs prediction |")
    print("|---|---|---|---|---|---|---|")
    for way, r in rows.items():
        m = np.mean(np.asarray(r, np.float64), axis=0)
        print(f"| {way} | {m[0]:.2f} | {m[1]:.2f} | {m[2]:.2f} | {m[3]:.4f} | {m[4]:.4f} | {m[5]:.4f} |")


if __name__ == "__main__":
    main()
