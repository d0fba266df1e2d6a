"""Stage C's measured closed loop: a per-pixel correction learned from the camera's own captures.

The paper's θ follows each capture's residual by Eq. 10: a fixed third of the
way per capture, as if the real rig answered every change of the model's
prediction one for one. A real rig does not: where its response or colour
mixing differ from the model's at a pixel and level, the camera moves by
``s`` times what the model predicts, ``s`` that pixel's own slope; and every
capture brings its own noise, which a fixed rate carries into the answer.

Here each pixel and channel keeps (all on the display area's rows):

* **its slope**, measured: a ridge regression of the captures ``y_k`` on the
  operator's predictions ``q_k = g·T z_k`` over the loop's captures, pulled
  towards 1 (the model) by as much as the capture noise makes the captures'
  spread uncertain. Where a pixel's captures do not follow the prediction at
  all (a capture shifted against the model at an edge, a pixel the projector
  does not reach), the slope is near 0 and the step below vanishes there,
  instead of chasing the edge;
* **θ as an estimate of what it needs**: each capture measures
  ``m_k = q_k − t + ŝ(t − y_k)/(ŝ² + κ)``, the θ with which the next solve's
  prediction would make the camera see the target (a Newton step on the
  measured slope, Tikhonov-damped by κ). In the first captures, while the
  residual lies well outside the capture noise, θ takes the latest
  measurement whole (converging); once inside, and for every pixel after
  :data:`FULL_STEP_CAPTURES` captures, θ averages the measurements (each
  capture's noise is averaged out, 1/n after n captures, instead of the
  third that Eq. 10 keeps);
* **the noise floor**: the first input is captured twice; half the squared
  difference, as a function of the captured level (sensor noise grows with
  the signal, from a floor in the dark), is each pixel's noise variance.

The loop stops when the residual's mean square reaches the noise floor (what
a capture of a perfect answer would show), at the capture budget, or when the
captures say the rig changed under it: a capture far further from the last
than the input's change explains (camera bumped, surface moved, a lamp
switched on), a capture black or saturated where the last was not, or a
residual that grew three captures in a row (the correction diverging). Then
the best answer captured so far is kept and the reason is reported.

Before all that, the first capture must be of the calibrated rig (:func:`other_rig_share`): a device of another
rig with as many projectors (another lab truth, another room) put its light elsewhere, and the loop then chased
it from 20.9 to 7.3 dB and exited 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from .schedule import CompensationError

#: Damping of the Newton step on the measured slope: step = ŝ/(ŝ² + κ); 1/(1 + κ) at the model's slope.
KAPPA = 0.05
#: Detail finer than this (σ, camera pixels) has its own slope: a blur the model lacks passes less of it.
FINE_SIGMA = 1.0
#: The fine slope is measured over a window of this σ (camera pixels): a blur changes slowly over the surface.
FINE_WINDOW = 12.0
#: A blur passes at most all of the fine detail; below a fifth, pushing harder only amplifies noise.
FINE_SLOPE_RANGE = (0.2, 1.2)
#: Measured slopes are kept in this range (a factor of 3 either way of the model).
SLOPE_RANGE = (0.0, 3.0)
#: The slope's prior weight, in captures' worth of spread at the noise level (pulls ŝ towards 1).
PRIOR_WEIGHT = 4.0
#: Older captures count this much less in the slope per capture (the level moves as the loop converges).
FORGET = 0.85
#: A residual within this many noise σ counts as converged: θ averages from then on; a converged pixel takes full
#: steps again only beyond :data:`RESET_SIGMA` (a noise draw past 2.5 σ, one in eighty, must not undo its average).
CONVERGED_SIGMA = 2.5
RESET_SIGMA = 5.0
#: Only this many captures may take a whole step: after them every pixel averages. A pixel whose residual stays
#: beyond the noise by then is one the loop cannot fix (an edge the model's blur misses, a colour the projector
#: cannot show), and whole steps there would only carry each capture's noise into the answer (0 and 2 such captures
#: were within 0.05 dB of each other on two targets of the lab's curve; 3 is what docs/results.md's figures ran).
FULL_STEP_CAPTURES = 3
#: The loop stops when the residual's mean square is within this factor of the noise floor.
FLOOR_FACTOR = 1.1
#: A capture that moved from the last by more than this many times what the input's change and the noise explain
#: means the rig changed (module doc).
JUMP_FACTOR = 6.0
#: A change of the captures under this mean square (an RMS of about 0.007 of white) is never called a rig change.
JUMP_FLOOR = 5e-5
#: Residual mean squares growing this many captures in a row: the correction diverges.
DIVERGING_CAPTURES = 3
#: A capture with more than this share of its values at 0 (or at 1) where the last had under half of that is
#: black (saturated).
EXTREME_SHARE = 0.5
#: How far the closed loop's first capture may depart from the operator's prediction, as a share of the image's RMS,
#: once one gain and one offset per channel are taken out (exposure, the room's light and black level, the
#: response's slope: what the loop itself corrects). What is left on the calibrated rig is the model's local error
#: (blur, edges, a response that bends, colour that varies over the frame): measured on the lab's own rigs, noise
#: taken out, 0.04–0.13 (the curve with the realistic effects 0.08 on city, 0.04 on grey; the other-forms rig at full
#: strength 0.09; two projectors with tone curves of their own 0.13, the worst). A device of another rig puts its
#: light elsewhere and leaves a share of the image itself: 0.40 (a curve's calibration, a plane's lab) and 0.60–0.75
#: (side-by-side projectors' calibration, stacked projectors' lab), runs that ended 5 to 18 dB below where they
#: started. 0.3 lies more than twice the worst agreement of a calibrated rig above it (a real rig's model is worse
#: than the lab's own), and below every rig whose light lands elsewhere.
OTHER_RIG_SHARE = 0.3
#: The image's RMS is taken as at least this level (of white): a dim target's capture is mostly the room's light and
#: the noise, which do not tell one rig from another.
OTHER_RIG_LEVEL = 0.1


class OtherRigError(CompensationError):
    """The closed loop's first capture is not of the calibrated rig (:func:`other_rig_share`)."""


