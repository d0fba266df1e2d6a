"""Benchmark of the sim-to-real diagnosis on lab data whose injected effects are withheld (issue 6).

For each case (a surface and a set of injected effects) it renders a lab capture
set, calibrates, and runs ``procam diagnose`` on the calibration alone; only this
script reads the truth file, to score the answer. Cases: no effect, each single
effect, and pairs, on each surface. It then compensates a few natural targets
open loop (θ from the validation captures), once with the base model and once
with the selected effects around stage C, and measures both through the lab.

Prints (and writes as JSON/Markdown with ``--out``) the confusion table, the
share of the above-floor residual each injected effect removes, and the
compensation PSNR with and without the selected effects. Resumable: each case's
folders under ``--work`` are reused when complete.

    .venv/bin/python scripts/bench_diagnosis.py --work /tmp/gapbench --out /tmp/gapbench/report

``--timing`` only times calibrate and diagnose on the demo's case, in one process as ``procam demo`` runs them, and
prints the diagnosis's verdict (what a faster diagnosis must leave as it was):

    .venv/bin/python scripts/bench_diagnosis.py --work /tmp/gapbench --timing
"""

from __future__ import annotations

import argparse
import filecmp
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

#: Injected alone, an effect whose held-out RMSE stays within this factor of the no-effect floor leaves no gap.
GAP_MARGIN = 1.05
#: An effect matters for compensation from the strength at which it changes the base model's PSNR this much (dB).
MATTERS_DB = 0.3
SINGLE = ("response", "crosstalk", "black_level", "vignetting", "defocus", "interreflection", "glossy",
          "camera_response", "distortion", "depth_noise")
#: Pairs injected together. Some pair an effect the calibration absorbs (found from its evidence) with one the
#: residual shows; interreflection on the plane cannot show (a flat surface has no bounces), so the summary also
#: counts the pairs whose effects each leave a gap or are found alone.
#: Other functional forms of modelled causes, and causes the diagnosis has no model for (the lab's registry says
#: which model names each one's cause: ``EffectKind.diagnosis_name``).
VARIANTS = ("response_scurve", "defocus_depth", "lamp", "distortion_tangential")
UNMODELLED = ("warmup", "surface_moved", "subsurface")
#: Effects that act in one place of the surface (a highlight, light bouncing in a crease): the diagnosis's first
#: region is scored against where the lab truth says each changes the image (``footprint``).
LOCAL = ("glossy", "interreflection")
PAIRS = (("response", "defocus"), ("crosstalk", "interreflection"), ("black_level", "glossy"),
         ("camera_response", "depth_noise"), ("response", "black_level"), ("crosstalk", "glossy"),
         ("camera_response", "defocus"), ("vignetting", "glossy"), ("distortion", "response"))


def _cli(argv: list[str]) -> None:
    from procam.addon.cli.app import main

    code = main(argv)
    if code != 0:
        raise SystemExit(f"procam {' '.join(argv)} failed with exit code {code}")


def case_name(surface: str, effects: tuple[str, ...], seed: int = 0, strength: float = 0.5) -> str:
    # strength 0.5 keeps the folder names of the first matrix, so its cases are reused
    return (f"{surface}__{'+'.join(effects) or 'none'}" + (f"__seed{seed}" if seed else "")
            + (f"__s{strength:g}" if effects and strength != 0.5 else ""))


def cause_of(effect: str) -> str | None:
    """The diagnosis model that names an injected lab effect's cause (None: the diagnosis has none)."""
    from procam.addon.lab.effects import REGISTRY

    return REGISTRY[effect].diagnosis_name


def run_case(work: Path, surface: str, effects: tuple[str, ...], strength: float, scale: float, samples: int,
             diag_scale: float, seed: int = 0) -> tuple[Path, Path, dict]:
    name = case_name(surface, effects, seed, strength)
    lab, truth, cal, diag = (work / name / "captures", work / name / "truth.json", work / name / "calibration",
                             work / name / "diagnosis")
    spec = ",".join(f"{e}={strength}" for e in effects) or "none"
    if not (truth.is_file() and (lab / "capture.json").is_file()):
        _cli(["lab", "--surface", surface, "--effects", spec, "--scale", str(scale), "--samples", str(samples),
              "--out", str(lab), "--truth", str(truth), "--seed", str(seed), "--force"])
    if not (cal / "calibration.json").is_file():
        _cli(["calibrate", str(lab), "--out", str(cal), "--no-blend-output", "--force"])
    if not (diag / "gap.json").is_file():
        _cli(["diagnose", str(cal), "--out", str(diag), "--scale", str(diag_scale), "--force"])
    return cal, truth, json.loads((diag / "gap.json").read_text())


