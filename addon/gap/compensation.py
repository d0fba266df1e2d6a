"""Compensation with diagnosed effects: the fitted effect models applied around stage C.

Stage C optimises through ``f̂``; the effects the diagnosis selected are put
around it rather than inside, each where it acts:

* input side (``response``, ``crosstalk``, ``black_level``'s projector part,
  ``vignetting``): the projector turns an input ``x`` into the light ``g(x)``,
  so the input sent is ``g⁻¹(x*)`` (the classical linearisation, clipped to
  what the projector can do), and the captures that estimate θ are paired with
  the light ``g(x)`` that was really emitted;
* camera side (``black_level``'s ambient part, ``camera_response``): the camera
  turns light ``v`` into ``h(v)``, so the target and every capture are taken
  back through ``h⁻¹`` before stage C compares them with ``f̂``;
* ``interreflection``: stage C simulates indirect light (3 bounces) instead of
  direct light only;
* ``depth_noise``: the surface is moved along the camera rays by the fitted
  smooth depth error;
* ``defocus``: the lens blurs the light. On the transport operator (the default
  schedule) the blur goes inside stage C's solve (``T B``, :meth:`EffectAdapter.blur_in_solve`):
  its bounded answer is sharpened for what the camera resolves, and is sent as
  it is. With the other schedules, which render every step, the input sent is
  the one in [0, 1] whose blur comes closest to ``g⁻¹(x*)`` (pre-sharpening by
  projected gradient, :func:`presharpen`): that matches every texel, detail no
  camera pixel resolves included, and buys a fifth to two thirds of what the solve
  does (docs/results.md, "Defocus inverted inside the solve").

* ``glossy``: the albedo was read from the white capture, which holds the lobe
  under white; for direct light the lobe sends each camera pixel the same
  projector texel as the diffuse part, so it is a per-pixel gain the albedo
  already holds, and rendering the lobe in the differentiable scene would count
  it twice. What the albedo lacks is the light the white capture clipped in the
  highlight: there the model is too dark at every level, and stage C would push
  the input up where the surface is already brighter than it thinks. So the
  glossy model's gain on those pixels (:meth:`.models.Composite.clipped_white_gain`,
  stored by the diagnosis) divides the target and the captures, a camera-side
  correction like the others.

``distortion`` is diagnosed but not inverted here (the display area itself
would need remapping); stage C's θ absorbs the shift. The result
says which effects it used and which it could not. With ``--effects auto`` it
uses the diagnosis's ``compensation`` list: the selected effects that still help
without the ones it cannot invert (:func:`.fit.compensation_subset`), less
those stage C already holds (a black level in θ, the first bounce of light in
its renders: :data:`HELD_BY_STAGE_C`) and an effect that stands in for another
(``gap.diagnose.CONTRA_SIGNATURE``); named with ``--effects``, those are
inverted too.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from ..errors import CaptureError, ProCamError
from ..stages.calibrate import SATURATED
from ..stages.compensate import Compensator
from .models import (MODELS, crosstalk_matrix, inverse_camera_curve, inverse_projector_tone, light_scale,
                     projector_tone, vignetting_radius)

#: Effects compensation inverts (see the module docstring); the others are reported as not used.
INVERTIBLE = ("response", "crosstalk", "black_level", "vignetting", "defocus", "camera_response", "interreflection",
              "depth_noise", "glossy")
NOT_INVERTED = {"distortion": "the display area is not remapped; θ absorbs the shift"}
#: Effects compensation can invert but ``--effects auto`` leaves to stage C, which already holds them. A black
#: level: θ is a per-pixel offset (open and closed loop); a real one inverted as well gained nothing on the lab's
#: four surfaces and lost up to 0.04 dB at strength 1, more than two captures of one input differ. Bounce light:
#: stage C renders direct light and one bounce; three bounces gained −0.03 to +0.02 dB on the 9 lab sets with
#: bounce light alone (curve, vedge, hedge; strengths 0.25–1) and −0.02 to −0.00 dB on 6 with a projector
#: response or colour crosstalk beside it, and cost the operator's indirect part two more bounces.
HELD_BY_STAGE_C = {
    "black_level": "stage C's θ already holds a constant offset; inverting it as well gains nothing",
    "interreflection": "stage C already simulates the first bounce; simulating three gains nothing"}
#: Emitted light below this share of white is treated as the darkest the projector can do.
_EPS = 1e-4
#: Projected-gradient steps of :func:`presharpen`, and the blur (input texels) below which it is skipped.
PRESHARPEN_STEPS = 40
MIN_DEFOCUS = 0.05


def _blur(x: np.ndarray, sigma: float) -> np.ndarray:
    return cv2.GaussianBlur(x, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)


def presharpen(wanted: np.ndarray, sigma: float, steps: int = PRESHARPEN_STEPS) -> np.ndarray:
    """The input in [0, 1] whose Gaussian blur (``sigma`` texels) is closest to ``wanted`` (least squares).

    Projected gradient with Nesterov momentum: the blur is symmetric and its gain is at most 1, so a unit step
    is safe and its adjoint is itself. Started from ``wanted`` itself, so a few steps already sharpen edges.
    """
    wanted = np.asarray(wanted, np.float32)
    if sigma <= MIN_DEFOCUS:
        return np.clip(wanted, 0.0, 1.0)
    x = y = np.clip(wanted, 0.0, 1.0)
    t = 1.0
    for _ in range(steps):
        x_new = np.clip(y - _blur(_blur(y, sigma) - wanted, sigma), 0.0, 1.0)
        t_new = (1.0 + np.sqrt(1.0 + 4.0 * t * t)) / 2.0
        y = x_new + ((t - 1.0) / t_new) * (x_new - x)
        x, t = x_new, t_new
    return x.astype(np.float32)


@dataclass
class EffectAdapter:
    """The selected effects with their fitted parameters, as transforms around stage C."""

    params: dict[str, dict[str, float]]
    projector: Any  # calibrated rig.model.Projector
    used: list[str] = field(default_factory=list)
    not_used: dict[str, str] = field(default_factory=dict)
    #: f̂ of a white input at the camera size, from the compensator (``camera_to_light`` needs it for a camera curve).
    white: np.ndarray | None = None
    #: the glossy model's gain where the white capture clipped, as the diagnosis stored it (``clipped_white`` in
    #: ``gap.json``: working and camera sizes, and ``[x, y, r, g, b]`` of each pixel whose gain is not 1)
    clipped_white: dict[str, Any] | None = None
    #: stage C's solve holds the fitted blur (:meth:`blur_in_solve`): the input it answers is the one to send
    #: before the blur, so :meth:`input_for` does not pre-sharpen it again
    defocus_in_solver: bool = False
    #: whether the camera side is inverted (:meth:`camera_to_light`); off for one projector of several, whose
    #: camera is every projector's (:func:`projector_adapter`)
    camera_side: bool = True
    _glossy_gain: np.ndarray | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        unknown = [n for n in self.params if n not in MODELS]
        if unknown:
            raise KeyError(f"unknown effect(s) {unknown}")
        self.used = [n for n in MODELS if n in self.params and n in INVERTIBLE]
        self.not_used = {n: NOT_INVERTED[n] for n in self.params if n in NOT_INVERTED}
        iw, ih = self.projector.input_size
        ys, xs = np.mgrid[0:ih, 0:iw].astype(np.float32)
        self._vig_r = vignetting_radius(self.projector, np.stack([xs, ys], axis=2))

    def _p(self, name: str) -> list[float] | None:
        return [float(v) for v in self.params[name].values()] if name in self.params else None

    def _response(self) -> tuple[np.ndarray, float, float] | None:
        """γ per channel, contrast and pivot (a diagnosis from before the S-curve has γ only)."""
        if "response" not in self.params:
            return None
        r = self.params["response"]
        gammas = np.array([r["gamma_r"], r["gamma_g"], r["gamma_b"]], np.float32)
        return gammas, float(r.get("contrast", 0.0)), float(r.get("pivot", 0.5))

    @property
    def defocus(self) -> float | None:
        """The fitted blur of the projector's lens (input texels), None below :data:`MIN_DEFOCUS` or without."""
        p = self._p("defocus")
        return p[0] if p is not None and p[0] > MIN_DEFOCUS else None

    @property
    def bounces(self) -> int | None:
        """Indirect bounces stage C should simulate (None: leave the caller's choice)."""
        p = self._p("interreflection")
        return None if p is None else (3 if p[0] >= 0.25 else 0)

    def blur_in_solve(self, compensator: Any) -> None:
        """Let ``compensator``'s solve on the transport operator hold the fitted blur (``T B``,
        ``stages/transport.py`` ``BlurredRows``) instead of pre-sharpening its answer here: it then sharpens for
        what the camera resolves. For the transport schedule only (the compensator refuses others)."""
        if self.defocus is not None:
            compensator.input_blur = self.defocus
            self.defocus_in_solver = True

    # ------------------------------------------------------------------ projector side

    def emitted(self, x: np.ndarray, *, blur: bool = True) -> np.ndarray:
        """g(x): the light the projector emits for the input ``x`` (input size, H×W×3); ``blur=False``: before
        the lens's blur."""
        a = np.clip(np.asarray(x, np.float32), 0.0, 1.0)
        if blur and (sigma := self.defocus) is not None:
            a = _blur(a, sigma)
        if (r := self._response()) is not None:
            a = projector_tone(a, *r)
        if (p := self._p("crosstalk")) is not None:
            a = a @ crosstalk_matrix(np.array(p)).T
        if (p := self._p("black_level")) is not None:
            a = p[0] + (1.0 - p[0]) * a
        if (p := self._p("vignetting")) is not None:
            a = a * self._vignetting_gain(p, a.shape)[..., None]
        return a.astype(np.float32)

    def input_for(self, light: np.ndarray) -> np.ndarray:
        """g⁻¹: the input that makes the projector emit ``light`` (clipped to what it can emit)."""
        a = np.asarray(light, np.float32)
        if (p := self._p("vignetting")) is not None:
            a = a / np.maximum(self._vignetting_gain(p, a.shape), 0.05)[..., None]
        if (p := self._p("black_level")) is not None:
            a = (a - p[0]) / max(1.0 - p[0], _EPS)
        if (p := self._p("crosstalk")) is not None:
            a = a @ np.linalg.inv(crosstalk_matrix(np.array(p))).T
        a = np.clip(a, 0.0, 1.0)
        if (r := self._response()) is not None:
            a = inverse_projector_tone(a, *r)
        if (sigma := self.defocus) is not None and not self.defocus_in_solver:
            a = presharpen(a, sigma)
        return np.clip(a, 0.0, 1.0).astype(np.float32)

    def _vignetting_gain(self, p: list[float], shape: tuple[int, ...]) -> np.ndarray:
        r = self._vig_r
        if r.shape != tuple(shape[:2]):
            r = cv2.resize(r, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
        return 1.0 - p[0] * np.power(r, p[1])

    # ------------------------------------------------------------------ camera side

    def glossy_gain(self) -> np.ndarray | None:
        """The glossy model's gain at the camera size where the white capture clipped (None: no glossy model, or
        nothing clipped)."""
        if not self.camera_side or "glossy" not in self.params or not (self.clipped_white or {}).get("pixels"):
            return None
        if self._glossy_gain is None:
            cw = self.clipped_white
            w, h = cw["working_size"]
            g = np.ones((h, w, 3), np.float32)
            px = np.asarray(cw["pixels"], np.float32)
            g[px[:, 1].astype(int), px[:, 0].astype(int)] = px[:, 2:5]
            self._glossy_gain = cv2.resize(g, tuple(cw["camera_size"]), interpolation=cv2.INTER_LINEAR)
        return self._glossy_gain

    def camera_to_light(self, image: np.ndarray, white: np.ndarray | None = None,
                        gain: np.ndarray | None = None) -> np.ndarray:
        """h⁻¹: a capture (or a target in capture space) in the model's units.

        With a camera curve the model's albedo holds the curve at white, so light
        is rescaled by the model's white ``white`` (f̂ of a white input, same size
        as ``image``); without ``white`` the image is assumed to be white-level.
        The glossy model's gain (``gain``, same size; by default :meth:`glossy_gain`
        when ``image`` is a whole camera image) divides the light last.
        """
        y = np.asarray(image, np.float32)
        if not self.camera_side:
            return y
        curve = self._p("camera_response")
        if curve is not None:
            y = inverse_camera_curve(y, curve[0])
        if (p := self._p("black_level")) is not None:
            y = y - np.array(p[1:], np.float32)
        if curve is not None:
            if white is None and self.white is not None and self.white.shape == y.shape:
                white = self.white
            if white is not None:
                y = y / light_scale(np.asarray(white, np.float32), curve[0])
        full = self.glossy_gain()
        if gain is None and full is not None and full.shape == y.shape:
            gain = full
        if gain is not None:
            y = y / gain
        return np.clip(y, 0.0, 1.0).astype(np.float32)

    # ------------------------------------------------------------------ stage C around the effects

    def compensator(self, calibration: Any, *, bounces: int = 1, spp: int = 4, seed: int = 0) -> Any:
        """The stage-C compensator of the calibration as the effects change it (surface, bounces); keeps its
        simulated white, which the camera-side inverse needs."""
        comp = Compensator(self.calibration(calibration), bounces=self.bounces if self.bounces is not None
                           else bounces, spp=spp, seed=seed)
        self.white = comp.white()
        return comp

    def model_target(self, fitted: np.ndarray, area: Any) -> np.ndarray:
        """A target fitted to the display area, in the units stage C compares with f̂."""
        gain = self.glossy_gain()
        return self.camera_to_light(fitted, white=area.crop(self.white) if self.white is not None else None,
                                    gain=area.crop(gain) if gain is not None else None)

    def frame_to_send(self, x_input: np.ndarray) -> np.ndarray:
        """The native projector frame to send for stage C's answer ``x*`` (input size)."""
        return self.projector.frame_from_input(self.input_for(x_input))

    # ------------------------------------------------------------------ geometry

    def calibration(self, calibration: Any) -> Any:
        """The calibration with the surface moved by the fitted depth error (unchanged without it)."""
        p = self._p("depth_noise")
        if p is None:
            return calibration
        v = np.asarray(calibration.surface.vertices, np.float64)
        xn, yn = v[:, 0] / v[:, 2], v[:, 1] / v[:, 2]
        delta = p[0] + p[1] * xn + p[2] * yn
        unit = v / np.linalg.norm(v, axis=1, keepdims=True)
        moved = replace(calibration.surface, vertices=(v + unit * delta[:, None]).astype(np.float32))
        return replace(calibration, surface=moved)


class AdaptedCaptures:
    """A capture set seen through the effects: patterns are the light emitted, images the light seen.

    Duck-types the parts of :class:`..capture.format.CaptureSet` that open-loop θ
    estimation reads.
    """

    def __init__(self, captures: Any, adapter: EffectAdapter) -> None:
        self._c, self._a = captures, adapter
        self.path, self.camera, self.projector = captures.path, captures.camera, captures.projector

    def entries_of(self, kind: str) -> list[Any]:
        return self._c.entries_of(kind)

    def image(self, kind: str, **filters: Any) -> np.ndarray:
        """h⁻¹ of the capture; NaN where the camera clipped it inside the glossy model's highlight.

        There the model's white is the lobe's restored one, and a clipped capture divided by the glossy gain
        reads darker than it: it had pulled open-loop θ's gain down in the highlight (on a glossy plane at the
        lab's strength 1 the lobe's inversion then cost 0.3 dB instead of gaining 6). Elsewhere the albedo was
        read from the same clipped white, so a clipped value agrees with it and is kept (left out there too, θ
        extrapolated from the dark patterns alone, far worse).
        """
        raw = self._c.image(kind, **filters)
        light = self._a.camera_to_light(raw)
        gain = self._a.glossy_gain()
        if gain is None or gain.shape != raw.shape:
            return light
        return np.where((raw >= SATURATED) & (gain != 1.0), np.nan, light).astype(np.float32)

    def pattern(self, kind: str, **filters: Any) -> np.ndarray:
        frame = np.array(self._c.pattern(kind, **filters), np.float32)
        p = self._a.projector
        x0, y0 = p.input_offset
        iw, ih = p.input_size
        frame[y0:y0 + ih, x0:x0 + iw] = self._a.emitted(frame[y0:y0 + ih, x0:x0 + iw])
        return frame


class AdaptedDevice:
    """A capture device seen through the effects (closed loop): send g⁻¹(x), return h⁻¹(capture)."""

    def __init__(self, device: Any, adapter: EffectAdapter) -> None:
        self._d, self._a = device, adapter
        self.projector = device.projector

    def __getattr__(self, name: str) -> Any:
        return getattr(self._d, name)

    def project(self, frame: np.ndarray) -> np.ndarray:
        return self._a.camera_to_light(self._d.project(self.send(frame)))

    @property
    def projectors(self) -> tuple[Any, ...]:
        return tuple(self._d.projectors)

    def project_all(self, frames: Sequence[np.ndarray]) -> np.ndarray:
        """Every projector's frame at once through the effects: one projector's, as :meth:`project` (the adapter
        models one projector's effects; passing several frames through it unadapted would be silently wrong)."""
        checked = self._d.check_frames(frames)
        if len(checked) > 1:
            raise CaptureError(f"the effect models of a diagnosis are one projector's; showing {len(checked)} "
                               "projectors at once through them is not implemented yet")
        return self.project(checked[0])

    def send(self, frame: np.ndarray) -> np.ndarray:
        """The native frame to give the real projector for the wanted light ``frame``."""
        return send_through(self._a, frame)


def send_through(adapter: EffectAdapter, frame: np.ndarray) -> np.ndarray:
    """The native frame to give ``adapter``'s projector for the wanted light ``frame`` (g⁻¹ on its input area)."""
    f = np.array(frame, np.float32)
    p = adapter.projector
    x0, y0 = p.input_offset
    iw, ih = p.input_size
    f[y0:y0 + ih, x0:x0 + iw] = adapter.input_for(f[y0:y0 + ih, x0:x0 + iw])
    return f


class AdaptedProjectors:
    """A device of several projectors seen through each projector's own effect models (closed loop of a joint
    solve): projector k's frame sent as g_k⁻¹ of it (``adapters[k]``; None: as it is); the capture through the
    camera's tone curve fitted once for the rig (``camera``, :class:`SharedCamera`), else as the camera gives it."""

    def __init__(self, device: Any, adapters: Sequence[EffectAdapter | None],
                 camera: SharedCamera | None = None) -> None:
        if len(adapters) != len(device.projectors):
            raise CaptureError(f"{len(adapters)} projectors' effect models for a device of "
                               f"{len(device.projectors)} projector(s)")
        self._d, self._adapters, self._camera = device, list(adapters), camera

    def __getattr__(self, name: str) -> Any:  # the device's camera_size, close, …
        if name in ("_d", "_adapters", "_camera"):  # not set yet: no recursion through the lookup below
            raise AttributeError(name)
        return getattr(self._d, name)

    @property
    def projectors(self) -> tuple[Any, ...]:
        return tuple(self._d.projectors)

    def project_all(self, frames: Sequence[np.ndarray]) -> np.ndarray:
        if len(frames) != len(self._adapters):
            raise CaptureError(f"{len(frames)} frames for a device of {len(self._adapters)} projectors")
        capture = self._d.project_all([f if a is None else send_through(a, f) for a, f in zip(self._adapters, frames)])
        return capture if self._camera is None else self._camera.to_model(capture)


def _checked_params(params: Any, where: str) -> dict[str, dict[str, float]]:
    """Effect parameters read from a diagnosis: known effect names, each with a table of finite numbers."""
    if not isinstance(params, dict):
        raise ProCamError(f"{where}: the effects' parameters are malformed; run procam diagnose again")
    out: dict[str, dict[str, float]] = {}
    for name, values in params.items():
        if name not in MODELS:
            raise ProCamError(f"{where} names the effect {name!r}, which this ProCam does not know (known: "
                              f"{', '.join(MODELS)}); it was written by another version or edited: run procam "
                              "diagnose again")
        if not isinstance(values, dict) or not all(
                isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) for v in values.values()):
            raise ProCamError(f"{where}: the parameters of the effect {name!r} are malformed (a table of finite "
                              "numbers is expected); run procam diagnose again")
        out[str(name)] = {str(k): float(v) for k, v in values.items()}
    return out


