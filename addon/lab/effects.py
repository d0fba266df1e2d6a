"""Real-world effects the virtual lab injects into its Cycles renders (pure numpy/OpenCV).

The lab renders the rig with Cycles; this module turns those clean renders into
what a real projector and camera would give (docs/developer.md, "Facts about the dependencies"). Every effect has a
name (shared with the diagnosis in ``addon/gap/``), one *strength* in [0, 1]
(0 = off = identity, 1 = strong but still met in real rooms) that maps to a few
physical parameters, and those parameters can be overridden one by one as
``NAME.PARAM=VALUE``.

Where each effect acts, in the order light meets it:

* :func:`apply_projector` on the native projector frame (before the renderer
  emits it): ``response`` → ``crosstalk`` → ``black_level`` (projector part) →
  ``vignetting`` → ``defocus``.
* the renderer itself, via :func:`render_settings`: ``interreflection``
  (bounces, share of indirect light) and ``glossy`` (a specular lobe on the
  surface material); distortion also asks for a margin around the camera
  render (:func:`camera_render_intrinsics`).
* :func:`apply_camera` on the linear camera render: ``black_level`` (ambient
  part) → ``distortion`` → ``noise`` → ``camera_response`` → clipping and
  16-bit quantisation.
* ``depth_noise`` acts on the depth map, see :mod:`.depth`.

Beyond the diagnosis's vocabulary the lab has two more families, to test it
on what it was not built from (each kind's ``cause`` says which diagnosis model
names its physical cause, ``None`` where none does):

* **other forms of a modelled cause**: ``response_scurve`` (a projector tone
  curve with toe and shoulder, which no power law fits), ``defocus_depth``
  (blur growing with |1/d − 1/d_focus| over the surface instead of one blur),
  ``lamp`` (an off-axis room lamp lighting the painted surface instead of a
  uniform veil), ``distortion_tangential`` (a decentred lens: tangential p1, p2
  beside a mild radial term, where the diagnosis fits radial k1, k2 only);
* **causes the diagnosis has no model for**: ``warmup`` (the projector's colour
  and brightness drift during the session as it warms up), ``surface_moved``
  (the surface was knocked between the calibration patterns and the validation
  ones, as between calibration and show), ``subsurface`` (a translucent paint:
  light spreads under the surface, Cycles' random-walk subsurface scattering).

Time enters through the shot's place in the session (``t`` in [0, 1]) and its
phase (``calibration`` until the validation patterns start, then
``validation``; a device used after the session is at ``show``).

Nothing here draws a random number without the ``np.random.Generator`` it is
given, so a seed reproduces every capture.
"""

from __future__ import annotations

import difflib
import functools
import math
from dataclasses import dataclass
from typing import Any
from collections.abc import Callable, Mapping

import cv2
import numpy as np

from ..colour import srgb_encode
from ..errors import LabError
from ..rig.model import Intrinsics, Projector


# --------------------------------------------------------------------------- registry

@dataclass(frozen=True)
class Param:
    """One physical parameter of an effect: its valid range and how strength sets it."""

    name: str
    unit: str
    lo: float
    hi: float
    at: Callable[[float], float]  # strength in [0, 1] -> value
    doc: str
    integer: bool = False


@dataclass(frozen=True)
class EffectKind:
    """A kind of effect: where it acts and the parameters its strength maps to."""

    name: str
    stage: str  # "projector", "render", "camera" or "depth"
    doc: str
    params: tuple[Param, ...]
    #: The diagnosis model that names this effect's physical cause ("" = its own name; None = none does).
    cause: str | None = ""

    @property
    def diagnosis_name(self) -> str | None:
        """What a correct diagnosis calls this effect (None: it should say "unexplained")."""
        return self.name if self.cause == "" else self.cause

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(name)

    def resolve(self, strength: float) -> dict[str, float]:
        out = {}
        for p in self.params:
            v = float(p.at(strength))
            out[p.name] = float(round(v)) if p.integer else v
        return out


def _interreflection_bounces(s: float) -> float:
    # any strength above 0 needs at least one bounce; most indirect energy is in the first two
    return 0.0 if s <= 0 else float(1 + math.floor(3 * s))


