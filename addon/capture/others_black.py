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


__all__ = ["BLACK_TOLERANCE", "check_others_black"]