def load_adapter(doc: dict[str, Any], projector: Any, names: list[str] | None = None,
                 where: str = "the diagnosis") -> EffectAdapter:
    """The adapter of a diagnosis (its ``gap.json`` document): the effects it found compensation can invert
    (``auto``), or ``names`` with their fitted parameters. A document naming an unknown effect, or with
    malformed parameters, is refused (``where`` names it)."""
    try:
        selected = dict(doc.get("selected_params") or {})
        if names is None:  # what the diagnosis found compensation can invert (older documents: every selected one)
            params = (doc.get("compensation") or {}).get("params", selected)
        else:
            fitted = {e["name"]: e["params"] for e in doc.get("effects", []) if e.get("params")}
            params = {n: selected.get(n, fitted.get(n)) for n in names if selected.get(n, fitted.get(n)) is not None}
    except (AttributeError, KeyError, TypeError, ValueError):
        raise ProCamError(f"{where}: its effects are malformed; run procam diagnose again") from None
    return EffectAdapter(_checked_params(params, where), projector, clipped_white=doc.get("clipped_white"))


def effects_wanted(effects: str | None) -> bool:
    """Whether an ``--effects`` value asks for effect models ('', 'none' and 'off' do not)."""
    return (effects or "none").strip().lower() not in ("", "none", "off")


