#!/usr/bin/env python3
"""Time joint stage C on a stored calibration of several projectors, on whichever Mitsuba variant this machine has.

Usage: ``.venv/bin/python scripts/bench_joint_time.py CAL TARGET... [--build] [--repeat 3]``.

Needs no lab (no Blender): the calibration folder and the targets only, so it also runs on a machine with a GPU and
no Blender (``PROCAM_VARIANT`` or the default: ``cuda_ad_rgb`` where a GPU is found). For each projector: its
operator built in memory (``--build``, timed; else the stored one read), then per target the joint open-loop solve
(transport schedule, derived blend, no θ) and projector 1 alone on the same target, each timed (median over
``--repeat`` runs after one warm-up) with the PSNR of its own prediction, so two variants' answers can be compared.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any
from collections.abc import Callable

import numpy as np

from procam.addon.render import backend
from procam.addon.stages.transport import build_transport
from procam.addon.steps import calibrate as calibrate_step
from procam.addon.steps import projectors
from procam.addon.steps.stage_c import StageCOptions


def timed(fn: Callable[[], Any], repeat: int) -> tuple[float, Any]:
    fn()  # warm-up: kernels compiled, views gathered
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("calibration", type=Path)
    ap.add_argument("targets", type=Path, nargs="+")
    ap.add_argument("--build", action="store_true")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    variant = backend.default_variant()
    cal = calibrate_step.read(args.calibration)
    stage = projectors.JointStage(cal, StageCOptions())
    comps = stage.compensators
    cam = cal.rig.camera.intrinsics.size
    print(f"variant {variant}, camera {cam[0]}×{cam[1]}, {len(comps)} projectors "
          + ", ".join(f"{c.rig.projector.input_size[0]}×{c.rig.projector.input_size[1]}" for c in comps), flush=True)
    if args.build:
        for k, c in enumerate(comps):
            t0 = time.perf_counter()
            c.transport = build_transport(cal.for_projector(k), variant=variant)
            print(f"projector {k + 1}: operator built in {time.perf_counter() - t0:.1f} s "
                  f"({c.transport.report['direct_renders']} direct renders)", flush=True)
    for path in args.targets:
        image, _ = stage.load(path)
        area = stage.area_for(image)
        fitted = stage.fitted(image, area)
        joint_s, joint = timed(lambda f=fitted, a=area: stage.joint.run(f, a, use_bias=False), args.repeat)
        one_s, one = timed(lambda f=fitted, a=area: comps[0].run(f, a, use_bias=False, verify=False,
                                                               schedule="transport"), args.repeat)
        print(f"{path.stem}: joint {joint_s:.3f} s (prediction {joint.report['psnr_simulated']:.2f} dB), projector 1 "
              f"alone {one_s:.3f} s (prediction {one.report['psnr_simulated']:.2f} dB), {joint_s / one_s:.2f}×",
              flush=True)


if __name__ == "__main__":
    main()