_KINDS: tuple[EffectKind, ...] = (
    EffectKind("response", "projector",
               "projector response curve: per-channel power law, 0 and 1 stay, mid-greys move "
               "(an un-linearised projector has gamma ≈ 2.2)",
               (Param("gamma", "", 0.2, 4.0, lambda s: 1.0 + 1.2 * s, "mean exponent of out = in^gamma"),
                Param("spread", "", 0.0, 0.5, lambda s: 0.05 * s,
                      "relative per-channel exponent difference: gamma·(1+spread, 1, 1−spread) for R, G, B"))),
    EffectKind("crosstalk", "projector",
               "projector colour mixing: a 3×3 matrix with rows summing to 1 (white stays white); "
               "neighbouring primaries (R↔G, G↔B) leak more than R↔B",
               (Param("leak", "", 0.0, 0.5, lambda s: 0.2 * s,
                      "share of each channel's light that appears in the other two"),)),
    EffectKind("black_level", "projector+camera",
               "projector black level (light leaking through a black panel) and ambient room light in the camera image",
               (Param("projector", "of white", 0.0, 0.2, lambda s: 0.02 * s,
                      "emitted light at input 0, as a share of white: out = b + (1−b)·in"),
                Param("ambient", "camera linear", 0.0, 0.5, lambda s: 0.05 * s,
                      "ambient light added to the camera image (linear, 1 = saturation)"),
                Param("warmth", "", 0.0, 1.0, lambda s: 0.5,
                      "tint of the ambient light, 0 neutral, 1 tungsten-like"))),
    EffectKind("vignetting", "projector",
               "projector lens falloff about the optical axis (principal point): the farthest corner loses `falloff`",
               (Param("falloff", "", 0.0, 0.9, lambda s: 0.35 * s,
                      "light lost at the frame corner farthest from the principal point"),
                Param("exponent", "", 1.0, 6.0, lambda s: 2.0,
                      "shape: gain = 1 − falloff·(r/r_max)^exponent, r = field angle tangent"))),
    EffectKind("defocus", "projector",
               "projector blur: a Gaussian/disk PSF on the native frame",
               (Param("sigma", "projector px", 0.0, 20.0, lambda s: 3.0 * s,
                      "PSF standard deviation in pixels of the projector's native frame"),
                Param("disk", "", 0.0, 1.0, lambda s: 0.5,
                      "share of a uniform disk (radius 2·sigma, same std) in the PSF; the rest is Gaussian"))),
    EffectKind("interreflection", "render",
               "light bounces between surface parts (Cycles bounces; indirect light scaled by `gain`)",
               (Param("bounces", "", 0.0, 8.0, _interreflection_bounces, "diffuse bounces", integer=True),
                Param("gain", "", 0.0, 1.0, lambda s: min(1.0, 2.0 * s),
                      "share of the indirect light kept (1 = physical); <1 needs the renderer's indirect pass"))),
    EffectKind("glossy", "render",
               "non-Lambertian surface: a GGX specular lobe mixed into the diffuse material",
               (Param("weight", "", 0.0, 1.0, lambda s: 0.2 * s, "mix factor of the glossy BSDF"),
                Param("roughness", "", 0.02, 1.0, lambda s: 0.6 - 0.35 * s, "GGX roughness of the lobe"))),
    EffectKind("camera_response", "camera",
               "camera processing: fixed white balance gains (on the raw signal) then a tone curve "
               "blending linear with the sRGB encoding",
               (Param("gain_r", "", 0.25, 4.0, lambda s: 1.0 + 0.25 * s, "red gain relative to green"),
                Param("gain_b", "", 0.25, 4.0, lambda s: 1.0 - 0.2 * s, "blue gain relative to green"),
                Param("curve", "", 0.0, 1.0, lambda s: s, "share of the sRGB encoding curve (0 = linear raw)"))),
    EffectKind("distortion", "camera",
               "camera lens radial distortion (OpenCV k1, k2 on normalised coordinates)",
               (Param("k1", "", -0.3, 0.3, lambda s: -0.12 * s, "radial coefficient of r²"),
                Param("k2", "", -0.1, 0.1, lambda s: 0.03 * s, "radial coefficient of r⁴"))),
    EffectKind("noise", "camera",
               "sensor noise, Poisson-Gaussian: variance = gain·signal + sigma²",
               (Param("gain", "per unit signal", 0.0, 0.05, lambda s: 1e-3 * s,
                      "shot-noise variance per unit of linear signal (1/full-well in signal units)"),
                Param("sigma", "camera linear", 0.0, 0.2, lambda s: 0.01 * s, "read-noise standard deviation"))),
    EffectKind("depth_noise", "depth",
               "phone LiDAR depth: noise, bias, missing returns; always captured at the sensor's native "
               "resolution and upsampled (see depth.py)",
               (Param("std", "m at 1 m", 0.0, 0.2, lambda s: 0.02 * s,
                      "depth noise std at 1 m; grows in proportion to depth"),
                Param("bias", "m", -0.2, 0.2, lambda s: 0.02 * s, "constant depth offset (positive = too far)"),
                Param("holes", "", 0.0, 1.0, lambda s: 0.5 * s,
                      "probability of losing a return where the surface is seen at a grazing angle"),
                Param("grazing_deg", "deg", 30.0, 89.0, lambda s: 75.0,
                      "angle to the view ray above which returns are lost"),
                Param("dropout", "", 0.0, 0.5, lambda s: 0.02 * s, "probability of a random missing return"),
                Param("width", "px", 8.0, 4096.0, lambda s: 256.0, "native depth width", integer=True),
                Param("height", "px", 6.0, 4096.0, lambda s: 192.0, "native depth height", integer=True),
                Param("max_range", "m", 0.5, 50.0, lambda s: 5.0, "no return beyond this depth"),
                Param("shift_x", "px", -20.0, 20.0, lambda s: 0.0,
                      "misregistration: the depth map shifted right against the colour camera, in pixels of a "
                      "640-wide camera (scaled with the camera's width)"),
                Param("shift_y", "px", -20.0, 20.0, lambda s: 0.0,
                      "misregistration: the depth map shifted down against the colour camera (as shift_x)"))),
    # ---- other functional forms of modelled causes
    EffectKind("response_scurve", "projector",
               "projector tone curve with a toe and a shoulder (a logistic S-curve mixed into the identity): "
               "dark and bright levels compress, mid levels steepen; no power law fits it",
               (Param("mix", "", 0.0, 1.0, lambda s: s, "share of the S-curve in out = (1−mix)·in + mix·S(in)"),
                Param("slope", "", 2.0, 20.0, lambda s: 9.0, "steepness of the logistic at its pivot"),
                Param("pivot", "", 0.2, 0.8, lambda s: 0.4, "input level of the S-curve's midpoint")),
               cause="response"),
    EffectKind("defocus_depth", "projector",
               "projector focused at one distance: blur σ ∝ |1/d − 1/d_focus| over the surface (thin lens), "
               "sharp at the focus depth, not one blur everywhere",
               (Param("sigma_max", "projector px", 0.0, 20.0, lambda s: 4.0 * s,
                      "blur σ where |1/d − 1/d_focus| is largest over the projected surface"),
                Param("focus", "", 0.0, 1.0, lambda s: 0.0,
                      "focus depth as a share of the surface's depth range seen by the projector (0 = nearest)")),
               cause="defocus"),
    EffectKind("lamp", "render",
               "an off-axis room lamp (a point light above and beside the rig) lighting the painted surface: "
               "ambient light that varies over the surface and follows its paint, not a uniform veil",
               (Param("power", "camera linear", 0.0, 0.5, lambda s: 0.06 * s,
                      "lamp light on the brightest part of a white surface (linear camera units)"),
                Param("side", "m", -3.0, 3.0, lambda s: 1.2, "lamp position to the camera's right"),
                Param("height", "m", -3.0, 3.0, lambda s: 0.8, "lamp position above the camera")),
               cause="black_level"),
    EffectKind("distortion_tangential", "camera",
               "camera lens with a decentred element: tangential distortion (OpenCV p1, p2) beside a mild radial "
               "part, which no radial k1, k2 fits",
               (Param("p1", "", -0.05, 0.05, lambda s: 0.012 * s, "tangential coefficient p1"),
                Param("p2", "", -0.05, 0.05, lambda s: -0.008 * s, "tangential coefficient p2"),
                Param("k1", "", -0.3, 0.3, lambda s: -0.03 * s, "radial coefficient of r²")),
               cause="distortion"),
    # ---- causes the diagnosis has no model for
    EffectKind("warmup", "projector",
               "the projector warms up during the session: its light starts dimmer and bluer-deficient and "
               "settles (exponentially in session time), so early and late captures disagree",
               (Param("drift", "", 0.0, 0.5, lambda s: 0.12 * s,
                      "relative light missing at the session's start (blue; green half, red a quarter)"),
                Param("tau", "of the session", 0.05, 2.0, lambda s: 0.35, "time constant as a share of the session")),
               cause=None),
    EffectKind("surface_moved", "render",
               "the surface was knocked after the calibration patterns: the validation captures and the show "
               "see it moved and turned a little",
               (Param("shift", "m", 0.0, 0.1, lambda s: 0.008 * s, "translation (sideways and back)"),
                Param("turn", "deg", 0.0, 10.0, lambda s: 1.0 * s, "rotation about the vertical axis")),
               cause=None),
    EffectKind("subsurface", "render",
               "translucent paint: light enters and spreads under the surface before leaving it "
               "(Cycles random-walk subsurface scattering mixed into the diffuse material)",
               (Param("weight", "", 0.0, 1.0, lambda s: 0.6 * s, "mix factor of the subsurface BSDF"),
                Param("radius", "m", 0.0, 0.2, lambda s: 0.04 * s, "mean free path scale")),
               cause=None),
)

