"""Where the simulation and the captures disagree, and which cause each place belongs to.

A region is a compact place in the camera image that holds a good share of the
error, with the cause it belongs to and what lies there. The error is split by
cause before regions are drawn: for each effect the diagnosis modelled, the
change its fitted model makes to the held-out prediction, squared (what it
explains there, without the captures' noise; for a local effect, spread over
where its fitted model puts light under white, from the calibrated geometry:
the change alone sits in a highlight's clipped core, because the albedo read
from white holds the lobe everywhere else); and what all the selected
effects leave on the smooth parts (the remainder: "unexplained" when
:mod:`.remainder` says it is above the captures' noise, "left over" when it
is not). A residual map taken
whole mixes causes, and on the demo its top region was the whole projected
area for every cause at once: nothing a person could act on.

Each cause's map becomes regions by one rule (:func:`hot_set`), also used by
the lab benchmark to draw an injected effect's true footprint: the map is
smoothed by the diagnosis's noise scale, the pixels above the level at which
the worst ones hold half of its sum are kept, closed and opened, and split into
connected components. An effect model whose form acts over the whole lit area
(a tone curve, a colour mix, a black level: ``EffectModel.local`` is False)
gets one region, the whole lit area, and no place is named for it; so does a
local cause (interreflection, glossy, the remainder) whose largest component
holds less than :data:`GLOBAL_SHARE` of its error or covers over half the lit
area.

Places that one modelled effect names and that hold comparable error (each at
least :data:`SAME_FINDING` of its largest's) are one region, "in N places": one
effect's light can fall in parts (the bounce light in the curve's two folds,
a highlight on both planes of the hedge), which are one thing to act on.

A share is of the error as split by cause: the sum of what each effect explains, what they leave on the
smooth parts and what they leave at pattern edges (:func:`error_split`). Two effects that explain the same
error both count it there, so it is not a share of the residual (against which a region had held 133 %);
the regions partition the split by cause and place, so their shares add up to at most 100 %, the rest being
the pattern edges' part and what scattered outside every place. With orthogonal causes the split is the residual.

Regions are ranked by that share, and described
against what the calibration alone knows: surface creases, the unlit side of a
concave edge, where the projector's mirror reflection falls (the calibrated
geometry's glossy lobe), a texture edge in the albedo, a depth step, the
projector border, a saturated white capture, the input levels and colour
channel that dominate its error, and whether it comes from sharp patterns.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..stages.calibrate import SATURATED
from .data import GapData
from .fit import SMOOTH_SIGMA
from .models import MODELS

#: Regions smaller than this share of the lit pixels are left out (scattered error).
MIN_REGION_PIXELS = 0.002
MAX_REGIONS = 6
#: A cause whose largest compact region holds less than this share of its error acts over the whole lit area.
GLOBAL_SHARE = 0.25
#: Places of one modelled effect holding at least this share of the error of its largest are one finding.
SAME_FINDING = 0.5
#: A region is described by a property of the place when at least this share of its pixels has it.
PLACE_SHARE = 0.3
#: ... and by a kind of pattern (input level, sharp edges) when its error gathers there this many times the
#: patterns' own share.
ENRICHED = 1.3
#: log-albedo change between neighbouring pixels that makes a texture edge (shading on a smooth surface
#: changes it by well under 1 % a pixel).
TEXTURE_EDGE = 0.15
#: relative depth change between neighbouring pixels that makes a depth step (an occlusion boundary, not a slope).
DEPTH_STEP = 0.05
UNEXPLAINED, LEFT_OVER, WHOLE = "unexplained", "left over", "whole lit area"
#: The remainder's part at pattern edges (sub-pixel misregistration): in the split of the error, in no region.
EDGES = "pattern edges"
#: What a region's share means, said in gap.json and the summaries.
SHARE_MEANS = ("a region's share is of the held-out squared error inside the lit area as split by cause (what each "
               "selected effect removes alone, what they leave on the smooth parts and at pattern edges), counted "
               "once per cause and place: the regions' shares add up to at most 100 %")


@dataclass
class Region:
    bbox: tuple[int, int, int, int]  # x, y, width, height in pixels of the full camera image
    share: float  # of the error as split by cause (error_split): the regions' add up to at most 1
    pixels: int
    description: str
    tags: list[str]
    cause: str = LEFT_OVER  # an effect model's name, UNEXPLAINED or LEFT_OVER
    mask: np.ndarray | None = field(default=None, repr=False)  # working-size pixels (not saved in gap.json)

    def to_dict(self) -> dict[str, Any]:
        return {"bbox": list(self.bbox), "share": round(self.share, 4), "pixels": self.pixels, "cause": self.cause,
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


def smoothed(energy: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """A per-pixel error map smoothed within the mask (normalised, so the mask's border keeps its level)."""
    m = mask.astype(np.float32)
    num = cv2.GaussianBlur(np.where(mask, energy, 0).astype(np.float32), (0, 0), SMOOTH_SIGMA)
    den = cv2.GaussianBlur(m, (0, 0), SMOOTH_SIGMA)
    return np.where(mask, num / np.maximum(den, 1e-6), 0.0)


def hot_set(energy: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The compact set that holds a map's error (see the module docstring): a boolean image.

    The set is drawn on the RMS (the root of the smoothed squared error), not on the squared error: squared, a
    peaked effect (a highlight clipped at its centre) puts half its sum in a few central pixels, and the set would
    be its core rather than the place it covers.
    """
    e = np.sqrt(np.maximum(smoothed(energy, mask), 0.0))
    if not mask.any() or float(e[mask].sum()) <= 0:
        return np.zeros_like(mask)
    hot = ((e >= _half_error_threshold(e[mask])) & mask).astype(np.uint8)
    hot = cv2.morphologyEx(hot, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    return cv2.morphologyEx(hot, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)).astype(bool) & mask


def energy_of(residuals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per-pixel squared residual, mean over patterns and channels, zero off the mask."""
    return np.where(mask, (residuals.astype(np.float64) ** 2).mean(axis=(0, 3)), 0.0)


def _error_maps(data: GapData, residuals: np.ndarray, pattern_index: list[int], *,
                causes: dict[str, np.ndarray] | None = None, lights: dict[str, np.ndarray] | None = None,
                remainder: np.ndarray | None = None, remainder_cause: str = LEFT_OVER
                ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """The error split by cause (see the module docstring): per-pixel squared error of each modelled effect (what
    it explains), of the remainder on the smooth parts (under ``remainder_cause``), and of the remainder on the
    pattern edges (placed nowhere), with the remainder itself with its edges zeroed."""
    mask = data.mask
    # What an effect explains is the change its model makes, (after − before)²: the captures' noise cancels
    # in that difference, where it would not in before² − after².
    maps = {name: energy_of(after - residuals, mask) for name, after in (causes or {}).items()}
    # A local effect is placed where its fitted model puts light, carrying what it explains: the change it makes
    # to the held-out residual gathers where the model's light is least like the albedo's, and for a highlight
    # that is its clipped core (the albedo read from white already holds the lobe everywhere else).
    for name, light in (lights or {}).items():
        own = np.where(mask, light.astype(np.float64) ** 2, 0.0)
        if name in maps and float(own.sum()) > 0:
            maps[name] = own * (float(maps[name].sum()) / float(own.sum()))
    # The remainder on the smooth parts only, as remainder.py judges it: pattern edges also hold sub-pixel
    # misregistration, which on a clean rig outweighs every effect and lies wherever the patterns have edges.
    whole = residuals if remainder is None else remainder
    edges = [data.observations[i].edges for i in pattern_index]
    left = np.stack([np.where(e[..., None], 0.0, r) if e is not None else r for r, e in zip(whole, edges)])
    maps[remainder_cause] = energy_of(left, mask)
    return maps, energy_of(whole - left, mask), left


def _shares_of(maps: dict[str, np.ndarray], edge_energy: np.ndarray, mask: np.ndarray
               ) -> tuple[dict[str, np.ndarray], float, float]:
    """Each cause's smoothed map, the error they split (the sum of all parts with the pattern edges'), and the
    edges' part of it."""
    smooth = {c: smoothed(m, mask) for c, m in maps.items()}
    edge = float(smoothed(edge_energy, mask).sum())
    return smooth, sum(float(e.sum()) for e in smooth.values()) + edge, edge


def error_split(data: GapData, residuals: np.ndarray, pattern_index: list[int], *,
                causes: dict[str, np.ndarray] | None = None, lights: dict[str, np.ndarray] | None = None,
                remainder: np.ndarray | None = None, remainder_cause: str = LEFT_OVER) -> dict[str, float]:
    """Each cause's share of the error as :func:`find_regions` splits it (same arguments), and the share of the
    remainder at pattern edges (:data:`EDGES`, placed in no region): the shares add up to 1, or are empty when
    there is no error."""
    maps, edge_energy, _ = _error_maps(data, residuals, pattern_index, causes=causes, lights=lights,
                                       remainder=remainder, remainder_cause=remainder_cause)
    smooth, total, edge = _shares_of(maps, edge_energy, data.mask)
    if total <= 0:
        return {}
    return {**{c: float(e.sum()) / total for c, e in smooth.items()}, EDGES: edge / total}


def find_regions(data: GapData, residuals: np.ndarray, full_size: tuple[int, int], pattern_index: list[int], *,
                 causes: dict[str, np.ndarray] | None = None, lights: dict[str, np.ndarray] | None = None,
                 remainder: np.ndarray | None = None, remainder_cause: str = LEFT_OVER,
                 absorbed: dict[str, np.ndarray] | None = None) -> list[Region]:
    """Compact regions of the error by cause, largest share first (see the module docstring).

    ``residuals`` is the structured held-out residual of the calibrated model (patterns ``pattern_index``);
    ``causes`` maps each modelled effect to the residual left after it alone, ``remainder`` is the residual
    after all of them (default: ``residuals``, nothing modelled), named ``remainder_cause``. ``lights`` maps a
    local effect among them to its fitted model's own light under white (h×w): where it is placed. ``absorbed``
    maps a local effect calibration absorbed (found from its inputs, not modelled) to its light likewise: it
    explains nothing, but its light is a place, and what the residual holds there is counted in it.

    A region's share is of the error as split by cause (:func:`error_split`), never of the residual alone: two
    effects that each explain the same error both count it, and against the residual a place they share had held
    133 % of it. The regions partition that split by cause and place (a whole-area region holds its cause's part
    everywhere, a place the local causes' parts there, and places are disjoint), so their shares add up to at
    most 1; what is left is the pattern edges' part and what scattered outside every place.
    """
    mask = data.mask
    maps, edge_energy, left = _error_maps(data, residuals, pattern_index, causes=causes, lights=lights,
                                          remainder=remainder, remainder_cause=remainder_cause)
    smooth, total, _ = _shares_of(maps, edge_energy, mask)
    if total <= 0:
        return []
    h, w = mask.shape
    sx, sy = full_size[0] / w, full_size[1] / h
    min_px = max(4, int(MIN_REGION_PIXELS * mask.sum()))

    def parts_of(energy: np.ndarray) -> list[np.ndarray]:
        count, labels, stats, _ = cv2.connectedComponentsWithStats(hot_set(energy, mask).astype(np.uint8),
                                                                    connectivity=8)
        return [labels == k for k in range(1, count) if stats[k, 4] >= min_px]

    place = _Place(data)

    # A region's error traits (levels, sharp edges, colour, sign) are read from the error its cause accounts for:
    # read from the whole residual, every region of the demo said "sharp pattern edges, simulation too dark", which
    # is the sub-pixel misregistration at edges that lies under every cause.
    accounted = {name: residuals - after for name, after in (causes or {}).items()}
    accounted[remainder_cause] = left

    def region(sel: np.ndarray, share: float, cause: str, note: str = "") -> Region:
        whole = sel is mask
        ys, xs = np.nonzero(sel)
        x0, y0 = int(xs.min()), int(ys.min())
        bbox = (int(x0 * sx), int(y0 * sy), int(round((xs.max() + 1 - x0) * sx)), int(round((ys.max() + 1 - y0) * sy)))
        tags, words = ([WHOLE], ["over the whole lit area"]) if whole else place.describe(sel, cause)
        t2, w2 = _error_traits(data, accounted.get(cause, residuals), sel, pattern_index)
        return Region(bbox, share, int(sel.sum()), ", ".join(words + w2) + note, tags + t2, cause, sel)

    regions, local = [], {}
    for cause, energy in maps.items():
        e = smooth[cause]
        own = float(e.sum())
        if own <= 0:
            continue
        # An effect whose form acts over the whole lit area (a tone curve, a colour mix, a black level) gets no
        # place even where its error happens to gather: on the demo the black level's brighter half was drawn
        # as a blob of 40 % of the lit area. The local ones (and the remainder) get places from the data.
        parts = parts_of(energy) if cause not in MODELS or MODELS[cause].local else []
        if (not parts or max(float(e[p].sum()) for p in parts) < GLOBAL_SHARE * own
                or max(int(p.sum()) for p in parts) > 0.5 * int(mask.sum())):
            regions.append(region(mask, own / total, cause))  # acts everywhere: no place to name
        else:
            local[cause] = (energy, e)
    # An absorbed local effect's light is a place of the weight of all the remainder (the remainder's error there
    # is counted in it); a remainder spread everywhere then keeps the rest as its whole-area region.
    rest_total = float(maps[remainder_cause].sum())
    places = [np.where(mask, light.astype(np.float64) ** 2, 0.0) for light in (absorbed or {}).values()]
    places = [q * (rest_total / float(q.sum())) for q in places if float(q.sum()) > 0 and rest_total > 0]
    spread_rest = bool(places) and remainder_cause not in local
    if spread_rest:  # counted in the places below, and over the whole lit area for what lies outside them
        local[remainder_cause] = (maps[remainder_cause], smooth[remainder_cause])
        regions = [r for r in regions if not (r.cause == remainder_cause and WHOLE in r.tags)]
    # Places are drawn where the modelled local effects act, and what they leave is counted there too: a
    # highlight the glossy model fits, with a clipped core it leaves to the remainder, is one place with two
    # shares, not two regions. The remainder gets places of its own only outside them.
    if local:
        modelled_maps = [energy for c, (energy, _) in local.items() if c != remainder_cause] + places
        sels = parts_of(sum(modelled_maps)) if modelled_maps else []
        taken = np.logical_or.reduce(sels) if sels else np.zeros_like(mask)
        if remainder_cause in local:
            rest = parts_of(np.where(taken, 0.0, local[remainder_cause][0]))
            sels += [q for q in (p & ~taken for p in rest) if int(q.sum()) >= min_px]
        named: list[tuple[np.ndarray, str, float]] = []
        for sel in sels:
            part = {c: float(e[sel].sum()) for c, (_, e) in local.items()}
            here = sum(part.values())
            if here <= 0:
                continue
            # a modelled effect that acts here names the place; the remainder does when none does (at least a
            # tenth of the error here), or when it is above the noise ("unexplained") and the largest part
            modelled = {c: v for c, v in part.items() if c != remainder_cause and v >= 0.1 * here}
            cause = max(part, key=part.get)
            if modelled and (cause != UNEXPLAINED):
                cause = max(modelled, key=modelled.get)
            named.append((sel, cause, here))
        for sel, cause, here in _one_finding_per_effect(named):
            part = {c: float(e[sel].sum()) for c, (_, e) in local.items()}
            others = [f"{c} {v / here:.0%}" for c, v in sorted(part.items(), key=lambda kv: -kv[1]) if v >= 0.1 * here]
            n = int((cv2.connectedComponentsWithStats(sel.astype(np.uint8), connectivity=8)[2][1:, 4] >= min_px).sum())
            regions.append(region(sel, here / total, cause, (f", in {n} places" if n > 1 else "")
                                  + (f"; of the error here: {', '.join(others)}" if len(others) > 1 else "")))
        if spread_rest:
            covered = np.logical_or.reduce(sels) if sels else np.zeros_like(mask)
            regions.append(region(mask, float(local[remainder_cause][1][~covered].sum()) / total, remainder_cause))
    # a remainder within the captures' noise over the whole area names nothing: it goes last
    regions.sort(key=lambda r: (r.cause == LEFT_OVER and WHOLE in r.tags, -r.share))
    return regions[:MAX_REGIONS]


def _one_finding_per_effect(named: list[tuple[np.ndarray, str, float]]) -> list[tuple[np.ndarray, str, float]]:
    """Places (mask, cause, error there) named by one modelled effect that hold comparable error (each at least
    :data:`SAME_FINDING` of its largest's), joined into one: light bouncing between the curve's folds lands in two
    bands, and the hedge's highlight falls on both planes; each is one thing to act on, and as separate places
    neither held half of it. The remainder's places are left apart: what no model explains need not be one cause.
    (The places are disjoint, so a joined place's error is the sum of its parts'.)"""
    out: list[tuple[np.ndarray, str, float]] = []
    joined: set[str] = set()
    for place in named:
        cause = place[1]
        if cause not in MODELS:
            out.append(place)
        elif cause not in joined:
            joined.add(cause)
            mine = [q for q in named if q[1] == cause]
            top = max(q[2] for q in mine)
            same = [q for q in mine if q[2] >= SAME_FINDING * top]
            out.append((np.logical_or.reduce([q[0] for q in same]), cause, sum(q[2] for q in same)))
            out += [q for q in mine if q[2] < SAME_FINDING * top]
    return out


def label_image(regions: list[Region], shape: tuple[int, int], full_size: tuple[int, int]) -> np.ndarray:
    """Region k+1's pixels (k in rank order, the first region on top) at the full camera size, 0 elsewhere."""
    lab = np.zeros(shape, np.uint8)
    for k in reversed(range(len(regions))):
        if regions[k].mask is not None:
            lab[regions[k].mask] = k + 1
    return cv2.resize(lab, full_size, interpolation=cv2.INTER_NEAREST)


class _Place:
    """What the calibration knows about each pixel's place: its maps, computed once for all regions."""

    def __init__(self, data: GapData) -> None:
        self.data = data
        mask = data.mask
        gain = data.gain.mean(axis=2)
        log_gain = np.log(np.maximum(gain, 1e-4)).astype(np.float32)
        grad = np.hypot(cv2.Sobel(log_gain, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(log_gain, cv2.CV_32F, 0, 1, ksize=3))
        inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        # Sobel's 3×3 kernel weighs a one-pixel step 4×; a crease's shading is a surface property, not texture
        self.texture = _near(inner & (grad / 4 > TEXTURE_EDGE) & (data.crease < 0.3))
        valid = np.isfinite(data.points).all(axis=2)
        depth = np.sqrt((np.where(valid[..., None], data.points, 0.0) ** 2).sum(axis=2)).astype(np.float32)
        dstep = np.maximum(np.abs(np.diff(depth, axis=0, append=depth[-1:])),
                           np.abs(np.diff(depth, axis=1, append=depth[:, -1:])))
        ok = valid & np.roll(valid, -1, 0) & np.roll(valid, -1, 1)
        self.depth_step = _near(ok & (dstep > DEPTH_STEP * np.maximum(depth, 1e-6)))
        lobes = data.white.glossy
        if lobes:
            lobe = lobes[sorted(lobes)[len(lobes) // 2]].mean(axis=2)
            self.mirror = hot_set(lobe.astype(np.float64) ** 2, mask)
        else:
            self.mirror = np.zeros_like(mask)

    def describe(self, sel: np.ndarray, cause: str) -> tuple[list[str], list[str]]:
        data = self.data
        tags: list[str] = []
        words: list[str] = []
        # on a crease, or holding one (a region around a crease is wider than the crease line)
        if float(data.crease[sel].mean()) > PLACE_SHARE or int((data.crease[sel] > 0.5).sum()) >= max(
                3, 0.01 * int(sel.sum())):
            tags.append("crease")
            gain = data.gain.mean(axis=2)
            near = cv2.dilate(sel.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
            if float(gain[sel].mean()) < 0.8 * float(gain[near & data.mask].mean()):
                tags.append("unlit side of a concave edge")
                words.append("on the darker side of a surface crease")
            else:
                words.append("near a surface crease")
        if float(self.mirror[sel].mean()) > 0.5:
            tags.append("mirror reflection")
            # a property of the geometry; it is a highlight only if the surface is glossy
            words.append("where the projector's mirror reflection falls"
                         + (" (a highlight, on a glossy surface)" if cause == "glossy" else ""))
        if float(self.texture[sel].mean()) > PLACE_SHARE:
            tags.append("texture edge")
            words.append("on an edge in the surface's paint")
        if float(self.depth_step[sel].mean()) > PLACE_SHARE:
            tags.append("depth step")
            words.append("at a depth step (an object's outline)")
        iw, ih = data.projector.input_size
        c = data.corr[sel]
        border = np.minimum.reduce([c[:, 0], c[:, 1], iw - 1 - c[:, 0], ih - 1 - c[:, 1]])
        if float(np.median(border)) < 0.05 * min(iw, ih):
            tags.append("projector border")
            words.append("near the border of the projector input")
        if float((data.white.capture[sel] >= SATURATED).any(axis=1).mean()) > PLACE_SHARE:
            # The albedo came from the white capture; where that clipped it is a lower bound (stages.calibrate).
            tags.append("saturated white")
            words.append("where the white capture is saturated (a highlight or too long an exposure: the albedo "
                         "read there is too dark)")
        return tags, words


def _near(edge: np.ndarray) -> np.ndarray:
    """Pixels on or next to a one-pixel-wide edge (a region's boundary rarely sits exactly on it)."""
    return cv2.dilate(edge.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)


def _error_traits(data: GapData, residuals: np.ndarray, sel: np.ndarray, pattern_index: list[int]
                  ) -> tuple[list[str], list[str]]:
    """The input levels, pattern kind, colour channel and sign that dominate a region's error."""
    tags: list[str] = []
    words: list[str] = []
    obs = [data.observations[i] for i in pattern_index]
    per = np.array([float((residuals[k][sel] ** 2).mean()) for k in range(len(obs))])
    levels = np.array([float(o.sampled[sel].mean()) for o in obs])
    if per.sum() > 0:
        w = per / per.sum()
        # A level names the error only where it gathers more than the patterns' own mix puts there: an error alike
        # at every level (a room light's) had read "in mid input levels" because most patterns are mid grey.
        bands = {"dark": levels < 0.2, "bright": levels > 0.8, "mid": (levels >= 0.2) & (levels <= 0.8)}
        for band, least in (("dark", 0.5), ("bright", 0.5), ("mid", 0.6)):
            there = float(w[bands[band]].sum())
            if there > max(least, ENRICHED * float(bands[band].mean())):
                tags.append(f"{band} input")
                words.append(f"in {band} input levels")
                break
        fine = float(w[[o.fine for o in obs]].sum())
        share_fine = sum(o.fine for o in obs) / len(obs)
        if fine > max(0.6, ENRICHED * share_fine):
            tags.append("high spatial frequency")
            words.append("at high spatial frequency (sharp pattern edges)")
    ch = (residuals[:, sel] ** 2).mean(axis=(0, 1))
    if ch.sum() > 0 and float(ch.max() / ch.sum()) > 0.5:
        name = "rgb"[int(ch.argmax())]
        tags.append(f"channel {name}")
        words.append(f"mostly in the {dict(r='red', g='green', b='blue')[name]} channel")
    signed = float(residuals[:, sel].mean())
    words.append("simulation too bright" if signed > 0 else "simulation too dark")
    return tags, words
