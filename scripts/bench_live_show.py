#!/usr/bin/env python3
"""Live shows in real time: how fast the real-time solve is, how close it comes to the full solve, and the loop.

Usage: ``.venv/bin/python scripts/bench_live_show.py [--parts quality,loop,speed] [--sizes 800x600,1920x1080]
[--variant llvm_ad_rgb|cuda_ad_rgb] [--scale 1] [--projector-size 1920x1080 --camera-size 1536x864] [--frames 12]
[--effects defocus --diagnosis DIR] [--follow] [--seconds 20] [--work DIR]``

With no argument it is the quick run (about five minutes on 2 cores): the lab
at the demo's resolution (camera 640×480, projector 800×600), its quality and
a 20 s loop; ``--seconds 60`` gives the 60 s clip's figures.

* **quality** — the lab at ``--scale`` (``realistic`` effects on the curve),
  calibrated, its inverse stored (``procam precompute --live``); ``--frames``
  frames of a panning clip compensated in real time and by the ``transport``
  schedule (40 steps a frame, warm-started from the previous frame as
  ``procam show`` does), every answer captured through the lab: captured PSNR
  inside the display area of both, and flicker (the mean absolute change
  between consecutive captured frames inside the area) against the targets'
  own; the real-time solve's milliseconds. The lab's camera adds fresh noise
  to every capture (the same frame captured twice differs by about as much
  as two frames of the pan), so every frame is captured a second time through
  the same lab without the camera's noise (sensor noise off, every shot
  drawing Cycles' first shot's samples: :class:`LabDevice`'s
  ``repeat_draws``): flicker and PSNR of those noise-free captures, and the
  flicker of the error (the mean absolute change of capture − target between
  consecutive frames: what changes beyond the content's own motion).
  ``--follow``: the real-time solve runs closed loop, its θ following the
  lab camera's (noisy) capture of every frame it showed (the live show
  follows one camera frame in three at 30 fps: this is its worst case). ``--effects`` (with the ``procam
  diagnose`` folder of that calibration, ``--diagnosis``) runs both solves with
  those effect models, as ``procam show --effects`` does; where they hold the
  projector lens's blur, the real-time solve without it is captured too.
* **loop** — ``procam live-show`` of that calibration on a projector window
  under Xvfb (open loop), a ``--seconds`` MJPEG clip of the panning picture
  at 30 fps as the source: frames per second of the whole loop, source → flip
  latency (median and 95th percentile), frames dropped. ``--fps 60`` plays a
  clip faster than the loop, to measure the loop's own ceiling.
* **speed** — for each projector size in ``--sizes``, the demo rig at that
  size (camera at 0.8 × its width and height, as the demo's 640×480 for
  800×600; the demo's lens, pose and input share of the frame) on the built-in
  curved surface: renders the transport operator and builds the approximate
  inverse (seconds), then times the real-time solve of a panning picture frame
  by frame: frames per second of the solve alone. ``--variant cuda_ad_rgb``
  runs it on a GPU (needs Mitsuba only: no lab, no Blender).

Ends with the line ``800x600: N fps solve, M fps loop`` (the quality part's real-time solves and the loop,
at ``--scale 1``; the speed part's 800x600 row when the lab parts are not run) to compare runs.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from procam.addon.capture.targets import natural_target
from procam.addon.cli.app import main as procam
from procam.addon.errors import ImageError
from procam.addon.stages.calibrate import Calibration
from procam.addon.stages.metrics import psnr
from procam.addon.stages.display_area import DisplayArea, fit_target, largest_rectangle
from procam.addon.stages.realtime import FrameGather, RealtimeView, build_inverse
from procam.addon.stages.transport import build_transport
from procam.addon.rig.demo import PROJECTOR_SHIFT_Y, PROJECTOR_THROW, demo_rig
from procam.addon.rig.model import Camera, Rig, intrinsics_from_fov, projector_intrinsics_from_throw
from procam.addon.steps import calibrate as calibrate_step
from procam.addon.steps.live_show import clip_latency
from procam.addon.steps.realtime import RealtimeSolver
from procam.addon.steps.stage_c import StageC, StageCOptions, device_pipeline
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


def flicker(seq: list[np.ndarray]) -> float:
    """The mean absolute change between consecutive images of ``seq`` (all pixels and channels), averaged over the
    pairs."""
    return float(np.mean([np.mean(np.abs(b - a)) for a, b in zip(seq, seq[1:])]))


def error_flicker(captures: list[np.ndarray], targets: list[np.ndarray]) -> float:
    """:func:`flicker` of the errors ``capture − target``: the change between consecutive frames beyond the
    targets' own (a capture that moves exactly as its target, offset or not, has none)."""
    return flicker([c - t for c, t in zip(captures, targets)])


