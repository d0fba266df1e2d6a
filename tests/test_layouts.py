"""The lab's projector layouts as geometry (no Blender, no render): the grid's shape, its footprints overlapping
across and down and covering the camera's view, every projector lighting the surface; side by side unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from procam.addon.errors import LabError
from procam.addon.lab.layouts import LAYOUTS, footprint, footprint_height, grid_shape, lay_out
from procam.addon.lab.truth import make_truth
from procam.addon.rig.model import Rig
from procam.addon.stages.transport import camera_to_input_of

CAMERA, PROJECTOR = (64, 48), (192, 108)


def _cover(truth) -> np.ndarray:
    """(N, H, W) the camera pixels each projector lights (ray cast through the true rig and surface)."""
    return np.asarray([camera_to_input_of(Rig(truth.rig.camera, p), truth.surface, CAMERA)[1]
                       for p in truth.rig.projectors])


def test_grid_shape_is_the_most_nearly_square_factorisation():
    assert [grid_shape(n) for n in range(1, 9)] == [(1, 1), (1, 2), (1, 3), (2, 2), (1, 5), (2, 3), (1, 7), (2, 4)]
    assert "grid" in LAYOUTS


@pytest.mark.parametrize("surface", ["curve", "plane"])
def test_a_two_by_two_grid_overlaps_across_and_down_and_covers_the_camera_s_view(surface):
    overlap = 0.2
    truth = make_truth(surface, camera_size=CAMERA, projector_size=PROJECTOR, projectors=4, layout="grid",
                       overlap=overlap)
    projectors = truth.rig.projectors
    z = float(np.median(truth.surface.vertices[:, 2]))
    centres = np.array([footprint(p, z)[0] for p in projectors])
    width, height = footprint(projectors[0], z)[1], footprint_height(projectors[0], z)
    # row-major 2×2: 1 and 2 on the top row (rig y down), 3 and 4 below; columns line up
    np.testing.assert_allclose(centres[0, 1], centres[1, 1], atol=1e-3)
    np.testing.assert_allclose(centres[0, 0], centres[2, 0], atol=1e-3)
    assert centres[2, 1] > centres[0, 1] and centres[1, 0] > centres[0, 0]
    # neighbours overlap by the fraction asked, across and down (footprints reckoned on the plane)
    assert centres[1, 0] - centres[0, 0] == pytest.approx((1 - overlap) * width, rel=0.02)
    assert centres[2, 1] - centres[0, 1] == pytest.approx((1 - overlap) * height, rel=0.05)
    # every projector is as bright as the template on its footprint: the same lens, closer in, scaled together
    assert len({round(p.intensity / footprint(p, z)[1] ** -2, 6) for p in projectors}) == 1
    cover = _cover(truth)
    lit = cover.sum(axis=(1, 2))
    assert lit.min() > 0.1 * CAMERA[0] * CAMERA[1]  # every projector lights the surface in the camera's view
    union, count = cover.any(axis=0), cover.sum(axis=0)
    ys, xs = np.nonzero(union)
    # the grid spans most of the camera's view in both directions (nine tenths of what camera and surface offer)
    assert xs.max() - xs.min() > 0.6 * CAMERA[0] and ys.max() - ys.min() > 0.6 * CAMERA[1]
    # the four footprints meet in the middle: all four light it, and pairs light the strips between
    cy, cx = int(np.mean(ys)), int(np.mean(xs))
    assert count[cy - 1:cy + 2, cx - 1:cx + 2].min() == 4
    assert (count >= 2).sum() > 0.05 * union.sum()


def test_side_by_side_is_a_one_row_grid_and_a_prime_count_makes_one_row():
    truth = make_truth("curve", camera_size=CAMERA, projector_size=PROJECTOR)
    template, camera, surface = truth.rig.projector, truth.rig.camera, truth.surface
    z = float(np.median(surface.vertices[:, 2]))
    row = lay_out(template, camera, surface, 4, "side-by-side", 0.2)
    centres = np.array([footprint(p, z)[0] for p in row])
    np.testing.assert_allclose(centres[:, 1], centres[0, 1], atol=1e-9)  # one row, the template's height
    np.testing.assert_allclose(np.diff(centres[:, 0]), 0.8 * footprint(row[0], z)[1], rtol=1e-6)
    three_grid = lay_out(template, camera, surface, 3, "grid", 0.2)
    three_row = lay_out(template, camera, surface, 3, "side-by-side", 0.2)
    for a, b in zip(three_grid, three_row):
        np.testing.assert_allclose(a.camera_from_projector, b.camera_from_projector)
    assert lay_out(template, camera, surface, 1, "grid") == (template,)
    with pytest.raises(LabError, match="side-by-side, stacked, grid"):
        lay_out(template, camera, surface, 4, "ring")
