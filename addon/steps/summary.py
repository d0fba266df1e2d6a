"""A step folder as a panel or a terminal shows it: a headline and a few lines, read without raising.

Panels redraw often and must draw whatever is on disk, so :func:`cached`
reads a folder's manifest once per modification and turns any failure into
a summary that says why (``ok`` false), never an exception.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import ProCamError
from .layout import FolderKind


@dataclass(frozen=True)
class Summary:
    """A step's folder as a panel shows it: ``ok`` False means absent or unreadable, with the reason."""

    ok: bool
    headline: str
    lines: tuple[str, ...] = ()
    data: dict[str, Any] = field(default_factory=dict)


_CACHE: dict[tuple[str, str], tuple[object, Summary]] = {}


def cached(kind: FolderKind, folder: str | Path, read: Callable[[Path, dict[str, Any]], Summary],
           missing: str) -> Summary:
    """``read(folder, manifest document)`` for a folder of ``kind``, cached by the manifest's modification time."""
    if not folder:
        return Summary(False, missing)
    root = Path(folder)
    path = root / kind.manifest
    try:
        stamp: object = path.stat().st_mtime_ns
    except OSError:
        return Summary(False, f"{root.name or root}: no {kind.manifest} — {missing}")
    key = (kind.manifest, str(root))
    hit = _CACHE.get(key)
    if hit is not None and hit[0] == stamp:
        return hit[1]
    try:
        doc = json.loads(path.read_text())
        if not isinstance(doc, dict):
            raise ValueError("not a JSON object")
        if doc.get("format") != kind.format:
            raise ValueError(f"not a ProCam {kind.what}")
        summary = read(root, doc)
    except (OSError, ValueError, KeyError, TypeError, ProCamError) as exc:
        summary = Summary(False, f"cannot read {path}: {exc}")
    _CACHE[key] = (stamp, summary)
    return summary


def fmt(value: Any, spec: str, unit: str = "") -> str:
    """``value`` formatted with ``spec``, or "–" when it is missing or not a number."""
    try:
        return f"{float(value):{spec}}{unit}"
    except (TypeError, ValueError):
        return "–"
