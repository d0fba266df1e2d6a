"""``procam show``: prepare a show — compensate every frame of a folder or numbered image sequence.

A separate command rather than a mode of ``procam compensate`` because the
output contract differs: ``compensate`` writes one folder atomically (all
targets or nothing, four images per target for inspection); ``show`` writes a
folder that grows frame by frame, resumes after a crash, and holds only what a
media server plays (``frame_0001.png`` … in the native projector resolution,
16-bit) plus its manifest ``show.json``. The engine is
:mod:`procam.addon.stages.sequence`; the stage-C options are the same as
``compensate``'s.

Exit codes: 0 when every frame is finished (this run or an earlier one), 2 when
a frame failed (the others are kept; fix it and rerun to resume) or the request
is refused, 130 when cancelled.
"""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

from ..cli import command
from .compensate import add_effect_options, add_schedule_options, check_schedule, open_device, schedule_arguments

EPILOG = """\
TARGETS is a folder of images, a numbered pattern (frames/shot_####.png or frames/shot_%04d.png), or a list of
image files. Output frame N is OUT/frame_NNNN.png, numbered like the input frames.

Rerunning the same command resumes: frames whose file matches the manifest (size and SHA-256) are skipped.
A rerun with other settings, another calibration, or after a target image changed is refused unless --force,
which redoes every frame. A frame that fails is recorded in show.json and the next ones go on; rerun to retry it.

exit codes: 0 every frame finished, 2 a frame failed or the request was refused (the message says what to do),
130 cancelled (Ctrl-C; finished frames are kept), 1 internal error."""


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("calibration", type=Path, help="calibration folder (from procam calibrate)")
    p.add_argument("targets", nargs="+", metavar="TARGETS",
                   help="a folder of target images, a numbered pattern like frames/shot_####.png, or image files")
    p.add_argument("--out", type=Path, required=True,
                   help="show folder: created, or resumed when it holds a show made with the same settings")
    add_schedule_options(p)
    add_effect_options(p)
    p.add_argument("--force", action="store_true",
                   help="redo every frame, even finished ones (needed when the settings or targets changed)")
    p.add_argument("--fail-fast", action="store_true",
                   help="stop at the first frame that fails instead of going on with the next ones")
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = EPILOG


@command("show", "Compensate every frame of an image sequence into a numbered 16-bit projector frame sequence "
                 "(resumable).", _configure)
def run(args: argparse.Namespace) -> int:
    from ..cli import cancel_on_interrupt
    from ..outputs import ProgressBar, progress
    from ..stages.display_area import parse_area
    from ..stages.sequence import SequenceError, ShowOptions, list_frames, prepare_show

    from ..gap.compensation import adapter_from_options
    from ..stages.calibrate import Calibration

    check_schedule(args)
    adapter = adapter_from_options(args.effects, args.diagnosis, Calibration.load(args.calibration).rig.projector)
    options = ShowOptions(**schedule_arguments(args), spp=args.spp, bounces=args.bounces, seed=args.seed,
                          area=parse_area(args.area) if args.area else None, target_encoding=args.target_encoding,
                          use_bias=not args.no_bias)
    options.check()
    frames = list_frames(args.targets)
    progress(f"show: {len(frames)} frame(s) {frames[0].number}…{frames[-1].number} from {args.targets[0]}"
             + (" …" if len(args.targets) > 1 else "") + f" → {args.out}")
    device_spec = None
    if args.device and not args.no_bias:
        kind, _, where = args.device.partition(":")
        device_spec = f"{kind}:{Path(where).absolute()}" if where else args.device
    with contextlib.ExitStack() as stack:
        cancel = stack.enter_context(cancel_on_interrupt())
        device = open_device(args.device) if device_spec else None
        if device is not None:
            stack.callback(device.close)
        bar: list[ProgressBar] = []

        def tick(done: float, total: int, message: str, finished: bool) -> None:
            if not bar:  # made at the first frame: its clock then measures compensation, not loading
                bar.append(stack.enter_context(ProgressBar(total, "show", unit="frames")))
            bar[0].update(done, message, force=finished)

        result = prepare_show(args.calibration, frames, args.out, options, device=device, device_spec=device_spec,
                              force=args.force, fail_fast=args.fail_fast, on_progress=tick, log=progress,
                              cancel=cancel, effects=adapter)
        if bar:
            bar[0].close()
    doc = result.manifest
    done_frames = [e for e in doc["frames"].values() if e.get("status") == "done"]
    psnrs = [e["psnr_model"] for e in done_frames if str(e["number"]) in {str(n) for n in result.done}]
    mean = f", model PSNR {sum(psnrs) / len(psnrs):.2f} dB mean in the display area" if psnrs else ""
    print(f"show: {args.out} — {len(result.done)} frame(s) compensated, {len(result.skipped)} already finished, "
          f"{len(result.failed)} failed, {result.seconds:.1f} s{mean}")
    if result.failed:
        listed = "; ".join(f"frame {n}: {msg}" for n, msg in sorted(result.failed.items())[:5])
        more = f" (and {len(result.failed) - 5} more)" if len(result.failed) > 5 else ""
        raise SequenceError(f"{len(result.failed)} frame(s) failed — {listed}{more}. The other frames are kept; "
                            f"fix the targets and rerun the same command to finish the show")
    return 0
