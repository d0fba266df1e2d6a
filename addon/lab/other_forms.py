"""A rig whose effects have forms ProCam does not model: what a real rig does to the pipeline.

The lab's effects (:mod:`.effects`) mostly share their functional forms with
the diagnosis's models, so the lab agrees with ProCam too easily. ``procam lab
--other-forms S`` adds, on top of whatever ``--effects`` asks for, one rig of
effects in forms none of ProCam's models has (S in [0, 1] scales them all; 0
off):

projector side, on the emitted frame (after :func:`.effects.apply_projector`):

* a response that varies over the frame: per channel a power law whose exponent
  drifts smoothly across the panel (about 0.9–1.7 at S = 1), mixed with a
  saturating exponential knee; ProCam's response is one curve for the whole frame;
* colour mixing that drifts from one side of the frame to the other (two 3×3
  mixings, blended by the column); ProCam's crosstalk is one matrix;
* vignetting of another law: an off-centre ellipse, falling linearly with the
  radius, faster in blue than in red; ProCam's is radial about the principal
  point, a power of the field angle, the same in every channel;
* a blur that is a uniform disk (not a Gaussian) whose radius grows across
  the frame, as on a surface tilted against the focal plane.

camera side, on the recorded image (after :func:`.effects.apply_camera`, so after
its sensor noise, as a camera processes the raw signal):

* white balance gains, then a tone curve linear up to a knee and compressed
  exponentially above it (ProCam's camera curve blends linear with sRGB);
* a JPEG round trip (8-bit sRGB, quality 85), decoded back to linear, as a
  phone's photographs are.

Nothing in the pipeline may import this module: its purpose is to be what the
models are not (``tests/test_architecture.py`` holds the rule). Every
parameter is drawn from the projector's number alone: one fixed rig, whatever the
lab's seed (which draws its noise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..colour import srgb_decode, srgb_encode
from ..errors import LabError

#: JPEG quality of the camera's round trip (a phone's default is 85–95).
JPEG_QUALITY = 85


def check_strength(value: Any) -> float:
    """The strength of ``--other-forms`` as a float in [0, 1], or a :class:`LabError` saying what is wrong."""
    try:
        s = float(value)
    except (TypeError, ValueError):
        raise LabError(f"--other-forms takes a strength from 0 (off) to 1, got {value!r}") from None
    if not 0.0 <= s <= 1.0 or not math.isfinite(s):
        raise LabError(f"--other-forms takes a strength from 0 (off) to 1, got {value!r}")
    return s


def _field(rng: np.random.Generator, shape: tuple[int, int], waves: int = 3) -> np.ndarray:
    """A smooth field in [−1, 1] over an H×W frame: a few low-frequency waves of random direction and phase."""
    h, w = shape
    v, u = np.meshgrid(np.linspace(0.0, 1.0, h, dtype=np.float32), np.linspace(0.0, 1.0, w, dtype=np.float32),
                       indexing="ij")
    out = np.zeros(shape, np.float32)
    for _ in range(waves):
        angle, freq, phase = rng.uniform(0, math.pi), rng.uniform(0.5, 1.5), rng.uniform(0, 2 * math.pi)
        out += np.cos(2 * math.pi * freq * (u * math.cos(angle) + v * math.sin(angle)) + phase).astype(np.float32)
    return out / max(float(np.abs(out).max()), 1e-6)


def _mixing(rng: np.random.Generator, leak: float) -> np.ndarray:
    """A 3×3 colour mixing with off-diagonal leaks up to ``leak``, each row summing to 1 (white stays white)."""
    m = np.eye(3) + rng.uniform(0.3, 1.0, (3, 3)) * leak * (1 - np.eye(3))
    return (m / m.sum(axis=1, keepdims=True)).astype(np.float32)


def _disk(radius: float) -> np.ndarray:
    """A uniform disk kernel of ``radius`` pixels, its edge pixels weighted by their covered share (4×4 samples)."""
    r = max(float(radius), 1e-3)
    n = int(math.ceil(r))
    sub = (np.arange(4) + 0.5) / 4 - 0.5
    ys, xs = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1), indexing="ij")
    cover = np.zeros(ys.shape, np.float64)
    for dy in sub:
        for dx in sub:
            cover += (ys + dy) ** 2 + (xs + dx) ** 2 <= r * r
    cover[n, n] = max(cover[n, n], 1.0)
    return (cover / cover.sum()).astype(np.float32)


@dataclass
class OtherForms:
    """The other-forms rig of strength ``strength`` (module doc); ``projector`` numbers the projector (from 0), so
    two projectors of one rig differ as two units of one make do."""

    strength: float
    projector: int = 0
    _cache: dict[tuple[int, int], dict[str, np.ndarray]] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self.strength = check_strength(self.strength)
        rng = np.random.default_rng([4231, int(self.projector)])
        s = self.strength
        self.gamma = (1.0 + s * (0.25 + 0.1 * rng.uniform(-1, 1, 3))).astype(np.float32)
        self.gamma_drift = 0.25 * s
        self.knee_mix = 0.35 * s
        self.knee = 2.5
        self.mix_left, self.mix_right = _mixing(rng, 0.12 * s), _mixing(rng, 0.12 * s)
        self.vignette_centre = rng.uniform(-0.2, 0.2, 2)
        self.vignette_depth = (0.3 * s * np.array([0.8, 1.0, 1.25])).astype(np.float32)
        self.blur = (0.3 * s, 2.2 * s)  # disk radius, native pixels, at the left and right edge of the frame
        self._seed_fields = int(rng.integers(1 << 30))
        self.wb = (1.0 + s * np.array([0.08, 0.0, -0.12])).astype(np.float32)
        self.camera_knee = 1.0 - 0.35 * s

    @property
    def active(self) -> bool:
        return self.strength > 0

    def _fields(self, shape: tuple[int, int]) -> dict[str, np.ndarray]:
        got = self._cache.get(shape)
        if got is None:
            rng = np.random.default_rng(self._seed_fields)
            h, w = shape
            v, u = np.meshgrid(np.linspace(-1, 1, h, dtype=np.float32), np.linspace(-1, 1, w, dtype=np.float32),
                               indexing="ij")
            cx, cy = self.vignette_centre
            r = np.clip(np.hypot((u - cx) / 1.3, (v - cy) / 1.0) / 1.2, 0.0, 1.0)
            got = {"gamma": np.stack([c * (1 + self.gamma_drift * _field(rng, shape)) for c in self.gamma], axis=-1),
                   "column": np.linspace(0.0, 1.0, w, dtype=np.float32)[None, :, None],
                   "vignette": 1.0 - self.vignette_depth[None, None, :] * r[..., None]}
            self._cache[shape] = got
        return got

    def projector_light(self, light: np.ndarray, native_width: int) -> np.ndarray:
        """The frame's emitted light (H×W×3, [0, 1], the lab projector's own effects already on it) through this
        projector's other forms; ``native_width`` scales the blur with a frame rendered below native size."""
        if not self.active:
            return light
        x = np.clip(np.asarray(light, np.float32), 0.0, 1.0)
        h, w = x.shape[:2]
        f = self._fields((h, w))
        knee = (1 - np.exp(-self.knee * x)) / (1 - math.exp(-self.knee))
        x = (1 - self.knee_mix) * np.power(x, f["gamma"]) + self.knee_mix * knee
        left = np.einsum("ij,hwj->hwi", self.mix_left, x)
        right = np.einsum("ij,hwj->hwi", self.mix_right, x)
        x = (1 - f["column"]) * left + f["column"] * right
        x = x * f["vignette"]
        scale = w / max(int(native_width), 1)
        r0, r1 = (r * scale for r in self.blur)
        if r1 > 0.2:
            radii = np.linspace(r0, r1, 4)
            blurred = [cv2.filter2D(x, -1, _disk(r), borderType=cv2.BORDER_CONSTANT) if r > 0.2 else x for r in radii]
            pos = f["column"][0, :, 0] * (len(radii) - 1)
            lo = np.minimum(pos.astype(int), len(radii) - 2)
            t = (pos - lo)[None, :, None]
            stack = np.stack(blurred)
            cols = np.arange(w)
            x = (1 - t) * stack[lo, :, cols].transpose(1, 0, 2) + t * stack[lo + 1, :, cols].transpose(1, 0, 2)
        return np.clip(x, 0.0, 1.0).astype(np.float32)

    def camera_tone(self, image: np.ndarray) -> np.ndarray:
        """The camera's processing of its linear image before the JPEG: white balance and the knee tone curve."""
        v = np.clip(np.asarray(image, np.float32) * self.wb, 0.0, None)
        k = self.camera_knee
        if k < 1.0:
            over = np.maximum(v - k, 0.0) / (1.0 - k)
            v = np.where(v > k, k + (1.0 - k) * (1.0 - np.exp(-1.6 * over)) / (1.0 - math.exp(-1.6)), v)
        return np.clip(v, 0.0, 1.0).astype(np.float32)

    def camera_record(self, image: np.ndarray) -> np.ndarray:
        """What the camera writes of its linear image (H×W×3, [0, 1], after its sensor noise): white balance, a
        knee tone curve, a JPEG round trip, read back as linear."""
        if not self.active:
            return image
        code = np.round(srgb_encode(self.camera_tone(image)) * 255.0).astype(np.uint8)
        ok, buf = cv2.imencode(".jpg", code[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise LabError("the other-forms camera could not encode its JPEG")
        back = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255.0
        return np.clip(srgb_decode(back), 0.0, 1.0).astype(np.float32)


__all__ = ["JPEG_QUALITY", "OtherForms", "check_strength"]
