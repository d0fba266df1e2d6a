#!/usr/bin/env python3
"""Four projectors at show scale: each projector's operator, and the joint solve per target against one projector's.

Usage: ``.venv/bin/python scripts/bench_show_scale.py [--work DIR] [--layouts 4x1,2x2] [--input-size 1920x1080]
[--camera-size 640x480] [--scale 1] [--targets city,forest,interior] [--repeat 3] [--surface curve]
[--overlap 0.2] [--spp 64] [--engine auto]``.

The rig is the lab's truth, not a calibration: ``--layouts`` lays out four copies of the demo projector
(``4x1``: ``procam lab --projectors 4 --layout side-by-side``; ``2x2``: ``--layout grid``) on the lab's
``--surface``, each projector's input its whole ``--input-size`` frame (1920×1080: no lens-shift margin), seen by
the demo camera at ``--camera-size``; each projector's one-projector calibration is its true pose and the true
surface, no warp. No Gray code is rendered and nothing is calibrated: the benchmark measures the operator and the
solve at show scale, not calibration (a calibrated pose differs from the truth by millimetres, which changes
neither the operator's size nor the solve's work). ``--scale`` scales both sizes (0.1: a test's 192×108 inputs).

For each layout: every projector's light-transport operator built (``build_transport``, the defaults ``procam
precompute`` uses: one bounce, ``--spp`` 64) in a process of its own, timed, with its arrays' size (index, weights,
indirect responses) and that process's peak RSS; the operators are kept in ``--work`` and reused by a later run (their
build figures read back, as are the solves' for the same targets and repeats). Then, in a fresh process that loads the
four operators, on each target (a photograph cropped to the area's aspect): the joint open-loop solve of the four
(transport schedule, derived blend, no θ, as ``bench_joint_time.py``; with the time its solver steps took, the rest
being the per-target work on whole inputs) over the largest area every projector lights part of (a wide one for 4×1),
and in turn with it one projector alone (the one lighting most of that area, its own operator, the same input size,
``verify=False``) on the same area (the joint solve's camera rows) and on its own area (the largest inside its own
footprint: a show of one projector). Times are medians of ``--repeat`` runs after one warm-up (which builds the area's
views of the operators), wall and CPU seconds (every thread's); the solves compared run in turn in one process,
because on shared cores the wall time of runs minutes apart differed by 2×.
Memory: the operators' arrays, and the peak RSS of the joint process against that of a process that loads the one
projector alone and runs the same solves. ``--engine``: where the solves' steps run (``numpy`` around the
operators' gathers, ``drjit`` all on the operators' backend, ``auto`` as ``compensate``: Dr.Jit;
stages/solve_jit.py); the variant is Mitsuba's default here (``cuda_ad_rgb`` where a GPU is found,
``PROCAM_VARIANT`` overrides).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from procam.addon.capture.targets import natural_target
from procam.addon.lab.truth import make_truth
from procam.addon.lab.layouts import lay_out
from procam.addon.rig.demo import demo_camera, demo_projector
from procam.addon.rig.model import Rig
from procam.addon.stages.calibrate import Calibration
from procam.addon.stages.compensate import Compensator
from procam.addon.stages.display_area import DisplayArea, DisplayAreaError, fit_target
from procam.addon.render import backend
from procam.addon.stages.joint import ENGINES, JointCompensator
from procam.addon.stages.transport import DIRECT_SPP, TransportOperator, build_transport
from procam.addon.steps.projectors import MIN_LIT, footprints, joint_area

#: ``--layouts`` names → (the lab's layout, projectors).
LAYOUT_NAMES = {"4x1": ("side-by-side", 4), "2x2": ("grid", 4)}


def size_arg(text: str) -> tuple[int, int]:
    w, _, h = text.lower().partition("x")
    return int(w), int(h)


def scaled(size: tuple[int, int], scale: float) -> tuple[int, int]:
    return max(8, round(size[0] * scale)), max(6, round(size[1] * scale))


def peak_rss_mb() -> float:
    """This process's peak resident memory (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def rig_of(args: argparse.Namespace, layout: str) -> tuple[Rig, Any]:
    """The layout's rig (every projector's input its whole frame) and the lab's surface."""
    camera = demo_camera(*scaled(args.camera_size, args.scale))
    frame = scaled(args.input_size, args.scale)
    template = replace(demo_projector(*frame), input_size=frame, input_offset=(0, 0))
    kind, count = LAYOUT_NAMES[layout]
    surface = make_truth(args.surface, rig=Rig(camera, template)).surface
    laid = lay_out(template, camera, surface, count, kind, args.overlap)
    truth = make_truth(surface, rig=Rig(camera, laid[0], tuple(laid[1:])), projectors=count,
                       surface_source=args.surface)
    return truth.rig, truth.surface


