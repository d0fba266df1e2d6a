"""Paths typed into ProCam's folder and file properties, resolved the way Blender does (``//`` = beside the .blend)."""

import fnmatch
import re
from pathlib import Path

import bpy

from ..addon.errors import ProCamError
from ..addon.imageio import READ_IMAGE_SUFFIXES


def resolve(value: str, what: str) -> Path:
    """An absolute path for a property value; a clear error when it is empty or relative to an unsaved file."""
    if not value:
        raise ProCamError(f"no {what} given: choose it in the ProCam panel")
    path = bpy.path.abspath(value)
    if path.startswith("//"):
        raise ProCamError(f"the {what} is relative to the .blend file, which is not saved: save it or give an "
                          "absolute path")
    return Path(path).absolute()


def existing(value: str, manifest: str) -> Path | None:
    """The folder of ``value`` if it holds ``manifest`` (cheap: for ``poll``), else None."""
    if not value:
        return None
    path = bpy.path.abspath(value)
    if path.startswith("//"):
        return None
    root = Path(path)
    return root if (root / manifest).is_file() else None


_NUMBERED_STEM = re.compile(r"\d+$")


def _natural(path: Path) -> list[object]:
    # pose_2 before pose_10, as a person numbers poses
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]


def holds_numbered_images(folder: Path) -> bool:
    """Whether ``folder`` holds images named like a board session's (``graycode_00.png`` …)."""
    try:
        return any(p.suffix.lower() in READ_IMAGE_SUFFIXES and _NUMBERED_STEM.search(p.stem) and p.is_file()
                   for p in folder.iterdir())
    except OSError:
        return False


def board_sessions(folder: Path, pattern: str = "*") -> list[Path]:
    """The subfolders of ``folder`` whose names match ``pattern`` (``*``, ``capture_*`` …) and that hold numbered
    images, in natural order: one board pose each."""
    try:
        subs = [p for p in folder.iterdir() if p.is_dir() and fnmatch.fnmatchcase(p.name, pattern or "*")]
    except OSError:
        return []
    return sorted((p for p in subs if holds_numbered_images(p)), key=_natural)
