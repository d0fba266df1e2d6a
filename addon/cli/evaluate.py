"""``procam evaluate``: project compensated inputs through a device and measure PSNR/SSIM in the display area.

Reads the folder ``procam compensate`` wrote (``--inputs``), projects each
target's input and, as a baseline, the uncompensated target through the device,
and writes a new folder (``addon/steps/evaluate.py``; replaced only with ``--force``):

``metrics.json``                  ``{"targets": [{"name", "psnr", "ssim", "uncompensated": {…}, …}],
                                  "mean": {"psnr", "ssim"}, …}``
``NAME_comparison.png``           target | uncompensated | compensated [| classical] | error map (area crops)
``NAME_capture.png``              the camera's view of the compensated input
``NAME_uncompensated_capture.png`` the camera's view of the uncompensated target

Targets are image files, a folder or a numbered pattern (as ``procam show`` takes them), or a video for a show
made from one; they are matched to the compensation by file stem, as ``procam compensate``
named them (a show folder: by the stems of the images its frames were made
from). Two or more targets, in order, also give the sequence's flicker
(``"flicker"``: captured, targets, excess = captured − targets). If a target
fails during the projections, the finished ones are kept and ``metrics.json``
records the failure (``"complete": false``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..options import add_arguments, from_arguments
from ..steps.evaluate import EvaluateOptions, run as evaluate, summary, target_files
from .app import command
from .terminal import print_summary, run_step


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("calibration", type=Path, help="calibration folder (from procam calibrate)")
    p.add_argument("--inputs", type=Path, required=True,
                   help="compensation folder (from procam compensate) or show folder (from procam show)")
    p.add_argument("--targets", type=Path, nargs="+", required=True, metavar="TARGET",
                   help="the targets given to procam compensate or show, in any form show takes: image files, one "
                        "folder of images, one numbered pattern like frames/shot_####.png, or (for a show made from "
                        "a video) that video, each finished frame measured; two or more, in order, also give the "
                        "sequence's flicker")
    p.add_argument("--out", type=Path, required=True, help="folder to create for the metrics and images")
    add_arguments(p, EvaluateOptions)
    p.add_argument("--force", action="store_true",
                   help="replace an existing evaluation folder at --out (one a failed or cancelled run left, marked "
                        "incomplete, is replaced without it)")


@command("evaluate", "Project compensated inputs through a device and measure PSNR/SSIM against the targets.",
         _configure)
def run(args: argparse.Namespace) -> int:
    options = from_arguments(EvaluateOptions, args, calibration=args.calibration, inputs=args.inputs,
                             targets=tuple(args.targets), out=args.out, force=args.force)
    run_step("evaluate", evaluate, options, total=len(target_files(options.targets)), unit="targets")
    print_summary("evaluation", args.out, summary(args.out))
    return 0

