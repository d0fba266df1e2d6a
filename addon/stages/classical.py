"""The classical baseline: per-pixel colour-mixing compensation (Nayar et al. 2003, Yoshida et al. 2003).

No simulation: every camera pixel ``p`` is modelled on its own as

    C_p = M_p · g(I(u_p)) + b_p

``u_p`` the projector pixel it sees (decoded from the Gray-code captures),
``I`` the projector input, ``g`` a global per-channel response that
linearises the input (projector gamma and camera curve together, as those
papers calibrate it from uniform grey images), ``M_p`` a 3×3 colour-mixing
matrix (surface albedo × projector/camera primaries × vignetting) and ``b_p``
an offset (black level, ambient light). Both are fitted by least squares per
pixel from flat-colour and known captures:

* the capture set's black, white and validation patterns (grey levels, colour
  ramps, smooth random colours), each read at ``u_p``;
* plus flat primaries (red, green, blue) projected through the device at fit
  time when one is given — the capture set has no uniform colour images, and
  the mixing columns are poorly conditioned from greys and ramps alone (Nayar
  et al. project exactly such images). The model's ``report`` says how many
  were captured.

Compensation inverts that per pixel — ``I = g⁻¹(clip(M_p⁻¹(T_p − b_p), 0, 1))``
— and carries the camera-space input to projector space through the inverse of
the Gray-code correspondence: each projector pixel takes the mean camera
position of the camera pixels that decode to it, holes inside the seen region
are filled by normalised convolution, and projector pixels the camera never
sees, or whose camera position lies outside the display area, stay black (as
in stage C's start). A small ridge pulls ill-conditioned pixels' ``M_p``
towards the median matrix instead of letting them explode.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..capture.devices import Device
from ..capture.format import CaptureSet
from ..capture.patterns import decode_gray_code_set, flat
from ..errors import CalibrationError, CaptureError

#: Flat colours projected at fit time (the capture set holds none): the three primaries.
PRIMARIES: tuple[tuple[float, float, float], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
#: Ridge weight towards the median mixing matrix (relative to a sample's weight of 1).
RIDGE = 1e-4
#: A pixel whose fit residual exceeds this many times the median is not trusted (filled from neighbours).
OUTLIER_RESIDUAL = 4.0
#: A camera pixel takes part when white − black exceeds this (linear camera units).
LIT_THRESHOLD = 0.02


@dataclass
class Response:
    """Per-channel input linearisation ``g``: ``v^gamma`` plus a piecewise-linear correction through knots."""

    gamma: np.ndarray  # (3,)
    knots: np.ndarray  # (K,) input levels, including 0 and 1
    values: np.ndarray  # (K, 3) g at the knots (0 at 0, 1 at 1)

    @staticmethod
    def linear() -> Response:
        k = np.array([0.0, 1.0])
        return Response(np.ones(3), k, np.stack([k] * 3, axis=1))

    def __call__(self, v: np.ndarray) -> np.ndarray:
        v = np.clip(np.asarray(v, np.float64), 0.0, 1.0)
        out = np.empty_like(v)
        for c in range(3):
            resid = self.values[:, c] - self.knots ** self.gamma[c]
            out[..., c] = v[..., c] ** self.gamma[c] + np.interp(v[..., c], self.knots, resid)
        return out

    def inverse(self, y: np.ndarray) -> np.ndarray:
        """``g⁻¹`` (g is monotone: checked when fitted), by a dense table."""
        table_v = np.linspace(0.0, 1.0, 4097)
        table = self(np.repeat(table_v[:, None], 3, axis=1))
        y = np.clip(np.asarray(y, np.float64), 0.0, 1.0)
        out = np.empty_like(y)
        for c in range(3):
            out[..., c] = np.interp(y[..., c], table[:, c], table_v)
        return out


def fit_response(levels: np.ndarray, normalised: np.ndarray) -> Response:
    """Per-channel ``g`` from grey levels ``levels`` (K,) and the median normalised captures (K, 3),
    where normalised = (C(v) − C(0)) / (C(1) − C(0))."""
    lv = np.asarray(levels, np.float64)
    nv = np.clip(np.asarray(normalised, np.float64), 1e-4, 1.0)
    inner = (lv > 0) & (lv < 1)
    gammas = np.ones(3)
    grid = np.linspace(0.2, 5.0, 961)
    for c in range(3):
        if inner.any():
            err = ((lv[inner][None, :] ** grid[:, None] - nv[inner, c][None, :]) ** 2).sum(axis=1)
            gammas[c] = grid[int(np.argmin(err))]
    knots = np.unique(np.concatenate([[0.0, 1.0], lv[inner]]))
    values = np.empty((len(knots), 3))
    for c in range(3):
        values[:, c] = np.interp(knots, np.concatenate([[0.0], lv[inner], [1.0]]),
                                 np.concatenate([[0.0], nv[inner, c], [1.0]]))
    resp = Response(gammas, knots, values)
    table = resp(np.repeat(np.linspace(0, 1, 1025)[:, None], 3, axis=1))
    if np.any(np.diff(table, axis=0) <= 0):
        # The knots bend the curve backwards (noise, clipping): keep the plain power law, which is monotone.
        resp = Response(gammas, np.array([0.0, 1.0]), np.array([[0.0] * 3, [1.0] * 3]))
    return resp


def fit_mixing(inputs: np.ndarray, captures: np.ndarray, *, ridge: float = RIDGE,
               prior: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel least squares ``captures ≈ M · inputs + b``.

    ``inputs``, ``captures``: N×P×3 (N samples of P pixels, inputs already
    linearised). Returns ``M`` (P×3×3, row = output channel), ``b`` (P×3) and
    each pixel's RMS residual (P). ``ridge`` pulls ``M`` towards ``prior`` (3×3, default
    the median of an unregularised fit); with ``ridge=0`` and well-posed
    data the fit is exact.
    """
    x = np.asarray(inputs, np.float64)
    y = np.asarray(captures, np.float64)
    if x.shape != y.shape or x.ndim != 3 or x.shape[2] != 3:
        raise CalibrationError(f"colour-mixing fit needs inputs and captures of the same N×P×3 shape, "
                               f"got {x.shape} and {y.shape}")
    n = x.shape[0]
    if n < 4:
        raise CalibrationError(f"a per-pixel 3×3 mixing + offset needs at least 4 known colours, got {n}")
    a = np.concatenate([x, np.ones(x.shape[:2] + (1,))], axis=2).transpose(1, 0, 2)  # P×N×4
    ata = np.einsum("pni,pnj->pij", a, a)
    aty = np.einsum("pni,pnc->pic", a, y.transpose(1, 0, 2))  # P×4×3
    reg = np.diag([1.0, 1.0, 1.0, 0.0]) * (ridge * n)
    if ridge > 0 and prior is None:
        coarse = np.linalg.solve(ata + reg[None] * 1e-3 + np.eye(4)[None] * 1e-9, aty)
        prior = np.median(coarse[:, :3, :], axis=0).T
    rhs = aty.copy()
    if ridge > 0:
        rhs[:, :3, :] += (ridge * n) * np.asarray(prior, np.float64).T[None]
    coef = np.linalg.solve(ata + reg[None] + np.eye(4)[None] * 1e-12, rhs)  # P×4×3
    m = coef[:, :3, :].transpose(0, 2, 1)
    b = coef[:, 3, :]
    pred = np.einsum("pci,npi->npc", m, x) + b[None]
    rms = np.sqrt(np.mean((pred - y) ** 2, axis=(0, 2)))
    return m.astype(np.float32), b.astype(np.float32), rms


