#!/usr/bin/env python3
"""The closed loop on a rig of other forms: the paper's damped θ against the measured loop, and where the gap lies.

Usage: ``.venv/bin/python scripts/bench_closed_loop.py [--surface curve] [--scale 0.5] [--other-forms 1]
[--lab-effects noise=0.4] [--rules damped/global,measured/global,open/pixel] [--effects auto] [--projectors 2]
[--attribute]
[--work DIR]``

Renders a lab capture set with ``procam lab --other-forms`` (a rig whose response,
colour mixing, vignetting, blur, camera curve and JPEG photos have forms ProCam
does not model: ``addon/lab/other_forms.py``; ``--other-forms 0`` is the lab's own
forms), calibrates it, and compensates six natural photographs at full
brightness (each scaled so its 99.5th percentile is 1) with ``--range auto``,
closed loop through that lab, once per loop rule (``procam compensate --loop``)
or in the open loop (``open``), each through the global models or each camera
pixel's own (``/pixel``: ``procam compensate --radiometry``); then evaluates
each (two captures of every answer: the camera's noise and the noise ceiling).
Prints per target the three ceilings below, each rule's PSNR and its distance to the
perfect answer's ceiling, the captures each used, and where the squared error beyond the
camera's noise lies (the last rule's answer).

Each target has three ceilings:

* the **noise ceiling** ``procam evaluate`` prints, the highest over the runs: it measures the camera's noise from
  two captures of the answer. On a rig whose photos are JPEG (the lab of other forms) the compression's error
  depends on the image and is the same in both captures, so the difference misses it, and what it does see
  follows the answer's texture (a blurred answer reads a quieter camera); it is a ceiling on a raw camera only;
* the **perfect answer** (``addon/lab/perfect.py``): what the lab's camera records of an answer whose noiseless
  capture is the target at every pixel (its noise, processing and JPEG), scored against the target. The lab
  knows its camera; this is the ceiling the camera sets, and every run's "below" is measured against it;
* the **perfect answer in the gamut**: the same for the target moved to the nearest colour each pixel can show
  (``addon/stages/gamut.py``, from the lab's captures of black and the three primaries), scored against the
  target: the best any answer can score on this rig.

The error beyond the noise splits into:

* ``at limit``: pixels whose input already gives all it can (evaluate's
  ``ceiling_gap_at_limit``): no loop can push further there;
* ``edges``: the tenth of the area where the target changes fastest (a blur or a
  misregistration the model lacks shows there);
* ``fine`` / ``coarse``: the rest, finer or coarser than 1.5 camera pixels;

the last three share what ``at limit`` leaves, in proportion to their own excess over the noise.

Beside the noise ceiling it prints the **gamut ceiling** (``addon/stages/gamut.py``): the target moved to the
nearest colour each pixel can show at all (the lab's captures of black and the three primaries), through the same
noise; where the projector mixes its colours the noise ceiling counts saturated colours no input can show.

``--projectors 2`` lays out two projectors side by side (20 % overlap) and prints each rule's seam step too.
``--attribute`` also runs the last rule with twice the captures, with its slope held at 1, through a copy of
the lab without sensor noise (evaluated through the lab with it), and, on a lab of other forms, through the lab
without one of its parts at a time (its blur, its colour mixing, its response; loop and evaluation alike), and
prints what each is worth and how far each lands below its own noise ceiling.
``--effects auto`` diagnoses the calibration first and compensates with the effects it selected around stage C.
``--work DIR`` keeps and reuses every folder.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_range import area_image, full_brightness_targets, step  # noqa: E402

#: Error finer than this (σ, camera pixels) counts as fine.
FINE_PX = 1.5
#: The share of the area, by the target's gradient, that counts as its edges.
EDGE_SHARE = 0.1


def error_parts(comp: Path, ev: Path, row: dict) -> dict[str, float]:
    """The capture's squared error beyond the camera's noise, split as the module doc says (shares of it)."""
    import cv2

    a, name = row["area"], row["name"]
    capture, target = area_image(ev / f"{name}_capture.png", a), area_image(comp / f"{name}_target.png", a)
    err = (capture - target) ** 2
    noise = row.get("capture_noise_rmse", 0.0) ** 2
    beyond = max(float(err.mean()) - noise, 1e-12)
    at_limit = row.get("ceiling_gap_at_limit") or row.get("at_limit_joint") or 0.0
    grad = np.abs(cv2.Laplacian(cv2.GaussianBlur(target, (0, 0), 0.7), cv2.CV_32F)).max(axis=2)
    edges = grad > np.quantile(grad, 1.0 - EDGE_SHARE)
    e = capture - target
    fine = e - cv2.GaussianBlur(e, (0, 0), FINE_PX)
    # each part's excess over the noise it holds (noise is white: spread evenly, mostly fine)
    edge_excess = max(float(err[edges].sum()) / err.size - EDGE_SHARE * noise, 0.0)
    rest = ~edges
    fine_noise = noise * float(np.mean((np.random.default_rng(0).normal(size=(64, 64)) - cv2.GaussianBlur(
        np.random.default_rng(0).normal(size=(64, 64)), (0, 0), FINE_PX)) ** 2))
    fine_excess = max(float((fine[rest] ** 2).sum()) / err.size - rest.mean() * fine_noise, 0.0)
    coarse_excess = max(float((err[rest] - fine[rest] ** 2).sum()) / err.size - rest.mean() * (noise - fine_noise),
                        0.0)
    parts = {"edges": edge_excess, "fine": fine_excess, "coarse": coarse_excess}
    total = sum(parts.values()) or 1e-12
    # the limit share is evaluate's, of the whole excess; the others share what is left in their proportions
    return {"at limit": at_limit, **{k: (1.0 - at_limit) * v / total for k, v in parts.items()},
            "excess_mse": beyond}


def joint_at_limit(work: Path, comp: Path, ev: Path, row: dict, black: np.ndarray, white: np.ndarray) -> float:
    """Of a several-projector answer's squared error beyond the target clipped to [black, white] (camera-sized),
    the share where every projector that lights the pixel already gives all it can: the capture too dark with
    each one's input at full, or too bright with each at zero (what evaluate's ``ceiling_gap_at_limit`` says for
    one projector)."""
    from procam.addon.imageio import read_image
    from procam.addon.stages.range import ceiling_gap_at_limit
    from procam.addon.stages.transport import camera_to_input
    from procam.addon.steps import calibrate as calibrate_step
    from procam.addon.steps.evaluate import input_seen

    cal = calibrate_step.read(work / "cal")
    a, name = row["area"], row["name"]
    inside = np.s_[a["y"]:a["y"] + a["height"], a["x"]:a["x"] + a["width"]]
    cam_size = cal.rig.camera.intrinsics.size
    seen = []
    for k in range(cal.projector_count):
        one = cal.for_projector(k)
        looks_at, _ = camera_to_input(one, cam_size)
        if one.warp is not None:
            hit = np.isfinite(looks_at[..., 0])
            looks_at[hit] = one.warp.map_m(looks_at[hit], one.rig.projector.input_size)
        frame = read_image(comp / f"{name}_frame_p{k + 1}.png")
        seen.append(input_seen(frame, one.rig.projector, looks_at)[inside])
    capture, target = area_image(ev / f"{name}_capture.png", a), area_image(comp / f"{name}_target.png", a)
    stack = np.stack(seen)
    lit = np.isfinite(stack).any(axis=0)
    lowest = np.where(lit, np.nanmin(np.where(np.isfinite(stack), stack, np.inf), axis=0), np.nan)
    highest = np.where(lit, np.nanmax(np.where(np.isfinite(stack), stack, -np.inf), axis=0), np.nan)
    # too dark: at the limit only if the dimmest projector there is at full; too bright: if the brightest is at 0
    x = np.where(capture < target, lowest, highest)
    got = ceiling_gap_at_limit(target, capture, black[inside], white[inside], x)
    return 0.0 if got is None else got


def primaries(truth: Path, repeats: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """The lab's captures of black and of the three primaries at full over every projector's input (each the mean
    of ``repeats``): what :func:`~procam.addon.stages.gamut.gamut_clip` needs. Only the input lights: texels of the
    native frame outside it are no answer's to use (a 300×300 input in a 400×300 frame leaves a side band that
    lights a neighbour's part of the area, which counted, made colours there look reachable that no answer shows)."""
    from procam.addon.lab.cycles_device import LabDevice
    from procam.addon.lab.truth import LabTruth

    lab = LabTruth.load(truth)
    with LabDevice(lab, seed=lab.seed + 977) as device:
        def shot(colour: tuple[float, float, float]) -> np.ndarray:
            frames = [p.frame_from_input(np.broadcast_to(np.asarray(colour, np.float32),
                                                         (p.input_size[1], p.input_size[0], 3)))
                      for p in lab.rig.projectors]
            return np.mean([device.project_all(frames) for _ in range(repeats)], axis=0)
        return shot((0.0, 0.0, 0.0)), np.stack([shot(c) for c in ((1, 0, 0), (0, 1, 0), (0, 0, 1))])


