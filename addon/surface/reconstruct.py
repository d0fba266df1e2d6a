"""RGBD → textured surface mesh in the rig frame (the paper's S_g and S_c).

A phone's depth image is a 2.5-D view from the camera, so we triangulate it on
its own pixel grid rather than run a Poisson reconstruction: the grid gives
the right topology (no invented surface behind edges or across holes), and
pymeshlab does what it is good at on that mesh — dropping small disconnected
islands and Taubin smoothing, which averages depth noise without shrinking
the surface. Before that, outliers (pixels far from their neighbourhood
median) are dropped and small holes filled from their neighbours.

The texture is the camera's own image: each vertex's UV is where the camera
sees it, so the albedo image is pixel-aligned with the captures.

What no reconstruction removes is a constant depth *bias* (a time-of-flight
sensor's offset; the lab's ``depth_noise.bias``, 1 cm at the ``realistic``
strength): smoothing averages noise, not an offset. Nor can the rest of the
calibration see it. Depth + b is nearly the whole scene scaled by
(1 + b/z̄) about the camera — 0.6 % for 1 cm at 1.7 m — which no camera or
projector image can tell apart (the pose scales with it). What is left,
b·(z − z̄)/z̄ along each ray (< 1 mm over this rig's 25 cm depth range), is
below what Gray code + PnP can resolve (``scripts/bench_surface.py
--bias-probe``: pose and b fitted together on ideal Gray-code
correspondences find a true 1 cm as 0.9–1.2 cm from otherwise exact depth,
but as −0.1…+0.7 cm once the depth is noisy and 1.9–3.8 cm under the lab's
lens distortion; on the plane not at all). So ``depth_offset`` takes a
device offset measured once: a depth image of a flat wall facing the
camera at a tape-measured distance, stored in the capture set as a
``depth`` entry with ``wall_distance_m`` (:func:`wall_depth_offset`; the
lab writes one), or given by hand; 0 when neither exists. Measured with
``scripts/bench_surface.py`` (full resolution, lab ``realistic`` depth, all
four built-in surfaces, 3 seeds): mean distance to the true surface over the
lit area 0.97–1.03 cm, of which the bias is 1.00 cm; without the bias, or
up to that unobservable scale, 0.23–0.27 cm (noise; holes and the 256×192
upsampling add < 0.01 cm).
"""

from __future__ import annotations

import numbers
import time
from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import SurfaceError
from ..native import import_pymeshlab
from ..rig.model import Intrinsics
from .mesh import SurfaceMesh

#: Largest sensor depth bias (metres) accepted as ``depth_offset``.
MAX_DEPTH_OFFSET = 0.5


@dataclass(frozen=True)
class ReconstructionReport:
    depth_offset: float  # metres subtracted from every depth (the sensor's known bias)
    valid_fraction: float  # share of depth pixels with a usable depth before hole filling
    outliers: int  # depth pixels dropped as outliers
    vertices: int
    faces: int
    seconds: float

    def to_dict(self) -> dict[str, float | int]:
        return dict(self.__dict__)


def _valid(depth: np.ndarray, near: float, far: float) -> np.ndarray:
    return np.isfinite(depth) & (depth > near) & (depth < far)


