"""Issue 50: the light outside the display area (spill) and each projector's share of the area."""

from __future__ import annotations

import numpy as np
import pytest

from procam.addon.stages.display_area import DisplayArea, area_inside
from procam.addon.stages.spill import guard_band, outside_mask, spill, spill_text, summarise


def _scene(level: float = 0.4) -> tuple[np.ndarray, np.ndarray, DisplayArea, np.ndarray]:
    """A 160×120 camera: the projector reaches x 20–140, the area is 60×60 at 50,30, the picture ``level``."""
    reach = np.zeros((120, 160), bool)
    reach[10:110, 20:140] = True
    area = DisplayArea(50, 30, 60, 60)
    black = np.full((120, 160, 3), 0.05, np.float32)
    capture = black.copy()
    capture[area.slices] += level
    return capture, black, area, reach


def test_outside_is_the_reach_beyond_the_guard_band():
    _, _, area, reach = _scene()
    out = outside_mask(reach, area, guard=2)
    assert not out[:, :20].any() and not out[28:92, 48:112].any()
    assert out[27, 60] and out[60, 47] and out[12, 22]
    assert guard_band(160) == 2 and guard_band(640) == 10


def test_a_dark_surround_spills_nothing_and_a_lit_block_is_measured_against_the_picture():
    capture, black, area, reach = _scene()
    fig = spill(capture, black, area, reach)
    assert fig["spill_mean"] == pytest.approx(0.0, abs=1e-6) and fig["spill_p995"] == pytest.approx(0.0, abs=1e-6)
    assert fig["picture_level"] == pytest.approx(0.4, abs=1e-5)
    # Light next to the area's edge (inside the guard band) is the edge's blur, not spill.
    capture[area.y - 1, area.x:area.x + area.width] += 0.3
    assert spill(capture, black, area, reach)["spill_mean"] == pytest.approx(0.0, abs=1e-6)
    # A block lit at the picture's level where the projector reaches: the 99.5th pixel reads 100 %.
    capture[12:40, 22:45] += 0.4
    fig = spill(capture, black, area, reach)
    outside = outside_mask(reach, area).sum()
    assert fig["spill_mean"] == pytest.approx(28 * 23 / outside, rel=1e-3)
    assert fig["spill_p995"] == pytest.approx(1.0, abs=1e-4)
    # Light where no projector reaches (the room) is not the projection's.
    capture2, *_ = _scene()
    capture2[:, :15] += 0.5
    assert spill(capture2, black, area, reach)["spill_mean"] == pytest.approx(0.0, abs=1e-6)


def test_a_repeat_capture_is_averaged_in_and_a_black_picture_gives_no_share():
    capture, black, area, reach = _scene()
    again = capture.copy()
    capture[12:40, 22:45] += 0.2
    assert spill(capture, black, area, reach, again=again)["spill_p995"] == pytest.approx(0.25, abs=1e-4)
    dark = spill(black, black, area, reach)
    assert dark["spill_mean"] is None and dark["spill_p995"] is None


def test_the_summary_means_over_targets_and_the_text_says_the_shares():
    rows = [{"spill_mean": 0.01, "spill_p995": 0.2, "uncompensated": {"spill_mean": 0.02, "spill_p995": 0.3}},
            {"spill_mean": 0.03, "spill_p995": 0.1, "uncompensated": {"spill_mean": 0.04, "spill_p995": 0.5}}]
    s = summarise(rows, 160)
    assert s == {"mean": 0.02, "p995": 0.15, "worst_p995": 0.2, "uncompensated_mean": 0.03,
                 "uncompensated_p995": 0.4, "guard_px": 2}
    assert summarise([], 160) is None
    assert spill_text(0.012, 0.18, 0.02, 0.3) == ("spill outside the area: mean 1.2 %, 99.5th pixel 18.0 % of the "
                                                  "picture's level (uncompensated 2.0 %, 30.0 %)")


def test_the_area_of_two_projectors_side_by_side_spans_both_and_says_each_ones_share():
    """The automatic area of a square target lies in the union of the footprints, across the overlap, and each
    projector's share of it is recorded and said."""
    from procam.addon.steps.compensate import _summary
    from procam.addon.steps.projectors import area_shares, shares_text

    cover = np.zeros((2, 120, 160), bool)
    cover[0, 30:90, 10:90] = True
    cover[1, 30:90, 70:150] = True
    area = area_inside(cover.any(axis=0), 1.0, margin_px=2)
    shares = area_shares(cover, area)
    assert area.width > 50 and min(shares) > 0.35 and sum(shares) >= 1.0
    assert shares_text([0.61, 0.65]) == "projector 1 lights 61 %, projector 2 65 % of the area"
    doc = {"mode": "open-loop", "projectors": [{}, {}], "targets": [
        {"name": "a", "status": "done", "psnr_simulated_start": 20.0, "psnr_simulated": 25.0, "seconds": 1.0,
         "mode": "open-loop", "area_shares": [0.61, 0.65],
         "projectors": [{"share": 0.5}, {"share": 0.5}]}]}
    line = _summary(None, doc).lines[0]  # type: ignore[arg-type]
    assert "projector 1 lights 61 %, projector 2 65 % of the area" in line
