"""What the projector can show on this surface, and one gain and offset that bring a show's targets inside it.

At camera pixel p the projector can make the camera see anything between the
black capture B(p) (projector black: its leak, the room) and the white capture
W(p) (full white: its brightness times the paint, plus light from elsewhere);
light adds, so every input lies in between. A target above W or below B there
cannot be shown: compensation clips it, and on bright, saturated content that
is most of the error. Two things follow:

* the **range ceiling** of a target, the PSNR of the target clipped per pixel
  to [B, W] against the target: no input can do better, so every figure can
  say how far it is from what this projector could show here;
* ``--range auto``: one gain g and offset o for the whole show (never per
  frame: a per-frame fit would flicker), mapping every target t to g·t + o.

The rule of ``auto``, documented because it trades clipped pixels against
brightness: the largest gain g ≤ 1 for which some offset keeps at least
1 − :data:`CLIP_SHARE` of the target values (all targets, pixels and colour
channels of the display areas) within [B, W] of their pixel; among the offsets
that keep the most, the one closest to 0 (the show stays as bright as the
targets ask where it can). g = 1, o = 0 when the targets already fit: a show
that fits is never dimmed. The captures stand in for the light-transport
operator until that exists: they are exactly what the operator's white and
black columns would sum to.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import ProCamError

#: The share of target values ``auto`` lets clip (1 %: a few specular highlights, not the sky).
CLIP_SHARE = 0.01
#: The most target values the fit looks at (evenly subsampled beyond this).
MAX_SAMPLES = 1_000_000
#: The range ceiling of a target that fits everywhere (dB).
CEILING_CAP = 100.0
#: Gains searched below this are refused: the surface cannot show the targets at any useful contrast.
MIN_GAIN = 0.05


class RangeError(ProCamError):
    """A range that cannot be used, or targets that cannot be brought inside the projector's range."""


@dataclass(frozen=True)
class RangeMap:
    """``t → gain·t + offset``, applied to every target of a show in linear camera units."""

    gain: float
    offset: float
    rule: str = "given"
    clipped_share: float | None = None  # of the targets' values, after the map (auto only)

    def apply(self, target: np.ndarray) -> np.ndarray:
        return (np.asarray(target, dtype=np.float32) * np.float32(self.gain) + np.float32(self.offset))

    def to_dict(self) -> dict[str, Any]:
        return {"gain": round(float(self.gain), 6), "offset": round(float(self.offset), 6), "rule": self.rule,
                "clipped_share": None if self.clipped_share is None else round(float(self.clipped_share), 6)}

    @staticmethod
    def from_dict(d: dict[str, Any] | None) -> "RangeMap | None":
        if not d:
            return None
        try:
            gain, offset = float(d["gain"]), float(d["offset"])
            if not (math.isfinite(gain) and math.isfinite(offset)) or gain <= 0 or not -1 < offset < 1:
                raise ValueError("gain or offset out of range")
        except (TypeError, KeyError, ValueError) as exc:
            # A record from a damaged or hand-edited manifest: the step that wrote it makes it again.
            raise RangeError(f"the range map {d!r} recorded with these results is not one ProCam writes ({exc}); "
                             "compensate again") from None
        return RangeMap(gain, offset, str(d.get("rule", "given")), d.get("clipped_share"))


def parse_range(text: str) -> str | RangeMap:
    """``auto``, ``none`` or ``GAIN,OFFSET``."""
    s = str(text).strip().lower()
    if s in ("auto", "none"):
        return s
    try:
        gain, offset = (float(v) for v in s.split(","))
    except ValueError:
        raise RangeError(f"--range must be auto, none or GAIN,OFFSET (e.g. 0.8,0.02), got {text!r}") from None
    if not (math.isfinite(gain) and math.isfinite(offset)) or gain <= 0 or not -1 < offset < 1:
        raise RangeError(f"--range GAIN,OFFSET needs a positive gain and an offset in (-1, 1), got {text!r}")
    return RangeMap(gain, offset)


