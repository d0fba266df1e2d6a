"""A media server's side of an MPCDI file: one content frame through a region's warp, alpha and beta gives the frame
that region's projector shows (§2.4: ``Pf = Pi·α·(1 − β) + β``), so the lab can project what a media server would.

Per projector pixel: its place on the warp grid (fill layout, §3.6) and bilinear interpolation of the grid (the
``linear`` hint; NaN spreads to its neighbours, as on a GPU, and shows black), the region's (u, v) placed in the
buffer and turned to the content's rows (v up, the region's y from the bottom: :mod:`.format`), the content sampled
bilinearly there (black outside it), then the alpha map (linearised by its ``gammaEmbedded``) and the beta map, both
stretched over the raster the same way. Values are projector input levels, as ProCam's frames are. Only 2D warps
are applied: a 3D profile's points need a renderer of the scene.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..errors import MpcdiError
from .format import Mpcdi, Region


def stretch(data: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """A grid or map over a raster of ``size`` = (width, height): bilinear, pixel centres aligned (fill layout)."""
    a = np.asarray(data, np.float32)
    if (a.shape[1], a.shape[0]) == tuple(size):
        return a
    out = cv2.resize(a, tuple(int(v) for v in size), interpolation=cv2.INTER_LINEAR)
    return out.reshape(size[1], size[0], *a.shape[2:])


def content_positions(m: Mpcdi, region: Region) -> np.ndarray:
    """(H, W, 2) normalised content coordinates (s right, t down) each of the region's pixels shows; NaN where the
    warp is unknown."""
    if m.profile not in ("2d", "3d"):
        raise MpcdiError(f"apply-mpcdi applies 2D warps (the 2d profile); a {m.profile} file holds 3D points that "
                         "a renderer of the scene draws from")
    uv = stretch(region.warp[..., :2], region.resolution)
    s = region.x + region.xsize * uv[..., 0]
    t = 1.0 - (region.y + region.ysize * uv[..., 1])
    return np.stack([s, t], axis=2)


def region_frame(m: Mpcdi, region: Region, content: np.ndarray) -> np.ndarray:
    """The frame (H×W×3, projector input levels) region ``region``'s projector shows for ``content`` (any size,
    H×W×3 in [0, 1], the whole buffer)."""
    img = np.asarray(content, np.float32)
    if img.ndim != 3 or img.shape[2] != 3 or not np.all(np.isfinite(img)):
        raise MpcdiError(f"content must be a finite H×W×3 image, got shape {img.shape}")
    ch, cw = img.shape[:2]
    st = content_positions(m, region)
    ok = np.all(np.isfinite(st), axis=2)
    mx = np.where(ok, st[..., 0] * cw - 0.5, -1e6).astype(np.float32)
    my = np.where(ok, st[..., 1] * ch - 0.5, -1e6).astype(np.float32)
    pi = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    alpha = np.clip(stretch(region.alpha, region.resolution), 0.0, 1.0) ** float(region.alpha_gamma)
    beta = np.zeros_like(alpha) if region.beta is None else np.clip(stretch(region.beta, region.resolution), 0, 1)
    if alpha.ndim == 2:
        alpha = alpha[..., None]
    if beta.ndim == 2:
        beta = beta[..., None]
    out = pi * alpha * (1.0 - beta) + beta
    # A pixel whose warp is unknown shows nothing of the content; beta still lifts it only where the map says so.
    out = np.where(ok[..., None], out, beta * np.ones_like(out))
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def frames(m: Mpcdi, content: np.ndarray) -> list[np.ndarray]:
    """Every region's frame for one content frame, in the file's region order."""
    return [region_frame(m, r, content) for r in m.regions]