def calibration_of(rig: Rig, surface: Any, k: int) -> Calibration:
    """Projector ``k``'s one-projector calibration from the truth: its true pose, the true surface, no warp."""
    return Calibration(Rig(rig.camera, rig.projectors[k]), surface, None, "")


def op_path(folder: Path, k: int) -> Path:
    return folder / f"transport_p{k + 1}.npz"


def load_op(folder: Path, k: int) -> TransportOperator:
    with np.load(op_path(folder, k)) as data:
        return TransportOperator.from_arrays(data, json.loads((folder / f"build_p{k + 1}.json").read_text())["report"])


def timed(fns: dict[str, Callable[[], Any]], repeat: int) -> dict[str, tuple[float, float, Any]]:
    """Each solve's median wall and CPU seconds (every thread of this process) and its last answer, the solves run
    in turn ``repeat`` times after one warm-up each, so that the ones compared share whatever else the cores
    were doing."""
    out: dict[str, Any] = {name: fn() for name, fn in fns.items()}  # warm-up: views gathered, kernels compiled
    walls: dict[str, list[float]] = {name: [] for name in fns}
    cpus: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeat):
        for name, fn in fns.items():
            t0, c0 = time.perf_counter(), time.process_time()
            out[name] = fn()
            walls[name].append(time.perf_counter() - t0)
            cpus[name].append(time.process_time() - c0)
    return {name: (float(np.median(walls[name])), float(np.median(cpus[name])), out[name]) for name in fns}


def lit_in(cover: np.ndarray, area: DisplayArea) -> list[int]:
    """How many pixels of ``area`` each projector lights (``cover``: (N, H, W) footprints)."""
    return [int(c[area.y:area.y + area.height, area.x:area.x + area.width].sum()) for c in cover]


def show_area(views: list[Calibration]) -> DisplayArea:
    """The largest display area every projector lights part of, over aspects from half to twice their lit bounding
    box's (footprints on a curved surface are no rectangles: the box's own aspect may hold only part of them)."""
    cover = footprints(views)
    ys, xs = np.nonzero(cover.any(axis=0))
    box = float(xs.max() - xs.min() + 1) / float(ys.max() - ys.min() + 1)
    areas = []
    for share in np.geomspace(0.5, 2.0, 13):
        try:
            area = joint_area(views, box * share)
        except DisplayAreaError:
            continue
        if min(lit_in(cover, area)) >= MIN_LIT:
            areas.append(area)
    if not areas:
        raise SystemExit("the projectors light no display area together; give a larger --scale")
    return max(areas, key=lambda a: a.width * a.height)


# -- the child processes ---------------------------------------------------------------------------------------

def child_build(args: argparse.Namespace, folder: Path, rig: Rig, surface: Any) -> None:
    k = args.projector
    t0 = time.perf_counter()
    op = build_transport(calibration_of(rig, surface, k), spp=args.spp)
    seconds = time.perf_counter() - t0
    np.savez(op_path(folder, k), **op.arrays())
    doc = {"seconds": seconds, "operator_mb": op.nbytes / 2 ** 20, "peak_rss_mb": peak_rss_mb(),
           "variant": backend.default_variant(), "report": op.report}
    (folder / f"build_p{k + 1}.json").write_text(json.dumps(doc, indent=1))


def child_solve(args: argparse.Namespace, folder: Path, rig: Rig, surface: Any) -> None:
    """``--child joint``: the four together, and in turn with them (same process, same moments) the projector
    lighting most of their area alone, on that area and on its own; ``--child one``: that projector alone in a
    process of its own, for its memory."""
    count = len(rig.projectors)
    views = [calibration_of(rig, surface, k) for k in range(count)]
    out: dict[str, Any] = {"targets": {}}
    area = show_area(views)
    lit = lit_in(footprints(views), area)
    one = int(np.argmax(lit))  # the projector lighting most of the area (in 4×1 an inner one)
    own = show_area(views[one:one + 1])
    out["projector"], out["lit"] = one + 1, lit
    comps: dict[int, Compensator] = {}
    for k in range(count) if args.child == "joint" else [one]:
        comps[k] = Compensator(views[k])
        comps[k].transport = load_op(folder, k)
        comps[k].engine = args.engine  # one projector alone steps where the joint solve does
    out["operator_mb"] = sum(c.transport.nbytes for c in comps.values()) / 2 ** 20
    joint = JointCompensator(list(comps.values()), engine=args.engine) if args.child == "joint" else None
    alone = comps[one]
    for name in args.targets:
        fitted = fit_target(natural_target(name, area.size), area)
        own_fitted = fit_target(natural_target(name, own.size), own)
        fns: dict[str, Callable[[], Any]] = {
            "alone": lambda f=fitted: alone.run(f, area, use_bias=False, verify=False, schedule="transport"),
            "own": lambda f=own_fitted: alone.run(f, own, use_bias=False, verify=False, schedule="transport")}
        if joint is not None:
            fns = {"joint": lambda f=fitted: joint.run(f, area, use_bias=False), **fns}
        row: dict[str, Any] = {"area": [area.width, area.height], "own_area": [own.width, own.height]}
        for key, (wall, cpu, res) in timed(fns, args.repeat).items():
            if key == "joint":
                out["engine"] = res.report["steps_on"]
            prefix = "" if key in ("joint", "alone") and key == next(iter(fns)) else f"{key}_"
            row.update({f"{prefix}seconds": wall, f"{prefix}cpu": cpu, f"{prefix}psnr": res.report["psnr_simulated"],
                        f"{prefix}steps": res.report.get("seconds_steps")})  # the last run's solver steps
        out["targets"][name] = row
    out["peak_rss_mb"] = peak_rss_mb()
    out["variant"] = backend.default_variant()
    solve_file(args, folder, args.child).write_text(json.dumps(out, indent=1))


