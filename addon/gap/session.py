"""Did the rig stay the same during the capture session? Light that drifted, a surface or camera that moved.

The effect models describe a rig that does not change; a session during which
the projector warmed up or the surface was knocked breaks that assumption, and
any model fitted to it explains a change as if it were a property of the rig.
So before naming effects the diagnosis asks the captures themselves, from two
invariants that hold for every static rig whatever its effects:

* **light**: complementary pairs add up to white + black
  (``capture/exposure.py`` measures each pair's per-channel gain; here the
  gains are only read, in capture order), and the closing white
  (``val_white_end``, the sequence's last capture) repeats the opening one.
  The light drifted when the gains change along the session by more than
  :data:`DRIFT_MIN` and by more than :data:`DRIFT_SCATTER` times the pairs'
  scatter about a straight line in time.
* **motion**: the closing white against the opening one. A static rig gives
  a ratio image that is a constant per channel (plus noise); a surface or
  camera that moved shifts the paint and the surface's outline, which shows as
  ``log(end / start) ≈ g_c − ∇log(start) · u(x)`` with ``u`` a small affine
  image motion (linearised, like one Lucas–Kanade step, fitted on the lit
  pixels away from the lit area's border, where the static projector footprint
  would pull it). The rig moved when the motion's RMS over the lit pixels
  exceeds :data:`MOTION_MIN_PX` and it explains at least
  :data:`MOTION_MIN_SHARE` of the ratio image's variance.

A capture set without a closing white (made before it existed, or without
validation patterns) is checked on its pairs only, and says so.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import cv2
import numpy as np

from ..capture.exposure import check_exposure, reduce_image, Shot
from ..capture.format import CaptureSet
from ..capture.patterns import CLOSING_WHITE
from ..errors import ImageError
from ..imageio import read_image

#: Smallest change of the light along the session reported as drift (log ratio, any channel): 1.5 %.
DRIFT_MIN = 0.015
#: ... and it must exceed the pairs' scatter about a straight line in time this many times.
DRIFT_SCATTER = 4.0
#: Smallest image motion (RMS over the lit pixels, in pixels of the checked image) reported as movement.
MOTION_MIN_PX = 0.08
#: ... and the motion must explain at least this share of the variance of log(end / start).
MOTION_MIN_SHARE = 0.15
#: The images are checked at this size (area averaging keeps the ratios and lowers the noise).
CHECK_SIDE = 320
#: Lit pixels nearer than this to the lit area's border are left out of the motion fit.
BORDER_PX = 4


@dataclass
class SessionCheck:
    """What :func:`check_session` found (``to_dict`` is what ``gap.json`` holds under ``session``)."""

    drift_detected: bool = False
    #: change of the light along the session per channel (log ratio, last against first measurement)
    drift_rgb: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: per checked capture: (name, place in the session 0..1, per-channel log gain against white + black)
    drift_series: list[tuple[str, float, tuple[float, float, float]]] = field(default_factory=list)
    motion_detected: bool = False
    motion_rms_px: float = 0.0
    motion_share: float = 0.0
    #: mean image shift (x, y) of the closing white against the opening one, checked-image pixels
    motion_shift_px: tuple[float, float] = (0.0, 0.0)
    closing_white: bool = False
    notes: list[str] = field(default_factory=list)

    @property
    def changed(self) -> bool:
        return self.drift_detected or self.motion_detected

    def sentence(self) -> str:
        """One plain sentence on what changed during the session (empty when nothing did)."""
        parts = []
        if self.drift_detected:
            ch = "RGB"[int(np.argmax(np.abs(self.drift_rgb)))]
            parts.append(f"the projected light changed by {np.expm1(max(self.drift_rgb, key=abs)):+.1%} "
                         f"({ch} most) between the first and the last captures (a projector still warming up, or "
                         "the camera's exposure drifting)")
        if self.motion_detected:
            parts.append(f"the surface or the camera moved during the session (the last white capture is "
                         f"{self.motion_rms_px:.2f} px off the first)")
        return "; ".join(parts)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["changed"] = self.changed
        d["sentence"] = self.sentence()
        d["drift_rgb"] = [round(float(v), 4) for v in self.drift_rgb]
        d["drift_series"] = [[n, round(t, 3), [round(float(v), 4) for v in g]] for n, t, g in self.drift_series]
        return d


def _order(captures: CaptureSet) -> dict[str, float]:
    """Each projected capture's place in the session, 0 (first) to 1 (last)."""
    shown = [e.name for e in captures.entries if e.kind != "depth"]
    n = max(len(shown) - 1, 1)
    return {name: i / n for i, name in enumerate(shown)}


def _read(captures: CaptureSet, entry: Any) -> np.ndarray:
    return reduce_image(read_image(captures.file(entry)), CHECK_SIDE)