def _sample(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear sample of ``image`` at corner-convention positions ``xy`` (…×2)."""
    mx = (xy[..., 0] - 0.5).astype(np.float32)
    my = (xy[..., 1] - 0.5).astype(np.float32)
    return cv2.remap(np.asarray(image, np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _consistent(coords: np.ndarray, valid: np.ndarray, tolerance: float = 3.0) -> np.ndarray:
    """``valid`` without decoding outliers: pixels whose projector position is more than ``tolerance`` px from
    the median of their valid 3×3 neighbours (a wrongly decoded bit throws a pixel far away)."""
    from numpy.lib.stride_tricks import sliding_window_view

    c = np.where(valid[..., None], coords, np.nan)
    pad = np.pad(c, ((1, 1), (1, 1), (0, 0)), constant_values=np.nan)
    win = sliding_window_view(pad, (3, 3), axis=(0, 1))  # H×W×2×3×3
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows
        med = np.nanmedian(win.reshape(win.shape[:3] + (9,)), axis=3)
    off = np.abs(c - med).max(axis=2)
    return valid & (off <= tolerance)


def _normalised_fill(values: np.ndarray, weight: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Fill pixels of ``region`` with weight 0 from their neighbours (normalised convolution, growing)."""
    v = np.where(weight[..., None] > 0, values, 0.0).astype(np.float32)
    w = weight.astype(np.float32)
    out = v / np.maximum(w, 1e-9)[..., None]
    todo = region & (w <= 0)
    sigma = 1.0
    while todo.any() and sigma < 64:
        sv = cv2.GaussianBlur(v, (0, 0), sigma)
        sw = cv2.GaussianBlur(w, (0, 0), sigma)
        ok = todo & (sw > 1e-4)
        out[ok] = sv[ok] / sw[ok][:, None]
        todo &= ~ok
        sigma *= 2.0
    return out


@dataclass
class ClassicalModel:
    """The fitted per-pixel model and the camera ↔ projector-input correspondence."""

    response: Response
    mixing: np.ndarray  # H×W×3×3 (camera size)
    offset: np.ndarray  # H×W×3
    valid: np.ndarray  # H×W: a decoded, lit camera pixel
    input_xy: np.ndarray  # H×W×2: projector input position (corner convention) seen by each camera pixel
    input_size: tuple[int, int]
    report: dict[str, Any] = field(default_factory=dict)
    _inverse: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(default=None, repr=False)

    def camera_input(self, target: np.ndarray) -> np.ndarray:
        """The projector colour each camera pixel needs (camera size; 0 where the pixel is not modelled)."""
        t = np.asarray(target, np.float64)
        lin = np.zeros_like(t)
        v = self.valid
        m = self.mixing[v].astype(np.float64)
        rhs = t[v] - self.offset[v]
        det = np.abs(np.linalg.det(m))
        good = det > 1e-9
        sol = np.zeros_like(rhs)
        sol[good] = np.linalg.solve(m[good], rhs[good][..., None])[..., 0]
        lin[v] = sol
        return self.response.inverse(np.clip(lin, 0.0, 1.0)).astype(np.float32)

    def inverse_map(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For each projector input pixel: camera x, y (pixel-centre coordinates) and whether it is seen."""
        if self._inverse is None:
            iw, ih = self.input_size
            v = self.valid
            ys, xs = np.nonzero(v)
            pu = np.floor(self.input_xy[v]).astype(int)
            inside = (pu[:, 0] >= 0) & (pu[:, 0] < iw) & (pu[:, 1] >= 0) & (pu[:, 1] < ih)
            idx = pu[inside, 1] * iw + pu[inside, 0]
            count = np.bincount(idx, minlength=iw * ih).reshape(ih, iw).astype(np.float32)
            sums = np.stack([np.bincount(idx, weights=xs[inside], minlength=iw * ih),
                             np.bincount(idx, weights=ys[inside], minlength=iw * ih)], axis=1)
            sums = sums.reshape(ih, iw, 2).astype(np.float32)
            # The seen region: decoded projector pixels, closed over the gaps a coarser camera leaves between them.
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7))
            seen = cv2.morphologyEx((count > 0).astype(np.uint8), cv2.MORPH_CLOSE, k).astype(bool)
            cam = _normalised_fill(sums, count, seen)
            self._inverse = (cam[..., 0].astype(np.float32), cam[..., 1].astype(np.float32), seen)
        return self._inverse

    def compensate(self, target: np.ndarray, area_mask: np.ndarray) -> np.ndarray:
        """The projector input (input size) for a camera-size ``target`` shown inside ``area_mask``."""
        want = self.camera_input(target)
        # Camera pixels in the area that are not modelled (Gray-code errors) take their neighbours' input.
        inside = area_mask & self.valid
        want = _normalised_fill(want, inside.astype(np.float32), area_mask)
        want[~area_mask] = 0.0
        mx, my, seen = self.inverse_map()
        x = cv2.remap(want.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                      borderValue=0)
        in_area = cv2.remap(area_mask.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                            borderValue=0) > 0.5
        return np.where((seen & in_area)[..., None], np.clip(x, 0.0, 1.0), 0.0).astype(np.float32)


def _known_samples(captures: CaptureSet) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, native frame, capture) of every capture set image whose pattern is a known colour image."""
    out = []
    for kind in ("black", "white", "validation"):
        for e in captures.entries_of(kind):
            if e.pattern:
                out.append((e.name, captures.pattern(kind, name=e.name), captures.image(kind, name=e.name)))
    return out


def fit_classical(captures: CaptureSet, *, device: Device | None = None,
                  colours: tuple[tuple[float, float, float], ...] = PRIMARIES, ridge: float = RIDGE) -> ClassicalModel:
    """Fit the per-pixel model from a capture set (and flat ``colours`` captured through ``device``)."""
    proj = captures.projector
    cw, ch = captures.camera.intrinsics.size
    decoding = decode_gray_code_set(captures)
    samples = _known_samples(captures)
    names = [s[0] for s in samples]
    if "black" not in names or "white" not in names:
        raise CaptureError(f"the classical baseline needs the white and black captures of {captures.path}")
    captured = 0
    if device is not None:
        for colour in colours:
            frame = proj.frame_from_input(flat(proj.input_size, colour))
            shot = np.asarray(device.project(frame), np.float32)
            if shot.shape != (ch, cw, 3):
                raise CaptureError(f"the device returned a {shot.shape[1]}×{shot.shape[0]} capture, but the camera "
                                   f"is {cw}×{ch}; is it the rig of this capture set?")
            samples.append((f"flat_{'_'.join(f'{c:g}' for c in colour)}", frame, shot))
            captured += 1
    frames = np.stack([s[1] for s in samples])
    shots = np.stack([s[2] for s in samples]).astype(np.float64)
    if shots.shape[1:3] != (ch, cw):
        raise CaptureError(f"captures of {captures.path} are not {cw}×{ch}")
    white, black = shots[names.index("white")], shots[names.index("black")]
    lit = decoding.valid & ((white - black).mean(axis=2) > LIT_THRESHOLD)
    valid = _consistent(decoding.coords, lit)
    if valid.sum() < 16:
        raise CalibrationError(f"only {int(valid.sum())} camera pixels of {captures.path} decode the Gray code "
                               "and are lit; the classical baseline cannot be fitted")
    coords = np.where(valid[..., None], decoding.coords, 0.5)
    inputs = np.stack([_sample(f, coords) for f in frames]).astype(np.float64)  # N×H×W×3, frame colours
    # Response from the grey images (black, val_grey_*, white): median normalised capture per level.
    levels, norm = [], []
    span = np.maximum(white - black, 1e-6)[valid]
    for (_name, _, _), x, y in zip(samples, inputs, shots):
        xi = x[valid]
        if np.ptp(xi) < 1e-3 and np.allclose(xi, xi[:, :1], atol=1e-3) and 0 < xi.mean() < 1:
            levels.append(float(xi.mean()))
            norm.append(np.median((y[valid] - black[valid]) / span, axis=0))
    response = fit_response(np.array(levels), np.array(norm).reshape(-1, 3)) if levels else Response.linear()
    lin = response(inputs[:, valid])
    m, b, rms = fit_mixing(lin, shots[:, valid], ridge=ridge)
    # Pixels the model does not explain (a mixed edge pixel, a glint) would get wild inputs: their neighbours fill in.
    fits = rms <= OUTLIER_RESIDUAL * float(np.median(rms))
    pixels = np.argwhere(valid)
    valid = valid.copy()
    valid[tuple(pixels[~fits].T)] = False
    m, b = m[fits], b[fits]
    mixing = np.zeros((ch, cw, 3, 3), np.float32)
    offset = np.zeros((ch, cw, 3), np.float32)
    mixing[valid], offset[valid] = m, b
    x0, y0 = proj.input_offset
    input_xy = (coords - np.array([x0, y0], np.float32)).astype(np.float32)
    report = {"method": "per-pixel 3×3 colour mixing + offset (Nayar et al. 2003), global per-channel response",
              "samples": len(samples), "patterns": [s[0] for s in samples], "flat_colours_captured": captured,
              "response_gamma": [round(float(g), 4) for g in response.gamma], "grey_levels": levels,
              "fit_rms": float(np.sqrt(np.mean(rms[fits] ** 2))), "fit_outliers": int((~fits).sum()),
              "pixels": int(valid.sum()), "decoding_outliers": int((lit & ~valid).sum()), "ridge": ridge}
    return ClassicalModel(response, mixing, offset, valid, input_xy, tuple(proj.input_size), report)


__all__ = ["ClassicalModel", "PRIMARIES", "Response", "fit_classical", "fit_mixing", "fit_response"]
