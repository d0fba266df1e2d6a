"""Stage C's bias θ: how a capture is predicted from the simulation, and θ of the open loop.

Open loop (no device): θ is estimated once from the calibration's white,
black and validation captures. Each captured pattern ``x`` is simulated as
``f̂(M(x))`` (``M`` the inverse warp, since ``x = W(z)`` means ``z = M(x)``),
and either the per-pixel mean residual (``pred = f̂ − θ``) or a per-pixel,
per-channel affine fit (``pred = a·f̂ + b``, ridge towards ``a = 1``) is kept,
whichever predicts held-out patterns better (leave-one-pattern-out).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..capture.format import CaptureSet
from ..errors import CalibrationError, ProCamError
from .schedule import REFERENCE_SPP


@dataclass
class BiasModel:
    """How a capture is predicted from the simulation: ``pred = clip(gain · f̂ − theta, 0, 1)``.

    ``gain`` None means 1 (the paper's θ); the bias of Eq. 3 is then
    ``f̂ − pred``, which satisfies Eq. 14 by construction.
    """

    theta: np.ndarray
    gain: np.ndarray | None = None
    kind: str = "mean"  # 'mean', 'affine' or 'zero'
    report: dict[str, Any] = field(default_factory=dict)

    def predict(self, simulated: np.ndarray) -> np.ndarray:
        f = np.asarray(simulated, dtype=np.float32)
        return np.clip((f if self.gain is None else self.gain * f) - self.theta, 0.0, 1.0)

    def bias(self, simulated: np.ndarray) -> np.ndarray:
        """θ of Eq. 3 for a simulation ``f̂`` (within [f̂ − 1, f̂])."""
        return np.asarray(simulated, dtype=np.float32) - self.predict(simulated)


def predict_capture(raw: np.ndarray, bias: BiasModel | None, theta: np.ndarray | None) -> np.ndarray:
    """What the camera should see for a simulation ``raw``: through ``bias`` when given, else ``raw − theta``."""
    if bias is not None:
        return bias.predict(raw)
    return np.clip(raw - (0.0 if theta is None else theta), 0.0, 1.0)


def estimate_bias(comp: Any, captures: Any = None, *, ridge: float = 0.05) -> BiasModel:
    """θ for open-loop compensation (module doc) by the :class:`~.compensate.Compensator` ``comp``, from
    ``captures`` (default: the calibration's capture set)."""
    if captures is None:
        try:
            captures = CaptureSet.load(comp.calibration.capture_dir, verify_images=False)
        except ProCamError as exc:
            raise CalibrationError(f"open-loop compensation needs the calibration's capture set to estimate θ, "
                                   f"but it cannot be read: {exc}") from None
    if captures.camera.intrinsics.size != comp.camera_size:
        cw, ch = captures.camera.intrinsics.size
        raise CalibrationError(f"the capture set {captures.path} has {cw}×{ch} camera images, but the "
                               f"calibration's camera is {comp.camera_size[0]}×{comp.camera_size[1]}: "
                               "the calibration comes from another capture set")
    entries = [e for kind in ("black", "white", "validation") for e in captures.entries_of(kind) if e.pattern]
    if len(entries) < 3:
        raise CalibrationError(f"the capture set {captures.path} has {len(entries)} captures of known patterns "
                               "(white, black, validation); open-loop θ needs at least 3")
    sims, caps = simulate_patterns(comp, captures, entries)
    lit = comp.white().mean(axis=2) > 1e-3
    return fit_bias(sims, caps, lit, [e.name for e in entries], ridge=ridge)


def simulate_patterns(comp: Any, captures: Any, entries: list[Any]) -> tuple[np.ndarray, np.ndarray]:
    """The simulations ``f̂(M(x))`` of the patterns ``entries`` name and their captures (float64 stacks)."""
    proj = comp.rig.projector
    x0, y0 = proj.input_offset
    sims, caps = [], []
    for i, e in enumerate(entries):
        frame = captures.pattern(e.kind, name=e.name)
        if frame.shape[:2] != (comp.fh, comp.fw):
            raise CalibrationError(f"pattern {e.pattern} is {frame.shape[1]}×{frame.shape[0]}, not the "
                                   f"projector's {comp.fw}×{comp.fh}: the calibration comes from another "
                                   "capture set")
        virtual = frame.copy()
        region = (slice(y0, y0 + comp.ih), slice(x0, x0 + comp.iw))
        virtual[region] = comp.warp_m(frame[region])
        sims.append(comp.model.render(virtual, spp=REFERENCE_SPP, seed=comp.seed + 1000 + i))
        caps.append(captures.image(e.kind, name=e.name))
    return np.stack(sims).astype(np.float64), np.stack(caps).astype(np.float64)


def _affine(k: np.ndarray, sf: np.ndarray, sc: np.ndarray, sff: np.ndarray, sfc: np.ndarray,
            ridge: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-value ``c = a·f + b`` from the sums of k values, ridge λ pulling ``a`` towards 1."""
    k = np.maximum(k, 1e-9)  # (no value left: a = 1, b = 0)
    mf, mc = sf / k, sc / k
    a = (sfc - k * mf * mc + ridge) / (sff - k * mf * mf + ridge)
    return a, mc - a * mf


def fit_bias(f: np.ndarray, c: np.ndarray, lit: np.ndarray, names: list[str], *, ridge: float = 0.05
             ) -> BiasModel:
    """The mean or affine bias, whichever predicts held-out patterns better, from simulations ``f`` and captures
    ``c`` (n × H × W × 3) of the patterns ``names``; ``lit``: the camera pixels the projector reaches (H × W)."""
    # A value given as NaN is left out: captures seen through a glossy model mark so what the camera clipped
    # in the highlight (``gap.compensation.AdaptedCaptures``).
    w = np.isfinite(c).astype(np.float64)
    c = np.where(w > 0, c, 0.0)
    n = len(f)
    lit = np.broadcast_to(lit[..., None], c.shape[1:])
    # Mean residual, leave-one-out: θ_{-i} = (Σr − r_i)/(k − 1) over the k values given.
    r = (f - c) * w
    r_sum, k_all = r.sum(axis=0), w.sum(axis=0)
    mean_err = [(r[i] - (r_sum - r[i]) / np.maximum(k_all - w[i], 1))[lit & (w[i] > 0)] for i in range(n)]
    # Affine c = a·f + b per pixel and channel; leave-one-out on the sums.
    sf, sc, sff, sfc = (w * f).sum(0), (w * c).sum(0), (w * f * f).sum(0), (w * f * c).sum(0)
    aff_err = []
    for i in range(n):
        wi = w[i]
        a, b = _affine(k_all - wi, sf - wi * f[i], sc - wi * c[i], sff - wi * f[i] ** 2, sfc - wi * f[i] * c[i],
                       ridge)
        aff_err.append((np.clip(a * f[i] + b, 0, 1) - c[i])[lit & (wi > 0)])
    rmse_mean = float(np.sqrt(np.mean(np.concatenate(mean_err) ** 2)))
    rmse_aff = float(np.sqrt(np.mean(np.concatenate(aff_err) ** 2)))
    rmse_zero = float(np.sqrt(np.mean(r[:, lit][w[:, lit] > 0] ** 2)))  # (r is 0 where left out)
    report = {"patterns": list(names),
              "held_out_rmse": {"no_bias": rmse_zero, "mean": rmse_mean, "affine": rmse_aff},
              "left_out_share": round(float(1.0 - w[:, lit].mean()), 4)}
    if rmse_aff < rmse_mean:
        a, b = _affine(k_all, sf, sc, sff, sfc, ridge)
        return BiasModel((-b).astype(np.float32), a.astype(np.float32), "affine", report)
    return BiasModel((r_sum / np.maximum(k_all, 1)).astype(np.float32), None, "mean", report)