def adapter_from_options(effects: str | None, diagnosis: dict[str, Any] | None, projector: Any,
                         where: str = "the diagnosis") -> EffectAdapter | None:
    """The adapter for ``--effects auto|NAME,...|none`` with the diagnosis document ``diagnosis`` (``gap.json``).

    ``auto`` uses the effects the diagnosis found compensation can invert; names use those effects' fitted
    parameters (from the selection, else from fitting each alone). Effect models always need a diagnosis:
    their parameters are fitted there, on the calibration's validation captures. ``where`` names it in messages.
    """
    if not effects_wanted(effects):
        return None
    spec = effects.strip().lower()
    if diagnosis is None:
        raise ProCamError(f"--effects {effects} needs --diagnosis DIR: the folder `procam diagnose CALIB --out DIR` "
                          "wrote, where the effects' parameters were fitted")
    if spec == "auto":
        return load_adapter(diagnosis, projector, where=where)
    names = [n.strip() for n in effects.split(",") if n.strip()]
    unknown = [n for n in names if n not in MODELS]
    if unknown:
        raise ProCamError(f"unknown effect(s) {', '.join(unknown)}; known: {', '.join(MODELS)}")
    adapter = load_adapter(diagnosis, projector, names, where)
    missing = [n for n in names if n not in adapter.params]
    if missing:
        raise ProCamError(f"{where} has no fitted parameters for {', '.join(missing)} "
                          "(it failed to fit or was not a candidate); rerun procam diagnose with it")
    return adapter