REGISTRY: dict[str, EffectKind] = {k.name: k for k in _KINDS}
NAMES: tuple[str, ...] = tuple(REGISTRY)

#: Presets: strengths of a plausible uncalibrated room at modest levels.
PRESETS: dict[str, dict[str, float]] = {
    "realistic": {"response": 0.4, "crosstalk": 0.3, "black_level": 0.3, "vignetting": 0.4, "defocus": 0.3,
                  "interreflection": 0.75, "glossy": 0.3, "camera_response": 0.3, "distortion": 0.3,
                  "noise": 0.4, "depth_noise": 0.5},
}


# --------------------------------------------------------------------------- models

@dataclass(frozen=True)
class Effect:
    """One effect with its strength and all its resolved parameters."""

    name: str
    strength: float
    values: tuple[tuple[str, float], ...]  # (param, value) in registry order; a tuple keeps it immutable

    @property
    def kind(self) -> EffectKind:
        return REGISTRY[self.name]

    @property
    def params(self) -> dict[str, float]:
        return dict(self.values)

    def __getitem__(self, param: str) -> float:
        for k, v in self.values:
            if k == param:
                return v
        raise KeyError(f"{self.name} has no parameter {param!r}")

    @property
    def overrides(self) -> dict[str, float]:
        """Parameters that differ from what the strength alone gives."""
        base = self.kind.resolve(self.strength)
        return {k: v for k, v in self.values if v != base[k]}

    @property
    def active(self) -> bool:
        """True unless every parameter equals its strength-0 (identity) value."""
        base = self.kind.resolve(0.0)
        return any(v != base[k] for k, v in self.values)


def _effect(name: str, strength: float, overrides: Mapping[str, float] | None = None) -> Effect:
    kind = REGISTRY[name]
    vals = kind.resolve(strength)
    vals.update(overrides or {})
    return Effect(name, float(strength), tuple((p.name, float(vals[p.name])) for p in kind.params))


@dataclass(frozen=True)
class EffectSet:
    """Every registry effect (off ones at strength 0), in registry order. Immutable."""

    effects: tuple[Effect, ...]

    def __post_init__(self) -> None:
        if tuple(e.name for e in self.effects) != NAMES:
            raise LabError("an EffectSet holds every effect in registry order; build it with parse_effects()")

    def __getitem__(self, name: str) -> Effect:
        if name not in REGISTRY:
            raise LabError(_unknown_effect(name))
        return self.effects[NAMES.index(name)]

    @property
    def active(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.effects if e.active)

    @property
    def spec(self) -> str:
        """A spec string that parses back to this set ("none" when nothing is on)."""
        parts = []
        for e in self.effects:
            if e.strength > 0:
                parts.append(f"{e.name}={e.strength!r}")
            parts += [f"{e.name}.{k}={v!r}" for k, v in e.overrides.items()]
        return ",".join(parts) or "none"

    def __str__(self) -> str:
        return self.spec

    def with_effect(self, name: str, strength: float, **overrides: float) -> EffectSet:
        """A copy with ``name`` set to ``strength`` (and parameter overrides), validated like a spec."""
        base = {e.name: e.strength for e in self.effects}
        base[name] = strength
        items = [f"{k}={v!r}" for k, v in base.items()] + [f"{name}.{k}={v!r}" for k, v in overrides.items()]
        keep = [f"{e.name}.{k}={v!r}" for e in self.effects if e.name != name for k, v in e.overrides.items()]
        return parse_effects(",".join(items + keep))

    def only(self, *names: str) -> EffectSet:
        """A copy with every effect not in ``names`` switched off."""
        for n in names:
            self[n]  # validates the name
        return EffectSet(tuple(e if e.name in names else _effect(e.name, 0.0) for e in self.effects))

    def to_dict(self) -> dict[str, Any]:
        """Everything resolved, for the sealed truth file."""
        return {"spec": self.spec, "active": list(self.active),
                "effects": {e.name: {"stage": e.kind.stage, "strength": e.strength, "active": e.active,
                                     "params": e.params} for e in self.effects}}

    @staticmethod
    def from_dict(d: Mapping[str, Any]) -> EffectSet:
        """Rebuild from :meth:`to_dict`; the stored parameters are taken as they are (validated)."""
        if not isinstance(d, Mapping) or not isinstance(d.get("effects"), Mapping):
            raise LabError("an effects description needs an 'effects' mapping of NAME -> {strength, params}")
        given = d["effects"]
        for name in given:
            if name not in REGISTRY:
                raise LabError(_unknown_effect(name))
        out = []
        for name in NAMES:
            entry = given.get(name, {})
            if not isinstance(entry, Mapping):
                raise LabError(f"effect {name!r}: expected {{strength, params}}, got {entry!r}")
            strength = _strength(name, entry.get("strength", 0.0))
            params = entry.get("params", {}) or {}
            if not isinstance(params, Mapping):
                raise LabError(f"effect {name!r}: 'params' must be a mapping")
            overrides = {k: _param_value(name, k, v) for k, v in params.items()}
            out.append(_effect(name, strength, overrides))
        return EffectSet(tuple(out))

    @staticmethod
    def none() -> EffectSet:
        return EffectSet(tuple(_effect(n, 0.0) for n in NAMES))