def same_captures(a: Path, b: Path) -> bool:
    """True when two capture folders hold byte for byte the same images and depth maps (``capture.json`` aside:
    it names the injected effects)."""
    def data(folder: Path) -> list[Path]:
        return sorted(f.relative_to(folder) for f in folder.rglob("*") if f.is_file() and f.parent != folder)

    names = data(a)
    return names == data(b) and all(filecmp.cmp(a / n, b / n, shallow=False) for n in names)


def changes_nothing(work: Path, surface: str, effects: tuple[str, ...], seed: int, strength: float, scale: float,
                    samples: int) -> bool:
    """True when the case's captures are the no-effect case's of the same seed (that lab is rendered if missing):
    the injected effect has nothing to act on there (bounce light on a flat plane), so no diagnosis can tell the
    case from one without it and "nothing" is the only right answer."""
    mine = work / case_name(surface, effects, seed, strength) / "captures"
    if not effects or not mine.is_dir():  # (a row logged from another work folder: cannot tell)
        return False
    none_lab = work / case_name(surface, (), seed) / "captures"
    if not (none_lab / "capture.json").is_file():
        _cli(["lab", "--surface", surface, "--effects", "none", "--scale", str(scale), "--samples", str(samples),
              "--out", str(none_lab), "--truth", str(none_lab.parent / "truth.json"), "--seed", str(seed),
              "--force"])
    return same_captures(mine, none_lab)


def footprint(truth_path: Path, effect: str, samples: int = 64) -> np.ndarray:
    """Where an injected effect changes the white capture, drawn by the diagnosis's own region rule.

    The white input is rendered twice through the lab truth, with and without the effect (pixel noise off,
    more samples than the captures), and the squared difference goes through ``gap.regions.hot_set``: the
    compact set holding half of it. For ``glossy`` the difference is the lobe's own light: the lab mixes
    the lobe in at weight w, so "with" is (1 − w)·diffuse + w·lobe, and the diffuse light the mix takes away
    (a per-pixel gain following the paint, which the albedo read from white holds) is not where the
    highlight is. Read from the truth, so only this script calls it.
    """
    from dataclasses import replace

    from procam.addon.gap.regions import hot_set
    from procam.addon.lab.truth import LabTruth
    from procam.addon.lab.cycles_device import LabDevice

    truth = LabTruth.load(truth_path)
    proj = truth.rig.projector
    white = proj.frame_from_input(np.ones(proj.input_size[::-1] + (3,), np.float32))
    shots = []
    for fx in (truth.effects, truth.effects.with_effect(effect, 0.0)):
        with LabDevice(replace(truth, effects=fx.with_effect("noise", 0.0)), samples=samples) as device:
            shots.append(device.project(white).mean(axis=2))
    lit = shots[1] > 0.08 * float(shots[1].max())
    keep = 1.0 - truth.effects["glossy"]["weight"] if effect == "glossy" else 1.0
    return hot_set((shots[0] - keep * shots[1]).astype(np.float64) ** 2, lit)


def region_scores(diag: Path, truth_path: Path, effect: str) -> dict:
    """IoU with the effect's footprint: of the diagnosis's first region, of its best region of the effect's cause,
    and of all the regions of the first region's cause together (light bouncing between the three folds of the
    curve lands in three bands: one place each, one cause); and of the first region with the parts of the
    footprint it lies on (``iou_part``: a footprint in disjoint parts, the hedge's highlight on both planes, cannot
    be one compact region)."""
    import cv2

    labels = cv2.imread(str(diag / "regions_label.png"), cv2.IMREAD_GRAYSCALE)
    truth = footprint(truth_path, effect)
    if labels is None:
        return {"error": "no regions_label.png (diagnosed before regions were saved)"}
    if truth.shape != labels.shape:
        truth = cv2.resize(truth.astype(np.uint8), labels.shape[::-1], interpolation=cv2.INTER_NEAREST) > 0
    regions = json.loads((diag / "gap.json").read_text())["regions"]

    def iou(ks: list[int]) -> float:
        sel = np.isin(labels, [k + 1 for k in ks])
        return float((sel & truth).sum() / max((sel | truth).sum(), 1))

    own = [k for k, r in enumerate(regions) if r.get("cause") == cause_of(effect)]
    top = regions[0].get("cause") if regions else None
    _, parts = cv2.connectedComponents(truth.astype(np.uint8), connectivity=8)
    first = labels == 1
    lies_on = np.isin(parts, np.unique(parts[first & truth]))
    return {"top_cause": top, "iou_top": iou([0]) if regions else 0.0,
            "iou_part": float((first & lies_on).sum() / max((first | lies_on).sum(), 1)),
            "iou_own": max((iou([k]) for k in own), default=0.0),
            "iou_cause": iou([k for k, r in enumerate(regions) if r.get("cause") == top]) if regions else 0.0,
            "footprint_pixels": int(truth.sum())}


