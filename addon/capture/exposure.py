"""Exposure and white balance that changed during a session, told from the captures themselves.

A capture session needs the camera's exposure and white balance fixed (the
exported sequence's instructions say so); a phone left on auto changes them
between photographs, and every later stage then reads the change as light from
the projector. The captures carry their own check, because light adds up: with
a fixed exposure, in linear values, every pair of complementary patterns sums
to what white and black sum to, pixel by pixel,

    graycode bit b  +  its inverse   =  white + black
    checker phase 0 +  phase 1       =  white + black

(each projector pixel is on in exactly one of the two; interreflections, blur
and the black level add up the same way). :func:`check_exposure` measures, per
pair and per colour channel, the trimmed mean of (A + B) / (W + K) over the lit,
unsaturated pixels that are clearly on in one image of the pair and off in the
other, away from the pattern's edges (there the sum holds whatever the camera's
response curve; partly lit pixels obey it only in exactly linear values, and
fine Gray-code bits with too few such pixels are skipped). A gain away from 1
by more than :data:`GAIN_TOLERANCE` is an exposure change, a channel away from
the pair's mean gain by more than :data:`COLOUR_TOLERANCE` a white-balance
change. The first offending file is named: the earlier image of the first pair
that disagrees, or the later one when it alone differs from its partner (the
change happened between the two).

What is not checked, and why: the ``surface`` photograph is taken with the
projector off and the room lights on (the sequence's instructions), so no
invariant ties it to ``black``; validation images depend on the projector's
response, which calibration measures. Captures are reduced by area averaging
(which keeps the sums exact) to at most :data:`CHECK_SIZE` pixels a side, so a
whole session fits in memory.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..errors import CaptureError, ImageError
from ..imageio import read_image
from .format import CaptureSet

#: Seconds between the two white captures of the exposure-lock check (auto exposure settles in about one second).
ADAPT_S = 1.0
#: The camera "sees" the white frame once its picture's mean rises this much above black's (linear units).
SEEN_STEP = 0.02

#: Captures are checked at most this many pixels a side (area averaging keeps sums exact and lowers noise).
CHECK_SIZE = 320
#: A pair whose gain (A + B)/(W + K) moves further than this from 1 (either way, as a log ratio, ≈ ±10 %) is
#: refused. Measured residuals with a fixed exposure: lab sets (curve/vedge/plane, 4 spp) at most 0.0005 as
#: rendered and 0.0064 once saved as 8-bit sRGB JPEGs with shot noise; the real kamino410 photographs (4
#: sessions, 12 pairs each, read as linear) at most 0.016, standard deviation 0.004–0.005. 0.1 is six times the
#: worst real residual and still catches a 1/6-stop change (auto exposure moves in steps of 1/3 stop, 0.23).
GAIN_TOLERANCE = 0.1
#: A channel whose gain moves further than this from the pair's mean gain (log ratio) is a white-balance change.
#: Measured with a fixed white balance: at most 0.0003 on lab sets as rendered, 0.016 once saved as 8-bit JPEGs
#: (chroma subsampling); the real photographs are monochrome. 0.05 (3× that) catches one channel changed by 8 %.
COLOUR_TOLERANCE = 0.05
#: Lit area: where white − black exceeds this share of its 99th percentile.
LIT_SHARE = 0.25
#: Pixels where the white capture reaches this value in any channel are left out (clipping hides a gain).
SATURATED = 0.9
#: A pixel is clearly on in one image of a pair and off in the other when their difference is at least this share
#: of white − black (a pair darker by 1/1.5 still passes).
CLEAR_SHARE = 0.6
#: A pair is judged only when this share of the lit area is clear (finer patterns are skipped).
CLEAR_PAIR = 0.25
#: Fewer lit, unsaturated pixels than this share of the image: the check cannot be made.
MIN_LIT = 0.01

_HOW = ("lock the camera's exposure and white balance (manual mode, or AE/AWB lock on a phone; no HDR, no "
        "auto ISO) and capture the whole sequence again")


@dataclass(frozen=True)
class Shot:
    """One capture for the check: its kind and parameters as in a capture set, linear image, and file name."""

    kind: str
    params: Mapping[str, Any]
    image: np.ndarray
    source: str


def reduce_image(image: np.ndarray, max_side: int = CHECK_SIZE) -> np.ndarray:
    """A linear H×W×3 capture area-averaged down to at most ``max_side`` pixels a side (float32)."""
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    h, w = img.shape[:2]
    f = max(h, w) / float(max_side)
    if f <= 1:
        return img.copy()
    size = (max(1, round(w / f)), max(1, round(h / f)))
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA).reshape(size[1], size[0], -1)


@dataclass(frozen=True)
class PairCheck:
    """The gain of one complementary pair against white + black."""

    first: str
    second: str
    #: per-channel trimmed mean of (A + B)/(W + K) over the clear pixels
    gain: tuple[float, float, float]
    #: exp(mean log gain): the exposure change
    exposure: float
    #: exp(largest channel deviation from the mean log gain): the white-balance change
    colour: float
    #: the on-pixels' own gains of the first and second image against white (to tell which one changed)
    own: tuple[float, float]

    def drift(self) -> tuple[float, float]:
        """|log exposure| and |log colour|."""
        return abs(float(np.log(self.exposure))), abs(float(np.log(self.colour)))


@dataclass(frozen=True)
class ExposureReport:
    """What :func:`check_exposure` measured (it raises when the session fails)."""

    checked: bool
    reason: str
    pairs: tuple[PairCheck, ...] = ()
    lit_fraction: float = 0.0
    reference: tuple[str, str] = ("", "")

    @property
    def max_exposure_drift(self) -> float:
        return max((p.drift()[0] for p in self.pairs), default=0.0)

    @property
    def max_colour_drift(self) -> float:
        return max((p.drift()[1] for p in self.pairs), default=0.0)

    def notes(self) -> dict[str, Any]:
        """What the capture set's ``notes["exposure"]`` records."""
        return {"checked": self.checked, "reason": self.reason, "pairs_checked": len(self.pairs),
                "lit_fraction": round(self.lit_fraction, 4),
                "max_exposure_drift_log": round(self.max_exposure_drift, 4),
                "max_colour_drift_log": round(self.max_colour_drift, 4),
                "tolerances_log": {"exposure": GAIN_TOLERANCE, "colour": COLOUR_TOLERANCE}}


