"""Compare calibration folders with the lab truth they came from: pose, depth bias, warp, seconds per stage.

    .venv/bin/python scripts/calibration_report.py CALIB_DIR:TRUTH_JSON [CALIB_DIR:TRUTH_JSON ...]
    .venv/bin/python scripts/calibration_report.py --work /tmp/t2work   # every SURFACE/{calibration,truth.json}

Evaluation code: it reads the truth (the pipeline never does). Prints one
Markdown row per calibration: projector position error (mm) and optical-axis
angle (°) against the truth, the depth bias calibration subtracted against
the lab's, checkerboard corners before → after the warp (median px), and the
seconds of each stage as ``calibration.json`` recorded them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def rows_for(pairs: list[tuple[Path, Path]]) -> list[dict]:
    from procam.addon.lab.truth import LabTruth
    from procam.addon.stages.pose import pose_error

    rows = []
    for cal_dir, truth_path in pairs:
        doc = json.loads((cal_dir / "calibration.json").read_text())
        truth = LabTruth.load(truth_path)
        pos, ang = pose_error(doc["camera_from_projector"], truth.rig.projector.camera_from_projector)
        warp = doc.get("warp_report") or {}
        surface = doc.get("surface_report") or {}
        cam = doc["rig"]["camera"]["intrinsics"]
        rows.append({"calibration": str(cal_dir), "surface": truth.surface_source,
                     "camera": [cam["width"], cam["height"]],
                     "position_mm": 1000 * pos, "direction_deg": ang,
                     "depth_offset_cm": 100 * float(surface.get("depth_offset", 0.0)),
                     "true_bias_cm": 100 * float(truth.effects["depth_noise"]["bias"]),
                     "corners_before_px": (warp.get("corners_before_px") or {}).get("median"),
                     "corners_after_px": (warp.get("corners_after_px") or {}).get("median"),
                     "seconds": doc.get("seconds", {}), "stages": doc.get("stages")})
    return rows


def markdown(rows: list[dict]) -> str:
    def num(v: object, spec: str) -> str:
        return "–" if v is None else format(float(v), spec)

    lines = ["| calibration | camera | position mm | direction ° | depth offset cm (lab bias) | "
             "corners px before → after | surface s | pose s | albedo s | warp s |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        s = r["seconds"]
        lines.append(f"| {r['calibration']} | {r['camera'][0]}×{r['camera'][1]} | {r['position_mm']:.1f} | "
                     f"{r['direction_deg']:.3f} | {r['depth_offset_cm']:.2f} ({r['true_bias_cm']:.2f}) | "
                     f"{num(r['corners_before_px'], '.2f')} → {num(r['corners_after_px'], '.2f')} | "
                     f"{num(s.get('surface'), '.1f')} | {num(s.get('pose'), '.1f')} | {num(s.get('albedo'), '.1f')} | "
                     f"{num(s.get('warp'), '.1f')} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("pairs", nargs="*", help="CALIB_DIR:TRUTH_JSON")
    p.add_argument("--work", type=Path, help="a bench work folder: each SURFACE/calibration with SURFACE/truth.json")
    p.add_argument("--out", type=Path, help="also write the rows as JSON here")
    args = p.parse_args(argv)
    pairs = []
    for spec in args.pairs:
        cal, _, truth = spec.partition(":")
        pairs.append((Path(cal), Path(truth)))
    if args.work:
        pairs += [(d / "calibration", d / "truth.json") for d in sorted(args.work.iterdir())
                  if (d / "calibration" / "calibration.json").is_file() and (d / "truth.json").is_file()]
    if not pairs:
        p.error("give CALIB_DIR:TRUTH_JSON pairs or --work DIR")
    rows = rows_for(pairs)
    print(markdown(rows))
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
