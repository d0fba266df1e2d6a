"""Pinhole models of the camera and the projector, and the rig that holds both.

Conventions (see docs/developer.md, "Conventions"):

* The rig frame is the camera's OpenCV frame: x right, y down, z forward,
  metres, camera at the origin.
* Intrinsics use *continuous* pixel coordinates: pixel ``(i, j)`` covers
  ``[i, i+1) × [j, j+1)``, so the top-left corner of the image is ``(0, 0)``
  and a centred principal point is ``(W/2, H/2)``. OpenCV puts pixel centres
  on integers; :meth:`Intrinsics.opencv_matrix` converts (``cx_cv = cx - 0.5``).
  We keep the corner convention because Blender, Mitsuba and texture lookups
  all use it, so only OpenCV calls need the half-pixel shift.
* A projector's lens shift is nothing but its principal point off centre,
  anywhere, also far outside the image (up to :data:`MAX_SHIFT` images).
  :func:`projector_intrinsics_from_throw` is the one place that converts the
  spec-sheet form (throw ratio, shift in % of the image) into ``K``.
* Poses are 4×4 matrices ``camera_from_X`` mapping points of device X's
  OpenCV frame into the rig frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from ..errors import ImageError, RigError


#: The largest lens shift accepted (principal point's distance from the image centre, in image widths/heights).
MAX_SHIFT = 5.0


def whole_pixels(value: Any, what: str) -> int:
    """A count of pixels read from a file: a whole number (``640`` or ``640.0``); 128.9 is refused, not truncated."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = float("nan")
    if isinstance(value, bool) or not number.is_integer():
        raise RigError(f"{what} must be a whole number of pixels, got {value!r}")
    return int(number)


def _pixel_pair(value: Any, what: str) -> tuple[int, int]:
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise RigError(f"{what} must be two whole numbers of pixels, got {value!r}")
    return whole_pixels(value[0], what), whole_pixels(value[1], what)


