#!/usr/bin/env python3
"""The live loop on the loopback rig: measured latency against injected, seconds per capture, and the whole loop.

Usage: ``.venv/bin/python scripts/bench_live.py [--delays 0,0.15,0.4] [--size 640x480] [--average 4] [--loop]``

Starts its own virtual X server (Debian's Xvfb) unless ``--display`` names
one, shows the projector window there, and films it with the loopback MJPEG
camera (``addon/live/loopback.py``) read over HTTP on 127.0.0.1 by OpenCV.
For each injected delay it prints the three latency measurements the live
device took at start, their median's error against the injection in camera
frames, and how many of a run of alternating flat frames came back holding the
previous frame. Then the seconds per capture at ``--size`` with ``--average``
frames. ``--loop`` also runs capture → calibrate → closed-loop compensation →
evaluation at 256×192 and prints the PSNR.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np


from procam.addon.capture.targets import natural_target
from procam.addon.cli.app import main as procam
from procam.addon.imageio import write_image
from procam.addon.live.device import LiveDevice
from procam.addon.live.loopback import LoopbackCamera, painted_wall

ORIGIN = (40, 30)


def start_xvfb(screen: tuple[int, int]) -> subprocess.Popen:
    if shutil.which("Xvfb") is None:
        raise SystemExit("Xvfb is not installed (apt-get install xvfb), and no --display was given")
    n = next(n for n in range(90, 200) if not Path(f"/tmp/.X11-unix/X{n}").exists())
    proc = subprocess.Popen(["Xvfb", f":{n}", "-screen", "0", f"{screen[0]}x{screen[1]}x24", "-nolisten", "tcp"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    for _ in range(200):
        if Path(f"/tmp/.X11-unix/X{n}").exists():
            break
        time.sleep(0.05)
    os.environ["DISPLAY"], os.environ["SDL_VIDEODRIVER"] = f":{n}", "x11"
    return proc


def device_string(url: str, average: int) -> str:
    return f"live:camera={url},position={ORIGIN[0]}:{ORIGIN[1]},encoding=linear,average={average}"


def latency_run(delay: float, size: tuple[int, int]) -> dict[str, float]:
    loop, _, truth = painted_wall(size, ORIGIN, delay_s=delay)
    loop.noise = 0.0
    with LoopbackCamera(loop) as cam, LiveDevice(device_string(cam.url, 1), truth) as device:
        report = device.report
        levels = [0.1, 0.9] * 6
        seen = [float(device.project(np.full((size[1], size[0], 3), v, np.float32)).mean()) for v in levels]
    lo, hi = np.mean(seen[0::2]), np.mean(seen[1::2])
    stale = sum(abs(s - (hi if v > 0.5 else lo)) > 0.25 * (hi - lo) for v, s in zip(levels, seen))
    median = float(np.median(report.latencies_s))
    return {"delay_ms": delay * 1000, "measured_ms": [round(v * 1000, 1) for v in report.latencies_s],
            "median_error_frames": (median - delay) / report.camera_frame_s,
            "camera_frame_ms": report.camera_frame_s * 1000,
            "stale_captures": int(stale), "captures": len(levels)}


def capture_speed(size: tuple[int, int], average: int, count: int = 20) -> dict[str, float]:
    loop, _, truth = painted_wall(size, ORIGIN, delay_s=0.15)
    with LoopbackCamera(loop) as cam, LiveDevice(device_string(cam.url, average), truth) as device:
        t0 = time.perf_counter()
        rng = np.random.default_rng(0)
        for _ in range(count):
            device.project(rng.random((size[1], size[0], 3)).astype(np.float32))
        per = (time.perf_counter() - t0) / count
        return {"size": f"{size[0]}x{size[1]}", "average": average, "latency_ms": device.latency_s * 1000,
                "seconds_per_capture": per}


def whole_loop(folder: Path) -> dict[str, float]:
    size = (256, 192)
    loop, depth, truth = painted_wall(size, ORIGIN, delay_s=0.15)
    np.save(folder / "depth.npy", depth)
    target = write_image(folder / "city.png", natural_target("city", (160, 160)))
    seconds = {}
    with LoopbackCamera(loop) as cam:
        dev = device_string(cam.url, 4)
        steps = {
            "capture": ["capture", "--device", dev, "--projector-width", "256", "--projector-height", "192",
                        "--input-width", str(truth.input_size[0]), "--input-height", str(truth.input_size[1]),
                        "--throw-ratio", "1.25", "--shift-y", "0.15", "--camera-fov", "58",
                        "--depth", str(folder / "depth.npy"), "--out", str(folder / "set")],
            "calibrate": ["calibrate", str(folder / "set"), "--out", str(folder / "cal")],
            "compensate": ["compensate", str(folder / "cal"), str(target), "--device", dev, "--iterations", "40",
                           "--out", str(folder / "comp")],
            "evaluate": ["evaluate", str(folder / "cal"), "--inputs", str(folder / "comp"), "--targets", str(target),
                         "--device", dev, "--out", str(folder / "eval")]}
        for name, args in steps.items():
            t0 = time.perf_counter()
            if procam(args) != 0:
                raise SystemExit(f"{name} failed")
            seconds[name] = time.perf_counter() - t0
    cal = json.loads((folder / "cal" / "calibration.json").read_text())
    pose_error = np.linalg.norm(np.asarray(cal["camera_from_projector"])[:3, 3] - truth.camera_from_projector[:3, 3])
    metrics = json.loads((folder / "eval" / "metrics.json").read_text())["targets"][0]
    return {**{f"{k}_s": v for k, v in seconds.items()}, "pose_error_mm": pose_error * 1000,
            "psnr_uncompensated": metrics["uncompensated"]["psnr"], "psnr_compensated": metrics["psnr"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--delays", default="0,0.15,0.4", help="injected camera delays, seconds")
    ap.add_argument("--size", default="640x480", help="camera and projector size for the speed run")
    ap.add_argument("--average", type=int, default=4, help="frames averaged per capture in the speed run")
    ap.add_argument("--loop", action="store_true", help="also run capture → calibrate → compensate → evaluate")
    ap.add_argument("--display", help="use this X display instead of starting Xvfb")
    args = ap.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    xvfb = None
    if args.display:
        os.environ["DISPLAY"] = args.display
    else:
        xvfb = start_xvfb((max(1024, size[0] + 100), max(768, size[1] + 100)))
    try:
        print("| Injected | Measured (3 at start) | Median − injected | Camera frame | Stale captures |")
        print("|---|---|---|---|---|")
        for delay in (float(v) for v in args.delays.split(",")):
            r = latency_run(delay, (256, 192))
            print(f"| {r['delay_ms']:.0f} ms | {', '.join(f'{v:.0f}' for v in r['measured_ms'])} ms | "
                  f"{r['median_error_frames']:.2f} frames | {r['camera_frame_ms']:.1f} ms | "
                  f"{r['stale_captures']} of {r['captures']} |", flush=True)
        s = capture_speed(size, args.average)
        print(f"\ncapture at {s['size']}, {s['average']} frames averaged, 150 ms injected latency: "
              f"{s['seconds_per_capture']:.3f} s per capture (latency waited: {s['latency_ms']:.0f} ms)", flush=True)
        if args.loop:
            with tempfile.TemporaryDirectory() as tmp:
                r = whole_loop(Path(tmp))
            print(f"\nwhole loop at 256×192: capture {r['capture_s']:.1f} s, calibrate {r['calibrate_s']:.1f} s, "
                  f"compensate {r['compensate_s']:.1f} s, evaluate {r['evaluate_s']:.1f} s; projector pose "
                  f"{r['pose_error_mm']:.1f} mm off; "
                  f"PSNR {r['psnr_uncompensated']:.2f} → {r['psnr_compensated']:.2f} dB")
    finally:
        import pygame
        pygame.display.quit()  # before its X server goes away
        if xvfb is not None:
            xvfb.terminate()


if __name__ == "__main__":
    main()