# --------------------------------------------------------------------------- parsing

def _unknown_effect(name: str) -> str:
    near = difflib.get_close_matches(name, list(NAMES) + list(PRESETS), n=1)
    hint = f" (did you mean {near[0]!r}?)" if near else ""
    return (f"unknown effect {name!r}{hint}; known effects: {', '.join(NAMES)}; "
            f"presets: {', '.join(PRESETS)}")


def _number(text: Any, what: str) -> float:
    if isinstance(text, bool):
        raise LabError(f"{what} must be a number, got {text!r}")
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise LabError(f"{what} must be a number, got {text!r}") from None
    if not math.isfinite(v):
        raise LabError(f"{what} must be a finite number, got {text!r}")
    return v


def _strength(name: str, text: Any) -> float:
    v = _number(text, f"strength of {name!r}")
    if not 0.0 <= v <= 1.0:
        raise LabError(f"strength of {name!r} must lie in [0, 1] (0 off, 1 strong), got {v:g}")
    return v


def _param_value(name: str, param: str, text: Any) -> float:
    kind = REGISTRY[name]
    try:
        p = kind.param(param)
    except KeyError:
        names = [q.name for q in kind.params]
        near = difflib.get_close_matches(param, names, n=1)
        hint = f" (did you mean {near[0]!r}?)" if near else ""
        raise LabError(f"effect {name!r} has no parameter {param!r}{hint}; "
                       f"its parameters: {', '.join(names)}") from None
    v = _number(text, f"{name}.{param}")
    if not p.lo <= v <= p.hi:
        raise LabError(f"{name}.{param} must lie in [{p.lo:g}, {p.hi:g}] {p.unit}".rstrip() + f", got {v:g}")
    if p.integer:
        if v != round(v):
            raise LabError(f"{name}.{param} must be a whole number, got {v:g}")
        v = float(round(v))
    return v


def parse_effects(spec: str | Mapping[str, Any] | EffectSet | None) -> EffectSet:
    """Parse ``"response=0.5,crosstalk=0.3,noise.sigma=0.01"``, ``"realistic"`` or ``"none"``.

    Items are comma-separated; a preset name sets its strengths, later items
    override earlier ones (``"realistic,noise=0"``). Parameter overrides are
    applied on top of the strengths wherever they stand in the string; an
    override of an effect whose strength is 0 sets just that parameter (e.g.
    ``noise.sigma=0.01`` alone gives read noise only). A mapping
    ``{"noise": 0.5, "noise.sigma": 0.01}`` works the same way.
    """
    if isinstance(spec, EffectSet):
        return spec
    if spec is None:
        items: list[tuple[str, Any]] = []
    elif isinstance(spec, Mapping):
        items = list(spec.items())
    elif isinstance(spec, str):
        items = []
        for raw in spec.split(","):
            tok = raw.strip()
            if not tok:
                continue
            if "=" not in tok:
                if tok.lower() in PRESETS or tok.lower() in ("none", "off"):
                    items.append((tok.lower(), None))
                    continue
                if tok in REGISTRY:
                    raise LabError(f"effect {tok!r} needs a strength in [0, 1], e.g. {tok}=0.5")
                raise LabError(_unknown_effect(tok))
            key, _, value = tok.partition("=")
            items.append((key.strip(), value.strip()))
    else:
        raise LabError(f"effects must be a string like 'response=0.5,noise=0.2' or a mapping, "
                       f"got {type(spec).__name__}")

    strengths = dict.fromkeys(NAMES, 0.0)
    overrides: dict[str, dict[str, float]] = {n: {} for n in NAMES}
    for key, value in items:
        if value is None:  # preset or none
            if key in PRESETS:
                strengths.update(PRESETS[key])
            else:
                strengths = dict.fromkeys(NAMES, 0.0)
                overrides = {n: {} for n in NAMES}
            continue
        name, dot, param = key.partition(".")
        if name not in REGISTRY:
            raise LabError(_unknown_effect(name))
        if dot:
            overrides[name][param] = _param_value(name, param, value)
        else:
            strengths[name] = _strength(name, value)
    return EffectSet(tuple(_effect(n, strengths[n], overrides[n]) for n in NAMES))


def effect_help() -> str:
    """A plain-text table of effects, parameters, ranges and their value at strength 1 (for --help)."""
    lines = []
    for k in _KINDS:
        lines.append(f"{k.name} [{k.stage}]: {k.doc}")
        for p in k.params:
            lines.append(f"    {k.name}.{p.name}: {p.doc} — range [{p.lo:g}, {p.hi:g}] {p.unit}".rstrip()
                         + f"; strength 0 → {p.at(0.0):g}, 1 → {p.at(1.0):g}")
    lines.append("presets: " + "; ".join(f"{n}: " + ",".join(f"{k}={v:g}" for k, v in s.items())
                                        for n, s in PRESETS.items()))
    return "\n".join(lines)


# --------------------------------------------------------------------------- image helpers

def _rgb(image: np.ndarray, what: str) -> np.ndarray:
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise LabError(f"{what} must be an H×W×3 image, got shape {img.shape}")
    if not np.all(np.isfinite(img)):
        raise LabError(f"{what} holds NaN or infinite values")
    return img


def crosstalk_matrix(leak: float) -> np.ndarray:
    """3×3 mixing matrix, out = M @ in per pixel; rows sum to 1, entries ≥ 0."""
    # neighbouring primaries overlap more in a projector's colour filters than red and blue do
    share = np.array([[0.0, 0.6, 0.4], [0.5, 0.0, 0.5], [0.4, 0.6, 0.0]])
    return (1.0 - leak) * np.eye(3) + leak * share