def compensation_gain(cal_dir: Path, truth_path: Path, doc: dict, targets: list[str], iterations: int,
                      ablate: str | None = None) -> dict[str, float] | None:
    """Mean PSNR in the display area, through the lab, open loop: base model vs with the selected effects
    (and, with ``ablate``, with them less that one: ``without``, what inverting it buys)."""
    from procam.addon.capture.targets import natural_target
    from procam.addon.gap.compensation import AdaptedCaptures, load_adapter
    from procam.addon.lab.truth import LabTruth
    from procam.addon.lab.cycles_device import LabDevice
    from procam.addon.steps.calibrate import captures_of, read as read_calibration
    from procam.addon.stages.compensate import Compensator, area_psnr
    from procam.addon.stages.display_area import choose_area, fit_target

    cal = read_calibration(cal_dir)
    base = Compensator(cal)
    bias = base.estimate_bias()
    truth = LabTruth.load(truth_path)

    def around(gap_doc: dict) -> tuple:
        """Stage C with a diagnosis's inverted effects around it, as the compensate step runs --effects auto:
        (adapter, compensator, open-loop θ), or None when it inverts nothing."""
        adapter = load_adapter(gap_doc, cal.rig.projector)
        if not adapter.params:
            return None
        comp = adapter.compensator(cal)
        adapter.blur_in_solve(comp)  # the schedule here is the default, transport
        return adapter, comp, comp.estimate_bias(AdaptedCaptures(captures_of(cal), adapter))

    def captured(x: np.ndarray, placed: np.ndarray, area, seed: int | None = None) -> float:
        # Each input is the first shot of a device of its own: base and effects see the same sensor and Cycles
        # noise draw (common random numbers), so their difference is the inputs' and not the noise's.
        with LabDevice(truth, seed=seed) as device:
            return area_psnr(device.project(x), placed, area)

    # base_again: the base input under another noise draw (another lab seed): how far two captures of the same
    # input differ, the scale against which a small difference between separate captures would be read.
    out = {"base": [], "effects": [], "base_again": []}
    variants = {"effects": around(doc)}
    inverted = (doc.get("compensation") or {}).get("params") or {}
    if ablate in inverted:
        variants["without"] = around({**doc, "compensation": {**doc["compensation"], "params": {
            n: v for n, v in inverted.items() if n != ablate}}})
        out["without"] = []
    for t in targets:
        img = natural_target(t, (400, 300))
        area = choose_area(cal, aspect=4 / 3)
        placed = area.place(fit_target(img, area), cal.rig.camera.intrinsics.size)
        r0 = base.run(img, area, open_loop_theta=bias, iterations_z=iterations, iterations_joint=0)
        out["base"].append(captured(r0.x_frame, placed, area))
        out["base_again"].append(captured(r0.x_frame, placed, area, seed=truth.seed + 1))
        for key, v in variants.items():
            if v is None:
                out[key].append(out["base"][-1])
                continue
            adapter, comp, theta = v
            r = comp.run(adapter.model_target(fit_target(img, area), area), area, open_loop_theta=theta,
                         iterations_z=iterations, iterations_joint=0)
            out[key].append(captured(adapter.frame_to_send(r.x_input), placed, area))
    return {k: float(np.mean(v)) for k, v in out.items()}


def verdict(doc: dict) -> dict:
    """What a diagnosis concludes, without its figures: what a faster diagnosis must leave as it was."""
    return {"selected": doc.get("selected"), "modelled": doc.get("modelled"), "absorbed": doc.get("absorbed"),
            "ranking": [e["name"] for e in doc.get("effects", [])],
            "rounds": [(s["added"], s["candidate"]) for s in doc.get("steps", [])],
            "confidence": {e["name"]: e.get("confidence", {}).get("level") for e in doc.get("effects", [])},
            "regions": [(r.get("cause"), tuple(r["bbox"])) for r in doc.get("regions", [])],
            "compensation": (doc.get("compensation") or {}).get("effects"), "headline": doc.get("headline")}