class SharedCamera:
    """The camera's tone curve of a rig of several projectors, fitted once on every projector's patterns
    (``gap.json``'s ``joint``, :mod:`.shared`): taken out of the target and of every capture the joint solve
    compares with its model (h⁻¹).

    Each projector's model is in the units of its own white capture (its albedo holds the curve at its white), so
    its light is ``h⁻¹(W_k) / W_k`` times its model (``W_k`` = f̂_k of a white input). The joint solve sums the
    projectors' models; one scale per pixel takes the sum to light, exact where every projector shows white and
    wherever one projector lights alone: ``Σ_k h⁻¹(W_k) / Σ_k W_k``.
    """

    def __init__(self, params: dict[str, dict[str, float]], whites: Sequence[np.ndarray]) -> None:
        self.params = {n: dict(v) for n, v in params.items()}
        self.curve = float(self.params["camera_response"]["curve"])
        self.whites = [np.asarray(w, np.float32) for w in whites]
        light = np.sum([inverse_camera_curve(w, self.curve) for w in self.whites], axis=0)
        model = np.sum(self.whites, axis=0)
        self.scale = np.where(model > 1e-3, light / np.maximum(model, 1e-3), 1.0).astype(np.float32)

    def to_model(self, image: np.ndarray, area: Any = None) -> np.ndarray:
        """A capture (camera size), or a target fitted to ``area``, in the units the joint solve's model has."""
        scale = self.scale if area is None else area.crop(self.scale)
        return (inverse_camera_curve(np.asarray(image, np.float32), self.curve) / scale).astype(np.float32)

    def for_projector(self, k: int, adapter: EffectAdapter | None, projector: Any) -> EffectAdapter:
        """Projector ``k``'s own effects (``adapter``) with the camera's curve in its own units (its white alone):
        what its captures, taken with the others black, are read through for its open-loop θ."""
        own = {} if adapter is None else adapter.params
        out = EffectAdapter({**own, **self.params}, projector, white=self.whites[k])
        out.defocus_in_solver = adapter is not None and adapter.defocus_in_solver
        return out