def _psf(sigma: float, disk: float) -> np.ndarray:
    """Normalised 2-D PSF: (1−disk)·Gaussian + disk·uniform disk of radius 2σ (both have std σ per axis)."""
    radius = 2.0 * sigma
    half = int(math.ceil(max(3.0 * sigma, radius))) + 1
    ax = np.arange(-half, half + 1, dtype=np.float64)
    xx, yy = np.meshgrid(ax, ax)
    gauss = np.exp(-(xx ** 2 + yy ** 2) / (2 * sigma ** 2))
    gauss /= gauss.sum()
    # disk coverage by 4×4 supersampling of each pixel, so small disks stay round and centred
    sub = (np.arange(4) + 0.5) / 4 - 0.5
    cover = np.zeros_like(xx)
    for dy in sub:
        for dx in sub:
            cover += ((xx + dx) ** 2 + (yy + dy) ** 2) <= radius ** 2
    psf = (1.0 - disk) * gauss
    if cover.sum() > 0:
        psf += disk * cover / cover.sum()
    return (psf / psf.sum()).astype(np.float32)


# --------------------------------------------------------------------------- projector side

def apply_projector(frame: np.ndarray, effects: EffectSet, projector: Projector,
                    rng: np.random.Generator | None = None, *, depth: np.ndarray | None = None,
                    t: float = 1.0) -> np.ndarray:
    """The light a real projector emits for ``frame`` (its native frame, H×W×3, values in [0, 1]).

    Order follows the light: response (electronics/panel) → crosstalk (colour
    filters) → black level (panel leak, also where the input is black, so the
    whole frame lifts) → vignetting and defocus (lens). ``frame`` may be the
    native frame at a reduced resolution of the same aspect (test renders):
    positions are measured in the projector's native pixels and defocus sigma
    scales with the frame. Every step maps [0, 1] into [0, 1] (convex mixes,
    gains ≤ 1), so the output stays in the panel's physical range: 1 = the
    projector's full white. ``rng`` is unused today (all projector effects are
    deterministic) and kept for a uniform signature. ``depth`` (H×W, metres
    along the projector's axis, NaN off the surface, any size of the frame's
    aspect) is what ``defocus_depth`` needs; ``t`` is the shot's place in the
    session for ``warmup`` (1 = settled).
    """
    del rng
    img = np.clip(_rgb(frame, "projector frame"), 0.0, 1.0)  # a panel cannot show more than white
    h, w = img.shape[:2]
    intr = projector.intrinsics
    if abs(w / h - intr.width / intr.height) > 0.01 * intr.width / intr.height:
        raise LabError(f"projector frame {w}×{h} does not have the aspect of the projector's native "
                       f"{intr.width}×{intr.height} frame; pass the full frame (Projector.frame_from_input)")
    scale = w / intr.width

    e = effects["response"]
    if e.active:
        g = e["gamma"] * (1.0 + e["spread"] * np.array([1.0, 0.0, -1.0]))
        img = np.power(img, g.astype(np.float32))

    e = effects["response_scurve"]
    if e.active and e["mix"] > 0:
        img = (1.0 - np.float32(e["mix"])) * img + np.float32(e["mix"]) * s_curve(img, e["slope"], e["pivot"])

    e = effects["crosstalk"]
    if e.active:
        img = np.einsum("ij,hwj->hwi", crosstalk_matrix(e["leak"]).astype(np.float32), img)

    e = effects["black_level"]
    if e["projector"] > 0:
        b = np.float32(e["projector"])
        img = b + (1.0 - b) * img

    e = effects["vignetting"]
    if e.active and e["falloff"] > 0:
        img = img * vignetting_gain(intr, (w, h), e["falloff"], e["exponent"])[..., None]

    e = effects["defocus"]
    sigma = e["sigma"] * scale
    if sigma > 0.05:  # below that the PSF is a single pixel
        # light that blurs past the panel edge is lost: the renderer cannot emit outside the frame
        img = cv2.filter2D(img, -1, _psf(sigma, e["disk"]), borderType=cv2.BORDER_CONSTANT)

    e = effects["defocus_depth"]
    if e.active and e["sigma_max"] > 0:
        if depth is None:
            raise LabError("defocus_depth needs the surface's depth seen from the projector (LabDevice gives it)")
        img = _depth_blur(img, depth_blur_sigma(depth, (w, h), e["sigma_max"] * scale, e["focus"]))

    e = effects["warmup"]
    if e.active and e["drift"] > 0:
        img = img * warmup_gain(t, e["drift"], e["tau"])
    return np.clip(img, 0.0, 1.0).astype(np.float32)


def s_curve(x: np.ndarray, slope: float, pivot: float) -> np.ndarray:
    """A logistic tone curve through (0, 0) and (1, 1): toe below the pivot, shoulder above it."""
    def f(v: np.ndarray | float) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-slope * (np.asarray(v, np.float32) - pivot)))
    lo, hi = f(0.0), f(1.0)
    return ((f(x) - lo) / (hi - lo)).astype(np.float32)


def warmup_gain(t: float, drift: float, tau: float) -> np.ndarray:
    """Per-channel share of the settled light a warming projector gives at session time ``t``."""
    # lamps and LEDs reach their colour last in the blue: the deficit is largest there
    deficit = float(drift) * math.exp(-max(float(t), 0.0) / float(tau))
    return (1.0 - deficit * np.array([0.25, 0.5, 1.0])).astype(np.float32)


