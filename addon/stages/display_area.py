"""The target display area: the camera-image rectangle where the projection should look like the target.

The paper's Fig. 7 draws it as a box in the camera image; Table 2 is measured
inside it (crop the capture to the box, resize the target to the crop). Here
it comes from, in order of preference:

1. a rectangle the user gives (``x, y, w, h`` in camera pixels, corner convention);
2. the capture set's ``target_area``;
3. the largest axis-aligned rectangle with the target's aspect ratio inside the
   region the projector lights in the camera: the calibrated model's render of a
   white input (geometry only: the albedo is set to white so that dark texture
   does not punch holes), intersected, when the captures are at hand, with the
   real white − black capture mask (holes filled, for the same reason), then
   eroded by a margin so that small pose/warp errors do not put the area's edge
   on the projector's edge.

Targets are read as linear float (8-bit files are sRGB-encoded photographs and
are linearised, 16-bit and float files are taken as linear; the choice is
reported) and resized to the area with ``cv2.INTER_AREA`` by :func:`fit_target`,
the one function evaluation must use too, so that compensation and measurement
see the same target pixels.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..capture.photos import stored_bit_depth
from ..capture.format import srgb_to_linear
from ..errors import ImageError, ProCamError
from ..imageio import read_image
from ..render.forward import ForwardModel
from ..surface.mesh import SurfaceMesh

#: Relative aspect-ratio difference above which fitting a target to an area warns that it is stretched.
ASPECT_TOLERANCE = 0.01
TARGET_ENCODINGS = ("auto", "srgb", "linear")


class DisplayAreaError(ProCamError):
    """A display area that is malformed, outside the camera image, or cannot be found."""


class TargetAspectWarning(UserWarning):
    """A target resized to an area of another aspect ratio (it is stretched)."""


@dataclass(frozen=True)
class DisplayArea:
    """A rectangle of the camera image (pixels, corner convention): ``x, y`` top-left, ``width × height``."""

    x: int
    y: int
    width: int
    height: int
    source: str = "user"  # 'user', 'capture-set' or 'auto'

    @property
    def aspect(self) -> float:
        return self.width / self.height

    @property
    def size(self) -> tuple[int, int]:
        return (self.width, self.height)

    @property
    def slices(self) -> tuple[slice, slice]:
        return slice(self.y, self.y + self.height), slice(self.x, self.x + self.width)

    def check(self, camera_size: tuple[int, int]) -> DisplayArea:
        """This area, if it lies inside a ``camera_size`` image; else a :class:`DisplayAreaError`."""
        cw, ch = camera_size
        if self.width < 2 or self.height < 2:
            raise DisplayAreaError(f"the display area must be at least 2×2 pixels, got {self.width}×{self.height}")
        if self.x < 0 or self.y < 0 or self.x + self.width > cw or self.y + self.height > ch:
            raise DisplayAreaError(
                f"the display area x={self.x}, y={self.y}, {self.width}×{self.height} reaches outside the "
                f"{cw}×{ch} camera image; give x, y, width, height with x + width ≤ {cw} and y + height ≤ {ch}")
        return self

    def mask(self, camera_size: tuple[int, int]) -> np.ndarray:
        """H×W bool mask of the area in a ``camera_size`` image."""
        cw, ch = camera_size
        m = np.zeros((ch, cw), dtype=bool)
        m[self.slices] = True
        return m

    def crop(self, image: np.ndarray) -> np.ndarray:
        """The area's pixels of a camera image."""
        return np.ascontiguousarray(np.asarray(image)[self.slices])

    def place(self, image: np.ndarray, camera_size: tuple[int, int]) -> np.ndarray:
        """A black ``camera_size`` image with ``image`` (area-sized) in the area."""
        img = np.asarray(image, dtype=np.float32)
        if img.shape[:2] != (self.height, self.width):
            raise ImageError(f"an image placed in the display area must be {self.width}×{self.height}, "
                             f"got {img.shape[1]}×{img.shape[0]}; fit it with fit_target")
        cw, ch = camera_size
        out = np.zeros((ch, cw) + img.shape[2:], dtype=np.float32)
        out[self.slices] = img
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"x": self.x, "y": self.y, "width": self.width, "height": self.height, "source": self.source}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> DisplayArea:
        try:
            return DisplayArea(int(d["x"]), int(d["y"]), int(d["width"]), int(d["height"]),
                               str(d.get("source", "user")))
        except (KeyError, TypeError, ValueError) as exc:
            raise DisplayAreaError(f"a display area needs x, y, width, height: {exc}") from None


