"""The approximate inverse of a calibration's light-transport operator, stored beside it (stages/realtime.py).

``procam precompute --live`` writes ``layout.inverse_files(k)`` for every
projector: ``inverse.npz`` (the stencil weights) and ``inverse.json`` (what it
holds, how long it took, and the calibration's hashes, bounces and seed, as
the operator's record has). A live show reads it when it belongs to the
calibration and fits its operator, and otherwise builds it in memory
(``steps/realtime.py``), because a show never writes into a calibration folder.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from ..imageio import read_arrays, write_atomic_bytes
from ..progress import Progress
from ..safepaths import inside
from ..stages.calibrate import Calibration
from ..stages.realtime import ApproximateInverse, InverseError, build_inverse, building_bytes
from ..stages.transport import TransportOperator, free_bytes
from . import calibrate as calibrate_step
from . import layout


def check_memory(camera_size: tuple[int, int]) -> None:
    """An :class:`InverseError` saying how much building the inverse needs when that is more than 80 % of the
    memory free now."""
    need, free = building_bytes(camera_size), free_bytes()
    if free is not None and need > 0.8 * free:
        cw, ch = camera_size
        raise InverseError(f"building the approximate inverse of a {cw}×{ch} camera needs about "
                           f"{need / 2 ** 30:.1f} GiB and {free / 2 ** 30:.1f} GiB are free: free memory, or use a "
                           "calibration at a lower camera resolution")


def _record(folder: Path, view: Calibration, bounces: int, seed: int) -> dict[str, Any]:
    ident = calibrate_step.identity(folder)
    return {"calibration_sha256": ident["sha256"], "surface_sha256": ident["surface_sha256"], "bounces": bounces,
            "seed": seed}


def store_inverse(folder: str | Path, view: Calibration, op: TransportOperator, *, bounces: int, seed: int,
                  progress: Progress | None = None) -> dict[str, Any]:
    """Build the inverse of projector ``view.projector_index``'s operator ``op`` and store it in the calibration
    folder (``layout.inverse_files``), each file atomically. Returns its record."""
    folder = Path(folder)
    check_memory(op.camera_size)
    inv = build_inverse(op, progress)
    data_file, report_file = layout.inverse_files(view.projector_index)
    doc = {**inv.report, **_record(folder, view, bounces, seed), "file": data_file}
    buf = io.BytesIO()
    np.savez(buf, **inv.arrays())
    write_atomic_bytes(folder / data_file, buf.getvalue())
    write_atomic_bytes(folder / report_file, (json.dumps(doc, indent=1) + "\n").encode())
    return doc


def load_inverse(view: Calibration, op: TransportOperator, *, bounces: int, seed: int) -> ApproximateInverse | None:
    """The stored inverse of ``view``'s projector when it belongs to this calibration (hashes, bounces and seed)
    and fits ``op``; None when there is none. :class:`InverseError` when it is damaged."""
    if not view.folder:
        return None
    folder = Path(view.folder)
    data_file, report_file = (inside(folder, name, what="the approximate inverse file", error=InverseError)
                              for name in layout.inverse_files(view.projector_index))
    if not data_file.is_file() or not report_file.is_file():
        return None
    try:
        doc = json.loads(report_file.read_text())
        mine = _record(folder, view, bounces, seed)
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or any(doc.get(k) != v for k, v in mine.items()):
        return None
    data = read_arrays(data_file, error=InverseError, remedy=f"run procam precompute {folder} --live --force")
    inv = ApproximateInverse.from_arrays(data, doc)
    return inv if inv.fits(op) else None


__all__ = ["check_memory", "load_inverse", "store_inverse"]
