"""The colours a projector can make the camera see at each pixel, measured: the gamut ceiling.

The range ceiling (stages/range.py) clips every channel of the target to that
channel of the black and white captures on its own. A real projector mixes its
colours (a red input lights the camera's green a little) and falls off in each
channel by its own law, so a saturated target can be inside [black, white] in
every channel and still out of reach: its blue asks for the blue of white while
its red and green ask for little, and without them blue is dimmer.

Light adds, and each channel's response is monotone, so what a pixel can show
is the parallelepiped ``black + M·u``, ``u ∈ [0, 1]³``, whose edges ``M``'s
columns are the captures of the three primaries at full minus black
(Grossberg et al., "Making one object look like another", CVPR 2004, measure
the same per-pixel mixing). :func:`gamut_clip` moves each target pixel to the
nearest colour of its parallelepiped; :func:`gamut_ceiling` is the PSNR of
that, through the camera's noise: a bound no input beats (it still ignores the
blur between neighbouring pixels), and a tighter one than the range ceiling
where the colours mix.
"""

from __future__ import annotations

import numpy as np

from .range import noise_ceiling

#: Projected-gradient steps of :func:`gamut_clip` (three unknowns a pixel: converged well before).
CLIP_STEPS = 60


def gamut_clip(target: np.ndarray, black: np.ndarray, primaries: np.ndarray) -> np.ndarray:
    """The colour nearest ``target`` (H×W×3) that the projector can make each pixel show: ``black + M u`` with
    ``u`` in [0, 1]³, ``M``'s columns ``primaries[c] − black`` (``primaries``: 3×H×W×3, the captures of red, green
    and blue at full). Box-constrained least squares per pixel by accelerated projected gradient."""
    t = np.asarray(target, np.float64).reshape(-1, 3)
    k = np.asarray(black, np.float64).reshape(-1, 3)
    m = np.stack([np.asarray(p, np.float64).reshape(-1, 3) - k for p in primaries], axis=2)  # N × 3 (out) × 3 (in)
    m = np.maximum(m, 0.0)  # a primary cannot take light away
    d = t - k
    mtm = np.einsum("noi,noj->nij", m, m)
    mtd = np.einsum("noi,no->ni", m, d)
    step = 1.0 / np.maximum(np.linalg.eigvalsh(mtm)[:, -1], 1e-9)
    u = np.clip(np.einsum("nio,no->ni", np.linalg.pinv(m), d), 0.0, 1.0)
    prev, y = u, u
    for i in range(CLIP_STEPS):
        grad = np.einsum("nij,nj->ni", mtm, y) - mtd
        u = np.clip(y - step[:, None] * grad, 0.0, 1.0)
        y = u + (i / (i + 3.0)) * (u - prev)
        prev = u
    return (k + np.einsum("noi,ni->no", m, u)).reshape(np.shape(target)).astype(np.float32)


def gamut_ceiling(target: np.ndarray, black: np.ndarray, primaries: np.ndarray, noise_mse: float) -> float:
    """The PSNR of the gamut-clipped target through the camera's noise of variance ``noise_mse`` (module doc)."""
    reach = gamut_clip(target, black, primaries)
    # noise_ceiling clips to [black, white] itself: hand it the clipped target with a range that holds it
    return noise_ceiling(np.asarray(target, np.float32), reach, reach, noise_mse)


__all__ = ["CLIP_STEPS", "gamut_ceiling", "gamut_clip"]