def _samples(targets: list[np.ndarray], blacks: list[np.ndarray], whites: list[np.ndarray]
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.concatenate([np.asarray(a, np.float64).ravel() for a in targets])
    b = np.concatenate([np.asarray(a, np.float64).ravel() for a in blacks])
    w = np.concatenate([np.asarray(a, np.float64).ravel() for a in whites])
    if not (t.shape == b.shape == w.shape):
        raise RangeError("each target needs the black and white captures of its display area, of the same size")
    if t.size > MAX_SAMPLES:
        pick = np.linspace(0, t.size - 1, MAX_SAMPLES).astype(np.int64)
        t, b, w = t[pick], b[pick], w[pick]
    return t, b, w


def _best_offset(t: np.ndarray, b: np.ndarray, w: np.ndarray, gain: float) -> tuple[int, float]:
    """The most values an offset keeps inside [b, w] at ``gain``, and that offset (closest to 0 among the best).

    Each value is kept by the offsets of one interval [b − g·t, w − g·t]; the
    best offsets are where most intervals overlap (a sweep over sorted ends)."""
    starts, ends = np.sort(b - gain * t), np.sort(w - gain * t)
    candidates = np.concatenate([starts, ends, [0.0]])
    kept = np.searchsorted(starts, candidates, side="right") - np.searchsorted(ends, candidates, side="left")
    best = int(kept.max())
    tied = candidates[kept == best]
    return best, float(tied[np.argmin(np.abs(tied))])


def fit_range(targets: list[np.ndarray], blacks: list[np.ndarray], whites: list[np.ndarray], *,
              clip_share: float = CLIP_SHARE) -> RangeMap:
    """The show's gain and offset by the module's rule, from each target fitted to its display area and the black
    and white captures cropped to that area (linear camera units)."""
    t, b, w = _samples(targets, blacks, whites)
    n = t.size
    need = math.ceil((1.0 - clip_share) * n)
    kept, offset = _best_offset(t, b, w, 1.0)
    inside_identity = int(np.count_nonzero((t >= b) & (t <= w)))
    if inside_identity >= need:
        return RangeMap(1.0, 0.0, "auto: the targets fit", 1.0 - inside_identity / n)
    lo, hi = 0.0, 1.0
    if kept < need:
        for _ in range(30):  # the kept count falls as the gain grows: bisect for the largest gain that keeps enough
            mid = 0.5 * (lo + hi)
            if _best_offset(t, b, w, mid)[0] >= need:
                lo = mid
            else:
                hi = mid
        if lo < MIN_GAIN:
            raise RangeError(f"even at gain {MIN_GAIN} no offset keeps {100 * (1 - clip_share):.0f} % of the "
                             "targets inside what the projector shows on this surface (its white capture is "
                             "barely above its black): check the white and black captures, or give --range "
                             "GAIN,OFFSET")
        gain = lo
    else:
        gain = 1.0
    kept, offset = _best_offset(t, b, w, gain)
    return RangeMap(gain, offset, f"auto: largest gain with ≤ {100 * clip_share:g} % clipped", 1.0 - kept / n)


def _psnr_of(mse: float) -> float:
    return CEILING_CAP if mse <= 10 ** (-CEILING_CAP / 10) else 10.0 * math.log10(1.0 / mse)


def _clip_mse(target: np.ndarray, black: np.ndarray, white: np.ndarray) -> float:
    t = np.asarray(target, np.float64)
    clipped = np.clip(t, np.asarray(black, np.float64), np.maximum(np.asarray(white, np.float64), black))
    return float(np.mean((clipped - t) ** 2))


def range_ceiling(target: np.ndarray, black: np.ndarray, white: np.ndarray) -> float:
    """PSNR (dB, peak 1) of the target clipped per pixel to [black, white] against the target: no input does
    better; :data:`CEILING_CAP` when the target lies inside everywhere (JSON has no infinity)."""
    return _psnr_of(_clip_mse(target, black, white))


def capture_noise_mse(first: np.ndarray, second: np.ndarray) -> float:
    """The camera's noise variance (mean over pixels and channels) from two captures of one input: their
    difference holds twice each capture's own noise (sensor, and whatever else changes from shot to shot)."""
    return float(np.mean((np.asarray(first, np.float64) - np.asarray(second, np.float64)) ** 2)) / 2.0


def noise_ceiling(target: np.ndarray, black: np.ndarray, white: np.ndarray, noise_mse: float) -> float:
    """The range ceiling as a capture can score it: the clipped target seen through the camera's noise of
    variance ``noise_mse`` (independent of the image, so the two squared errors add). With the range mapped
    (``--range auto``) the clipped target is almost the target, the range ceiling reaches 59–68 dB on the lab,
    and no capture of a camera with noise comes near it: this is the one a result can be held to."""
    return _psnr_of(_clip_mse(target, black, white) + max(float(noise_mse), 0.0))


#: An input at or above this (at or below :data:`INPUT_ZERO`) where a pixel looks cannot give it more (less).
INPUT_FULL = 0.99
INPUT_ZERO = 0.01


def ceiling_gap_at_limit(target: np.ndarray, capture: np.ndarray, black: np.ndarray, white: np.ndarray,
                         seen_input: np.ndarray) -> float | None:
    """Of what separates a compensated capture from the range ceiling (its squared error beyond the clipped
    target's), the share at pixels and channels where the projector's input already gives all it can there: the
    capture is darker than the target with the input the pixel sees (``seen_input``) at full, or brighter with it
    at zero. No solver pushes further there. The per-pixel ceiling is loose at such pixels: the white capture
    lights every neighbour and every channel at once, while a target asks for some of them dark, and the
    projector's blur and colour crosstalk carry that darkness over (the lab's plane: 96 % of the white where its
    sky is at full input). None when the capture is nowhere worse than the ceiling."""
    t, c = np.asarray(target, np.float64), np.asarray(capture, np.float64)
    clipped = np.clip(t, black, np.maximum(white, black))
    excess = np.maximum((c - t) ** 2 - (clipped - t) ** 2, 0.0)
    total = float(excess.sum())
    if total <= 0.0:
        return None
    x = np.nan_to_num(np.asarray(seen_input, np.float64), nan=0.5)
    at_limit = ((c < t) & (x >= INPUT_FULL)) | ((c > t) & (x <= INPUT_ZERO))
    return float(excess[at_limit].sum()) / total


__all__ = ["CLIP_SHARE", "INPUT_FULL", "INPUT_ZERO", "RangeError", "RangeMap", "capture_noise_mse",
           "ceiling_gap_at_limit", "fit_range", "noise_ceiling", "parse_range", "range_ceiling"]
