"""Spill: the light a projection puts outside its display area, as a share of the picture's level.

Compensation should light the display area and leave the rest of the
projectors' reach dark (or at the surround colour asked for). ``evaluate``
measures how far it does, on a capture of the compensated input:

* **outside** are the camera pixels some projector reaches (its footprint on the
  surface: model coverage ∩ captured white − black, :func:`.display_area.model_coverage`)
  that lie more than :func:`guard_band` pixels from the display area. Pixels no
  projector can light say nothing about compensation; the band next to the
  area's edge is the edge itself, blurred by the lens, the camera and the
  sub-pixel warp (an edge camera pixel shares texels with the surround), so it
  is left out as the automatic area keeps the same margin from the footprint's
  edge;
* the light there is the capture minus the black capture (every projector
  black: its black level and the room's light), averaged over the channels;
* the **picture's level** is the mean of that light inside the area;
* ``spill_mean`` is the outside's mean and ``spill_p995`` its 99.5th
  percentile, each over the picture's level (0.02 = 2 %). The percentile
  counts single pixels, so at small camera sizes it holds the camera's noise
  (one capture's noise alone read 11 % on the quarter-scale lab): a capture
  repeated for the noise is averaged in first.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .display_area import DisplayArea, capture_coverage, edge_margin, model_coverage

#: the percentile of the outside's light reported beside its mean
PERCENTILE = 99.5


def guard_band(camera_width: int) -> int:
    """Pixels next to the display area left out of the spill: the automatic area's margin (module doc)."""
    return edge_margin(camera_width)


def outside_mask(reach: np.ndarray, area: DisplayArea, guard: int | None = None) -> np.ndarray:
    """H×W bool: the pixels of ``reach`` (what some projector lights) farther than ``guard`` pixels from ``area``."""
    reach = np.asarray(reach, dtype=bool)
    h, w = reach.shape
    g = guard_band(w) if guard is None else int(guard)
    x0, y0 = max(area.x - g, 0), max(area.y - g, 0)
    x1, y1 = min(area.x + area.width + g, w), min(area.y + area.height + g, h)
    out = reach.copy()
    out[y0:y1, x0:x1] = False
    return out


def spill(capture: np.ndarray, black: np.ndarray, area: DisplayArea, reach: np.ndarray, *,
          again: np.ndarray | None = None, guard: int | None = None) -> dict[str, Any]:
    """The spill of a capture (module doc): ``spill_mean``, ``spill_p995`` (shares of the picture's level, None
    when nothing of the reach lies outside or the picture is black), ``picture_level`` and ``outside_pixels``.
    ``again``: a second capture of the same input, averaged in."""
    cap = np.asarray(capture, np.float32)
    if again is not None:
        cap = 0.5 * (cap + np.asarray(again, np.float32))
    light = (cap - np.asarray(black, np.float32)).mean(axis=2)
    level = float(area.crop(light).mean())
    out = outside_mask(reach, area, guard)
    n = int(out.sum())
    if n == 0 or not level > 1e-6:
        return {"spill_mean": None, "spill_p995": None, "picture_level": round(level, 5), "outside_pixels": n}
    values = light[out]
    return {"spill_mean": round(float(values.mean()) / level, 4),
            "spill_p995": round(float(np.percentile(values, PERCENTILE)) / level, 4),
            "picture_level": round(level, 5), "outside_pixels": n}


def record(row: dict[str, Any], capture: np.ndarray, plain: np.ndarray, black: np.ndarray, area: DisplayArea,
           reach: np.ndarray, *, again: np.ndarray | None = None) -> None:
    """An evaluation ``row`` given the :func:`spill` of its ``capture`` (with its repeat ``again``) and, in its
    ``uncompensated`` record, the mean and percentile of the ``plain`` capture's."""
    row.update(spill(capture, black, area, reach, again=again))
    plain_spill = spill(plain, black, area, reach)
    row["uncompensated"].update(spill_mean=plain_spill["spill_mean"], spill_p995=plain_spill["spill_p995"])


def one_projector_reach(calibration: Any, white: np.ndarray, black: np.ndarray) -> np.ndarray:
    """The camera pixels one calibrated projector lights: its model's coverage ∩ its captured white − black."""
    cover = model_coverage(calibration)
    real = capture_coverage(white, black)
    return cover & real if real.shape == cover.shape else cover


#: what ``metrics.json`` says the spill figures are
MEASURE = ("spill_mean / spill_p995: the light outside the display area (capture − black capture, over the pixels "
           "some projector reaches, farther than guard_px from the area) as a share of the picture's level (the "
           "mean of that light inside the area): its mean and its 99.5th percentile, the capture averaged with its "
           "repeat when there is one")


def summarise(rows: list[dict[str, Any]], camera_width: int) -> dict[str, Any] | None:
    """The spill over finished ``rows`` (each with ``spill_mean``/``spill_p995``, and the same in its
    ``uncompensated``): the means over targets, the worst target's 99.5th percentile, and the guard band."""
    def mean(values: list[Any]) -> float | None:
        vals = [v for v in values if isinstance(v, (int, float))]
        return round(float(np.mean(vals)), 4) if vals else None

    if not rows:
        return None
    plain = [r.get("uncompensated") or {} for r in rows]
    p995 = [float(v) for r in rows if isinstance(v := r.get("spill_p995"), (int, float))]
    return {"mean": mean([r.get("spill_mean") for r in rows]), "p995": mean([r.get("spill_p995") for r in rows]),
            "worst_p995": round(float(max(p995)), 4) if p995 else None,
            "uncompensated_mean": mean([u.get("spill_mean") for u in plain]),
            "uncompensated_p995": mean([u.get("spill_p995") for u in plain]),
            "guard_px": guard_band(camera_width)}


def spill_text(mean: Any, p995: Any, plain_mean: Any = None, plain_p995: Any = None) -> str:
    """"spill outside the area: mean 1.2 %, 99.5th pixel 18 % of the picture's level (uncompensated …)"."""
    def pc(v: Any) -> str:
        return f"{100 * v:.1f} %" if isinstance(v, (int, float)) else "n/a"

    plain = (f" (uncompensated {pc(plain_mean)}, {pc(plain_p995)})"
             if isinstance(plain_mean, (int, float)) or isinstance(plain_p995, (int, float)) else "")
    return f"spill outside the area: mean {pc(mean)}, 99.5th pixel {pc(p995)} of the picture's level{plain}"


__all__ = ["MEASURE", "PERCENTILE", "guard_band", "one_projector_reach", "outside_mask", "record", "spill",
           "spill_text", "summarise"]
