"""The built-in demo end to end, made of the real steps: lab → calibrate → compensate → evaluate → diagnose →
compensate and evaluate again with the effects the diagnosis found.

Every stage of the demo is the step a user would run, writing the folder that
step writes, in place under the demo folder, so that ``procam evaluate``,
``procam diagnose``, ``procam show`` and Blender read the demo's folders like
any other:

``captures/`` + ``lab-truth.json``  the lab's capture set of the demo rig (lens-shifted projector) on a built-in
                                    surface with the ``realistic`` effects, its truth sealed beside it
``calibration/``                    surface, projector pose (stage A), warp (stage B)
``cross-check/``                    Cycles vs Mitsuba on the true rig (the foundation check; images)
``targets/``                        the natural photographs compensated (16-bit, linear)
``compensation/``                   stage C, closed loop through the lab
``evaluation/``                     each input projected in the lab, PSNR/SSIM next to the uncompensated target
``diagnosis/``                      the sim-to-real diagnosis of the calibration (the lab truth is not read)
``compensation-effects/``,          the loop closed: the targets compensated again with the effects the diagnosis
``evaluation-effects/``             says compensation can invert (``--effects auto``), and evaluated (when it
                                    names any)
``summary.json``                    the figures the demo prints
``report.html``                     all of the above on one page (``procam report``), pictures embedded

Default: half resolution (camera 320×240, projector 400×300) so it runs in minutes on 2 cores; ``full`` uses
the paper's 640×480 / 800×600.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..capture.targets import natural_target
from ..errors import ProCamError
from ..imageio import write_image
from ..lab.crosscheck import run_cross_check
from ..lab.effects import parse_effects
from ..lab.truth import LabTruth
from ..options import option, same_option
from ..outputs import folder_in_place, write_manifest
from ..progress import Cancel, Progress, part, quiet
from ..stages.display_area import choose_area
from . import calibrate, capture, compensate, diagnose, evaluate, layout, projectors, report
from .capture import LabOptions
from .stage_c import StageCOptions

KIND = layout.DEMO
#: The demo's stages and their share of its running time, for progress.
PLAN = (("lab", 0.13), ("calibrate", 0.05), ("cross-check", 0.02), ("compensate", 0.2), ("evaluate", 0.05),
        ("diagnose", 0.38), ("with effects", 0.15), ("report", 0.02))


#: the strength of the tone curve of the demo's second projector (the lab's ``response``; ``realistic`` has 0.4)
SECOND_RESPONSE = 0.9


def second_projector(effects: str) -> str:
    """The lab's ``--projector-effects`` of the demo's second projector: the projector effects of ``effects``
    (every projector has them), with a tone curve of its own, as mixed projectors in a real rig have."""
    shared = parse_effects(effects)
    own = {n: shared[n].strength for n in shared.active if shared[n].kind.stage == "projector"}
    own["response"] = SECOND_RESPONSE
    return "2:" + ",".join(f"{n}={v:g}" for n, v in own.items())


def _names(text: str) -> tuple[str, ...]:
    return tuple(n.strip() for n in text.split(",") if n.strip())


@dataclass(frozen=True)
class DemoOptions:
    """What ``procam demo`` asks for."""

    out: Path = Path("out/demo")
    full: bool = option(False, help="paper resolution: camera 640×480, projector 800×600")
    scale: float | None = option(
        None, min=0.05, max=2.0,
        help="fraction of the paper's resolution (default 0.5, or 1 with --full); e.g. 0.2 for a quick check")
    surface: str = option("vedge", choices=("plane", "curve", "vedge", "hedge"), help="the lab's surface")
    effects: str = option("realistic", help="lab effects (default: realistic)")
    targets: tuple[str, ...] = option(("city", "forest"), parse=_names, metavar="TARGETS",
                                      help="built-in targets, comma-separated (default city,forest)")
    # stage C's own declarations: the same flags, limits and help as procam compensate's
    schedule: str = same_option(StageCOptions, "schedule")
    iterations: int | None = same_option(StageCOptions, "iterations")
    samples: int = option(16, min=1, help="Cycles samples per pixel for the lab")
    projectors: int = same_option(LabOptions, "projectors",
                                  help="projectors side by side, overlapping by a fifth (default 1); above 1 the "
                                       "second has a tone curve of its own, their inputs are solved together and the "
                                       "evaluation reports the overlap")
    seed: int = option(0, min=0, help="seed of every random stream")
    force: bool = False


def _heat(diff: np.ndarray, scale: float) -> np.ndarray:
    """Signed difference as a blue–white–red image (|diff| = scale is saturated)."""
    d = np.clip(diff.mean(axis=2) / scale, -1, 1)
    out = np.ones(d.shape + (3,), np.float32)
    out[..., 0] -= np.clip(-d, 0, 1)
    out[..., 1] -= np.abs(d)
    out[..., 2] -= np.clip(d, 0, 1)
    return out


def run(options: DemoOptions, progress: Progress | None = None, cancel: Cancel | None = None, *,
        blend_writer: calibrate.BlendWriter | None = None) -> dict[str, Any]:
    """Run the demo into ``options.out`` (module doc); returns the summary it writes to ``summary.json``.
    ``blend_writer``: what writes the calibration's ``scene.blend`` (none without it)."""
    if options.samples < 1:
        raise ProCamError("samples must be ≥ 1")
    if not options.targets:
        raise ProCamError("the demo needs at least one built-in target")
    scale = options.scale if options.scale is not None else (1.0 if options.full else 0.5)
    if not 0.1 <= scale <= 1.0:
        raise ProCamError(f"the demo's scale must lie in [0.1, 1] of the paper's resolution, got {scale}")
    say = progress or quiet
    cam, proj = (round(640 * scale), round(480 * scale)), (round(800 * scale), round(600 * scale))
    summary: dict[str, Any] = {"format": KIND.format, "version": KIND.version,
                               "resolution": {"camera": cam, "projector": proj}, "surface": options.surface,
                               "effects": options.effects, "cycles_samples": options.samples, "seed": options.seed}
    seconds: dict[str, float] = {}
    spans, start = {}, 0.0
    for name, share in PLAN:
        spans[name] = part(say, start, start + share, f"[{name}] ")
        start += share
    t_start = time.perf_counter()
    with folder_in_place(options.out, force=options.force, what=KIND.what, replaceable=KIND.holds,
                         inputs=()) as out:
        t0 = time.perf_counter()
        truth_path = out / "lab-truth.json"
        several = options.projectors > 1
        # Mixed projectors are the rule in a real rig: the second one's tone curve is its own.
        capture.run_lab(LabOptions(out / "captures", surface=options.surface, effects=options.effects,
                                   seed=options.seed, samples=options.samples, truth=truth_path,
                                   camera_size=cam, projector_size=proj, projectors=options.projectors,
                                   projector_effects=second_projector(options.effects) if several else ""),
                        spans["lab"], cancel)
        truth = LabTruth.load(truth_path)
        seconds["lab"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        cal = calibrate.run(calibrate.CalibrateOptions(out / "captures", out / "calibration", seed=options.seed,
                                                       with_blend=blend_writer is not None),
                            spans["calibrate"], cancel, blend_writer=blend_writer)
        seconds["calibrate"] = time.perf_counter() - t0
        summary["calibration"] = {**pose_errors(cal.rig.projector, truth.rig.projector),
                                  "seconds": cal.report.get("seconds"),
                                  "warp_corners": cal.report.get("warp_report")}
        if several:
            summary["calibration"]["projectors"] = [
                {**pose_errors(cal.rig.projectors[k], truth.rig.projectors[k]),
                 "warp_corners": cal.for_projector(k).report.get("warp_report")} for k in range(options.projectors)]

        t0 = time.perf_counter()
        spans["cross-check"]("Cycles vs Mitsuba on the true rig, direct light", 0.0)
        check = run_cross_check(truth.for_projector(0).rig, truth.surface, bounces=0, samples=32, spp=32,
                                seed=options.seed)
        (out / "cross-check").mkdir()
        for name, img in check.images.items():
            write_image(out / "cross-check" / f"{name}.png", img)
        write_image(out / "cross-check" / "difference_white.png",
                    _heat(check.images["cycles_white"] - check.images["mitsuba_white"], 0.05))
        summary["cross_renderer"] = check.summary()
        seconds["cross_check"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        area = projectors.joint_area(projectors.views_of(cal), 4 / 3) if several else choose_area(cal, aspect=4 / 3)
        (out / "targets").mkdir()
        targets = tuple(write_image(out / "targets" / f"{name}.png", natural_target(name, area.size))
                        for name in options.targets)
        device = f"lab:{truth_path}"
        view = compensate.run(compensate.CompensateOptions(
            out / "calibration", targets, out / "compensation",
            StageCOptions(schedule=options.schedule, iterations=options.iterations, seed=options.seed,
                          device=device)), spans["compensate"], cancel)
        seconds["compensate"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        metrics = evaluate.run(evaluate.EvaluateOptions(out / "calibration", out / "compensation", targets, device,
                                                        out / "evaluation"), spans["evaluate"], cancel)
        seconds["evaluate"] = time.perf_counter() - t0
        summary["compensation"] = {"area": view.doc.get("area"), **_measured(view, metrics)}
        if several:
            summary["compensation"]["overlap"] = {"mean": metrics["mean"],
                                                  "mean_uncompensated": metrics["mean_uncompensated"]}

        t0 = time.perf_counter()
        # 192×144 working images, as scripts/bench_diagnosis.py measured the diagnosis.
        gap = diagnose.run(diagnose.DiagnoseOptions(out / "calibration", out / "diagnosis",
                                                    scale=min(1.0, 0.3 / scale)), spans["diagnose"], cancel)
        if several:
            summary["diagnosis"] = {"headline": gap["headline"], "differs": gap["differs"],
                                    "ranking": gap["ranking"][:4], "projectors": gap["projectors"]}
            gap = {"compensation": {"effects": []}}  # effect models around stage C: one projector only, for now
        else:
            summary["diagnosis"] = {"headline": gap.get("headline", ""), "residual": gap["residual"],
                                    "residual_after": gap["residual_after"],
                                    "selected": gap["selected"], "selected_params": gap["selected_params"],
                                    "absorbed": gap["absorbed"], "compensation": gap["compensation"]["effects"],
                                    "regions": gap["regions"][:3], "warnings": gap.get("warnings", [])}
        seconds["diagnose"] = time.perf_counter() - t0

        if gap["compensation"]["effects"]:
            # The loop closed: what inverting the effects the diagnosis found buys on the same targets.
            t0 = time.perf_counter()
            fx = part(spans["with effects"], 0.0, 0.8)
            view = compensate.run(compensate.CompensateOptions(
                out / "calibration", targets, out / "compensation-effects",
                StageCOptions(schedule=options.schedule, iterations=options.iterations, seed=options.seed,
                              device=device, effects="auto", diagnosis=out / "diagnosis")), fx, cancel)
            metrics = evaluate.run(evaluate.EvaluateOptions(out / "calibration", out / "compensation-effects",
                                                            targets, device, out / "evaluation-effects"),
                                   part(spans["with effects"], 0.8, 1.0), cancel)
            summary["with_effects"] = {"effects": gap["compensation"]["effects"], **_measured(view, metrics)}
            seconds["with_effects"] = time.perf_counter() - t0
        summary["seconds"] = {k: round(v, 1) for k, v in seconds.items()}
        summary["seconds_total"] = round(time.perf_counter() - t_start, 1)
        write_manifest(out / KIND.manifest, summary)
        # the page a person opens first: every folder above, pictures and plots in one file
        missing = report.missing_libraries()
        if missing:  # a Python without the plotting libraries (Blender's): the folders are the results
            summary["report"] = {"skipped": f"building it needs {' and '.join(missing)}"}
        else:
            t0 = time.perf_counter()
            made = report.run(report.ReportOptions((out,), out / report.REPORT_HTML, title="ProCam demo"),
                              spans["report"], cancel)
            summary["report"] = {"html": report.REPORT_HTML, "bytes": made.bytes, "seconds": round(made.seconds, 1)}
            seconds["report"] = time.perf_counter() - t0
            summary["seconds"]["report"] = round(seconds["report"], 1)
        write_manifest(out / KIND.manifest, summary)
    say("done", 1.0)
    return summary


def pose_errors(estimated: Any, true: Any) -> dict[str, float]:
    """A calibrated projector's position (cm) and direction (degrees) error against the lab's truth."""
    ang = np.degrees(np.arccos(np.clip(estimated.direction @ true.direction, -1, 1)))
    return {"position_error_cm": 100 * float(np.linalg.norm(estimated.position - true.position)),
            "direction_error_deg": float(ang)}


def _measured(view: Any, metrics: dict[str, Any]) -> dict[str, Any]:
    """Per target and on average: PSNR and SSIM of the evaluation, uncompensated and compensated."""
    rows = [{"name": t["name"], "psnr": t["psnr"], "ssim": t["ssim"],
             "uncompensated_psnr": t["uncompensated"]["psnr"], "uncompensated_ssim": t["uncompensated"]["ssim"],
             "seconds": next(c.seconds for c in view.targets if c.name == t["name"]), "mode": t["mode"]}
            for t in metrics["targets"] if t.get("status") == "done"]
    return {"targets": rows, "mean": {k: float(np.mean([r[k] for r in rows]))
                                      for k in ("psnr", "ssim", "uncompensated_psnr", "uncompensated_ssim")}}