def noise_free_device(truth: Path, cal: Calibration) -> Any:
    """The lab of ``truth`` through ``cal``'s device pipeline without the camera's noise: sensor noise off and
    every shot drawing the first shot's Cycles samples, so two captures differ only where their frames do."""
    from procam.addon.lab.cycles_device import LabDevice  # bpy
    from procam.addon.lab.truth import LabTruth

    quiet = LabDevice(LabTruth.load(truth).without("noise"), repeat_draws=True)
    return device_pipeline(f"lab:{truth}", cal, device=quiet)


def step(args: list[str], done: Path) -> None:
    """``procam ARGS`` unless ``done`` exists (``--work`` reuses what an earlier run made)."""
    if done.exists():
        return
    if procam([str(a) for a in args]) != 0:
        raise SystemExit(f"procam {args[0]} failed")


def lab_calibration(work: Path, scale: float, projector_size: str | None = None, camera_size: str | None = None,
                    samples: int = 8) -> tuple[Path, Path]:
    """The lab's capture set at ``scale`` (realistic effects, the curve; the demo rig, or its projector and camera
    at the sizes given), calibrated, with its inverse stored."""
    lab, cal, truth = work / "lab", work / "cal", work / "lab.truth.json"
    sizes = [*(["--projector-size", projector_size] if projector_size else []),
             *(["--camera-size", camera_size] if camera_size else [])]
    step(["lab", "--out", lab, "--surface", "curve", "--effects", "realistic", "--scale", scale, "--samples", samples,
          *sizes, "--truth", truth], lab)
    step(["calibrate", lab, "--out", cal], cal / "calibration.json")
    step(["precompute", cal, "--live"], cal / "inverse.npz")
    return cal, truth


def quality(cal_dir: Path, truth: Path, frames: int, effects: str = "none",
            diagnosis: Path | None = None, follow: bool = False) -> dict[str, Any]:
    """Real time against the ``transport`` schedule on a panning clip, captured through the lab (module doc); with
    ``effects`` (``--effects`` of ``procam show``, fitted in ``diagnosis``) both hold them, and where they hold a
    lens blur the real-time solve is captured once more without it (as before it was held)."""
    cal = calibrate_step.read(cal_dir)
    device = device_pipeline(f"lab:{truth}", cal)
    assert device is not None
    quiet = noise_free_device(truth, cal)
    cw, ch = cal.rig.camera.intrinsics.size
    picture = picture_of(round(1.25 * cw), round(1.25 * ch))
    ours: list[float] = []
    noise = float("nan")
    theirs: list[float] = []
    solve_ms: list[float] = []
    unheld: list[float] = []
    unheld_ms: list[float] = []
    caps: dict[str, list[np.ndarray]] = {"realtime": [], "transport": [], "target": [],
                                         "realtime_noise_free": [], "transport_noise_free": []}
    clean: dict[str, list[float]] = {"realtime": [], "transport": []}
    clean_noise = float("nan")
    blur = None
    try:
        with StageC(cal, StageCOptions(effects=effects, diagnosis=diagnosis)) as stage:
            solver = RealtimeSolver.for_stage(stage)
            blur = stage.compensator.input_blur
            plain = RealtimeSolver(stage, solver.inverses, hold_blur=False) if blur else None
            start = None
            for i in range(frames):
                image = panning(picture, i)
                fast = solver.solve(image)
                solve_ms.append(fast.solve_ms)
                if plain is not None:
                    other = plain.solve(image)
                    unheld_ms.append(other.solve_ms)
                full = stage.compensate(image, name=f"frame {i}", what="frame", start=start, verify=False)
                start = stage.start_from_frame(full.frame)
                area = full.area
                target = full.fitted
                for name, frame in (("realtime", fast.frames[0][..., :3].astype(np.float32) / 255.0),
                                    ("transport", full.frame)):
                    seen = device.project(frame)
                    if follow and name == "realtime":
                        solver.follow(seen, fast)  # as the live show's closed loop gives θ a camera frame
                    cap = area.crop(seen)
                    caps[name].append(cap)
                    (ours if name == "realtime" else theirs).append(psnr(np.clip(cap, 0, 1), target))
                    cap = area.crop(quiet.project(frame))
                    caps[f"{name}_noise_free"].append(cap)
                    clean[name].append(psnr(np.clip(cap, 0, 1), target))
                caps["target"].append(target)
                if plain is not None:
                    cap = area.crop(device.project(other.frames[0][..., :3].astype(np.float32) / 255.0))
                    unheld.append(psnr(np.clip(cap, 0, 1), target))
                if i == frames - 1:  # the camera's own change: the last frame captured once more
                    again = area.crop(device.project(fast.frames[0][..., :3].astype(np.float32) / 255.0))
                    noise = float(np.mean(np.abs(again - caps["realtime"][-1])))
                    again = area.crop(quiet.project(fast.frames[0][..., :3].astype(np.float32) / 255.0))
                    clean_noise = float(np.mean(np.abs(again - caps["realtime_noise_free"][-1])))
                print(f"  frame {i}: realtime {ours[-1]:.2f} dB ({fast.solve_ms:.1f} ms), transport {theirs[-1]:.2f} "
                      f"dB" + (f", realtime without the blur held {unheld[-1]:.2f} dB ({other.solve_ms:.1f} ms)"
                               if plain is not None else ""), flush=True)
    finally:
        device.close()
        quiet.close()

    ms = np.asarray(solve_ms[2:] or solve_ms)  # the first frames build the area's views and compile the kernels
    held = {} if not unheld else {
        "psnr_realtime_blur_not_held": round(float(np.mean(unheld)), 2),
        "solve_ms_median_blur_not_held": round(float(np.median(unheld_ms[2:] or unheld_ms)), 1)}
    return {"camera": f"{cw}x{ch}", "projector": "x".join(map(str, cal.rig.projector.intrinsics.size)),
            "effects": effects, "input_blur": blur, "follow": follow, **held,
            "frames": frames, "psnr_realtime": round(float(np.mean(ours)), 2),
            "psnr_transport": round(float(np.mean(theirs)), 2),
            "flicker_realtime": round(flicker(caps["realtime"]), 4),
            "flicker_transport": round(flicker(caps["transport"]), 4),
            "flicker_targets": round(flicker(caps["target"]), 4), "flicker_noise_floor": round(noise, 4),
            "psnr_realtime_noise_free": round(float(np.mean(clean["realtime"])), 2),
            "psnr_transport_noise_free": round(float(np.mean(clean["transport"])), 2),
            "flicker_realtime_noise_free": round(flicker(caps["realtime_noise_free"]), 4),
            "flicker_transport_noise_free": round(flicker(caps["transport_noise_free"]), 4),
            "flicker_noise_floor_noise_free": round(clean_noise, 4),
            "error_flicker_realtime": round(error_flicker(caps["realtime_noise_free"], caps["target"]), 4),
            "error_flicker_transport": round(error_flicker(caps["transport_noise_free"], caps["target"]), 4),
            "solve_ms_median": round(float(np.median(ms)), 1), "solve_ms_p95": round(float(np.percentile(ms, 95)), 1),
            "fps_solve": round(1000.0 / float(np.median(ms)), 1)}


