"""The projector's achievable range: the show's gain and offset (``--range auto``) and the range ceiling."""

from __future__ import annotations

import math

import numpy as np
import pytest

from procam.addon.stages.display_area import DisplayArea
from procam.addon.stages.range import (CEILING_CAP, RangeError, RangeMap, fit_bright, fit_range, parse_range,
                                       range_ceiling)


def _clipped_share(targets, black, white, r: RangeMap) -> float:
    mapped = [r.apply(t) for t in targets]
    out = sum(int(np.count_nonzero((m < black - 1e-6) | (m > white + 1e-6))) for m in mapped)
    return out / sum(m.size for m in mapped)


def test_bright_targets_are_brought_inside_with_the_largest_gain():
    rng = np.random.default_rng(0)
    black = np.full((40, 50, 3), 0.05, np.float32)
    white = (0.6 + 0.05 * rng.random((40, 50, 3))).astype(np.float32)
    targets = [rng.random((40, 50, 3)).astype(np.float32) for _ in range(3)]
    r = fit_range(targets, [black] * 3, [white] * 3)
    assert _clipped_share(targets, black, white, r) <= 0.0101 and r.clipped_share <= 0.0101
    # The widest [o, g + o] inside [0.05, 0.6] holds g = 0.55; 1 % clipped buys a little more.
    assert 0.54 < r.gain < 0.62 and 0.0 < r.offset < 0.08
    # A gain 5 % larger clips more than the rule allows, whatever the offset.
    bigger = r.gain * 1.05
    best = min(_clipped_share(targets, black, white, RangeMap(bigger, o)) for o in np.linspace(-0.1, 0.2, 301))
    assert best > 0.01


def test_targets_that_fit_are_left_alone_and_a_dark_surface_is_refused():
    black, white = np.full((10, 10, 3), 0.02, np.float32), np.full((10, 10, 3), 0.9, np.float32)
    t = np.full((10, 10, 3), 0.5, np.float32)
    r = fit_range([t], [black], [white])
    assert (r.gain, r.offset) == (1.0, 0.0) and "fit" in r.rule
    dead = np.full((10, 10, 3), 0.021, np.float32)  # white barely above black
    with pytest.raises(RangeError, match="barely above its black"):
        fit_range([np.linspace(0, 1, 300, dtype=np.float32).reshape(10, 10, 3)], [black], [dead])


def test_parse_and_record():
    assert parse_range("auto") == "auto" and parse_range("None") == "none"
    assert parse_range("0.8,0.02") == RangeMap(0.8, 0.02)
    assert parse_range("bright") == "bright:5" and parse_range("Bright:2.5") == "bright:2.5"
    for bad in ("brighter", "bright:0", "bright:x", "0,0.1", "1,2", "nan,0"):
        with pytest.raises(RangeError, match="--range"):
            parse_range(bad)
    r = RangeMap(0.75, 0.031, "auto: x", 0.004)
    assert RangeMap.from_dict(r.to_dict()) == r and RangeMap.from_dict(None) is None


def test_range_ceiling():
    black, white = np.full((4, 4, 3), 0.1, np.float32), np.full((4, 4, 3), 0.5, np.float32)
    assert range_ceiling(np.full((4, 4, 3), 0.3, np.float32), black, white) == CEILING_CAP
    t = np.full((4, 4, 3), 0.3, np.float32)
    t[0] = 0.9  # a quarter of the pixels 0.4 above white
    assert range_ceiling(t, black, white) == pytest.approx(10 * math.log10(1 / (0.25 * 0.4 ** 2)), abs=1e-4)


def test_the_noise_ceiling_adds_the_cameras_noise_to_what_the_range_clips():
    from procam.addon.stages.range import capture_noise_mse, noise_ceiling

    rng = np.random.default_rng(0)
    clean = rng.uniform(0.2, 0.6, (64, 64, 3))
    shots = [clean + rng.normal(0, 0.01, clean.shape) for _ in range(2)]
    assert capture_noise_mse(*shots) == pytest.approx(0.01 ** 2, rel=0.05)
    black, white = np.full((4, 4, 3), 0.1), np.full((4, 4, 3), 0.5)
    inside = np.full((4, 4, 3), 0.3)
    assert noise_ceiling(inside, black, white, 1e-4) == pytest.approx(40.0)
    assert noise_ceiling(inside, black, white, 0.0) == CEILING_CAP == range_ceiling(inside, black, white)
    t = inside.copy()
    t[0] = 0.9
    assert noise_ceiling(t, black, white, 1e-4) == pytest.approx(10 * math.log10(1 / (0.25 * 0.4 ** 2 + 1e-4)))


