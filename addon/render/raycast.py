"""Exact ray casting against the surface with Mitsuba's BVH: depth maps and first hits.

Used where a true geometric answer is needed (the lab's true depth image,
evaluation); numpy's ``surface.mesh.ray_intersect`` is fine for a few hundred
rays, this is for whole images.
"""

from __future__ import annotations

import numpy as np

from ..rig.model import Intrinsics
from ..surface.mesh import SurfaceMesh
from .backend import mitsuba
from .scene import surface_mesh


def first_hits(surface: SurfaceMesh, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Distance along each (not necessarily unit) direction to the surface; ``inf`` where it misses."""
    mi = mitsuba()
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    o = np.broadcast_to(np.asarray(origins, dtype=np.float64), d.shape)
    norm = np.linalg.norm(d, axis=1)
    scene = mi.load_dict({"type": "scene", "surface": surface_mesh(mi, surface)})
    ray = mi.Ray3f(mi.Point3f(*(o.T.astype(np.float32))), mi.Vector3f(*((d / norm[:, None]).T.astype(np.float32))))
    si = scene.ray_intersect(ray)
    t = np.array(si.t, dtype=np.float64)
    hit = np.array(si.is_valid(), dtype=bool)
    return np.where(hit, t / norm, np.inf)


def depth_map(surface: SurfaceMesh, camera: Intrinsics) -> np.ndarray:
    """Depth along the camera's z axis at each pixel centre (metres, NaN where no surface)."""
    w, h = camera.size
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    rays = camera.rays(np.stack([xs.ravel(), ys.ravel()], axis=1))  # z = 1, so distance = depth
    t = first_hits(surface, np.zeros(3), rays)
    return np.where(np.isfinite(t), t, np.nan).reshape(h, w).astype(np.float32)