def _round(value: float | None) -> float | None:
    return None if value is None else round(value, 1)


def write_clip(path: Path, size: tuple[int, int], seconds: float, fps: float = 30.0) -> Path:
    """A ``seconds`` MJPEG clip of the panning picture (8-bit sRGB, as a video file is)."""
    picture = picture_of(*size)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, size)
    try:
        for i in range(round(seconds * fps)):
            srgb = np.where(picture <= 0.0031308, 12.92 * picture, 1.055 * np.power(picture, 1 / 2.4) - 0.055)
            writer.write(cv2.cvtColor(np.clip(np.rint(panning(srgb, i) * 255), 0, 255).astype(np.uint8),
                                      cv2.COLOR_RGB2BGR))
    finally:
        writer.release()
    return path


def loop(cal_dir: Path, work: Path, seconds: float, fps: float = 30.0) -> dict[str, Any]:
    """``procam live-show`` of ``cal_dir`` under Xvfb, a ``seconds`` clip as the source (module doc)."""
    if shutil.which("Xvfb") is None:
        raise SystemExit("the loop part needs Xvfb (Debian: apt-get install xvfb)")
    cal = calibrate_step.read(cal_dir)
    fw, fh = cal.rig.projector.intrinsics.size
    cw, ch = cal.rig.camera.intrinsics.size
    clip = write_clip(work / f"clip-{round(seconds)}s-{round(fps)}fps.avi", (cw, ch), seconds, fps)
    n = next(i for i in range(90, 200) if not Path(f"/tmp/.X11-unix/X{i}").exists())
    server = subprocess.Popen(["Xvfb", f":{n}", "-screen", "0", f"{fw + 40}x{fh + 40}x24", "-nolisten", "tcp"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 10
        while not Path(f"/tmp/.X11-unix/X{n}").exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        os.environ.update(DISPLAY=f":{n}", SDL_VIDEODRIVER="x11")
        figures, report = clip_latency(cal_dir, clip, "live:position=0:0")
    finally:
        import pygame  # here: the speed part runs where only Mitsuba is installed (a GPU machine)

        pygame.quit()  # SDL lets go of the display before it goes away
        server.terminate()
        server.wait()
    sm, sp = report.solve_ms
    return {"projector": f"{fw}x{fh}", "seconds": seconds, "clip_fps": fps, "frames_in": figures.frames_in,
            "shown": figures.shown, "dropped": figures.dropped, "fps_loop": round(figures.fps, 1),
            "latency_ms_median": _round(figures.median_ms), "latency_ms_p95": _round(figures.p95_ms),
            "solve_ms_median": _round(sm)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--parts", default="quality,loop")
    ap.add_argument("--sizes", default="800x600")
    ap.add_argument("--variant", default=None, help="Mitsuba variant of the speed part (default: the CPU's)")
    ap.add_argument("--scale", type=float, default=1.0, help="lab resolution of the quality and loop parts")
    ap.add_argument("--projector-size", default=None, metavar="WxH",
                    help="the lab's projector (quality and loop parts; e.g. 1920x1080, with --camera-size 1536x864)")
    ap.add_argument("--camera-size", default=None, metavar="WxH", help="the lab's camera (quality and loop parts)")
    ap.add_argument("--samples", type=int, default=8, help="the lab's Cycles samples (quality and loop parts)")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--effects", default="none",
                    help="the quality part's --effects, as procam show takes it (e.g. defocus; needs --diagnosis)")
    ap.add_argument("--diagnosis", type=Path, default=None,
                    help="the procam diagnose folder of the lab's calibration, for --effects")
    ap.add_argument("--follow", action="store_true",
                    help="the quality part's real-time solve closed loop: θ follows the lab camera's every capture")
    ap.add_argument("--seconds", type=float, default=20.0, help="clip length of the loop part")
    ap.add_argument("--fps", type=float, default=30.0, help="the clip's frame rate (above 30: the loop's own ceiling)")
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None, help="write every figure here too")
    args = ap.parse_args()
    parts = set(args.parts.split(","))
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-live-"))
    work.mkdir(parents=True, exist_ok=True)
    figures: dict[str, Any] = {}
    fps_solve = fps_loop = None
    if parts & {"quality", "loop"}:
        cal_dir, truth = lab_calibration(work, args.scale, args.projector_size, args.camera_size, args.samples)
    if "quality" in parts:
        row = figures["quality"] = quality(cal_dir, truth, args.frames, args.effects, args.diagnosis, args.follow)
        print(f"quality {row['projector']} (camera {row['camera']}), {row['frames']} frames of a pan, captured in the "
              f"lab: real time{' (θ following every capture)' if row['follow'] else ''} {row['psnr_realtime']} dB, "
              f"transport schedule {row['psnr_transport']} dB; flicker "
              f"{row['flicker_realtime']} (transport {row['flicker_transport']}, targets {row['flicker_targets']}, the "
              f"camera's noise alone {row['flicker_noise_floor']}); without the camera's noise: "
              f"{row['psnr_realtime_noise_free']} dB and {row['psnr_transport_noise_free']} dB, flicker "
              f"{row['flicker_realtime_noise_free']} (transport {row['flicker_transport_noise_free']}, targets "
              f"{row['flicker_targets']}, the same frame twice {row['flicker_noise_floor_noise_free']}), the error's "
              f"flicker {row['error_flicker_realtime']} (transport {row['error_flicker_transport']}); "
              f"solve {row['solve_ms_median']} ms median, {row['solve_ms_p95']} ms p95"
              + (f"; effects {row['effects']} (lens blur σ {row['input_blur']:.2f} texels held; without it "
                 f"{row['psnr_realtime_blur_not_held']} dB, {row['solve_ms_median_blur_not_held']} ms)"
                 if "psnr_realtime_blur_not_held" in row else ""), flush=True)
        if row["projector"] == "800x600":
            fps_solve = row["fps_solve"]
    if "loop" in parts:
        row = figures["loop"] = loop(cal_dir, work, args.seconds, args.fps)
        print(f"loop {row['projector']} under Xvfb, {row['seconds']:.0f} s clip at {row['clip_fps']:.0f} fps: "
              f"{row['fps_loop']} fps, "
              f"{row['shown']} shown of {row['frames_in']}, {row['dropped']} dropped; latency source → flip "
              f"{row['latency_ms_median']} ms median, {row['latency_ms_p95']} ms p95; solve {row['solve_ms_median']} "
              "ms median", flush=True)
        if row["projector"] == "800x600":
            fps_loop = row["fps_loop"]
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
            if row["projector"] == "800x600" and fps_solve is None:
                fps_solve = row["fps_solve"]
    if args.json:
        args.json.write_text(json.dumps(figures, indent=1) + "\n")
    print(f"800x600: {fps_solve if fps_solve is not None else 'n/a'} fps solve, "
          f"{fps_loop if fps_loop is not None else 'n/a'} fps loop")


if __name__ == "__main__":
    main()
