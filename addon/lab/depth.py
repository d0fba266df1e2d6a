"""Phone-LiDAR depth simulation for the virtual lab: what an RGBD phone gives of a rendered depth map.

The paper's iPad Pro delivers depth at 256×192 and upsamples it with OpenCV to
the 640×480 colour image (Sec. IV). :func:`depth_capture` does the same to the
renderer's exact depth: area-average down to the sensor's native resolution
(depth edges become mixed "flying" pixels, as on the real sensor), add the
``depth_noise`` effect (noise growing with depth, a bias, lost returns at
grazing angles and at random, nothing beyond the range limit), then upsample
bilinearly back to the camera's resolution, shifted against the colour image
when the effect's ``shift_x``/``shift_y`` (a misregistration) are set.

At strength 0 the result is still the low-resolution, re-upsampled depth — that
is the sensor, not an effect — but no noise, bias or holes are added; the real
iPad shows ≈ 0.5–1 cm noise at 1 m, which ``depth_noise≈0.3–0.5`` gives.
"""

from __future__ import annotations


import cv2
import numpy as np

from ..rig.model import Intrinsics
from .effects import EffectSet, LabError

#: A low-resolution pixel holds a return only if at least this share of its footprint saw a surface.
MIN_COVERAGE = 0.5


def _resize_valid(values: np.ndarray, valid: np.ndarray, size: tuple[int, int], interpolation: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Resize ignoring invalid pixels: returns (values, coverage); values are NaN where coverage < MIN_COVERAGE."""
    w = valid.astype(np.float32)
    num = cv2.resize(np.where(valid, values, 0.0).astype(np.float32), size, interpolation=interpolation)
    den = cv2.resize(w, size, interpolation=interpolation)
    ok = den >= MIN_COVERAGE
    out = np.full(den.shape, np.nan, dtype=np.float32)
    out[ok] = num[ok] / den[ok]
    return out, den


def grazing_angle(depth: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """Angle (degrees) between the surface normal and the view ray per pixel; NaN where undefined."""
    h, w = depth.shape
    u = (np.arange(w) + 0.5 - intrinsics.cx) / intrinsics.fx
    v = (np.arange(h) + 0.5 - intrinsics.cy) / intrinsics.fy
    x = depth * u[None, :]
    y = depth * v[:, None]
    p = np.stack([x, y, depth], axis=-1).astype(np.float64)
    du = np.gradient(p, axis=1)
    dv = np.gradient(p, axis=0)
    n = np.cross(du, dv)
    num = np.abs(np.sum(n * p, axis=-1))
    den = np.linalg.norm(n, axis=-1) * np.linalg.norm(p, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.where(den > 0, num / den, np.nan)
    return np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))


def depth_capture(true_depth: np.ndarray, camera_intrinsics: Intrinsics, effects: EffectSet,
                  rng: np.random.Generator | None) -> np.ndarray:
    """The phone's depth map (H×W metres, float32, NaN = no return) for the renderer's exact depth.

    ``true_depth`` is H×W metres along the camera's z axis at the camera's
    resolution, NaN (or ≤ 0) where no surface is seen.
    """
    intr = camera_intrinsics
    d = np.asarray(true_depth, dtype=np.float64)
    if d.ndim != 2 or d.shape != (intr.height, intr.width):
        raise LabError(f"true depth must be {intr.width}×{intr.height} (the camera's resolution), "
                       f"got shape {d.shape}")
    if np.any(np.isinf(d)):
        raise LabError("true depth holds infinite values; use NaN where no surface is seen")
    e = effects["depth_noise"]
    valid = np.isfinite(d) & (d > 0)
    lw, lh = sensor_resolution(effects, intr)

    # the sensor integrates over its footprint: area averaging, not point sampling
    low, _ = _resize_valid(d, valid, (lw, lh), cv2.INTER_AREA)
    low = low.astype(np.float64)
    low[low > e["max_range"]] = np.nan

    if e["holes"] > 0:
        if rng is None:
            raise LabError("depth holes need a seeded np.random.Generator")
        angle = grazing_angle(low, intr.scaled(lw, lh))
        lost = (np.nan_to_num(angle, nan=0.0) > e["grazing_deg"]) & (rng.random(low.shape) < e["holes"])
        low[lost] = np.nan
    if e["dropout"] > 0:
        if rng is None:
            raise LabError("depth dropout needs a seeded np.random.Generator")
        low[rng.random(low.shape) < e["dropout"]] = np.nan
    if e["std"] > 0:
        if rng is None:
            raise LabError("depth noise needs a seeded np.random.Generator")
        # time-of-flight noise grows with distance; drawn at the sensor's pixels, so it is spatially
        # correlated over ~2.5 camera pixels after upsampling, as on the real device
        low = low + e["std"] * low * rng.standard_normal(low.shape)
    if e["bias"] != 0:
        low = low + e["bias"]

    ok = np.isfinite(low) & (low > 0)
    # OpenCV's bilinear resize, as the paper upsamples; invalid neighbours are left out of the blend
    up, _ = _resize_valid(low, ok, (intr.width, intr.height), cv2.INTER_LINEAR)
    if e["shift_x"] or e["shift_y"]:
        up = misregister(up, e["shift_x"] * intr.width / 640, e["shift_y"] * intr.width / 640)
    return up.astype(np.float32)


def misregister(depth: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """The depth map shifted by (dx, dy) camera pixels against the colour image (a phone's depth and colour
    cameras registered a little wrong): pixel (u, v) reads the depth of (u − dx, v − dy); NaN where that leaves
    the map or meets no return."""
    h, w = depth.shape
    ok = np.isfinite(depth)
    m = np.float32([[1.0, 0.0, dx], [0.0, 1.0, dy]])
    moved, _ = _warp_valid(np.where(ok, depth, 0.0), ok, m, (w, h))
    return moved


def _warp_valid(values: np.ndarray, valid: np.ndarray, m: np.ndarray, size: tuple[int, int]
                       ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_resize_valid` for an affine warp: invalid pixels are left out of the bilinear blend."""
    num = cv2.warpAffine(values.astype(np.float32), m, size, flags=cv2.INTER_LINEAR, borderValue=0.0)
    den = cv2.warpAffine(valid.astype(np.float32), m, size, flags=cv2.INTER_LINEAR, borderValue=0.0)
    out = np.full(den.shape, np.nan, dtype=np.float32)
    good = den >= MIN_COVERAGE
    out[good] = num[good] / den[good]
    return out, den


def sensor_resolution(effects: EffectSet, camera_intrinsics: Intrinsics) -> tuple[int, int]:
    """(width, height) at which the depth is sensed for this camera.

    The sensor's native resolution (256×192 unless overridden), except for a
    camera smaller than that (a reduced test render): there the paper's ratio
    of 256×192 to 640×480 is kept, so the depth stays coarser than the colour.
    """
    e = effects["depth_noise"]
    lw, lh = int(e["width"]), int(e["height"])
    if lw > camera_intrinsics.width or lh > camera_intrinsics.height:
        lw = max(2, round(camera_intrinsics.width * 256 / 640))
        lh = max(2, round(camera_intrinsics.height * 192 / 480))
    return lw, lh
