"""The export step: compensated projector frames as a numbered 16-bit PNG sequence, and a calibration as a .blend.

``frames.json`` beside the frames names the compensation and calibration they
come from, the mode, and each frame's target and simulated PSNR. The frames
are the native projector resolution, in the compensation's target order,
copied bit for bit (a media server plays them as they are).

A compensation of several projectors gives one sequence per projector in one
folder, each what a media server plays on that projector's output, laid out as
a show of several projectors is::

    projector_1/frame_0001.png …   projector 1's frames (K counted from 1)
    projector_2/frame_0001.png …
    frames.json                    projector_count, each projector's frame size and input area (``projectors``),
                                   and per frame every projector's file, size and SHA-256 under ``projectors``
                                   (projector 1's file also under ``file``)
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import ImageError
from ..options import option, validate
from ..outputs import check_replaceable, file_sha256, fresh_output_folder, write_manifest
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
    """Copy the compensated frames into a new numbered sequence with ``frames.json``; returns the folder. A
    compensation of several projectors gives one sequence per projector (module doc)."""
    say = progress or quiet
    validate(options, ImageError)
    check_replaceable(options.out, force=options.force, what=KIND.what, replaceable=KIND.holds,
                      inputs=(options.compensation,), error=ImageError)
    view = compensate_step.read(options.compensation)
    if not view.targets:
        raise ImageError(f"{options.compensation} holds no finished targets to export; run procam compensate first "
                         "(Compensate in Blender)")
    count = view.projector_count
    for t in view.targets:
        if len(t.frame_paths) != count:  # a record that does not name every projector's frame
            raise ImageError(f"target {t.name!r} of {options.compensation} names the frames of {len(t.frame_paths)} "
                             f"projector(s), but the compensation is for {count}; run procam compensate again "
                             "(Compensate in Blender)")
        for k, path in enumerate(t.frame_paths):
            if not path.is_file():
                which = f" (projector {k + 1})" if count > 1 else ""
                raise ImageError(f"compensated frame {path}{which} is missing; run procam compensate again "
                                 "(Compensate in Blender)")
    digits = max(4, len(str(options.first + len(view.targets) - 1)))
    sources = [p for t in view.targets for p in t.frame_paths]
    with fresh_output_folder(options.out, force=options.force, what=KIND.what, replaceable=KIND.holds,
                             inputs=(options.compensation, *sources)) as tmp:
        frames = []
        for i, t in enumerate(view.targets):
            check(cancel, "the export was cancelled; nothing was written")
            say(f"frame {i + 1}/{len(view.targets)}: {t.name}", i / len(view.targets))
            number = options.first + i
            if count == 1:
                file = layout.frame_name(number)
                shutil.copyfile(t.frame_path, tmp / file)
                frames.append({"index": number, "file": file, "target": t.name, "mode": t.mode,
                               "psnr_simulated": t.psnr_simulated})
                continue
            files = [layout.projector_frame_name(number, digits, k) for k in range(count)]
            for k, (source, file) in enumerate(zip(t.frame_paths, files)):
                (tmp / layout.PROJECTOR_FOLDER.format(k=k + 1)).mkdir(exist_ok=True)
                shutil.copyfile(source, tmp / file)
            frames.append({"index": number, "file": files[0], "target": t.name, "mode": t.mode,
                           "psnr_simulated": t.psnr_simulated,
                           "projectors": [{"projector": k + 1, "file": f, "bytes": (tmp / f).stat().st_size,
                                           "sha256": file_sha256(tmp / f)} for k, f in enumerate(files)]})
        several: dict[str, Any] = {}
        if count > 1:
            several = {"projector_count": count, "projectors": view.doc.get("projectors"),
                       "frame_pattern": f"{layout.PROJECTOR_FOLDER.format(k='K')}/{layout.FRAME_PREFIX}"
                                        f"{'#' * digits}.png"}
        write_manifest(tmp / KIND.manifest, {
            "format": KIND.format, "version": KIND.version, "compensation": str(Path(options.compensation).absolute()),
            "calibration": view.doc.get("calibration"), "mode": view.mode,
            "encoding": "raw projector input levels, 16-bit PNG, native projector resolution, no sRGB transfer",
            **several, "written": time.strftime("%Y-%m-%dT%H:%M:%S"), "frames": frames})
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
