"""A shooting command made of the lab: renders a frame on a lab truth into a photograph file.

    python -m procam.addon.lab.shoot --truth T.json --frame FRAME.png --out PHOTO [--shot N] [--samples S]
    python -m procam.addon.lab.shoot --truth T.json --grab X:Y --out PHOTO …

It stands in for a camera behind ProCam's command devices (``capture/command.py``, ``live/shoot.py``) so that they
can be run end to end without hardware: ``command:run='python -m procam.addon.lab.shoot --truth T --frame {frame}
--out {out} --shot {n}'`` shows and photographs, as a rig's own software would; with ``--grab X:Y`` it reads the
frame off the screen where the projector window shows it (the live device's ``shoot=``), so a photograph holds what
the window showed when the command ran, not the frame ProCam meant. Several projectors: one ``--frame`` (or
``--grab``) each, in rig order.

The photograph: ``.png`` 16-bit linear, ``.exr`` float linear, ``.jpg`` 8-bit sRGB (as a camera's JPEG). ``--shot N``
draws shot N's randomness (a lab device's shot N, ``cycles_device.py``), so a series of commands numbered by ``{n}``
has the noise of one device's series. Exit status 2 with the reason on standard error when it cannot.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from ..capture.format import linear_to_srgb
from ..errors import ProCamError
from ..imageio import read_image, write_image
from .truth import LabTruth


def grab(x: int, y: int, width: int, height: int) -> np.ndarray:
    """The screen area at desktop ``(x, y)`` of ``width``×``height`` as frame levels in [0, 1] (mss)."""
    try:
        import mss
    except ImportError:
        raise ProCamError("--grab needs the mss package (pip install mss)") from None
    with mss.MSS() as screen:
        shot = np.asarray(screen.grab({"left": x, "top": y, "width": width, "height": height}))
    return shot[..., 2::-1].astype(np.float32) / 255.0  # BGRA → RGB


def write_photo(path: Path, image: np.ndarray) -> None:
    """``image`` (linear) as a camera would save it at ``path``: JPEG 8-bit sRGB, or PNG/EXR as :func:`write_image`."""
    if path.suffix.lower() in (".jpg", ".jpeg"):
        levels = np.clip(np.rint(linear_to_srgb(np.clip(image, 0.0, 1.0)) * 255.0), 0, 255).astype(np.uint8)
        if not cv2.imwrite(str(path), levels[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95]):
            raise ProCamError(f"cannot write {path}")
    else:
        write_image(path, image)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m procam.addon.lab.shoot", description=__doc__.split("\n\n")[0])
    p.add_argument("--truth", type=Path, required=True, help="the lab truth (procam lab --truth)")
    p.add_argument("--frame", type=Path, action="append", default=[], help="a projector frame (one per projector)")
    p.add_argument("--grab", action="append", default=[], help="X:Y, the projector window's desktop position")
    p.add_argument("--out", type=Path, required=True, help="the photograph (.png, .exr or .jpg)")
    p.add_argument("--shot", type=int, default=0, help="the shot's number (its randomness)")
    p.add_argument("--samples", type=int, default=None, help="Cycles samples (default: the truth's)")
    args = p.parse_args(argv)
    try:
        truth = LabTruth.load(args.truth)
        projectors = truth.rig.projectors
        if bool(args.frame) == bool(args.grab) or len(args.frame or args.grab) != len(projectors):
            raise ProCamError(f"give one --frame or one --grab per projector ({len(projectors)})")
        if args.frame:
            frames = [read_image(f) for f in args.frame]
        else:
            frames = []
            for where, proj in zip(args.grab, projectors):
                x, y = (int(v) for v in where.split(":"))
                frames.append(grab(x, y, *proj.intrinsics.size))
        from .cycles_device import LabDevice  # bpy: only once the arguments are known to be good

        with LabDevice(truth, samples=args.samples, first_shot=args.shot) as device:
            photo = device.project_all(frames)
        write_photo(args.out, photo)
    except (ProCamError, ValueError, OSError) as exc:
        print(f"lab shoot: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
