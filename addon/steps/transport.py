"""The precompute step: the light-transport operator of a calibration, stored in the calibration folder.

``procam precompute CALIB`` renders ``T`` (``stages/transport.py``) and writes
``transport.npz`` (the operator) and ``transport.json`` (what it holds, how
long it took, and the content hashes of the calibration it belongs to) into
the calibration folder, each atomically (``calibrate.store_transport``, which
``procam calibrate`` also runs by default). A calibration of several
projectors gets one operator per projector, lit alone (``layout.transport_files(k)``:
``transport_p2.npz`` … beside the first's): each holds its projector's direct
light and its indirect light everywhere in the camera, so also the light it
bounces onto the other projectors' areas. Stage C's ``transport`` schedule reads
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
from ..outputs import writer_lock
from ..progress import Cancel, Progress, part, quiet
from ..safepaths import inside
from ..stages.calibrate import Calibration
from ..stages.transport import TransportError, TransportOperator
from . import calibrate as calibrate_step
from .inverse import load_inverse, store_inverse
from .layout import inverse_files, transport_files

#: the operator's files of one projector (of the first of several), as scripts read them
OPERATOR_FILE, REPORT_FILE = transport_files(0)


@dataclass(frozen=True)
class PrecomputeOptions:
    """What ``procam precompute`` asks for."""

    calibration: Path
    # declared here, not taken from StageCOptions: stage C imports this module
    bounces: int = option(1, min=0, help="indirect bounces, as compensate will use")
    seed: int = option(0, min=0, help="seed, as compensate will use")
    live: bool = option(False, label="Live", help="also store each operator's approximate inverse, which "
                        "procam live-show solves with (inverse.npz beside transport.npz)")
    force: bool = False


def run(options: PrecomputeOptions, progress: Progress | None = None, cancel: Cancel | None = None
        ) -> dict[str, Any]:
    """Render and store the operator of every projector; returns its report (one projector), or ``{"projectors":
    [each one's report]}`` (several). An operator already there for the same calibration, bounces and seed is kept
    unless ``force``."""
    validate(options, CalibrationError)
    say = progress or quiet
    folder = Path(options.calibration)
    with writer_lock(folder):  # it writes into the calibration: another run writing it is refused first
        return _run(options, folder, say, cancel)


def _run(options: PrecomputeOptions, folder: Path, say: Progress, cancel: Cancel | None) -> dict[str, Any]:
    cal = calibrate_step.read(folder)
    count = cal.projector_count
    docs = []
    for k in range(count):
        view = cal.for_projector(k)
        name = f"projector {k + 1}: " if count > 1 else ""
        op = None if options.force else load(view, bounces=options.bounces, seed=options.seed)
        if op is not None:
            doc = json.loads((folder / transport_files(k)[1]).read_text())
            say(f"{name}the transport operator of this calibration is already there (--force renders it again)",
                (k + 1) / count)
        else:
            doc = calibrate_step.store_transport(folder, view, bounces=options.bounces, seed=options.seed,
                                                 progress=part(say, k / count, (k + 1) / count, name),
                                                 cancel=cancel)
        if options.live:
            doc = {**doc, "inverse": _live_inverse(folder, view, op, options, part(say, k / count, (k + 1) / count,
                                                                                    name))}
        docs.append(doc)
    return docs[0] if count == 1 else {"projectors": docs}


def _live_inverse(folder: Path, view: Calibration, op: TransportOperator | None, options: PrecomputeOptions,
                  say: Progress) -> dict[str, Any]:
    """The approximate inverse of one projector's operator (``op``, read again when it was just rendered), kept
    when the stored one belongs to it, else built and stored."""
    op = op or load(view, bounces=options.bounces, seed=options.seed)
    if op is None:
        raise CalibrationError("the transport operator just stored cannot be read back; run procam precompute "
                               "--force")
    if not options.force and load_inverse(view, op, bounces=options.bounces, seed=options.seed) is not None:
        say("the approximate inverse of this calibration is already there (--force builds it again)", 1.0)
        return json.loads((folder / inverse_files(view.projector_index)[1]).read_text())
    return store_inverse(folder, view, op, bounces=options.bounces, seed=options.seed, progress=say)


def load(calibration: Calibration, *, bounces: int, seed: int) -> TransportOperator | None:
    """The stored operator of ``calibration`` when it belongs to it (same hashes, bounces and seed), else None: of
    its projector ``calibration.projector_index`` for a :meth:`~.Calibration.for_projector` view (a calibration of
    several projectors itself: its first projector's)."""
    if not calibration.folder:
        return None
    folder = Path(calibration.folder)
    index = calibration.projector_index if calibration.projector_count == 1 else 0
    # Fixed names, but the files may be links: the operator of another folder is not this calibration's.
    operator, report = (inside(folder, name, what="the light-transport operator file", error=TransportError)
                        for name in transport_files(index))
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
