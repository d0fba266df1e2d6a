"""``procam capture`` and ``procam live-check``: the calibration sequence captured live, and a look at the rig first.

The live device is ``live:camera=SOURCE,display=N`` (``addon/live/device.py``
lists its options). ``live-check`` opens it, measures latency, noise and
whether exposure is locked, and says what it found; ``capture`` shows and
captures the whole calibration sequence and writes a capture set, resuming an
interrupted session; ``--projectors N`` with one display each (``display=1+2``)
captures every projector's sequence, the others black, into one capture set. ``live-show`` compensates a video
file, camera or stream frame by frame as it arrives and shows it in the projector window(s)
(``addon/steps/live_show.py``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..live.shoot import open_camera_device
from ..live.window import list_displays
from ..options import add_arguments, declared, from_arguments
from ..steps.capture import PatternsOptions, PhotoSettings
from ..steps.live import LiveCaptureOptions, LiveCheckOptions, LiveRigSheet, run_live_capture
from ..steps.live_show import LiveShowOptions, run_live_show
from .app import command
from .capture import add_camera_options, add_projector_options, depth_native_size, projector_from_args
from .terminal import run_step

def _configure_check(p: argparse.ArgumentParser) -> None:
    add_arguments(p, LiveCheckOptions)
    add_arguments(p, LiveRigSheet)


@command("live-check", "Open a live projector window and camera: latency, noise, exposure lock.", _configure_check)
def live_check(args: argparse.Namespace) -> int:
    options = from_arguments(LiveCheckOptions, args)
    if options.list_displays:
        for i, w, h, hz in list_displays():
            print(f"display {i}: {w}×{h}" + (f" at {hz:.0f} Hz" if hz else ""))
        return 0
    projector = options.projector()
    others = from_arguments(LiveRigSheet, args).others(projector)
    device = run_step("live-check", lambda o, progress=None, cancel=None: open_camera_device(
        o, projector, others=others, progress=progress, check_exposure=options.check_exposure), options.device)
    try:
        print("\n".join(device.report.lines()))
    finally:
        device.close()
    return 0


def _configure_capture(p: argparse.ArgumentParser) -> None:
    add_arguments(p, LiveCaptureOptions, exclude=[d.name for d in declared(PhotoSettings)] + ["restart"])
    add_projector_options(p)
    add_arguments(p, LiveRigSheet)
    # accepted as patterns takes it; the live session shows the procam layout
    add_arguments(p, PatternsOptions, only=("layout",))
    add_camera_options(p)
    p.add_argument("--out", type=Path, required=True, help="new capture-set folder (the session waits beside it, "
                                                           "in OUT.session, until every frame is captured)")
    add_arguments(p, LiveCaptureOptions, only=("restart",))
    p.add_argument("--force", action="store_true", help="replace an existing capture set at --out")


@command("capture", "Show and capture the calibration sequence live (resumes an interrupted session).",
         _configure_capture)
def capture(args: argparse.Namespace) -> int:
    projector = projector_from_args(args)
    options = from_arguments(LiveCaptureOptions, args, projector=projector, out=args.out,
                             depth_native_size=depth_native_size(args), force=args.force,
                             others=from_arguments(LiveRigSheet, args).others(projector))
    cs = run_step("capture", run_live_capture, options)
    w, h = cs.camera.intrinsics.size
    many = f" of {len(cs.projectors)} projectors" if cs.others else ""
    print(f"wrote capture set {cs.path}: {len(cs)} images{many}, camera {w}×{h}")
    return 0


SHOW_EPILOG = """\
The status line, every second: frames in (from the source), shown (compensated and flipped), dropped (arrived
while the solver was busy with an earlier one: the show never queues), the solve's milliseconds and the latency
from a frame's arrival to its flip (medians over the last second), and the loop's frames per second.

A source that stalls or ends shows its last frame for --hold seconds, then black; a video file that ended then
stops the show (exit 0); a stream that resumes goes on. Esc in the projector window stops the show (exit 0).

exit codes: 0 the show ran and stopped (the file ended, --duration, Esc), 2 a problem you can fix (a source or
window that cannot be opened; the message says what to do), 130 cancelled (Ctrl-C), 1 internal error."""


def _configure_show(p: argparse.ArgumentParser) -> None:
    p.add_argument("calibration", type=Path, help="calibration folder (from procam calibrate)")
    add_arguments(p, LiveShowOptions)
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = SHOW_EPILOG


@command("live-show", "Compensate a video file, camera or stream frame by frame and show it live in the projector "
                      "window(s).", _configure_show)
def live_show(args: argparse.Namespace) -> int:
    options = from_arguments(LiveShowOptions, args, calibration=args.calibration)
    report = run_step("live-show", run_live_show, options)
    print("\n".join(report.lines()))
    return 0
