"""A surface from the user's own mesh (a scan or CAD model): registered to the rig by ICP against measured points.

Many crews already have a mesh of the object, in its own frame and units.
:func:`register_mesh` finds the rigid transform that puts it where the
measured points are (the depth image's points, or the Gray code triangulated
with a calibrated rig, :mod:`.triangulate`); calibration then uses the moved
mesh as the surface, with the camera-aligned texture and albedo as for a
reconstructed one (:func:`place_mesh`).

How, and why:

* **Correspondences**: each measured point's nearest point of the mesh, from
  an area-uniform sampling of its triangles (a CAD wall may be two
  triangles) with each sample's face normal, looked up with an exact k-d
  tree (OpenCV's FLANN, single tree: exact and ~3 µs a query; its
  randomised forest found the true nearest sample only 10–25 % of the time).
  Measured points are moved into the mesh's frame, so the tree is built once.
* **Objective**: point-to-plane (the distance along the mesh normal, which does
  not depend on the sampling density), plus a point-to-point term at a tenth
  of the weight: on a surface that slides into itself (a plane, a cylinder —
  the lab's curve) point-to-plane alone leaves the sliding free and only the
  mesh's outline, which only point-to-point sees, pins it.
* **Robustness**: pairs farther than a gate (3 robust σ of the distances, at
  least :data:`MIN_GATE`) are dropped (measured points the mesh does not
  have: clutter, the floor, a wall behind). The coarse starts also drop the
  worst :data:`TRIM` share, which ranks them robustly while they are far
  off; the final fit does not, because near a crease the worst pairs are the
  very ones that pull the crease into place (measured on the hedge: trimmed,
  ICP stalled with its crease 5 mm RMS off; untrimmed, it lies 0.26 mm from
  the true surface). Each step is a 6×6 Gauss–Newton solve; it has
  converged when a step moves no point by more than :data:`TOLERANCE`.
* **Starts**: the identity (the mesh is roughly in place already), the
  centroids matched, and the principal axes matched in their four proper
  orientations; each runs a few iterations, and of those that fit as well
  as the best (overlap, trimmed RMS) the one that moves the mesh least from
  its own placement is run to convergence (a symmetric object fits several
  ways). A given ``initial`` transform is the only start.
* **What the points cannot tell**: a surface that slides into itself (all
  four lab surfaces do: the curve and the edges along their axis, the plane
  in two directions) is pinned there only by its outline, which a depth
  image samples once per camera pixel: along the sliding direction the
  placement is good to about half a pixel's footprint (lab, quarter
  resolution: ~6 mm), while the surface itself — what calibration uses —
  lies within a fraction of a millimetre of the truth.

Refused, with what to do (:class:`SurfaceError`): a mesh that overlaps fewer
than :data:`MIN_OVERLAP` of the measured points, an ICP that does not
converge. A mesh whose size is ~1000× the points' is taken as millimetres,
scaled and reported as a warning.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import SurfaceError
from ..rig.model import Intrinsics
from .mesh import SurfaceMesh, read_mesh_file

#: Share of the gated pairs dropped each iteration (the worst point-to-plane residuals).
TRIM = 0.15
#: Smallest gate (metres) on a pair's distance: depth noise and a sensor's residual bias stay inside it.
MIN_GATE = 0.01
#: A measured point overlaps the registered mesh when it lies this close to it (metres).
OVERLAP_DISTANCE = 0.015
#: Fewest share of the measured points that must overlap the registered mesh.
MIN_OVERLAP = 0.3
#: Converged when one step moves no measured point by more than this (metres).
TOLERANCE = 1e-5
MAX_ITERATIONS = 80
#: Iterations each start gets before the best one is run to convergence.
START_ITERATIONS = 12
#: Weight of the point-to-point term against point-to-plane (module doc).
POINT_WEIGHT = 0.1
#: Measured points used (a random, seeded subset): ICP's accuracy does not grow past a few thousand.
MAX_POINTS = 6000
#: Measured points each coarse start is tried with.
START_POINTS = 1500
#: Mesh samples per square metre, and their bounds.
SAMPLE_DENSITY = 1.0 / 0.003 ** 2
SAMPLES = (20000, 300000)
#: A mesh this many times the points' size (bounding-box diagonal) is taken as millimetres.
MM_RATIO = (300.0, 3000.0)


@dataclass(frozen=True)
class Registration:
    """Where a mesh's own frame lies in the rig frame, and how well it fits the measured points."""

    transform: np.ndarray  # 4×4 rig_from_mesh (after ``scale``), metres
    scale: float  # applied to the mesh's coordinates before ``transform`` (0.001 for a mesh in millimetres)
    rms_mm: float  # point-to-plane residual over the overlapping points within 3 robust σ
    median_mm: float
    overlap: float  # share of the measured points within OVERLAP_DISTANCE of the registered mesh
    iterations: int
    converged: bool
    start: str  # which coarse start won
    points: int  # measured points used
    warnings: list[str] = field(default_factory=list)

    def apply(self, vertices: np.ndarray) -> np.ndarray:
        """Mesh-frame vertices (N×3, the file's units) in the rig frame (metres)."""
        v = np.asarray(vertices, dtype=np.float64) * self.scale
        return v @ self.transform[:3, :3].T + self.transform[:3, 3]

    def report(self) -> dict[str, Any]:
        return {"rms_mm": self.rms_mm, "median_mm": self.median_mm, "overlap": self.overlap,
                "iterations": self.iterations, "converged": self.converged, "start": self.start,
                "points": self.points, "scale": self.scale, "transform": self.transform.tolist(),
                "warnings": list(self.warnings)}


