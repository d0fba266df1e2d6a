"""Each camera pixel's own radiometric model, measured from a few flat captures: its response and colour mixing.

The global effect models (``gap/``) give the whole rig one response curve, one
colour mixing, one vignetting law: a real rig whose response drifts over the
panel, whose mixing changes from one side of the frame to the other, or whose
camera bends its highlights in a knee differs from them at every pixel. Here
every camera pixel ``p`` gets its own::

    c = b_p + M_p · r_p(v),    v = f̂ / ŵ

``f̂`` the model's simulation (linear light, the units stage C solves in),
``ŵ`` the model's white, so ``v`` is the flat input level each channel of the
simulation stands for; ``r_p`` one increasing curve per channel (``r(0) = 0``,
``r(1) = 1``, piecewise linear between knots at the grey levels; interpolated
along the pixel's nearest power law ``v^γ`` instead, it predicted the held-out
captures as well and compensated 0.8 dB worse on the lab of other forms: the
inverse's steep start near black); ``M_p`` the 3×3 mixing (camera channel ←
projector primary) and ``b_p`` the black capture. The open loop works through
it on the camera side: the target is taken to the light
``ŵ · r⁻¹(M⁻¹(t − b))`` that the model must simulate
(:meth:`PixelRadiometry.to_light`), and the projector input is sent as it is
(the curve holds the projector's response, so no global ``g⁻¹`` either). A
closed loop starts from that answer and corrects it in the camera's own units,
where it measures each pixel's slope (``steps/stage_c.py``): through the
model, a capture's noise near black would be stretched by ``r⁻¹``'s steep
start and, clipped at 0, biased.

Measured from the captures a calibration already has (no new patterns): the
black and the white, the flat greys (0.25, 0.5, 0.75), and the per-channel
ramps, which say each primary's colour direction in the camera. A ramp
covers one level per pixel, dark on one side, so the directions are pooled
over a few pixels, weighted by the ramp's level; each column's length comes
from the white (averaged with the session's closing white: ``W − b = M · 1``),
each curve from the greys (``r(L) = M⁻¹(G_L − b)``), smoothed over 1.5 px
against the camera's noise. Whether it is used is decided by held-out captures
(the random textures, which none of this reads) against the global models'
prediction of them (:func:`choose_radiometry`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..errors import CalibrationError
from .bias import simulate_patterns, fit_bias

#: Pooling of a primary's colour direction (camera pixels, σ): colour mixing changes slowly over a lens's frame.
DIRECTION_SIGMA = 4.0
#: Smoothing of the response curves (σ, camera pixels), against the noise of one capture per level.
CURVE_SIGMA = 1.5
#: Below this share of the white (per channel) a pixel is too dark to measure: the identity model is kept there.
MIN_SIGNAL = 0.02
#: The smallest slope a curve keeps between two knots (so that it can be inverted).
MIN_SLOPE = 0.05


@dataclass
class PixelRadiometry:
    """Per camera pixel: black ``black`` (H×W×3), mixing ``mixing`` (H×W×3×3, camera ← primary), its inverse,
    curves ``curves`` (H×W×3×L at the input ``levels``, L knots from 0 to 1, linear between them) and the model's
    white ``white`` (H×W×3). Arrays of any leading shape (:meth:`crop` cuts a display area out)."""

    black: np.ndarray
    mixing: np.ndarray
    inverse: np.ndarray
    levels: np.ndarray
    curves: np.ndarray
    white: np.ndarray
    report: dict[str, Any] = field(default_factory=dict)

    def crop(self, area: Any) -> PixelRadiometry:
        """The model on a display area's pixels (``area.crop`` of every per-pixel array)."""
        return PixelRadiometry(area.crop(self.black), area.crop(self.mixing), area.crop(self.inverse), self.levels,
                               area.crop(self.curves), area.crop(self.white), self.report)

    def _knots(self) -> np.ndarray:
        return np.broadcast_to(self.levels, self.curves.shape)

    def to_light(self, image: np.ndarray) -> np.ndarray:
        """The light the model must simulate for the camera to see ``image`` (a capture or a target)."""
        u = np.einsum("...jk,...k->...j", self.inverse, np.asarray(image, np.float32) - self.black)
        v = _interpolate(u, self.curves, self._knots())
        return (np.clip(v, 0.0, None) * self.white).astype(np.float32)

    def to_camera(self, light: np.ndarray) -> np.ndarray:
        """What the camera sees for the simulated light ``light`` (the inverse of :meth:`to_light`)."""
        v = np.asarray(light, np.float32) / np.maximum(self.white, 1e-6)
        r = _interpolate(v, self._knots(), self.curves)
        return np.clip(self.black + np.einsum("...jk,...k->...j", self.mixing, r), 0.0, 1.0).astype(np.float32)


