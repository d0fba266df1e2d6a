"""Stage B — the image warp (paper Sec. IV-B, Eq. 6–8): what the real projector does to its input that f̂ does not.

After stage A the simulated projection f̂ still lands slightly off the real
one: the pose is not exact, the reconstructed surface is not the real one, the
camera lens distorts. The paper models the rest as a warp of the projector
input, ``f(x) ≈ f̂(z)`` with ``x = W(z)``. Eq. 6 cannot be differentiated (f is
the real world), so it fits the *inverse* warp ``M`` through the simulation,

    M = argmin ‖ y − f̂(M(c)) ‖²                                       (Eq. 7)

with ``c`` the projected checkerboard and ``y`` its binarised capture, and then
``W`` from ``W(M(z)) ≈ z`` (Eq. 8).

The warp model (the thin-plate spline, M and W, sampling) is ``stages/warp_model.py``.

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

import math
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..capture.format import CaptureSet, Entry
from ..capture.patterns import refine_corners
from ..errors import CalibrationError, Cancelled, ProCamError
from ..progress import Cancel, Progress
from ..render import backend
from ..render.forward import ForwardModel
from ..rig.model import Rig
from ..surface.mesh import SurfaceMesh, frame_points_to_camera
from .warp_model import (DEFAULT_GRID, Warp, bending_matrix, check_lattice, grid_image, pixel_basis, pixel_centres,
                         sample_bilinear, solve_inverse)


#: The paper's per-channel binarisation threshold, applied to the normalised capture (see module notes).
THRESHOLD = 0.7


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
    check_lattice(size, grid)
    say("reading and binarising the checkerboard captures", 0.0)
    boards, lit_capture = _collect_boards(captures, rig)
    check_cancel()

    mi = backend.mitsuba()
    say("building the simulation", 0.03)
    model, inv_white, mask = _simulation(captures, surface, rig, lit_capture, spp=spp, seed=seed)
    fit = _FitM(mi, model, boards, mask, inv_white, grid=grid, spp=spp, seed=seed)
    lr0 = learning_rate if learning_rate is not None else 0.004 * fit.scale
    m_shifts, losses = fit.run(iterations, lr0, bending, l2, say, check_cancel)
    check_cancel()

    say("solving W from M", 0.82)
    w_shifts, inverse_error = solve_inverse(m_shifts, size, fit.n)
    warp = Warp(fit.n, size, m_shifts, w_shifts)

    say("measuring checkerboard corners before and after", 0.85)
    corners, diagnostics = _measure(model, surface, boards[0], warp, inv_white, mask, spp=spp, seed=seed,
                                    check_cancel=check_cancel)
    result = WarpResult(warp, losses, corners.stats("before"), corners.stats("after"),
                        time.perf_counter() - t_start, diagnostics, inverse_error)
    say(f"corners {result.corners_before_px['median']:.2f} px → {result.corners_after_px['median']:.2f} px "
        "(median)", 1.0)
    return result


def _simulation(captures: CaptureSet, surface: SurfaceMesh, rig: Rig, lit_capture: np.ndarray, *, spp: int,
                seed: int) -> tuple[ForwardModel, np.ndarray, np.ndarray]:
    """Stage B's direct-light model, 1 / its white (0 where unlit), and the loss pixels: lit in the capture and
    in the simulation, away from both footprints' borders."""
    proj = rig.projector
    size = proj.input_size
    try:
        model = ForwardModel(rig, surface, bounces=0, spp=spp, smoothing_eps=0.0, clamp=False, seed=seed)
    except ProCamError as exc:
        raise CalibrationError(f"stage B cannot simulate the projection: {exc}") from None
    white_frame = (captures.pattern("white") if captures.entry("white").pattern
                   else proj.frame_from_input(np.ones((size[1], size[0], 3), np.float32)))
    white_model = model.render(white_frame, spp=max(16, spp), seed=seed + 1_000_003)
    lit_model = _lit_from_contrast(white_model)
    inv_white = np.where(lit_model[..., None], 1.0 / np.maximum(white_model, 1e-6), 0.0).astype(np.float32)
    mask = _erode(lit_capture & lit_model, 2)
    overlap = mask.sum() / max(1, _erode(lit_capture, 2).sum())
    if mask.sum() < 200 or overlap < 0.3:
        raise CalibrationError(
            f"stage B: the simulated projection covers only {100 * overlap:.0f} % of the lit area of the white "
            f"capture {captures.path / captures.entry('white').file}; the projector pose from stage A (or the "
            "surface) is too far off for a warp to bridge")
    return model, inv_white, mask


