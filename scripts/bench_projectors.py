#!/usr/bin/env python3
"""Several projectors on the lab: joint compensation against the edge-blend ramps users know, the overlap, the pose.

Usage: ``.venv/bin/python scripts/bench_projectors.py [--surfaces curve,vedge] [--scale 0.5] [--samples 16]
[--iterations N] [--targets 6] [--parts side,stacked,shift,timing,diagnosis,camera] [--work DIR]``

``side``: two projectors side by side, 20 % overlap, ``realistic`` lab effects, projector 2 with a tone curve of
its own (``--projector-effects 1:…,response=0.9``, its other projector effects realistic's), on each surface:
``procam lab``, ``procam calibrate`` (each projector's pose error against the sealed truth), then six natural
photographs compensated closed loop through the lab (``procam compensate`` + ``procam evaluate``: PSNR overall,
inside the overlap, outside it, the seam step), and in the open loop three ways on the same operators, each
projected through the lab: jointly with the derived blend prior, jointly without it, and each projector alone on its
linear edge-blend ramp (the baseline).
``stacked``: two projectors on the same area, bright targets: the range ceiling of both together against one
projector's, and ours; the reach ceiling (through the operators with the diagnosed blur held) and the oracle ceiling
(through the lab's own light transport, measured from its captures: ``bench_stacked_error.py --oracle``).
``shift``: projector 2's calibrated pose moved sideways by one camera pixel after calibration (its operator rendered
again): how much the overlap loses, with the blend prior and without, in the open loop.
``timing``: seconds per target of the joint solve against one projector's, on the same calibration.
``diagnosis``: an effect injected into projector 2 only (five, at strength 0.6, on each surface, the camera's effects
shared): ``procam diagnose`` must name it first and attribute it to projector 2.
``camera``: a tone curve injected on the camera (:data:`CAMERA_CASES`, one case with a tone curve of projector 2's own
beside it): ``procam diagnose`` must name it the camera's (fitted once on both projectors' patterns) and blame no
projector for it, and compensation with ``--effects auto`` against none (open loop, evaluated through the lab).
``--work DIR`` keeps and reuses every folder.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from procam.addon.capture.targets import DEFAULT_TARGETS, natural_target
from procam.addon.cli.app import main as procam
from procam.addon.imageio import write_image
from procam.addon.lab.truth import LabTruth
from procam.addon.capture.devices import OneProjector
from procam.addon.stages.joint import JointCompensator, ramp_baseline
from procam.addon.stages.metrics import psnr
from procam.addon.stages.range import range_ceiling
from procam.addon.stages.transport import build_transport
from procam.addon.steps import calibrate as calibrate_step
from procam.addon.steps import projectors
from procam.addon.steps.demo import second_projector
from procam.addon.steps.stage_c import StageCOptions, device_pipeline

SECOND = second_projector("realistic")


#: Iterations of the open-loop solve that gives the reach ceiling (the bench prints how much the last half added).
REACH_ITERATIONS = 1000


def step(args: list[str], done: Path) -> None:
    if done.exists():
        return
    if procam(args) != 0:
        raise SystemExit(f"procam {args[0]} failed")


def lab(work: Path, surface: str, layout: str, args: argparse.Namespace) -> tuple[Path, Path]:
    """The lab set and its calibration (made once in ``work``)."""
    caps, truth, cal = work / "lab", work / "lab.truth.json", work / "cal"
    step(["lab", "--surface", surface, "--projectors", "2", "--layout", layout, "--overlap", "0.2", "--effects",
          args.effects, "--projector-effects", SECOND, "--scale", str(args.scale), "--samples", str(args.samples),
          "--out", str(caps), "--truth", str(truth)], caps)
    step(["calibrate", str(caps), "--out", str(cal)], cal)
    return cal, truth


def pose_line(cal: Any, truth: LabTruth) -> str:
    out = []
    for k, (est, true) in enumerate(zip(cal.rig.projectors, truth.rig.projectors)):
        ang = np.degrees(np.arccos(np.clip(est.direction @ true.direction, -1, 1)))
        out.append(f"projector {k + 1}: {100 * np.linalg.norm(est.position - true.position):.2f} cm, {ang:.3f}°")
    return "; ".join(out)


def targets_for(work: Path, area: Any, count: int, bright: bool = False) -> list[Path]:
    (work / "targets").mkdir(exist_ok=True)
    paths = []
    for name in DEFAULT_TARGETS[:count]:
        img = natural_target(name, area.size)
        if bright:  # the case where one projector clips: each scaled so that its 99.5th percentile is 1
            img = np.clip(img / max(float(np.percentile(img, 99.5)), 1e-6), 0.0, 1.0)
        paths.append(write_image(work / "targets" / f"{name}.png", img))
    return paths


class Harness:
    """The open-loop solves of one calibration of several projectors, each projected through the lab and scored."""

    def __init__(self, cal_dir: Path, truth: Path, iterations: int | None, device: Any = None) -> None:
        """``device``: the lab of ``truth`` as opened elsewhere (e.g. with an effect switched off); it is closed
        with the harness."""
        self.cal = calibrate_step.read(cal_dir)
        self.options = StageCOptions(iterations=iterations)
        self.stage = projectors.JointStage(self.cal, self.options)
        self.stage.estimate_bias()
        self.device = device if device is not None else device_pipeline(f"lab:{truth}", self.cal)
        self.cam = self.cal.rig.camera.intrinsics.size

    def fitted(self, path: Path) -> tuple[np.ndarray, Any]:
        image, _ = self.stage.load(path)
        area = self.stage.area_for(image)
        return self.stage.fitted(image, area), area

    def score(self, frames: list[np.ndarray], fitted: np.ndarray, area: Any) -> dict[str, Any]:
        masks = projectors.overlap_masks(self.stage.coverage(), area)
        capture = projectors.project_all(self.device, frames, self.cam)
        return projectors.score(capture, fitted, area, masks)

    def solve(self, joint: JointCompensator, fitted: np.ndarray, area: Any, how: str) -> Any:
        args = self.options.run_arguments()
        args.pop("schedule")
        open_loop = {"biases": self.stage.biases, "black": self.stage.black}
        if how.startswith("ramps"):
            args.pop("capture_every", None)
            if how == "ramps-closed":
                return ramp_baseline(joint, fitted, area, device=self.device, **args)
            return ramp_baseline(joint, fitted, area, **open_loop, **args)
        return joint.run(fitted, area, blend=how, **open_loop, **args)

    def close(self) -> None:
        self.device.close()


def mean(rows: list[dict[str, Any]], key: str) -> float:
    vals = [r[key] for r in rows if isinstance(r.get(key), (int, float))]
    return float(np.mean(vals)) if vals else float("nan")


def side(work: Path, surface: str, args: argparse.Namespace) -> None:
    cal_dir, truth_path = lab(work, surface, "side-by-side", args)
    truth = LabTruth.load(truth_path)
    h = Harness(cal_dir, truth_path, args.iterations)
    try:
        area = h.stage.area_for(np.zeros((300, 400, 3), np.float32))
        paths = targets_for(work, area, args.targets)
        iters = [] if args.iterations is None else ["--iterations", str(args.iterations)]
        comp, ev = work / "comp", work / "eval"
        step(["compensate", str(cal_dir), *map(str, paths), "--device", f"lab:{truth_path}", *iters, "--out",
              str(comp)], comp)
        step(["evaluate", str(cal_dir), "--inputs", str(comp), "--targets", *map(str, paths), "--device",
              f"lab:{truth_path}", "--out", str(ev)], ev)
        closed = json.loads((ev / "metrics.json").read_text())
        rows: dict[str, list[dict[str, Any]]] = {"derived": [], "none": [], "ramps": [], "ramps-closed": []}
        for path in paths:
            fitted, area = h.fitted(path)
            for how in rows:
                res = h.solve(h.stage.joint, fitted, area, how)
                rows[how].append(h.score(res.x_frames, fitted, area))
    finally:
        h.close()
    print(f"\n{surface}, two projectors side by side, 20 % overlap, realistic, projector 2: {SECOND[2:]}, scale "
          f"{args.scale}: pose {pose_line(h.cal, truth)}")
    print("| | PSNR | inside the overlap | outside it | along its edge | seam step |")
    print("|---|---|---|---|---|---|")
    m, u = closed["mean"], closed["mean_uncompensated"]
    for label, r in (("uncompensated (split evenly)", u), ("ours, closed loop", m)):
        print(f"| {label} | {r['psnr']:.2f} | {r['psnr_overlap']:.2f} | {r['psnr_outside']:.2f} | "
              f"{r['psnr_border']:.2f} | {r['seam_step']:.4f} |")
    for how, label in (("ramps-closed", "each alone on edge-blend ramps, closed loop each"),
                       ("derived", "ours, open loop"), ("none", "ours, open loop, no blend prior"),
                       ("ramps", "each alone on edge-blend ramps, open loop")):
        r = rows[how]
        print(f"| {label} | {mean(r, 'psnr'):.2f} | {mean(r, 'psnr_overlap'):.2f} | {mean(r, 'psnr_outside'):.2f} | "
              f"{mean(r, 'psnr_border'):.2f} | {mean(r, 'seam_step'):.4f} |")
    d, ramps, closed_ramps = rows["derived"], rows["ramps"], rows["ramps-closed"]
    print(f"inside the overlap: ours closed loop {m['psnr_overlap'] - m['psnr_outside']:+.2f} dB against outside it, "
          f"{m['psnr_overlap'] - mean(closed_ramps, 'psnr_overlap'):+.2f} dB against the ramps closed loop; open "
          f"loop ours {mean(d, 'psnr_overlap') - mean(ramps, 'psnr_overlap'):+.2f} dB against the ramps open loop")


def stacked(work: Path, surface: str, args: argparse.Namespace) -> None:
    cal_dir, truth_path = lab(work, surface, "stacked", args)
    h = Harness(cal_dir, truth_path, args.iterations)
    try:
        captures = calibrate_step.captures_of(h.cal)
        assert captures is not None
        area = h.stage.area_for(np.zeros((300, 400, 3), np.float32))
        paths = targets_for(work, area, args.targets, bright=True)
        black, white = projectors.combined_black_white(captures)
        one = captures.for_projector(0)
        b1, w1 = one.image("black"), one.image("white")
        iters = [] if args.iterations is None else ["--iterations", str(args.iterations)]
        device = ["--device", f"lab:{truth_path}"]
        diag = work / "diag"
        # what a user learns of the rig's lens blur: each projector's blur fitted by the diagnosis
        step(["diagnose", str(cal_dir), "--out", str(diag)], diag)
        blur = ["--effects", "defocus", "--diagnosis", str(diag)]
        metrics = {}
        for key, extra in (("plain", []), ("blur", blur)):
            comp, ev = work / f"comp-{key}", work / f"eval-{key}"
            step(["compensate", str(cal_dir), *map(str, paths), *device, *iters, *extra, "--out", str(comp)], comp)
            step(["evaluate", str(cal_dir), "--inputs", str(comp), "--targets", *map(str, paths), *device,
                  "--out", str(ev)], ev)
            metrics[key] = json.loads((ev / "metrics.json").read_text())["targets"]
        alone = OneProjector(h.device, 0)
        first = h.stage.compensators[0]
        args_c = h.options.run_arguments()
        reach_stage = projectors.JointStage(h.cal, StageCOptions(effects="defocus", diagnosis=diag))
        sigmas = [c.input_blur for c in reach_stage.compensators]
        table: dict[str, list[float]] = {k: [] for k in ("one", "both", "noise", "reach", "reach_noise", "single",
                                                          "ours", "ours_blur")}
        for path, row, row_blur in zip(paths, metrics["plain"], metrics["blur"]):
            fitted, area = h.fitted(path)
            table["one"].append(range_ceiling(fitted, area.crop(b1), area.crop(w1)))
            table["both"].append(range_ceiling(fitted, area.crop(black), area.crop(white)))
            table["noise"].append(row.get("noise_ceiling", float("nan")))
            # the reach ceiling: the best any inputs in [0, 1] show through the operators with the diagnosed blur
            # held (open loop, no θ, no blend prior), then seen through the camera's noise
            best = reach_stage.joint.run(fitted, area, use_bias=False, iterations_z=REACH_ITERATIONS,
                                         iterations_joint=0, blend="none")
            table["reach"].append(best.report["psnr_simulated"])
            noise_mse = float(row.get("capture_noise_rmse", 0.0)) ** 2
            table["reach_noise"].append(10 * np.log10(1 / (10 ** (-table["reach"][-1] / 10) + noise_mse)))
            # projector 1 alone, its own closed loop with projector 2 black: what stacking adds to
            res = first.run(fitted, area, device=alone, verify=False, **args_c)
            table["single"].append(psnr(area.crop(alone.project(res.x_frame)), fitted))
            table["ours"].append(row["psnr"])
            table["ours_blur"].append(row_blur["psnr"])
    finally:
        h.close()
    print(f"\n{surface}, two projectors stacked on one area, bright targets (99.5th percentile at 1), effects "
          f"{args.effects}, scale {args.scale}, closed loop; the diagnosis's blur σ " + ", ".join(
              "none" if s is None else f"{s:.2f}" for s in sigmas) + " texels")
    print("| Target | range ceiling, projector 1 alone | both | both, through the camera's noise | reach ceiling "
          "(blur held) | through the camera's noise | projector 1 alone | ours, both | ours, blur held |")
    print("|---|---|---|---|---|---|---|---|---|")
    cols = [table[k] for k in ("one", "both", "noise", "reach", "reach_noise", "single", "ours", "ours_blur")]
    for path, *vals in zip(paths, *cols):
        print(f"| {path.stem} | " + " | ".join(f"{v:.2f}" for v in vals) + " |")
    print("| mean | " + " | ".join(f"{np.mean(v):.2f}" for v in cols) + " |")
    m = {k: float(np.mean(v)) for k, v in table.items()}
    print(f"both projectors' range ceiling {m['both'] - m['one']:+.2f} dB above one's; ours "
          f"{m['ours'] - m['single']:+.2f} dB above one projector compensated alone, "
          f"{m['noise'] - m['ours']:.2f} dB below the noise ceiling; with the blur held "
          f"{m['reach_noise'] - m['ours_blur']:.2f} dB below the reach ceiling through the noise "
          f"({m['noise'] - m['reach_noise']:.2f} dB of the noise ceiling no input reaches through the blur)")
    # The oracle ceiling: the most any inputs show through the lab's own light transport, measured from its captures
    # (bench_stacked_error.py --oracle, which imports this module: imported here).
    import bench_stacked_error

    print()
    bench_stacked_error.oracle(work, ",".join(p.stem for p in paths), bench_stacked_error.ORACLE_SPACING)


def shift(work: Path, surface: str, args: argparse.Namespace) -> None:
    cal_dir, truth_path = lab(work, surface, "side-by-side", args)
    h = Harness(cal_dir, truth_path, args.iterations)
    try:
        cal = h.cal
        second = cal.for_projector(1)
        f_cam = cal.rig.camera.intrinsics.fx
        depth = float(np.median(cal.surface.vertices[:, 2]))
        step_m = depth / f_cam  # one camera pixel on the surface, for a projector moved parallel to it
        proj = second.rig.projector
        pose = proj.camera_from_projector.copy()
        pose[:3, 3] += step_m * pose[:3, 0]
        moved = replace(second, rig=replace(second.rig, projector=proj.with_pose(pose)))
        comps = list(h.stage.compensators)
        comp1 = type(comps[1])(moved, bounces=1, spp=4, seed=0)
        comp1.transport = build_transport(moved, bounces=1, seed=0)
        joint_moved = JointCompensator([comps[0], comp1])
        paths = targets_for(work, h.stage.area_for(np.zeros((300, 400, 3), np.float32)), args.targets)
        rows: dict[tuple[str, str], list[dict[str, Any]]] = {}
        for path in paths:
            fitted, area = h.fitted(path)
            for which, joint in (("calibrated", h.stage.joint), ("moved", joint_moved)):
                for how in ("derived", "none"):
                    res = h.solve(joint, fitted, area, how)
                    rows.setdefault((which, how), []).append(h.score(res.x_frames, fitted, area))
    finally:
        h.close()
    print(f"\n{surface}: projector 2's calibrated pose moved {1000 * step_m:.2f} mm sideways (one camera pixel on "
          f"the surface) after calibration, open loop, {len(paths)} targets; PSNR inside the overlap / seam step")
    for how, label in (("derived", "with the blend prior"), ("none", "without it")):
        a, b = rows[("calibrated", how)], rows[("moved", how)]
        print(f"{label}: {mean(a, 'psnr_overlap'):.2f} → {mean(b, 'psnr_overlap'):.2f} dB "
              f"({mean(b, 'psnr_overlap') - mean(a, 'psnr_overlap'):+.2f} dB), seam step "
              f"{mean(a, 'seam_step'):.4f} → {mean(b, 'seam_step'):.4f}")


def timing(work: Path, surface: str, args: argparse.Namespace) -> None:
    cal_dir, truth_path = lab(work, surface, "side-by-side", args)
    h = Harness(cal_dir, truth_path, args.iterations)
    try:
        paths = targets_for(work, h.stage.area_for(np.zeros((300, 400, 3), np.float32)), args.targets)
        one = h.stage.compensators[0]
        joint_s, one_s = [], []
        for path in paths:
            fitted, area = h.fitted(path)
            t0 = time.perf_counter()
            h.solve(h.stage.joint, fitted, area, "derived")
            joint_s.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            one.run(fitted, area, open_loop_theta=h.stage.biases[0], verify=False,
                    **h.options.run_arguments())
            one_s.append(time.perf_counter() - t0)
    finally:
        h.close()
    cam = h.cam
    both, alone = float(np.median(joint_s[1:] or joint_s)), float(np.median(one_s[1:] or one_s))
    print(f"\n{surface}, camera {cam[0]}×{cam[1]}, transport schedule, open loop, median after a first warm-up "
          f"target: joint {both:.2f} s per target, one projector {alone:.2f} s ({both / alone:.2f}×)")


#: effects injected into projector 2 only (lab name → the diagnosis's model that should name it)
INJECTED = {"response": "response", "crosstalk": "crosstalk", "vignetting": "vignetting", "defocus": "defocus",
            "response_scurve": "response"}
#: what both projectors share in the diagnosis part: the camera's noise and tone curve, bounce light
SHARED = "noise=0.4,camera_response=0.3,interreflection=0.75"


def diagnosis(work: Path, surface: str, args: argparse.Namespace) -> None:
    """Each of :data:`INJECTED` given to projector 2 alone (strength 0.6): is it named first, and on projector 2?"""
    hits = []
    for effect, model in INJECTED.items():
        case = work / f"diagnosis-{effect}"
        caps, truth, cal, diag = case / "lab", case / "lab.truth.json", case / "cal", case / "diag"
        case.mkdir(parents=True, exist_ok=True)
        step(["lab", "--surface", surface, "--projectors", "2", "--overlap", "0.2", "--effects", SHARED,
              "--projector-effects", f"1:{effect}=0.6", "--scale", str(args.scale), "--samples", str(args.samples),
              "--out", str(caps), "--truth", str(truth)], caps)
        step(["calibrate", str(caps), "--out", str(cal)], cal)
        step(["diagnose", str(cal), "--out", str(diag)], diag)
        # the verdict `procam diagnose` wrote: with a shared effect selected (the camera's curve here) it compares
        # each projector's own effects as fitted beside the shared ones (a folder kept from an earlier run keeps its
        # verdict: use a fresh --work after changing the rule)
        doc = json.loads((diag / "gap.json").read_text())
        top = doc.get("differs") or {}
        hit = top.get("projector") == 2 and top.get("effect") == model
        hits.append(hit)
        print(f"{surface}, {effect}=0.6 on projector 2: {'named' if hit else 'MISSED'} — {doc['headline']}",
              flush=True)
    print(f"{surface}: {sum(hits)} of {len(hits)} named first and on projector 2", flush=True)


#: the camera part's cases: what the lab injects on the camera (shared by both projectors) and on projector 2 alone
CAMERA_CASES = (("camera_response=0.6", ""), ("camera_response=1.0", ""),
                ("camera_response=0.6", "1:response=0.6"))


def camera(work: Path, surface: str, args: argparse.Namespace) -> None:
    """A tone curve injected on the camera of two projectors side by side: is it named the camera's (fitted once
    on both projectors' patterns, no projector blamed), and what does modelling it buy (open loop, through the lab)?"""
    rows = []
    for k, (cam, own) in enumerate(CAMERA_CASES):
        case = work / f"camera-{k}"
        caps, truth, cal, diag = case / "lab", case / "lab.truth.json", case / "cal", case / "diag"
        case.mkdir(parents=True, exist_ok=True)
        step(["lab", "--surface", surface, "--projectors", "2", "--overlap", "0.2", "--effects", cam,
              *(["--projector-effects", own] if own else []), "--scale", str(args.scale), "--samples",
              str(args.samples), "--out", str(caps), "--truth", str(truth)], caps)
        step(["calibrate", str(caps), "--out", str(cal)], cal)
        step(["diagnose", str(cal), "--out", str(diag)], diag)
        doc = json.loads((diag / "gap.json").read_text())
        area = projectors.JointStage(calibrate_step.read(cal), StageCOptions()).area_for(
            np.zeros((300, 400, 3), np.float32))
        paths = targets_for(case, area, args.targets)
        iters = [] if args.iterations is None else ["--iterations", str(args.iterations)]
        psnrs = {}
        for effects in ("none", "auto"):
            comp, ev = case / f"comp-{effects}", case / f"eval-{effects}"
            step(["compensate", str(cal), *map(str, paths), *iters, "--effects", effects, "--diagnosis", str(diag),
                  "--out", str(comp)], comp)
            step(["evaluate", str(cal), "--inputs", str(comp), "--targets", *map(str, paths), "--device",
                  f"lab:{truth}", "--out", str(ev)], ev)
            psnrs[effects] = json.loads((ev / "metrics.json").read_text())["mean"]["psnr"]
        joint = doc.get("joint") or {}
        named = "camera_response" in (joint.get("shared") or [])
        top = doc.get("differs") or {}
        blamed = f"projector {top['projector']}'s {top['effect']}" if top else "none"
        want = "projector 2's response" if own else "none"
        rows.append((cam, own or "–", named, (joint.get("params") or {}).get("camera_response", {}).get("curve"),
                     blamed, blamed == want, psnrs["none"], psnrs["auto"]))
        print(f"{surface}, camera {cam}, projector 2 {own or 'as projector 1'}: {doc['headline']}", flush=True)
    print(f"\n{surface}, two projectors side by side, 20 % overlap, scale {args.scale}, open loop, {args.targets} "
          "natural targets, evaluated through the lab")
    print("| camera | projector 2 | named the camera's | curve fitted | projector blamed | right | PSNR without "
          "| PSNR with the camera modelled |")
    print("|---|---|---|---|---|---|---|---|")
    for cam, own, named, curve, blamed, right, without, with_ in rows:
        print(f"| {cam} | {own} | {'yes' if named else 'NO'} | {'–' if curve is None else f'{curve:.2f}'} | "
              f"{blamed} | {'yes' if right else 'NO'} | {without:.2f} | {with_:.2f} |")
    print(f"{surface}: named the camera's in {sum(r[2] for r in rows)} of {len(rows)}, attribution right in "
          f"{sum(r[5] for r in rows)} of {len(rows)}; modelling the camera "
          f"{np.mean([r[7] - r[6] for r in rows]):+.2f} dB on average", flush=True)


PARTS = {"side": side, "stacked": stacked, "shift": shift, "timing": timing, "diagnosis": diagnosis,
         "camera": camera}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--surfaces", default="curve,vedge")
    ap.add_argument("--scale", type=float, default=0.5)
    # another lab than the (e.g. realistic,distortion=0: what the camera's lens costs); a new --work folder
    ap.add_argument("--effects", default="realistic")
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--targets", type=int, default=6)
    ap.add_argument("--parts", default="side,stacked,shift,timing")
    ap.add_argument("--work", type=Path, help="keep the folders here and reuse them")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        for part in args.parts.split(","):
            for surface in args.surfaces.split(","):
                layout = "stacked" if part == "stacked" else "side-by-side"
                folder = work / f"{surface}-{layout}"
                folder.mkdir(parents=True, exist_ok=True)
                PARTS[part](folder, surface, args)


if __name__ == "__main__":
    main()
