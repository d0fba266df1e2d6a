"""The textured triangle mesh that every renderer and stage shares.

Vertices are in the rig frame (metres). The diffuse albedo is an image
(float32, linear, H×W×3) looked up with per-vertex UVs, with ``v = 0`` at the
*bottom* row of the image as in Blender and OBJ files (row 0 of the array is
the top of the image).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ProCamError, SurfaceError
from ..imageio import read_image
from ..native import import_pymeshlab
from ..rig.model import Rig


@dataclass(frozen=True)
class SurfaceMesh:
    vertices: np.ndarray  # N×3 float64, rig frame
    faces: np.ndarray  # M×3 int32, counter-clockwise seen from the camera side
    uvs: np.ndarray  # N×2 float64 in [0, 1]
    albedo: np.ndarray  # H×W×3 float32, linear, ≥ 0 (a reflectance ≤ 1, or read in camera units: may exceed 1)
    name: str = "surface"

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, dtype=np.float64)
        f = np.asarray(self.faces)
        uv = np.asarray(self.uvs, dtype=np.float64)
        a = np.asarray(self.albedo, dtype=np.float32)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3:
            raise SurfaceError(f"surface {self.name!r}: vertices must be N×3 with N ≥ 3, got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise SurfaceError(f"surface {self.name!r} has no triangles")
        if not np.issubdtype(f.dtype, np.integer) or f.min() < 0 or f.max() >= len(v):
            raise SurfaceError(f"surface {self.name!r}: face indices must index its {len(v)} vertices")
        if uv.shape != (len(v), 2):
            raise SurfaceError(f"surface {self.name!r}: needs one UV per vertex, got {uv.shape}")
        if a.ndim != 3 or a.shape[2] != 3 or min(a.shape[:2]) < 1:
            raise SurfaceError(f"surface {self.name!r}: albedo must be an H×W×3 image, got {a.shape}")
        if not (np.all(np.isfinite(v)) and np.all(np.isfinite(uv)) and np.all(np.isfinite(a))):
            raise SurfaceError(f"surface {self.name!r} holds NaN or infinite values")
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f.astype(np.int32))
        object.__setattr__(self, "uvs", uv)
        # Not clipped at 1: an albedo read in camera units exceeds 1 where the camera is brighter than the
        # simulated irradiance (a white-balance gain, a tone curve); clipped, the model was too dark there.
        object.__setattr__(self, "albedo", np.maximum(a, 0.0))

    def face_normals(self) -> np.ndarray:
        p = self.vertices[self.faces]
        n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def ray_intersect(mesh: SurfaceMesh, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Distance along each ray to the nearest triangle (Möller–Trumbore), ``inf`` where it misses.

    ``origins``/``directions`` are N×3 (or 3) in the rig frame; directions need
    not be unit length (the result is in units of the direction's length).
    """
    o = np.broadcast_to(np.asarray(origins, dtype=np.float64), np.shape(directions)).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    tri = mesh.vertices[mesh.faces]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    best = np.full(len(d), np.inf)
    for start in range(0, len(d), 256):  # chunks keep the N×M temporaries small
        dd, oo = d[start:start + 256, None, :], o[start:start + 256, None, :]
        p = np.cross(dd, e2[None])
        det = np.einsum("nmk,mk->nm", p, e1)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = oo - tri[None, :, 0]
        u = np.einsum("nmk,nmk->nm", s, p) * inv
        q = np.cross(s, e1[None])
        v = np.einsum("nk,nmk->nm", dd[:, 0], q) * inv
        t = np.einsum("mk,nmk->nm", e2, q) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
        best[start:start + 256] = np.where(hit, t, np.inf).min(axis=1)
    return best


def frame_points_to_camera(rig: Rig, surface: SurfaceMesh, px: np.ndarray) -> np.ndarray:
    """Camera pixels (N×2) of projector-frame points ``px`` (N×2, native frame, corner convention),
    by ray casting onto the surface; NaN where the ray misses or the camera does not see the hit point."""
    proj = rig.projector
    px = np.asarray(px, dtype=np.float64).reshape(-1, 2)
    dirs = proj.intrinsics.rays(px) @ proj.camera_from_projector[:3, :3].T
    t = ray_intersect(surface, proj.position, dirs)
    pts = proj.position + dirs * t[:, None]
    cam = rig.camera.intrinsics.project(pts)
    # Hidden from the camera if the camera ray meets the surface sooner.
    tc = ray_intersect(surface, np.zeros(3), pts)
    cam[~np.isfinite(t) | (tc < 0.999)] = np.nan
    return cam


def read_mesh_file(path: str | Path, *, texture: bool = True, error: type[ProCamError] = SurfaceError) -> SurfaceMesh:
    """A user's ``.obj``/``.ply``/``.stl`` mesh as the file holds it (its frame, its units), with the texture it
    names when ``texture`` (else a plain grey one: calibration makes its own); ``error`` says what is wrong. The
    one mesh reader: the lab's surfaces and the meshes calibration registers both come through here."""
    path = Path(path)
    if not path.is_file():
        raise error(f"no mesh file at {path}; give the .obj or .ply of the object (scan or CAD)")
    pymeshlab = import_pymeshlab()
    ms = pymeshlab.MeshSet()
    try:
        ms.load_new_mesh(str(path))
    except pymeshlab.PyMeshLabException as exc:
        raise error(f"cannot read the mesh {path}: {exc}; export it as .obj or .ply") from None
    m = ms.current_mesh()
    verts, faces = np.asarray(m.vertex_matrix(), np.float64), np.asarray(m.face_matrix(), np.int64)
    if len(faces) == 0:
        raise error(f"the mesh {path} has no triangles (a point cloud?); give a triangle mesh")
    albedo = np.full((4, 4, 3), 0.8, np.float32)
    uvs = np.zeros((len(verts), 2))
    if texture and m.has_wedge_tex_coord() and m.texture_number() > 0:
        wedge = np.asarray(m.wedge_tex_coord_matrix()).reshape(-1, 3, 2)
        uvs[faces.ravel()] = wedge.reshape(-1, 2)  # one UV per vertex: seams take the last wedge's UV
        tex = path.parent / m.texture(0).name if hasattr(m.texture(0), "name") else None
        if tex is not None and tex.is_file():
            albedo = read_image(tex)
    elif texture and m.has_vertex_tex_coord():
        uvs = np.asarray(m.vertex_tex_coord_matrix())
    return SurfaceMesh(verts, faces, uvs, albedo, name=path.stem)
