"""The projector's achievable range: the show's gain and offset (``--range auto``) and the range ceiling."""

from __future__ import annotations

import math

import numpy as np
import pytest

from procam.addon.stages.range import (CEILING_CAP, RangeError, RangeMap, fit_range, parse_range,
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
    for bad in ("bright", "0,0.1", "1,2", "nan,0"):
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