def _drift(captures: CaptureSet, order: dict[str, float], closing: np.ndarray | None, white: np.ndarray,
           black: np.ndarray, out: SessionCheck) -> None:
    shots = [Shot(e.kind, dict(e.params), _read(captures, e), e.name)
             for e in captures.entries if e.kind in ("white", "black", "checker", "graycode")]
    # Only the measured gains are wanted here, never a refusal: the tolerances are opened wide.
    report = check_exposure(shots, gain_tolerance=np.inf, colour_tolerance=np.inf)
    series = [(p.first, order.get(p.first, 0.0), tuple(float(np.log(max(g, 1e-6))) for g in p.gain))
              for p in report.pairs]
    if closing is not None:
        ref = white.astype(np.float64) + black
        lit = _lit(white, black)
        if lit.sum() >= 50:
            g = [float(np.median((closing[..., c] + black[..., c])[lit] / ref[..., c][lit])) for c in range(3)]
            series.append((CLOSING_WHITE, order.get(CLOSING_WHITE, 1.0), tuple(float(np.log(v)) for v in g)))
    # white itself is the first measurement: gain 1 by definition
    series.insert(0, ("white", order.get("white", 0.0), (0.0, 0.0, 0.0)))
    out.drift_series = series
    if len(series) < 3:
        out.notes.append("light drift not measured: fewer than two complementary pairs or closing white")
        return
    t = np.array([s[1] for s in series])
    g = np.array([s[2] for s in series])  # n×3
    a = np.stack([np.ones_like(t), t], axis=1)
    coef, *_ = np.linalg.lstsq(a, g, rcond=None)
    fitted = a @ coef
    scatter = float(np.sqrt(np.mean((g - fitted) ** 2))) if len(series) > 2 else 0.0
    change = g[-1] - g[0] if closing is not None else coef[1] * (t[-1] - t[0])
    out.drift_rgb = tuple(float(v) for v in change)
    big = float(np.max(np.abs(change)))
    out.drift_detected = big > DRIFT_MIN and big > DRIFT_SCATTER * scatter
    out.notes.append(f"light: {len(series) - 1} measurements along the session, largest change "
                     f"{big:.3f} (log), scatter about a line {scatter:.4f}")


def _lit(white: np.ndarray, black: np.ndarray) -> np.ndarray:
    signal = (white - black).mean(axis=2)
    top = float(np.percentile(signal, 99))
    return (signal > 0.25 * top) & (white.max(axis=2) < 0.95) & (black.min(axis=2) >= 0) if top > 0 else \
        np.zeros(signal.shape, bool)


def _motion(white: np.ndarray, closing: np.ndarray, black: np.ndarray, out: SessionCheck) -> None:
    lit = _lit(white, black)
    inner = cv2.erode(lit.astype(np.uint8), np.ones((2 * BORDER_PX + 1,) * 2, np.uint8)).astype(bool)
    if inner.sum() < 200:
        out.notes.append("motion not measured: too few lit pixels in the white captures")
        return
    s = np.log(np.maximum(cv2.GaussianBlur(white - black, (0, 0), 0.7), 1e-4))
    e = np.log(np.maximum(cv2.GaussianBlur(closing - black, (0, 0), 0.7), 1e-4))
    gy, gx = np.gradient(s, axis=(0, 1))
    h, w = lit.shape
    ys, xs = np.nonzero(inner)
    u = (xs - w / 2) / (w / 2)
    v = (ys - h / 2) / (h / 2)
    rows, rhs = [], []
    for c in range(3):
        gxc, gyc = gx[ys, xs, c], gy[ys, xs, c]
        onehot = np.zeros((len(xs), 3))
        onehot[:, c] = 1.0
        # d = e − s ≈ g_c − (gx·(a0 + a1 u + a2 v) + gy·(b0 + b1 u + b2 v))
        rows.append(np.concatenate([onehot, -np.stack([gxc, gxc * u, gxc * v, gyc, gyc * u, gyc * v], 1)], 1))
        rhs.append((e - s)[ys, xs, c])
    a, d = np.concatenate(rows), np.concatenate(rhs)
    coef, *_ = np.linalg.lstsq(a, d, rcond=None)
    gains_only = d - np.repeat([float(np.mean(r)) for r in rhs], len(xs))
    resid = d - a @ coef
    share = 1.0 - float(np.sum(resid ** 2)) / max(float(np.sum(gains_only ** 2)), 1e-12)
    mx = coef[3] + coef[4] * u + coef[5] * v
    my = coef[6] + coef[7] * u + coef[8] * v
    out.motion_rms_px = float(np.sqrt(np.mean(mx ** 2 + my ** 2)))
    out.motion_share = max(share, 0.0)
    out.motion_shift_px = (float(mx.mean()), float(my.mean()))
    out.motion_detected = out.motion_rms_px > MOTION_MIN_PX and out.motion_share > MOTION_MIN_SHARE
    out.notes.append(f"motion: closing white {out.motion_rms_px:.3f} px RMS off the opening one, explaining "
                     f"{out.motion_share:.0%} of their ratio's variance")


def check_session(captures: CaptureSet) -> SessionCheck:
    """Light drift and motion during the session, from its own captures (see the module docstring)."""
    out = SessionCheck()
    order = _order(captures)
    try:
        white = _read(captures, captures.entries_of("white")[0])
        black = _read(captures, captures.entries_of("black")[0])
        ends = [e for e in captures.entries_of("validation") if e.name == CLOSING_WHITE]
        closing = _read(captures, ends[0]) if ends else None
    except (IndexError, ImageError) as exc:
        out.notes.append(f"session not checked: {exc or 'no white or black capture'}")
        return out
    out.closing_white = closing is not None
    _drift(captures, order, closing, white, black, out)
    if closing is None:
        out.notes.append("motion not measured: the capture set has no closing white (val_white_end); sequences "
                         "exported by this version end with one")
    else:
        _motion(white, closing, black, out)
    return out


__all__ = ["SessionCheck", "check_session"]