class _FitM:
    """The fit of M's shifts (Eq. 7): Adam on the shifts through the renders' adjoint, coarse to fine."""

    def __init__(self, mi: Any, model: ForwardModel, boards: list[_Board], mask: np.ndarray, inv_white: np.ndarray,
                 *, grid: int, spp: int, seed: int) -> None:
        proj = model.rig.projector
        size = proj.input_size
        self.mi, self.model, self.boards, self.spp, self.seed = mi, model, boards, spp, seed
        w, h = size
        self.n = n = int(grid)
        self.scale = float(max(w, h))
        square = min(b.square for b in boards)
        self.sigma0, self.sigma1 = max(1.0, square / 5.0), 0.5
        self.warp_dr = _DrWarp(mi, size, proj.intrinsics.size, proj.input_offset)
        self.basis = pixel_basis(w, h, n)
        self.mask_dr = mi.Float(np.repeat(mask.ravel(), 3).astype(np.float32))
        self.inv_white_dr = mi.Float(inv_white.ravel())
        self.n_mask = float(mask.sum() * 3)
        self.targets = [mi.Float(np.where(mask[..., None], b.target, 0.0).astype(np.float32).ravel()) for b in boards]
        self.bases = [mi.Float(b.frame_base.ravel()) if b.frame_base.any() else None for b in boards]
        self.energy = bending_matrix(size, n)

    def gradient(self, s: np.ndarray, blurred: list[np.ndarray], it: int) -> tuple[np.ndarray, float]:
        """The data loss's gradient with respect to the shifts ``s`` (through the TPS layer's adjoint), and the loss."""
        import drjit as dr

        mi = self.mi
        d = self.basis @ s.astype(np.float32)
        dx, dy = mi.Float(np.ascontiguousarray(d[:, 0])), mi.Float(np.ascontiguousarray(d[:, 1]))
        dr.enable_grad(dx, dy)
        loss = mi.Float(0.0)
        for k, _board in enumerate(self.boards):
            self.warp_dr.set_pattern(blurred[k])
            frame = self.warp_dr.frame(dx, dy, self.bases[k])
            image = self.model.render_dr(frame, seed=self.seed + 2 * it + 1, spp=self.spp)
            r = image.array * self.inv_white_dr
            diff = (r - self.targets[k]) * self.mask_dr
            loss = loss + dr.sum(dr.square(diff)) / (self.n_mask * len(self.boards))
        dr.backward(loss)
        grad_d = np.stack([np.array(dr.grad(dx)), np.array(dr.grad(dy))], axis=1)
        g = (self.basis.T @ grad_d).astype(np.float64)  # the TPS layer's adjoint
        data = float(loss[0]) if dr.width(loss) else float(loss)
        if not (np.all(np.isfinite(g)) and math.isfinite(data)):
            raise CalibrationError("stage B diverged (NaN in the warp gradient); check the surface mesh and pose")
        return g, data

    def run(self, iterations: int, lr0: float, bending: float, l2: float, say: Progress,
            check_cancel: Any) -> tuple[np.ndarray, list[float]]:
        """M's shifts (n×n×2: the mean of the last 15 % of the iterates) and the data loss at each step."""
        n, scale = self.n, self.scale
        blurred: list[np.ndarray] = [b.pattern for b in self.boards]
        s = np.zeros((n * n, 2))
        m1, m2 = np.zeros_like(s), np.zeros_like(s)
        beta1, beta2 = 0.9, 0.99
        losses: list[float] = []
        tail: list[np.ndarray] = []
        tail_start = int(0.85 * iterations)
        current_sigma = None
        for it in range(iterations):
            check_cancel()
            sigma = round(_sigma(it, iterations, self.sigma0, self.sigma1), 2)
            if sigma != current_sigma:
                blurred = [_blur(b.pattern, sigma) for b in self.boards]
                current_sigma = sigma
            g, data = self.gradient(s, blurred, it)
            g += (2.0 * bending * (self.energy @ s) + 2.0 * l2 * s) / scale ** 2  # regularisers on s / scale
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
        return (np.mean(tail, axis=0) if tail else s).reshape(n, n, 2), losses


def _measure(model: ForwardModel, surface: SurfaceMesh, board: _Board, warp: Warp, inv_white: np.ndarray,
             mask: np.ndarray, *, spp: int, seed: int, check_cancel: Any) -> tuple[_Corners, dict[str, np.ndarray]]:
    """The checkerboard's inner corners in the capture and in the simulation before and after the warp, and the
    diagnostic images."""
    proj = model.rig.projector
    w, h = size = proj.input_size
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
    return corners, diagnostics

__all__ = ["THRESHOLD", "WarpResult", "binarise", "distance_stats", "estimate_warp", "measure_corners",
           "normalised_capture"]