def timing(args: argparse.Namespace) -> int:
    """The demo's lab, calibration and diagnosis (``procam demo``'s defaults: vedge, the realistic effects, half
    the paper's resolution, a diagnosis at 192×144), run in this process as the demo runs them: the seconds
    (wall and this process's CPU, every thread) of calibrate and of diagnose, their ratio, and the verdict."""
    import resource

    from procam.addon.steps import calibrate, capture, demo, diagnose
    from procam.addon.steps.capture import LabOptions

    work = args.work / (f"timing_{args.timing_surface}_{args.timing_effects.replace(',', '+')}_s{args.timing_scale:g}"
                        + (f"_p{args.timing_projectors}" if args.timing_projectors > 1 else ""))
    scale = args.timing_scale
    cam, proj = (round(640 * scale), round(480 * scale)), (round(800 * scale), round(600 * scale))
    if not (work / "captures" / "capture.json").is_file():  # the lab is not timed: reused when there
        capture.run_lab(LabOptions(work / "captures", surface=args.timing_surface, effects=args.timing_effects,
                                   seed=0, samples=args.samples, truth=work / "lab-truth.json", camera_size=cam,
                                   projector_size=proj, projectors=args.timing_projectors,
                                   projector_effects=demo.second_projector(args.timing_effects)
                                   if args.timing_projectors > 1 else "", force=True))

    def timed(run) -> tuple[float, float, object]:
        t0, c0 = time.perf_counter(), time.process_time()
        out = run()
        return time.perf_counter() - t0, time.process_time() - c0, out

    from procam.addon.cli.calibrate import blend_writer  # the demo's calibration writes its scene.blend too

    cal_wall, cal_cpu, _ = timed(lambda: calibrate.run(calibrate.CalibrateOptions(
        work / "captures", work / "calibration", seed=0, with_blend=True, force=True), blend_writer=blend_writer()))
    diag_wall, diag_cpu, doc = timed(lambda: diagnose.run(diagnose.DiagnoseOptions(
        work / "calibration", work / "diagnosis", scale=min(1.0, 0.3 / scale), force=True)))
    load = os.getloadavg()[0]
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"| step | wall s | CPU s |\n|---|---|---|\n| calibrate | {cal_wall:.1f} | {cal_cpu:.1f} |\n"
          f"| diagnose | {diag_wall:.1f} | {diag_cpu:.1f} |\n| diagnose ÷ calibrate | {diag_wall / cal_wall:.2f} | "
          f"{diag_cpu / cal_cpu:.2f} |")
    print(f"({work}; {args.timing_projectors} projector(s), {args.timing_surface}, {args.timing_effects}, scale "
          f"{scale:g}; load average {load:.1f} on {os.cpu_count()} CPUs at the end; peak RSS {peak:.0f} MB)")
    projectors = [doc] if args.timing_projectors == 1 else \
        [json.loads((work / "diagnosis" / p["folder"] / "gap.json").read_text()) for p in doc["projectors"]]
    for k, d in enumerate(projectors):
        print(f"verdict{'' if len(projectors) == 1 else f' of projector {k + 1}'}: "
              + json.dumps({**verdict(d), "seconds": d.get("seconds")}))
    if args.timing_projectors > 1:
        print("rig: " + json.dumps({k: doc.get(k) for k in ("headline", "differs")}))
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="folder for the cases (reused when rerun)")
    ap.add_argument("--out", type=Path, help="write report.json and report.md here")
    ap.add_argument("--surfaces", default="vedge,plane")
    ap.add_argument("--strength", default="0.5",
                    help="strength of each injected effect, or a comma list for the matrix (e.g. 0.25,0.5,1)")
    ap.add_argument("--scale", type=float, default=0.3, help="lab resolution as a share of the demo rig's")
    ap.add_argument("--samples", type=int, default=16, help="Cycles samples per pixel")
    ap.add_argument("--diag-scale", type=float, default=1.0, help="diagnosis working scale of the capture size")
    ap.add_argument("--cases", default="all",
                    help="'all' (none, singles, pairs), 'single', 'variants' (other forms of modelled causes), "
                         "'unmodelled', or a list such as 'none,response,response+defocus'")
    ap.add_argument("--seeds", type=int, default=1,
                    help="lab seeds per case (surface texture and noise; seed 0 keeps the plain case names)")
    ap.add_argument("--first-seed", type=int, default=0,
                    help="the first lab seed (seeds --first-seed … +--seeds−1), to add seeds to an earlier run")
    ap.add_argument("--targets", type=int, default=2, help="natural targets for the compensation comparison (0: skip)")
    ap.add_argument("--iterations", type=int, default=60, help="stage-C iterations per target (open loop)")
    ap.add_argument("--ablate", default=None, metavar="EFFECT",
                    help="also compensate with the inverted effects less this one (what inverting it buys)")
    ap.add_argument("--threshold", action="store_true",
                    help="detection thresholds: per surface and effect, the strengths in rising order until the "
                         "effect is ranked first (the stronger ones are not run)")
    ap.add_argument("--summarise", type=Path, default=None,
                    help="only print the tables of the case rows (JSON lines) an earlier, interrupted run logged")
    ap.add_argument("--timing", action="store_true",
                    help="only time calibrate and diagnose on the demo's case (see --timing-*) and print the verdict")
    ap.add_argument("--timing-scale", type=float, default=0.5, help="the timed lab's share of the paper's resolution "
                    "(the demo's default 0.5); the diagnosis works at 0.3 of it, as the demo's")
    ap.add_argument("--timing-surface", default="vedge")
    ap.add_argument("--timing-effects", default="realistic")
    ap.add_argument("--timing-projectors", type=int, default=1)
    args = ap.parse_args(argv)
    if args.timing:
        return timing(args)
    if args.summarise:
        rows = [json.loads(line) for line in args.summarise.read_text().splitlines() if line.startswith("{")]
        # A case logged twice (e.g. seed 0 of --cases none after the full matrix) counts once, as last logged.
        rows = list({(r["surface"], r.get("seed", 0), tuple(r["injected"]), r.get("strength", 0.5)): r
                     for r in rows}.values())
        for r in rows:  # rows logged before the check
            if "changes_nothing" not in r and len(r["injected"]) == 1:
                r["changes_nothing"] = changes_nothing(args.work, r["surface"], tuple(r["injected"]),
                                                       r.get("seed", 0), r.get("strength", 0.5), args.scale,
                                                       args.samples)
        print(report_markdown(rows, args))
        return 0

    families = {"all": [()] + [(e,) for e in SINGLE] + list(PAIRS), "single": [(e,) for e in SINGLE],
                "variants": [(e,) for e in VARIANTS], "unmodelled": [(e,) for e in UNMODELLED]}
    cases = []
    for c in args.cases.split(","):
        cases += families.get(c) or [tuple(c.split("+")) if c != "none" else ()]
    strengths = [float(v) for v in args.strength.split(",")]
    targets = ["city", "forest", "interior", "sunrise"][:args.targets]
    rows = []
    plan = [(s, k, e, st) for s in args.surfaces.split(",")
            for k in range(args.first_seed, args.first_seed + args.seeds) for e in cases
            for st in (strengths if e else strengths[:1])]
    found_at: set[tuple] = set()  # (surface, seed, effects) already ranked first at a lower strength
    for surface, seed, effects, strength in plan:
        if args.threshold and (surface, seed, effects) in found_at:
            continue
        t0 = time.perf_counter()
        cal, truth, doc = run_case(args.work, surface, effects, strength, args.scale, args.samples,
                                   args.diag_scale, seed)
        ranked = [e["name"] for e in doc["effects"] if not e.get("error")]
        before, after = doc["residual"]["rmse_structured"], doc["residual_after"]["rmse_structured"]
        floor_case = args.work / case_name(surface, (), seed) / "diagnosis" / "gap.json"
        floor_doc = json.loads(floor_case.read_text())["residual"] if floor_case.is_file() else None
        floor = floor_doc["rmse_structured"] if floor_doc else None
        removed = None
        if effects and floor_doc:
            # Per pixel class (smooth parts, pattern edges): the share of the RMSE above the no-effect
            # floor that the selected effects remove, in the class where the injected effect shows.
            shares = []
            for b, a, f in zip(doc["residual"]["mse_classes"], doc["residual_after"]["mse_classes"],
                               floor_doc["mse_classes"]):
                b, a, f = np.sqrt(b), np.sqrt(a), np.sqrt(f)
                if b - f > 0.1 * f:
                    shares.append((b - a) / (b - f))
            removed = max(shares) if shares else None
        comp = compensation_gain(cal, truth, doc, targets, args.iterations, args.ablate) if args.targets else None
        local = (region_scores(args.work / case_name(surface, effects, seed, strength) / "diagnosis", truth,
                               effects[0]) if len(effects) == 1 and effects[0] in LOCAL else None)
        row = {"surface": surface, "seed": seed, "strength": strength, "injected": list(effects),
               "causes": [cause_of(e) for e in effects], "first": ranked[0] if ranked else None,
               "unexplained": doc.get("unexplained"), "session_changed": doc.get("session", {}).get("changed"),
               # found where calibration absorbed it: the share of it the diagnosis's own law reaches
               "model_share": ((doc.get("evidence") or {}).get(cause_of(effects[0]) or "") or {}).get("model_share")
               if len(effects) == 1 else None,
               "changes_nothing": changes_nothing(args.work, surface, effects, seed, strength, args.scale,
                                                  args.samples) if len(effects) == 1 else False,
               "selected": doc["selected"], "absorbed": doc.get("absorbed", []), "rmse_before": before,
               "rmse_after": after, "floor": floor,
               "removed_above_floor": removed, "compensation": comp, "regions": local,
               "seconds": round(time.perf_counter() - t0, 1),
               "confidence": {e["name"]: e["confidence"].get("level") for e in doc["effects"]
                              if e["name"] in doc["selected"]}}
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
        if len(effects) == 1 and row["first"] == row["causes"][0]:
            found_at.add((surface, seed, effects))
    md = report_markdown(rows, args)
    print(md)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "report.json").write_text(json.dumps({"rows": rows, "settings": vars(args)}, indent=1,
                                                         default=str))
        (args.out / "report.md").write_text(md)
    return 0


