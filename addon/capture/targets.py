"""Natural target images: the real photographs that ship inside the bpy package as studio-light HDRIs
(``datafiles/studiolights/world/*.exr``), tone-mapped to displayable linear images.

A target is what the camera should see, so it stays linear. The tone map is
a global Reinhard curve on luminance with the exposure set from the log-average
luminance, then a central crop to the requested aspect — a photograph, not a
panorama. The tone-mapped range is kept inside [0.05, 0.85]: a projector on a
coloured surface can neither reach pure black (ambient, black level) nor the
brightest whites everywhere, and a target no rig can show measures nothing.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import ImageError
from ..imageio import read_image

#: The six targets of the benchmark, like the paper's six images.
DEFAULT_TARGETS = ("city", "courtyard", "forest", "interior", "sunrise", "studio")


def studiolight_folder() -> Path:
    """The folder of Blender's bundled world HDRIs (from the bpy package)."""
    import importlib.util

    spec = importlib.util.find_spec("bpy")
    if spec is None or spec.origin is None:
        raise ImageError("the bpy package is not installed, so Blender's bundled photographs are not available")
    root = Path(spec.origin).parent
    hits = sorted(root.glob("*/datafiles/studiolights/world"))
    if not hits:
        raise ImageError(f"no datafiles/studiolights/world folder inside {root}")
    return hits[-1]


def available_targets() -> list[str]:
    return sorted(p.stem for p in studiolight_folder().glob("*.exr"))


def tone_map(hdr: np.ndarray, *, key: float = 0.25, low: float = 0.05, high: float = 0.85) -> np.ndarray:
    """Reinhard global tone map to linear [low, high]."""
    lum = np.maximum(hdr @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32), 1e-6)
    scaled = key / float(np.exp(np.mean(np.log(lum)))) * lum
    out = hdr * (scaled / (1.0 + scaled) / lum)[..., None]
    return np.clip(low + (high - low) * np.clip(out, 0, 1), 0, 1).astype(np.float32)


def natural_target(name: str, size: tuple[int, int]) -> np.ndarray:
    """A tone-mapped, centrally cropped photograph at ``size`` = (width, height)."""
    path = studiolight_folder() / f"{name}.exr"
    if not path.is_file():
        raise ImageError(f"no built-in target {name!r}; choose one of {', '.join(available_targets())}")
    hdr = read_image(path)
    h, w = hdr.shape[:2]
    # The equirectangular panorama's middle band is the least distorted: crop there.
    tw, th = size
    ch = h // 2
    cw = min(w, int(round(ch * tw / th)))
    y0, x0 = (h - ch) // 2, (w - cw) // 2
    crop = hdr[y0:y0 + ch, x0:x0 + cw]
    return tone_map(cv2.resize(crop, (tw, th), interpolation=cv2.INTER_AREA))