def parse_area(text: str) -> tuple[int, int, int, int]:
    """``"x,y,w,h"`` (whole camera pixels) → a tuple; a :class:`DisplayAreaError` saying what is wrong."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        values = tuple(int(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 4:
        raise DisplayAreaError(f"a display area is x,y,width,height in whole camera pixels (e.g. 120,80,400,300), "
                               f"got {text!r}")
    return values


def parse_surround(text: str) -> tuple[float, float, float]:
    """``"R,G,B"`` (each 0–1, a share of the projector's white) → a tuple; a :class:`DisplayAreaError` saying what
    is wrong. One number is a grey."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) == 1:
        values = values * 3
    if len(values) != 3 or not all(0.0 <= v <= 1.0 for v in values):
        raise DisplayAreaError(f"a surround colour is R,G,B, each from 0 to 1 as a share of the projector's white "
                               f"(e.g. 0.05,0.05,0.05, or one number for a grey), got {text!r}")
    return values  # type: ignore[return-value]


# -- the projector's footprint -------------------------------------------------------------------

def _fill_holes(mask: np.ndarray) -> np.ndarray:
    """``mask`` with every background region not connected to the image border filled in."""
    m = mask.astype(np.uint8)
    padded = np.pad(m, 1)
    flood = padded.copy()
    ff_mask = np.zeros((flood.shape[0] + 2, flood.shape[1] + 2), np.uint8)
    cv2.floodFill(flood, ff_mask, (0, 0), 1)
    holes = flood[1:-1, 1:-1] == 0
    return mask | holes


def _erode(mask: np.ndarray, px: int) -> np.ndarray:
    if px <= 0:
        return mask
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * px + 1, 2 * px + 1))
    # Pixels beyond the image border count as uncovered, so the area also keeps off the image edge by px.
    return cv2.erode(mask.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)


def model_coverage(calibration: Any, *, spp: int = 1, level: float = 0.25) -> np.ndarray:
    """Camera pixels the calibrated projector lights (direct light, white input, white albedo).

    ``level`` is the share of the 99th-percentile irradiance below which a
    pixel counts as unlit (irradiance varies ~2× across the footprint with
    distance and incidence; outside it is zero).
    """

    s = calibration.surface
    flat = SurfaceMesh(s.vertices, s.faces, s.uvs, np.ones((4, 4, 3), np.float32), s.name)
    model = ForwardModel(calibration.rig, flat, bounces=0, spp=spp, smoothing_eps=0.0, clamp=False)
    proj = calibration.rig.projector
    w, h = proj.input_size
    irr = model.render_input(np.ones((h, w, 3), np.float32)).mean(axis=2)
    top = float(np.percentile(irr, 99))
    if top <= 0:
        raise DisplayAreaError("the calibrated projector lights no camera pixel; "
                               "check the calibration's projector pose")
    return irr > level * top


def capture_coverage(white: np.ndarray, black: np.ndarray, threshold: float = 0.05) -> np.ndarray:
    """Camera pixels the real projector lights: white − black above ``threshold``, holes (dark texture) filled."""
    diff = (np.asarray(white, np.float32) - np.asarray(black, np.float32)).mean(axis=2)
    return _fill_holes(diff > threshold)


def largest_rectangle(mask: np.ndarray, aspect: float) -> tuple[int, int, int, int] | None:
    """The largest axis-aligned rectangle of ``aspect`` (width / height) inside ``mask``: (x, y, w, h).

    Fitting is monotone in size (a smaller box of the same aspect fits wherever
    a larger one does), so a binary search over the height with an
    integral-image test of all positions at once finds the largest. Among the
    positions where it fits, the one nearest the mask's centroid wins.
    """
    m = np.asarray(mask, dtype=bool)
    hgt, wid = m.shape
    if not m.any() or not aspect > 0:
        return None
    integral = cv2.integral(m.astype(np.uint8)).astype(np.int64)

    def fits(h: int) -> np.ndarray | None:
        w = max(1, round(aspect * h))
        if h > hgt or w > wid:
            return None
        sums = integral[h:, w:] - integral[:-h, w:] - integral[h:, :-w] + integral[:-h, :-w]
        ok = sums == w * h
        return ok if ok.any() else None

    lo, hi = 0, hgt  # lo fits (trivially 0), hi + 1 is an upper bound
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if fits(mid) is not None:
            lo = mid
        else:
            hi = mid - 1
    if lo < 2:
        return None
    h = lo
    w = max(1, round(aspect * h))
    ok = fits(h)
    ys, xs = np.nonzero(ok)
    cy, cx = np.argwhere(m).mean(axis=0)
    best = int(np.argmin((ys + h / 2 - cy) ** 2 + (xs + w / 2 - cx) ** 2))
    return int(xs[best]), int(ys[best]), int(w), int(h)


def auto_area(calibration: Any, aspect: float, *, captures: Any = None, margin_px: int | None = None) -> DisplayArea:
    """The largest rectangle of ``aspect`` the calibrated projector covers (see the module docstring)."""
    cover = model_coverage(calibration)
    if captures is not None and captures.entries_of("white") and captures.entries_of("black"):
        real = capture_coverage(captures.image("white"), captures.image("black"))
        if real.shape == cover.shape:
            cover &= real
    return area_inside(cover, aspect, margin_px=margin_px)


