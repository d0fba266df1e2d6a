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
    return find(calibration, bounces=bounces, seed=seed).operator


@dataclass(frozen=True)
class StoredOperator:
    """What a calibration folder holds of one projector's operator: the operator when it is this calibration's
    and this run's, else None and why not (``problem``)."""

    operator: TransportOperator | None
    #: the operator's file name (``transport.npz``, ``transport_p2.npz`` …)
    file: str
    #: why the stored operator is not used ("is missing", "was made with --bounces 0 …"); None when it is
    problem: str | None = None


def find(calibration: Calibration, *, bounces: int, seed: int) -> StoredOperator:
    """:func:`load`, saying why no operator is used when there is none (:class:`StoredOperator`)."""
    index = calibration.projector_index if calibration.projector_count == 1 else 0
    names = transport_files(index)
    if not calibration.folder:
        return StoredOperator(None, names[0], "has no calibration folder to be read from")
    folder = Path(calibration.folder)
    # Fixed names, but the files may be links: the operator of another folder is not this calibration's.
    operator, report = (inside(folder, name, what="the light-transport operator file", error=TransportError)
                        for name in names)
    if not operator.is_file() or not report.is_file():
        gone = [p.name for p in (operator, report) if not p.is_file()]
        return StoredOperator(None, names[0], f"is missing ({' and '.join(gone)} not in the calibration folder)")
    try:
        doc = json.loads(report.read_text())
        ident = calibrate_step.identity(folder)
    except (OSError, ValueError, CalibrationError):
        return StoredOperator(None, names[0], f"cannot be used ({names[1]} cannot be read)")
    if not isinstance(doc, dict):  # not the record precompute writes: no operator of this calibration
        return StoredOperator(None, names[0], f"cannot be used ({names[1]} is not an operator's record)")
    if (doc.get("calibration_sha256"), doc.get("surface_sha256")) != (ident["sha256"], ident["surface_sha256"]):
        return StoredOperator(None, names[0], "was made for another calibration (the folder was calibrated again "
                                              "since)")
    if (doc.get("bounces"), doc.get("seed")) != (bounces, seed):
        return StoredOperator(None, names[0], f"was made with --bounces {doc.get('bounces')} --seed "
                                              f"{doc.get('seed')}, and this run uses --bounces {bounces} --seed {seed}")
    data = read_arrays(operator, error=TransportError, remedy=f"run procam precompute {folder} --force")
    return StoredOperator(TransportOperator.from_arrays(data, doc), names[0])


def rebuild_note(calibration: Calibration, found: StoredOperator, *, bounces: int, seed: int) -> str:
    """What a run that renders an operator in memory says (progress and its record): which file, why, and the
    command that stores it.

    A run that reads a calibration never writes the operator into it, even when it has just rendered it: the
    calibration is an input (issue 53), which several runs may read at once and a user may have archived or
    shared; storing is what ``procam precompute`` (and ``procam calibrate``) is for, under the calibration's
    own writer lock. So the note says that every run renders it again until it is stored, and how to store it.
    """
    folder = calibration.folder or "CALIBRATION"
    settings = (f" --bounces {bounces}" if bounces != 1 else "") + (f" --seed {seed}" if seed else "")
    return (f"the stored light-transport operator {found.file} {found.problem}: this run renders it in memory "
            f"(every run does until it is stored: a run that reads a calibration never writes into it): run "
            f"`procam precompute {folder}{settings}` once to store it")
