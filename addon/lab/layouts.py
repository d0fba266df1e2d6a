"""Where the lab puts several projectors: side by side or in a grid with overlapping footprints, or stacked.

Pure geometry, no Blender. A layout starts from one template projector (the
demo projector, its lens and pose) and the surface, and gives N projectors of
the same lens:

* ``side-by-side``: footprints in a row across the surface, neighbours
  overlapping by ``overlap`` of a footprint's width, the row together spanning
  nine tenths of what both the camera and the surface offer. Each projector is
  the template moved and brought closer (a homothety about its footprint's
  centre), its intensity scaled with the square of the distance so that every
  footprint is as bright as the template's.
* ``grid``: footprints in rows × columns (the most nearly square factorisation of N
  with at least as many columns as rows: 2×2 for 4, 2×3 for 6, 2×4 for 8; a prime N
  is one row, as side by side), neighbours overlapping by ``overlap`` of a footprint's
  width across and of its height down, the grid spanning nine tenths of what both the
  camera and the surface offer in whichever direction is tighter (one scale for both
  directions, so footprints keep the template's shape); moved and brightened as side
  by side.
* ``stacked``: all projectors light the template's area from positions 12 cm
  apart vertically (the first one is the template), each turned so that its
  image centre lands where the template's does: the footprints nearly
  coincide, as for stacking projectors for brightness.

Footprints are reckoned on the plane through the template's image centre
facing the camera; on a curved surface they are approximate, which is all a
lab layout needs.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import LabError
from ..rig.model import Camera, Projector
from ..surface.mesh import SurfaceMesh

LAYOUTS = ("side-by-side", "stacked", "grid")
#: The largest number of projectors the lab lays out (the issue's two to eight).
MAX_PROJECTORS = 8
#: Vertical distance between stacked projectors (metres).
STACK_STEP = 0.12
#: Share of the span both the camera and the surface offer that a side-by-side row covers.
SPAN_SHARE = 0.9


def _input_rays(projector: Projector) -> np.ndarray:
    """Rig-frame directions through the input's centre, left-edge middle and right-edge middle."""
    (x0, y0), (w, h) = projector.input_offset, projector.input_size
    px = np.array([[x0 + w / 2, y0 + h / 2], [x0, y0 + h / 2], [x0 + w, y0 + h / 2]], dtype=float)
    return projector.intrinsics.rays(px) @ projector.camera_from_projector[:3, :3].T


def _on_plane(origin: np.ndarray, rays: np.ndarray, z: float) -> np.ndarray:
    """Where rays from ``origin`` meet the plane of depth ``z``; a LabError when one runs away from it."""
    t = (z - origin[2]) / rays[:, 2]
    if not np.all(np.isfinite(t)) or np.any(t <= 0):
        raise LabError("the projector's image does not land in front of the camera; a layout needs a projector "
                       "that lights the surface")
    return origin + t[:, None] * rays


def footprint(projector: Projector, z: float) -> tuple[np.ndarray, float]:
    """The centre of the projector input's footprint on the plane of depth ``z``, and its width there (metres)."""
    centre, left, right = _on_plane(projector.position, _input_rays(projector), z)
    return centre, float(np.linalg.norm(right - left))


def footprint_height(projector: Projector, z: float) -> float:
    """The height of the projector input's footprint on the plane of depth ``z`` (metres), through its centre."""
    (x0, y0), (w, h) = projector.input_offset, projector.input_size
    px = np.array([[x0 + w / 2, y0], [x0 + w / 2, y0 + h]], dtype=float)
    top, bottom = _on_plane(projector.position, projector.intrinsics.rays(px)
                            @ projector.camera_from_projector[:3, :3].T, z)
    return float(np.linalg.norm(bottom - top))


def grid_shape(count: int) -> tuple[int, int]:
    """(rows, columns) of a grid of ``count`` projectors: the most nearly square factorisation, columns ≥ rows."""
    rows = max(r for r in range(1, math.isqrt(count) + 1) if count % r == 0)
    return rows, count // rows


