"""The MPCDI steps: a calibration handed to media servers as a VESA MPCDI file, and an MPCDI file applied to content
frames the way a media server applies it.

``procam export-mpcdi CALIBRATION --out show.mpcdi`` (and Export ▸ MPCDI in Blender) writes one ``.mpcdi`` file
(:mod:`..mpcdi.format`): in the ``2d`` profile one buffer, the content canvas (``--content-size``), holding one
region per projector; in ``sl`` one buffer per projector with its frustum, pose and the surface under its pixels.
What each region holds, and what a static hand-off keeps and loses: :mod:`..mpcdi.derive`. The content is the
display area ProCam compensates targets in: ``--area``, else the capture set's, else the largest rectangle of the
content's aspect that the projectors cover together (as ``procam compensate`` chooses it). The blend is the joint
blend's (the light-transport operators' shares) when the calibration stores every projector's operator
(``procam calibrate`` does; ``procam precompute`` adds it), else geometric ramps, and the command says which.
The file is written under a temporary name and renamed into place: an existing file is replaced only with
``--force`` and only when it is an MPCDI archive; a calibration of one projector gives a valid one-region file.

``procam apply-mpcdi FILE CONTENT… --out DIR`` reads the file back and writes, per content image, the frame each
region's projector shows (``Pf = Pi·α·(1 − β) + β``, :mod:`..mpcdi.apply`), laid out as ``procam export-frames``
lays out several projectors' frames (``projector_K/frame_0001.png``, ``frames.json``), so the lab or a rig can
show them.
"""

from __future__ import annotations

import os
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import MpcdiError
from ..imageio import atomic_path, write_failed, write_image
from ..options import Choice, option, validate
from ..outputs import check_file_replaceable, fresh_output_folder, output_names, write_manifest
from ..progress import Cancel, Progress, check, part, quiet
from ..stages.calibrate import Calibration
from ..stages.display_area import DisplayArea, load_target, parse_area
from ..stages.joint import blend_shares, calibration_certainty, distance_shares
from ..mpcdi import apply as apply_mpcdi
from ..mpcdi.derive import CameraMaps, Derived, build
from ..mpcdi.format import WRITTEN_PROFILES, Mpcdi, XML_NAME, read_mpcdi, write_archive
from . import calibrate as calibrate_step
from . import layout, projectors
from . import transport as transport_step

KIND = layout.FRAMES
#: the operators ``procam calibrate`` stores (``procam precompute``'s defaults): the ones whose shares are the blend
STORED_BOUNCES, STORED_SEED = 1, 0
SUFFIX = ".mpcdi"


def parse_content_size(text: str) -> tuple[int, int]:
    """``"1920x1080"`` → (1920, 1080)."""
    parts = str(text).lower().replace("×", "x").split("x")
    try:
        w, h = (int(p) for p in parts)
    except ValueError:
        raise MpcdiError(f"a content size is WIDTHxHEIGHT in pixels (e.g. 1920x1080), got {text!r}") from None
    if not (2 <= w <= 65536 and 2 <= h <= 65536):
        raise MpcdiError(f"a content size of {w}×{h} pixels is out of range (2 to 65536 each)")
    return w, h


@dataclass(frozen=True)
class ExportMpcdiOptions:
    """What ``procam export-mpcdi`` and Export ▸ MPCDI ask for."""

    calibration: Path
    out: Path  # the .mpcdi file
    profile: str = option("2d", choices=(Choice("2d", "2D Media", "One region per projector in the content: its "
                                                "warp, blend and black level (read by every media server)"),
                                         Choice("sl", "Shader Lamps", "Each projector's frustum, pose and the "
                                                "surface under its pixels, with its blend and black level")),
                          help="MPCDI profile: 2d (warp of the content per projector; WATCHOUT, Pixera, TouchDesigner "
                               "and nDisplay read it) or sl (shader lamps: each projector's frustum, pose and the "
                               "surface's 3D points)")
    content_size: tuple[int, int] = option((1920, 1080), parse=parse_content_size, metavar="WxH",
                                           help="the media server's canvas in pixels: the buffer's resolution and the "
                                                "display area's aspect (default 1920x1080)")
    warp_step: int = option(4, min=1, max=64, help="projector pixels between two samples of the warp grid "
                            "(default 4; 1: per pixel; a grid of at most 32×32 is the 2d profile's level 1)")
    area: tuple[int, int, int, int] | None = option(
        None, parse=parse_area, help="display area x,y,width,height in camera pixels (default: the capture set's, "
                                     "else the largest rectangle of the content's aspect the projectors cover)")
    force: bool = False