def _fill_holes(depth: np.ndarray, valid: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Fill holes up to ~2·iterations pixels wide with the mean of valid neighbours.

    Only enclosed holes are filled: invalid regions that touch the image border
    are background around the surface, and growing into them would invent surface.
    """
    n, labels, stats, _ = cv2.connectedComponentsWithStats((~valid).astype(np.uint8), connectivity=4)
    h, w_ = valid.shape
    x, y, bw, bh = (stats[:, i] for i in range(4))
    border = (x == 0) | (y == 0) | (x + bw == w_) | (y + bh == h)
    fillable = ~border & (np.minimum(bw, bh) <= 2 * iterations + 1)
    fillable[0] = False  # label 0 is the valid region
    allowed = valid | fillable[labels]
    d = np.where(valid, depth, 0.0).astype(np.float32)
    w = valid.astype(np.float32)
    kernel = np.ones((3, 3), np.float32)
    for _ in range(iterations):
        if not np.any((w == 0) & allowed):
            break
        s = cv2.filter2D(d * w, -1, kernel, borderType=cv2.BORDER_CONSTANT)
        n = cv2.filter2D(w, -1, kernel, borderType=cv2.BORDER_CONSTANT)
        grow = (w == 0) & (n > 0) & allowed
        d = np.where(grow, s / np.maximum(n, 1e-6), d)
        w = np.where(grow, 1.0, w)
    return d, w > 0


def wall_depth_offset(depth: np.ndarray, distance_m: float, *, min_valid: float = 0.25) -> float:
    """The depth sensor's constant bias from its image of a flat wall facing it at ``distance_m`` (metres).

    The median over the valid pixels: for a plane, depth varies about
    linearly across the image, so the median is the depth at the image centre
    even when the wall is not square to the camera; holes and outliers do not
    move it. Raises :class:`SurfaceError` when the image cannot give one.
    """
    if isinstance(distance_m, bool) or not isinstance(distance_m, numbers.Real) or not 0.1 <= distance_m <= 20.0:
        raise SurfaceError(f"the wall distance must be a number of metres in [0.1, 20], got {distance_m!r}")
    d = np.asarray(depth, dtype=np.float64)
    valid = np.isfinite(d) & (d > 0)
    if valid.mean() < min_valid:
        raise SurfaceError(f"the wall depth image is mostly empty ({100 * valid.mean():.0f} % valid, need "
                           f"{100 * min_valid:.0f} %); recapture the wall facing it, in less sunlight")
    offset = float(np.median(d[valid])) - float(distance_m)
    if abs(offset) > MAX_DEPTH_OFFSET:
        raise SurfaceError(f"the wall depth image reads {offset:+.2f} m from the stated {distance_m} m, more than a "
                           f"sensor bias (±{MAX_DEPTH_OFFSET} m); check the distance and the depth units")
    return offset


def reconstruct_surface(depth: np.ndarray, camera: Intrinsics, rgb: np.ndarray | None = None, *,
                        step: int = 4, near: float = 0.1, far: float = 20.0, min_valid: float = 0.5,
                        fill_iterations: int = 4, smoothing_steps: int = 20, edge_jump: float = 0.04,
                        depth_offset: float = 0.0, name: str = "reconstructed"
                        ) -> tuple[SurfaceMesh, ReconstructionReport]:
    """Mesh + texture from a depth image (metres, camera-aligned) and the RGB image of the unlit surface.

    ``step`` is the grid spacing in depth pixels; ``edge_jump`` the relative
    depth difference across a triangle beyond which it is treated as an
    occlusion edge and not filled. ``depth_offset`` (metres, + = the sensor
    reads too far) is the sensor's constant bias, measured once per device; it
    is subtracted from every depth (see the module doc for why nothing here
    can estimate it). Raises :class:`SurfaceError` when the depth map cannot
    give a surface.
    """
    t0 = time.perf_counter()
    if isinstance(depth_offset, bool) or not isinstance(depth_offset, numbers.Real) \
            or not abs(depth_offset) <= MAX_DEPTH_OFFSET:
        raise SurfaceError(f"the depth offset must be a number of metres within ±{MAX_DEPTH_OFFSET}, got "
                           f"{depth_offset!r}; give the sensor's measured bias (+ = it reads too far) — a larger "
                           "error is a wrong unit or scale, not an offset")
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim == 3:
        depth = depth[..., 0]
    depth = depth - float(depth_offset)
    h, w = depth.shape
    if (w, h) != camera.size:
        if abs(w / h - camera.width / camera.height) > 1e-3:
            raise SurfaceError(f"depth image is {w}×{h} but the camera is {camera.width}×{camera.height} "
                               "with another aspect ratio; register the depth to the colour image first")
        camera = camera.scaled(w, h)
    valid = _valid(depth, near, far)
    frac = float(valid.mean())
    if frac < min_valid:
        raise SurfaceError(f"the depth map is mostly empty: only {100 * frac:.0f} % of its pixels hold a depth "
                           f"between {near} and {far} m (need {100 * min_valid:.0f} %); recapture the depth "
                           "facing the surface, closer, or in less sunlight")

    # Outliers: far from the local median by more than a robust multiple of the local spread.
    filled, _ = _fill_holes(depth, valid, 2)
    med = cv2.medianBlur(filled.astype(np.float32), 5).astype(np.float64)
    resid = np.abs(depth - med)
    mad = np.median(resid[valid]) if valid.any() else 0.0
    outlier = valid & (resid > max(6.0 * 1.4826 * mad, 0.02 * np.median(depth[valid])))
    valid &= ~outlier
    d, valid = _fill_holes(depth, valid, fill_iterations)

    # Grid vertices at pixel centres every `step` pixels.
    ys = np.arange(step / 2, h, step)
    xs = np.arange(step / 2, w, step)
    gx, gy = np.meshgrid(xs, ys)
    iy, ix = np.minimum(gy.astype(int), h - 1), np.minimum(gx.astype(int), w - 1)
    # Average depth over each cell so the grid sees all the data, not every step-th sample.
    box = cv2.blur(np.where(valid, d, 0).astype(np.float32), (step, step))
    cnt = cv2.blur(valid.astype(np.float32), (step, step))
    zc = np.where(cnt > 0.25, box / np.maximum(cnt, 1e-6), np.nan)[iy, ix]
    rays = camera.rays(np.stack([gx.ravel(), gy.ravel()], axis=1))
    verts = rays * zc.reshape(-1, 1)
    ok = np.isfinite(zc)
    idx = np.arange(zc.size).reshape(zc.shape)
    a, b, c, e = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    tris = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([a, e, c], -1).reshape(-1, 3)])
    tz = zc.ravel()[tris]
    keep = ok.ravel()[tris].all(axis=1)
    keep[keep] &= (np.nanmax(tz[keep], axis=1) / np.nanmin(tz[keep], axis=1)) < 1 + edge_jump
    tris = tris[keep]
    if len(tris) < 2:
        raise SurfaceError("the depth map gives no connected surface (all neighbouring depths jump); "
                           "check that the depth image shows the projection surface")

    pymeshlab = import_pymeshlab()
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.nan_to_num(verts),
                               face_matrix=tris.astype(np.int32)))
    ms.meshing_remove_unreferenced_vertices()
    n_faces = ms.current_mesh().face_number()
    ms.meshing_remove_connected_component_by_face_number(mincomponentsize=max(10, n_faces // 50))
    ms.meshing_remove_unreferenced_vertices()
    if smoothing_steps > 0:
        ms.apply_coord_taubin_smoothing(lambda_=0.5, mu=-0.53, stepsmoothnum=smoothing_steps)
    m = ms.current_mesh()
    v = np.asarray(m.vertex_matrix(), dtype=np.float64)
    f = np.asarray(m.face_matrix(), dtype=np.int32)
    if len(f) == 0:
        raise SurfaceError("reconstruction left no surface after removing small fragments; the depth is too noisy")

    px = camera.project(v)
    uv = np.stack([px[:, 0] / camera.width, 1.0 - px[:, 1] / camera.height], axis=1)
    albedo = np.full((8, 8, 3), 0.8, np.float32) if rgb is None else np.asarray(rgb, dtype=np.float32)
    mesh = SurfaceMesh(v, f, np.clip(uv, 0, 1), albedo, name=name)
    if np.mean(mesh.face_normals()[:, 2]) > 0:  # keep normals facing the camera
        mesh = SurfaceMesh(v, f[:, ::-1].copy(), mesh.uvs, mesh.albedo, name=name)
    report = ReconstructionReport(float(depth_offset), frac, int(outlier.sum()), len(v), len(f),
                                  time.perf_counter() - t0)
    return mesh, report