def depth_blur_sigma(depth: np.ndarray, size: tuple[int, int], sigma_max: float, focus: float) -> np.ndarray:
    """Blur σ per pixel of a ``size`` frame from the projector-side depth: ∝ |1/d − 1/d_focus| (thin lens)."""
    w, h = size
    d = cv2.resize(np.asarray(depth, np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
    ok = np.isfinite(d) & (d > 0)
    if not ok.any():
        raise LabError("defocus_depth: the projector sees no surface")
    near, far = float(d[ok].min()), float(d[ok].max())
    d_focus = near + float(focus) * (far - near)
    inv = np.abs(1.0 / np.where(ok, d, d_focus) - 1.0 / d_focus)
    top = float(inv[ok].max())
    # off the surface nothing is seen; use the nearest surface value so the blur does not step at its outline
    sigma = np.where(ok, inv / top if top > 0 else 0.0, 0.0) * float(sigma_max)
    if not ok.all():
        _, idx = cv2.distanceTransformWithLabels((~ok).astype(np.uint8), cv2.DIST_L2, 5,
                                                 labelType=cv2.DIST_LABEL_PIXEL)
        ys, xs = np.nonzero(ok)
        lut = np.zeros(idx.max() + 1, np.float32)
        lut[idx[ok]] = sigma[ys, xs]
        sigma = lut[idx]
    return sigma.astype(np.float32)


def _depth_blur(img: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Spatially varying Gaussian blur: per pixel, interpolate between images blurred at a ladder of σ."""
    top = float(sigma.max())
    if top <= 0.05:
        return img
    levels = np.linspace(0.0, top, max(3, int(math.ceil(top / 0.75)) + 1))
    stack = [img] + [cv2.GaussianBlur(img, (0, 0), float(s), borderType=cv2.BORDER_CONSTANT) for s in levels[1:]]
    pos = np.clip(sigma / (levels[1] - levels[0]), 0, len(levels) - 1 - 1e-6)
    i = np.floor(pos).astype(int)
    f = (pos - i)[..., None].astype(np.float32)
    out = np.zeros_like(img)
    for k in range(len(levels) - 1):
        sel = (i == k)[..., None]
        out += np.where(sel, (1 - f) * stack[k] + f * stack[k + 1], 0.0).astype(np.float32)
    return out


def vignetting_gain(intr: Intrinsics, size: tuple[int, int], falloff: float, exponent: float) -> np.ndarray:
    """H×W gain 1 − falloff·(r/r_max)^exponent, r = tangent of the field angle from the principal point."""
    w, h = size
    u = (np.arange(w) + 0.5) * intr.width / w  # pixel centres in native projector pixels (corner convention)
    v = (np.arange(h) + 0.5) * intr.height / h
    x = (u - intr.cx) / intr.fx
    y = (v - intr.cy) / intr.fy
    r = np.hypot(x[None, :], y[:, None])
    # the lens image circle is centred on the optical axis, so a lens-shifted frame is brightest at the axis
    corners_x = (np.array([0.0, intr.width]) - intr.cx) / intr.fx
    corners_y = (np.array([0.0, intr.height]) - intr.cy) / intr.fy
    r_max = max(math.hypot(a, b) for a in corners_x for b in corners_y)
    return (1.0 - falloff * np.clip(r / r_max, 0.0, 1.0) ** exponent).astype(np.float32)


# --------------------------------------------------------------------------- renderer side

def render_settings(effects: EffectSet, camera_intrinsics: Intrinsics | None = None) -> dict[str, Any]:
    """What the renderer must do that no image operation can.

    * ``diffuse_bounces``: 0 = direct light only (the lab's default); the
      renderer sets Cycles' diffuse (and total) bounces to it.
    * ``indirect_gain``: scale of the indirect light; below 1 the renderer
      composes direct + gain·indirect from Cycles' DiffDir/DiffInd passes
      (at 1 the combined image is right as it is).
    * ``glossy_weight``/``glossy_roughness``: mix a GGX glossy BSDF with this
      factor into the diffuse surface; weight 0 means a *pure* diffuse BSDF
      (not a Principled BSDF, whose default specular would be a hidden effect).
    * ``glossy_bounces``: 1 when the glossy lobe should also carry indirect
      light, else 0.
    * ``camera_margin``: (x, y) pixels to add on each side of the camera render
      so that distortion has image to pull in; see
      :func:`camera_render_intrinsics` (only when intrinsics are given).
    """
    inter, gloss = effects["interreflection"], effects["glossy"]
    bounces = int(inter["bounces"])
    out: dict[str, Any] = {
        "diffuse_bounces": bounces,
        "indirect_gain": float(inter["gain"]) if bounces > 0 else 0.0,
        "glossy_weight": float(gloss["weight"]),
        "glossy_roughness": float(gloss["roughness"]),
        "glossy_bounces": 1 if (bounces > 0 and gloss["weight"] > 0) else 0,
        "max_bounces": bounces + (1 if (bounces > 0 and gloss["weight"] > 0) else 0),
    }
    # Only when on, so that a set without them keeps exactly the settings it always had.
    lamp, moved, sss = effects["lamp"], effects["surface_moved"], effects["subsurface"]
    if lamp.active and lamp["power"] > 0:
        out.update(lamp_power=float(lamp["power"]), lamp_position=(float(lamp["side"]), float(lamp["height"])))
    if moved.active:
        out.update(surface_shift=float(moved["shift"]), surface_turn_deg=float(moved["turn"]))
    if sss.active and sss["weight"] > 0:
        out.update(subsurface_weight=float(sss["weight"]), subsurface_radius=float(sss["radius"]))
    if camera_intrinsics is not None:
        out["camera_margin"] = camera_margin(effects, camera_intrinsics)
    return out


#: OpenCV k1, k2, p1, p2. The lab's lens is written apart from the diagnosis's (rig/lens.py) on purpose: it is the
#: truth the diagnosis must find, inverted exactly here where the diagnosis stops after a few fixed-point steps.
Lens = tuple[float, float, float, float]


def lens_of(effects: EffectSet) -> Lens | None:
    """The camera lens's distortion coefficients from ``distortion`` and ``distortion_tangential`` (None: ideal)."""
    radial, tangential = effects["distortion"], effects["distortion_tangential"]
    if not (radial.active or tangential.active):
        return None
    k1 = (radial["k1"] if radial.active else 0.0) + (tangential["k1"] if tangential.active else 0.0)
    k2 = radial["k2"] if radial.active else 0.0
    p1, p2 = (tangential["p1"], tangential["p2"]) if tangential.active else (0.0, 0.0)
    return float(k1), float(k2), float(p1), float(p2)


def _distort_normalised(x: np.ndarray, y: np.ndarray, lens: Lens) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's lens model (k1, k2, p1, p2) on ideal normalised coordinates."""
    k1, k2, p1, p2 = lens
    r2 = x * x + y * y
    f = 1 + k1 * r2 + k2 * r2 * r2
    return (x * f + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * f + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def _undistort_lens(xd: np.ndarray, yd: np.ndarray, lens: Lens) -> tuple[np.ndarray, np.ndarray]:
    """Ideal normalised coordinates that ``lens`` maps onto (xd, yd): the radial Newton solve when it is radial,
    else fixed-point steps on the full model (as OpenCV's undistortPoints; NaN where they do not settle)."""
    k1, k2, p1, p2 = lens
    if p1 == 0.0 and p2 == 0.0:
        return _undistort_normalised(xd, yd, k1, k2)
    xu, yu = xd.copy(), yd.copy()
    for _ in range(50):
        x2, y2 = _distort_normalised(xu, yu, lens)
        ex, ey = x2 - xd, y2 - yd
        xu, yu = xu - ex, yu - ey
        if max(np.max(np.abs(ex), initial=0.0), np.max(np.abs(ey), initial=0.0)) < 1e-12:
            break
    else:
        bad = np.hypot(ex, ey) > 1e-9
        xu, yu = np.where(bad, np.nan, xu), np.where(bad, np.nan, yu)
    return xu, yu


def _undistort_normalised(xd: np.ndarray, yd: np.ndarray, k1: float, k2: float) -> tuple[np.ndarray, np.ndarray]:
    """Ideal normalised coordinates whose radial distortion lands on (xd, yd) (Newton on the radius)."""
    rd = np.hypot(xd, yd)
    ru = rd.copy()
    for _ in range(30):
        r2 = ru * ru
        f = ru * (1 + k1 * r2 + k2 * r2 * r2) - rd
        if np.max(np.abs(f), initial=0.0) < 1e-12:
            break
        ru = ru - f / (1 + 3 * k1 * r2 + 5 * k2 * r2 * r2)
    else:
        ru = np.full_like(ru, np.nan)  # no convergence: the lens folds there; callers check for NaN
    scale = np.where(rd > 1e-12, ru / np.maximum(rd, 1e-12), 1.0)
    return xd * scale, yd * scale


def _check_monotone(intr: Intrinsics, k1: float, k2: float) -> None:
    # beyond the radius where d(r_d)/d(r_u) <= 0 the lens would fold the image back on itself
    corners = [((a - intr.cx) / intr.fx, (b - intr.cy) / intr.fy) for a in (0, intr.width) for b in (0, intr.height)]
    rd_max = max(math.hypot(*c) for c in corners)
    # the ideal radius that lands on the farthest corner (larger than it for a barrel lens)
    xu, _ = _undistort_normalised(np.array([rd_max]), np.array([0.0]), k1, k2)
    ru_max = float(xu[0])
    r = np.linspace(0.0, 1.05 * ru_max, 512)
    landed = ru_max * (1 + k1 * ru_max ** 2 + k2 * ru_max ** 4)
    if not math.isfinite(ru_max) or ru_max <= 0 or abs(landed - rd_max) > 1e-6 or \
            np.any(1 + 3 * k1 * r ** 2 + 5 * k2 * r ** 4 <= 0.05):
        raise LabError(f"distortion k1={k1:g}, k2={k2:g} folds the image inside this camera's field of view; "
                       "use a smaller |k1|/|k2|")


def _check_lens(intr: Intrinsics, lens: Lens) -> None:
    _check_monotone(intr, lens[0], lens[1])
    if lens[2] or lens[3]:
        u = np.array([0.0, intr.width, 0.0, intr.width])
        v = np.array([0.0, 0.0, intr.height, intr.height])
        xu, _ = _undistort_lens((u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, lens)
        if not np.all(np.isfinite(xu)):
            raise LabError(f"lens distortion {lens} cannot be inverted at this camera's corners; use smaller "
                           "coefficients")


def camera_margin(effects: EffectSet, camera_intrinsics: Intrinsics) -> tuple[int, int]:
    """Pixels to render beyond each side of the camera image (x, y) so distortion finds image everywhere."""
    lens = lens_of(effects)
    if lens is None:
        return (0, 0)
    intr = camera_intrinsics
    _check_lens(intr, lens)
    # the extreme ideal positions come from the image border (radial maps are monotone there)
    u = np.concatenate([np.linspace(0, intr.width, 64), np.full(64, intr.width), np.linspace(0, intr.width, 64),
                        np.zeros(64)])
    v = np.concatenate([np.zeros(64), np.linspace(0, intr.height, 64), np.full(64, intr.height),
                        np.linspace(0, intr.height, 64)])
    xu, yu = _undistort_lens((u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, lens)
    pu, pv = xu * intr.fx + intr.cx, yu * intr.fy + intr.cy
    mx = max(0.0, -pu.min(), pu.max() - intr.width)
    my = max(0.0, -pv.min(), pv.max() - intr.height)
    return (int(math.ceil(mx)) + 2, int(math.ceil(my)) + 2)  # +2 px: bilinear support


def camera_render_intrinsics(effects: EffectSet, camera_intrinsics: Intrinsics) -> Intrinsics:
    """The (larger) pinhole camera the renderer should render with; equal to the camera without distortion."""
    mx, my = camera_margin(effects, camera_intrinsics)
    c = camera_intrinsics
    return Intrinsics(c.width + 2 * mx, c.height + 2 * my, c.fx, c.fy, c.cx + mx, c.cy + my)


# --------------------------------------------------------------------------- camera side

def apply_camera(image: np.ndarray, effects: EffectSet, camera_intrinsics: Intrinsics,
                 rng: np.random.Generator | None, *,
                 ambient_irradiance_image: np.ndarray | None = None, supersample: int = 1) -> np.ndarray:
    """What the camera records of a clean linear render ``image`` (H×W×3, linear, ≥ 0).

    Order follows the light: ambient light joins the scene light → lens
    distortion → sensor noise (on the linear signal, Poisson-Gaussian; the
    sensor saturates at 1) → camera processing (white balance gains, tone
    curve) → clipping to [0, 1] and 16-bit quantisation, as written to the
    capture PNG. (Noise comes before the camera curve because a sensor adds it
    to the raw signal; with camera_response off the order does not matter.)

    ``image`` is either camera-sized or rendered with
    :func:`camera_render_intrinsics` (a margin of :func:`camera_margin` pixels
    on each side), which distortion needs to avoid black corners; the output
    is always camera-sized. ``ambient_irradiance_image`` (same size as
    ``image``) is the scene lit by room light only, scaled so that a white
    Lambertian surface facing that light reads 1; black_level.ambient scales
    it. Without it the ambient light is a uniform veil (stray light, flare).

    ``supersample`` > 1: ``image`` was rendered at that many times the
    resolution (:func:`camera_render_intrinsics` scaled by it). Distortion
    then resamples it at that resolution and the result is averaged down to
    the camera's pixels, as a real sensor integrates the lens's continuous
    image. Why: resampling an image already sampled at the camera's pixels
    biases patterns finer than about two pixels (measured: Gray code of a
    projector whose pixel is 0.6 camera pixel decodes up to 0.3 projector
    pixel off, radially, under k1 = −0.06; a board calibration reads it as
    projector distortion).
    """
    intr = camera_intrinsics
    img = _rgb(image, "camera image")
    h, w = img.shape[:2]
    ss = int(supersample)
    if ss < 1 or w % ss or h % ss:
        raise LabError(f"camera image is {w}×{h}, not a whole multiple of the supersampling {supersample}")
    mx2, my2 = w // ss - intr.width, h // ss - intr.height
    if mx2 < 0 or my2 < 0 or mx2 % 2 or my2 % 2:
        raise LabError(f"camera image is {w}×{h}; expected the camera's {intr.width}×{intr.height} "
                       "or that plus an equal margin on each side (camera_render_intrinsics)"
                       + (f", times the supersampling {ss}" if ss > 1 else ""))
    mx, my = mx2 // 2, my2 // 2
    img = np.maximum(img, 0.0)

    e = effects["black_level"]
    if e["ambient"] > 0:
        tint = np.array([1.0 + 0.15 * e["warmth"], 1.0, 1.0 - 0.3 * e["warmth"]], dtype=np.float32)
        tint /= tint.mean()  # warmth changes the colour, not the amount
        if ambient_irradiance_image is None:
            img = img + np.float32(e["ambient"]) * tint
        else:
            amb = np.asarray(ambient_irradiance_image, dtype=np.float32)
            if amb.ndim == 2:
                amb = amb[..., None]
            if amb.shape[:2] != (h, w):
                raise LabError(f"ambient image is {amb.shape[1]}×{amb.shape[0]}, the camera image {w}×{h}")
            img = img + np.float32(e["ambient"]) * np.maximum(amb, 0.0) * tint

    lens = lens_of(effects)
    fine = intr.scaled(intr.width * ss, intr.height * ss) if ss > 1 else intr
    if lens is not None:
        img = _distort(img, fine, (mx * ss, my * ss), lens)
    elif mx or my:
        img = img[my * ss:(my + intr.height) * ss, mx * ss:(mx + intr.width) * ss]
    if ss > 1:
        img = cv2.resize(img, (intr.width, intr.height), interpolation=cv2.INTER_AREA)
    if effects["noise"].active and rng is None:
        raise LabError("sensor noise needs a seeded np.random.Generator")
    return record_signal(img, effects, rng)


def record_signal(image: np.ndarray, effects: EffectSet, rng: np.random.Generator | None) -> np.ndarray:
    """What the camera records of the linear signal ``image`` reaching its sensor (camera-sized, after the lens):
    sensor noise (Poisson-Gaussian; the sensor saturates at 1), then its processing (white balance gains, tone
    curve), clipped and quantised to 16 bits as written to a capture PNG. ``rng`` None: without the noise."""
    img = image
    e = effects["noise"]
    if e.active and rng is not None:
        sig = np.clip(img, 0.0, None).astype(np.float64)
        if e["gain"] > 0:
            sig = rng.poisson(sig / e["gain"]) * e["gain"]  # photo-electrons are Poisson counts
        if e["sigma"] > 0:
            sig = sig + rng.normal(0.0, e["sigma"], size=sig.shape)
        img = sig.astype(np.float32)
    img = np.clip(img, 0.0, 1.0)  # full well / ADC range

    e = effects["camera_response"]
    if e.active:
        gains = np.array([e["gain_r"], 1.0, e["gain_b"]], dtype=np.float32)
        img = np.clip(img * gains, 0.0, 1.0)
        c = np.float32(e["curve"])
        if c > 0:
            img = (1.0 - c) * img + c * srgb_encode(img).astype(np.float32)

    return quantise16(img)


def quantise16(image: np.ndarray) -> np.ndarray:
    """Clip to [0, 1] and round to the 16-bit levels of a capture PNG."""
    return (np.round(np.clip(image, 0.0, 1.0) * 65535.0) / 65535.0).astype(np.float32)


def _distort(img: np.ndarray, intr: Intrinsics, margin: tuple[int, int], lens: Lens) -> np.ndarray:
    """Resample an ideal pinhole render into the distorted camera image (camera-sized)."""
    map_x, map_y = _distortion_maps(intr, margin, lens)
    return cv2.remap(img, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=(0, 0, 0))


@functools.lru_cache(maxsize=8)  # a capture set renders dozens of frames with the same lens
def _distortion_maps(intr: Intrinsics, margin: tuple[int, int], lens: Lens) -> tuple[np.ndarray, np.ndarray]:
    _check_lens(intr, lens)
    mx, my = margin
    # output pixel centres in the corner convention, as distorted normalised coordinates
    u = np.arange(intr.width, dtype=np.float64) + 0.5
    v = np.arange(intr.height, dtype=np.float64) + 0.5
    xd, yd = np.meshgrid((u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy)
    xu, yu = _undistort_lens(xd, yd, lens)
    # remap indexes pixel centres at integers: subtract the half pixel, add the render margin
    map_x = (xu * intr.fx + intr.cx - 0.5 + mx).astype(np.float32)
    map_y = (yu * intr.fy + intr.cy - 0.5 + my).astype(np.float32)
    map_x.flags.writeable = False  # shared through the cache
    map_y.flags.writeable = False
    return map_x, map_y


def distort_points(points: np.ndarray, camera_intrinsics: Intrinsics, effects: EffectSet) -> np.ndarray:
    """Where ideal pinhole pixel positions (N×2, corner convention) land in the distorted camera image."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    lens = lens_of(effects)
    if lens is None:
        return p.copy()
    intr = camera_intrinsics
    x, y = _distort_normalised((p[:, 0] - intr.cx) / intr.fx, (p[:, 1] - intr.cy) / intr.fy, lens)
    return np.stack([x * intr.fx + intr.cx, y * intr.fy + intr.cy], axis=1)


def describe(effects: EffectSet) -> str:
    """One line per active effect with its parameters (for logs and the lab report)."""
    rows = [f"{e.name}={e.strength:g}: " + ", ".join(f"{k}={v:.4g}" for k, v in e.values)
            for e in effects.effects if e.active]
    return "\n".join(rows) or "no effects"


__all__ = [
    "LabError", "Param", "EffectKind", "Effect", "EffectSet", "REGISTRY", "NAMES", "PRESETS",
    "parse_effects", "effect_help", "apply_projector", "apply_camera", "render_settings",
    "camera_margin", "camera_render_intrinsics", "vignetting_gain", "crosstalk_matrix", "quantise16",
    "distort_points", "describe", "s_curve", "warmup_gain", "depth_blur_sigma", "lens_of",
]