@dataclass
class ExportResult:
    """What was written: the file, its size, the seconds it took, what it holds and what to tell the user."""

    path: Path
    bytes: int
    seconds: float
    report: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


def is_mpcdi(path: Path) -> bool:
    """Whether ``path`` is an MPCDI archive (a zip holding ``mpcdi.xml``): what ``force`` may replace."""
    try:
        with zipfile.ZipFile(path) as z:
            return XML_NAME in z.namelist()
    except (OSError, zipfile.BadZipFile, ValueError):
        return False


def camera_maps(calibration: Calibration) -> tuple[CameraMaps, Any, Any, list[str]]:
    """The blend's shares and the measured black level in camera space (:class:`CameraMaps`), the capture set and
    its per-projector views (None when it moved), and what to tell the user."""
    views = projectors.views_of(calibration)
    captures = calibrate_step.captures_of(calibration, required=False)
    cviews = projectors.captures_views(captures, len(views))
    said: list[str] = []
    ops = [transport_step.load(v, bounces=STORED_BOUNCES, seed=STORED_SEED) for v in views]
    if all(op is not None for op in ops):
        shares = blend_shares(ops, [calibration_certainty(v) for v in views])  # type: ignore[arg-type]
        blend = "joint blend: each projector's share of the light, from its light-transport operator"
    else:
        shares = distance_shares(projectors.footprints(views, cviews))
        blend = "geometric ramps: linear edge blend across each overlap, from the projectors' footprints"
        if len(views) > 1:
            said.append("the calibration stores no light-transport operator for every projector (procam precompute "
                        "stores them): the blend was derived as geometric ramps from the projectors' footprints")
    black = lit = None
    if cviews is not None:
        blacks = [v.image("black") for v in cviews]
        # Each projector's captures were taken with the others showing black: every black capture is the rig black.
        black = np.mean(blacks, axis=0).astype(np.float32)
        lit = [np.clip(v.image("white") - b, 0.0, None).astype(np.float32) for v, b in zip(cviews, blacks)]
    return CameraMaps(shares.astype(np.float32), blend, black, lit), captures, cviews, said


def export_area(calibration: Calibration, options: ExportMpcdiOptions, captures: Any, cviews: Any) -> DisplayArea:
    """The display area the content fills (module doc)."""
    size = calibration.rig.camera.intrinsics.size
    if options.area is not None:
        return DisplayArea(*options.area, source="user").check(size)
    if captures is not None and captures.target_area is not None:
        return DisplayArea(*captures.target_area, source="capture-set").check(size)
    w, h = options.content_size
    return projectors.joint_area(projectors.views_of(calibration), w / h, captures=cviews)


def check_out(options: ExportMpcdiOptions, calibration_dir: Path) -> bool:
    """Refuse an output that must not be written (module doc); True when an existing file will be replaced."""
    out = Path(options.out)
    if out.suffix.lower() != SUFFIX:
        raise MpcdiError(f"an MPCDI file's name ends in {SUFFIX} (VESA MPCDI §3.1), got {out.name!r}")
    return check_file_replaceable(out, force=options.force, what="MPCDI file", replaceable=is_mpcdi,
                                  inputs=(calibration_dir, *layout.step_folders_around(out)), error=MpcdiError)


def derive(options: ExportMpcdiOptions, progress: Progress | None = None, cancel: Cancel | None = None
           ) -> tuple[Derived, Calibration]:
    """The file's content, not written (the benchmark times the writing apart)."""
    say = progress or quiet
    validate(options, MpcdiError)
    if options.profile not in WRITTEN_PROFILES:
        raise MpcdiError(f"profile must be one of {', '.join(WRITTEN_PROFILES)}, got {options.profile!r}")
    check_out(options, Path(options.calibration))
    say("reading the calibration", 0.0)
    cal = calibrate_step.read(options.calibration)
    maps, captures, cviews, said = camera_maps(cal)
    area = export_area(cal, options, captures, cviews)
    check(cancel, "the MPCDI export was cancelled; nothing was written")
    done = build(cal, area, maps, content_size=options.content_size, warp_step=options.warp_step,
                 profile=options.profile, progress=part(say, 0.05, 0.9), cancel=cancel)
    done.warnings[:0] = said
    return done, cal