def other_rig_share(y: np.ndarray, q: np.ndarray, noise_variance: float = 0.0) -> float:
    """How far the capture ``y`` departs from the operator's prediction ``q`` (rows × 3 of the display area): the RMS
    left after a least-squares gain and offset per channel, the capture noise (``noise_variance``, of ``y``) taken
    out, as a share of the prediction's RMS (at least :data:`OTHER_RIG_LEVEL`). Compared with
    :data:`OTHER_RIG_SHARE`."""
    y64, q64 = np.asarray(y, np.float64).reshape(-1, 3), np.asarray(q, np.float64).reshape(-1, 3)
    left = 0.0
    for c in range(3):
        design = np.stack([q64[:, c], np.ones(len(q64))], axis=1)
        coef, *_ = np.linalg.lstsq(design, y64[:, c], rcond=None)
        left += float(np.mean((y64[:, c] - design @ coef) ** 2)) / 3.0
    excess = max(left - float(noise_variance), 0.0)
    level = max(float(np.sqrt(np.mean(q64 ** 2))), OTHER_RIG_LEVEL)
    return float(np.sqrt(excess)) / level


def check_first_capture(y: np.ndarray, q: np.ndarray, name: str, noise_variance: float = 0.0) -> None:
    """Refuse (:class:`OtherRigError`) a first capture of target ``name`` that is not of the calibrated rig."""
    share = other_rig_share(y, q, noise_variance)
    if share > OTHER_RIG_SHARE:
        raise OtherRigError(
            f"the device's first capture of {name!r} departs from what the calibration predicts by {share:.0%} of the "
            f"image (a calibrated rig stays within about {OTHER_RIG_SHARE:.0%}, after exposure and black level): the "
            "device is not the rig of this calibration (another lab truth or room, another camera or projector, or "
            "the rig moved since it was calibrated). Give the device of this calibration, or calibrate this rig "
            "again (procam calibrate CAPTURES --out CAL)")


@dataclass(frozen=True)
class NoiseModel:
    """The camera's noise variance as a function of the captured level: piecewise linear through ``levels`` and
    ``variances`` (held flat beyond them): a sensor's noise grows with the signal, from a floor in the dark."""

    levels: tuple[float, ...]
    variances: tuple[float, ...]

    def __call__(self, level: np.ndarray) -> np.ndarray:
        return np.interp(np.clip(level, 0.0, 1.0), self.levels, self.variances).astype(np.float32)

    @staticmethod
    def flat(variance: float) -> NoiseModel:
        return NoiseModel((0.0, 1.0), (float(variance), float(variance)))


def noise_variance_model(first: np.ndarray, second: np.ndarray, bins: int = 8) -> NoiseModel:
    """The :class:`NoiseModel` of two captures of one input (rows × 3): half their squared difference, averaged in
    ``bins`` bins of equal count by level."""
    level = np.clip(0.5 * (first + second), 0.0, 1.0).ravel()
    d2 = 0.5 * (first - second).ravel() ** 2
    order = np.argsort(level, kind="stable")
    xs, ys = [], []
    for part in np.array_split(order, bins):
        if len(part) >= 16:
            xs.append(float(level[part].mean()))
            ys.append(max(float(d2[part].mean()), 1e-10))
    if len(xs) < 2:
        return NoiseModel.flat(max(float(d2.mean()), 1e-10))
    return NoiseModel(tuple(xs), tuple(ys))


