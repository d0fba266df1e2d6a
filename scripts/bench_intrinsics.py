"""Projector intrinsics from a wrong spec sheet: kept (``--projector-intrinsics spec``) or fitted to the Gray code
(``fit``), on each lab surface, down to the compensation's PSNR.

    .venv/bin/python scripts/bench_intrinsics.py [--surfaces plane,curve,vedge,hedge] [--scale 0.5]
        [--nominal-error 10,20] [--camera-fov-error 0] [--effects realistic] [--samples 16] [--targets city]
        [--iterations N] [--supersample 1] [--projectors 1]

For each surface: a lab capture set whose projector spec is wrong by ``--nominal-error`` (focal length %, vertical
lens shift % of the height) and whose camera's field of view is ``--camera-fov-error`` degrees off, calibrated
both ways; focal length (%) and principal point (px) errors, projector
position (mm) and axis (°) errors against the sealed truth; then closed-loop compensation through the lab of the
built-in targets with each calibration, and its PSNR (the evaluate step's, inside the display area).
``--projectors 2`` lays two projectors side by side (both with the wrong spec): a row per projector, each fitted to
its own Gray code with the camera held (the PSNR is the rig's, on each row).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from procam.addon.capture.targets import natural_target
from procam.addon.imageio import write_image
from procam.addon.lab.effects import lens_of
from procam.addon.lab.truth import LabTruth
from procam.addon.stages.display_area import choose_area
from procam.addon.steps import calibrate, capture, compensate, evaluate
from procam.addon.steps.stage_c import StageCOptions


def lens_taken_out(caps: Path, truth: LabTruth, root: Path) -> Path:
    """``caps`` with the lab's true camera lens taken out (``procam undistort-captures``), through a rig file that
    holds the true camera K and lens as a board calibration of the camera would (the projector's part is not read)."""
    from procam.addon.stages.rig_calibration import RigCalibration
    from procam.addon.steps.rig import write

    cam = truth.rig.camera.intrinsics
    proj = truth.rig.projectors[0].intrinsics
    lens = lens_of(truth.effects) or (0.0, 0.0, 0.0, 0.0)
    rig = write(root / "camera-rig.json", RigCalibration.known(cam.size, proj.size, cam.opencv_matrix(),
                                                               [*lens, 0.0], proj.opencv_matrix()))  # k1 k2 p1 p2 k3
    out = root / "captures-pinhole"
    capture.run_undistort(capture.UndistortOptions(caps, rig=rig, out=out))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--surfaces", default="plane,curve,vedge,hedge")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--nominal-error", default="10,20")
    ap.add_argument("--camera-fov-error", type=float, default=0.0)
    ap.add_argument("--supersample", type=int, default=1, help="as procam lab's")
    ap.add_argument("--effects", default="realistic")
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--targets", default="city")
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--projectors", type=int, default=1, help="as procam lab's (side by side)")
    ap.add_argument("--camera-lens", choices=("fitted", "given"), default="fitted",
                    help="given: the camera's lens taken out of the set first (procam undistort-captures with a "
                         "rig file holding the lab's true camera K and lens, as a board calibration of the camera "
                         "gives it) before calibrating; fitted: the Gray code fits it with the projector's K")
    args = ap.parse_args(argv)
    error = tuple(float(v) / 100 for v in args.nominal_error.split(","))
    print(f"spec wrong by {args.nominal_error} (focal %, shift % of height), "
          f"camera FoV {args.camera_fov_error:+g}°, camera lens {args.camera_lens}; scale {args.scale:g}, effects "
          f"{args.effects or 'none'}, {args.samples} spp; targets {args.targets}, closed loop, fast schedule")
    print("| surface | projector | K from | focal err % | principal point err px | determined | camera focal err % | "
          "pose mm | axis ° | PSNR dB |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for surface in args.surfaces.split(","):
        with tempfile.TemporaryDirectory() as tmp:
            root = Path(tmp)
            caps, truth_path = root / "captures", root / "truth.json"
            capture.run_lab(capture.LabOptions(caps, surface=surface, effects=args.effects, samples=args.samples,
                                               scale=args.scale, truth=truth_path, nominal_error=error,
                                               camera_fov_error=args.camera_fov_error,
                                               supersample=args.supersample, projectors=args.projectors))
            truth = LabTruth.load(truth_path)
            if args.camera_lens == "given":
                caps = lens_taken_out(caps, truth, root)
            cals = {m: calibrate.run(calibrate.CalibrateOptions(caps, root / f"cal-{m}", with_blend=False,
                                                                projector_intrinsics=m)) for m in ("spec", "fit")}
            area = choose_area(cals["fit"], aspect=4 / 3)
            (root / "targets").mkdir()
            targets = tuple(write_image(root / "targets" / f"{n}.png", natural_target(n, area.size))
                            for n in args.targets.split(","))
            for m, cal in cals.items():
                device = f"lab:{truth_path}"
                compensate.run(compensate.CompensateOptions(
                    root / f"cal-{m}", targets, root / f"comp-{m}",
                    StageCOptions(iterations=args.iterations, device=device)))
                metrics = evaluate.run(evaluate.EvaluateOptions(root / f"cal-{m}", root / f"comp-{m}", targets,
                                                                device, root / f"eval-{m}"))
                psnr = np.mean([t["psnr"] for t in metrics["targets"] if t.get("status") == "done"])
                cam_err = 100 * (cal.rig.camera.intrinsics.fx / truth.rig.camera.intrinsics.fx - 1)
                for j in range(cal.projector_count):
                    one, tp = cal.for_projector(j), truth.rig.projectors[j]
                    k, p, tk = one.rig.projector.intrinsics, one.rig.projector, tp.intrinsics
                    pos = 1000 * float(np.linalg.norm(p.position - tp.position))
                    ang = float(np.degrees(np.arccos(np.clip(p.direction @ tp.direction, -1, 1))))
                    det = (one.report.get("projector_intrinsics") or {}).get("determined")
                    lens = (one.report.get("projector_intrinsics") or {}).get("camera_distortion") or {}
                    if lens.get("determined"):
                        print(f"#   {surface} {m} projector {j + 1}: camera k1 {lens['k1']:+.4f}, k2 "
                              f"{lens['k2']:+.4f} (lab: {truth.effects['distortion']['k1']:+.4f}, "
                              f"{truth.effects['distortion']['k2']:+.4f})", flush=True)
                    det_s = "—" if det is None else ", ".join(n for n, v in det.items() if v) or "nothing"
                    print(f"| {surface} | {j + 1} | {m} | {100 * (k.fx / tk.fx - 1):+.2f} | "
                          f"{np.hypot(k.cx - tk.cx, k.cy - tk.cy):.1f} | {det_s} | {cam_err:+.2f} | {pos:.1f} | "
                          f"{ang:.3f} | {psnr:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
