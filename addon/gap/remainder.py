"""What the selected effect models leave unexplained, above the captures' own noise.

The structured residual (``fit.structured``) has two classes of pixels. On the
smooth parts, where the residual is smoothed with a Gaussian of σ =
``SMOOTH_SIGMA``, pixel noise of variance v leaves v·Σg² (Σg² = 1/(4πσ²) for
a Gaussian kernel g); v itself is read from the raw residual's high-pass
``r − g∗r``, whose variance is v·(1 − 2g₀ + Σg²) for white noise (g₀ the
kernel's centre weight). Whatever the smooth parts hold above v·Σg² is
structure: an effect, modelled or not. (On pattern edges the floor also holds
sub-pixel misregistration, which no noise estimate gives, so the remainder is
judged on the smooth parts and the edges are only reported.)

The selected effects explain a share of the smooth residual above that floor.
When they leave at least :data:`UNEXPLAINED_SHARE` of it, and it is more than
:data:`UNEXPLAINED_MIN_RMSE` (about 1/3 of an 8-bit level), the diagnosis says
"unexplained": its model of the rig lacks something, and any effect it names
stands for part of it at most.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import cv2
import numpy as np

from .data import GapData
from .fit import SMOOTH_SIGMA, Fit, residual_stack
from .models import Composite

#: The selected effects leave this share (or more) of the smooth residual above the noise floor: unexplained.
UNEXPLAINED_SHARE = 0.5
#: ... and the remainder is at least this RMSE (linear camera units).
UNEXPLAINED_MIN_RMSE = 0.0015


@dataclass
class Remainder:
    """The smooth-part residual before and after the selected effects, and the floor noise leaves."""

    noise_rmse: float  # the captures' pixel noise (raw residual's high-pass), one channel
    floor_mse: float  # what that noise leaves in the smoothed residual
    before_mse: float
    after_mse: float
    edges_before_mse: float
    edges_after_mse: float

    @property
    def explained_share(self) -> float:
        """Share of the smooth residual above the floor that the selected effects remove (1 when none is left)."""
        gap = self.before_mse - self.floor_mse
        if gap <= 0:
            return 1.0
        return float(np.clip((self.before_mse - self.after_mse) / gap, 0.0, 1.0))

    @property
    def unexplained_rmse(self) -> float:
        return math.sqrt(max(self.after_mse - self.floor_mse, 0.0))

    @property
    def detected(self) -> bool:
        return 1.0 - self.explained_share >= UNEXPLAINED_SHARE and self.unexplained_rmse >= UNEXPLAINED_MIN_RMSE

    def to_dict(self) -> dict[str, Any]:
        d = {k: float(f"{v:.4g}") for k, v in asdict(self).items()}
        return {**d, "explained_share": round(self.explained_share, 3), "share": round(1 - self.explained_share, 3),
                "unexplained_rmse": round(self.unexplained_rmse, 5), "detected": self.detected}


def _kernel_terms(sigma: float) -> tuple[float, float]:
    """Centre weight g₀ and Σg² of the discrete Gaussian ``cv2.GaussianBlur`` uses."""
    impulse = np.zeros((41, 41), np.float32)
    impulse[20, 20] = 1.0
    k = cv2.GaussianBlur(impulse, (0, 0), sigma)
    return float(k[20, 20]), float((k.astype(np.float64) ** 2).sum())


def remainder(data: GapData, base: Fit, final: Fit) -> Remainder:
    """How much of the held-out smooth residual the selected effects (``final``) leave above the noise floor."""
    g0, g2 = _kernel_terms(SMOOTH_SIGMA)
    raw = residual_stack(Composite(data, final.names), final.theta, data.held_index)
    hp_sum, hp_n = 0.0, 0
    for r, i in zip(raw, data.held_index):
        edges = data.observations[i].edges
        flat = data.mask & ~(edges if edges is not None else np.zeros_like(data.mask))
        # away from edges by the kernel's reach, where the high-pass would hold the edge itself
        flat = cv2.erode(flat.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
        hp = r - cv2.GaussianBlur(r, (0, 0), SMOOTH_SIGMA)
        hp_sum += float((hp[flat].astype(np.float64) ** 2).sum())
        hp_n += int(flat.sum()) * 3
    v = hp_sum / max(hp_n, 1) / (1.0 - 2.0 * g0 + g2)
    return Remainder(noise_rmse=math.sqrt(v), floor_mse=v * g2, before_mse=base.held_mse_classes[0],
                     after_mse=final.held_mse_classes[0], edges_before_mse=base.held_mse_classes[1],
                     edges_after_mse=final.held_mse_classes[1])


__all__ = ["Remainder", "UNEXPLAINED_MIN_RMSE", "UNEXPLAINED_SHARE", "remainder"]
