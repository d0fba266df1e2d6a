"""Built-in projection surfaces like the paper's: plane, curve, vertical edge, horizontal edge.

Each is a textured grid mesh about ``distance`` metres in front of the camera,
facing it, with a coloured albedo pattern (soft colour blobs over stripes) so
that photometric compensation has something to undo.
"""

from __future__ import annotations

import numpy as np

from ..errors import SurfaceError
from .mesh import SurfaceMesh

SHAPES = ("plane", "curve", "vedge", "hedge")


def albedo_pattern(size: int = 512, seed: int = 0) -> np.ndarray:
    """A coloured, smooth-plus-stripes albedo in [0.25, 0.95] (H×W×3, float32)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    img = np.full((size, size, 3), 0.8, dtype=np.float64)
    for _ in range(6):
        cx, cy, r = rng.uniform(0.1, 0.9), rng.uniform(0.1, 0.9), rng.uniform(0.08, 0.22)
        colour = rng.uniform(0.3, 1.0, size=3)
        w = np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * r * r))[..., None]
        img = img * (1 - 0.7 * w) + 0.7 * w * colour
    stripes = 0.5 + 0.5 * np.sign(np.sin(2 * np.pi * 5 * (x + 0.3 * y)))
    img *= (0.85 + 0.15 * stripes)[..., None]
    return np.clip(img, 0.25, 0.95).astype(np.float32)


def _grid(nx: int, ny: int) -> tuple[np.ndarray, np.ndarray]:
    """UVs of an (nx+1)×(ny+1) vertex grid and its triangles (u right, v up)."""
    u, v = np.meshgrid(np.linspace(0, 1, nx + 1), np.linspace(0, 1, ny + 1))
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    idx = np.arange((nx + 1) * (ny + 1)).reshape(ny + 1, nx + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return uv, faces


def builtin_surface(name: str, *, distance: float = 1.6, width: float = 1.6, height: float = 1.2,
                    depth: float = 0.25, resolution: int = 48, seed: int = 0,
                    texture_size: int = 512) -> SurfaceMesh:
    """A built-in surface in the rig frame (camera at origin looking +z, y down).

    ``depth`` is how far the curve bulges or the edge recedes (metres).
    ``plane``: flat, facing the camera. ``curve``: a cylinder section with a
    vertical axis, concave towards the camera. ``vedge``: two planes meeting at
    a vertical crease that points away from the camera (a concave corner).
    ``hedge``: the same with a horizontal crease.
    """
    if name not in SHAPES:
        raise SurfaceError(f"unknown surface {name!r}; choose one of {', '.join(SHAPES)} or give a mesh file")
    uv, faces = _grid(resolution, resolution)
    x = (uv[:, 0] - 0.5) * width
    y = (0.5 - uv[:, 1]) * height  # v up = rig y down negated
    if name == "plane":
        z = np.full_like(x, distance)
    elif name == "curve":
        z = distance + depth * (1 - (2 * x / width) ** 2)
    elif name == "vedge":
        z = distance + depth * (1 - np.abs(2 * x / width))
    else:
        z = distance + depth * (1 - np.abs(2 * y / height))
    verts = np.stack([x, y, z], axis=1)
    # Winding: make normals face the camera (−z).
    mesh = SurfaceMesh(verts, faces, uv, albedo_pattern(texture_size, seed), name=name)
    if np.mean(mesh.face_normals()[:, 2]) > 0:
        mesh = SurfaceMesh(verts, faces[:, ::-1].copy(), uv, mesh.albedo, name=name)
    return mesh
