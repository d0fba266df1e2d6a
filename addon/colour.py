"""The sRGB transfer function (IEC 61966-2-1), written once for every module that decodes or encodes it.

Callers say where sRGB applies (no transfer touches data silently: docs/developer.md,
"Facts about the dependencies"): photographs and video frames stored sRGB-encoded, 8-bit images a
.blend holds, and the blend of linear and sRGB that the lab's camera response
injects and the diagnosis's camera-curve model fits. Both functions compute in
the input's float type; callers cast.
"""

from __future__ import annotations

import numpy as np


def srgb_decode(values: np.ndarray) -> np.ndarray:
    """sRGB-encoded values → linear light (no clipping)."""
    v = values
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def srgb_encode(values: np.ndarray) -> np.ndarray:
    """Linear light → sRGB-encoded values, clipped to [0, 1] first."""
    v = np.clip(values, 0.0, 1.0)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)


__all__ = ["srgb_decode", "srgb_encode"]
