"""Image quality inside the target display area, as the paper's Table 2: PSNR and SSIM (Wang et al. 2004),
one projection measured through a device, and the baselines measured beside it.

* **uncompensated** — the target projected as is, through the warp: the
  target placed in its area, carried into the projector input by the
  calibrated geometry (``Compensator.initial_input(how='geometric')``), then
  ``x = W(·)``;
* **classical** — :mod:`.classical` (per-pixel colour mixing, Gray-code geometry);
* the **ablations** of the paper's Fig. 9 — no θ (stage C with
  ``use_bias=False``) and no W (stage C on the calibration with its warp
  replaced by the identity, :func:`without_warp`).

SSIM comes from OpenCV-contrib's ``quality`` module, whose constants assume
8-bit ranges (C1 = (0.01·255)²), so images in [0, 1] are scaled by 255 first;
the result is averaged over the three channels.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np

from ..capture.devices import Device
from ..errors import CaptureError, ImageError
from .display_area import DisplayArea
from .warp_model import Warp


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


def area_psnr(image: np.ndarray, target: np.ndarray, area: DisplayArea) -> float:
    """PSNR (dB, peak 1) of ``image`` against ``target`` inside the area (both camera size)."""
    return psnr(area.crop(image), area.crop(target))


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


# -- measuring one projection --------------------------------------------------------------------

@dataclass
class Measurement:
    """One projection through the device: the capture and its quality inside the display area."""

    capture: np.ndarray  # camera size
    psnr: float
    ssim: float
    seconds: float

    def scores(self) -> dict[str, float]:
        return {"psnr": round(self.psnr, 4), "ssim": round(self.ssim, 5)}


def check_capture(image: np.ndarray, camera_size: tuple[int, int]) -> np.ndarray:
    """A device capture as float32, if it has the camera's size and finite values; else a :class:`CaptureError`."""
    img = np.asarray(image, dtype=np.float32)
    cw, ch = camera_size
    if img.shape != (ch, cw, 3):
        got = f"{img.shape[1]}×{img.shape[0]}" if img.ndim >= 2 else str(img.shape)
        raise CaptureError(f"the capture device returned a {got} image (shape {img.shape}), but the calibrated camera "
                           f"is {cw}×{ch}×3; is the device the rig that was calibrated?")
    if not np.all(np.isfinite(img)):
        raise CaptureError("the capture device returned an image with NaN or infinite values")
    return img


def measure(device: Device, frame: np.ndarray, fitted: np.ndarray, area: DisplayArea,
            camera_size: tuple[int, int]) -> Measurement:
    """Project ``frame`` (native projector frame), capture, and score the area against ``fitted`` (area size)."""
    t0 = time.perf_counter()
    shot = check_capture(device.project(frame), camera_size)
    crop = area.crop(shot)
    return Measurement(shot, psnr(crop, fitted), ssim(crop, fitted), time.perf_counter() - t0)


def uncompensated_input(compensator: Any, placed: np.ndarray) -> np.ndarray:
    """The uncompensated baseline's projector input: the camera-size ``placed`` target carried into the
    projector by the calibrated geometry, as is (no photometric change), then through the warp W."""
    return compensator.warp_w(compensator.initial_input(placed, how="geometric"))


def without_warp(calibration: Any) -> Any:
    """The calibration with its warp replaced by the identity: the no-W ablation (paper's Fig. 9)."""
    return replace(calibration, warp=Warp.identity(calibration.rig.projector.input_size))


def side_by_side(target: np.ndarray, uncompensated: np.ndarray, compensated: np.ndarray,
                 *extra: np.ndarray, gap: int = 4) -> np.ndarray:
    """Area crops side by side: target | uncompensated | compensated | (extra…) | error map of compensated."""
    panels = [target, uncompensated, compensated, *extra, error_map(compensated, target)]
    h = target.shape[0]
    sep = np.ones((h, gap, 3), np.float32)
    row: list[np.ndarray] = []
    for p in panels:
        if row:
            row.append(sep)
        row.append(np.clip(np.asarray(p, np.float32), 0, 1))
    return np.concatenate(row, axis=1)


def mean_scores(rows: list[dict[str, Any]], key: str | None = None) -> dict[str, float] | None:
    """Mean PSNR/SSIM of ``rows`` (or of ``row[key]``); None when there is none."""
    vals = [r if key is None else r.get(key) for r in rows]
    vals = [v for v in vals if v]
    if not vals:
        return None
    return {k: round(float(np.mean([v[k] for v in vals])), 4) for k in ("psnr", "ssim")}
