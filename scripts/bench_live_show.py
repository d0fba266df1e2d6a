#!/usr/bin/env python3
"""Live shows in real time: how fast the real-time solve is, how close it comes to the full solve, and the loop.

Usage: ``.venv/bin/python scripts/bench_live_show.py [--parts speed,quality,loop] [--sizes 800x600,1920x1080]
[--variant llvm_ad_rgb|cuda_ad_rgb] [--scale 0.5] [--frames 24] [--seconds 60] [--work DIR]``

With no argument it is the quick run (under five minutes on 2 cores):

* **speed** — for each projector size, the demo rig at that size (camera at
  0.8 × its width and height, as the demo's 640×480 for 800×600; the demo's
  lens, pose and input share of the frame) on the built-in curved surface:
  renders the transport operator and builds the approximate inverse (seconds),
  then times the real-time solve of a panning picture frame by frame (the
  inverse, one SIRT step, the native frame): frames per second of the solve
  alone. ``--variant cuda_ad_rgb`` runs it on a GPU.
* **quality** — the lab at ``--scale`` (``realistic`` effects), calibrated,
  ``--frames`` frames of a panning clip compensated in real time and by the
  ``transport`` schedule (40 steps a frame, warm-started), every answer
  captured through the lab: captured PSNR of both, and flicker (the mean
  absolute change between consecutive captured frames inside the area, against
  the targets' own).
* **loop** — ``procam live-show`` on a projector window under Xvfb with the
  loopback camera, a video file as the source: frames per second of the whole
  loop, source → flip latency (median and 95th percentile), dropped frames
  over ``--seconds``.

Ends with the line ``800x600: N fps solve, M fps loop`` to compare runs.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from procam.addon.capture.targets import natural_target
from procam.addon.errors import ImageError
from procam.addon.stages.calibrate import Calibration
from procam.addon.stages.display_area import DisplayArea, fit_target, largest_rectangle
from procam.addon.stages.realtime import FrameGather, RealtimeView, build_inverse
from procam.addon.stages.transport import build_transport
from procam.addon.rig.demo import PROJECTOR_SHIFT_Y, PROJECTOR_THROW, demo_rig
from procam.addon.rig.model import Camera, Rig, intrinsics_from_fov, projector_intrinsics_from_throw
from procam.addon.surface.shapes import builtin_surface


def panning(image: np.ndarray, frame: int, step: int = 3) -> np.ndarray:
    """A clip's frame ``frame``: ``image`` moved ``step`` pixels a frame (a slow pan, as video content moves)."""
    return np.roll(image, step * frame, axis=1)


def picture_of(width: int, height: int) -> np.ndarray:
    """A natural picture (Blender's bundled photograph), or where bpy is not installed (a GPU machine with
    Mitsuba alone) smooth random colour with sharp bars: the solve's speed does not depend on what it shows."""
    try:
        return natural_target("city", (width, height))
    except ImageError:
        rng = np.random.default_rng(0)
        smooth = cv2.resize(rng.random((6, 8, 3)).astype(np.float32), (width, height), interpolation=cv2.INTER_CUBIC)
        smooth[:, ::16] = 1.0
        return np.clip(smooth, 0.0, 1.0)


def rig_at(width: int, height: int) -> Rig:
    """The demo rig with a projector of ``width × height`` (square pixels at any aspect: the demo's throw, lens
    shift and pose, its input ¾ of the frame's width) and a camera of 0.8 × that with the demo camera's field."""
    demo = demo_rig()
    proj = replace(demo.projector, intrinsics=projector_intrinsics_from_throw(width, height, PROJECTOR_THROW, 0.0,
                                                                               PROJECTOR_SHIFT_Y),
                   input_size=(round(0.75 * width), height), input_offset=None)
    return Rig(Camera(intrinsics_from_fov(round(0.8 * width), round(0.8 * height), 58.0)), proj)


def speed(size: tuple[int, int], variant: str | None, frames: int) -> dict[str, Any]:
    """The real-time solve of the demo rig at projector ``size`` (module doc, "speed")."""
    w, h = size
    rig = rig_at(w, h)
    cal = Calibration(rig, builtin_surface("curve"), None, "")
    t0 = time.perf_counter()
    op = build_transport(cal, variant=variant)
    t_op = time.perf_counter() - t0
    t0 = time.perf_counter()
    inv = build_inverse(op)
    t_inv = time.perf_counter() - t0
    cw, ch = op.camera_size
    lit = (op.weight.sum(axis=(1, 2)) > 0).reshape(ch, cw)
    box = largest_rectangle(lit, 4 / 3)
    assert box is not None, "the projector lights nothing the camera sees"
    area = DisplayArea(*box)
    view = op.rows(np.flatnonzero(area.mask((cw, ch)).ravel()), variant)
    rv = RealtimeView(view, inv)
    gather = FrameGather(view, rig.projector, None)
    picture = fit_target(picture_of(area.width, area.height), area)
    times = []
    for i in range(frames + 3):
        t = time.perf_counter()
        placed = area.place(panning(picture, i), (cw, ch)).reshape(-1, 3)[view.rows]
        frame = gather(rv.solve(placed, None, 1))
        if i >= 3:  # the first frames compile the kernels
            times.append(time.perf_counter() - t)
    assert frame.shape == (h, w, 3)
    ms = 1000 * np.asarray(times)
    return {"projector": f"{w}x{h}", "camera": f"{cw}x{ch}", "input": "x".join(map(str, rig.projector.input_size)),
            "variant": variant or "default", "operator_s": round(t_op, 1), "operator_mb": round(op.nbytes / 2 ** 20),
            "inverse_s": round(t_inv, 1), "inverse_mb": round(inv.nbytes / 2 ** 20),
            "solve_ms_median": round(float(np.median(ms)), 1), "solve_ms_p95": round(float(np.percentile(ms, 95)), 1),
            "fps_solve": round(1000 / float(np.median(ms)), 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--parts", default="speed,quality,loop")
    ap.add_argument("--sizes", default="800x600")
    ap.add_argument("--variant", default=None, help="Mitsuba variant of the speed part (default: the CPU's)")
    ap.add_argument("--scale", type=float, default=0.5, help="lab resolution of the quality part")
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--seconds", type=float, default=60.0, help="clip length of the loop part")
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None, help="write every figure here too")
    args = ap.parse_args()
    parts = set(args.parts.split(","))
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-live-"))
    work.mkdir(parents=True, exist_ok=True)
    figures: dict[str, Any] = {}
    fps_solve = fps_loop = None
    if "speed" in parts:
        figures["speed"] = []
        for text in args.sizes.split(","):
            size = tuple(int(v) for v in text.lower().split("x"))
            row = speed(size, args.variant, args.frames)  # type: ignore[arg-type]
            figures["speed"].append(row)
            print(f"speed {row['projector']} (camera {row['camera']}, input {row['input']}, {row['variant']}): "
                  f"operator {row['operator_s']} s / {row['operator_mb']} MB, inverse {row['inverse_s']} s / "
                  f"{row['inverse_mb']} MB; solve {row['solve_ms_median']} ms median, {row['solve_ms_p95']} ms p95 "
                  f"= {row['fps_solve']} fps", flush=True)
            if row["projector"] == "800x600":
                fps_solve = row["fps_solve"]
    if args.json:
        args.json.write_text(json.dumps(figures, indent=1) + "\n")
    print(f"800x600: {fps_solve if fps_solve is not None else 'n/a'} fps solve, "
          f"{fps_loop if fps_loop is not None else 'n/a'} fps loop")


if __name__ == "__main__":
    main()