def _pairs(shots: list[Shot]) -> list[tuple[Shot, Shot]]:
    """Complementary pairs in capture order: Gray-code bit + inverse, checker phase 0 + 1 of one square size."""
    groups: dict[tuple, dict[Any, int]] = {}
    for i, s in enumerate(shots):
        p = s.params
        if s.kind == "graycode":
            key, side = ("graycode", str(p.get("axis")), int(p.get("bit", -1))), bool(p.get("inverted"))
        elif s.kind == "checker":
            key, side = ("checker", p.get("square")), int(p.get("phase", 0)) % 2
        else:
            continue
        groups.setdefault(key, {}).setdefault(side, i)
    pairs = [tuple(sorted(g.values())) for g in groups.values() if len(g) == 2]
    return [(shots[i], shots[j]) for i, j in sorted(pairs)]


def _trimmed_mean(values: np.ndarray, trim: float = 0.1) -> float:
    """The mean of the values between their ``trim`` and 1 − ``trim`` quantiles."""
    lo, hi = np.quantile(values, [trim, 1.0 - trim])
    inside = values[(values >= lo) & (values <= hi)]
    return float(inside.mean()) if inside.size else float(np.median(values))


def _lum(img: np.ndarray) -> np.ndarray:
    return img.mean(axis=2)


