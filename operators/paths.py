"""Paths typed into ProCam's folder and file properties, resolved the way Blender does (``//`` = beside the .blend)."""

from pathlib import Path

import bpy

from ..addon.errors import ProCamError


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