def edge_margin(camera_width: int) -> int:
    """The automatic area's margin from the footprint's edge: 1.5 % of the camera's width, at least 2 pixels."""
    return max(2, round(0.015 * camera_width))


def area_inside(cover: np.ndarray, aspect: float, *, margin_px: int | None = None,
                what: str = "the projector covers") -> DisplayArea:
    """The largest rectangle of ``aspect`` inside the camera pixels ``cover``, ``margin_px`` from its edge
    (default 1.5 % of the camera's width)."""
    margin = edge_margin(cover.shape[1]) if margin_px is None else int(margin_px)
    rect = largest_rectangle(_erode(cover, margin), aspect)
    if rect is None:
        raise DisplayAreaError(f"{what} too little of the camera image to hold a display area "
                               f"of aspect {aspect:.3g} (margin {margin} px); give one with --area x,y,w,h")
    return DisplayArea(*rect, source="auto")


def choose_area(calibration: Any, *, aspect: float, user: tuple[int, int, int, int] | DisplayArea | None = None,
                captures: Any = None) -> DisplayArea:
    """The display area: ``user``'s rectangle, else the capture set's ``target_area``, else :func:`auto_area`."""
    size = calibration.rig.camera.intrinsics.size
    if isinstance(user, DisplayArea):
        return user.check(size)
    if user is not None:
        return DisplayArea(*(int(v) for v in user), source="user").check(size)
    if captures is not None and captures.target_area is not None:
        return DisplayArea(*captures.target_area, source="capture-set").check(size)
    return auto_area(calibration, aspect, captures=captures)


# -- targets -------------------------------------------------------------------------------------

def load_target(path: str | Path, *, encoding: str = "auto") -> tuple[np.ndarray, str]:
    """A target image as linear float H×W×3 in [0, 1], and a note on how it was decoded.

    ``encoding='auto'``: 8-bit files (JPEG, 8-bit PNG/TIFF) are sRGB-encoded
    photographs and are linearised; 16-bit and float files are taken as linear.
    Float values above 1 are clipped (a note says so).
    """

    if encoding not in TARGET_ENCODINGS:
        raise ImageError(f"target encoding must be one of {', '.join(TARGET_ENCODINGS)}, got {encoding!r}")
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"target image not found: {path}")
    if path.stat().st_size == 0:
        raise ImageError(f"target image {path} is empty (0 bytes)")
    img = read_image(path)  # ImageError names the file when it is unreadable or holds NaN
    if img.shape[0] < 2 or img.shape[1] < 2:
        raise ImageError(f"target image {path} is {img.shape[1]}×{img.shape[0]} pixels; it needs at least 2×2")
    bits = stored_bit_depth(path)
    if encoding == "auto":
        encoding = "srgb" if bits is not None and bits <= 8 else "linear"
    note = f"{bits}-bit" if bits else "unknown bit depth"
    if encoding == "srgb":
        img = srgb_to_linear(img)
        note = f"sRGB-encoded {note}, linearised"
    else:
        note = f"linear {note}"
    if img.min() < 0 or img.max() > 1:
        note += f"; values clipped to [0, 1] (were {img.min():.3g}…{img.max():.3g})"
        img = np.clip(img, 0.0, 1.0)
    return img.astype(np.float32), note


def fit_target(target: np.ndarray, area: DisplayArea, *, what: str = "the target") -> np.ndarray:
    """``target`` resized to the area (``cv2.INTER_AREA``, linear float); warns when that stretches it."""
    img = np.asarray(target, dtype=np.float32)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise ImageError(f"{what} must be an H×W×3 image, got shape {img.shape}")
    if not np.all(np.isfinite(img)):
        raise ImageError(f"{what} holds NaN or infinite values")
    h, w = img.shape[:2]
    if (w, h) == area.size:
        return np.clip(img, 0.0, 1.0)
    ratio = (w / h) / area.aspect
    if abs(math.log(ratio)) > ASPECT_TOLERANCE:
        warnings.warn(f"{what} ({w}×{h}, aspect {w / h:.3f}) is stretched to the display area "
                      f"({area.width}×{area.height}, aspect {area.aspect:.3f})", TargetAspectWarning, stacklevel=2)
    # INTER_AREA averages when shrinking (no aliasing); it falls back to bilinear when enlarging.
    out = cv2.resize(img, area.size, interpolation=cv2.INTER_AREA)
    # In place: the resized image is this function's own (a copy and a cast cost 10 ms of a live 1080p frame).
    return np.clip(out, 0.0, 1.0, out=out)


__all__ = ["DisplayArea", "DisplayAreaError", "TargetAspectWarning", "auto_area", "capture_coverage",
           "choose_area", "edge_margin", "fit_target", "largest_rectangle", "load_target", "model_coverage",
           "parse_area", "parse_surround"]