def thresholds_table(rows: list[dict]) -> list[str]:
    """Per effect and surface, the smallest strength at which its cause is ranked first in ≥ 90 % of the seeds."""
    single = [r for r in rows if len(r["injected"]) == 1]
    if len({r.get("strength", 0.5) for r in single}) < 2:
        return []
    surfaces = sorted({r["surface"] for r in single})
    effects = list(dict.fromkeys(r["injected"][0] for r in single))
    lines = ["", "Detection threshold: the smallest strength at which the cause is ranked first in ≥ 90 % of the "
             "seeds (in brackets: named first / seeds at each strength tried; '–' never at the strengths tried):", "",
             "| effect | " + " | ".join(surfaces) + " |", "|---|" + "---|" * len(surfaces)]
    for e in effects:
        cells = []
        for surface in surfaces:
            mine = [r for r in single if r["surface"] == surface and r["injected"][0] == e]
            if mine and all(r.get("changes_nothing") for r in mine):
                cells.append("nothing to find (the captures are the no-effect case's)")
                continue
            mine = [r for r in mine if not r.get("changes_nothing")]
            tried = sorted({r.get("strength", 0.5) for r in mine})
            hits = {st: (sum(r["first"] == r["causes"][0] for r in mine if r.get("strength", 0.5) == st),
                         sum(r.get("strength", 0.5) == st for r in mine)) for st in tried}
            at = next((st for st in tried if hits[st][0] >= 0.9 * hits[st][1]), None)
            cells.append((f"{at:g}" if at is not None else "–") + " ("
                         + ", ".join(f"{st:g}: {h}/{n}" for st, (h, n) in hits.items()) + ")" if tried else "")
        lines.append(f"| {e} | " + " | ".join(cells) + " |")
    return lines