def load_mesh(path: str | Path) -> SurfaceMesh:
    """A user's ``.obj``/``.ply``/``.stl`` mesh, in its own frame and units (no texture: calibration makes one)."""
    return read_mesh_file(path, texture=False)


def save_obj(mesh: SurfaceMesh, path: str | Path) -> None:
    """Write a mesh's vertices and triangles as a plain OBJ (what a scanner or CAD program hands over)."""
    lines = [f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in mesh.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    Path(path).write_text("\n".join(lines) + "\n")


def depth_points(depth: np.ndarray, camera: Intrinsics) -> np.ndarray:
    """The rig-frame points (N×3) of a camera-aligned depth image (metres, NaN or ≤ 0 = none)."""
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim == 3:
        d = d[..., 0]
    h, w = d.shape
    cam = camera if (w, h) == camera.size else camera.scaled(w, h)
    ok = np.isfinite(d) & (d > 0)
    rows, cols = np.nonzero(ok)
    return cam.rays(np.stack([cols, rows], axis=1) + 0.5) * d[ok][:, None]


def place_mesh(mesh: SurfaceMesh, registration: Registration, camera: Intrinsics, rgb: np.ndarray | None = None,
               name: str = "registered") -> SurfaceMesh:
    """The registered mesh in the rig frame, textured like a reconstructed one: UVs where the camera sees each
    vertex, the camera's image as its texture (calibration replaces it with the albedo)."""
    v = registration.apply(mesh.vertices)
    px = camera.project(v)
    uv = np.stack([px[:, 0] / camera.width, 1.0 - px[:, 1] / camera.height], axis=1)
    uv = np.clip(np.nan_to_num(uv, nan=0.0), 0.0, 1.0)  # vertices behind the camera are never seen by it
    albedo = np.full((8, 8, 3), 0.8, np.float32) if rgb is None else np.asarray(rgb, dtype=np.float32)
    return SurfaceMesh(v, mesh.faces, uv, albedo, name=name)


def _samples(mesh: SurfaceMesh, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform points on the mesh's triangles (and its vertices), each with its face's unit normal."""
    tri = mesh.vertices[mesh.faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    keep = area2 > 1e-18
    if not keep.any():
        raise SurfaceError(f"the mesh {mesh.name!r} has only degenerate triangles (no area)")
    tri, cross, area2 = tri[keep], cross[keep], area2[keep]
    normals = cross / area2[:, None]
    n = int(np.clip(0.5 * area2.sum() * SAMPLE_DENSITY, *SAMPLES))
    face = rng.choice(len(tri), n, p=area2 / area2.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    pts = (1 - s)[:, None] * tri[face, 0] + (s * (1 - r2))[:, None] * tri[face, 1] + (s * r2)[:, None] * tri[face, 2]
    # The vertices too (with one of their faces' normals), so that corners and outlines are sampled exactly.
    vf = np.full(len(mesh.vertices), -1)
    idx = np.flatnonzero(keep)
    for k in range(3):
        vf[mesh.faces[idx, k]] = np.arange(len(idx))
    has = vf >= 0
    return (np.concatenate([pts, mesh.vertices[has]]), np.concatenate([normals[face], normals[vf[has]]]))


def _rodrigues(w: np.ndarray) -> np.ndarray:
    r, _ = cv2.Rodrigues(np.asarray(w, dtype=np.float64).reshape(3, 1))
    return r


def _compose(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, t
    return m


class _Matcher:
    """Nearest mesh sample of points given in the mesh's frame (exact k-d tree)."""

    def __init__(self, samples: np.ndarray, normals: np.ndarray) -> None:
        self.origin = samples.mean(axis=0)  # float32 search: keep the coordinates small
        self.samples, self.normals = samples, normals
        self.index = cv2.flann_Index((samples - self.origin).astype(np.float32), {"algorithm": 4, "leaf_max_size": 10})

    def __call__(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        idx, _ = self.index.knnSearch((q - self.origin).astype(np.float32), 1, params={"checks": -1})
        idx = idx.ravel()
        return self.samples[idx], self.normals[idx]


@dataclass
class _Fit:
    s: np.ndarray  # 4×4 mesh_from_rig
    iterations: int = 0
    converged: bool = False
    rms: float = math.inf
    overlap: float = 0.0


def _icp(matcher: _Matcher, points: np.ndarray, normals: np.ndarray | None, s: np.ndarray, iterations: int,
         extent: float, trim: float = 0.0) -> _Fit:
    """Point-to-plane ICP (module doc; the worst ``trim`` share of pairs dropped) from ``s`` (mesh_from_rig)
    for at most ``iterations`` steps."""
    fit = _Fit(s.copy())
    gate = math.inf
    history: list[np.ndarray] = []
    scale_w = np.array([extent, extent, extent, 1.0, 1.0, 1.0])  # rotation as the motion it gives at the extent
    for it in range(iterations):
        q = points @ fit.s[:3, :3].T + fit.s[:3, 3]
        p, n = matcher(q)
        diff = q - p
        dist = np.linalg.norm(diff, axis=1)
        plane = np.sum(diff * n, axis=1)
        use = dist < gate
        if normals is not None:
            # A pair whose normals disagree by more than 60° is a match on the wrong side or a wrong part.
            use &= np.abs(np.sum((normals @ fit.s[:3, :3].T) * n, axis=1)) > 0.5
        if use.sum() < 12:
            break
        if trim > 0:
            use &= np.abs(plane) <= np.quantile(np.abs(plane[use]), 1.0 - trim)
        qu, nu, du, pu = q[use], n[use], diff[use], plane[use]
        # Point-to-plane rows: r = (q − p)·n, ∂r/∂ω = q × n, ∂r/∂v = n (a small motion q → q + ω×q + v).
        jp = np.concatenate([np.cross(qu, nu), nu], axis=1)
        a = jp.T @ jp
        b = -jp.T @ pu
        # Point-to-point rows at a lower weight: r = q − p, ∂r/∂ω = −[q]×, ∂r/∂v = I.
        w2 = POINT_WEIGHT ** 2
        qx = np.zeros((len(qu), 3, 3))
        qx[:, 0, 1], qx[:, 0, 2], qx[:, 1, 2] = -qu[:, 2], qu[:, 1], -qu[:, 0]
        qx[:, 1, 0], qx[:, 2, 0], qx[:, 2, 1] = qu[:, 2], -qu[:, 1], qu[:, 0]
        jt = np.concatenate([-qx, np.broadcast_to(np.eye(3), qx.shape)], axis=2)  # N×3×6
        a += w2 * np.einsum("nki,nkj->ij", jt, jt)
        b -= w2 * np.einsum("nki,nk->i", jt, du)
        try:
            x = np.linalg.solve(a + 1e-12 * np.eye(6), b)
        except np.linalg.LinAlgError:
            break
        fit.s = _compose(_rodrigues(x[:3]), x[3:]) @ fit.s
        # A surface that slides into itself converges slowly: only its outline pulls along the sliding direction
        # while every interior pair holds it back, so each step is a small share of what is left, and noisy. When
        # the last steps, averaged over three, keep one direction and shrink by ρ, take the rest of the geometric
        # series at once (ρ/(1 − ρ) of the step, at most 30×), as Besl & McKay's accelerated ICP does.
        history.append(x * scale_w)
        if len(history) >= 6:
            now, before = np.mean(history[-3:], axis=0), np.mean(history[-6:-3], axis=0)
            n_now, n_before = np.linalg.norm(now), np.linalg.norm(before)
            cos = float(np.dot(now, before)) / max(n_now * n_before, 1e-300)
            rho = (n_now / max(n_before, 1e-300)) ** (1.0 / 3.0)
            if cos > 0.9 and rho < 0.995:
                extra = now / scale_w * min(rho / (1.0 - rho), 30.0)
                fit.s = _compose(_rodrigues(extra[:3]), extra[3:]) @ fit.s
                x = x + extra
                history.clear()
        fit.iterations = it + 1
        fit.rms = float(np.sqrt(np.mean(pu ** 2)))
        fit.overlap = float(np.mean(dist < OVERLAP_DISTANCE))
        mad = 1.4826 * float(np.median(dist[use]))
        gate = max(MIN_GATE, 3.0 * mad, 3.0 * fit.rms)
        if np.linalg.norm(x[:3]) * extent + np.linalg.norm(x[3:]) < TOLERANCE:
            fit.converged = True
            break
    return fit


def _starts(samples: np.ndarray, points: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Coarse rig_from_mesh transforms: identity, centroids matched, principal axes matched (4 orientations)."""
    cm, cp = samples.mean(axis=0), points.mean(axis=0)
    out = [("identity", np.eye(4)), ("centroids", _compose(np.eye(3), cp - cm))]
    um = np.linalg.svd(samples - cm, full_matrices=False)[2].T  # columns: principal axes
    up = np.linalg.svd(points - cp, full_matrices=False)[2].T
    for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        flip = np.diag([sx, sy, 1.0])
        r = up @ flip @ um.T
        if np.linalg.det(r) < 0:
            r = up @ flip @ np.diag([1.0, 1.0, -1.0]) @ um.T
        out.append((f"principal axes {'+' if sx > 0 else '−'}{'+' if sy > 0 else '−'}", _compose(r, cp - r @ cm)))
    return out


def _motion(t: np.ndarray, samples: np.ndarray) -> float:
    """How far ``t`` moves the mesh (rms over its samples, metres)."""
    moved = samples @ t[:3, :3].T + t[:3, 3]
    return float(np.sqrt(np.mean(np.sum((moved - samples) ** 2, axis=1))))


def _diagonal(p: np.ndarray) -> float:
    return float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))


def register_mesh(mesh: SurfaceMesh, points: np.ndarray, normals: np.ndarray | None = None, *,
                  initial: np.ndarray | None = None, seed: int = 0, source: str | None = None) -> Registration:
    """Rigidly register ``mesh`` (its own frame) to the measured ``points`` (N×3, rig frame, metres).

    ``normals`` (N×3, optional) of the points reject pairs that face apart.
    ``initial`` (4×4 rig_from_mesh, after any millimetre scaling) is then the
    only start; otherwise several coarse starts are tried (module doc).
    ``source`` names the mesh in messages (its file). Raises
    :class:`SurfaceError` when the mesh does not overlap the points or ICP
    does not converge.
    """
    where = source or f"the mesh {mesh.name!r}"
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    keep = np.all(np.isfinite(pts), axis=1)
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        keep &= np.all(np.isfinite(normals), axis=1)
    pts = pts[keep]
    if len(pts) < 100:
        raise SurfaceError(f"only {len(pts)} measured points to register {where} to (need 100); the depth image or "
                           "the triangulated Gray code shows too little of the surface")
    rng = np.random.default_rng(seed)
    pick = rng.permutation(len(pts))[:MAX_POINTS]  # random order: the first START_POINTS are a fair subset
    pts = pts[pick]
    nrm = normals[keep][pick] if normals is not None else None
    warnings: list[str] = []
    scale = 1.0
    ratio = _diagonal(mesh.vertices) / max(_diagonal(pts), 1e-12)
    if MM_RATIO[0] <= ratio <= MM_RATIO[1]:
        scale = 1e-3
        warnings.append(f"{where} is {ratio:.0f}× the size of the measured surface: read as millimetres and "
                        "scaled to metres; export it in metres to silence this")
    scaled = SurfaceMesh(mesh.vertices * scale, mesh.faces, mesh.uvs, mesh.albedo, mesh.name)
    samples, sample_normals = _samples(scaled, rng)
    matcher = _Matcher(samples, sample_normals)
    extent = _diagonal(pts)
    if initial is not None:
        t0 = np.asarray(initial, dtype=np.float64)
        if t0.shape != (4, 4) or not np.all(np.isfinite(t0)):
            raise SurfaceError(f"the initial placement of {where} must be a finite 4×4 matrix")
        starts = [("given", t0)]
    else:
        starts = _starts(samples, pts)
    # A few iterations from each start; the most overlap (then the lowest residual) goes on.
    few = slice(0, START_POINTS)  # the points are in random order already
    trials = [(name, _icp(matcher, pts[few], None if nrm is None else nrm[few], np.linalg.inv(t), START_ITERATIONS,
                          extent, TRIM)) for name, t in starts]
    # A symmetric object (the lab's surfaces turned 180° about the view axis) fits equally well several ways: of
    # the starts that fit as well as the best, keep the one that moves the mesh least from its own placement.
    top = max(f.overlap for _, f in trials)
    low = min(f.rms for _, f in trials if f.overlap >= top - 0.01)
    good = [(n, f) for n, f in trials if f.overlap >= top - 0.01 and f.rms <= 1.2 * low + 1e-4]
    name, best = min(good, key=lambda nf: _motion(np.linalg.inv(nf[1].s), samples))
    fit = _icp(matcher, pts, nrm, best.s, MAX_ITERATIONS, extent)
    iterations = best.iterations + fit.iterations
    # Final figures over all measured points kept, at the final transform.
    q = pts @ fit.s[:3, :3].T + fit.s[:3, 3]
    p, n = matcher(q)
    dist = np.linalg.norm(q - p, axis=1)
    plane = np.abs(np.sum((q - p) * n, axis=1))
    near = dist < OVERLAP_DISTANCE
    overlap = float(near.mean())
    median = float(np.median(plane[near])) * 1000 if near.any() else math.inf
    # The residual over the inliers (within 3 robust σ), so that a few gross outliers do not dominate it. The rest
    # is the measured points' own noise, not the placement's error: triangulated Gray code at half resolution is
    # ~4.5 mm (median) off the true plane per point, and the mesh registered to it lies 0.07 mm from it.
    inlier = near & (plane <= max(3.0 * 1.4826 * median / 1000, 1e-4))
    rms = float(np.sqrt(np.mean(plane[inlier] ** 2))) * 1000 if inlier.any() else math.inf
    if overlap < MIN_OVERLAP:
        raise SurfaceError(
            f"{where} does not overlap the measured surface: at its best placement (start: {name}) only "
            f"{overlap:.0%} of the measured points lie within {1000 * OVERLAP_DISTANCE:.0f} mm of it (need "
            f"{MIN_OVERLAP:.0%}); is it the mesh of this object, in metres or millimetres?")
    if not fit.converged:
        raise SurfaceError(f"registering {where} to the measured surface did not converge in {MAX_ITERATIONS} "
                           f"iterations (start: {name}, residual {rms:.1f} mm): the measured points do not pin it, "
                           "because the surface slides into itself (a plane, a cylinder, an edge) and its outline is "
                           "not among them; measure more of the object (a depth image shows its outline), or use the "
                           "measured surface itself (--surface-from depth or graycode)")
    return Registration(np.linalg.inv(fit.s), scale, rms, median, overlap, iterations, True, name, len(pts),
                        warnings)