#: What ``--attribute`` takes out of the lab of other forms, one at a time, for the loop and its evaluation alike:
#: name → the parameters of :class:`~procam.addon.lab.other_forms.OtherForms` that make it the identity.
PARTS_OFF = {"blur": {"blur": (0.0, 0.0)},
             "colour mixing": {"mix_left": np.eye(3, dtype=np.float32), "mix_right": np.eye(3, dtype=np.float32)},
             "response": {"gamma": np.ones(3, np.float32), "gamma_drift": 0.0, "knee_mix": 0.0}}


def without_part(part: str) -> Any:
    """A context in which every lab of other forms opened lacks ``part`` (:data:`PARTS_OFF`)."""
    @contextlib.contextmanager
    def patch() -> Iterator[None]:
        from procam.addon.lab import other_forms

        init = other_forms.OtherForms.__post_init__

        def patched(self: Any) -> None:
            init(self)
            for name, value in PARTS_OFF[part].items():
                setattr(self, name, value)
        other_forms.OtherForms.__post_init__ = patched  # type: ignore[method-assign]
        try:
            yield
        finally:
            other_forms.OtherForms.__post_init__ = init  # type: ignore[method-assign]
    return patch


@contextlib.contextmanager
def slope_fixed() -> Iterator[None]:
    """The measured loop with every pixel's slope held at the model's (1): what measuring the slope buys."""
    from procam.addon.stages import closed_loop

    before = closed_loop.PRIOR_WEIGHT
    closed_loop.PRIOR_WEIGHT = 1e12
    try:
        yield
    finally:
        closed_loop.PRIOR_WEIGHT = before


