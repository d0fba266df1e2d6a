"""Stage B from the Gray code, for capture sets without a projected checkerboard.

Many real sessions hold only Gray code, white and black (OpenCV's structured-light
sequence, a board session for ``procam calibrate-rig``). Stage B's own fit needs
checkerboard captures; the Gray code gives the same information more densely:
each decoded camera pixel names the real projector texel it sees, and the
calibrated rig and surface name the texel the model says it sees. Their
difference is M's shift there (``apply_m(c)(q) = c(q + d_M(q))``: the model's
texel ``q`` shows what the real projector put at ``q + d_M(q)``), so M is a
regularised linear least-squares fit of the TPS shifts to those pairs, and W its
inverse (:func:`.warp_model.solve_inverse`), as for the checkerboard warp.

The decoded texel is whole (±0.5 texel), but unbiased, and a few thousand pairs
per control point average it out. Decoding errors (dark paint, grazing light)
are outliers, dropped by their distance from a first fit.
"""

from __future__ import annotations

import time

import numpy as np

from ..capture.format import CaptureSet
from ..capture.patterns import decode_gray_code_set
from ..errors import CalibrationError, CaptureError
from ..rig.model import Rig
from ..surface.mesh import SurfaceMesh
from .transport import camera_to_input_of
from .warp import WarpResult, distance_stats
from .warp_model import DEFAULT_GRID, Warp, bending_matrix, grid_image, solve_inverse, tps_basis

#: Pairs the fit uses at most (a fixed random subset of the decoded lit pixels).
MAX_PAIRS = 60000
#: Fewer decoded pairs than this cannot pin a warp.
MIN_PAIRS = 500
#: A pair farther than this many texels from the first fit is a decoding error.
OUTLIER_TEXELS = 3.0
#: Weight of the TPS bending energy (shifts in input texels) against the mean squared pair residual.
BENDING = 1e-3


def warp_from_graycode(captures: CaptureSet, surface: SurfaceMesh, rig: Rig, *, grid: int = DEFAULT_GRID,
                       seed: int = 0) -> WarpResult:
    """M and W fitted to the decoded Gray code against the model's camera → input correspondence.

    The result's ``corners_*_px`` hold the distance, in input texels, between the decoded texel and the model's
    before and after the warp (``max``: the 99th percentile), over the pairs kept."""
    t0 = time.perf_counter()
    try:
        dec = decode_gray_code_set(captures)
    except CaptureError as exc:
        raise CalibrationError(f"stage B (warp from the Gray code): {exc}") from None
    cam_size = captures.camera.intrinsics.size
    size = rig.projector.input_size
    u, lit = camera_to_input_of(rig, surface, cam_size)
    ox, oy = rig.projector.input_offset
    # Decoded positions are native-frame pixels (the coded grid's offset included); the warp's are input texels.
    real = dec.coords.astype(np.float64) - np.array([ox, oy], np.float64)
    w, h = size
    use = dec.valid & lit & np.isfinite(real).all(axis=2)
    use &= (real[..., 0] >= 0) & (real[..., 0] <= w) & (real[..., 1] >= 0) & (real[..., 1] <= h)
    ys, xs = np.nonzero(use)
    if len(xs) < MIN_PAIRS:
        raise CalibrationError(f"stage B (warp from the Gray code): only {len(xs)} camera pixels decode where the "
                               "calibrated projector lights the surface; the pose or the Gray-code captures are off "
                               "(check the pose diagnostics), or add a projected checkerboard to the capture set")
    if len(xs) > MAX_PAIRS:
        pick = np.sort(np.random.default_rng(seed).choice(len(xs), MAX_PAIRS, replace=False))
        ys, xs = ys[pick], xs[pick]
    q, p = u[ys, xs].astype(np.float64), real[ys, xs]
    d = p - q
    basis = tps_basis(q, size, grid)
    # Shifts in texels; the bending energy is in normalised coordinates, so scale it to texels² per pair.
    reg = BENDING * bending_matrix(size, grid) * float(max(w, h)) ** 2 / len(q)
    keep = np.ones(len(q), bool)
    shifts = np.zeros((grid * grid, 2))
    for _ in range(3):
        a = basis[keep]
        shifts = np.linalg.solve(a.T @ a / keep.sum() + reg + 1e-9 * np.eye(grid * grid), a.T @ d[keep] / keep.sum())
        resid = np.linalg.norm(d - basis @ shifts, axis=1)
        new = resid < max(OUTLIER_TEXELS, 3.0 * float(np.median(resid[keep])))
        if np.array_equal(new, keep):
            break
        keep = new
    before, after = np.linalg.norm(d[keep], axis=1), np.linalg.norm((d - basis @ shifts)[keep], axis=1)
    m_shifts = shifts.reshape(grid, grid, 2)
    w_shifts, inverse_err = solve_inverse(m_shifts, size, grid)
    warp = Warp(grid, size, m_shifts, w_shifts)
    return WarpResult(warp, [float(np.mean(after ** 2))], distance_stats(before, 99), distance_stats(after, 99),
                      time.perf_counter() - t0, {"grid": grid_image(warp, size)}, inverse_err)


__all__ = ["warp_from_graycode"]
