#!/usr/bin/env python3
"""Where the stacked closed loop's error is: frequency band, noise or systematic, the solve or the rig, per projector.

Usage: ``.venv/bin/python scripts/bench_stacked_error.py DIR [--targets forest,city] [--blur SIGMA]
[--noise-free] [--off EFFECTS] [--oracle-operators]``, ``… DIR --oracle``, ``… DIR --sources``; DIR a folder of
``scripts/bench_projectors.py --parts stacked --work W`` (``W/curve-stacked``: ``cal``, ``lab.truth.json``,
``targets``).

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

``--noise-free``: the lab's sensor noise switched off (the sealed truth with that effect at 0, in memory); ``--off
EFFECTS`` (comma-separated) switches off others. ``--iterations-joint N``, ``--captures N``: the transport
schedule's closed loop with more solver steps or captures.

``--oracle [--spacing S]``: the oracle ceiling, the most any inputs in [0, 1] show through the lab's own light
transport rather than through ProCam's model of it. Each projector's transport is measured from the lab's captures
(lattices of every S-th texel, the lab's nonlinear effects, offsets, noise and bounce light switched off and every
shot drawn with the same random numbers, so that it is linear; kept in ``DIR/oracle-S.npz``), checked against a
capture of texel noise, then the open-loop solve runs on it (as the reach ceiling, 1,000 steps) for every target
(``--targets``, default all six) and is printed beside the camera's noise and ours from the bench's evaluations
(``DIR/eval-plain``, ``DIR/eval-blur`` or ``--held FOLDER``), and again through the lab camera's white balance
and tone curve (the light solved for, then Newton's steps on it). ``--oracle-operators``: the closed loop above on
those measured operators instead of the rendered ones.

``--sources [VARIANTS]``: instead of the loop, where the rig's blur comes from. Each projector alone shows texel
noise (0.5 ± 0.2, every texel drawn apart: the finest detail there is) through the lab as it is, without its lens
defocus, and with the camera rendered at 2 and 4 times its resolution (the lab's camera lens then resamples finer
pixels; the same samples per camera pixel); each capture against the operator's prediction as above. VARIANTS
(comma-separated) names others: ``asis``, ``ss2``…``ss4``, or effects switched off joined by ``+``
(``defocus+distortion``). ``--operator-spp N``: the operators rendered again in memory at N direct samples a pixel.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_projectors as bench  # noqa: E402

from procam.addon.stages import joint as joint_module  # noqa: E402
from procam.addon.stages.schedule import get_schedule  # noqa: E402

BAND = 1.5  # camera pixels: the Gaussian that splits the low band from the detail
BLURS = (0.0, 0.45, 0.9, 1.0, 1.3)


def db(mse: Any) -> float:
    return 10.0 * float(np.log10(1.0 / max(mse, 1e-12)))


def low(x: np.ndarray, sigma: float = BAND) -> np.ndarray:
    return cv2.GaussianBlur(np.asarray(x, np.float32), (0, 0), sigma)


def detail(x: np.ndarray, sigma: float = BAND) -> np.ndarray:
    g = np.asarray(x, np.float32).mean(axis=2)
    return g - cv2.GaussianBlur(g, (0, 0), sigma)


def lab_device(path: Path, cal: Any, *effects: str, supersample: int = 1, repeat_draws: bool = False) -> Any:
    """The lab of the truth file ``path`` without ``effects``, through ``cal``'s device pipeline (the camera
    rendered ``supersample`` times finer, with the same samples per camera pixel; ``repeat_draws``: every shot
    rendered with the first shot's random numbers, so the lab is linear in what it is shown)."""
    from procam.addon.lab.cycles_device import LabDevice  # bpy: the lab renders with Cycles

    truth = bench.LabTruth.load(path)
    lab = LabDevice(truth.without(*effects), supersample=supersample, repeat_draws=repeat_draws,
                    samples=max(1, truth.samples // (supersample * supersample)))
    return bench.device_pipeline(f"lab:{path}", cal, device=lab)


def alone(device: Any, comps: list[Any], k: int, z: np.ndarray) -> np.ndarray:
    """The capture of projector ``k`` showing the virtual input ``z`` (through its warp), the others black."""
    frames = [c.rig.projector.frame_from_input(c.warp_w(z) if i == k else np.zeros(
        (c.rig.projector.input_size[1], c.rig.projector.input_size[0], 3), np.float32)) for i, c in enumerate(comps)]
    return bench.projectors.project_all(device, frames, comps[0].camera_size)


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
    ap.add_argument("--oracle", action="store_true")
    ap.add_argument("--oracle-operators", action="store_true")
    ap.add_argument("--off", default="", metavar="EFFECTS")
    ap.add_argument("--iterations-joint", type=int, default=None)
    ap.add_argument("--captures", type=int, default=None)
    ap.add_argument("--spacing", type=int, default=ORACLE_SPACING)
    ap.add_argument("--held", default="eval-blur", metavar="FOLDER")
    args = ap.parse_args()
    if args.sources:
        blur_sources(args.folder, args.sources, args.operator_spp)
        return
    if args.oracle:
        oracle(args.folder, args.targets if args.targets != ap.get_default("targets") else ALL_TARGETS,
               args.spacing, args.held)
        return
    cal = bench.calibrate_step.read(args.folder / "cal")
    off = (["noise"] if args.noise_free else []) + [e for e in args.off.split(",") if e]
    device = lab_device(args.folder / "lab.truth.json", cal, *off)
    h = bench.Harness(args.folder / "cal", args.folder / "lab.truth.json", None, device=device)
    try:
        if args.oracle_operators:
            for c, op in zip(h.stage.compensators, oracle_operators(args.folder, cal, h.stage.compensators,
                                                                      args.spacing)):
                c.transport = op
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
                capture = np.mean([alone(device, comps, k, z) for _ in range(2)], axis=0)
                dx, dy, sigma, gain = shift_and_blur(capture, op.apply(z).reshape(capture.shape))
                print(f"  {label}: projector {k + 1}: shift ({dx:+.3f}, {dy:+.3f}) camera px, blur σ {sigma:.2f} "
                      f"camera px (gain {gain:.2f})", flush=True)
        finally:
            device.close()


#: What the oracle's lab switches off: what is not linear in the light shown (the projectors' and the camera's
#: responses; the colour crosstalk, which a white lattice cannot tell apart per channel), the offsets (black level),
#: the sensor noise, and the bounced light (a lattice capture would give it to the nearest node). What stays is what
#: blurs, dims or bends the light on its way: the projectors' defocus and vignetting, the glossy lobe, the camera's
#: lens distortion.
ORACLE_OFF = ("noise", "response", "crosstalk", "black_level", "camera_response", "interreflection")
#: Lattice spacing (texels) of the oracle's captures: wider than the widest blurred footprint (the lab's defocus is
#: σ 0.9 texel with a disk, the camera's lens about 0.7 texel more), so each camera pixel sees one node.
ORACLE_SPACING = 12
#: Entries kept per camera pixel (a blurred footprint spans more texels than the rendered operators' 16).
ORACLE_ENTRIES = 36
ALL_TARGETS = "city,courtyard,forest,interior,studio,sunrise"


def measured_operator(device: Any, comps: list[Any], k: int, cam: tuple[int, int], spacing: int) -> Any:
    """Projector ``k``'s light transport read off the lab's own captures instead of rendered from the calibration:
    one capture per lattice offset (every ``spacing``-th texel white, the rest and the other projectors black, the
    black capture taken off), each camera pixel's value given to the lattice node nearest where the calibration
    says it looks, the largest :data:`ORACLE_ENTRIES` kept."""
    from procam.addon.stages.transport import TransportOperator, camera_to_input, largest_entries, lattice_nodes

    iw, ih = comps[k].rig.projector.input_size
    u, lit = camera_to_input(comps[k].calibration, cam)
    flat_u, ok = u.reshape(-1, 2), lit.ravel()
    black = alone(device, comps, k, np.zeros((ih, iw, 3), np.float32)).reshape(-1, 3)
    index, weight = [], []
    for a in range(spacing):
        for b in range(spacing):
            z = np.zeros((ih, iw, 3), np.float32)
            z[a::spacing, b::spacing] = 1.0
            img = alone(device, comps, k, z).reshape(-1, 3) - black
            node, inside = lattice_nodes(flat_u, ok, a, b, spacing, (iw, ih))
            index.append(node)
            weight.append(np.where(inside[:, None], np.maximum(img, 0.0), 0.0).astype(np.float32))
        print(f"  projector {k + 1}: lattice row {a + 1}/{spacing} captured", flush=True)
    idx, w, dropped = largest_entries(np.stack(index, axis=1), np.stack(weight, axis=1), ORACLE_ENTRIES)
    op = TransportOperator(tuple(cam), (iw, ih), idx, w, (0, 0), np.zeros((0, 1, 1, 3), np.float32))
    op.report = {"light_dropped": round(dropped, 5), "black": black}
    return op


def oracle_operators(folder: Path, cal: Any, comps: list[Any], spacing: int) -> list[Any]:
    """Every projector's :func:`measured_operator` through the lab without :data:`ORACLE_OFF` (kept in
    ``folder/oracle-SPACING.npz`` once measured), each checked against a capture of texel noise."""
    from procam.addon.stages.transport import TransportOperator

    cam = cal.rig.camera.intrinsics.size
    store = folder / f"oracle-{spacing}.npz"
    device = lab_device(folder / "lab.truth.json", cal, *ORACLE_OFF, repeat_draws=True)
    print(f"the lab without {', '.join(ORACLE_OFF)}, every shot with the first shot's random numbers; lattice every "
          f"{spacing} texels:", flush=True)
    try:
        if store.exists():
            data = np.load(store)
            ops = []
            for k in range(len(comps)):
                op = TransportOperator.from_arrays({n.split("-", 1)[1]: data[n] for n in data.files
                                                    if n.startswith(f"{k}-")})
                op.report = {"light_dropped": float(data[f"{k}-dropped"]), "black": data[f"{k}-black"]}
                ops.append(op)
        else:
            ops = [measured_operator(device, comps, k, cam, spacing) for k in range(len(comps))]
            arrays = {f"{k}-{n}": v for k, op in enumerate(ops) for n, v in op.arrays().items()}
            arrays.update({f"{k}-dropped": np.asarray(op.report["light_dropped"]) for k, op in enumerate(ops)})
            arrays.update({f"{k}-black": op.report["black"] for k, op in enumerate(ops)})
            np.savez(store, **arrays)
        rng = np.random.default_rng(1)
        for k, (comp, op) in enumerate(zip(comps, ops)):
            iw, ih = comp.rig.projector.input_size
            z = np.clip(0.5 + 0.2 * rng.standard_normal((ih, iw, 1)), 0, 1).repeat(3, axis=2).astype(np.float32)
            capture = alone(device, comps, k, z) - op.report["black"].reshape(cam[1], cam[0], 3)
            pred = op.apply(z).reshape(capture.shape)
            lit = pred.mean(axis=2) > 0.05
            dx, dy, sigma, gain = shift_and_blur(capture, pred)
            rendered = shift_and_blur(capture, comp.transport.apply(z).reshape(capture.shape))
            print(f"  projector {k + 1}: light dropped {op.report['light_dropped']:.4f}; texel noise captured against "
                  f"the measured operator {db(float(np.mean((capture - pred)[lit] ** 2))):.2f} dB, shift "
                  f"({dx:+.3f}, {dy:+.3f}) px, blur σ {sigma:.2f} px (gain {gain:.2f}); against the rendered "
                  f"operator blur σ {rendered[2]:.2f} px", flush=True)
    finally:
        device.close()
    return ops


def oracle(folder: Path, targets: str, spacing: int, held: str = "eval-blur") -> None:
    """The most any inputs in [0, 1] show through the lab's own light transport (measured, module doc of
    :func:`measured_operator`), next to the noise ceiling and ours from the bench's evaluations (``eval-plain``,
    and ``held``: with the blur held)."""
    cal = bench.calibrate_step.read(folder / "cal")
    stage = bench.projectors.JointStage(cal, bench.StageCOptions())
    comps = stage.compensators
    names = targets.split(",")
    fitted = {}
    for name in names:  # the display area and fitted target of the bench's own runs, before the operators change
        image, _ = stage.load(folder / "targets" / f"{name}.png")
        area = stage.area_for(image)
        fitted[name] = (stage.fitted(image, area), area)
    ops = oracle_operators(folder, cal, comps, spacing)
    for c, op in zip(comps, ops):
        c.input_blur = None
        c.transport = op
    evals = {key: {t["name"]: t for t in json.loads((folder / sub / "metrics.json").read_text())["targets"]}
             for key, sub in (("plain", "eval-plain"), ("blur", held)) if (folder / sub / "metrics.json").exists()}
    curve = camera_of(bench.LabTruth.load(folder / "lab.truth.json"))
    print("\n| target | oracle ceiling (500 / 1000 steps) | through the camera's noise | with the camera's curve, "
          "through the noise | noise ceiling | ours | ours, blur held | ours (blur held) below the oracle through "
          "the noise | below it with the curve |\n|---|---|---|---|---|---|---|---|---|")
    rows = []
    for name in names:
        f, area = fitted[name]
        best = [stage.joint.run(f, area, use_bias=False, iterations_z=n, iterations_joint=0, blend="none")
                .report["psnr_simulated"] for n in (bench.REACH_ITERATIONS // 2, bench.REACH_ITERATIONS)]
        plain, blur = (evals.get(key, {}).get(name, {}) for key in ("plain", "blur"))
        noise_mse = float(plain.get("capture_noise_rmse", 0.0)) ** 2
        through = db(10 ** (-best[1] / 10) + noise_mse)
        # the oracle's lab has no camera curve; the real lab's camera takes the light through it
        curved = db(curved_best(stage, f, area, curve) + noise_mse)
        ours, held = plain.get("psnr", float("nan")), blur.get("psnr", float("nan"))
        rows.append((best[1], through, curved, plain.get("noise_ceiling", float("nan")), ours, held, through - held,
                     curved - held))
        print(f"| {name} | {best[0]:.2f} / {best[1]:.2f} | {through:.2f} | {curved:.2f} | {rows[-1][3]:.2f} | "
              f"{ours:.2f} | {held:.2f} | {through - held:.2f} | {curved - held:.2f} |", flush=True)
    m = np.mean(rows, axis=0)
    print("| mean | " + " | ".join(f"{v:.2f}" for v in m) + " |")


#: Outer steps of :func:`curved_best` (each a warm-started solve of :data:`CURVED_STEPS` steps).
CURVED_ROUNDS, CURVED_STEPS = 6, 300


def curved_best(stage: Any, f: np.ndarray, area: Any, curve: tuple[Any, Any]) -> float:
    """The least MSE found against ``f`` (captured values) through the lab camera's white balance and tone curve
    (``curve``: :func:`camera_of`): the light that gives ``f`` through them solved for, then Newton's step per
    pixel on that light from what the answer shows through them, warm-started each round; an answer within
    reach, so at most the best there is."""
    fwd, inv = curve
    want, zs, best = inv(f), None, np.inf
    for _ in range(CURVED_ROUNDS):
        r = stage.joint.run(want, area, use_bias=False, iterations_z=CURVED_STEPS, iterations_joint=0,
                            blend="none", start=zs)
        light = area.crop(r.simulated)
        seen = fwd(light)
        best = min(best, float(np.mean((seen - f) ** 2)))
        lo, hi = np.maximum(light - 1e-3, 0.0), light + 1e-3
        slope = (fwd(hi) - fwd(lo)) / (hi - lo)
        want = np.clip(want + (f - seen) / np.maximum(slope, 0.05), 0.0, None)
        zs = r.z
    return best


def camera_of(truth: Any) -> tuple[Any, Any]:
    """The lab camera's white balance and tone curve as (light → captured value, its inverse), identities when
    the truth has none (what the oracle's linear lab leaves out)."""
    from procam.addon.gap.models import camera_curve, inverse_camera_curve

    e = truth.effects["camera_response"]
    if not e.active:
        return (lambda x: x), (lambda y: y)
    gains = np.array([e["gain_r"], 1.0, e["gain_b"]], np.float32)
    c = float(e["curve"])
    return ((lambda x: camera_curve(np.clip(x * gains, 0.0, 1.0), c)),
            (lambda y: np.clip(inverse_camera_curve(y, c) / gains, 0.0, None)))


def run(h: Any, args: argparse.Namespace) -> None:
    comps = h.stage.compensators
    trace: list[float] = []
    capture = joint_module.JointSolve.capture

    def logged(self: Any, zc: np.ndarray) -> np.ndarray:
        y = capture(self, zc)
        trace.append(db(float(np.mean((y - self.target) ** 2))))
        return y

    joint_module.JointSolve.capture = logged  # type: ignore[method-assign]
    schedule: dict[str, Any] = {}
    if args.iterations_joint or args.captures:
        base = get_schedule("transport")
        schedule["schedule"] = replace(base, iterations_joint=args.iterations_joint or base.iterations_joint,
                                       captures=args.captures or base.captures)
    for name in args.targets.split(","):
        fitted, area = h.fitted(args.folder / "targets" / f"{name}.png")
        for c in comps:
            c.input_blur = args.blur or None
        trace.clear()
        res = h.stage.joint.run(fitted, area, device=h.device, **{**h.options.run_arguments(), **schedule})
        ys = [area.crop(bench.projectors.project_all(h.device, res.x_frames, h.cam)) for _ in range(3)]
        y, mean_y, pred = ys[0], np.mean(ys, axis=0), area.crop(res.simulated)
        e = y - fitted
        noise = float(np.mean([np.mean((c - mean_y) ** 2) for c in ys])) * 1.5
        systematic = float(np.mean((mean_y - fitted) ** 2)) - noise / 3
        sys_e = mean_y - fitted
        lap = np.abs(cv2.Laplacian(fitted.mean(axis=2), cv2.CV_32F))
        edges = lap > np.percentile(lap, 80)
        print(f"\n{name}, blur held {args.blur} texels{', noise-free lab' if args.noise_free else ''}"
              f"{', the lab without ' + args.off if args.off else ''}"
              f"{', the oracle operators' if args.oracle_operators else ''}"
              + (f", {schedule['schedule'].iterations_joint} joint steps over {schedule['schedule'].captures} "
                 "captures" if schedule else "") + ": capture "
              "PSNR per capture " + " ".join(f"{p:.2f}" for p in trace))
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
        if args.oracle_operators:
            continue  # the sharpness ceiling is the rendered operators'; --oracle gives the oracle's
        ceiling = []
        for s in BLURS:
            for c in comps:
                c.input_blur = s or None
            r = h.stage.joint.run(fitted, area, use_bias=False, iterations_z=300, iterations_joint=0, blend="none")
            ceiling.append(f"σ {s}: {r.report['psnr_simulated']:.2f}")
        print("  sharpness ceiling (no θ, no noise, 300 iterations): " + ", ".join(ceiling) + " dB", flush=True)


if __name__ == "__main__":
    main()