def compensation_table(rows: list[dict]) -> list[str]:
    """Per effect and surface: what the effect costs compensation with the base model (against the no-effect
    case of the same seed), what the selected effects give back, and the smallest strength changing it by
    ≥ ``MATTERS_DB``."""
    none = {(r["surface"], r.get("seed", 0)): r["compensation"]["base"] for r in rows
            if not r["injected"] and r["compensation"]}
    single = [r for r in rows if len(r["injected"]) == 1 and r["compensation"]
              and (r["surface"], r.get("seed", 0)) in none]
    if not single:
        return []
    surfaces = sorted({r["surface"] for r in single})
    lines = ["", f"Compensation cost: PSNR lost by the base model against the no-effect case (mean over seeds), and "
             f"what the selected effects give back (cost / gain in dB at each strength; a negative cost: the effect "
             f"raised it); the strength from which it changes compensation by ≥ {MATTERS_DB} dB ('–' none of those "
             f"tried):", "",
             "| effect | " + " | ".join(surfaces) + " |", "|---|" + "---|" * len(surfaces)]
    for e in dict.fromkeys(r["injected"][0] for r in single):
        cells = []
        for surface in surfaces:
            mine = [r for r in single if r["surface"] == surface and r["injected"][0] == e]
            at, parts = None, []
            for st in sorted({r.get("strength", 0.5) for r in mine}):
                here = [r for r in mine if r.get("strength", 0.5) == st]
                cost = float(np.mean([none[(r["surface"], r.get("seed", 0))] - r["compensation"]["base"]
                                      for r in here]))
                gain = float(np.mean([r["compensation"]["effects"] - r["compensation"]["base"] for r in here]))
                parts.append(f"{st:g}: {cost:.2f} / {gain:+.2f}")
                if at is None and abs(cost) >= MATTERS_DB:
                    at = st
            cells.append((f"{at:g}" if at is not None else "–") + f" ({'; '.join(parts)})" if parts else "")
        lines.append(f"| {e} | " + " | ".join(cells) + " |")
    return lines


