"""Effect models: extensions of the forward model ``f̂`` named after the lab's effects (one registry).

Each model adds a few parameters to ``f̂`` and predicts a capture from the
renders in :class:`.data.Observation`. Where light meets each effect:

* on the real input, before the renderer (``response`` → ``crosstalk`` →
  ``black_level``'s projector part → ``vignetting``; ``defocus`` blurs the input
  first): evaluated along each camera pixel's light path, so a change
  ``x → g(x)`` of the input changes direct light by ``gain · (g(x) − x)(corr)``;
* in the renderer (``interreflection`` adds a share of the indirect-light render,
  ``glossy`` mixes in a white GGX lobe, and where the lobe clipped the white
  capture, from which calibration read the albedo, puts back the light the
  sensor lost), and the geometry (``depth_noise``: a
  smooth depth error moves each pixel's light path, ``corr``);
* on the camera image (``black_level``'s ambient part → ``distortion`` →
  ``camera_response``).

The same names as ``addon/lab/effects.py``; ``noise`` has no model (it is the
floor the diagnosis cannot remove). Parameters are plain floats with bounds; the
``identity`` values switch a model off exactly.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..colour import srgb_encode
from ..memo import recent
from ..rig.lens import undistort_normalised
from ..stages.calibrate import SATURATED
from .data import GLOSSY_ROUGHNESS, GapData, Observation, column, sample_pattern

#: Width (share of the working image width) over which the diffuse white is carried into clipped highlights.
FILL_SIGMA = 0.04
#: A clipped highlight's light is capped at this percentile of the model's light over the saturated patch: its
#: edge level, robust to the few patch pixels that the diffuse light alone clipped.
CAP_PERCENTILE = 10


@dataclass(frozen=True)
class EffectModel:
    """A named extension of f̂: parameter names, identity values, bounds, and where it should show."""

    name: str
    params: tuple[str, ...]
    identity: tuple[float, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    signature: str  # where its residual should lie, in words (see ``signature_mask``)
    start: tuple[float, ...] | None = None  # where the fit starts (identity is a saddle for some models)
    #: Parameters first held at their identity values; freed only if that lowers the fit error (``fit.NESTED_GAIN``)
    nested: tuple[int, ...] = ()
    #: Its form acts in places the geometry sets (light carried between surface parts, a highlight), not by input
    #: level, colour or image position over the whole lit area: only such an effect has a place to point at.
    local: bool = False

    def initial(self) -> np.ndarray:
        return np.asarray(self.start if self.start is not None else self.identity, float)


MODELS: dict[str, EffectModel] = {m.name: m for m in (
    # A power law per channel, then a shared logistic S-curve (toe and shoulder; contrast 0 = none): a power law
    # alone bends one way everywhere and could not fit a projector whose tone curve has a toe (measured: on the
    # lab's S-curve response the diagnosis named black level and crosstalk instead). The S-curve is tried only
    # on top of the power law (``nested``): a mild S with a lower γ mimics a power law, and a plain power law
    # should be reported as one.
    EffectModel("response", ("gamma_r", "gamma_g", "gamma_b", "contrast", "pivot"), (1, 1, 1, 0, 0.5),
                (0.3, 0.3, 0.3, 0, 0.2), (3.5, 3.5, 3.5, 4, 0.8), "mid input levels", nested=(3, 4)),
    EffectModel("crosstalk", ("rg", "rb", "gr", "gb", "br", "bg"), (0,) * 6, (-0.1,) * 6, (0.5,) * 6,
                "saturated input colours"),
    EffectModel("black_level", ("projector", "ambient_r", "ambient_g", "ambient_b"), (0, 0, 0, 0),
                (0, -0.02, -0.02, -0.02), (0.2, 0.5, 0.5, 0.5), "dark input levels"),
    EffectModel("vignetting", ("falloff", "exponent"), (0, 2), (-0.5, 1), (0.9, 6), "near the projector's corners",
                start=(0.05, 2)),
    EffectModel("defocus", ("sigma",), (0,), (0,), (12,), "at edges of the projected pattern (high spatial "
                "frequency)", start=(0.7,)),
    EffectModel("interreflection", ("gain",), (0,), (0,), (2.5,), "where indirect light is strong (concave parts)",
                local=True),
    EffectModel("glossy", ("weight", "roughness"), (0, 0.4), (0, GLOSSY_ROUGHNESS[0]), (0.8, GLOSSY_ROUGHNESS[-1]),
                "where a glossy lobe changes the image (view-dependent highlights)", start=(0.05, 0.4), local=True),
    EffectModel("camera_response", ("curve",), (0,), (0,), (1,), "mid camera levels", start=(0.1,)),
    EffectModel("distortion", ("k1", "k2"), (0, 0), (-0.4, -0.15), (0.4, 0.15), "near the camera image border"),
    EffectModel("depth_noise", ("offset", "slope_x", "slope_y"), (0, 0, 0), (-0.1,) * 3, (0.1,) * 3,
                "at edges of the projected pattern, along the projector–camera baseline"),
)}
NAMES: tuple[str, ...] = tuple(MODELS)
#: The models :meth:`Composite.predict` applies before the scene's extra light (on the input, the lens, the light
#: paths; black level's projector part is among them, its ambient part on the camera's side), and the scene's.
PROJECTOR_SIDE = ("depth_noise", "defocus", "response", "crosstalk", "black_level", "vignetting")
SCENE_SIDE = ("interreflection", "glossy")


def projector_tone(a: np.ndarray, gammas: np.ndarray, contrast: float = 0.0, pivot: float = 0.5) -> np.ndarray:
    """The ``response`` model's curve: ``S(a^γ)``, S a logistic through (0, 0) and (1, 1) (identity at contrast 0).

    The logistic's slope is ``10·√contrast``: the curve departs from the identity in proportion to the square of
    the slope, so in ``contrast`` it does so linearly, and a fit starting from none can move (no saddle).
    """
    y = np.power(np.clip(a, 0.0, 1.0), np.asarray(gammas, np.float32))
    if contrast <= 1e-6:
        return y.astype(np.float32, copy=False)
    lo, hi = _logistic(0.0, contrast, pivot), _logistic(1.0, contrast, pivot)
    return ((_logistic(y, contrast, pivot) - lo) / (hi - lo)).astype(np.float32)


def inverse_projector_tone(y: np.ndarray, gammas: np.ndarray, contrast: float = 0.0, pivot: float = 0.5
                           ) -> np.ndarray:
    """The input whose :func:`projector_tone` is ``y`` (clipped to [0, 1])."""
    z = np.clip(np.asarray(y, np.float64), 0.0, 1.0)
    if contrast > 1e-6:
        lo, hi = _logistic(0.0, contrast, pivot), _logistic(1.0, contrast, pivot)
        q = np.clip(lo + z * (hi - lo), 1e-12, 1 - 1e-12)
        z = np.clip(pivot + np.log(q / (1 - q)) / (10.0 * np.sqrt(contrast)), 0.0, 1.0)
    g = np.maximum(np.asarray(gammas, np.float64), 1e-3)
    return np.power(z, 1.0 / g).astype(np.float32)


def _logistic(v: np.ndarray | float, contrast: float, p: float) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-10.0 * np.sqrt(contrast) * (np.asarray(v, np.float64) - p)))


def crosstalk_matrix(p: np.ndarray) -> np.ndarray:
    """3×3 mixing, rows summing to 1 (white stays white): out_c = Σ_d M[c, d] · in_d."""
    rg, rb, gr, gb, br, bg = p
    return np.array([[1 - rg - rb, rg, rb], [gr, 1 - gr - gb, gb], [br, bg, 1 - br - bg]], np.float32)


def vignetting_radius(projector: Any, positions: np.ndarray) -> np.ndarray:
    """Field-angle radius about the projector's principal point, over that of the farthest input corner,
    at real-input positions (…×2, cv2.remap convention)."""
    iw, ih = projector.input_size
    k = projector.intrinsics
    ccx, ccy = k.cx - projector.input_offset[0] - 0.5, k.cy - projector.input_offset[1] - 0.5
    rx, ry = (positions[..., 0] - ccx) / k.fx, (positions[..., 1] - ccy) / k.fy
    rmax = max(np.hypot(cx / k.fx, cy / k.fy)
               for cx in (-0.5 - ccx, iw - 0.5 - ccx) for cy in (-0.5 - ccy, ih - 0.5 - ccy))
    return (np.hypot(rx, ry) / rmax).astype(np.float32)


def camera_curve(v: np.ndarray, curve: float) -> np.ndarray:
    """The camera's tone curve: linear light → captured value (a blend of linear and the sRGB encoding)."""
    v = np.clip(v, 0.0, 1.0)
    return ((1.0 - curve) * v + curve * srgb_encode(v)).astype(np.float32)