def _span(lo_view: float, hi_view: float, coords: np.ndarray, what: str) -> tuple[float, float]:
    """The interval of the plane both the camera's view and the surface's extent cover along one axis."""
    lo, hi = max(lo_view, float(coords.min())), min(hi_view, float(coords.max()))
    if hi <= lo:
        raise LabError(f"the camera does not see the surface{what}, so the lab cannot lay projectors out on it")
    return lo, hi


def _turn(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` to unit vector ``b``."""
    v, c = np.cross(a, b), float(a @ b)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def lay_out(template: Projector, camera: Camera, surface: SurfaceMesh, count: int, layout: str = "side-by-side",
            overlap: float = 0.2) -> tuple[Projector, ...]:
    """``count`` projectors of the template's lens in ``layout`` (see the module's doc); one: the template."""
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or not 1 <= count <= MAX_PROJECTORS:
        raise LabError(f"the lab lays out 1 to {MAX_PROJECTORS} projectors, got {count!r}")
    if layout not in LAYOUTS:
        raise LabError(f"the projector layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    if not (isinstance(overlap, (int, float)) and math.isfinite(overlap) and 0.0 <= overlap < 1.0):
        raise LabError(f"the overlap must be a fraction of a footprint's width from 0 to below 1, got {overlap!r}")
    if count == 1:
        return (template,)
    z = float(np.median(surface.vertices[:, 2]))  # the surface's typical depth: footprints are reckoned there
    centre, width = footprint(template, z)
    if layout == "stacked":
        out = [template]
        for i in range(1, count):
            pos = template.position + np.array([0.0, -STACK_STEP * i, 0.0])  # rig y is down: stacked above
            moved = template.camera_from_projector.copy()
            moved[:3, 3] = pos
            now = template.with_pose(moved)
            ray = _input_rays(now)[0]
            want = centre - pos
            moved[:3, :3] = _turn(ray / np.linalg.norm(ray), want / np.linalg.norm(want)) @ moved[:3, :3]
            out.append(template.with_pose(moved))
        return tuple(out)
    k = camera.intrinsics
    lo, hi = _span(-k.cx / k.fx * z, (k.width - k.cx) / k.fx * z, surface.vertices[:, 0], "")
    rows, cols = grid_shape(count) if layout == "grid" else (1, count)
    span = SPAN_SHARE * (hi - lo)
    each = span / (cols - (cols - 1) * overlap)  # a footprint's width that fills the span across
    scale = each / width
    mid_y = centre[1]
    if rows > 1:  # the grid's height may be the tighter bound: one scale for both directions
        top, bottom = _span(-k.cy / k.fy * z, (k.height - k.cy) / k.fy * z, surface.vertices[:, 1],
                            " from top to bottom")
        height = footprint_height(template, z)
        scale = min(scale, SPAN_SHARE * (bottom - top) / (rows - (rows - 1) * overlap) / height)
        each, mid_y = scale * width, (top + bottom) / 2
        span = each * (cols - (cols - 1) * overlap)
        step_y = (1.0 - overlap) * scale * height
    out = []
    for i in range(count):
        row, col = divmod(i, cols)
        x = (lo + hi) / 2 - span / 2 + each / 2 + col * (1.0 - overlap) * each
        y = mid_y + (row - (rows - 1) / 2) * step_y if rows > 1 else centre[1]
        target = np.array([x, y, z])
        pose = template.camera_from_projector.copy()
        pose[:3, 3] = target + scale * (template.position - centre)
        out.append(Projector(template.intrinsics, pose, template.intensity * scale ** 2, template.input_size,
                             template.input_offset, template.lens_distortion))
    return tuple(out)


__all__ = ["LAYOUTS", "MAX_PROJECTORS", "footprint", "footprint_height", "grid_shape", "lay_out"]