def poses_against(cal_folder: Path, truth: Any) -> str:
    """Each calibrated projector's position (mm) and axis (°) error against the lab's truth, and the one-σ
    uncertainty the calibration states for it (``pose_uncertainty``)."""
    from procam.addon.stages.pose import pose_error
    from procam.addon.steps import calibrate as calibrate_step

    cal = calibrate_step.read(cal_folder)
    out = []
    for k in range(cal.projector_count):
        one = cal.for_projector(k)
        metres, degrees = pose_error(one.rig.projector.camera_from_projector,
                                     truth.rig.projectors[k].camera_from_projector)
        u = one.report.get("pose_uncertainty") or {}
        stated = (f" (stated ±{100 * u['position_std_m']:.1f} cm, ±{u['axis_std_deg']:.2f}°)"
                  if u.get("position_std_m") else "")
        out.append(f"projector {k + 1}: {1000 * metres:.1f} mm, {degrees:.3f}°{stated}")
    return "poses against the lab's truth: " + "; ".join(out)


def slug(label: str) -> str:
    """A run's folder name (``comp-SLUG``, ``eval-SLUG``): a run through the global models keeps its older name."""
    return label.replace(", ", "-").replace(" ", "_").replace("/global", "").replace("/", "-")


def lab_and_calibration(work: Path, surface: str, effects: str, other_forms: float, scale: float,
                        projectors: int = 1) -> Path:
    """The lab of other forms in ``work`` (``lab``, its truth, ``cal``), rendered and calibrated unless there
    already; the truth file's path."""
    lab, truth = work / "lab", work / "lab.truth.json"
    step(["lab", "--surface", surface, "--effects", effects, "--other-forms", str(other_forms), "--scale", str(scale),
          "--projectors", str(projectors), "--out", str(lab), "--truth", str(truth)], lab)
    step(["calibrate", str(lab), "--out", str(work / "cal")], work / "cal")
    return truth


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--surface", default="curve")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--other-forms", type=float, default=1.0, help="procam lab --other-forms (0: the lab's own)")
    ap.add_argument("--lab-effects", default="noise=0.4", help="procam lab --effects under the other forms")
    ap.add_argument("--rules", default="damped/global,measured/global",
                    help="the runs, in order: RULE[/RADIOMETRY], RULE a procam compensate --loop rule or 'open' "
                         "(the open loop, no device), RADIOMETRY its --radiometry (default global)")
    ap.add_argument("--effects", choices=("none", "auto"), default="none",
                    help="auto: run procam diagnose and compensate with the effects it selected")
    ap.add_argument("--projectors", type=int, default=1, help="procam lab --projectors (side by side, 20 %% overlap)")
    ap.add_argument("--attribute", action="store_true",
                    help="also run the last rule with twice the captures, with its slope held at 1, through a copy "
                         "of the lab without sensor noise (evaluated through the lab with it) and, on a lab of other "
                         "forms, without its blur, colour mixing or response in turn: what each is worth")
    ap.add_argument("--work", type=Path, help="keep the folders here and reuse them")
    args = ap.parse_args()
    rules = args.rules.split(",")
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        truth = lab_and_calibration(work, args.surface, args.lab_effects, args.other_forms, args.scale,
                                    args.projectors)
        targets = full_brightness_targets(work / "targets")
        effects, fx = [], ""
        if args.effects == "auto":
            step(["diagnose", str(work / "cal"), "--out", str(work / "diagnosis")], work / "diagnosis")
            effects, fx = ["--effects", "auto", "--diagnosis", str(work / "diagnosis")], "-fx"
        rows, comps = {}, {}
        runs = [(rule, rule, [], truth, contextlib.nullcontext) for rule in rules]
        # (label, rule, extra flags, lab truth of the loop, patch)
        if args.attribute:
            from procam.addon.lab.truth import LabTruth

            quiet = work / "lab-quiet.truth.json"
            if not quiet.exists():
                LabTruth.load(truth).without("noise").save(quiet)
            last = rules[-1]
            runs += [(f"{last}, 30 captures", last, ["--iterations", "80", "--capture-every", "2"], truth,
                      contextlib.nullcontext),
                     (f"{last}, slope held at 1", last, [], truth, slope_fixed),
                     (f"{last}, loop without noise", last, [], quiet, contextlib.nullcontext)]
            if args.other_forms:
                runs += [(f"{last}, lab without its {part}", last, [], truth, without_part(part)) for part in PARTS_OFF]
        for label, rule, extra, device_truth, patch in runs:
            comp, ev = work / f"comp-{slug(label)}{fx}", work / f"eval-{slug(label)}{fx}"
            loop, _, radiometry = rule.partition("/")
            how = ([] if loop == "open" else ["--device", f"lab:{device_truth}", "--loop", loop]) + \
                ["--radiometry", radiometry or "global"]
            with patch():
                step(["compensate", str(work / "cal"), *targets, "--range", "auto", *how, *extra, *effects,
                      "--out", str(comp)], comp)
                # a part taken out of the lab is out of the evaluation too; the loop without noise is evaluated
                # through the lab with it
                step(["evaluate", str(work / "cal"), "--inputs", str(comp), "--targets", *targets, "--device",
                      f"lab:{truth}", "--out", str(ev)], ev)
            rows[label] = json.loads((ev / "metrics.json").read_text())
            comps[label] = {t["name"]: t for t in json.loads((comp / "compensation.json").read_text())["targets"]}
        from procam.addon.imageio import read_image
        from procam.addon.lab.perfect import perfect_ceiling, render_noise
        from procam.addon.lab.truth import LabTruth
        from procam.addon.stages.gamut import gamut_ceiling, gamut_clip

        black, prims = primaries(truth)
        lab_truth = LabTruth.load(truth)
        last = rules[-1]
        gamut, perfect, perfect_gamut = {}, {}, {}
        for t in rows[rules[0]]["targets"]:
            a = t["area"]
            inside = np.s_[a["y"]:a["y"] + a["height"], a["x"]:a["x"] + a["width"]]
            target = area_image(work / f"comp-{slug(rules[0])}{fx}" / f"{t['name']}_target.png", a)
            gamut[t["name"]] = gamut_ceiling(target, black[inside], prims[:, inside[0], inside[1]],
                                             t.get("capture_noise_rmse", 0.0) ** 2)
            # the perfect answer: the target placed in a capture of the camera (its surround reaches the JPEG's
            # blocks at the area's border), then the same within the colours each pixel can show
            placed = read_image(work / f"eval-{slug(rules[0])}{fx}" / f"{t['name']}_capture.png").copy()
            placed[inside] = target
            # the render's noise, drawn from two renders of the last run's answer (its light is near the target's)
            frame_files = [f"{t['name']}_frame.png"] if args.projectors == 1 else \
                [f"{t['name']}_frame_p{k + 1}.png" for k in range(args.projectors)]
            render = render_noise(lab_truth, [read_image(work / f"comp-{slug(last)}{fx}" / n) for n in frame_files],
                                  seed=lab_truth.seed + 991)
            perfect[t["name"]] = perfect_ceiling(lab_truth, placed, inside, render=render)
            placed[inside] = gamut_clip(target, black[inside], prims[:, inside[0], inside[1]])
            perfect_gamut[t["name"]] = perfect_ceiling(lab_truth, placed, inside, target=target, render=render)
        print(f"\n{args.surface}, lab --effects {args.lab_effects} --other-forms {args.other_forms}, "
              f"scale {args.scale}, --range auto --effects {args.effects}, closed loop\n")
        several = args.projectors > 1
        head = " | ".join(f"{r}: PSNR (below the ceiling), captures, s/capture" + (", seam step" if several else "")
                          for r in rules)
        last = rules[-1]
        print(f"| target | noise ceiling (evaluate) | gamut ceiling | perfect answer | perfect answer in the gamut "
              f"| {head} | {last}: beyond the noise: at limit / edges / fine / coarse |")
        print("|---|---|---|---|---|" + "---|" * len(rules) + "---|")

        def cell(label: str, i: int, name: str, ceil: float | None) -> str:
            t, c = rows[label]["targets"][i], comps[label][name]
            per = c["seconds"] / max(c["captures"], 1)
            below = "–" if ceil is None else f"{ceil - t['psnr']:.2f}"
            seam = t.get("seam_step")
            return f"{t['psnr']:.2f} ({below}), {c['captures']}, {per:.2f}" + (
                "" if not several else f", {'–' if seam is None else f'{seam:.4f}'}")

        def ceiling(i: int) -> float | None:
            got = [r["targets"][i].get("noise_ceiling") for r in rows.values()]
            return max(got) if all(c is not None for c in got) else None

        names = [t["name"] for t in rows[rules[0]]["targets"]]
        if several:  # evaluate splits the limit out for one projector only
            white = black + np.sum(np.maximum(prims - black[None], 0.0), axis=0)
            for r in rows[last]["targets"]:
                r["at_limit_joint"] = joint_at_limit(work, work / f"comp-{slug(last)}{fx}",
                                                     work / f"eval-{slug(last)}{fx}", r, black, white)
        for i, name in enumerate(names):
            ceil = perfect[name]
            parts = error_parts(work / f"comp-{slug(last)}{fx}", work / f"eval-{slug(last)}{fx}",
                                rows[last]["targets"][i])
            split = " / ".join(f"{100 * parts[k]:.0f} %" for k in ("at limit", "edges", "fine", "coarse"))
            noise = ceiling(i)
            print(f"| {name} | {'–' if noise is None else f'{noise:.2f}'} | {gamut[name]:.2f} | {ceil:.2f} | "
                  f"{perfect_gamut[name]:.2f} | "
                  + " | ".join(cell(r, i, name, ceil) for r in rules) + f" | {split} |")
        noise_ceilings = [ceiling(i) for i in range(len(names))]
        mean_noise = round(float(np.mean(noise_ceilings)), 2) if all(c is not None for c in noise_ceilings) else None
        mean_ceil = round(float(np.mean([perfect[n] for n in names])), 2)
        mean_shown = round(float(np.mean([perfect_gamut[n] for n in names])), 2)

        def mean(label: str) -> str:
            psnr = rows[label]["mean"]["psnr"]
            return f"{psnr:.2f}" + ("" if mean_ceil is None else f" ({mean_ceil - psnr:.2f})")

        print(f"| mean | {mean_noise} | {np.mean(list(gamut.values())):.2f} | {mean_ceil:.2f} | {mean_shown:.2f} | "
              + " | ".join(mean(r) for r in rules) + " | |")
        print("\nBelow the perfect answer within the gamut (the best any answer can score): "
              + ", ".join(f"{r} {mean_shown - rows[r]['mean']['psnr']:.2f} dB" for r in rules))
        print("\n" + poses_against(work / "cal", lab_truth))
        extra = [label for label in rows if label not in rules]
        if extra:
            base = rows[last]["mean"]["psnr"]
            print(f"\nWhat each part is worth to {last} (mean PSNR, and its change):\n")
            print("| run | mean PSNR | change | below its own noise ceiling | captures a target |")
            print("|---|---|---|---|---|")
            for label in [last, *extra]:
                psnr, ceil = rows[label]["mean"]["psnr"], rows[label].get("mean_noise_ceiling")
                caps = np.mean([c["captures"] for c in comps[label].values()])
                print(f"| {label} | {psnr:.2f} | {psnr - base:+.2f} | {'–' if ceil is None else f'{ceil - psnr:.2f}'} "
                      f"| {caps:.1f} |")

if __name__ == "__main__":
    main()
