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

* ``--range bright``: one offset and a gain that varies smoothly over the
  surface, dimmer only where the paint or the distance demands it (below).

The rule of ``auto``, documented because it trades clipped pixels against
brightness: the largest gain g ≤ 1 for which some offset keeps at least
1 − :data:`CLIP_SHARE` of the target values (all targets, pixels and colour
channels of the display areas) within [B, W] of their pixel; among the offsets
that keep the most, the one closest to 0 (the show stays as bright as the
targets ask where it can). g = 1, o = 0 when the targets already fit: a show
that fits is never dimmed. The captures stand in for the light-transport
operator until that exists: they are exactly what the operator's white and
black columns would sum to.

``auto`` holds the whole show to the darkest paint and the farthest corner: on
an independent phone-rig simulation it chose gain 0.175, a fifth of the light
everywhere for the last percent of pixels. The rule of ``bright`` trades
brightness against clipping as a viewer sees it: a viewer does not see a slow
change of brightness, so the gain may fall where the surface cannot show the
targets and stay at 1 elsewhere, as long as it changes slowly. Its steps:

1. one offset o for the show: the black capture's (1 − :data:`CLIP_SHARE`)
   quantile over the display areas (the room's black, under which no value is
   shown);
2. on a grid of cells over the camera image (:data:`GRID_CELLS` on its long
   side), the gain each cell needs: the largest g ≤ 1 at which at most
   :data:`CLIP_SHARE` of the cell's target values (all targets, pixels,
   channels) exceed its white capture, g·t + o > W;
