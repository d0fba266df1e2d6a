"""``procam capture`` and ``procam live-check``: the calibration sequence captured live, and a look at the rig first.

The live device is ``live:camera=SOURCE,display=N`` (``addon/live/device.py``
lists its options). ``live-check`` opens it, measures latency, noise and
whether exposure is locked, and says what it found; ``capture`` shows and
captures the whole calibration sequence and writes a capture set, resuming an
interrupted session.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import LiveError
from ..live.device import LiveDevice
from ..rig.model import Projector, projector_intrinsics_from_throw
from ..live.window import list_displays
from ..steps.live import LiveCaptureOptions, run_live_capture
from .app import command
from .capture import (add_camera_options, add_pattern_options, add_projector_options, depth_native_size,
                      projector_from_args)
from .terminal import run_step

DEVICE_HELP = ("live:camera=SOURCE,display=N — SOURCE a camera index, a device path or a URL (http://…mjpg, "
               "rtsp://…); display=N covers display N (at the projector's native size), position=X:Y puts the "
               "window at desktop coordinates instead; options: average=N or noise=σ (frames per capture), "
               "encoding=srgb|linear, latency=auto|SECONDS, size=WxH")


def _configure_check(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", help=DEVICE_HELP)
    p.add_argument("--projector-width", type=int, help="native projector width (px): the window's width")
    p.add_argument("--projector-height", type=int, help="native projector height (px)")
    p.add_argument("--list-displays", action="store_true", help="list the displays and their sizes, then stop")
    p.add_argument("--no-exposure-check", action="store_true", help="skip the exposure-lock check")


@command("live-check", "Open a live projector window and camera: latency, noise, exposure lock.", _configure_check)
def live_check(args: argparse.Namespace) -> int:
    if args.list_displays:
        for i, w, h, hz in list_displays():
            print(f"display {i}: {w}×{h}" + (f" at {hz:.0f} Hz" if hz else ""))
        return 0
    if not (args.device and args.projector_width and args.projector_height):
        raise LiveError("live-check needs --device, --projector-width and --projector-height (or --list-displays)")
    projector = Projector(projector_intrinsics_from_throw(args.projector_width, args.projector_height, 1.0))
    device = run_step("live-check", lambda o, progress=None, cancel=None: LiveDevice(
        o, projector, progress=progress, check_exposure=not args.no_exposure_check), args.device)
    try:
        print("\n".join(device.report.lines()))
    finally:
        device.close()
    return 0


def _configure_capture(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", required=True, help=DEVICE_HELP)
    add_projector_options(p)
    add_pattern_options(p)
    add_camera_options(p)
    p.add_argument("--out", type=Path, required=True, help="new capture-set folder (the session waits beside it, "
                                                           "in OUT.session, until every frame is captured)")
    p.add_argument("--restart", action="store_true",
                   help="discard an interrupted session of other settings instead of refusing")
    p.add_argument("--force", action="store_true", help="replace an existing capture set at --out")


@command("capture", "Show and capture the calibration sequence live (resumes an interrupted session).",
         _configure_capture)
def capture(args: argparse.Namespace) -> int:
    options = LiveCaptureOptions(
        args.device, projector_from_args(args), args.out, checker=args.checker, area=args.area,
        graycode=not args.no_graycode, validation=not args.no_validation, seed=args.seed,
        camera_fov=args.camera_fov, depth_path=args.depth, depth_units=args.depth_units,
        depth_native_size=depth_native_size(args), rig=args.rig, check_exposure=not args.no_exposure_check,
        force=args.force, restart=args.restart)
    cs = run_step("capture", run_live_capture, options)
    w, h = cs.camera.intrinsics.size
    print(f"wrote capture set {cs.path}: {len(cs)} images, camera {w}×{h}")
    return 0
