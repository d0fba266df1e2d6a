"""Where the simulation and the captures disagree: residual maps and the regions that hold the error.

Regions are found from the data: the per-pixel mean squared residual (over the
patterns and channels) is thresholded at the level above which the worst pixels
hold half of the squared error, opened/closed, and split into connected
components, largest share of the squared error first. Each region is then
described against what is known about the scene from the calibration alone:
surface creases, the unlit side of a concave edge, the projector border, a
saturated white capture (the albedo there is a lower bound), the input levels
and colour channel that dominate its error, and whether its error comes from
sharp (binary) or smooth patterns.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..stages.calibrate import SATURATED
from .data import GapData

#: Regions smaller than this share of the lit pixels are merged into "scattered" error.
MIN_REGION_PIXELS = 0.002
MAX_REGIONS = 6


@dataclass
class Region:
    bbox: tuple[int, int, int, int]  # x, y, width, height in pixels of the full camera image
    share: float  # of the total squared residual
    pixels: int
    description: str
    tags: list[str]

    def to_dict(self) -> dict[str, Any]:
        return {"bbox": list(self.bbox), "share": round(self.share, 4), "pixels": self.pixels,
                "description": self.description, "tags": self.tags}


def residual_maps(residuals: np.ndarray, mask: np.ndarray) -> dict[str, np.ndarray]:
    """Signed mean, mean absolute and RMS residual per pixel and channel (h×w×3), zero off the mask."""
    m = mask[..., None]
    return {"signed": np.where(m, residuals.mean(axis=0), 0.0).astype(np.float32),
            "abs": np.where(m, np.abs(residuals).mean(axis=0), 0.0).astype(np.float32),
            "rms": np.where(m, np.sqrt((residuals ** 2).mean(axis=0)), 0.0).astype(np.float32)}


def _half_error_threshold(sq: np.ndarray) -> float:
    v = np.sort(sq.ravel())[::-1]
    c = np.cumsum(v)
    return float(v[min(int(np.searchsorted(c, 0.5 * c[-1])), len(v) - 1)]) if c[-1] > 0 else float("inf")


def find_regions(data: GapData, residuals: np.ndarray, full_size: tuple[int, int], pattern_index: list[int]
                 ) -> list[Region]:
    """Connected regions of high residual, with what is known about each (see module docstring)."""
    mask = data.mask
    sq = np.where(mask, (residuals ** 2).mean(axis=(0, 3)), 0.0)
    total = float(sq.sum())
    if total <= 0:
        return []
    hot = (sq >= _half_error_threshold(sq[mask])) & mask
    kernel = np.ones((3, 3), np.uint8)
    hot = cv2.morphologyEx(cv2.morphologyEx(hot.astype(np.uint8), cv2.MORPH_CLOSE, kernel), cv2.MORPH_OPEN, kernel)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(hot, connectivity=8)
    h, w = mask.shape
    sx, sy = full_size[0] / w, full_size[1] / h
    min_px = max(4, int(MIN_REGION_PIXELS * mask.sum()))
    regions = []
    for lab in range(1, count):
        x, y, bw, bh, area = stats[lab]
        if area < min_px:
            continue
        sel = labels == lab
        tags, words = _describe(data, residuals, sel, pattern_index)
        regions.append(Region((int(x * sx), int(y * sy), int(round(bw * sx)), int(round(bh * sy))),
                              float(sq[sel].sum() / total), int(area), words, tags))
    regions.sort(key=lambda r: -r.share)
    return regions[:MAX_REGIONS]


def _describe(data: GapData, residuals: np.ndarray, sel: np.ndarray, pattern_index: list[int]
              ) -> tuple[list[str], str]:
    tags: list[str] = []
    words: list[str] = []
    if float(data.crease[sel].mean()) > 0.3:
        tags.append("crease")
        gain = data.gain.mean(axis=2)
        near = cv2.dilate(sel.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        if float(gain[sel].mean()) < 0.8 * float(gain[near & data.mask].mean()):
            tags.append("unlit side of a concave edge")
            words.append("on the darker side of a surface crease")
        else:
            words.append("near a surface crease")
    iw, ih = data.projector.input_size
    c = data.corr[sel]
    border = np.minimum.reduce([c[:, 0], c[:, 1], iw - 1 - c[:, 0], ih - 1 - c[:, 1]])
    if float(np.median(border)) < 0.05 * min(iw, ih):
        tags.append("projector border")
        words.append("near the border of the projector input")
    if float((data.white.capture[sel] >= SATURATED).any(axis=1).mean()) > 0.3:
        # The albedo came from the white capture; where that clipped it is a lower bound (stages.calibrate).
        tags.append("saturated white")
        words.append("where the white capture is saturated (a highlight or too long an exposure: the albedo "
                     "read there is too dark)")
    obs = [data.observations[i] for i in pattern_index]
    per = np.array([float((residuals[k][sel] ** 2).mean()) for k in range(len(obs))])
    levels = np.array([float(o.sampled[sel].mean()) for o in obs])
    if per.sum() > 0:
        w = per / per.sum()
        dark, bright = float(w[levels < 0.2].sum()), float(w[levels > 0.8].sum())
        if dark > 0.5:
            tags.append("dark input")
            words.append("in dark input levels")
        elif bright > 0.5:
            tags.append("bright input")
            words.append("in bright input levels")
        elif float(w[(levels >= 0.2) & (levels <= 0.8)].sum()) > 0.6:
            tags.append("mid input")
            words.append("in mid input levels")
        fine = float(w[[o.fine for o in obs]].sum())
        share_fine = sum(o.fine for o in obs) / len(obs)
        if fine > max(0.6, 1.3 * share_fine):
            tags.append("high spatial frequency")
            words.append("at high spatial frequency (sharp pattern edges)")
    ch = (residuals[:, sel] ** 2).mean(axis=(0, 1))
    if ch.sum() > 0 and float(ch.max() / ch.sum()) > 0.5:
        name = "rgb"[int(ch.argmax())]
        tags.append(f"channel {name}")
        words.append(f"mostly in the {dict(r='red', g='green', b='blue')[name]} channel")
    signed = float(residuals[:, sel].mean())
    words.append("simulation too bright" if signed > 0 else "simulation too dark")
    return tags, ", ".join(words)
