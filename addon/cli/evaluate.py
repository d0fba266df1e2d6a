"""``procam evaluate``: project compensated inputs through a device and measure PSNR/SSIM in the display area.

Reads the folder ``procam compensate`` wrote (``--inputs``), projects each
target's input and, as a baseline, the uncompensated target through the device,
and writes a new folder (``addon/steps/evaluate.py``; replaced only with ``--force``):

``metrics.json``                  ``{"targets": [{"name", "psnr", "ssim", "uncompensated": {…}, …}],
                                  "mean": {"psnr", "ssim"}, …}``
``NAME_comparison.png``           target | uncompensated | compensated [| classical] | error map (area crops)
``NAME_capture.png``              the camera's view of the compensated input
``NAME_uncompensated_capture.png`` the camera's view of the uncompensated target

Targets are matched to the compensation by file stem, as ``procam compensate``
named them (a show folder: by the stems of the images its frames were made
from). Two or more targets, in order, also give the sequence's flicker
(``"flicker"``: captured, targets, excess = captured − targets). If a target fails during the projections, the finished ones are
kept and ``metrics.json`` records the failure (``"complete": false``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..stages.display_area import TARGET_ENCODINGS
from ..steps.evaluate import EvaluateOptions, run as evaluate, summary
from .app import command
from .terminal import print_summary, run_step


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("calibration", type=Path, help="calibration folder (from procam calibrate)")
    p.add_argument("--inputs", type=Path, required=True,
                   help="compensation folder (from procam compensate) or show folder (from procam show)")
    p.add_argument("--targets", type=Path, nargs="+", required=True, metavar="TARGET",
                   help="the target images given to procam compensate or show (for a show made from a video: that "
                        "video, each finished frame measured); two or more, in order, also give the sequence's "
                        "flicker")
    p.add_argument("--device", required=True, help="lab:TRUTH_FILE (virtual lab), folder:CAPTURE_DIR or live:camera=SOURCE,display=N")
    p.add_argument("--out", type=Path, required=True, help="folder to create for the metrics and images")
    p.add_argument("--classical", action="store_true",
                   help="also measure the classical per-pixel colour-mixing baseline (captures 3 flat primaries)")
    p.add_argument("--target-encoding", choices=TARGET_ENCODINGS, default="auto",
                   help="auto: 8-bit files are sRGB and are linearised, 16-bit/float are linear")
    p.add_argument("--no-repeat", dest="repeat", action="store_false",
                   help="capture each compensated input once (default: twice, for the camera's noise and the noise "
                        "ceiling, the range ceiling as a capture through that noise can score it)")
    p.add_argument("--force", action="store_true", help="replace an existing evaluation folder at --out")


@command("evaluate", "Project compensated inputs through a device and measure PSNR/SSIM against the targets.",
         _configure)
def run(args: argparse.Namespace) -> int:
    options = EvaluateOptions(args.calibration, args.inputs, tuple(args.targets), args.device, args.out,
                              classical=args.classical, target_encoding=args.target_encoding, force=args.force,
                              repeat=args.repeat)
    run_step("evaluate", evaluate, options, total=len(options.targets), unit="targets")
    print_summary("evaluation", args.out, summary(args.out))
    return 0