class RowGrid:
    """The display area's rows (flat camera pixel indices) as an image, for what acts across pixels: blurs that
    count only the area's own pixels (normalised convolution), so its border is not darkened by what lies outside."""

    def __init__(self, rows: np.ndarray, camera_size: tuple[int, int]) -> None:
        cw, _ = camera_size
        ys, xs = np.divmod(np.asarray(rows), cw)
        self.y0, self.x0 = int(ys.min()), int(xs.min())
        self.shape = (int(ys.max()) - self.y0 + 1, int(xs.max()) - self.x0 + 1)
        self.iy, self.ix = ys - self.y0, xs - self.x0
        mask = np.zeros(self.shape, np.float32)
        mask[self.iy, self.ix] = 1.0
        self.mask = mask
        self._norm: dict[float, np.ndarray] = {}

    def blur(self, values: np.ndarray, sigma: float) -> np.ndarray:
        """Rows × C values blurred by a Gaussian of ``sigma`` camera pixels over the area's pixels alone."""
        c = values.shape[1]
        img = np.zeros((*self.shape, c), np.float32)
        img[self.iy, self.ix] = values
        norm = self._norm.get(sigma)
        if norm is None:
            norm = self._norm[sigma] = np.maximum(cv2.GaussianBlur(self.mask, (0, 0), sigma), 1e-6)
        out = cv2.GaussianBlur(img, (0, 0), sigma) / norm[..., None]
        return out[self.iy, self.ix].astype(np.float64)