3. the gain field: the largest field under every cell's need whose relative
   change is at most ``per_degree`` per degree of visual angle, g(c) =
   min over c' of need(c')·(1 + per_degree)^d(c, c') with d in degrees, capped at
   1 (a lower envelope of cones: a dark patch dims its surroundings only as
   far as the gradient demands). Degrees are the camera's (its focal length):
   the camera stands where the audience looks from. Between cells the field
   is interpolated linearly in log gain.

The gradient limit, :data:`BRIGHT_PER_DEGREE` (5 % per degree) by default: a
smooth ramp is judged by its total change rather than its slope (McCann,
Savoy & Hall 1974, "Visibility of continuous luminance gradients", Vision
Research 14:917–927), and observers cannot tell a ramp's direction below a
6 % change across fields of 1 to 25° (Erens, Kappers & Koenderink 1993,
"Estimating the gradient direction of a luminance ramp", Vision Research
33:1639–1643). At 5 % per degree no patch a viewer fixates (about 1°) holds a
change at that threshold; over tens of degrees the change adds up and would be
seen on a uniform grey, which is why the limit is a parameter
(``--range bright:PCT``) and the brightness the field keeps is printed and
recorded: the mean of the mapped white g(p) + o over the display areas, as a
share of the targets' white (1 for ``none``, g + o for a uniform map).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field as dc_field
from typing import Any

import cv2
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
#: ``bright``'s default limit on the gain field's relative change per degree of visual angle (module docstring).
BRIGHT_PER_DEGREE = 0.05
#: ``bright``'s gain field has this many cells on the camera image's long side.
GRID_CELLS = 32


class RangeError(ProCamError):
    """A range that cannot be used, or targets that cannot be brought inside the projector's range."""


@dataclass(frozen=True, eq=False)
class GainField:
    """A gain that varies over the camera image: ``cells`` (rows × columns, each ``cell`` camera pixels square)
    interpolated linearly in log gain; what ``--range bright`` fits (module docstring)."""

    cells: np.ndarray
    cell: int
    camera_size: tuple[int, int]
    per_degree: float
    degrees_per_pixel: float
    _image: list[np.ndarray] = dc_field(default_factory=list, repr=False)  # the image, made once (real-time frames)

    def image(self) -> np.ndarray:
        """The gain at every camera pixel (h×w, float32)."""
        if not self._image:
            self._image.append(self._make_image())
        return self._image[0]

    def _make_image(self) -> np.ndarray:
        rows, cols = self.cells.shape
        log = cv2.resize(np.log(self.cells).astype(np.float32), (cols * self.cell, rows * self.cell),
                         interpolation=cv2.INTER_LINEAR)
        cw, ch = self.camera_size
        return np.exp(log[:ch, :cw])

    def on(self, area: Any) -> np.ndarray:
        """The gain on a display area's pixels (h×w×1, float32)."""
        return np.ascontiguousarray(self.image()[area.slices])[..., None]

    def to_dict(self) -> dict[str, Any]:
        return {"cells": np.round(self.cells, 4).tolist(), "cell_px": self.cell, "camera_size": list(self.camera_size),
                "per_degree": self.per_degree, "degrees_per_pixel": round(self.degrees_per_pixel, 6)}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> GainField:
        cells = np.asarray(d["cells"], np.float64)
        cw, ch = (int(v) for v in d["camera_size"])
        cell = int(d["cell_px"])
        if (cells.ndim != 2 or not np.all(np.isfinite(cells)) or cells.min() <= 0 or cells.max() > 1 or cell < 1
                or cells.shape[0] * cell < ch or cells.shape[1] * cell < cw):
            raise ValueError("a gain field needs cells in (0, 1] covering the camera image")
        return GainField(cells, cell, (cw, ch), float(d["per_degree"]), float(d["degrees_per_pixel"]))


@dataclass(frozen=True)
class RangeMap:
    """``t → gain·t + offset``, applied to every target of a show in linear camera units; with a ``field``
    (``--range bright``) the gain is the field's at each pixel and ``gain`` its mean over the display areas."""

    gain: float
    offset: float
    rule: str = "given"
    clipped_share: float | None = None  # of the targets' values, after the map (auto and bright only)
    field: GainField | None = None
    #: the mean mapped white over the display areas as a share of the targets' white (module docstring)
    brightness: float | None = None

    def gain_on(self, area: Any) -> np.ndarray | float:
        """The gain at each pixel of a display area (h×w×1), or the one gain."""
        if self.field is None:
            return float(self.gain)
        if area is None:
            raise RangeError("a range map whose gain varies over the surface needs the display area it applies to")
        return self.field.on(area)

    def apply(self, target: np.ndarray, area: Any = None) -> np.ndarray:
        """The mapped target; ``area`` (the display area it fills) is needed with a gain field."""
        gain = self.gain_on(area)
        return (np.asarray(target, dtype=np.float32) * np.float32(gain) + np.float32(self.offset)).astype(np.float32)

    def unmap(self, image: np.ndarray, area: Any = None) -> np.ndarray:
        """An image in mapped units (a capture) read back in the targets' own: (image − offset) / gain."""
        return ((np.asarray(image, np.float32) - np.float32(self.offset)) / np.float32(self.gain_on(area))
                ).astype(np.float32)

    def brightness_kept(self, area: Any = None) -> float:
        """The mean mapped white (gain + offset) over a display area as a share of the targets' white."""
        return float(np.mean(self.gain_on(area))) + float(self.offset)

    def describe(self) -> str:
        """One line for a person: the map, its rule and the brightness it keeps."""
        if self.field is None:
            text = f"{self.gain:.3f}·t {self.offset:+.3f}"
            kept = self.gain + self.offset
        else:
            cells = self.field.cells
            text = (f"g(p)·t {self.offset:+.3f} with g from {cells.min():.3f} to {cells.max():.3f} over the camera "
                    f"image (mean {self.gain:.3f} in the display areas)")
            kept = self.brightness if self.brightness is not None else self.gain + self.offset
        clipped = "" if self.clipped_share is None else f", {100 * self.clipped_share:.2f} % of the values clipped"
        return f"{text} ({self.rule}); brightness kept {100 * kept:.0f} % of the targets' white{clipped}"

    def to_dict(self) -> dict[str, Any]:
        brightness = self.brightness if self.brightness is not None else (
            None if self.field is not None else self.gain + self.offset)
        return {"gain": round(float(self.gain), 6), "offset": round(float(self.offset), 6), "rule": self.rule,
                "clipped_share": None if self.clipped_share is None else round(float(self.clipped_share), 6),
                "brightness_kept": None if brightness is None else round(float(brightness), 4),
                **({"field": self.field.to_dict()} if self.field is not None else {})}

    @staticmethod
    def from_dict(d: dict[str, Any] | None) -> RangeMap | None:
        if not d:
            return None
        try:
            gain, offset = float(d["gain"]), float(d["offset"])
            if not (math.isfinite(gain) and math.isfinite(offset)) or gain <= 0 or not -1 < offset < 1:
                raise ValueError("gain or offset out of range")
            field = GainField.from_dict(d["field"]) if d.get("field") is not None else None
            # a uniform map's brightness follows from its gain and offset
            brightness = None if field is None or d.get("brightness_kept") is None else float(d["brightness_kept"])
        except (TypeError, KeyError, ValueError) as exc:
            # A record from a damaged or hand-edited manifest: the step that wrote it makes it again.
            raise RangeError(f"the range map {d!r} recorded with these results is not one ProCam writes ({exc}); "
                             "compensate again") from None
        return RangeMap(gain, offset, str(d.get("rule", "given")), d.get("clipped_share"), field, brightness)


def range_line(record: Any) -> list[str]:
    """The range map a compensation or show recorded, in a line (none without one; older records keep their
    gain and offset only)."""
    try:
        r = RangeMap.from_dict(record) if isinstance(record, dict) else None
    except ProCamError as exc:
        return [f"range: {exc}"]
    return [] if r is None else [f"range: targets mapped to {r.describe()}"]


def parse_range(text: str) -> str | RangeMap:
    """``auto``, ``none``, ``bright``, ``bright:PCT`` (the gradient limit in % per degree; returned as
    ``bright:PCT``) or ``GAIN,OFFSET``."""
    s = str(text).strip().lower()
    if s in ("auto", "none"):
        return s
    if s.split(":")[0] == "bright":
        return f"bright:{100 * bright_per_degree(s):g}"
    try:
        gain, offset = (float(v) for v in s.split(","))
    except ValueError:
        raise RangeError(f"--range must be auto, bright, bright:PCT, none or GAIN,OFFSET (e.g. 0.8,0.02), got "
                         f"{text!r}") from None
    if not (math.isfinite(gain) and math.isfinite(offset)) or gain <= 0 or not -1 < offset < 1:
        raise RangeError(f"--range GAIN,OFFSET needs a positive gain and an offset in (-1, 1), got {text!r}")
    return RangeMap(gain, offset)


def bright_per_degree(text: str) -> float:
    """The gradient limit of ``bright`` or ``bright:PCT`` as a fraction per degree."""
    head, _, pct = str(text).strip().lower().partition(":")
    if head != "bright":
        raise RangeError(f"not a bright range: {text!r}")
    if not pct:
        return BRIGHT_PER_DEGREE
    try:
        value = float(pct.rstrip("%")) / 100
    except ValueError:
        value = float("nan")
    if not (math.isfinite(value) and 0 < value <= 1):
        raise RangeError(f"--range bright:PCT needs the gain's largest change in % per degree of visual angle, "
                         f"between 0 and 100 (e.g. bright:5), got {text!r}")
    return value


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


def fit_bright(targets: list[np.ndarray], blacks: list[np.ndarray], whites: list[np.ndarray], areas: list[Any],
               camera_size: tuple[int, int], degrees_per_pixel: float, *, per_degree: float = BRIGHT_PER_DEGREE,
               clip_share: float = CLIP_SHARE) -> RangeMap:
    """The show's offset and gain field by the ``bright`` rule (module docstring), from each target fitted to its
    display area (``areas``, each a :class:`~.display_area.DisplayArea` of the ``camera_size`` image) and the black
    and white captures cropped to that area; ``degrees_per_pixel``: the camera's visual angle of one pixel."""
    if not (len(targets) == len(blacks) == len(whites) == len(areas)) or not targets:
        raise RangeError("each target needs its display area and the black and white captures of that area")
    t, b, w = _samples(targets, blacks, whites)
    n = t.size
    inside_identity = int(np.count_nonzero((t >= b) & (t <= w)))
    if inside_identity >= math.ceil((1.0 - clip_share) * n):
        return RangeMap(1.0, 0.0, "bright: the targets fit", 1.0 - inside_identity / n, brightness=1.0)
    offset = float(np.clip(np.quantile(b, 1.0 - clip_share), 0.0, 0.5))
    cw, ch = camera_size
    cell = max(1, math.ceil(max(cw, ch) / GRID_CELLS))
    rows, cols = math.ceil(ch / cell), math.ceil(cw / cell)
    index, ratio = [], []
    for target, white, area in zip(targets, whites, areas):
        tt = np.asarray(target, np.float64)
        ys, xs = np.mgrid[area.y:area.y + area.height, area.x:area.x + area.width]
        idx = (ys // cell) * cols + xs // cell
        index.append(np.broadcast_to(idx[..., None], tt.shape).ravel())
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.where(tt > 1e-6, (np.asarray(white, np.float64) - offset) / np.maximum(tt, 1e-6), np.inf)
        ratio.append(np.maximum(r, 0.0).ravel())
    idx_all, r_all = np.concatenate(index), np.concatenate(ratio)
    if idx_all.size > MAX_SAMPLES:
        pick = np.linspace(0, idx_all.size - 1, MAX_SAMPLES).astype(np.int64)
        idx_all, r_all = idx_all[pick], r_all[pick]
    # each cell's need: its clip_share quantile of (W − o) / t, the gain above which more than that share clips
    order = np.lexsort((r_all, idx_all))
    counts = np.bincount(idx_all, minlength=rows * cols)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    sampled = np.nonzero(counts)[0]
    need = np.minimum(r_all[order][starts[sampled] + np.floor(clip_share * counts[sampled]).astype(np.int64)], 1.0)
    # the lower envelope of cones of slope log(1 + per_degree) per degree under each cell's need
    cy, cx = np.divmod(np.arange(rows * cols), cols)
    centres = np.stack([(cx + 0.5) * cell, (cy + 0.5) * cell], axis=1) * degrees_per_pixel
    dist = np.hypot(*(centres[:, None, :] - centres[None, sampled, :]).transpose(2, 0, 1))
    log_field = np.min(np.log(np.maximum(need, 1e-4))[None, :] + math.log1p(per_degree) * dist, axis=1)
    field = GainField(np.exp(np.minimum(log_field, 0.0)).reshape(rows, cols), cell, (cw, ch), per_degree,
                      degrees_per_pixel)
    on = [field.on(a) for a in areas]
    lowest = min(float(g.min()) for g in on)
    if lowest < MIN_GAIN:
        raise RangeError(f"even at gain {MIN_GAIN} the projector cannot show {100 * (1 - clip_share):.0f} % of the "
                         f"targets' values somewhere in the display area (its white capture is barely above "
                         f"{offset:.3f}, the room's black there): check the white and black captures, or give "
                         "--range GAIN,OFFSET")
    clipped = sum(int(np.count_nonzero((g * np.asarray(tt) + offset > wh) | (g * np.asarray(tt) + offset < bl)))
                  for g, tt, wh, bl in zip(on, targets, whites, blacks))
    values = sum(int(np.asarray(tt).size) for tt in targets)
    gains = np.concatenate([g.ravel() for g in on])
    return RangeMap(float(gains.mean()), offset,
                    f"bright: gain ≤ 1 changing ≤ {100 * per_degree:g} % per degree, ≤ {100 * clip_share:g} % "
                    "clipped per cell", clipped / values, field, min(float(gains.mean()) + offset, 1.0))


def fit_rule(rule: str, targets: list[np.ndarray], blacks: list[np.ndarray], whites: list[np.ndarray],
             areas: list[Any], camera: Any) -> RangeMap:
    """The show's map by a fitted rule (``auto`` or ``bright:PCT`` as :func:`parse_range` gives it); ``camera``:
    the camera's intrinsics (its size and focal length give the degrees of ``bright``)."""
    if rule == "auto":
        return fit_range(targets, blacks, whites)
    return fit_bright(targets, blacks, whites, areas, (int(camera.width), int(camera.height)),
                      math.degrees(1.0 / float(camera.fx)), per_degree=bright_per_degree(rule))


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
    and no capture of a camera with noise comes near it: this is the one a result can be held to. A camera that
    compresses its photos (JPEG) quantises the picture's texture as well, the same way in two captures of one
    input, which ``noise_mse`` (their difference) misses: there it is optimistic (lab/perfect.py)."""
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


__all__ = ["BRIGHT_PER_DEGREE", "CLIP_SHARE", "INPUT_FULL", "INPUT_ZERO", "GainField", "RangeError", "RangeMap",
           "bright_per_degree", "capture_noise_mse", "ceiling_gap_at_limit", "fit_bright", "fit_range", "fit_rule",
           "noise_ceiling", "parse_range", "range_ceiling", "range_line"]
