"""The export step: compensated projector frames as a numbered 16-bit PNG sequence, and a calibration as a .blend.

``frames.json`` beside the frames names the compensation and calibration they
come from, the mode, and each frame's target and simulated PSNR. The frames
are the native projector resolution, in the compensation's target order,
copied bit for bit (a media server plays them as they are).
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..errors import ImageError
from ..options import option, validate
from ..outputs import check_replaceable, fresh_output_folder, write_manifest
from ..progress import Cancel, Progress, check, quiet
from . import calibrate as calibrate_step
from . import compensate as compensate_step
from . import layout

KIND = layout.FRAMES


@dataclass(frozen=True)
class ExportFramesOptions:
    """What ``procam export-frames`` and Export Projector Frames ask for."""

    compensation: Path
    out: Path
    first: int = option(1, min=0, help="number of the first frame (default 1)")
    force: bool = False


def run_frames(options: ExportFramesOptions, progress: Progress | None = None, cancel: Cancel | None = None) -> Path:
    """Copy the compensated frames into a new numbered sequence with ``frames.json``; returns the folder."""
    say = progress or quiet
    validate(options, ImageError)
    check_replaceable(options.out, force=options.force, what=KIND.what, replaceable=KIND.holds,
                      inputs=(options.compensation,), error=ImageError)
    view = compensate_step.read(options.compensation)
    if not view.targets:
        raise ImageError(f"{options.compensation} holds no finished targets to export; run Compensate first")
    if view.projector_count > 1:  # one sequence of projector 1's frames would pass for the whole show
        raise ImageError(f"{options.compensation} holds the frames of {view.projector_count} projectors; exporting "
                         "them as numbered sequences is not implemented yet for several projectors: each "
                         "projector's frame of target NAME is NAME_frame_pK.png in that folder (K from 1)")
    for t in view.targets:
        if not t.frame_path.is_file():
            raise ImageError(f"compensated frame {t.frame_path} is missing; run Compensate again")
    with fresh_output_folder(options.out, force=options.force, what=KIND.what, replaceable=KIND.holds,
                             inputs=(options.compensation, *(t.frame_path for t in view.targets))) as tmp:
        frames = []
        for i, t in enumerate(view.targets):
            check(cancel, "the export was cancelled; nothing was written")
            say(f"frame {i + 1}/{len(view.targets)}: {t.name}", i / len(view.targets))
            file = layout.frame_name(options.first + i)
            shutil.copyfile(t.frame_path, tmp / file)
            frames.append({"index": options.first + i, "file": file, "target": t.name, "mode": t.mode,
                           "psnr_simulated": t.psnr_simulated})
        write_manifest(tmp / KIND.manifest, {
            "format": KIND.format, "version": KIND.version, "compensation": str(Path(options.compensation).absolute()),
            "calibration": view.doc.get("calibration"), "mode": view.mode,
            "encoding": "raw projector input levels, 16-bit PNG, native projector resolution, no sRGB transfer",
            "written": time.strftime("%Y-%m-%dT%H:%M:%S"), "frames": frames})
    say("done", 1.0)
    return Path(options.out)


@dataclass(frozen=True)
class ExportBlendOptions:
    """What Save Calibration .blend asks for."""

    calibration: Path
    out: Path  # a .blend file
    force: bool = False


#: Writes a calibration as a .blend file at a path, replacing one only with ``force``: Blender's side supplies it
#: (``addon/blender/blend_file.save_calibration_blend_atomic``).
AtomicBlendWriter = Callable[..., Path]


def run_blend(options: ExportBlendOptions, progress: Progress | None = None, cancel: Cancel | None = None, *,
              writer: AtomicBlendWriter) -> Path:
    """Save a calibration (rig, textured surface, diagnostic images) as a .blend through ``writer``; the open
    Blender file is untouched. Blender's writer needs bpy on the main thread."""
    (progress or quiet)("reading the calibration", 0.0)
    view = calibrate_step.read_view(options.calibration)
    out = writer(options.out, view.calibration.rig, view.calibration.surface, view.images, force=options.force)
    (progress or quiet)("done", 1.0)
    return out