# -- the parent -------------------------------------------------------------------------------------------------

def run_child(args: argparse.Namespace, layout: str, child: str, projector: int = 0) -> None:
    cmd = [sys.executable, __file__, "--child", child, "--projector", str(projector), "--layouts", layout,
           "--work", str(args.work), "--input-size", "x".join(map(str, args.input_size)),
           "--camera-size", "x".join(map(str, args.camera_size)), "--scale", str(args.scale),
           "--targets", ",".join(args.targets), "--repeat", str(args.repeat), "--surface", args.surface,
           "--overlap", str(args.overlap), "--spp", str(args.spp), "--engine", args.engine]
    # The child finds this very procam package (the parent may have it from a path of its own, not PYTHONPATH).
    home = str(Path(sys.modules["procam"].__file__ or "").parent.parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (home, os.environ.get("PYTHONPATH")) if p)}
    subprocess.run(cmd, check=True, env=env)


def folder_of(args: argparse.Namespace, layout: str) -> Path:
    cam, frame = scaled(args.camera_size, args.scale), scaled(args.input_size, args.scale)
    return args.work / (f"{layout}-{args.surface}-cam{cam[0]}x{cam[1]}-in{frame[0]}x{frame[1]}-ov{args.overlap:g}"
                        f"-spp{args.spp}")


def solve_file(args: argparse.Namespace, folder: Path, child: str) -> Path:
    """Where a solve's figures are kept: per targets and repeats (the operators are the folder's)."""
    engine = f"-{args.engine}" if args.engine != "auto" else ""
    return folder / f"solve_{child}-{'_'.join(args.targets)}-r{args.repeat}{engine}-{backend.default_variant()}.json"


def measure(args: argparse.Namespace, layout: str) -> dict[str, Any]:
    folder = folder_of(args, layout)
    folder.mkdir(parents=True, exist_ok=True)
    count = LAYOUT_NAMES[layout][1]
    builds = []
    for k in range(count):
        if not (op_path(folder, k).is_file() and (folder / f"build_p{k + 1}.json").is_file()):
            print(f"{layout}: building projector {k + 1}'s operator", flush=True)
            run_child(args, layout, "build", k)
        builds.append(json.loads((folder / f"build_p{k + 1}.json").read_text()))
    solves = {}
    for child in ("one", "joint"):
        if not solve_file(args, folder, child).is_file():
            print(f"{layout}: timing {'the joint solve' if child == 'joint' else 'one projector alone'}", flush=True)
            run_child(args, layout, child)
        solves[child] = json.loads(solve_file(args, folder, child).read_text())
    return {"builds": builds, **solves}


def steps_text(seconds: float | None) -> str:
    """The joint solve's steps (its last timed run), or a dash for figures kept before they were recorded."""
    return "–" if seconds is None else f"{seconds:.3f}"