def square_scaled_size(width: int, height: int, scale: float, *, minimum: tuple[int, int] = (2, 2)
                       ) -> tuple[int, int]:
    """The size nearest to ``scale`` × (width, height) whose two axes scale alike, so that a square-pixel camera
    stays one (the renderer needs it): rounding each axis alone gave 1280×1024 at 0.1 a 128×102 image, whose rows
    are 0.4 % taller than its columns are wide. Widths within ±10 % of the target are tried: the nearest one whose
    height is within 0.05 px of the aspect ratio's, else the one that comes closest to it."""
    target = max(float(minimum[0]), width * scale)
    best: tuple[bool, float, float, int, int] | None = None
    for w in range(max(minimum[0], math.floor(0.9 * target)), math.ceil(1.1 * target) + 1):
        h = max(minimum[1], round(w * height / width))
        off = abs(w * height / width - h)
        cand = (off > 0.05, abs(w - target) if off <= 0.05 else off, abs(w - target), w, h)
        best = cand if best is None or cand[:3] < best[:3] else best
    assert best is not None
    return best[3], best[4]


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels of the native resolution (corner convention)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value <= 0:
                raise RigError(f"resolution {name} must be a positive whole number of pixels, got {value!r}")
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if not math.isfinite(float(value)):
                raise RigError(f"intrinsic {name} must be a finite number, got {value!r}")
        if self.fx <= 0 or self.fy <= 0:
            raise RigError(f"focal lengths must be positive (fx={self.fx}, fy={self.fy}); check the throw ratio or K")
        # A principal point outside the image is normal (a projector above or below its image: the real one in
        # realdata/ sits 1.27 image heights off centre). Only a shift no lens makes is refused, because it is
        # almost always a unit mistake (cx in millimetres, a shift in % given as a fraction ×100).
        off_x, off_y = abs(self.cx - self.width / 2) / self.width, abs(self.cy - self.height / 2) / self.height
        if max(off_x, off_y) > MAX_SHIFT:
            raise RigError(
                f"principal point ({self.cx:.1f}, {self.cy:.1f}) lies {off_x:.1f} image widths and {off_y:.1f} "
                f"image heights from the centre of the {self.width}×{self.height} image; no lens shifts beyond "
                f"±{MAX_SHIFT:.0%} — check that cx, cy are in pixels of this resolution and the shift in % of the image"
            )

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return (int(self.width), int(self.height))

    @property
    def matrix(self) -> np.ndarray:
        """3×3 K in the corner convention."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def opencv_matrix(self) -> np.ndarray:
        """3×3 K in OpenCV's pixel-centre convention."""
        k = self.matrix
        k[0, 2] -= 0.5
        k[1, 2] -= 0.5
        return k

    @staticmethod
    def from_opencv_matrix(width: int, height: int, matrix: np.ndarray) -> Intrinsics:
        """The inverse of :meth:`opencv_matrix`: a 3×3 K with pixel centres at integers, for this resolution."""
        m = np.asarray(matrix, dtype=np.float64)
        return Intrinsics(int(width), int(height), float(m[0, 0]), float(m[1, 1]), float(m[0, 2]) + 0.5,
                          float(m[1, 2]) + 0.5)

    @property
    def square_pixels(self) -> bool:
        return abs(self.fx - self.fy) <= 1e-6 * self.fx

    def project(self, points: np.ndarray) -> np.ndarray:
        """Project N×3 points of this device's OpenCV frame to N×2 pixels (NaN behind the device)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        z = np.where(p[:, 2] > 1e-12, p[:, 2], np.nan)
        return np.stack([self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy], axis=1)

    def rays(self, pixels: np.ndarray) -> np.ndarray:
        """Directions (z = 1) in the device frame through N×2 pixel positions."""
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        return np.stack([(px[:, 0] - self.cx) / self.fx, (px[:, 1] - self.cy) / self.fy, np.ones(len(px))], axis=1)

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same lens at another resolution (e.g. a small test render)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(int(width), int(height), self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy)

    @property
    def shift(self) -> tuple[float, float]:
        """Lens shift as (right, up) fractions of the image width/height."""
        return ((self.width / 2 - self.cx) / self.width, (self.cy - self.height / 2) / self.height)

    @property
    def throw_ratio(self) -> float:
        """Distance / image width (horizontal)."""
        return self.fx / self.width

    def to_dict(self) -> dict[str, Any]:
        return {"width": int(self.width), "height": int(self.height), "fx": float(self.fx), "fy": float(self.fy),
                "cx": float(self.cx), "cy": float(self.cy), "convention": "pixel corners at integers"}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> Intrinsics:
        try:
            return Intrinsics(whole_pixels(d["width"], "resolution width"),
                              whole_pixels(d["height"], "resolution height"),
                              float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise RigError(f"intrinsics need width, height, fx, fy, cx, cy: {exc}") from None


def intrinsics_from_fov(width: int, height: int, fov_x_deg: float) -> Intrinsics:
    """Square-pixel intrinsics with a centred principal point and a horizontal field of view."""
    if not 0 < fov_x_deg < 180:
        raise RigError(f"horizontal field of view must lie in (0°, 180°), got {fov_x_deg}")
    f = width / (2 * math.tan(math.radians(fov_x_deg) / 2))
    return Intrinsics(int(width), int(height), f, f, width / 2, height / 2)


def projector_intrinsics_from_throw(width: int, height: int, throw_ratio: float,
                                    shift_x: float = 0.0, shift_y: float = 0.0) -> Intrinsics:
    """Spec-sheet form to K: the one place where throw ratio and lens shift become intrinsics.

    ``throw_ratio`` is distance / image width. ``shift_x``/``shift_y`` are the
    displacement of the image centre from the lens axis, as fractions of the
    image width/height, positive right/up (a table-top projector whose image
    starts at the lens axis has ``shift_y = 0.5``).
    """
    if not (isinstance(throw_ratio, (int, float)) and math.isfinite(throw_ratio)) or throw_ratio <= 0:
        raise RigError(f"throw ratio must be a positive number (distance / image width), got {throw_ratio!r}")
    if width <= 0 or height <= 0:
        raise RigError(f"projector resolution must be positive, got {width}×{height}")
    f = throw_ratio * width
    return Intrinsics(int(width), int(height), f, f, width / 2 - shift_x * width, height / 2 + shift_y * height)


def _as_pose(matrix: Any, what: str) -> np.ndarray:
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise RigError(f"{what} must be a finite 4×4 matrix")
    r = m[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-5) or np.linalg.det(r) < 0 or not np.allclose(m[3], [0, 0, 0, 1]):
        raise RigError(f"{what} must be a rigid transform (rotation + translation, no scale or mirror)")
    return m


@dataclass(frozen=True)
class Camera:
    """The camera: it defines the rig frame, so its pose is the identity."""

    intrinsics: Intrinsics

    def to_dict(self) -> dict[str, Any]:
        return {"intrinsics": self.intrinsics.to_dict()}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> Camera:
        return Camera(Intrinsics.from_dict(d["intrinsics"]))


@dataclass(frozen=True)
class Projector:
    """A projector: pinhole intrinsics of its native frame, pose, brightness, and where its input sits.

    ``input_size``/``input_offset`` place the projector input image (the paper's
    600×600) inside the native frame (800×600); the rest of the frame is black.
    ``intensity`` scales emitted light: 1 gives an irradiance of π·value on a
    plane 1 m in front of the lens (Mitsuba's ``projector`` with ``scale = 1``).
    ``lens_distortion``: OpenCV's k1 k2 p1 p2 k3 of the lens when a rig calibration measured them. The renderer's
    projector is a pinhole, and stage B's warp takes the lens up; only what must see the real projector's pixels
    before the warp exists (triangulating the Gray code) uses them.
    """

    intrinsics: Intrinsics
    camera_from_projector: np.ndarray = field(default_factory=lambda: np.eye(4))
    intensity: float = 1.0
    input_size: tuple[int, int] | None = None
    input_offset: tuple[int, int] | None = None
    lens_distortion: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "camera_from_projector", _as_pose(self.camera_from_projector, "projector pose"))
        if not math.isfinite(self.intensity) or self.intensity <= 0:
            raise RigError(f"projector intensity must be positive, got {self.intensity}")
        w, h = self.intrinsics.size
        size = tuple(int(v) for v in (self.input_size or (w, h)))
        if size[0] <= 0 or size[1] <= 0 or size[0] > w or size[1] > h:
            raise RigError(f"projector input size {size} must be positive and fit in the {w}×{h} frame")
        offset = self.input_offset
        if offset is None:
            offset = ((w - size[0]) // 2, (h - size[1]) // 2)
        offset = tuple(int(v) for v in offset)
        if offset[0] < 0 or offset[1] < 0 or offset[0] + size[0] > w or offset[1] + size[1] > h:
            raise RigError(f"projector input {size} at offset {offset} does not fit in the {w}×{h} frame")
        object.__setattr__(self, "input_size", size)
        object.__setattr__(self, "input_offset", offset)
        if self.lens_distortion is not None:
            dist = tuple(float(v) for v in self.lens_distortion)
            if len(dist) not in (4, 5, 8) or not all(math.isfinite(v) for v in dist):
                raise RigError(f"projector lens distortion must be 4, 5 or 8 finite OpenCV coefficients, got {dist}")
            object.__setattr__(self, "lens_distortion", dist if any(dist) else None)

    def undistort(self, pixels: np.ndarray) -> np.ndarray:
        """Native-frame pixels (N×2, corner convention) of the real lens → where the pinhole puts those rays."""
        p = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        if self.lens_distortion is None:
            return p.copy()
        k = self.intrinsics.opencv_matrix()
        out = cv2.undistortPoints((p - 0.5).reshape(-1, 1, 2), k, np.asarray(self.lens_distortion), P=k)
        return out.reshape(-1, 2) + 0.5

    @property
    def position(self) -> np.ndarray:
        return self.camera_from_projector[:3, 3].copy()

    @property
    def direction(self) -> np.ndarray:
        """Unit optical axis (+z of the projector frame) in the rig frame."""
        return self.camera_from_projector[:3, 2].copy()

    def frame_from_input(self, image: np.ndarray) -> np.ndarray:
        """Place an input image (input_size) into a black native frame."""
        w, h = self.input_size
        img = np.asarray(image, dtype=np.float32)
        if img.shape[:2] != (h, w):
            raise ImageError(f"projector input must be {w}×{h} pixels, got {img.shape[1]}×{img.shape[0]}")
        fw, fh = self.intrinsics.size
        frame = np.zeros((fh, fw) + img.shape[2:], dtype=np.float32)
        x0, y0 = self.input_offset
        frame[y0:y0 + h, x0:x0 + w] = img
        return frame

    def project(self, points_rig: np.ndarray) -> np.ndarray:
        """Projector pixels of N×3 rig-frame points."""
        inv = np.linalg.inv(self.camera_from_projector)
        p = np.asarray(points_rig, dtype=np.float64).reshape(-1, 3) @ inv[:3, :3].T + inv[:3, 3]
        return self.intrinsics.project(p)

    def with_pose(self, camera_from_projector: np.ndarray) -> Projector:
        return replace(self, camera_from_projector=np.asarray(camera_from_projector, dtype=np.float64))

    def scaled(self, width: int, height: int) -> Projector:
        """The same projector at another native resolution; the input keeps its share of the frame."""
        sx, sy = width / self.intrinsics.width, height / self.intrinsics.height
        size = (max(1, round(self.input_size[0] * sx)), max(1, round(self.input_size[1] * sy)))
        offset = (round(self.input_offset[0] * sx), round(self.input_offset[1] * sy))
        offset = (min(offset[0], width - size[0]), min(offset[1], height - size[1]))
        return replace(self, intrinsics=self.intrinsics.scaled(width, height), input_size=size, input_offset=offset)

    def to_dict(self) -> dict[str, Any]:
        return {"intrinsics": self.intrinsics.to_dict(),
                "camera_from_projector": self.camera_from_projector.tolist(),
                "intensity": float(self.intensity),
                "input_size": list(self.input_size), "input_offset": list(self.input_offset),
                **({"lens_distortion": list(self.lens_distortion)} if self.lens_distortion else {})}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> Projector:
        try:
            return Projector(Intrinsics.from_dict(d["intrinsics"]), np.asarray(d["camera_from_projector"], dtype=float),
                             float(d.get("intensity", 1.0)),
                             _pixel_pair(d["input_size"], "input size") if d.get("input_size") else None,
                             _pixel_pair(d["input_offset"], "input offset") if d.get("input_offset") else None,
                             tuple(d["lens_distortion"]) if d.get("lens_distortion") else None)
        except KeyError as exc:
            raise RigError(f"projector description lacks {exc}") from None
        except (IndexError, OverflowError) as exc:  # an input size or offset of one number, or an infinite one
            raise RigError(f"projector description has an invalid input size or offset ({exc})") from None


#: Two projectors whose centres are closer than this (metres) and whose axes agree within MIN_TURN_DEG are one
#: projector given twice, almost always a copy-paste mistake in a rig file.
MIN_SEPARATION = 1e-3
MIN_TURN_DEG = 0.01


@dataclass(frozen=True)
class Rig:
    """Camera (at the origin of the rig frame) and one or more projectors.

    ``projector`` is the first projector (index 0), the one every single-projector step uses; ``others`` are
    projectors 2…N of a multi-projector rig, each with its own size, lens, pose and intensity. ``Rig(camera,
    projector)`` is the one-projector rig it always was, and its dictionary is unchanged: the ``projectors`` list
    is written only when there is more than one.
    """

    camera: Camera
    projector: Projector
    others: tuple[Projector, ...] = ()

    def __post_init__(self) -> None:
        others = tuple(self.others)
        if not all(isinstance(p, Projector) for p in others):
            raise RigError("the rig's other projectors must be Projector descriptions")
        object.__setattr__(self, "others", others)
        projectors = self.projectors
        for i, a in enumerate(projectors):
            for j in range(i + 1, len(projectors)):
                b = projectors[j]
                apart = float(np.linalg.norm(a.position - b.position))
                turn = math.degrees(math.acos(float(np.clip(a.direction @ b.direction, -1.0, 1.0))))
                if apart < MIN_SEPARATION and turn < MIN_TURN_DEG:
                    raise RigError(f"projectors {i + 1} and {j + 1} have the same pose (centres "
                                   f"{apart * 1000:.2f} mm apart, same direction); each projector needs its own pose")

    @property
    def projectors(self) -> tuple[Projector, ...]:
        """Every projector, the first (``projector``) first."""
        return (self.projector, *self.others)

    def projector_at(self, index: int) -> Projector:
        """Projector ``index`` (0 = the first), or a :class:`RigError` naming how many there are."""
        projectors = self.projectors
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index < len(projectors):
            raise RigError(f"the rig has {len(projectors)} projector(s), numbered 0 to {len(projectors) - 1}; "
                           f"there is no projector {index!r}")
        return projectors[int(index)]

    def with_projectors(self, projectors: Any) -> Rig:
        """The same camera with these projectors (at least one; the first becomes ``projector``)."""
        projectors = tuple(projectors)
        if not projectors:
            raise RigError("a rig needs at least one projector")
        return Rig(self.camera, projectors[0], projectors[1:])

    def to_dict(self) -> dict[str, Any]:
        # "projector" stays the first projector, so a reader that knows only one projector reads the first
        return {"frame": "OpenCV camera frame: x right, y down, z forward, metres",
                "camera": self.camera.to_dict(), "projector": self.projector.to_dict(),
                **({"projectors": [p.to_dict() for p in self.projectors]} if self.others else {})}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> Rig:
        try:
            camera = Camera.from_dict(d["camera"])
        except KeyError as exc:
            raise RigError(f"rig description lacks {exc}") from None
        return Rig(camera, *projectors_from_dict(d))


def projectors_from_dict(d: dict[str, Any]) -> tuple[Projector, tuple[Projector, ...]]:
    """The first projector and the others of a description holding ``projector`` (one projector) or a
    ``projectors`` list (several; a ``projector`` beside it must be the first of them), as a rig or a capture set
    writes them."""
    try:
        many = d.get("projectors")
        if many is None:
            return Projector.from_dict(d["projector"]), ()
        if not isinstance(many, list) or not many or not all(isinstance(p, dict) for p in many):
            raise RigError("'projectors' must be a list of one or more projector descriptions")
        projectors = [Projector.from_dict(p) for p in many]
        if "projector" in d and Projector.from_dict(d["projector"]).to_dict() != projectors[0].to_dict():
            raise RigError("'projector' differs from the first of the 'projectors'; give the first projector once, "
                           "in 'projectors', or make the two the same")
        return projectors[0], tuple(projectors[1:])
    except KeyError as exc:
        raise RigError(f"rig description lacks {exc}") from None


def look_at_pose(position: Any, target: Any, up: Any = (0.0, -1.0, 0.0)) -> np.ndarray:
    """OpenCV-frame pose (z towards target, y down ≈ against ``up``) as a 4×4 camera_from_device."""
    p, t, u = (np.asarray(v, dtype=np.float64) for v in (position, target, up))
    z = t - p
    if np.linalg.norm(z) < 1e-12:
        raise RigError("look-at target coincides with the position")
    z /= np.linalg.norm(z)
    x = np.cross(-u, z)  # y points down, so x = y × z with y = -up
    if np.linalg.norm(x) < 1e-9:
        raise RigError("look-at 'up' is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, p
    return m
