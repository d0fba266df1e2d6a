"""Paths read from a manifest: resolved inside the folder that holds the manifest, never outside it.

Folders come from other people (a capture set mailed in, a calibration copied
from a show crew). A manifest that names ``/etc/passwd``, ``../../x`` or a
symlink that leaves its folder must not make ProCam read, copy or count a file
the user never gave it. Every reader resolves the names it finds with
:func:`inside`; a step that keeps an absolute path to another folder (a
compensation naming its calibration) checks the file it takes from there with
:func:`within`.
"""

from __future__ import annotations

import os
from pathlib import Path

from .errors import ProCamError


def _real(path: Path) -> Path:
    return Path(os.path.realpath(path))


def within(root: str | Path, path: str | Path, *, what: str, error: type[ProCamError] = ProCamError) -> Path:
    """``path`` (absolute, or relative to the working folder), refused unless it and every symlink on the way
    stay inside ``root``; returns it unresolved, so messages name what the user gave."""
    path = Path(path)
    try:
        root_real, real = _real(Path(root)), _real(path)
        outside = real != root_real and root_real not in real.parents
    except (OSError, ValueError):  # a NUL byte, or a name the system cannot resolve
        outside = True
    if outside:
        raise error(f"{what} {path} lies outside {root} (a link or a path that leaves the folder); a ProCam folder "
                    "only names files inside itself — ask for a folder made by ProCam, or remake it")
    return path


def inside(root: str | Path, name: object, *, what: str, error: type[ProCamError] = ProCamError) -> Path:
    """The file or folder a manifest in ``root`` names by ``name``: a non-empty relative path whose parts do not
    climb out and whose symlinks, if any, stay inside ``root``."""
    if not isinstance(name, str) or not name or "\x00" in name:
        raise error(f"{what} in {root} is named {name!r}, which is not a file name; remake the folder with ProCam")
    rel = Path(name)
    # No parts: "." or "./" names the folder itself, not a file in it.
    if rel.is_absolute() or rel.drive or not rel.parts or ".." in rel.parts:
        raise error(f"{what} {name!r} in {root} must be a relative path inside the folder; a ProCam folder only "
                    "names files inside itself — ask for a folder made by ProCam, or remake it")
    return within(root, Path(root) / rel, what=what, error=error)