def test_the_gap_to_the_ceiling_is_split_by_whether_the_input_could_give_more():
    from procam.addon.stages.range import ceiling_gap_at_limit

    black, white = np.full((2, 2, 3), 0.02), np.full((2, 2, 3), 0.8)
    target = np.full((2, 2, 3), 0.5)
    target[0, 0] = 0.95  # above white: the ceiling is white there
    capture = target.copy()
    capture[0, 0] = 0.7  # 0.1 short of white where the input is at full: the projector's limit
    capture[1, 1] = 0.45  # 0.05 short where the input could still rise: the solver's
    seen = np.full((2, 2, 3), 0.5)
    seen[0, 0] = 1.0
    share = ceiling_gap_at_limit(target, capture, black, white, seen)
    # excess at (0,0): 0.25² − 0.15² = 0.04 per channel; at (1,1): 0.05² = 0.0025
    assert share == pytest.approx(0.04 / 0.0425)
    assert ceiling_gap_at_limit(target, np.clip(target, black, white), black, white, seen) is None


def _dark_corner_case(seed: int = 0):
    """A 160×120 camera whose display area (140×100) has dark paint in one corner (white 0.12 there, 0.85
    elsewhere) and six targets of values all over [0, 1]."""
    rng = np.random.default_rng(seed)
    area = DisplayArea(10, 10, 140, 100)
    white = np.full((100, 140, 3), 0.85, np.float32)
    white[:30, :35] = 0.12
    black = np.full((100, 140, 3), 0.02, np.float32)
    targets = [rng.random((100, 140, 3)).astype(np.float32) for _ in range(6)]
    return area, black, white, targets


def test_bright_dims_only_near_the_dark_paint_and_keeps_the_show_bright():
    """auto holds the whole show to the dark corner (gain ≈ 0.1); bright keeps the gain at 1 away from it, changes
    it no faster than its limit per degree, clips about 1 % of each cell's values, and says the brightness kept."""
    area, black, white, targets = _dark_corner_case()
    n = len(targets)
    auto = fit_range(targets, [black] * n, [white] * n)
    dpp = 0.25  # degrees per camera pixel: 1 / (fx = 229 px) in radians
    bright = fit_bright(targets, [black] * n, [white] * n, [area] * n, (160, 120), dpp)
    assert auto.gain < 0.15 and auto.to_dict()["brightness_kept"] == pytest.approx(auto.gain + auto.offset, abs=1e-4)
    g = bright.field.on(area)[..., 0]
    assert g.max() <= 1.0 + 1e-6 and g.min() >= 0.8 * auto.gain  # auto spends its 1 % all in the corner
    assert g[:30, :35].mean() < 0.2  # the dark paint is dimmed as much as auto dims everything ...
    assert g[-20:, -40:].min() > 2.5 * auto.gain  # ... and 20° away from it the gain has risen 2.6 times
    assert bright.brightness > 1.6 * (auto.gain + auto.offset)  # 0.24 against 0.135
    assert bright.brightness == pytest.approx(float(g.mean()) + bright.offset, abs=1e-6)
    # the field's relative change: at most the limit (5 % per degree) between neighbouring camera pixels
    slope = max(np.abs(np.diff(np.log(g), axis=a)).max() for a in (0, 1)) / dpp
    assert slope <= math.log1p(0.05) * 1.05
    mapped = [bright.apply(t, area) for t in targets]
    clipped = np.mean([np.mean((m > white + 1e-6) | (m < black - 1e-6)) for m in mapped])
    assert clipped == pytest.approx(bright.clipped_share, abs=1e-4) and clipped < 0.01
    # read back through the map, a capture equal to the mapped target is the target
    assert np.allclose(bright.unmap(mapped[0], area), targets[0], atol=1e-5)
    # a stricter limit dims more of the area
    strict = fit_bright(targets, [black] * n, [white] * n, [area] * n, (160, 120), dpp, per_degree=0.01)
    assert strict.brightness < bright.brightness


def test_bright_leaves_fitting_targets_alone_and_is_recorded_and_read_back():
    area, black, white, targets = _dark_corner_case()
    inside = [np.clip(t, 0.05, 0.1) for t in targets]
    r = fit_bright(inside, [black] * 6, [white] * 6, [area] * 6, (160, 120), 0.25)
    assert (r.gain, r.offset, r.field, r.brightness) == (1.0, 0.0, None, 1.0)
    r = fit_bright(targets, [black] * 6, [white] * 6, [area] * 6, (160, 120), 0.25)
    doc = r.to_dict()
    assert doc["rule"].startswith("bright") and doc["field"]["per_degree"] == 0.05
    back = RangeMap.from_dict(doc)
    assert back.brightness == doc["brightness_kept"]
    assert np.allclose(back.apply(targets[1], area), r.apply(targets[1], area), atol=1e-3)
    with pytest.raises(RangeError, match="display area"):
        r.apply(targets[1])
    doc["field"]["cells"][0][0] = 1.5  # a gain above 1 is not one this rule writes
    with pytest.raises(RangeError, match="compensate again"):
        RangeMap.from_dict(doc)
