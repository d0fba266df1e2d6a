"""The check of a multi-projector capture set that each projector's sequence was taken while the others showed black.

Every projector's sequence holds a ``black`` capture, taken with that projector showing black and, as the capture
rule says, every other projector black too: all of them photograph the same scene (every projector black), so
they agree up to noise. A projector that was left showing something (the last pattern of its own sequence, a
desktop, a test card) while another's sequence was captured lifts that sequence's black capture inside its own
footprint: measured there against its own black capture, in units of its own white, the excess names both.
"""

from __future__ import annotations

import numpy as np

from ..errors import CaptureError
from ..imageio import read_image
from .format import CaptureSet

#: How much brighter (a fraction of projector j's white over black, averaged over j's footprint) projector k's black
#: capture may be than projector j's own black capture there. A projector left on a pattern lifts it by tens of
#: percent; noise averages out over the footprint, and a projector's black level is in both captures alike.
BLACK_TOLERANCE = 0.03
#: Fewer lit camera pixels than this and a projector's footprint is too small to measure anything in.
MIN_FOOTPRINT = 16


def _mean_of(captures: CaptureSet, kind: str) -> np.ndarray | None:
    entries = captures.entries_of(kind)
    if not entries:
        return None
    return np.mean([read_image(captures.file(e)) for e in entries], axis=0).mean(axis=2)


def check_others_black(captures: CaptureSet, *, tolerance: float = BLACK_TOLERANCE,
                       where: str | None = None) -> dict[tuple[int, int], float]:
    """Refuse a multi-projector capture set in which a projector was not black while another's sequence was taken.

    For every pair of projectors (k, j): the mean of projector k's black capture minus projector j's own black
    capture, over j's footprint (its white over its black above half their 99th percentile), in units of j's
    white over black there. Above ``tolerance`` a :class:`CaptureError` says that projector j (numbered from 1)
    was not black while projector k's captures were taken. Returns every pair's excess (projectors numbered from
    0); a one-projector set, or a projector without a black and a white capture, has nothing to compare.
    ``where`` names the set in the message (default its folder; a set not yet in place is named by its final one).
    """
    count = len(captures.projectors)
    if count < 2:
        return {}
    blacks: list[np.ndarray | None] = []
    footprints: list[tuple[np.ndarray, float] | None] = []
    for k in range(count):
        view = captures.for_projector(k)
        black, white = _mean_of(view, "black"), _mean_of(view, "white")
        blacks.append(black)
        if black is None or white is None:
            footprints.append(None)
            continue
        lit = white - black
        mask = lit > 0.5 * float(np.percentile(lit, 99))
        footprints.append((mask, float(lit[mask].mean())) if mask.sum() >= MIN_FOOTPRINT else None)
    excess: dict[tuple[int, int], float] = {}
    for j, foot in enumerate(footprints):
        own = blacks[j]
        if foot is None or own is None or foot[1] <= 0:
            continue
        mask, level = foot
        for k, black in enumerate(blacks):
            if k != j and black is not None:
                excess[(k, j)] = float((black - own)[mask].mean()) / level
    if excess:
        (k, j), worst = max(excess.items(), key=lambda item: item[1])
        if worst > tolerance:
            raise CaptureError(
                f"capture set {where or captures.path}: projector {k + 1}'s black capture is brighter inside projector "
                f"{j + 1}'s footprint than projector {j + 1}'s own black capture, by {worst:.0%} of projector "
                f"{j + 1}'s white: projector {j + 1} was not black while projector {k + 1}'s captures were taken. "
                f"Show black on every other projector and capture projector {k + 1}'s sequence again")
    return excess


#: Two projectors' captures of the same pattern that differ by less than this (mean absolute difference, a fraction
#: of their mean level), pattern after pattern, are one projector's photographs twice. Two real projectors differ
#: far more in their checkerboards and Gray codes, even stacked on one another: a fraction of a pixel of pose moves
#: every edge; a copy saved again, or re-encoded, stays well under it.
SAME_TOLERANCE = 0.01
#: The kinds compared: what a projector shows, so what tells two projectors apart.
_COMPARED = ("white", "checker", "graycode")


def check_distinct_projectors(captures: CaptureSet, *, tolerance: float = SAME_TOLERANCE,
                              where: str | None = None) -> None:
    """Refuse a multi-projector capture set in which two projectors' photographs are the same (identical, or nearly:
    saved again, re-encoded): one projector's photographs given as another's, which no calibration can tell apart
    but as two projectors at one pose. Their captures of the same patterns (kind and parameters alike) are compared
    pattern after pattern; the first pair that differs by more than ``tolerance`` of its level ends the
    comparison. ``where`` names the set in the message (default its folder)."""
    count = len(captures.projectors)
    if count < 2:
        return
    shown = []
    for k in range(count):
        view = captures.for_projector(k)
        shown.append({(e.kind, repr(sorted((n, v) for n, v in e.params.items() if n != "source"))): e
                      for e in view.entries if e.kind in _COMPARED})
    for j in range(1, count):
        for k in range(j):
            alike = [key for key in shown[j] if key in shown[k]]
            if all(key[0] == "white" for key in alike):
                continue  # a flat white alone proves nothing: two stacked projectors light one area alike
            worst = 0.0
            for key in alike:
                a = read_image(captures.file(shown[k][key]))
                b = read_image(captures.file(shown[j][key]))
                if a.shape != b.shape:
                    worst = np.inf
                    break
                level = max(float(a.mean() + b.mean()) / 2, 1e-6)
                worst = max(worst, float(np.abs(a - b).mean()) / level)
                if worst >= tolerance:
                    break
            if worst < tolerance:
                raise CaptureError(
                    f"capture set {where or captures.path}: projector {j + 1}'s photographs are the same as projector "
                    f"{k + 1}'s ({len(alike)} photographs of the same patterns differ by {worst:.2%} of their level "
                    f"at most; two projectors differ far more): were projector {j + 1}'s photographs copied from "
                    f"projector {k + 1}'s? Photograph projector {j + 1}'s own sequence, shown on projector {j + 1} "
                    "with every other projector black, and import those")


def check_projector_captures(captures: CaptureSet, *, where: str | None = None) -> None:
    """Both checks of a multi-projector capture set: no projector's photographs are another's
    (:func:`check_distinct_projectors`), and each projector's were taken with the others black
    (:func:`check_others_black`)."""
    check_distinct_projectors(captures, where=where)
    check_others_black(captures, where=where)


__all__ = ["BLACK_TOLERANCE", "SAME_TOLERANCE", "check_distinct_projectors", "check_others_black",
           "check_projector_captures"]
