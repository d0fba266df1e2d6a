"""Image quality inside the target display area: PSNR and SSIM (Wang et al. 2004), as the paper's Table 2.

SSIM comes from OpenCV-contrib's ``quality`` module, whose constants assume
8-bit ranges (C1 = (0.01·255)²), so images in [0, 1] are scaled by 255 first;
the result is averaged over the three channels.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..errors import ImageError


def _pair(image: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = np.asarray(image, np.float32), np.asarray(target, np.float32)
    if a.shape != b.shape:
        raise ImageError(f"cannot compare images of shapes {a.shape} and {b.shape}")
    return np.clip(a, 0, 1), np.clip(b, 0, 1)


def psnr(image: np.ndarray, target: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1] (peak 1)."""
    a, b = _pair(image, target)
    mse = float(np.mean((a.astype(np.float64) - b) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(1.0 / mse)


def ssim(image: np.ndarray, target: np.ndarray) -> float:
    """Mean SSIM over channels (Gaussian window 11, σ 1.5, as Wang et al.)."""
    a, b = _pair(image, target)
    score = cv2.quality.QualitySSIM_compute(np.ascontiguousarray(a * 255.0), np.ascontiguousarray(b * 255.0))[0]
    channels = a.shape[2] if a.ndim == 3 else 1
    return float(np.mean(score[:channels]))


def error_map(image: np.ndarray, target: np.ndarray, scale: float = 0.2) -> np.ndarray:
    """Signed difference ``image − target`` (channel mean) as blue (too dark) – white – red (too bright);
    ``|difference| = scale`` saturates."""
    a, b = _pair(image, target)
    d = np.clip((a - b).mean(axis=2) / scale, -1, 1) if a.ndim == 3 else np.clip((a - b) / scale, -1, 1)
    out = np.ones(d.shape + (3,), np.float32)
    out[..., 0] -= np.clip(-d, 0, 1)
    out[..., 1] -= np.abs(d)
    out[..., 2] -= np.clip(d, 0, 1)
    return out