def inverse_camera_curve(y: np.ndarray, curve: float) -> np.ndarray:
    """Captured value → linear light (the curve is increasing, so a table inverts it)."""
    grid = np.linspace(0.0, 1.0, 4097, dtype=np.float32)
    y = np.asarray(y, np.float32)
    # Above 1 (an effective albedo may exceed 1) continue with slope 1 rather than saturate.
    return (np.interp(np.clip(y, 0.0, 1.0), camera_curve(grid, curve), grid) + np.maximum(y - 1.0, 0.0)
            ).astype(np.float32)


def light_scale(white: np.ndarray, curve: float) -> np.ndarray:
    """Per pixel: linear light over model units, where the model's white (``white``) is a captured value."""
    white = np.asarray(white, np.float32)
    # Where white gives (almost) no light the scale is undefined and nothing depends on it: keep 1.
    return np.where(white > 1e-3, inverse_camera_curve(white, curve) / np.maximum(white, 1e-3), 1.0
                    ).astype(np.float32)


class Composite:
    """Several effect models on top of f̂, with one flat parameter vector (in ``names`` order)."""

    def __init__(self, data: GapData, names: tuple[str, ...]) -> None:
        unknown = [n for n in names if n not in MODELS]
        if unknown:
            raise KeyError(f"unknown effect model(s) {unknown}; known: {', '.join(NAMES)}")
        self.data = data
        self.names = tuple(n for n in NAMES if n in names)  # the physical order, whatever the caller's
        self.slices: dict[str, slice] = {}
        i = 0
        for n in self.names:
            k = len(MODELS[n].params)
            self.slices[n] = slice(i, i + k)
            i += k
        self.size = i
        h, w = data.mask.shape
        c = data.camera
        ys, xs = np.mgrid[0:h, 0:w] + 0.5
        self._xn = ((xs - c.cx) / c.fx).astype(np.float32)
        self._yn = ((ys - c.cy) / c.fy).astype(np.float32)
        self._vig_r = vignetting_radius(data.projector, data.corr)
        self._saturated, self._diffuse_white = _clipped_white(data)
        # A fit's finite differences move one parameter at a time: the blurred input, the response's curve and
        # the camera curve's light scale stay the same for every other column, so the last few are kept
        # (measured: the two curves took ~45 % of a demo diagnosis, recomputed for every column; the blur,
        # once it was kept too, most of what a fit with defocus took).
        self._inputs: dict[float, dict[int, np.ndarray]] = {}
        self._tones: dict[tuple[float, ...], dict[int, np.ndarray]] = {}
        self._scales: dict[float, np.ndarray] = {}
        # ... and the image before the scene's effects and before the camera's (keyed by the parameters they
        # depend on): a column of the camera's or the scene's parameters recomputes only the stages after it.
        # Every column moves off the same point, so a composite on a few pixels (:meth:`on_pixels`) keeps one entry
        # a column and a few more; one on the whole image the last three.
        self._lit: dict[tuple[float, ...], dict[int, np.ndarray]] = {}
        self._scene: dict[tuple[float, ...], dict[int, np.ndarray]] = {}
        self._keep = 3
        #: rows of ``data`` that repeat the first ``len / _repeat`` (a stack of patterns, :meth:`on_pixels`)
        self._repeat = 1

    def on_pixels(self, pixels: np.ndarray, index: list[int] | None = None) -> Composite:
        """This composite at some working pixels only (:meth:`GapData.on_pixels`; predictions n×1×3): a fit's
        residual uses 8,000 pixels a pattern (:data:`fit.FIT_PIXELS`), and predicting the whole image for it
        was most of a diagnosis's time. With ``index``, the patterns ``index`` stacked into one observation
        (:meth:`GapData.stacked`, ``data.observations[data.fit_index[0]]``; predictions (len(index)·n)×1×3).
        Not with a lens distortion, which moves the image."""
        if "distortion" in self.names:
            raise ValueError("a distortion moves the image: predict the whole image")
        sub = copy.copy(self)
        repeat = 1 if index is None else len(index)

        def col(a: np.ndarray) -> np.ndarray | None:
            c = column(a, pixels)
            return c if repeat == 1 or c is None else np.concatenate([c] * repeat)

        sub.data = self.data.on_pixels(pixels) if index is None else self.data.stacked(pixels, index)
        sub._xn, sub._yn, sub._vig_r = (col(a) for a in (self._xn, self._yn, self._vig_r))
        sub._saturated, sub._diffuse_white = col(self._saturated), col(self._diffuse_white)
        sub._inputs, sub._tones, sub._scales, sub._lit, sub._scene = {}, {}, {}, {}, {}
        sub._repeat = repeat
        # images of a few thousand pixels: enough for every column of a finite-difference Jacobian
        sub._keep = self.size + 3
        return sub

    def _per_pattern(self, cache: dict, key: Any, obs: Observation, make: Any, keep: int = 3) -> np.ndarray:
        """``make()`` for this pattern, remembered in ``cache`` under ``key`` (None: made every time) with the
        ``keep`` most recent keys."""
        if key is None:
            return make()
        per = recent(cache, key, dict, keep)
        out = per.get(id(obs))
        if out is None:
            out = per[id(obs)] = make()
        return out

    def _input_at(self, obs: Observation, sigma: float, corr: np.ndarray) -> np.ndarray:
        """The pattern's input at each camera pixel's light path ``corr``, through a lens blur of ``sigma``
        texels (0: none); remembered on the calibrated light paths."""
        d = self.data

        def make() -> np.ndarray:
            moved = corr is not d.corr
            if sigma <= 0:
                return sample_pattern(obs, corr) if moved else obs.sampled
            if d.footprint <= 0:
                return sample_pattern(obs, corr, blur=sigma)
            # A pixel wider than two texels sees the blur's change averaged over its footprint (data.py).
            plain, averaged = (sample_pattern(obs, corr), sample_pattern(obs, corr, d.footprint)) if moved else \
                (obs.sampled, obs.averaged)
            return plain + sample_pattern(obs, corr, d.footprint, sigma) - averaged

        return self._per_pattern(self._inputs, sigma if corr is d.corr else None, obs, make)

    def _tone(self, a: np.ndarray, obs: Observation, r: np.ndarray, sigma: float | None) -> np.ndarray:
        """:func:`projector_tone` of the pattern's input ``a`` (from :meth:`_input_at` with a blur of ``sigma``);
        remembered unless ``sigma`` is None (light paths moved), each channel on its own parameters: a column of
        a channel's exponent recomputes that channel alone (the curve was a sixth of a demo diagnosis's fits)."""
        contrast, pivot = float(r[3]), float(r[4])
        if sigma is None:
            return projector_tone(a, r[:3], contrast, pivot)
        out = np.empty_like(a)
        for c in range(3):
            def make(c: int = c) -> np.ndarray:
                return projector_tone(a[..., c], np.asarray(r[c], np.float32), contrast, pivot)

            out[..., c] = self._per_pattern(self._tones, (sigma, c, float(r[c]), contrast, pivot), obs, make,
                                            3 * self._keep)
        return out

    def _light_scale(self, curve: float) -> np.ndarray:
        def make() -> np.ndarray:
            if self._repeat == 1:
                return light_scale(self.data.gain, curve)
            # a stack repeats each pixel's gain: the curve's table is inverted once a pixel
            rows = len(self.data.gain) // self._repeat
            return np.concatenate([light_scale(self.data.gain[:rows], curve)] * self._repeat)

        return recent(self._scales, curve, make)

    @staticmethod
    def _key(p: dict[str, np.ndarray], names: tuple[str, ...]) -> tuple[float, ...]:
        """The values of the parameters of ``names`` that act there (black level: its projector part)."""
        return tuple(v for n in names if n in p for v in (p[n][:1] if n == "black_level" else p[n]).tolist())

    def initial(self) -> np.ndarray:
        return np.concatenate([MODELS[n].initial() for n in self.names]) if self.names else np.zeros(0)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.concatenate([MODELS[n].lower for n in self.names]) if self.names else np.zeros(0)
        hi = np.concatenate([MODELS[n].upper for n in self.names]) if self.names else np.zeros(0)
        return lo.astype(float), hi.astype(float)

    def split(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        return {n: np.asarray(theta[s], float) for n, s in self.slices.items()}

    # ------------------------------------------------------------------ prediction

    def _corr(self, p: dict[str, np.ndarray]) -> np.ndarray:
        d = self.data
        if "depth_noise" not in p:
            return d.corr
        off, sx, sy = p["depth_noise"]
        # A smooth depth error δ (metres along each camera ray) moves each light path to first order.
        delta = (off + sx * self._xn + sy * self._yn)[..., None]
        return np.where(d.corr > -5, d.corr + d.corr_per_metre * delta, d.corr).astype(np.float32)

    def predict(self, theta: np.ndarray, obs: Observation, corr: np.ndarray | None = None) -> np.ndarray:
        """The capture this composite model predicts for one pattern (h×w×3, clipped to [0, 1])."""
        p = self.split(theta)
        d = self.data
        given = corr is not None
        # the image the projector side gives (input, lens, light paths), then with the scene's extra light:
        # remembered on their own parameters unless the light paths were given
        lit_key = None if given else ("lit", *self._key(p, PROJECTOR_SIDE))
        scene_key = None if lit_key is None else (*lit_key, *self._key(p, SCENE_SIDE))

        def lit() -> np.ndarray:
            return self._lit_image(p, obs, corr if corr is not None else self._corr(p))

        def scene() -> np.ndarray:
            img = self._per_pattern(self._lit, lit_key, obs, lit, self._keep)
            # The albedo was estimated from the white capture, so it already holds white's share of any extra
            # light (indirect, glossy): the model adds only what a pattern gets beyond white × its input level.
            white = d.white
            if "interreflection" in p:
                img = img + float(p["interreflection"][0]) * (obs.indirect - white.indirect * obs.sampled)
            if "glossy" in p:
                weight, rough = p["glossy"]
                img = img + weight * (glossy_at(obs, float(rough)) - glossy_at(white, float(rough)) * obs.sampled)
                if weight > 0 and self._saturated.any():  # weight 0 is the identity, exactly
                    img = img * self.clipped_white_gain(float(weight), float(rough))
            return img

        img = self._per_pattern(self._scene, scene_key, obs, scene, self._keep)
        if "camera_response" in p:
            # The albedo holds the curve at white: take the image to light with white's scale before the
            # ambient light adds and the curve applies (white-balance gains cancel against the albedo).
            img = img * self._light_scale(float(p["camera_response"][0]))
        if "black_level" in p:
            img = img + p["black_level"][1:].astype(np.float32)
        if "distortion" in p:
            img = self._distort(img, *p["distortion"])
        if "camera_response" in p:
            img = camera_curve(img, float(p["camera_response"][0]))
        return np.clip(img, 0.0, 1.0).astype(np.float32)

    def _lit_image(self, p: dict[str, np.ndarray], obs: Observation, corr: np.ndarray) -> np.ndarray:
        """The image of the pattern's direct light through the projector-side models (before the scene's)."""
        d = self.data
        sigma = float(p["defocus"][0]) if "defocus" in p and p["defocus"][0] > 0.05 else 0.0
        a = self._input_at(obs, sigma, corr)
        if "response" in p:
            a = self._tone(a, obs, p["response"], sigma if corr is d.corr else None)
        if "crosstalk" in p:
            # as one (pixels × 3) product: a stack of one-pixel rows (n×1×3) multiplied row by row took 9× longer
            a = (a.reshape(-1, 3) @ crosstalk_matrix(p["crosstalk"]).T).reshape(a.shape)
        if "black_level" in p:
            b = float(p["black_level"][0])
            a = b + (1.0 - b) * a
        if "vignetting" in p:
            falloff, exponent = p["vignetting"]
            a = a * (1.0 - falloff * np.power(self._vig_r, exponent))[..., None]
        return obs.direct + d.gain * (a - obs.sampled)

    def clipped_white_gain(self, weight: float, rough: float) -> np.ndarray:
        """The glossy model's camera-side gain (h×w×3): where the white capture clipped, the albedo holds only
        what the sensor could take, so the model is too dark at every lower level. The lobe says what white
        really was (the diffuse white of the neighbourhood plus the highlight); 1 elsewhere."""
        if weight <= 0 or not self._saturated.any():
            return np.ones_like(self.data.gain)
        gain = self.data.gain
        full = self._diffuse_white + weight * glossy_at(self.data.white, rough)
        return np.where(self._saturated, np.maximum(full, gain) / np.maximum(gain, 1e-3), 1.0).astype(np.float32)

    def _distort(self, img: np.ndarray, k1: float, k2: float) -> np.ndarray:
        # The captured pixel at distorted position p shows the scene of the undistorted position:
        # sample the undistorted image at p's undistorted position (one fixed-point step is enough
        # for |k1| ≤ 0.4 over a normal field of view).
        c = self.data.camera
        xu, yu = undistort_normalised(self._xn, self._yn, k1, k2, steps=3)
        mx = (xu * c.fx + c.cx - 0.5).astype(np.float32)
        my = (yu * c.fy + c.cy - 0.5).astype(np.float32)
        return cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _clipped_white(data: GapData) -> tuple[np.ndarray, np.ndarray]:
    """Where the white capture saturated (h×w×3 bool), and the model's white carried into those pixels from
    the unclipped neighbourhood (normalised Gaussian convolution): the diffuse part of a clipped highlight."""
    sat = (data.white.capture >= SATURATED) & data.mask[..., None]
    if not sat.any():
        return sat, data.gain
    sigma = max(1.0, FILL_SIGMA * data.mask.shape[1])
    keep = (data.mask[..., None] & ~sat).astype(np.float32)
    num = cv2.GaussianBlur(data.gain * keep, (0, 0), sigma)
    den = cv2.GaussianBlur(keep, (0, 0), sigma)
    fill = np.where(den > 1e-3, num / np.maximum(den, 1e-3), data.gain)
    return sat, np.where(sat, fill, data.gain).astype(np.float32)


def glossy_at(obs: Observation, rough: float) -> np.ndarray:
    """The white GGX lobe render of a pattern at roughness ``rough`` (interpolated between the rendered ones)."""
    rs = sorted(obs.glossy)
    rough = min(max(rough, rs[0]), rs[-1])
    j = max(0, min(len(rs) - 2, int(np.searchsorted(rs, rough)) - 1))
    r0, r1 = rs[j], rs[j + 1]
    t = (rough - r0) / (r1 - r0)
    return (1 - t) * obs.glossy[r0] + t * obs.glossy[r1]


def local_light(name: str, values: np.ndarray, data: GapData) -> np.ndarray:
    """A local effect model's own light under the white input (h×w, mean over channels), at fitted ``values``:
    the bounce light or the highlight, where the calibrated geometry puts it; a highlight as far as the camera saw
    it (:func:`_seen_as_clipped`)."""
    if name == "interreflection":
        light = float(values[0]) * data.white.indirect
    elif name == "glossy":
        return _seen_as_clipped(float(values[0]) * glossy_at(data.white, float(values[1])).mean(axis=2), data)
    else:
        raise ValueError(f"{name} is not a local effect model")
    return light.mean(axis=2)


def _seen_as_clipped(light: np.ndarray, data: GapData) -> np.ndarray:
    """A highlight's light as far as the camera saw it: where the white capture saturated around the lobe's peak,
    the camera saw no more than at the patch's edge, so the light is capped at its level there.

    Uncapped, a strong lobe's light is a sharp peak and the region drawn on it (the set holding half of it) was
    the peak alone, a third of the patch the highlight clipped (lab, glossy at 1.0: IoU 0.36–0.45 against the
    footprint). The cap comes from the captured saturation: placed by the model's diffuse light plus its lobe
    clipped at 1 instead, the plane's highlight at 0.5 was drawn far too wide (IoU 0.87 → 0.34).
    """
    sat = ((data.white.capture >= SATURATED).any(axis=2) & data.mask).astype(np.uint8)
    peak = np.unravel_index(int(np.argmax(np.where(data.mask, light, -np.inf))), light.shape)
    if not sat[peak]:
        return light
    _, labels = cv2.connectedComponents(sat, connectivity=8)
    patch = labels == labels[peak]
    return np.minimum(light, float(np.percentile(light[patch], CAP_PERCENTILE)))


def signature_mask(name: str, data: GapData, obs: Observation) -> np.ndarray:
    """Camera pixels (h×w bool) of one pattern where the effect's residual should lie."""
    a = obs.sampled
    level = a.mean(axis=2)
    if name == "response":
        return (level > 0.15) & (level < 0.85)
    if name == "crosstalk":
        return (a.max(axis=2) - a.min(axis=2)) > 0.3
    if name == "black_level":
        return level < 0.15
    if name == "vignetting":
        comp = Composite(data, ())
        return comp._vig_r > 0.6
    if name in ("defocus", "depth_noise"):
        gx = cv2.Sobel(level, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(level, cv2.CV_32F, 0, 1, ksize=3)
        return cv2.dilate((np.hypot(gx, gy) > 0.5).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    if name == "interreflection":
        ind = obs.indirect.mean(axis=2)
        return ind > np.percentile(ind[data.mask], 75) if data.mask.any() else ind > 0
    if name == "glossy":
        diff = np.abs(glossy_at(obs, 0.4) - obs.direct).mean(axis=2)
        lobe = diff > np.percentile(diff[data.mask], 75) if data.mask.any() else diff > 0
        return lobe | (data.white.capture >= SATURATED).any(axis=2)
    if name == "camera_response":
        v = obs.direct.mean(axis=2)
        return (v > 0.15) & (v < 0.7)
    if name == "distortion":
        h, w = data.mask.shape
        ys, xs = np.mgrid[0:h, 0:w]
        r = np.hypot((xs - w / 2) / (w / 2), (ys - h / 2) / (h / 2))
        return r > 0.6
    raise KeyError(name)


def describe_params(name: str, values: np.ndarray) -> dict[str, float]:
    return {p: round(float(v), 5) for p, v in zip(MODELS[name].params, values)}


__all__ = ["Composite", "EffectModel", "MODELS", "NAMES", "crosstalk_matrix", "describe_params",
           "inverse_projector_tone", "local_light", "projector_tone", "signature_mask"]