def check_exposure(shots: Sequence[Shot], *, gain_tolerance: float = GAIN_TOLERANCE,
                   colour_tolerance: float = COLOUR_TOLERANCE, where: str = "") -> ExposureReport:
    """Refuse a session whose exposure or white balance changed (see the module's docstring).

    ``shots`` are the session's captures in capture order (linear, one common
    size; :func:`reduce_image` them first to save memory). Returns what was
    measured; raises a :class:`CaptureError` naming the first offending file.
    A session without white, black or complementary pairs is not checked.
    """
    shots = list(shots)
    whites = [s for s in shots if s.kind == "white"]
    blacks = [s for s in shots if s.kind == "black"]
    pairs = _pairs(shots)
    if not whites or not blacks or not pairs:
        return ExposureReport(False, "exposure not checked: no white, black and complementary pattern pairs")
    white, black = whites[0], blacks[0]
    shapes = {s.image.shape for s in [white, black, *[x for ab in pairs for x in ab]]}
    if len(shapes) != 1:
        raise CaptureError(f"{where or 'the captures'}: captures of different sizes ({sorted(shapes)}); "
                           "every photograph of a session must have the same size")
    w, k = white.image.astype(np.float64), black.image.astype(np.float64)
    ref = w + k
    wl, kl = _lum(w), _lum(k)
    signal = wl - kl
    top = float(np.percentile(signal, 99))
    lit = ((signal > LIT_SHARE * top) & (w.max(axis=2) < SATURATED) & np.all(ref > 1e-4, axis=2)) if top > 0 \
        else np.zeros(signal.shape, bool)
    if lit.mean() < MIN_LIT:
        bright = top > 0 and float((signal > LIT_SHARE * top).mean()) >= MIN_LIT
        why = "the white capture is saturated over the lit area" if bright else \
            "white and black hardly differ (is the projector on?)"
        return ExposureReport(False, f"exposure not checked: {why}", lit_fraction=float(lit.mean()),
                              reference=(white.source, black.source))
    checks: list[PairCheck] = []
    checked_pairs: list[tuple[Shot, Shot]] = []
    checked_at: list[int] = []  # each check's index in ``pairs``
    for j, (a, b) in enumerate(pairs):
        ai, bi = a.image.astype(np.float64), b.image.astype(np.float64)
        al, bl = _lum(ai), _lum(bi)
        # Pixels fully on in one image and off in the other: there A + B = W + K whatever the camera's response
        # curve; partly lit pixels (fine stripes, edges) obey it only in exactly linear values.
        clear = lit & (np.abs(al - bl) >= CLEAR_SHARE * signal)
        # away from the patterns' edges too, where blur and flare mix the two (eroded by 2 pixels)
        clear = cv2.erode(clear.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        if clear.sum() < CLEAR_PAIR * lit.sum():
            continue
        # a trimmed mean, not a median: when only one image of the pair changed, the ratios split in two groups
        gain = tuple(_trimmed_mean((ai[..., c] + bi[..., c])[clear] / ref[..., c][clear]) for c in range(3))
        logs = np.log(np.maximum(gain, 1e-6))
        on_a, on_b = clear & (al > bl), clear & (bl > al)
        own_a = float(np.median(al[on_a] / wl[on_a])) if on_a.sum() >= 10 else float("nan")
        own_b = float(np.median(bl[on_b] / wl[on_b])) if on_b.sum() >= 10 else float("nan")
        checks.append(PairCheck(a.source, b.source, gain, float(np.exp(logs.mean())),
                                float(np.exp(np.max(np.abs(logs - logs.mean())))), (own_a, own_b)))
        checked_pairs.append((a, b))
        checked_at.append(j)
    if not checks:
        return ExposureReport(False, "exposure not checked: no pattern pair has enough clearly lit pixels",
                              lit_fraction=float(lit.mean()), reference=(white.source, black.source))
    for n, ((a, b), pc) in enumerate(zip(checked_pairs, checks)):
        exp_drift, col_drift = pc.drift()
        if exp_drift <= gain_tolerance and col_drift <= colour_tolerance:
            continue
        # The change happened at the pair's first image, or between its two images when the second alone differs.
        culprit = a
        own_a, own_b = pc.own
        if np.isfinite(own_a) and np.isfinite(own_b) and own_a > 0 and own_b > 0:
            step = float(np.log(own_b / own_a))
            if step * np.log(pc.exposure) > 0 and abs(step) > exp_drift:
                culprit = b
        if exp_drift > gain_tolerance:
            kind = "the camera's exposure changed during the session"
            what = (f"{'brighter' if pc.exposure > 1 else 'darker'}: {a.source} + {b.source} add up to "
                    f"{pc.exposure:.2f}× white + black ({white.source} + {black.source}), where a fixed exposure "
                    f"gives 1 (tolerance ±{np.expm1(gain_tolerance):.0%})")
        else:
            ch = "RGB"[int(np.argmax(np.abs(np.log(pc.gain) - np.log(pc.exposure))))]
            kind = "the camera's white balance changed during the session"
            what = (f"differently coloured: {a.source} + {b.source} add up to white + black × "
                    f"{pc.gain[0]:.2f}/{pc.gain[1]:.2f}/{pc.gain[2]:.2f} (R/G/B), the {ch} channel off by "
                    f"{pc.colour - 1:.0%} (tolerance {np.expm1(colour_tolerance):.0%})")
        hint = ""
        if len(checks) > 1 and all(x.drift()[0] > gain_tolerance or x.drift()[1] > colour_tolerance for x in checks):
            hint += (f" Every pair disagrees with white + black alike: {white.source} or {black.source} may be the "
                     "odd ones out.")
        later = [float(np.log(x.exposure)) for x in checks[n:]]
        if exp_drift > gain_tolerance and float(np.ptp(later)) > 0.5 * gain_tolerance:
            # Not one step but a change that comes and goes with the patterns: more like a wrong response curve.
            hint += (" If the exposure was in fact locked, the photographs' encoding may be wrong (8-bit photographs "
                     "from a linear machine-vision camera need --encoding linear).")
        since = culprit.source
        skipped_from = checked_at[n - 1] + 1 if n > 0 else 0
        if culprit is a and skipped_from < checked_at[n]:
            since += (f" (or from as early as {pairs[skipped_from][0].source}: "
                      "the pairs between have patterns too fine to check)")
        raise CaptureError(f"{where + ': ' if where else ''}{kind}, from {since} on: it is {what}.{hint} "
                           f"Nothing was imported; {_HOW}")
    return ExposureReport(True, "exposure and white balance steady", tuple(checks), float(lit.mean()),
                          (white.source, black.source))


def capture_set_shots(captures: CaptureSet) -> list[Shot]:
    """The shots of an existing capture set (reduced), named by their photograph's file when it has one."""
    out = []
    for e in captures.entries:
        if e.kind in ("white", "black", "checker", "graycode"):
            try:
                img = read_image(captures.file(e))
            except ImageError as exc:
                raise CaptureError(f"capture set {captures.path}: {e.file} is unreadable ({exc})") from None
            out.append(Shot(e.kind, dict(e.params), reduce_image(img), str(e.params.get("source", e.file))))
    return out


def check_capture_set(captures: CaptureSet, **kwargs: Any) -> ExposureReport:
    """:func:`check_exposure` on an existing capture set."""
    return check_exposure(capture_set_shots(captures), where=f"capture set {captures.path}", **kwargs)


__all__ = ["COLOUR_TOLERANCE", "ExposureReport", "GAIN_TOLERANCE", "PairCheck", "Shot", "capture_set_shots",
           "check_capture_set", "check_exposure", "reduce_image"]