def _interpolate(x: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Piecewise-linear y(x) per pixel and channel through increasing knots ``xs`` → ``ys`` (… × L), linear beyond
    the end knots; the segment is the count of inner knots below ``x``."""
    i = np.zeros(x.shape, np.int64)
    for k in range(1, xs.shape[-1] - 1):
        i += x > xs[..., k]
    x0, x1 = (np.take_along_axis(xs, j[..., None], axis=-1)[..., 0] for j in (i, i + 1))
    y0, y1 = (np.take_along_axis(ys, j[..., None], axis=-1)[..., 0] for j in (i, i + 1))
    return y0 + (x - x0) / np.maximum(x1 - x0, 1e-6) * (y1 - y0)


def _blur(image: np.ndarray, sigma: float) -> np.ndarray:
    return cv2.GaussianBlur(np.ascontiguousarray(image, np.float32), (0, 0), sigma, borderType=cv2.BORDER_REFLECT)


def inverse3(m: np.ndarray) -> np.ndarray:
    """Each 3×3 matrix of ``m`` (…×3×3) inverted, in float64 from its adjugate (the rows' cross products): numpy's
    batched inverse took 0.3 s for a 640×480 camera's matrices, this 0.06, the same values in float32. A singular
    matrix (no camera pixel's mixing is, its diagonal is the channels' own white) gets its diagonal's inverse."""
    a = np.asarray(m, np.float64)
    r0, r1, r2 = a[..., 0, :], a[..., 1, :], a[..., 2, :]
    adjugate = np.stack([np.cross(r1, r2), np.cross(r2, r0), np.cross(r0, r1)], axis=-1)
    det = np.einsum("...i,...i->...", r0, adjugate[..., 0])
    ok = np.isfinite(det) & (det != 0.0)
    d = np.diagonal(a, axis1=-2, axis2=-1)
    out = adjugate / np.where(ok, det, 1.0)[..., None, None]
    diagonal = np.eye(3) / np.where(d != 0.0, d, 1.0)[..., None, :]
    return np.where(ok[..., None, None], out, diagonal)


def fit_pixel_radiometry(black: np.ndarray, white: np.ndarray, greys: dict[float, np.ndarray],
                         ramps: dict[int, tuple[np.ndarray, np.ndarray]], white_sim: np.ndarray
                         ) -> PixelRadiometry:
    """The model (module doc) from the captures of ``black`` and ``white``, of flat ``greys`` (level → capture) and
    of per-channel ``ramps`` (channel → (capture, the ramp's level per camera pixel in that channel, from the
    simulation)); ``white_sim``: the model's white ŵ. All camera-sized (H×W×3; the levels H×W)."""
    # the black is dim and smooth (the projector's leak and the room's light): smoothed, it adds no noise
    b = _blur(np.asarray(black, np.float32), CURVE_SIGMA)
    w = np.asarray(white, np.float32) - b
    h, wd = b.shape[:2]
    # Colour directions: column k of M relative to its own channel, pooled where ramp k is bright.
    ratio = np.repeat(np.eye(3, dtype=np.float32)[None, None], h * wd, axis=0).reshape(h, wd, 3, 3)
    for k, (capture, level) in ramps.items():
        weight = np.clip(np.asarray(level, np.float32), 0.0, 1.0)
        light = (np.asarray(capture, np.float32) - b) * weight[..., None]
        pooled = _blur(light, DIRECTION_SIGMA)
        own = pooled[..., k]
        ok = own > MIN_SIGNAL * np.maximum(_blur(w * weight[..., None], DIRECTION_SIGMA)[..., k], 1e-6)
        for j in range(3):
            if j != k:
                ratio[..., j, k] = np.where(ok, pooled[..., j] / np.maximum(own, 1e-6), 0.0)
    # Column lengths from the white: W − b = ratio · s.
    s = np.linalg.solve(ratio, w[..., None])[..., 0]
    dark = s < MIN_SIGNAL * np.maximum(w.max(axis=2, keepdims=True), 1e-3)
    s = np.where(dark, np.maximum(w, 1e-3), s)
    ratio = np.where(dark.any(axis=2)[..., None, None], np.eye(3, dtype=np.float32), ratio)
    mixing = (ratio * s[..., None, :]).astype(np.float32)
    inverse = inverse3(mixing).astype(np.float32)
    # Curves at the grey levels from M⁻¹(G_L − b), smoothed, then made increasing.
    inner = sorted(float(v) for v in greys if 0.0 < float(v) < 1.0)
    levels = np.array([0.0, *inner, 1.0], np.float32)
    knots = [np.zeros_like(b)]
    for level in inner:
        u = np.einsum("...jk,...k->...j", inverse, np.asarray(greys[level], np.float32) - b)
        knots.append(_blur(u, CURVE_SIGMA))
    knots.append(np.ones_like(b))
    curves = np.stack(knots, axis=-1)
    for i in range(1, len(levels)):
        floor = curves[..., i - 1] + MIN_SLOPE * (levels[i] - levels[i - 1])
        curves[..., i] = np.maximum(curves[..., i], floor)
    curves[..., -1] = np.maximum(curves[..., -1], 1.0)
    report = {"levels": [round(float(v), 4) for v in levels], "ramps": sorted(int(k) for k in ramps),
              "dark_share": round(float(dark.any(axis=2).mean()), 4)}
    return PixelRadiometry(b, mixing, inverse, levels, curves.astype(np.float32),
                           np.asarray(white_sim, np.float32), report)


#: The pixels a decision compares: lit at least this share of the model's brightest white, away from the edge.
DECISION_LIT = 0.2
#: … and this many camera pixels inside the lit region's edge (where blur and misregistration dominate both models).
DECISION_MARGIN = 8
#: The per-pixel model is used when its held-out error is below this share of the global model's (ties: global).
DECISION_MARGIN_SHARE = 0.98


def decision_region(white_sim: np.ndarray) -> np.ndarray:
    """The camera pixels a held-out comparison reads (H×W bool): well lit by the model's white, not near its edge."""
    grey = np.asarray(white_sim, np.float32).mean(axis=2)
    lit = (grey > DECISION_LIT * float(np.percentile(grey, 99.5))).astype(np.uint8)
    size = 2 * DECISION_MARGIN + 1
    return cv2.erode(lit, np.ones((size, size), np.uint8)).astype(bool)


@dataclass
class RadiometryPatterns:
    """Which captures of a set the per-pixel model reads and which it holds out (entries of a capture set)."""

    black: Any
    whites: list[Any]  # the white, and white shown again (the session's closing white): averaged
    greys: dict[float, Any]
    ramps: dict[int, Any]
    held_out: list[Any]

    @property
    def fit(self) -> list[Any]:
        return [self.black, *self.whites, *self.greys.values(), *self.ramps.values()]

    @classmethod
    def of(cls, captures: Any) -> RadiometryPatterns | str:
        """The patterns of ``captures``, or why the model cannot be measured from them."""
        blacks = [e for e in captures.entries_of("black") if e.pattern]
        whites = [e for e in captures.entries_of("white") if e.pattern]
        greys: dict[float, Any] = {}
        ramps: dict[int, Any] = {}
        held: list[Any] = []
        for e in captures.entries_of("validation"):
            p = e.params
            if not e.pattern:
                continue
            if p.get("pattern") == "grey" and 0.0 < float(p.get("level", 0.0)) < 1.0:
                greys.setdefault(float(p["level"]), e)
            elif p.get("pattern") == "grey" and float(p.get("level", 0.0)) == 1.0 and whites:
                whites.append(e)
            elif p.get("pattern") == "ramp" and p.get("channel") in ("r", "g", "b"):
                ramps.setdefault("rgb".index(p["channel"]), e)
            elif p.get("pattern") == "random":
                held.append(e)
        missing = [what for what, have in (("a black capture", blacks), ("a white capture", whites),
                                           ("flat greys", greys), ("a ramp in each of r, g and b", len(ramps) == 3),
                                           ("random textures to judge it on", held)) if not have]
        if missing:
            listed = ", ".join(missing[:-1]) + (" and " if len(missing) > 1 else "") + missing[-1]
            return f"the capture set lacks {listed}"
        return cls(blacks[0], whites, greys, ramps, held)


def choose_radiometry(comp: Any, captures: Any, rule: str, *, global_view: Any = None,
                      to_space: Callable[[np.ndarray], np.ndarray] | None = None
                      ) -> tuple[PixelRadiometry | None, dict[str, Any]]:
    """The per-pixel model of the :class:`~.compensate.Compensator` ``comp`` from ``captures`` (its capture set),
    and the record of the choice: ``rule`` 'pixel' uses it (refused when the set cannot give it), 'auto' when it
    predicts the held-out random textures better than the global models do.

    The global models see the set as ``global_view`` (the effect models' :class:`AdaptedCaptures`; default the set
    itself): θ (stages/bias.py) is fitted on the same patterns as the per-pixel model and predicts the held-out
    ones. ``to_space`` takes a camera image into the space the global models compare in (their camera-side inverse,
    if they have one), so that both errors are in the same units."""
    patterns = RadiometryPatterns.of(captures)
    if isinstance(patterns, str):
        if rule == "pixel":
            raise CalibrationError(f"--radiometry pixel needs the calibration's black, white, grey, ramp and random "
                                   f"validation captures, but {patterns}: capture the validation patterns "
                                   "(procam export-patterns writes them), or use --radiometry global")
        return None, {"used": "global", "reason": patterns}
    fit, held = patterns.fit, patterns.held_out
    sims, caps = simulate_patterns(comp, captures, fit + held)
    white_sim = comp.white()
    n = len(fit)
    ramp_at = {k: n - len(patterns.ramps) + i for i, k in enumerate(patterns.ramps)}
    level = {k: sims[i][..., k] / np.maximum(white_sim[..., k], 1e-6) for k, i in ramp_at.items()}
    nw = len(patterns.whites)
    greys = {v: caps[1 + nw + i] for i, v in enumerate(patterns.greys)}
    model = fit_pixel_radiometry(caps[0], caps[1:1 + nw].mean(axis=0), greys,
                                 {k: (caps[i], level[k]) for k, i in ramp_at.items()},
                                 white_sim)
    region = decision_region(white_sim)
    space = to_space or (lambda image: image)
    pixel_err = np.concatenate([(space(model.to_camera(sims[n + i])) - space(caps[n + i]))[region]
                                for i in range(len(held))])
    if global_view is None:
        g_sims, g_caps = sims, caps
    else:
        g_sims, g_caps = simulate_patterns(comp, global_view, fit + held)
    bias = fit_bias(g_sims[:n], g_caps[:n], white_sim.mean(axis=2) > 1e-3, [e.name for e in fit])
    global_err = np.concatenate([(bias.predict(g_sims[n + i]) - g_caps[n + i])[region] for i in range(len(held))])
    rmse = {"pixel": float(np.sqrt(np.nanmean(pixel_err ** 2))), "global": float(np.sqrt(np.nanmean(global_err ** 2)))}
    better = rmse["pixel"] < DECISION_MARGIN_SHARE * rmse["global"]
    used = "pixel" if rule == "pixel" or better else "global"
    record = {"used": used, "rule": rule, "held_out": [e.name for e in held],
              "held_out_rmse": {k: round(v, 5) for k, v in rmse.items()}, "global_bias": bias.kind,
              "pixels_compared": int(region.sum()), **model.report}
    if rule == "auto":
        record["reason"] = (f"the per-pixel model predicts the held-out captures {'better' if better else 'no better'}"
                            f" than the global models (RMS {rmse['pixel']:.4f} against {rmse['global']:.4f})")
    return (model if used == "pixel" else None), record