def report_markdown(rows: list[dict], args: argparse.Namespace) -> str:
    lines = [f"Diagnosis benchmark: lab scale {args.scale}, {args.samples} Cycles spp, strength {args.strength}, "
             f"diagnosis at {args.diag_scale} of the capture size; compensation open loop, {args.iterations} "
             f"iterations, {args.targets} targets.", "",
             "| surface | injected | ranked first | selected | held-out RMSE before → after | floor | removed above "
             "floor | comp. PSNR base → with effects | s |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        comp = r["compensation"]
        c = f"{comp['base']:.2f} → {comp['effects']:.2f}" if comp else "–"
        rem = f"{r['removed_above_floor']:.0%}" if r["removed_above_floor"] is not None else "–"
        fl = f"{r['floor']:.4f}" if r["floor"] is not None else "–"
        where = (r["surface"] + (f" (seed {r['seed']})" if r.get("seed") else "")
                 + (f" at {r['strength']:g}" if r.get("injected") and r.get("strength", 0.5) != 0.5 else ""))
        lines.append(f"| {where} | {'+'.join(r['injected']) or 'none'} | {r['first']} | "
                     f"{', '.join(r['selected']) or 'none'} | {r['rmse_before']:.4f} → {r['rmse_after']:.4f} | {fl} | "
                     f"{rem} | {c} | {r['seconds']} |")
    single = [r for r in rows if len(r["injected"]) == 1 and r.get("causes", r["injected"]) == r["injected"]
              and not r.get("changes_nothing")]
    # An injected effect with nothing to act on leaves the captures byte for byte the no-effect case's: scored as
    # what it is, a no-effect case, not as a miss no diagnosis could avoid.
    void = [r for r in rows if r.get("changes_nothing")]
    variants = [r for r in rows if len(r["injected"]) == 1 and r.get("causes", r["injected"])[0]
                not in (None, r["injected"][0])]
    unmodelled = [r for r in rows if len(r["injected"]) == 1 and r.get("causes", r["injected"])[0] is None]
    none = [r for r in rows if not r["injected"]]
    pairs = [r for r in rows if len(r["injected"]) == 2]
    lines += thresholds_table(rows)
    lines += compensation_table(rows)
    lines += ["", "Summary:"]
    # An effect "leaves a gap" on a surface when, injected alone, it lifts the held-out RMSE > 5 % above the
    # no-effect floor; one that does not (absorbed by the calibration, or absent from that surface) cannot be found.
    def key(r: dict, effect: str) -> tuple:
        return r["surface"], r.get("seed", 0), effect, r.get("strength", 0.5)

    gap = {key(r, r["injected"][0]): r["floor"] is not None and r["rmse_before"] > GAP_MARGIN * r["floor"]
           for r in single}
    if single:
        first = sum(r["first"] == r["injected"][0] for r in single)
        sel = sum(r["selected"][:1] == r["injected"] for r in single)
        half = sum((r["removed_above_floor"] or 0) >= 0.5 for r in single)
        lines.append(f"- single effects: ranked first {first}/{len(single)}, selected first {sel}/{len(single)}, "
                     f"≥ 50 % of the above-floor residual removed {half}/{len(single)}")
        shows = [r for r in single if gap[key(r, r["injected"][0])]]
        hidden = [r for r in single if not gap[key(r, r["injected"][0])]]
        lines.append(f"  - that leave a gap ({len(shows)}): ranked first "
                     f"{sum(r['first'] == r['injected'][0] for r in shows)}, ≥ 50 % removed "
                     f"{sum((r['removed_above_floor'] or 0) >= 0.5 for r in shows)}")
        lines.append(f"  - that leave none ({len(hidden)}: "
                     f"{', '.join(sorted({r['surface'] + ' ' + r['injected'][0] for r in hidden}))}): ranked first "
                     f"{sum(r['first'] == r['injected'][0] for r in hidden)} (found where calibration absorbed it "
                     f"{sum(r['injected'][0] in r.get('absorbed', []) for r in hidden)}), nothing modelled "
                     f"{sum(not (set(r['selected']) - set(r.get('absorbed', []))) for r in hidden)}")
    if variants:
        named = sum(r["first"] == r["causes"][0] for r in variants)
        lines.append(f"- other forms of a modelled cause: the cause ranked first {named}/{len(variants)} ("
                     + ", ".join(f"{r['surface']} {r['injected'][0]} → {r['first']}"
                                 + (f" (its law fits {r['model_share']:.0%})" if r.get("model_share") is not None
                                    and r["first"] in r.get("absorbed", []) else
                                    f" (explains {r['unexplained']['explained_share']:.0%})" if r.get("unexplained")
                                    else "") for r in variants) + ")")
    if unmodelled:
        def wrong_high(r: dict) -> bool:
            return any(level == "high" for level in r["confidence"].values())
        said = sum(bool(r.get("session_changed") or (r.get("unexplained") or {}).get("detected"))
                   for r in unmodelled)
        lines.append(f"- effects the diagnosis has no model for: no high-confidence name "
                     f"{sum(not wrong_high(r) for r in unmodelled)}/{len(unmodelled)}; said the rig changed or "
                     f"left a remainder unexplained {said}/{len(unmodelled)} ("
                     + ", ".join(f"{r['surface']} {r['injected'][0]}: "
                                 + ("rig changed" if r.get("session_changed") else
                                    "unexplained" if (r.get("unexplained") or {}).get("detected") else
                                    f"selected {', '.join(r['selected']) or 'none'}")
                                 + (f" [{', '.join(f'{k} {v}' for k, v in r['confidence'].items())}]"
                                    if r["confidence"] else "") for r in unmodelled) + ")")
    if void:
        lines.append(f"- injected effects that change no capture ({len(void)}: "
                     f"{', '.join(sorted({r['surface'] + ' ' + r['injected'][0] for r in void}))}; their captures are "
                     f"the no-effect case's, byte for byte): nothing selected {sum(not r['selected'] for r in void)}/"
                     f"{len(void)}")
    if none:
        lines.append(f"- no effect: nothing selected {sum(not r['selected'] for r in none)}/{len(none)}; "
                     f"'unexplained' said {sum(bool((r.get('unexplained') or {}).get('detected')) for r in none)}, "
                     f"'the rig changed' said {sum(bool(r.get('session_changed')) for r in none)}")
    if pairs:
        both = sum(set(r["injected"]) <= set(r["selected"]) for r in pairs)
        lines.append(f"- two effects: both selected {both}/{len(pairs)}")
        known = [r for r in pairs if all(key(r, e) in gap for e in r["injected"])]
        shows = [r for r in known if all(gap[key(r, e)] for e in r["injected"])]
        found = {key(r, r["injected"][0]) for r in single if r["first"] == r["injected"][0]}
        alone = [r for r in known if all(key(r, e) in found for e in r["injected"])]
        if known:
            lines.append(f"  - where both leave a gap alone: both selected "
                         f"{sum(set(r['injected']) <= set(r['selected']) for r in shows)}/{len(shows)}; where "
                         f"each is found alone (a gap, or absorbed and found): "
                         f"{sum(set(r['injected']) <= set(r['selected']) for r in alone)}/{len(alone)}")
    # an effect that leaves no gap (bounces on a flat plane, a lobe the albedo holds) has no place to find
    local = [r for r in rows if r.get("regions") and "iou_top" in r["regions"] and r["floor"] is not None
             and r["rmse_before"] > GAP_MARGIN * r["floor"]]
    if local:
        lines.append(f"- regions of local effects that leave a gap: the first region overlaps the effect's true "
                     f"footprint with IoU ≥ 0.5 in {sum(r['regions']['iou_top'] >= 0.5 for r in local)}/{len(local)}; "
                     f"the regions of the first one's cause together in "
                     f"{sum(r['regions'].get('iou_cause', 0) >= 0.5 for r in local)}/{len(local)}; the first region "
                     f"with the parts of the footprint it lies on in "
                     f"{sum(r['regions'].get('iou_part', 0) >= 0.5 for r in local)}/{len(local)} (first / cause's / "
                     f"part: "
                     + ", ".join(f"{r['surface']} {r['injected'][0]} {r['strength']:g}: {r['regions']['iou_top']:.2f}"
                                 f" / {r['regions'].get('iou_cause', float('nan')):.2f}"
                                 f" / {r['regions'].get('iou_part', float('nan')):.2f} [{r['regions']['top_cause']}]"
                                 for r in local) + ")")
    comp = [r for r in rows if r["compensation"] and r["injected"]]
    if comp:
        gains = [r["compensation"]["effects"] - r["compensation"]["base"] for r in comp]
        worse = sum(g < -0.05 for g in gains)
        lines.append(f"- compensation with the selected effects: mean gain {np.mean(gains):+.2f} dB where an effect "
                     f"was injected; worse (by > 0.05 dB) in {worse}/{len(comp)} cases; worst "
                     f"{min(gains):+.2f} dB")
        ablated = [r for r in comp if "without" in r["compensation"]]
        if ablated:
            lines.append(f"- inverting {args.ablate} (with the other inverted effects against without it): "
                         + ", ".join(f"{r['surface']} {'+'.join(r['injected'])} {r['strength']:g}: "
                                     f"{r['compensation']['without']:.2f} → {r['compensation']['effects']:.2f} dB"
                                     for r in ablated))
        again = [abs(r["compensation"]["base_again"] - r["compensation"]["base"]) for r in rows
                 if r["compensation"] and "base_again" in r["compensation"]]
        if again:
            lines.append(f"- two captures of the same input differ by {np.median(again):.3f} dB (median), up to "
                         f"{max(again):.3f} dB, over {len(again)} cases")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
