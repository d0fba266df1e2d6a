"""Benchmark of the surface's sources: depth image, Gray code triangulated with the known rig, a registered mesh.

    .venv/bin/python scripts/bench_surface_sources.py [--scale 0.5] [--surfaces plane,curve,vedge,hedge]
        [--samples 8] [--effects ''] [--work DIR]

For each built-in surface it renders a lab capture set (``procam lab``), then
makes the surface as ``procam calibrate``'s surface stage does
(:func:`procam.addon.stages.surface.surface_from_captures`) from

* ``depth``     the capture set's depth image (lab depth, wall-image bias);
* ``graycode``  a copy of the capture set without its depth images whose
                ``capture.json`` marks the projector's pose known, with the TRUE
                pose (what ``import-captures --rig`` with a metric rig gives);
* ``mesh``      the true surface turned 5° and shifted 10 cm, saved as an OBJ and
                registered to the triangulated points (no depth at all; the lit area
                does not show the mesh's outline).

and measures the mean distance to the true surface over the lit area, as
``scripts/bench_surface.py`` does (``normal``: the displacement along each
camera ray projected on the true normal; ``cover``: share of the lit pixels the
surface covers — the Gray code covers only the projector's input area, not
its whole frame). The issue's bar for the triangulated surface is < 3 mm.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_surface import distances, lit_pixels  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--surfaces", default="plane,curve,vedge,hedge")
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--effects", default="")
    ap.add_argument("--work", type=Path, default=None, help="keep the lab sets here (reused when present)")
    args = ap.parse_args()

    from procam.addon.capture.format import CaptureSet
    from procam.addon.cli.app import main as procam
    from procam.addon.errors import ProCamError
    from procam.addon.lab.truth import LabTruth
    from procam.addon.stages.surface import surface_from_captures
    from procam.addon.surface.mesh import SurfaceMesh
    from procam.addon.surface.register import save_obj

    work = args.work or Path(tempfile.mkdtemp(prefix="bench-surface-sources-"))
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for surf in args.surfaces.split(","):
        captures, truth_path = work / surf, work / f"{surf}.truth.json"
        if not captures.exists():
            assert procam(["lab", "--out", str(captures), "--truth", str(truth_path), "--surface", surf, "--scale",
                           str(args.scale), "--samples", str(args.samples), "--effects", args.effects]) == 0
        truth = LabTruth.load(truth_path)  # evaluation only
        rays, depth_true, normals = lit_pixels(truth)
        known = work / f"{surf}-nodepth"
        if not known.exists():
            shutil.copytree(captures, known)
            doc = json.loads((known / "capture.json").read_text())
            doc["images"] = [e for e in doc["images"] if e["kind"] != "depth"]
            doc["projector"]["camera_from_projector"] = truth.rig.projector.camera_from_projector.tolist()
            doc["projector_pose_known"] = True
            (known / "capture.json").write_text(json.dumps(doc))
        axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
        r, _ = cv2.Rodrigues(axis * np.radians(5.0))
        s = truth.surface
        obj = work / f"{surf}-moved.obj"
        save_obj(SurfaceMesh(s.vertices @ r.T + [0.06, -0.05, 0.0632], s.faces, s.uvs, s.albedo), obj)
        for source, folder, kwargs in (("depth", captures, {}), ("graycode", known, {}),
                                       ("mesh", known, {"surface_mesh": obj})):
            t0 = time.perf_counter()
            try:
                mesh, report, _ = surface_from_captures(CaptureSet.load(folder), source, **kwargs)
            except ProCamError as exc:
                rows.append({"surface": surf, "source": source, "refused": str(exc)})
                print(f"# {surf} {source}: refused: {exc}", file=sys.stderr, flush=True)
                continue
            seconds = time.perf_counter() - t0
            row = {"surface": surf, "source": source, **distances(mesh, rays, depth_true, normals),
                   "seconds": seconds}
            if "triangulation" in report:
                row["reprojection_rms_px"] = report["triangulation"]["reprojection_rms_px"]
                row["angle_deg"] = report["triangulation"]["triangulation_angle_deg"]
            if "registration" in report:
                row["registration_rms_mm"] = report["registration"]["rms_mm"]
            rows.append(row)
            print(f"# {surf} {source}: normal mean {10 * row['normal_mean']:.2f} mm, {seconds:.1f} s",
                  file=sys.stderr, flush=True)
    print(f"\nscale {args.scale}, effects {args.effects or 'none'}, lab sets in {work}\n")
    print("| surface | source | mean mm (normal) | median | p95 | signed mm | cover | reprojection px | "
          "ICP residual mm | seconds |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r_ in rows:
        if "refused" in r_:
            refused = r_["refused"].removeprefix("surface: ").split(" (start")[0]
            print(f"| {r_['surface']} | {r_['source']} | refused: {refused} "
                  "| | | | | | | |")
            continue
        rep = f"{r_['reprojection_rms_px']:.2f}" if "reprojection_rms_px" in r_ else ""
        icp = f"{r_['registration_rms_mm']:.2f}" if "registration_rms_mm" in r_ else ""
        print(f"| {r_['surface']} | {r_['source']} | {10 * r_['normal_mean']:.2f} | {10 * r_['normal_median']:.2f} | "
              f"{10 * r_['normal_p95']:.2f} | {10 * r_['signed_mean']:+.2f} | {r_['cover']:.0%} | {rep} | {icp} | "
              f"{r_['seconds']:.1f} |")


if __name__ == "__main__":
    main()
