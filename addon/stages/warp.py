"""Stage B — the image warp (paper Sec. IV-B, Eq. 6–8): what the real projector does to its input that f̂ does not.

After stage A the simulated projection f̂ still lands slightly off the real
one: the pose is not exact, the reconstructed surface is not the real one, the
camera lens distorts. The paper models the rest as a warp of the projector
input, ``f(x) ≈ f̂(z)`` with ``x = W(z)``. Eq. 6 cannot be differentiated (f is
the real world), so it fits the *inverse* warp ``M`` through the simulation,

    M = argmin ‖ y − f̂(M(c)) ‖²                                       (Eq. 7)

with ``c`` the projected checkerboard and ``y`` its binarised capture, and then
``W`` from ``W(M(z)) ≈ z`` (Eq. 8).

Warp model
    A thin-plate spline (TPS) on the projector *input* image (``input_size``):
    an ``n × n`` lattice of control points spanning the image corner to corner
    (default 8 × 8), each with a shift in input pixels. ``M(c)`` samples ``c``
    at ``φ_M(p) = p + d_M(p)``, where ``d_M`` is the TPS interpolant of the
    shifts (kernel ``r² log r²`` in coordinates divided by the longer image
    side, so the spline is isotropic and independent of the resolution), and
    is black where ``φ_M(p)`` leaves the image — the projector shows nothing
    outside its input. ``W`` is the same kind of spline with its own shifts.
    ``d`` is *linear* in the shifts, ``d(p) = B(p) · s``, with ``B`` (pixels ×
    n²) fixed by the lattice (DESIGN.md §4): we build ``B`` once. In the
    optimisation ``d = B·s`` enters Dr.Jit as a leaf, a bilinear
    ``dr.gather`` of the pattern with differentiable weights builds the
    projector frame, and the render's adjoint arrives at ``d``; the linear
    layer's adjoint ``Bᵀ·∂L/∂d`` is then one matrix product (see
    :class:`_DrWarp` for why not in Dr.Jit).

Target: why normalise before binarising
    The paper binarises each colour channel of the capture at 0.7. A raw
    capture's level depends on albedo, vignetting, the projector and camera
    responses and the ambient light, so a fixed threshold would erase dark
    parts of the surface. We first map each channel to where it lies between
    the black and white captures, ``(checker − black) / (white − black)``: for
    a binary pattern every effect that acts per pixel (albedo, vignetting,
    response curves, black level) cancels, a lit square reads ≈ 1 and an unlit
    one ≈ 0, and 0.7 means "70 % of the way to white" everywhere. The
    simulation is normalised the same way: ``f̂(M(c)) / f̂(white)`` (direct
    light, no clamping: the ratio is the warped pattern as the camera sees
    it), so the loss compares like with like on a textured surface too.

Both checkerboard phases
    The 0.7 threshold shrinks lit squares by the blur of the projector (and
    camera), which would bias edges. Phase 1 is the complement of phase 0, so
    its binarised capture ``y₁`` says where phase 0's *dark* squares are, with
    the opposite bias. With normalised renders ``r₁ = 1 − r₀``, hence
    ``‖y₀ − r₀‖² + ‖y₁ − r₁‖² = 2 ‖r₀ − (y₀ + 1 − y₁)/2‖² + const``: one
    render per step against the averaged target uses both captures and
    cancels the threshold's bias. Patterns that are neither equal nor
    complementary (another square size) get a render of their own.

Optimisation
    Adam on the shifts, coarse to fine: the checkerboard fed to the simulation
    is blurred (σ from about a fifth of a square down to half a pixel), which
    widens the basin (the gradient of a sharp edge lives on one texel) without
    moving edges (a symmetric blur keeps a straight edge where it is, and the
    L2 optimum against a sharp target too). Regularised by the TPS bending
    energy (zero for affine motion) and a small L2 on the shifts, so control
    points that no camera pixel constrains stay where the smooth field puts
    them rather than drift with noise. Direct light only, as in the paper,
    one sample per pixel (each step renders anew, so the noise averages out
    over the steps; measured: as accurate as 2 spp, and 0.33 s instead of
    0.45 s a step at full resolution), 70 steps, and M
    is the mean of the last 15 % of the iterates, which removes the jitter
    the render noise leaves in Adam's steps.

W from M (Eq. 8)
    Closed form. ``W(M(z)) = z ∘ φ_M ∘ φ_W`` is ``z`` when ``φ_W = φ_M⁻¹``. We
    push a dense grid of points ``q`` through ``φ_M``, giving pairs
    ``(φ_M(q), q)``, and solve the linear least-squares problem
    ``B(φ_M(q)) · s_W = q − φ_M(q)`` for W's shifts (the TPS is linear in
    them). The residual ``|φ_M(φ_W(p)) − p|`` over the image is reported; it
    is far below 0.1 px for warps of a few pixels.

Measuring
    Checkerboard inner corners are located to sub-pixel precision
    (``cornerSubPix``) in the normalised capture and in the normalised
    simulation, before (``M`` = identity) and after the warp; we report the
    median and maximum distance over corners that are seen cleanly by both
    (:func:`measure_corners`). ``scripts/bench_warp.py``, lab sets with the
    ``realistic`` effects, surface reconstructed from the set's depth, the
    true projector pose moved 5 mm and turned 0.2° (a stage-A residual);
    camera px, median / max, 121 corners; seconds wall / CPU on 2 cores shared
    with other jobs (load 4–12)::

        scale 0.5 (320×240, input 300²)  before        after         stage B
        plane                            1.76 / 2.20   0.09 / 0.36   25 s / 12 s
        curve                            1.63 / 2.06   0.08 / 0.25   19 s /  9 s
        vedge                            1.63 / 2.10   0.08 / 0.27   18 s /  9 s
        hedge                            1.68 / 2.01   0.10 / 0.36   20 s / 10 s
        full (640×480, input 600²)
        vedge                            3.26 / 4.33   0.12 / 0.77   79 s / 38 s
        hedge                            3.30 / 4.13   0.12 / 0.45   69 s / 34 s

    With the true pose and surface the gap is the lab's own (camera lens
    distortion, Cycles vs Mitsuba): 0.10–0.13 px → 0.06–0.10 px median, max
    0.4–0.6 → ≤ 0.26 px at scale 0.5. From 15 mm / 0.6° off, 4.7 px → 0.10–0.14 px.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..capture.format import CaptureSet, Entry
from ..capture.patterns import refine_corners
from ..errors import CalibrationError, Cancelled, ImageError, ProCamError
from ..progress import Cancel, Progress
from ..render import backend
from ..render.forward import ForwardModel
from ..rig.model import Rig
from ..surface.mesh import SurfaceMesh, frame_points_to_camera


DEFAULT_GRID = 8
#: The paper's per-channel binarisation threshold, applied to the normalised capture (see module notes).
THRESHOLD = 0.7
FORMAT = "procam-warp-tps"


# ============================================================================ thin-plate spline

def _tps_kernel(r2: np.ndarray) -> np.ndarray:
    """U(r) = r² log r² (from squared distances), 0 at r = 0."""
    return np.where(r2 > 0.0, r2 * np.log(np.maximum(r2, 1e-300)), 0.0)


def _check_lattice(size: tuple[int, int], grid: int) -> tuple[int, int, int]:
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise CalibrationError(f"warp size must be (width, height), got {size!r}") from None
    if w < 2 or h < 2:
        raise CalibrationError(f"warp size must be at least 2×2 pixels, got {w}×{h}")
    if not isinstance(grid, (int, np.integer)) or isinstance(grid, bool) or not 2 <= grid <= 64:
        raise CalibrationError(f"warp grid must be a whole number of control points per side in [2, 64], got {grid!r}")
    return w, h, int(grid)


@functools.lru_cache(maxsize=8)
def _tps_system(w: int, h: int, grid: int) -> tuple[np.ndarray, np.ndarray]:
    """Control points (n²×2, normalised) and the inverse of the TPS system matrix L (n²+3 square)."""
    scale = float(max(w, h))
    ii, jj = np.meshgrid(np.linspace(0.0, w, grid), np.linspace(0.0, h, grid))  # row-major: [row j, col i]
    ctrl = np.stack([ii.ravel(), jj.ravel()], axis=1) / scale
    k = _tps_kernel(((ctrl[:, None, :] - ctrl[None, :, :]) ** 2).sum(-1))
    p = np.concatenate([np.ones((len(ctrl), 1)), ctrl], axis=1)
    n = len(ctrl)
    big = np.zeros((n + 3, n + 3))
    big[:n, :n], big[:n, n:], big[n:, :n] = k, p, p.T
    linv = np.linalg.inv(big)
    ctrl.setflags(write=False)
    linv.setflags(write=False)
    return ctrl, linv


def tps_basis(points: np.ndarray, size: tuple[int, int], grid: int) -> np.ndarray:
    """B (N × n²): the TPS displacement at ``points`` (N×2 input pixels) is ``B @ shifts.reshape(n², 2)``.

    Row-major control order: control point ``(j, i)`` (row j, column i) is column ``j·n + i``.
    """
    w, h, n = _check_lattice(size, grid)
    ctrl, linv = _tps_system(w, h, n)
    q = np.asarray(points, dtype=np.float64).reshape(-1, 2) / float(max(w, h))
    out = np.empty((len(q), n * n))
    for start in range(0, len(q), 65536):  # chunks keep the N × n² kernel matrix small
        qc = q[start:start + 65536]
        u = _tps_kernel(((qc[:, None, :] - ctrl[None, :, :]) ** 2).sum(-1))
        a = np.concatenate([u, np.ones((len(qc), 1)), qc], axis=1)
        out[start:start + len(qc)] = a @ linv[:, :n * n]
    return out


def pixel_centres(size: tuple[int, int]) -> np.ndarray:
    """(h·w)×2 pixel centres (corner convention: ``i + 0.5``), row-major."""
    w, h = int(size[0]), int(size[1])
    x, y = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    return np.stack([x.ravel(), y.ravel()], axis=1)


@functools.lru_cache(maxsize=2)
def _pixel_basis(w: int, h: int, grid: int) -> np.ndarray:
    """The basis at every pixel centre, float32 (92 MB for 600×600 and 8×8), built once per lattice."""
    b = tps_basis(pixel_centres((w, h)), (w, h), grid).astype(np.float32)
    b.setflags(write=False)
    return b


def bending_matrix(size: tuple[int, int], grid: int) -> np.ndarray:
    """E (n²×n²): the TPS bending energy of one coordinate's shifts ``s`` is ``s @ E @ s`` (up to 8π).

    Zero for affine shift fields; in normalised coordinates, so shifts in pixels give px².
    """
    w, h, n = _check_lattice(size, grid)
    _, linv = _tps_system(w, h, n)
    e = linv[:n * n, :n * n]
    return 0.5 * (e + e.T)


def bilinear_taps(size: tuple[int, int], x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The four (flat index, weight) taps of bilinear samples of a ``size`` = (w, h) image at continuous positions
    (corner convention), each (4, …) like ``x``; taps outside the image get weight 0."""
    w, h = size
    u, v = np.asarray(x, dtype=np.float64) - 0.5, np.asarray(y, dtype=np.float64) - 0.5
    i0, j0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fu, fv = (u - i0).astype(np.float32), (v - j0).astype(np.float32)
    index, weight = [], []
    for di, dj, wt in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)), (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
        ii, jj = i0 + di, j0 + dj
        ok = (ii >= 0) & (ii < w) & (jj >= 0) & (jj < h)
        index.append(np.clip(jj, 0, h - 1) * w + np.clip(ii, 0, w - 1))
        weight.append(np.where(ok, wt, 0.0).astype(np.float32))
    return np.stack(index), np.stack(weight)


def channel_taps(index: np.ndarray, weight: np.ndarray, channels: int) -> tuple[np.ndarray, np.ndarray]:
    """Taps from :func:`bilinear_taps` spread over the values of an image with ``channels`` channels, for
    :func:`sample_taps` (flat gathers are 3× faster than gathering whole pixels)."""
    shape = index.shape[1:]
    idx = (index.reshape(4, -1, 1) * channels + np.arange(channels)).reshape(4, -1)
    return idx, np.repeat(weight.reshape(4, -1), channels, axis=1).reshape((4, *shape, channels))


def sample_taps(image: np.ndarray, index: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` (H×W×C, float32) through taps from :func:`channel_taps` with its C."""
    flat = np.asarray(image, dtype=np.float32).reshape(-1)
    out = np.take(flat, index[0]).reshape(weight.shape[1:]) * weight[0]
    for k in range(1, 4):
        out += np.take(flat, index[k]).reshape(weight.shape[1:]) * weight[k]
    return out


def sample_bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` (H×W or H×W×C) at continuous positions (corner convention); 0 outside."""
    img = np.asarray(image, dtype=np.float32)
    taps = channel_taps(*bilinear_taps((img.shape[1], img.shape[0]), x, y), img.shape[2] if img.ndim == 3 else 1)
    out = sample_taps(img, *taps)
    return out if img.ndim == 3 else out[..., 0]


# ============================================================================ the warp as data

@dataclass(frozen=True, eq=False)
class Warp:
    """The warps M (simulation side) and W (real projector side) on the projector input image.

    ``size`` is the input image (width, height) the shifts are measured in;
    ``m_shifts``/``w_shifts`` are ``grid × grid × 2`` arrays ``[row, col, (dx, dy)]``
    in pixels of that image, for control points spaced evenly from the image's
    top-left corner ``(0, 0)`` to its bottom-right corner ``(w, h)``.
    ``apply_m(c)(p) = c(p + d_M(p))``; ``apply_w`` likewise with W's shifts.
    Give the real projector ``apply_w(z)`` to show what the simulation shows for ``z``.
    """

    grid: int
    size: tuple[int, int]
    m_shifts: np.ndarray
    w_shifts: np.ndarray

    def __post_init__(self) -> None:
        w, h, n = _check_lattice(self.size, self.grid)
        object.__setattr__(self, "size", (w, h))
        object.__setattr__(self, "grid", n)
        for name in ("m_shifts", "w_shifts"):
            a = np.asarray(getattr(self, name), dtype=np.float64)
            if a.shape != (n, n, 2):
                raise CalibrationError(f"warp {name} must be {n}×{n}×2 (grid × grid × (dx, dy)), got shape {a.shape}")
            if not np.all(np.isfinite(a)):
                raise CalibrationError(f"warp {name} holds NaN or infinite values")
            a = a.copy()
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        object.__setattr__(self, "_taps", {})

    def __eq__(self, other: object) -> bool:
        # Exact equality (the generated __eq__ would compare arrays ambiguously).
        return (isinstance(other, Warp) and self.grid == other.grid and self.size == other.size
                and np.array_equal(self.m_shifts, other.m_shifts) and np.array_equal(self.w_shifts, other.w_shifts))

    __hash__ = None  # type: ignore[assignment]  # holds arrays

    @staticmethod
    def identity(size: tuple[int, int], grid: int = DEFAULT_GRID) -> "Warp":
        """No warp: both maps are the identity."""
        w, h, n = _check_lattice(size, grid)
        return Warp(n, (w, h), np.zeros((n, n, 2)), np.zeros((n, n, 2)))

    @property
    def is_identity(self) -> bool:
        return not (np.any(self.m_shifts) or np.any(self.w_shifts))

    # -- point maps ------------------------------------------------------------------------------

    def _map(self, shifts: np.ndarray, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        return p + tps_basis(p, self.size, self.grid) @ shifts.reshape(-1, 2)

    def map_m(self, points: np.ndarray, size: tuple[int, int] | None = None) -> np.ndarray:
        """φ_M: where ``apply_m`` samples its input for output positions ``points`` (N×2 input pixels; of an input
        of ``size``, default the warp's own, when the input has another resolution of the same image)."""
        if size is None or tuple(size) == self.size:
            return self._map(self.m_shifts, points)
        scale = np.asarray(self.size, np.float64) / np.asarray(size, np.float64)
        return self._map(self.m_shifts, np.asarray(points, np.float64).reshape(-1, 2) * scale) / scale

    def map_w(self, points: np.ndarray) -> np.ndarray:
        """φ_W: where ``apply_w`` samples its input for output positions ``points`` (N×2 input pixels)."""
        return self._map(self.w_shifts, points)

    def displacement(self, which: str = "m", size: tuple[int, int] | None = None) -> np.ndarray:
        """Dense displacement field (h×w×2, pixels of ``size``, default the warp's size) of M or W."""
        shifts = {"m": self.m_shifts, "w": self.w_shifts}[which]
        w, h = self.size if size is None else (int(size[0]), int(size[1]))
        if (w, h) == self.size:
            d = _pixel_basis(w, h, self.grid) @ shifts.reshape(-1, 2).astype(np.float32)
        else:
            # Another resolution of the same image: evaluate at its pixel centres in warp pixels, scale back.
            sx, sy = self.size[0] / w, self.size[1] / h
            centres = pixel_centres((w, h)) * (sx, sy)
            d = (tps_basis(centres, self.size, self.grid) @ shifts.reshape(-1, 2)) / (sx, sy)
        return d.reshape(h, w, 2).astype(np.float32)

    # -- images ----------------------------------------------------------------------------------

    def _apply(self, which: str, image: np.ndarray) -> np.ndarray:
        img = np.asarray(image, dtype=np.float32)
        if img.ndim not in (2, 3) or min(img.shape[:2]) < 1:
            raise ImageError(f"a warp applies to an H×W or H×W×C image, got shape {img.shape}")
        h, w = img.shape[:2]
        if abs(w / h - self.size[0] / self.size[1]) > 0.02:
            raise ImageError(f"the warp is for {self.size[0]}×{self.size[1]} projector input images; "
                             f"a {w}×{h} image has another aspect ratio")
        shifts = self.m_shifts if which == "m" else self.w_shifts
        if not np.any(shifts):
            return img.copy()  # exact identity (bilinear sampling at pixel centres would be too, up to rounding)
        # The taps depend on the warp and the image's shape alone: kept, since stage C warps every capture's input.
        channels = img.shape[2] if img.ndim == 3 else 1
        taps = self._taps.get((which, w, h, channels))
        if taps is None:
            d = self.displacement(which, (w, h))
            c = pixel_centres((w, h)).reshape(h, w, 2)
            taps = self._taps[(which, w, h, channels)] = channel_taps(
                *bilinear_taps((w, h), c[..., 0] + d[..., 0], c[..., 1] + d[..., 1]), channels)
        out = sample_taps(img, *taps)
        return out if img.ndim == 3 else out[..., 0]

    def apply_m(self, image: np.ndarray) -> np.ndarray:
        """M(image): the input the *simulation* needs to reproduce what the real projector shows for ``image``."""
        return self._apply("m", image)

    def apply_w(self, image: np.ndarray) -> np.ndarray:
        """W(image): the input to give the *real* projector so it shows what the simulation shows for ``image``."""
        return self._apply("w", image)

    # -- serialisation ---------------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        return {"format": FORMAT, "model": "thin-plate spline, kernel r^2 log r^2, coordinates / max(width, height)",
                "grid": int(self.grid), "size": [int(v) for v in self.size],
                "control_points": "grid x grid from (0, 0) to (width, height), row-major [row][col]",
                "shifts": "input pixels (dx, dy); M samples its input at p + d_M(p), W at p + d_W(p)",
                "m_shifts": np.round(self.m_shifts, 6).tolist(), "w_shifts": np.round(self.w_shifts, 6).tolist()}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> "Warp":
        if not isinstance(d, dict):
            raise CalibrationError("a warp description must be a JSON object")
        if d.get("format", FORMAT) != FORMAT:
            raise CalibrationError(f"unknown warp format {d.get('format')!r} (expected {FORMAT!r})")
        try:
            size = tuple(int(v) for v in d["size"])
            return Warp(int(d["grid"]), size, np.asarray(d["m_shifts"], dtype=np.float64),
                        np.asarray(d["w_shifts"], dtype=np.float64))
        except KeyError as exc:
            raise CalibrationError(f"warp description lacks {exc}") from None
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"warp description is malformed: {exc}") from None


def solve_inverse(m_shifts: np.ndarray, size: tuple[int, int], grid: int, *, step: float | None = None
                  ) -> tuple[np.ndarray, float]:
    """W's shifts from M's (Eq. 8) by linear least squares, and the max residual |φ_M(φ_W(p)) − p| in px.

    Samples ``q`` every ``step`` px (default: ~100 per side) over the image and
    fits ``φ_W(φ_M(q)) = q``; the residual is then checked the other way round
    (W then M, i.e. ``W(M(z)) = z``) at pixel centres where ``φ_W(p)`` stays in the image.
    """
    w, h, n = _check_lattice(size, grid)
    m = np.asarray(m_shifts, dtype=np.float64).reshape(-1, 2)
    if not np.any(m):
        return np.zeros((n, n, 2)), 0.0
    step = step or max(1.0, max(w, h) / 100)
    xs, ys = np.arange(0.0, w + 1e-9, step), np.arange(0.0, h + 1e-9, step)
    q = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    x = q + tps_basis(q, size, n) @ m
    a = tps_basis(x, size, n)
    s_w = np.linalg.lstsq(a, q - x, rcond=None)[0]
    # Check W∘M on a grid offset from the fitting samples.
    p = q[::3] + 0.5 * step
    p = p[(p[:, 0] < w) & (p[:, 1] < h)]
    pw = p + tps_basis(p, size, n) @ s_w
    inside = (pw[:, 0] >= 0) & (pw[:, 0] <= w) & (pw[:, 1] >= 0) & (pw[:, 1] <= h)
    back = pw + tps_basis(pw, size, n) @ m
    err = np.linalg.norm(back - p, axis=1)[inside]
    return s_w.reshape(n, n, 2), float(err.max()) if err.size else 0.0


def grid_image(warp: Warp, size: tuple[int, int] | None = None, *, lines: int | None = None,
               exaggerate: float = 1.0) -> np.ndarray:
    """An image (h×w×3, [0, 1]) of the warp M for the UI: the regular lattice in grey, the deformed one in
    white (where M makes the simulation sample each lattice line), control points and their shifts in orange.

    ``exaggerate`` scales the displacements so warps of a pixel or two are visible.
    """
    w, h = warp.size if size is None else (int(size[0]), int(size[1]))
    sx, sy = w / warp.size[0], h / warp.size[1]
    lines = lines or (2 * (warp.grid - 1) + 1)
    img = np.full((h, w, 3), 0.08, np.float32)
    shift = 4  # cv2 drawing with sub-pixel precision (coordinates × 16)

    def poly(points_warp: np.ndarray) -> np.ndarray:
        d = warp.map_m(points_warp) - points_warp
        pts = (points_warp + exaggerate * d) * (sx, sy) - 0.5  # OpenCV draws on pixel centres
        return np.round(pts * (1 << shift)).astype(np.int32).reshape(-1, 1, 2)

    t = np.linspace(0.0, 1.0, 101)
    for k in np.linspace(0.0, 1.0, lines):
        for seg in (np.stack([t * warp.size[0], np.full_like(t, k * warp.size[1])], 1),
                    np.stack([np.full_like(t, k * warp.size[0]), t * warp.size[1]], 1)):
            plain = np.round((seg * (sx, sy) - 0.5) * (1 << shift)).astype(np.int32).reshape(-1, 1, 2)
            cv2.polylines(img, [plain], False, (0.35, 0.35, 0.35), 1, cv2.LINE_AA, shift)
            cv2.polylines(img, [poly(seg)], False, (1.0, 1.0, 1.0), 1, cv2.LINE_AA, shift)
    ctrl = np.stack(np.meshgrid(np.linspace(0, warp.size[0], warp.grid), np.linspace(0, warp.size[1], warp.grid)),
                    -1).reshape(-1, 2)
    tip = ctrl + exaggerate * warp.m_shifts.reshape(-1, 2)
    radius = max(2, round(min(w, h) / 150))
    for a, b in zip(ctrl, tip):
        pa = tuple(int(v) for v in np.round((a * (sx, sy) - 0.5) * (1 << shift)))
        pb = tuple(int(v) for v in np.round((b * (sx, sy) - 0.5) * (1 << shift)))
        cv2.line(img, pa, pb, (1.0, 0.55, 0.1), 1, cv2.LINE_AA, shift)
        cv2.circle(img, pb, radius << shift, (1.0, 0.55, 0.1), -1, cv2.LINE_AA, shift)
    return np.clip(img, 0.0, 1.0)


# ============================================================================ result

@dataclass
class WarpResult:
    """What stage B found and how well it closes the gap, in camera pixels."""

    warp: Warp
    losses: list[float]  # the data term (mean squared error over lit camera pixels) at each step
    corners_before_px: dict[str, float]
    corners_after_px: dict[str, float]
    seconds: float
    diagnostics: dict[str, np.ndarray] = field(default_factory=dict)
    #: max |φ_M(φ_W(p)) − p| over the input image, pixels (how well W inverts M).
    inverse_error_px: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {"warp": self.warp.to_dict(), "losses": [float(v) for v in self.losses],
                "corners_before_px": dict(self.corners_before_px), "corners_after_px": dict(self.corners_after_px),
                "inverse_error_px": float(self.inverse_error_px), "seconds": round(float(self.seconds), 2)}


# ============================================================================ captures → targets

@dataclass
class _Board:
    """One distinct checkerboard fed to the simulation and the target its captures give."""

    pattern: np.ndarray  # h×w grey, input image
    frame_base: np.ndarray  # native frame outside the input area (zeros inside), H_p×W_p×3
    target: np.ndarray  # camera H×W×3, averaged binarised captures in [0, 1]
    grey: np.ndarray  # camera H×W, averaged normalised captures (complements flipped), for corner finding
    names: list[str]
    square: int


def _grey(img: np.ndarray) -> np.ndarray:
    return img.mean(axis=2) if img.ndim == 3 else img


def _lit_from_contrast(contrast: np.ndarray) -> np.ndarray:
    """Pixels the projector lights clearly: white − black above 15 % of its 99th percentile (≥ 0.02)."""
    g = _grey(contrast)
    ref = float(np.percentile(g, 99)) if g.size else 0.0
    return g > max(0.02, 0.15 * ref)


def normalised_capture(image: np.ndarray, white: np.ndarray, black: np.ndarray) -> np.ndarray:
    """(image − black) / (white − black) per channel (0 where the projector does not reach)."""
    contrast = white - black
    lit = _lit_from_contrast(contrast)
    out = (image - black) / np.maximum(contrast, 1e-4)
    return np.where(lit[..., None], out, 0.0).astype(np.float32)


def binarise(normalised: np.ndarray, threshold: float = THRESHOLD) -> np.ndarray:
    """The paper's per-channel binarisation (1 where a channel exceeds ``threshold``)."""
    return (normalised > threshold).astype(np.float32)


def _erode(mask: np.ndarray, radius: int) -> np.ndarray:
    if radius <= 0:
        return mask
    k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    return cv2.erode(mask.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)


def _read(captures: CaptureSet, kind: str, entry: Entry, cam_size: tuple[int, int]) -> np.ndarray:
    img = captures.image(kind, name=entry.name)
    if (img.shape[1], img.shape[0]) != cam_size:
        raise CalibrationError(f"{captures.path / entry.file}: capture is {img.shape[1]}×{img.shape[0]} pixels, "
                               f"but the camera is {cam_size[0]}×{cam_size[1]}")
    return img


def _collect_boards(captures: CaptureSet, rig: Rig) -> tuple[list[_Board], np.ndarray]:
    """Check the checkerboard captures, binarise them and group them by pattern (complements merged)."""
    checkers = captures.entries_of("checker")
    if not checkers:
        raise CalibrationError(f"the capture set {captures.path} has no checkerboard capture; stage B (warp) "
                               "needs at least one projected checkerboard")
    for kind in ("white", "black"):
        if not captures.entries_of(kind):
            raise CalibrationError(f"the capture set {captures.path} has no '{kind}' capture; stage B needs white "
                                   "and black captures to binarise the checkerboard")
    cam_size = rig.camera.intrinsics.size
    proj = rig.projector
    if captures.projector.intrinsics.size != proj.intrinsics.size or captures.projector.input_size != proj.input_size:
        raise CalibrationError(f"the capture set's projector ({captures.projector.intrinsics.size}, input "
                               f"{captures.projector.input_size}) differs from the rig's ({proj.intrinsics.size}, "
                               f"input {proj.input_size})")
    we, be = captures.entry("white"), captures.entry("black")
    white, black = _read(captures, "white", we, cam_size), _read(captures, "black", be, cam_size)
    contrast = white - black
    lit = _lit_from_contrast(contrast)
    if float(_grey(contrast).max(initial=0.0)) < 0.02 or lit.mean() < 0.002:
        raise CalibrationError(f"the white capture {captures.path / we.file} is no brighter than the black one "
                               f"{captures.path / be.file}: the projector did not reach the camera (lens cap, "
                               "projector off, wrong display?) so the checkerboard cannot be binarised")
    core = _erode(lit, 1)
    (x0, y0), (w, h) = proj.input_offset, proj.input_size
    boards: list[_Board] = []
    for e in checkers:
        where = captures.path / e.file
        img = _read(captures, "checker", e, cam_size)
        n = normalised_capture(img, white, black)
        y = binarise(n)
        vals = n[core]
        ones = (vals > THRESHOLD).mean(axis=0)
        clear = ((vals > THRESHOLD) | (vals < 1.0 - THRESHOLD)).mean(axis=0)
        if core.sum() < 50 or np.any(ones < 0.1) or np.any(ones > 0.9) or np.any(clear < 0.5):
            raise CalibrationError(
                f"the checkerboard capture {where} cannot be binarised: between the black and white captures only "
                f"{100 * float(ones.min()):.0f}–{100 * float(ones.max()):.0f} % of its lit pixels are bright "
                f"(expected about half) and {100 * float(clear.min()):.0f} % are clearly bright or dark; was the "
                "checkerboard projected, in focus, and the camera's exposure the same as for white and black?")
        frame = captures.pattern("checker", name=e.name)
        if (frame.shape[1], frame.shape[0]) != proj.intrinsics.size:
            raise CalibrationError(f"{captures.path / (e.pattern or e.file)}: projected pattern is "
                                   f"{frame.shape[1]}×{frame.shape[0]}, but the projector frame is "
                                   f"{proj.intrinsics.width}×{proj.intrinsics.height}")
        pattern = _grey(frame[y0:y0 + h, x0:x0 + w]).astype(np.float32)
        if pattern.max() - pattern.min() < 0.5:
            raise CalibrationError(f"{captures.path / (e.pattern or e.file)}: the recorded checkerboard pattern "
                                   "has no contrast inside the projector input area")
        base = frame.copy()
        base[y0:y0 + h, x0:x0 + w] = 0.0
        square = int(e.params.get("square", max(4, round(min(w, h) / 12))))
        for b in boards:
            if b.square != square:
                continue
            if np.allclose(b.pattern, pattern, atol=0.02) and np.allclose(b.frame_base, base, atol=0.02):
                b.target = b.target + y
                b.grey = b.grey + _grey(n)
                b.names.append(e.name)
                break
            if np.allclose(b.pattern, 1.0 - pattern, atol=0.02) and not base.any() and not b.frame_base.any():
                # The complement: its dark squares are this board's lit ones (see the module notes).
                b.target = b.target + np.where(lit[..., None], 1.0 - y, 0.0)
                b.grey = b.grey + np.where(lit, 1.0 - _grey(n), 0.0)
                b.names.append(e.name)
                break
        else:
            boards.append(_Board(pattern, base.astype(np.float32), y, _grey(n), [e.name], square))
    for b in boards:
        b.target = (b.target / len(b.names)).astype(np.float32)
        b.grey = np.clip(b.grey / len(b.names), 0.0, 1.0).astype(np.float32)
    return boards, lit


# ============================================================================ the differentiable warp (Dr.Jit)

class _DrWarp:
    """M(c) in Dr.Jit: a bilinear ``dr.gather`` of the pattern at ``p + d(p)``, placed in the projector frame.

    The displacement ``d = B·s`` is computed outside (numpy) and enters as a Dr.Jit leaf with gradients
    enabled; the adjoint of that linear layer is ``Bᵀ·∂L/∂d``, one matrix product. (Writing ``Σ_k B_k s_k``
    in Dr.Jit works too, but its adjoint is 2n² separate broadcast reductions: 0.4 s a step at 180×180,
    more than the render.)
    """

    def __init__(self, mi: Any, size: tuple[int, int], frame_size: tuple[int, int], offset: tuple[int, int]) -> None:
        import drjit as dr

        self.mi, self.dr = mi, dr
        self.w, self.h = size
        c = pixel_centres(size)
        # Texel-centre coordinates of each output pixel before the warp (bilinear lookups subtract 0.5).
        self.u0 = mi.Float((c[:, 0] - 0.5).astype(np.float32))
        self.v0 = mi.Float((c[:, 1] - 0.5).astype(np.float32))
        fw, fh = frame_size
        fy, fx = np.mgrid[0:fh, 0:fw]
        ix, iy = fx - offset[0], fy - offset[1]
        inside = (ix >= 0) & (ix < self.w) & (iy >= 0) & (iy < self.h)
        idx = np.where(inside, iy * self.w + ix, 0).ravel()
        self.frame_shape = (fh, fw, 3)
        self.index3 = mi.UInt32(np.repeat(idx, 3).astype(np.uint32))
        self.inside3 = mi.Bool(np.repeat(inside.ravel(), 3))
        self.texture = mi.Float(0.0)

    def set_pattern(self, pattern: np.ndarray) -> None:
        self.texture = self.mi.Float(np.ascontiguousarray(pattern, dtype=np.float32).ravel())

    def frame(self, dx: Any, dy: Any, base: Any = None) -> Any:
        """The native frame (``mi.TensorXf``) showing the pattern sampled at ``p + (dx, dy)``; black outside."""
        mi, dr = self.mi, self.dr
        u, v = self.u0 + dx, self.v0 + dy
        i0, j0 = dr.floor(u), dr.floor(v)
        fu, fv = u - i0, v - j0  # the bilinear weights carry the gradient to (dx, dy)
        i0, j0 = mi.Int32(i0), mi.Int32(j0)
        value = mi.Float(0.0)
        for di, dj, wt in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)), (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
            ii, jj = i0 + di, j0 + dj
            ok = (ii >= 0) & (ii < self.w) & (jj >= 0) & (jj < self.h)
            texel = dr.gather(mi.Float, self.texture, mi.UInt32(dr.select(ok, jj * self.w + ii, 0)), ok)
            value = dr.fma(wt, texel, value)
        flat = dr.gather(mi.Float, value, self.index3, self.inside3)
        if base is not None:
            flat = flat + base
        return mi.TensorXf(flat, self.frame_shape)


# ============================================================================ corners

def _inner_corners(size: tuple[int, int], square: int) -> np.ndarray:
    w, h = size
    xs = np.arange(square, w - square // 2, square, dtype=np.float64)
    ys = np.arange(square, h - square // 2, square, dtype=np.float64)
    xs, ys = xs[xs < w], ys[ys < h]
    return np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)


def _saddle_ok(img: np.ndarray, pts: np.ndarray, r: float, contrast: float = 0.25) -> np.ndarray:
    """A checkerboard corner: the four diagonal neighbours alternate bright/dark by at least ``contrast``."""
    if len(pts) == 0:
        return np.zeros(0, bool)
    offs = np.array([[-r, -r], [r, -r], [r, r], [-r, r]])
    vals = np.stack([sample_bilinear(img, pts[:, 0] + o[0], pts[:, 1] + o[1]) for o in offs], axis=1)
    a, b = vals[:, 0] + vals[:, 2], vals[:, 1] + vals[:, 3]
    same = (np.abs(vals[:, 0] - vals[:, 2]) < contrast) & (np.abs(vals[:, 1] - vals[:, 3]) < contrast)
    return same & (np.abs(a - b) / 2 > contrast)


@dataclass
class _Corners:
    capture: np.ndarray  # N×2 camera px
    before: np.ndarray
    after: np.ndarray

    def stats(self, which: str) -> dict[str, float]:
        other = self.before if which == "before" else self.after
        return distance_stats(np.linalg.norm(self.capture - other, axis=1))


def distance_stats(d: np.ndarray, top: float = 100.0) -> dict[str, float]:
    """Median, mean and largest of distances (px), as stage B reports them; ``top`` < 100: that percentile stands
    for the largest (decoded Gray code has outliers a checkerboard corner fit does not)."""
    if d.size == 0:
        return {"median": float("nan"), "mean": float("nan"), "max": float("nan"), "n": 0}
    return {"median": round(float(np.median(d)), 4), "mean": round(float(d.mean()), 4),
            "max": round(float(np.percentile(d, top)), 4), "n": int(d.size)}


def measure_corners(capture: np.ndarray, before: np.ndarray, after: np.ndarray, guesses: np.ndarray,
                    square_cam: float, valid: np.ndarray) -> _Corners:
    """Sub-pixel inner corners in three grey camera images (normalised capture, simulation before and
    after the warp) near ``guesses``; keeps corners found cleanly in all three, inside ``valid``.

    The capture's corners are searched from the guesses alone (not from the warp), first with a window of
    0.4 squares — so they are found up to that far from the prediction — then refined with a third of a
    square; the simulation after the warp is searched from the capture's corners, as closely. A corner is
    dropped unless all three are clean checkerboard saddles; ``n`` in the statistics says how many remain.
    """

    h, w = capture.shape
    g = guesses[np.all(np.isfinite(guesses), axis=1)]
    coarse = int(max(2, 0.4 * square_cam))
    fine = int(max(2, min(10, square_cam // 3)))
    inner = _erode(valid, fine + 2)
    ij = np.clip(np.floor(g).astype(int), 0, [w - 1, h - 1])
    g = g[inner[ij[:, 1], ij[:, 0]]]
    if len(g) == 0:
        return _Corners(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2)))

    def find(img: np.ndarray, start: np.ndarray) -> np.ndarray:
        return refine_corners(img, refine_corners(img, start, coarse), fine)

    cap = find(capture, g)
    bef = find(before, g)
    aft = find(after, cap)
    keep = np.ones(len(g), bool)
    r = max(1.5, 0.3 * square_cam)
    for img, pts, start in ((capture, cap, g), (before, bef, g), (after, aft, cap)):
        keep &= np.all(np.isfinite(pts), axis=1) & (np.linalg.norm(pts - start, axis=1) < 0.45 * square_cam)
        keep &= _saddle_ok(img, pts, r)
        pij = np.clip(np.floor(pts).astype(int), 0, [w - 1, h - 1])
        keep &= inner[pij[:, 1], pij[:, 0]]
    return _Corners(cap[keep], bef[keep], aft[keep])


# ============================================================================ stage B

def _lr(it: int, iterations: int, lr0: float) -> float:
    """Cosine decay to 5 % of ``lr0``."""
    t = it / max(1, iterations - 1)
    return lr0 * (0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * t)))


def _sigma(it: int, iterations: int, sigma0: float, sigma1: float) -> float:
    """Geometric coarse-to-fine blur over the first 70 % of the iterations, then ``sigma1``."""
    t = min(1.0, it / max(1.0, 0.7 * (iterations - 1)))
    return sigma0 * (sigma1 / sigma0) ** t


def _blur(pattern: np.ndarray, sigma: float) -> np.ndarray:
    if sigma < 0.3:
        return pattern
    return cv2.GaussianBlur(pattern, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)


def estimate_warp(captures: CaptureSet, surface: SurfaceMesh, rig: Rig, *, grid: int = DEFAULT_GRID,
                  iterations: int = 70, spp: int = 1, learning_rate: float | None = None,
                  bending: float = 10.0, l2: float = 0.1, progress: Progress | None = None,
                  cancel: Cancel | None = None, seed: int = 0) -> WarpResult:
    """Fit M by differentiable rendering against the binarised checkerboard captures, then W (Eq. 7–8).

    ``rig`` carries the projector pose from stage A and ``surface`` the
    reconstructed mesh (with its albedo). ``iterations`` Adam steps at
    ``spp`` samples per pixel (one render and its adjoint per distinct
    checkerboard per step); ``learning_rate`` in input pixels per step
    (default 0.4 % of the input's longer side); ``bending``/``l2`` weight the
    TPS bending energy and the squared shifts, both measured with shifts in
    units of the input's longer side, against a data loss that is a mean
    squared error over lit camera pixels. (In those units both the data
    gradient and the regulariser's scale alike with the resolution, so one
    weight serves every size; measured on 'vedge' at 0.3 scale, a 30× stronger
    bending weight stops the warp short — 0.5 px instead of 0.13 px — while
    none at all lets M wiggle: W∘M 0.07 px instead of 0.002 px.)
    ``progress(message, fraction)`` is
    called as it goes; ``cancel()`` returning True stops it with
    :class:`Cancelled`. Bad captures raise :class:`CalibrationError`
    naming the file at fault.
    """

    t_start = time.perf_counter()
    say = progress or (lambda msg, frac: None)

    def check_cancel() -> None:
        if cancel is not None and cancel():
            raise Cancelled("stage B (warp) was cancelled; no warp was stored")

    if not isinstance(iterations, int) or iterations < 0:
        raise CalibrationError(f"stage B iterations must be a whole number ≥ 0, got {iterations!r}")
    proj = rig.projector
    size = proj.input_size
    _check_lattice(size, grid)
    say("reading and binarising the checkerboard captures", 0.0)
    boards, lit_capture = _collect_boards(captures, rig)
    check_cancel()

    mi = backend.mitsuba()
    import drjit as dr

    say("building the simulation", 0.03)
    try:
        model = ForwardModel(rig, surface, bounces=0, spp=spp, smoothing_eps=0.0, clamp=False, seed=seed)
    except ProCamError as exc:
        raise CalibrationError(f"stage B cannot simulate the projection: {exc}") from None
    white_frame = (captures.pattern("white") if captures.entry("white").pattern
                   else proj.frame_from_input(np.ones((size[1], size[0], 3), np.float32)))
    white_model = model.render(white_frame, spp=max(16, spp), seed=seed + 1_000_003)
    lit_model = _lit_from_contrast(white_model)
    inv_white = np.where(lit_model[..., None], 1.0 / np.maximum(white_model, 1e-6), 0.0).astype(np.float32)
    # Loss pixels: lit in the capture and in the simulation, away from both footprints' borders.
    mask = _erode(lit_capture & lit_model, 2)
    overlap = mask.sum() / max(1, _erode(lit_capture, 2).sum())
    if mask.sum() < 200 or overlap < 0.3:
        raise CalibrationError(
            f"stage B: the simulated projection covers only {100 * overlap:.0f} % of the lit area of the white "
            f"capture {captures.path / captures.entry('white').file}; the projector pose from stage A (or the "
            "surface) is too far off for a warp to bridge")
    w, h = size
    n = int(grid)
    scale = float(max(w, h))
    lr0 = learning_rate if learning_rate is not None else 0.004 * scale
    square = min(b.square for b in boards)
    sigma0, sigma1 = max(1.0, square / 5.0), 0.5

    warp_dr = _DrWarp(mi, size, proj.intrinsics.size, proj.input_offset)
    basis = _pixel_basis(w, h, n)
    mask_dr = mi.Float(np.repeat(mask.ravel(), 3).astype(np.float32))
    inv_white_dr = mi.Float(inv_white.ravel())
    n_mask = float(mask.sum() * 3)
    targets = [mi.Float(np.where(mask[..., None], b.target, 0.0).astype(np.float32).ravel()) for b in boards]
    bases = [mi.Float(b.frame_base.ravel()) if b.frame_base.any() else None for b in boards]
    blurred: list[np.ndarray] = [b.pattern for b in boards]
    energy = bending_matrix(size, n)

    s = np.zeros((n * n, 2))
    m1, m2 = np.zeros_like(s), np.zeros_like(s)
    beta1, beta2 = 0.9, 0.99
    losses: list[float] = []
    tail: list[np.ndarray] = []
    tail_start = int(0.85 * iterations)
    current_sigma = None
    for it in range(iterations):
        check_cancel()
        sigma = round(_sigma(it, iterations, sigma0, sigma1), 2)
        if sigma != current_sigma:
            blurred = [_blur(b.pattern, sigma) for b in boards]
            current_sigma = sigma
        d = basis @ s.astype(np.float32)
        dx, dy = mi.Float(np.ascontiguousarray(d[:, 0])), mi.Float(np.ascontiguousarray(d[:, 1]))
        dr.enable_grad(dx, dy)
        loss = mi.Float(0.0)
        for k, _board in enumerate(boards):
            warp_dr.set_pattern(blurred[k])
            frame = warp_dr.frame(dx, dy, bases[k])
            image = model.render_dr(frame, seed=seed + 2 * it + 1, spp=spp)
            r = image.array * inv_white_dr
            diff = (r - targets[k]) * mask_dr
            loss = loss + dr.sum(dr.square(diff)) / (n_mask * len(boards))
        dr.backward(loss)
        grad_d = np.stack([np.array(dr.grad(dx)), np.array(dr.grad(dy))], axis=1)
        g = (basis.T @ grad_d).astype(np.float64)  # the TPS layer's adjoint
        data = float(loss[0]) if dr.width(loss) else float(loss)
        if not (np.all(np.isfinite(g)) and math.isfinite(data)):
            raise CalibrationError("stage B diverged (NaN in the warp gradient); check the surface mesh and pose")
        g += (2.0 * bending * (energy @ s) + 2.0 * l2 * s) / scale ** 2  # regularisers on s / scale
        losses.append(data)
        m1 = beta1 * m1 + (1 - beta1) * g
        m2 = beta2 * m2 + (1 - beta2) * g * g
        mh, vh = m1 / (1 - beta1 ** (it + 1)), m2 / (1 - beta2 ** (it + 1))
        # The floor on Adam's denominator (0.1 % of the largest) keeps control points whose gradient is
        # nearly zero (no camera pixel sees their neighbourhood) from taking full-size noisy steps.
        s = s - _lr(it, iterations, lr0) * mh / (np.sqrt(vh) + 1e-12 + 1e-3 * np.sqrt(vh).max())
        if it >= tail_start:
            tail.append(s.copy())
        if it % 5 == 0 or it == iterations - 1:
            say(f"iteration {it + 1}/{iterations}, loss {data:.4f}", 0.05 + 0.75 * (it + 1) / iterations)
    # The average of the last iterates: Adam's steps jitter with the render noise; their mean does not.
    m_shifts = (np.mean(tail, axis=0) if tail else s).reshape(n, n, 2)
    check_cancel()

    say("solving W from M", 0.82)
    w_shifts, inverse_error = solve_inverse(m_shifts, size, n)
    warp = Warp(n, size, m_shifts, w_shifts)

    say("measuring checkerboard corners before and after", 0.85)
    board = boards[0]
    x0, y0 = proj.input_offset

    def frame_of(pattern: np.ndarray) -> np.ndarray:
        frame = board.frame_base.copy()
        frame[y0:y0 + h, x0:x0 + w] = pattern[..., None]
        return frame

    render_spp = max(16, spp)
    before = model.render(frame_of(board.pattern), spp=render_spp, seed=seed + 2_000_003) * inv_white
    after = model.render(frame_of(warp.apply_m(board.pattern)), spp=render_spp, seed=seed + 3_000_017) * inv_white
    check_cancel()
    # With both phases, (n₀ + 1 − n₁)/2 of the normalised captures is the cleanest picture of the board.
    capture_grey = board.grey
    before_grey = np.clip(_grey(before), 0.0, 1.0).astype(np.float32)
    after_grey = np.clip(_grey(after), 0.0, 1.0).astype(np.float32)

    corners_in = _inner_corners(size, board.square)
    guesses = frame_points_to_camera(model.rig, surface, corners_in + (x0, y0))
    good = guesses[np.all(np.isfinite(guesses), axis=1)]
    if len(good) > 1:
        tree = np.linalg.norm(good[:, None] - good[None], axis=2)
        np.fill_diagonal(tree, np.inf)
        square_cam = float(np.median(tree.min(axis=1)))
    else:
        square_cam = 8.0
    corners = measure_corners(capture_grey, before_grey, after_grey, guesses, square_cam, mask)

    def rgb(grey: np.ndarray) -> np.ndarray:
        return np.repeat(np.clip(grey, 0, 1)[..., None], 3, axis=2).astype(np.float32)

    def compare(sim: np.ndarray) -> np.ndarray:
        # Red: binarised capture, green: simulation; aligned squares are yellow, misalignment shows red/green.
        t = _grey(board.target)
        return np.stack([t, np.clip(sim, 0, 1), np.zeros_like(t)], axis=2).astype(np.float32) * mask[..., None]

    diagnostics = {"checker_capture": rgb(capture_grey), "checker_target": board.target.copy(),
                   "render_before": rgb(before_grey), "render_after": rgb(after_grey),
                   "compare_before": compare(before_grey), "compare_after": compare(after_grey),
                   "grid": grid_image(warp, size, exaggerate=1.0)}
    result = WarpResult(warp, losses, corners.stats("before"), corners.stats("after"),
                        time.perf_counter() - t_start, diagnostics, inverse_error)
    say(f"corners {result.corners_before_px['median']:.2f} px → {result.corners_after_px['median']:.2f} px "
        "(median)", 1.0)
    return result


__all__ = ["DEFAULT_GRID", "THRESHOLD", "Warp", "WarpResult", "bending_matrix", "binarise", "distance_stats",
           "estimate_warp", "grid_image", "measure_corners", "normalised_capture", "sample_bilinear", "solve_inverse",
           "tps_basis"]
