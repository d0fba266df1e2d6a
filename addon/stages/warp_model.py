"""The warp model of stage B: a thin-plate spline on the projector input image, the maps M and W it gives,
and bilinear sampling through them (estimated by ``stages/warp.py`` and ``stages/graycode_warp.py``; applied by
stage C, the metrics and the steps).

The paper models what the real projector does to its input that f̂ does not
as a warp, ``f(x) ≈ f̂(z)`` with ``x = W(z)``, and ``M`` its inverse
(``z = M(x)``).

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
    n²) fixed by the lattice (docs/developer.md, "Facts about the dependencies"): we build ``B`` once. In the
    optimisation ``d = B·s`` enters Dr.Jit as a leaf, a bilinear
    ``dr.gather`` of the pattern with differentiable weights builds the
    projector frame, and the render's adjoint arrives at ``d``; the linear
    layer's adjoint ``Bᵀ·∂L/∂d`` is then one matrix product (stages/warp.py,
    ``_DrWarp``, says why not in Dr.Jit).

W from M (Eq. 8)
    Closed form. ``W(M(z)) = z ∘ φ_M ∘ φ_W`` is ``z`` when ``φ_W = φ_M⁻¹``. We
    push a dense grid of points ``q`` through ``φ_M``, giving pairs
    ``(φ_M(q), q)``, and solve the linear least-squares problem
    ``B(φ_M(q)) · s_W = q − φ_M(q)`` for W's shifts (the TPS is linear in
    them). The residual ``|φ_M(φ_W(p)) − p|`` over the image is reported; it
    is far below 0.1 px for warps of a few pixels.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..errors import CalibrationError, ImageError


DEFAULT_GRID = 8
FORMAT = "procam-warp-tps"


# ============================================================================ thin-plate spline

def _tps_kernel(r2: np.ndarray) -> np.ndarray:
    """U(r) = r² log r² (from squared distances), 0 at r = 0."""
    return np.where(r2 > 0.0, r2 * np.log(np.maximum(r2, 1e-300)), 0.0)


def check_lattice(size: tuple[int, int], grid: int) -> tuple[int, int, int]:
    """(width, height, grid) of a lattice, or a CalibrationError saying which is bad."""
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
    w, h, n = check_lattice(size, grid)
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
def pixel_basis(w: int, h: int, grid: int) -> np.ndarray:
    """The basis at every pixel centre, float32 (92 MB for 600×600 and 8×8), built once per lattice."""
    b = tps_basis(pixel_centres((w, h)), (w, h), grid).astype(np.float32)
    b.setflags(write=False)
    return b


def bending_matrix(size: tuple[int, int], grid: int) -> np.ndarray:
    """E (n²×n²): the TPS bending energy of one coordinate's shifts ``s`` is ``s @ E @ s`` (up to 8π).

    Zero for affine shift fields; in normalised coordinates, so shifts in pixels give px².
    """
    w, h, n = check_lattice(size, grid)
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
        w, h, n = check_lattice(self.size, self.grid)
        object.__setattr__(self, "size", (w, h))
        object.__setattr__(self, "grid", n)
        for name in ("m_shifts", "w_shifts"):
            a = np.asarray(getattr(self, name), dtype=np.float64)
            if a.shape != (n, n, 2):
                raise CalibrationError(f"warp {name} must be {n}×{n}×2 (grid × grid × (dx, dy)), got shape "
                                       f"{a.shape}")
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
    def identity(size: tuple[int, int], grid: int = DEFAULT_GRID) -> Warp:
        """No warp: both maps are the identity."""
        w, h, n = check_lattice(size, grid)
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
            d = pixel_basis(w, h, self.grid) @ shifts.reshape(-1, 2).astype(np.float32)
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
    def from_dict(d: dict[str, Any]) -> Warp:
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
    w, h, n = check_lattice(size, grid)
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


__all__ = ["DEFAULT_GRID", "FORMAT", "Warp", "bending_matrix", "bilinear_taps", "channel_taps", "check_lattice",
           "grid_image", "pixel_basis", "pixel_centres", "sample_bilinear", "sample_taps", "solve_inverse",
           "tps_basis"]