#: What one projector of several inverts from its own diagnosis: the effects of its lamp, lens and electronics
#: (``steps/diagnose.py`` PROJECTOR_EFFECTS), each on its own frame; its blur held in the joint solve.
#: What a per-pixel radiometric model holds (``stages/radiometry.py``): the effects it replaces when stage C uses it.
RADIOMETRIC = ("response", "crosstalk", "black_level", "vignetting", "camera_response", "glossy")
PROJECTOR_SIDE = ("response", "crosstalk", "black_level", "vignetting", "defocus")
#: Why the camera's and the surface's effects are not inverted from one projector's diagnosis of several.
SHARED_EFFECT = ("the camera's and the surface's effects are every projector's: fitted once on every projector's "
                 "patterns (the diagnosis's joint fit), not from one projector's")
#: The shared effects compensation of several projectors inverts, from the diagnosis's joint fit (SharedCamera).
SHARED_INVERTIBLE = ("camera_response",)


def projector_adapter(effects: str | None, diagnosis: dict[str, Any] | None, projector: Any,
                      where: str = "the diagnosis") -> EffectAdapter | None:
    """One projector's adapter in a rig of several, from its own diagnosis (``gap.json`` of ``projector_K/``): the
    effects of :data:`PROJECTOR_SIDE` only, inverted on its frame (g⁻¹; a black level's projector part only) with
    its lens's blur held in the joint solve (:meth:`EffectAdapter.blur_in_solve`), and the camera side off. With
    ``auto`` the others the diagnosis would invert are reported as not used; named, they are refused."""
    if effects_wanted(effects) and (effects or "").strip().lower() != "auto":
        shared = [n.strip() for n in (effects or "").split(",")
                  if n.strip() in MODELS and n.strip() not in PROJECTOR_SIDE + SHARED_INVERTIBLE]
        if shared:
            raise ProCamError(f"--effects {', '.join(shared)}: with several projectors each projector's own effects "
                              f"({', '.join(PROJECTOR_SIDE)}) and the camera's tone curve ("
                              f"{', '.join(SHARED_INVERTIBLE)}) are inverted; the surface's effects and the camera's "
                              "lens are not. Name those, or use --effects auto")
        own = ",".join(n.strip() for n in (effects or "").split(",") if n.strip() not in SHARED_INVERTIBLE)
        if not own:
            return None  # the camera's curve alone: the rig's (:class:`SharedCamera`), no projector effect
        effects = own
    adapter = adapter_from_options(effects, diagnosis, projector, where)
    if adapter is None:
        return None
    left = {n: SHARED_EFFECT for n in adapter.params if n not in PROJECTOR_SIDE}
    mine = EffectAdapter({n: v for n, v in adapter.params.items() if n in PROJECTOR_SIDE}, projector,
                         camera_side=False)
    mine.not_used.update(left)
    return mine