def table(args: argparse.Namespace, results: dict[str, dict[str, Any]]) -> str:
    cam, frame = scaled(args.camera_size, args.scale), scaled(args.input_size, args.scale)
    first = next(iter(results.values()))["joint"]
    lines = [f"Variant `{first.get('variant')}`, the joint solve's steps in {first.get('engine')}. "
             f"Camera {cam[0]}×{cam[1]}, 4 projectors with {frame[0]}×{frame[1]} inputs, `{args.surface}`, overlap "
             f"{args.overlap:g}; calibration: the lab's truth (true poses and surface, no Gray code rendered); "
             f"open loop, transport schedule, no θ; median of {args.repeat} after a warm-up, the joint solve and the "
             "projector alone timed in turn in one process (wall seconds, CPU seconds of every thread in brackets); "
             "memory: each in a process of its own.", ""]
    lines += ["| layout | projector | operator build s | operator MB | build peak RSS MB | spacing | "
              "pixels wider than spacing |", "|---|---|---|---|---|---|---|"]
    for layout, res in results.items():
        for k, b in enumerate(res["builds"]):
            rep = b["report"]
            wide = 100 * rep["pixels_wider_than_spacing"]
            lines.append(f"| {layout} | {k + 1} | {b['seconds']:.1f} | {b['operator_mb']:.1f} | "
                         f"{b['peak_rss_mb']:.0f} | {rep['spacing']} | {wide:.1f} % |")
    lines += ["", "| layout | target | area | joint s (CPU s) | alone: projector | alone s, same area (CPU s) | "
              "joint ÷ alone (CPU) | own area | alone s, own area (CPU s) | joint ÷ alone own (CPU) | "
              "prediction dB, joint / alone own | joint's steps s |", "|" + "---|" * 12]
    for layout, res in results.items():
        for name, j in res["joint"]["targets"].items():
            lines.append(f"| {layout} | {name} | {j['area'][0]}×{j['area'][1]} | {j['seconds']:.3f} ({j['cpu']:.3f}) | "
                         f"{res['joint']['projector']} | {j['alone_seconds']:.3f} ({j['alone_cpu']:.3f}) | "
                         f"{j['seconds'] / j['alone_seconds']:.2f}× ({j['cpu'] / j['alone_cpu']:.2f}×) | "
                         f"{j['own_area'][0]}×{j['own_area'][1]} | {j['own_seconds']:.3f} ({j['own_cpu']:.3f}) | "
                         f"{j['seconds'] / j['own_seconds']:.2f}× ({j['cpu'] / j['own_cpu']:.2f}×) | "
                         f"{j['psnr']:.2f} / {j['own_psnr']:.2f} | {steps_text(j.get('steps'))} |")
    lines += ["", "| layout | operators MB, 4 / 1 | ratio | peak RSS MB, joint / alone (own processes) | ratio | "
              "time per target s, joint / alone same area, mean | ratio (CPU) |", "|---|---|---|---|---|---|---|"]
    for layout, res in results.items():
        j, o = res["joint"], res["one"]
        mean = {key: float(np.mean([t[key] for t in j["targets"].values()]))
                for key in ("seconds", "cpu", "alone_seconds", "alone_cpu")}
        rss = (j["peak_rss_mb"], o["peak_rss_mb"])
        lines.append(f"| {layout} | {j['operator_mb']:.1f} / {o['operator_mb']:.1f} | "
                     f"{j['operator_mb'] / o['operator_mb']:.2f}× | {rss[0]:.0f} / {rss[1]:.0f} | "
                     f"{rss[0] / rss[1]:.2f}× | "
                     f"{mean['seconds']:.3f} / {mean['alone_seconds']:.3f} | "
                     f"{mean['seconds'] / mean['alone_seconds']:.2f}× ({mean['cpu'] / mean['alone_cpu']:.2f}×) |")
    return "\n".join(lines)


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("bench-show-scale"))
    ap.add_argument("--layouts", default="4x1,2x2")
    ap.add_argument("--input-size", type=size_arg, default=(1920, 1080))
    ap.add_argument("--camera-size", type=size_arg, default=(640, 480))
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--targets", default="city,forest,interior")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--surface", default="curve")
    ap.add_argument("--overlap", type=float, default=0.2)
    ap.add_argument("--spp", type=int, default=DIRECT_SPP, help="samples per pixel of the operator's direct renders "
                    f"(default {DIRECT_SPP}, as procam precompute; a test's tiny run takes fewer)")
    ap.add_argument("--engine", choices=ENGINES, default="auto",
                    help="where the solves' steps run (default auto, as compensate: Dr.Jit)")
    ap.add_argument("--child", choices=("build", "one", "joint"), help=argparse.SUPPRESS)
    ap.add_argument("--projector", type=int, default=0, help=argparse.SUPPRESS)
    return ap


def main(argv: list[str] | None = None) -> str:
    args = parser().parse_args(argv)
    args.targets = [t for t in args.targets.split(",") if t]
    layouts = [name for name in args.layouts.split(",") if name]
    unknown = [name for name in layouts if name not in LAYOUT_NAMES]
    if unknown:
        raise SystemExit(f"--layouts takes {', '.join(LAYOUT_NAMES)}, got {', '.join(unknown)}")
    args.work = args.work.absolute()
    if args.child:
        rig, surface = rig_of(args, layouts[0])
        folder = folder_of(args, layouts[0])
        (child_build if args.child == "build" else child_solve)(args, folder, rig, surface)
        return ""
    results = {name: measure(args, name) for name in layouts}
    text = table(args, results)
    print(text, flush=True)
    (args.work / "table.md").write_text(text + "\n")
    return text


if __name__ == "__main__":
    main()