def write(m: Mpcdi, out: Path, *, force: bool) -> int:
    """The archive at ``out``, written under a temporary name in its folder and renamed into place (an existing
    file is replaced only then, never half-written); returns its size in bytes."""
    out = Path(out)
    if not out.parent.is_dir():
        raise MpcdiError(f"cannot write {out}: its folder {out.parent} does not exist")
    tmp, final = atomic_path(out)
    try:
        with open(tmp, "wb") as fh:
            write_archive(m, fh)
        size = tmp.stat().st_size
        if final.exists() and not force:  # appeared while writing
            raise MpcdiError(f"the MPCDI file {final} already exists; it is never overwritten without --force")
        os.replace(tmp, final)
    except OSError as exc:
        raise write_failed(final, exc) from None
    finally:
        tmp.unlink(missing_ok=True)
    return size


def run_export(options: ExportMpcdiOptions, progress: Progress | None = None, cancel: Cancel | None = None
               ) -> ExportResult:
    """Write the calibration's MPCDI file (module doc); returns what was written."""
    say = progress or quiet
    t0 = time.perf_counter()
    done, _ = derive(options, progress, cancel)
    check(cancel, "the MPCDI export was cancelled; nothing was written")
    check_out(options, Path(options.calibration))  # again: the file may have appeared meanwhile
    say("writing the archive", 0.95)
    size = write(done.mpcdi, options.out, force=options.force)
    say("done", 1.0)
    return ExportResult(Path(options.out), size, round(time.perf_counter() - t0, 3), done.report, done.warnings)


# -- applying a file -----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ApplyMpcdiOptions:
    """What ``procam apply-mpcdi`` asks for."""

    mpcdi: Path
    content: tuple[Path, ...]
    out: Path
    first: int = option(1, min=0, help="number of the first frame (default 1)")
    force: bool = False


def run_apply(options: ApplyMpcdiOptions, progress: Progress | None = None, cancel: Cancel | None = None) -> Path:
    """Each content image through every region of the file; one numbered sequence per region (module doc)."""
    say = progress or quiet
    validate(options, MpcdiError)
    if not options.content:
        raise MpcdiError("give at least one content image to apply the MPCDI file to")
    m = read_mpcdi(options.mpcdi)
    if m.profile != "2d":
        raise MpcdiError(f"{options.mpcdi} is of the {m.profile} profile; apply-mpcdi applies the 2d profile (a 3D "
                         "profile's warp is drawn by a renderer of the scene)")
    images = []
    for path in options.content:  # read them all before anything is written
        image, _ = load_target(path)
        images.append(image)
    names = output_names(options.content)
    count = len(m.regions)
    digits = max(4, len(str(options.first + len(images) - 1)))
    with fresh_output_folder(options.out, force=options.force, what=KIND.what, replaceable=KIND.holds,
                             inputs=(options.mpcdi, *options.content)) as tmp:
        rows = []
        for i, (name, image) in enumerate(zip(names, images)):
            check(cancel, "apply-mpcdi was cancelled; nothing was written")
            say(f"content {i + 1}/{len(images)}: {name}", i / len(images))
            files = []
            for k, frame in enumerate(apply_mpcdi.frames(m, image)):
                rel = layout.projector_frame_name(options.first + i, digits, k)
                (tmp / layout.PROJECTOR_FOLDER.format(k=k + 1)).mkdir(exist_ok=True)
                write_image(tmp / rel, frame)
                files.append({"projector": k + 1, "region": m.regions[k].id, "file": rel})
            rows.append({"index": options.first + i, "file": files[0]["file"], "content": name,
                         "projectors": files})
        write_manifest(tmp / KIND.manifest, {
            "format": KIND.format, "version": KIND.version, "mpcdi": str(Path(options.mpcdi).absolute()),
            "profile": m.profile, "projector_count": count,
            "projectors": [{"projector": k + 1, "region": r.id, "frame_size": list(r.resolution)}
                           for k, r in enumerate(m.regions)],
            "encoding": "projector input levels through the MPCDI file's warp, alpha and beta (Pi·α·(1−β) + β), "
                        "16-bit PNG, no sRGB transfer",
            "frame_pattern": f"{layout.PROJECTOR_FOLDER.format(k='K')}/{layout.FRAME_PREFIX}{'#' * digits}.png",
            "written": time.strftime("%Y-%m-%dT%H:%M:%S"), "frames": rows})
    say("done", 1.0)
    return Path(options.out)


__all__ = ["ApplyMpcdiOptions", "ExportMpcdiOptions", "ExportResult", "camera_maps", "derive", "export_area",
           "is_mpcdi", "parse_content_size", "run_apply", "run_export", "write"]
