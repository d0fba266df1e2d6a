#!/usr/bin/env python3
"""Where the stacked closed loop's error is: frequency band, noise or systematic, the solve or the rig, per projector.

Usage: ``.venv/bin/python scripts/bench_stacked_error.py DIR [--targets forest,city] [--blur SIGMA]
[--noise-free]``, DIR a folder of ``scripts/bench_projectors.py --parts stacked --work W`` (``W/curve-stacked``:
``cal``, ``lab.truth.json``, ``targets``).

For each target, the joint closed loop as ``procam compensate`` runs it (``--blur``: each projector's lens blur held
in the solve, σ texels, as ``--effects defocus`` does), then:

* the capture PSNR after each of the loop's captures;
* the final frames captured three times: the error against the target split into a low band (Gaussian σ 1.5 camera
  pixels) and the detail above it, into the camera's noise (the captures' spread) and what is left (systematic), and
  into the high-gradient fifth of the target and the rest; the solve's own prediction against the target;
* each projector alone (the other black) against its own operator's prediction: the sub-pixel shift between them
  (phase correlation of the detail) and the camera-space Gaussian blur that best maps the prediction's detail onto
  the capture's;
* the sharpness ceiling: the best the operators show in the box with no θ and no noise, with a lens blur of σ texels
  held in them (0 the calibrated operators), the most the closed loop could reach if the rig blurred that much.

``--noise-free``: the lab's sensor noise switched off (the sealed truth with that effect at 0, in memory).

``--sources [VARIANTS]``: instead of the loop, where the rig's blur comes from. Each projector alone shows texel
noise (0.5 ± 0.2, every texel drawn apart: the finest detail there is) through the lab as it is, without its lens
defocus, and with the camera rendered at 2 and 4 times its resolution (the lab's camera lens then resamples finer
pixels; the same samples per camera pixel); each capture against the operator's prediction as above. VARIANTS
(comma-separated) names others: ``asis``, ``ss2``…``ss4``, or effects switched off joined by ``+``
(``defocus+distortion``). ``--operator-spp N``: the operators rendered again in memory at N direct samples a pixel.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_projectors as bench  # noqa: E402

from procam.addon.stages import joint as joint_module  # noqa: E402

BAND = 1.5  # camera pixels: the Gaussian that splits the low band from the detail
BLURS = (0.0, 0.45, 0.9, 1.0, 1.3)


def db(mse: Any) -> float:
    return 10.0 * float(np.log10(1.0 / max(mse, 1e-12)))


def low(x: np.ndarray, sigma: float = BAND) -> np.ndarray:
    return cv2.GaussianBlur(np.asarray(x, np.float32), (0, 0), sigma)


def detail(x: np.ndarray, sigma: float = BAND) -> np.ndarray:
    g = np.asarray(x, np.float32).mean(axis=2)
    return g - cv2.GaussianBlur(g, (0, 0), sigma)


def lab_device(path: Path, cal: Any, *effects: str, supersample: int = 1) -> Any:
    """The lab of the truth file ``path`` without ``effects``, through ``cal``'s device pipeline (the camera
    rendered ``supersample`` times finer, with the same samples per camera pixel)."""
    from procam.addon.lab.cycles_device import LabDevice  # bpy: the lab renders with Cycles

    truth = bench.LabTruth.load(path)
    lab = LabDevice(truth.without(*effects), supersample=supersample,
                    samples=max(1, truth.samples // (supersample * supersample)))
    return bench.device_pipeline(f"lab:{path}", cal, device=lab)


def shift_and_blur(capture: np.ndarray, prediction: np.ndarray) -> tuple[float, float, float, float]:
    """(dx, dy) of the capture's detail against the prediction's, the camera-space σ and gain that fit it best."""
    lit = (prediction.mean(axis=2) > 0.05).astype(np.uint8)
    mask = cv2.erode(lit, np.ones((11, 11), np.uint8)).astype(bool)
    a, b = detail(prediction) * mask, detail(capture) * mask
    (dx, dy), _ = cv2.phaseCorrelate(a.astype(np.float64), b.astype(np.float64))
    best = (np.inf, 0.0, 0.0)
    for s in np.arange(0.0, 2.001, 0.05):
        p = detail(prediction if s == 0 else cv2.GaussianBlur(prediction, (0, 0), float(s)))[mask]
        g = float(p @ b[mask] / max(float(p @ p), 1e-12))
        r = float(np.mean((b[mask] - g * p) ** 2))
        if r < best[0]:
            best = (r, float(s), g)
    return float(dx), float(dy), best[1], best[2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--targets", default="forest,city")
    ap.add_argument("--blur", type=float, default=0.0)
    ap.add_argument("--noise-free", action="store_true")
    ap.add_argument("--sources", nargs="?", const=SOURCES, default=None, metavar="VARIANTS")
    ap.add_argument("--operator-spp", type=int, default=None)
    args = ap.parse_args()
    if args.sources:
        blur_sources(args.folder, args.sources, args.operator_spp)
        return
    cal = bench.calibrate_step.read(args.folder / "cal")
    device = lab_device(args.folder / "lab.truth.json", cal, *(["noise"] if args.noise_free else []))
    h = bench.Harness(args.folder / "cal", args.folder / "lab.truth.json", None, device=device)
    try:
        run(h, args)
    finally:
        h.close()


#: ``--sources`` variants when none are named: the lab as it is, without its defocus, its camera rendered finer.
SOURCES = "asis,defocus,ss2,ss4"


def blur_sources(folder: Path, variants: str = SOURCES, operator_spp: int | None = None) -> None:
    """Each projector alone showing texel noise, its capture against its operator's prediction, through each variant
    of the lab: ``asis``, ``ssN`` (camera rendered N× finer, the same samples per camera pixel), or effects to
    switch off joined by ``+`` (``defocus+distortion``). ``operator_spp``: the operators rendered again at that many
    direct samples per pixel (in memory; the stored ones are left as they are)."""
    from procam.addon.stages.transport import build_transport

    cal = bench.calibrate_step.read(folder / "cal")
    comps = bench.projectors.JointStage(cal, bench.StageCOptions()).compensators
    operators = [c.transport if operator_spp is None else build_transport(cal.for_projector(k), spp=operator_spp)
                 for k, c in enumerate(comps)]
    cam = cal.rig.camera.intrinsics.size
    print("each projector alone showing texel noise, its capture against its operator's prediction"
          + ("" if operator_spp is None else f" (operators rendered at {operator_spp} samples a pixel)") + ":")
    for variant in variants.split(","):
        ss = int(variant[2:]) if re.fullmatch(r"ss[1-4]", variant) else 1
        off = variant.split("+") if variant != "asis" and ss == 1 else []
        label = ("the lab as it is" if variant == "asis" else f"camera rendered {ss}x" if ss > 1 else
                 "without " + " and ".join(off))
        device = lab_device(folder / "lab.truth.json", cal, *off, supersample=ss)
        rng = np.random.default_rng(1)  # the same noise for every variant
        try:
            for k, (comp, op) in enumerate(zip(comps, operators)):
                iw, ih = comp.rig.projector.input_size
                z = np.clip(0.5 + 0.2 * rng.standard_normal((ih, iw, 1)), 0, 1).repeat(3, axis=2).astype(np.float32)
                frames = [c.rig.projector.frame_from_input(comp.warp_w(z) if i == k else np.zeros_like(z))
                          for i, c in enumerate(comps)]
                capture = np.mean([bench.projectors.project_all(device, frames, cam) for _ in range(2)], axis=0)
                dx, dy, sigma, gain = shift_and_blur(capture, op.apply(z).reshape(capture.shape))
                print(f"  {label}: projector {k + 1}: shift ({dx:+.3f}, {dy:+.3f}) camera px, blur σ {sigma:.2f} "
                      f"camera px (gain {gain:.2f})", flush=True)
        finally:
            device.close()


def run(h: Any, args: argparse.Namespace) -> None:
    comps = h.stage.compensators
    trace: list[float] = []
    capture = joint_module.JointSolve.capture

    def logged(self: Any, zc: np.ndarray) -> np.ndarray:
        y = capture(self, zc)
        trace.append(db(float(np.mean((y - self.target) ** 2))))
        return y

    joint_module.JointSolve.capture = logged  # type: ignore[method-assign]
    for name in args.targets.split(","):
        fitted, area = h.fitted(args.folder / "targets" / f"{name}.png")
        for c in comps:
            c.input_blur = args.blur or None
        trace.clear()
        res = h.stage.joint.run(fitted, area, device=h.device, **h.options.run_arguments())
        ys = [area.crop(bench.projectors.project_all(h.device, res.x_frames, h.cam)) for _ in range(3)]
        y, mean_y, pred = ys[0], np.mean(ys, axis=0), area.crop(res.simulated)
        e = y - fitted
        noise = float(np.mean([np.mean((c - mean_y) ** 2) for c in ys])) * 1.5
        systematic = float(np.mean((mean_y - fitted) ** 2)) - noise / 3
        sys_e = mean_y - fitted
        lap = np.abs(cv2.Laplacian(fitted.mean(axis=2), cv2.CV_32F))
        edges = lap > np.percentile(lap, 80)
        print(f"\n{name}, blur held {args.blur} texels{', noise-free lab' if args.noise_free else ''}: capture "
              f"PSNR per capture " + " ".join(f"{p:.2f}" for p in trace))
        mse = {"all": np.mean(e ** 2), "low": np.mean(low(e) ** 2), "detail": np.mean(detail(e) ** 2),
               "edges": np.mean(e[edges] ** 2), "rest": np.mean(e[~edges] ** 2)}
        print(f"  final capture {db(mse['all']):.2f} dB: low band {db(mse['low']):.2f}, detail {db(mse['detail']):.2f}"
              f"; high-gradient fifth {db(mse['edges']):.2f}, the rest {db(mse['rest']):.2f}")
        print(f"  noise {db(noise):.2f} dB, systematic {db(systematic):.2f} dB (its low band "
              f"{db(float(np.mean(low(sys_e) ** 2))):.2f}); the solve's prediction against the target "
              f"{db(float(np.mean((pred - fitted) ** 2))):.2f}, the capture against the prediction "
              f"{db(float(np.mean((y - pred) ** 2))):.2f}")
        black = [np.zeros_like(f) for f in res.x_frames]
        for k, comp in enumerate(comps):
            frames = [f if i == k else b for i, (f, b) in enumerate(zip(res.x_frames, black))]
            alone = np.mean([bench.projectors.project_all(h.device, frames, h.cam) for _ in range(2)], axis=0)
            predicted = comp.transport.apply(comp.transport_view(area).blur(res.z[k]) if args.blur else res.z[k])
            dx, dy, sigma, gain = shift_and_blur(alone, predicted)
            print(f"  projector {k + 1} alone against its operator: shift ({dx:+.3f}, {dy:+.3f}) camera px, "
                  f"its detail fits the prediction blurred by σ {sigma:.1f} camera px (gain {gain:.2f})")
        ceiling = []
        for s in BLURS:
            for c in comps:
                c.input_blur = s or None
            r = h.stage.joint.run(fitted, area, use_bias=False, iterations_z=300, iterations_joint=0, blend="none")
            ceiling.append(f"σ {s}: {r.report['psnr_simulated']:.2f}")
        print("  sharpness ceiling (no θ, no noise, 300 iterations): " + ", ".join(ceiling) + " dB", flush=True)


if __name__ == "__main__":
    main()