@dataclass
class MeasuredCorrection:
    """The per-pixel state of the measured loop for one target (module doc); arrays are rows × 3."""

    target: np.ndarray
    grid: RowGrid
    noise: NoiseModel = NoiseModel.flat(1e-4)
    n_avg: np.ndarray = field(init=False)
    history: list[dict[str, Any]] = field(default_factory=list)

    def __post_init__(self) -> None:
        shape = self.target.shape
        self.n_avg = np.zeros(shape, np.float32)
        self._sw = 0.0
        self._sq = np.zeros(shape, np.float64)
        self._sy = np.zeros(shape, np.float64)
        self._sqq = np.zeros(shape, np.float64)
        self._sqy = np.zeros(shape, np.float64)
        self.slope = np.ones(shape, np.float32)
        self.fine_slope = np.ones(shape, np.float32)
        self._fa = np.zeros(shape, np.float64)
        self._fb = np.zeros(shape, np.float64)
        self.theta: np.ndarray | None = None
        self._last: tuple[np.ndarray, np.ndarray] | None = None
        self._updates = 0

    @property
    def floor(self) -> float:
        """The mean noise variance over the target's levels: the residual of a perfect answer's capture."""
        return float(np.mean(self.noise(self.target)))

    def _update_slope(self, q: np.ndarray, y: np.ndarray, weight: float) -> None:
        f = FORGET
        self._sw = f * self._sw + weight
        self._sq = f * self._sq + weight * q
        self._sy = f * self._sy + weight * y
        self._sqq = f * self._sqq + weight * q * q
        self._sqy = f * self._sqy + weight * q * y
        sw = max(self._sw, 1e-9)
        var_q = np.maximum(self._sqq - self._sq ** 2 / sw, 0.0)
        cov = self._sqy - self._sq * self._sy / sw
        prior = PRIOR_WEIGHT * self.noise(self.target)
        self.slope = np.clip((cov + prior) / (var_q + prior), *SLOPE_RANGE).astype(np.float32)

    def fine(self, values: np.ndarray) -> np.ndarray:
        """The part of rows × 3 ``values`` finer than :data:`FINE_SIGMA` camera pixels."""
        return values - self.grid.blur(values, FINE_SIGMA)

    def _update_fine_slope(self, q: np.ndarray, y: np.ndarray) -> None:
        """How much of a fine change of the prediction reaches the camera (a lens's blur the model lacks), from the
        change between the last two captures, averaged over :data:`FINE_WINDOW` pixels around each."""
        if self._last is None:
            return
        last_y, last_q = self._last
        dq, dy = self.fine(q - last_q), self.fine(y - last_y)
        self._fa = FORGET * self._fa + dq * dy
        self._fb = FORGET * self._fb + dq * dq
        a, b = self.grid.blur(self._fa, FINE_WINDOW), self.grid.blur(self._fb, FINE_WINDOW)
        prior = 0.25 * self.floor
        self.fine_slope = np.clip((a + prior) / (b + prior), *FINE_SLOPE_RANGE).astype(np.float32)

    def check(self, y: np.ndarray, q: np.ndarray) -> str | None:
        """Why the capture ``y`` of the prediction ``q`` says the rig changed under the loop, or None."""
        if self._last is None:
            return None
        last_y, last_q = self._last
        for what, extreme in (("black", y <= 1e-3), ("saturated", y >= 0.999)):
            share, before = float(extreme.mean()), float((last_y <= 1e-3 if what == "black" else last_y >= 0.999)
                                                        .mean())
            if share > EXTREME_SHARE and before < 0.5 * share:
                return (f"the capture is {what} ({100 * share:.0f} % of the display area, the last {100 * before:.0f} "
                        "%): the camera or projector changed (lens cap, exposure, a dark or bright frame shown); "
                        "check the rig and run again")
        # What the input's change should have done to the last capture, by the measured slope; what is left is the
        # camera's noise (twice: two captures), the model's own error on that change (at an edge the light moves
        # between pixels, where a slope per pixel cannot say it: up to the whole change), or a rig that changed. An
        # absolute floor keeps a noiseless camera from calling its model's small misses a change.
        change = self.slope * (q - last_q)
        unexplained = float(np.mean((y - last_y - change) ** 2))
        allowed = 2.0 * self.floor + float(np.mean(change ** 2)) + JUMP_FLOOR
        if unexplained > JUMP_FACTOR * allowed:
            return (f"the capture changed {np.sqrt(unexplained / allowed):.1f}× more than the input's change and the "
                    "camera's noise explain: the camera or the surface moved, or the light in the room changed; put "
                    "the rig back (or calibrate again) and run again")
        return None

    def update(self, y: np.ndarray, q: np.ndarray, *, repeats: int = 1) -> np.ndarray:
        """θ after the capture ``y`` (the mean of ``repeats`` captures) of an input the operator predicts as ``q``."""
        y = y.astype(np.float64)
        var = self.noise(y) / repeats
        self._update_fine_slope(q, y)
        self._update_slope(self.grid.blur(q, FINE_SIGMA), self.grid.blur(y, FINE_SIGMA), float(repeats))
        s, sf = self.slope, self.fine_slope
        resid = self.target - y
        coarse = self.grid.blur(resid, FINE_SIGMA)
        m = q - self.target + s * coarse / (s * s + KAPPA) + sf * (resid - coarse) / (sf * sf + KAPPA)
        self._updates += 1
        if self._updates > FULL_STEP_CAPTURES:
            converged = np.ones(resid.shape, bool)
        else:
            converged = resid * resid <= np.where(self.n_avg > 0, RESET_SIGMA ** 2, CONVERGED_SIGMA ** 2) * var
        if self.theta is None:
            theta = m
            self.n_avg = np.where(converged, float(repeats), 0.0).astype(np.float32)
        else:
            n = np.where(converged, self.n_avg + repeats, 0.0)
            beta = np.where(converged, repeats / np.maximum(n, 1.0), 1.0)
            theta = self.theta + beta * (m - self.theta)
            self.n_avg = n.astype(np.float32)
        self.theta = theta.astype(np.float32)
        self._last = (y, q)
        self.history.append({"residual_rms": round(float(np.sqrt(np.mean(resid ** 2))), 5), "repeats": repeats,
                             "converged_share": round(float(converged.mean()), 3),
                             "slope_median": round(float(np.median(s)), 3),
                             "fine_slope_median": round(float(np.median(sf)), 3)})
        return self.theta

    def stop_reason(self) -> str | None:
        """'noise floor' when the last residual reached it, 'diverging' when it grew :data:`DIVERGING_CAPTURES`
        captures in a row, else None."""
        rms = [h["residual_rms"] for h in self.history]
        # a capture that is the mean of several holds that much less noise: a perfect answer's residual is smaller
        if rms and rms[-1] ** 2 <= FLOOR_FACTOR * self.floor / self.history[-1].get("repeats", 1):
            return "noise floor"
        if len(rms) > DIVERGING_CAPTURES and all(b > a * 1.02 for a, b in zip(rms[-DIVERGING_CAPTURES - 1:-1],
                                                                              rms[-DIVERGING_CAPTURES:])):
            return "diverging"
        return None


__all__ = ["MeasuredCorrection", "NoiseModel", "OtherRigError", "RowGrid", "check_first_capture",
           "noise_variance_model", "other_rig_share"]
