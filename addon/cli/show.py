"""``procam show``: prepare a show — compensate every frame of a folder or numbered image sequence.

A separate command rather than a mode of ``procam compensate`` because the
output contract differs: ``compensate`` writes one folder atomically (all
targets or nothing, four images per target for inspection); ``show`` writes a
folder that grows frame by frame, resumes after a crash, and holds only what a
media server plays (``frame_0001.png`` … in the native projector resolution,
16-bit) plus its manifest ``show.json``. The engine is
:mod:`procam.addon.steps.show`; the stage-C options are the same as
``compensate``'s.

Exit codes: 0 when every frame is finished (this run or an earlier one), 2 when
a frame failed (the others are kept; fix it and rerun to resume) or the request
is refused, 130 when cancelled.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..options import add_arguments, from_arguments
from ..steps.show import SequenceError, ShowOptions, list_frames, run as prepare_show, summary
from .app import command
from .compensate import add_effect_options, add_schedule_options, stage_c_options
from .terminal import print_summary, run_step

EPILOG = """\
TARGETS is a folder of images, a numbered pattern (frames/shot_####.png or frames/shot_%04d.png), a list of
image files, or one video file (.mp4, .mov, .avi, .mkv, …; frames 1…N, 8-bit sRGB like 8-bit images). Output
frame N is OUT/frame_NNNN.png, numbered like the input frames; with a calibration of several projectors, one
sequence per projector: OUT/projector_1/frame_NNNN.png, OUT/projector_2/frame_NNNN.png, … (all solved together;
--workers/--cluster not yet).

Each frame's stage C starts from the previous frame's answer (warm start), within chunks of --chunk frames by
frame number (1–24, 25–48, …); --cold-start starts every frame from the target alone. --workers N computes the
chunks side by side on a local Dask cluster of N processes, --cluster tcp://HOST:8786 on a running Dask cluster
(its workers must see the calibration and targets at the same paths); the frames are byte-identical to a run in
this process with the same --threads (Dr.Jit's thread count orders the samples' sums), and this process alone
writes OUT. The closed loop (--device) runs in this process only.

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
    add_arguments(p, ShowOptions, exclude=("workers", "cluster"))
    add_arguments(p.add_mutually_exclusive_group(), ShowOptions, only=("workers", "cluster"))
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = EPILOG


@command("show", "Compensate every frame of an image sequence into a numbered 16-bit projector frame sequence "
                 "(resumable).", _configure)
def run(args: argparse.Namespace) -> int:
    options = from_arguments(ShowOptions, args, calibration=args.calibration, targets=tuple(args.targets),
                             out=args.out, stage_c=stage_c_options(args), force=args.force)
    options.check(options.stage_c.mode)  # a refused cluster request fails before anything is read
    frames = list_frames(options.targets)  # a bad sequence fails before the bar starts
    result = run_step("show", prepare_show, options, total=len(frames), unit="frames")
    print_summary("show", result.folder, summary(result.folder))
    if result.failed:
        listed = "; ".join(f"frame {n}: {msg}" for n, msg in sorted(result.failed.items())[:5])
        more = f" (and {len(result.failed) - 5} more)" if len(result.failed) > 5 else ""
        raise SequenceError(f"{len(result.failed)} frame(s) failed — {listed}{more}. The other frames are kept; "
                            f"fix the targets and rerun the same command to finish the show")
    return 0
