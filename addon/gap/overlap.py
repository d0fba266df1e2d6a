"""What only the overlap of two projectors shows: each projector's lens falloff (vignetting), which calibration
takes into the albedo.

Where one projector lights the surface alone, its white capture over the simulated irradiance is the paint times
that projector's falloff, and calibration keeps it as the albedo: the falloff is absorbed, and a diagnosis of that
projector's patterns against the calibrated model cannot see it (measured on the lab: a falloff of 0.21 injected
into projector 2 alone fitted −0.042 there, against −0.041 for projector 1, which has none). Where two projectors
light the same point, each gives its own reading of the same paint, and the paint cancels in their ratio::

    log(a_2 / a_1) = c + log(1 − f_2 ρ_2²) − log(1 − f_1 ρ_1²)   ≈   c − f_2 ρ_2² + f_1 ρ_1²

with ``a_k`` projector k's reading ((white − black) / simulated irradiance), ``ρ_k`` the point's field-angle radius
in projector k's image over its farthest corner's (:func:`..gap.models.vignetting_radius`, the diagnosis's own
``vignetting`` model with its exponent 2) and ``c`` what else differs by a constant (one lamp brighter than the
other). Across a strip-shaped overlap ``ρ_1²`` rises as ``ρ_2²`` falls, so their sum alone would be pinned; the
overlap's height, where both rise together, pins each.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..render.forward import ForwardModel
from ..stages.transport import camera_to_input
from ..surface.mesh import SurfaceMesh
from .models import vignetting_radius

#: Camera pixels the two projectors must share for the fit (fewer: nothing said).
MIN_PIXELS = 200
#: A reading counts where the projector's simulated irradiance is above this share of its 99th percentile.
LIT = 0.25


def readings(calibration: Any, captures: Any) -> tuple[np.ndarray, np.ndarray]:
    """One projector's reading of the paint per camera pixel, ``(white − black) / irradiance`` (channels
    averaged, NaN where it does not light or the white capture is saturated), and its vignetting radius there."""
    white, black = captures.image("white"), captures.image("black")
    s = calibration.surface
    flat = SurfaceMesh(s.vertices, s.faces, s.uvs, np.ones((4, 4, 3), np.float32), s.name)
    irradiance = ForwardModel(calibration.rig, flat, spp=4, smoothing_eps=0.0, clamp=False).render(
        captures.pattern("white")).mean(axis=2)
    top = float(np.percentile(irradiance, 99))
    ok = (irradiance > LIT * max(top, 1e-9)) & (white.max(axis=2) < 0.99)
    a = np.where(ok, (white - black).mean(axis=2) / np.maximum(irradiance, 1e-9), np.nan)
    looks, lit = camera_to_input(calibration, calibration.rig.camera.intrinsics.size)
    rho = np.where(lit, vignetting_radius(calibration.rig.projector, np.nan_to_num(looks)), np.nan)
    return np.where(a > 1e-4, a, np.nan), rho


def fit_falloffs(ratio: np.ndarray, rho_1: np.ndarray, rho_2: np.ndarray) -> tuple[float, float] | None:
    """``(f_1, f_2)`` from the log-ratio ``log(a_2 / a_1)`` of the overlap's pixels and their radii in each
    projector (module doc), by least squares with a constant; None when the overlap cannot pin them (too few
    pixels, or radii that vary together)."""
    ok = np.isfinite(ratio) & np.isfinite(rho_1) & np.isfinite(rho_2)
    if ok.sum() < MIN_PIXELS:
        return None
    design = np.stack([np.ones(int(ok.sum())), rho_1[ok] ** 2, -rho_2[ok] ** 2], axis=1)
    if np.linalg.cond(design) > 1e4:
        return None
    # Robust to the odd pixel (an edge, a highlight): drop residuals beyond 3 MADs once and fit again.
    coef, *_ = np.linalg.lstsq(design, ratio[ok], rcond=None)
    resid = ratio[ok] - design @ coef
    mad = float(np.median(np.abs(resid - np.median(resid)))) * 1.4826
    keep = np.abs(resid) <= 3 * max(mad, 1e-6)
    if keep.sum() >= MIN_PIXELS:
        coef, *_ = np.linalg.lstsq(design[keep], ratio[ok][keep], rcond=None)
    return float(coef[1]), float(coef[2])


def overlap_falloffs(calibration: Any, captures: Any) -> list[float | None]:
    """Each projector's falloff as the overlaps say it (module doc): for every pair of projectors that share
    enough of the camera image, the pair's fit; a projector in several pairs gets their mean; None where it shares
    too little with any other."""
    count = calibration.projector_count
    views = [(readings(calibration.for_projector(k), captures.for_projector(k))) for k in range(count)]
    found: list[list[float]] = [[] for _ in range(count)]
    for i in range(count):
        for j in range(i + 1, count):
            (a_i, r_i), (a_j, r_j) = views[i], views[j]
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.log(a_j / a_i)
            pair = fit_falloffs(ratio, r_i, r_j)
            if pair is not None:
                found[i].append(pair[0])
                found[j].append(pair[1])
    return [float(np.mean(f)) if f else None for f in found]
