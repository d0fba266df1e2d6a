"""The precompute step: the light-transport operator of a calibration, stored in the calibration folder.

``procam precompute CALIB`` renders ``T`` (``stages/transport.py``) and writes
``transport.npz`` (the operator) and ``transport.json`` (what it holds, how
long it took, and the content hashes of the calibration it belongs to) into
the calibration folder, each atomically (``calibrate.store_transport``, which
``procam calibrate`` also runs by default). Stage C's ``transport`` schedule reads
it when its hashes match the calibration and the compensator's bounces and
seed, and otherwise renders its own in memory (saying so), because
compensation never writes into a calibration folder.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import CalibrationError
from ..imageio import read_arrays
from ..options import option, validate
from ..progress import Cancel, Progress, quiet
from ..safepaths import inside
from ..stages.calibrate import Calibration
from ..stages.transport import TransportError, TransportOperator
from . import calibrate as calibrate_step
from .layout import TRANSPORT_JSON as REPORT_FILE, TRANSPORT_NPZ as OPERATOR_FILE


@dataclass(frozen=True)
class PrecomputeOptions:
    """What ``procam precompute`` asks for."""

    calibration: Path
    # declared here, not taken from StageCOptions: stage C imports this module
    bounces: int = option(1, min=0, help="indirect bounces, as compensate will use")
    seed: int = option(0, min=0, help="seed, as compensate will use")
    force: bool = False


def run(options: PrecomputeOptions, progress: Progress | None = None, cancel: Cancel | None = None
        ) -> dict[str, Any]:
    """Render and store the operator; returns its report. An operator already there for the same calibration,
    bounces and seed is kept unless ``force``."""
    validate(options, CalibrationError)
    say = progress or quiet
    folder = Path(options.calibration)
    cal = calibrate_step.read(folder)
    if not options.force and load(cal, bounces=options.bounces, seed=options.seed) is not None:
        doc = json.loads((folder / REPORT_FILE).read_text())
        say("the transport operator of this calibration is already there (--force renders it again)", 1.0)
        return doc
    return calibrate_step.store_transport(folder, cal, bounces=options.bounces, seed=options.seed, progress=say,
                                          cancel=cancel)


def load(calibration: Calibration, *, bounces: int, seed: int) -> TransportOperator | None:
    """The stored operator of ``calibration`` when it belongs to it (same hashes, bounces and seed), else None."""
    if not calibration.folder:
        return None
    folder = Path(calibration.folder)
    # Fixed names, but the files may be links: the operator of another folder is not this calibration's.
    operator, report = (inside(folder, name, what="the light-transport operator file", error=TransportError)
                        for name in (OPERATOR_FILE, REPORT_FILE))
    if not operator.is_file() or not report.is_file():
        return None
    try:
        doc = json.loads(report.read_text())
        ident = calibrate_step.identity(folder)
    except (OSError, ValueError, CalibrationError):
        return None
    if not isinstance(doc, dict):  # not the record precompute writes: no operator of this calibration
        return None
    if (doc.get("calibration_sha256"), doc.get("surface_sha256"), doc.get("bounces"), doc.get("seed")) != \
            (ident["sha256"], ident["surface_sha256"], bounces, seed):
        return None
    data = read_arrays(operator, error=TransportError, remedy=f"run procam precompute {folder} --force")
    return TransportOperator.from_arrays(data, doc)
