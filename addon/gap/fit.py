"""Fitting effect models on some patterns, scoring them on the held-out rest, and greedy selection.

Each candidate is fitted (bounded Levenberg–Marquardt, finite-difference
Jacobian: the models have at most a handful of parameters and evaluate in
milliseconds per pattern) on the *fit* patterns and scored by the RMSE of
simulation vs capture on the *held-out* patterns, over the lit camera pixels.
Effects are added greedily, the one that lowers the held-out RMSE most first,
while each still removes at least ``min_share`` of the RMSE that is left: an
effect that only fits noise does not pass, so "no effect" is a possible answer.

Scoring uses the *structured* residual: the residual image smoothed with a
small Gaussian (``SMOOTH_SIGMA`` pixels) except on the edges of the projected
pattern, where it is kept as it is. Sensor and render noise is independent from
pixel to pixel and mostly averages out; what effects leave is either coherent
over several pixels (light levels, indirect light) or sits on pattern edges
(blur, misregistration), whose two-signed profile smoothing would cancel.
Measured on lab sets (vedge, 192×144): with interreflection injected, the
indirect-light model removes 1 % of the raw held-out RMSE (the capture noise
that bounces add dominates) but 16 % (σ = 1 px) to 35 % (σ = 2 px) of the
smoothed one, and 0.2 % of it on the set without the effect. Because pattern
edges keep their noise, an effect is scored by the share of the error it removes
in each class of pixels (smooth parts, pattern edges), whichever is larger.
Fits use the raw residual (noise does not bias a least-squares fit) under
Huber's robust loss (iteratively reweighted least squares, its scale
re-estimated from the residual's median absolute deviation at every step).
Pattern edges hold the calibration's sub-pixel misregistration, which no
effect model holds and which a steep tone curve magnifies: with the lab's full
sRGB camera curve the edges dominated a plain least-squares fit, which paired
a camera curve of 0.65–0.70 with a projector power law of 0.74–0.79 to flatten
the curve's slope there, and compensation through that pair lost 2.6 dB
against the true curve on the vedge. Under the robust loss the fit finds the
curve at 1.00 and nothing beside it. A blur or a distortion, whose change is
systematic over every edge, is still fitted there. The constant is wide
(:data:`HUBER_K`) because a local effect's own residuals are large and few:
at the usual 1.345 the bounce-light model removed half as much of the curve's
crease error as the plain fit. The raw RMSE is reported beside the structured
one.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Protocol, TypeVar

import cv2
import numpy as np

from ..progress import Cancel, Progress
from .data import GapData
from .models import Composite, MODELS, NAMES, describe_params
from .parallel import run_fits

#: An effect is added only if it removes at least this share of the held-out RMSE still left.
MIN_SHARE = 0.06
#: Rounds of the greedy selection (effects selected at most): each round fits every candidate left on top of
#: those selected, and the later rounds' fits are the slowest. The demo's `realistic` lab set needs five: at four
#: its blur was left out, second in every round (its diagnosis: four rounds 60 s, five 83 s, six 127 s).
MAX_EFFECTS = 5
#: Camera pixels per pattern the fit uses (a fixed random subset of the lit ones; scoring uses all).
FIT_PIXELS = 8000
#: Gaussian (pixels of the working image) that separates the structured residual from pixel noise.
SMOOTH_SIGMA = 1.5
#: Huber's constant, on the residual's robust standard deviation (1.4826 × its median absolute deviation):
#: residuals beyond it weigh in proportion to their size rather than its square. Wider than the usual 1.345
#: (95 % efficiency on Gaussian noise), which took too much weight from a local effect's own residuals.
HUBER_K = 3.0
#: Models a nested parameter can trade against (both bend the levels): beside one of them, the selected effects'
#: nested parameters are tried free in every round (:func:`select_effects`).
TRADES_WITH_NESTED = ("camera_response",)
#: A model's nested parameters (``EffectModel.nested``) are freed only when that lowers the fit patterns' robust
#: mean squared error (:func:`huber_rms` squared) by at least this share.
NESTED_GAIN = 0.05



@dataclass
class Fit:
    """One composite model fitted on the fit patterns and scored on the held-out ones."""

    names: tuple[str, ...]
    theta: np.ndarray
    fit_rmse: float
    held_rmse: float  # structured residual (smoothed off pattern edges)
    seconds: float
    error: str | None = None
    held_rmse_raw: float = float("nan")  # the plain simulation-vs-capture RMSE
    held_mse_classes: tuple[float, float] = (float("nan"), float("nan"))  # structured MSE: smooth parts, edges
    loss_scale: float = 0.0  # the Huber scale ``fit_rmse`` is measured at

    def share_of(self, before: Fit) -> float:
        """Share of ``before``'s held-out error this fit removes: the larger of the two pixel classes."""
        if self.error is not None:
            return float("-inf")
        shares = [(b - a) / b for b, a in zip(before.held_mse_classes, self.held_mse_classes) if b > 0]
        return float(max(shares)) if shares else 0.0

    def values(self) -> dict[str, np.ndarray]:
        """Each model's fitted parameters, unrounded."""
        comp_slices, i = {}, 0
        for n in (n for n in NAMES if n in self.names):
            k = len(MODELS[n].params)
            comp_slices[n] = self.theta[i:i + k]
            i += k
        return comp_slices

    def params(self) -> dict[str, dict[str, float]]:
        return {n: describe_params(n, v) for n, v in self.values().items()}

    def nested_held(self) -> tuple[str, ...]:
        """The models of this fit whose nested parameters stayed at their identity values (:func:`fit_composite`
        kept the fit that held them)."""
        return tuple(n for n, v in self.values().items() if MODELS[n].nested and
                     all(v[k] == MODELS[n].identity[k] for k in MODELS[n].nested))


def structured(residual: np.ndarray, edges: np.ndarray | None = None) -> np.ndarray:
    """The residual image without its pixel noise, kept sharp on ``edges`` (see the module docstring)."""
    if SMOOTH_SIGMA <= 0:
        return residual
    smooth = cv2.GaussianBlur(residual, (0, 0), SMOOTH_SIGMA)
    return smooth if edges is None else np.where(edges[..., None], residual, smooth)


def rmse(comp: Composite, theta: np.ndarray, index: list[int], *, smooth: bool = True) -> float:
    """RMSE of prediction vs capture over the lit pixels and all channels of the given patterns
    (of the structured residual unless ``smooth`` is False)."""
    return scores(comp, theta, index)["structured" if smooth else "raw"]


def scores(comp: Composite, theta: np.ndarray, index: list[int]) -> dict[str, Any]:
    """Raw and structured RMSE, and the structured MSE on smooth parts and on pattern edges."""
    m = comp.data.mask
    sums = {"raw": 0.0, "flat": 0.0, "edge": 0.0}
    counts = {"raw": 0, "flat": 0, "edge": 0}
    for i in index:
        o = comp.data.observations[i]
        r = comp.predict(theta, o) - o.capture
        st = structured(r, o.edges)
        edge = (o.edges if o.edges is not None else np.zeros_like(m)) & m
        flat = m & ~edge
        for key, img, sel in (("raw", r, m), ("flat", st, flat), ("edge", st, edge)):
            v = img[sel].astype(np.float64)
            sums[key] += float(np.sum(v ** 2))
            counts[key] += v.size
    mse = {k: sums[k] / max(counts[k], 1) for k in sums}
    total = (sums["flat"] + sums["edge"]) / max(counts["flat"] + counts["edge"], 1)
    return {"raw": float(np.sqrt(mse["raw"])), "structured": float(np.sqrt(total)),
            "classes": (mse["flat"], mse["edge"])}


def _scored(names: tuple[str, ...], theta: np.ndarray, fit_rmse: float, comp: Composite, data: GapData,
            seconds: float, loss_scale: float = 0.0) -> Fit:
    sc = scores(comp, theta, data.held_index)
    return Fit(names, theta, fit_rmse, sc["structured"], seconds, held_rmse_raw=sc["raw"],
               held_mse_classes=sc["classes"], loss_scale=loss_scale)


def residual_stack(comp: Composite, theta: np.ndarray, index: list[int]) -> np.ndarray:
    """Signed residuals prediction − capture (n × h × w × 3) of the given patterns."""
    return np.stack([comp.predict(theta, comp.data.observations[i]) - comp.data.observations[i].capture
                     for i in index])


def _huber_scale(r: np.ndarray) -> float:
    return HUBER_K * 1.4826 * float(np.median(np.abs(r - np.median(r))))


def huber_root_weights(r: np.ndarray) -> np.ndarray:
    """√ of the IRLS weights of Huber's loss for the residual ``r``: 1 within :data:`HUBER_K` robust standard
    deviations, ``k / |r|`` beyond."""
    k = _huber_scale(r)
    if k <= 0:
        return np.ones_like(r)
    a = np.abs(r)
    return np.sqrt(np.where(a <= k, 1.0, k / np.maximum(a, 1e-300)))


def huber_levenberg_marquardt(plain: Callable[[np.ndarray], np.ndarray], theta: np.ndarray, lo: np.ndarray,
                              hi: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Bounded Levenberg–Marquardt under Huber's loss from ``theta``: ``plain(t)`` is the unweighted residual,
    parameters with ``lo == hi`` stay put. Returns the parameters and the residual there; raises
    FloatingPointError when the parameters become NaN."""
    step = 1e-3 * (hi - lo)
    free = [k for k in range(theta.size) if hi[k] > lo[k]]
    lam = 1e-3
    at_theta = plain(theta)  # the unweighted residual at the current parameters
    for _ in range(iterations):
        # Reweighted at the current parameters; the step below is accepted on the cost under these weights.
        root_w = huber_root_weights(at_theta)
        r = at_theta * root_w
        cost = float(r @ r)
        # The Jacobian's transpose: each parameter's column is written as one contiguous row (written down a
        # column of the Jacobian, strided by the parameter count, it took ten times longer).
        # Written in place: the temporaries of a 300,000-row residual cost as much as the products.
        jac_t = np.empty((len(free), r.size))
        for row, k in zip(jac_t, free):
            t = theta.copy()
            # Step inwards at an upper bound so the difference stays inside the box.
            h = step[k] if theta[k] + step[k] <= hi[k] else -step[k]
            t[k] += h
            np.subtract(plain(t), at_theta, out=row)
            row *= root_w
            row /= h
        jtj, jtr = np.zeros((theta.size, theta.size)), np.zeros(theta.size)
        jtj[np.ix_(free, free)], jtr[free] = jac_t @ jac_t.T, jac_t @ r
        improved, shrink = False, 0.0
        for _ in range(6):
            a = jtj + lam * np.diag(np.maximum(np.diag(jtj), 1e-12))
            try:
                delta = -np.linalg.solve(a, jtr)
            except np.linalg.LinAlgError:
                delta = -np.linalg.lstsq(a, jtr, rcond=None)[0]
            cand = np.clip(theta + delta, lo, hi)
            at_cand = plain(cand)
            rc = at_cand * root_w
            c = float(rc @ rc)
            if np.isfinite(c) and c < cost:
                shrink = (cost - c) / max(cost, 1e-30)
                theta, at_theta, lam = cand, at_cand, max(lam / 3, 1e-7)
                improved = True
                break
            lam *= 4
        if not improved or shrink < 1e-5:
            break
    if not np.all(np.isfinite(theta)):
        raise FloatingPointError("parameters became NaN")
    return theta, at_theta


def huber_rms(r: np.ndarray, k: float) -> float:
    """√ of the mean of twice Huber's loss at scale ``k`` (``r²`` within it, ``2k|r| − k²`` beyond): the robust
    fit's RMSE, comparable between two fits of the same pixels at the same ``k`` (IRLS's weighted squares are not:
    each fit has its own weights)."""
    a = np.abs(r)
    loss = a * a if k <= 0 else np.where(a <= k, a * a, 2 * k * a - k * k)
    return float(np.sqrt(np.mean(loss))) if r.size else 0.0


def _fit_pixels(data: GapData, seed: int = 0) -> np.ndarray:
    flat = np.flatnonzero(data.mask.ravel())
    if len(flat) > FIT_PIXELS:
        flat = np.sort(np.random.default_rng(seed).choice(flat, FIT_PIXELS, replace=False))
    return flat


def fit_composite(data: GapData, names: tuple[str, ...], *, start: dict[str, np.ndarray] | None = None,
                  iterations: int = 15, hold: tuple[str, ...] = ()) -> Fit:
    """Fit the composite of ``names`` on the fit patterns (starting from ``start`` where given).

    Nested parameters (``EffectModel.nested``) are first held at their identity values; they are then freed from
    that fit's answer and kept only if they lower the fit patterns' robust MSE by :data:`NESTED_GAIN`. Those of the
    models in ``hold`` stay held (not tried free).
    """
    comp = Composite(data, names)
    held = [comp.slices[n].start + k for n in comp.names for k in MODELS[n].nested]
    if not held:
        return _fit_box(data, comp, start)
    lo, hi = comp.bounds()
    ident = np.concatenate([np.asarray(MODELS[n].identity, float) for n in comp.names])
    stay = [comp.slices[n].start + k for n in comp.names if n in hold for k in MODELS[n].nested]
    tried = [k for k in held if k not in stay]
    simple = _fit_box(data, comp, start, pinned=held, iterations=iterations)
    if simple.error is not None or not tried:
        return simple
    free = _fit_box(data, comp, {n: simple.theta[comp.slices[n]] for n in comp.names},
                    iterations=iterations, pinned=stay, nudge={k: ident[k] + 0.01 * (hi[k] - lo[k]) for k in tried},
                    loss_scale=simple.loss_scale)
    if free.error is None and free.fit_rmse ** 2 < (1.0 - NESTED_GAIN) * simple.fit_rmse ** 2:
        free.seconds += simple.seconds
        return free
    simple.seconds += free.seconds
    return simple


def _fit_box(data: GapData, comp: Composite, start: dict[str, np.ndarray] | None, *, iterations: int = 15,
             pinned: list[int] | None = None, nudge: dict[int, float] | None = None,
             loss_scale: float | None = None) -> Fit:
    """Bounded Levenberg–Marquardt under Huber's loss; ``pinned`` parameters stay at their identity values,
    ``nudge`` moves some starting values (off an identity that another fit left them at); ``loss_scale``: the Huber
    scale its ``fit_rmse`` is measured at (default: its own residual's), to compare it with another fit's."""
    t0 = time.perf_counter()
    theta = comp.initial()
    for n, v in (start or {}).items():
        if n in comp.slices:
            theta[comp.slices[n]] = v
    lo, hi = comp.bounds()
    if pinned:
        ident = np.concatenate([np.asarray(MODELS[n].identity, float) for n in comp.names])
        lo, hi = lo.copy(), hi.copy()
        lo[pinned] = hi[pinned] = ident[pinned]
    for k, v in (nudge or {}).items():
        theta[k] = v
    theta = np.clip(theta, lo, hi)
    if comp.size == 0:
        return _scored(comp.names, theta, rmse(comp, theta, data.fit_index, smooth=False), comp, data,
                       time.perf_counter() - t0)
    pixels = _fit_pixels(data)

    caps = np.concatenate([data.observations[i].capture.reshape(-1, 3)[pixels].ravel() for i in data.fit_index])
    sub = comp.on_pixels(pixels, data.fit_index) if "distortion" not in comp.names else None

    def plain(t: np.ndarray) -> np.ndarray:
        if sub is not None:  # every fit pattern in one prediction
            pred = sub.predict(t, sub.data.observations[sub.data.fit_index[0]]).ravel()
        else:
            pred = np.concatenate([comp.predict(t, data.observations[i]).reshape(-1, 3)[pixels].ravel()
                                   for i in data.fit_index])
        return (pred - caps).astype(np.float64)

    try:
        theta, at_theta = huber_levenberg_marquardt(plain, theta, lo, hi, iterations)
    except (FloatingPointError, ValueError, np.linalg.LinAlgError) as exc:
        return Fit(comp.names, comp.initial(), float("nan"), float("nan"), time.perf_counter() - t0,
                   error=f"{type(exc).__name__}: {exc}")
    k = _huber_scale(at_theta) if loss_scale is None else loss_scale
    return _scored(comp.names, theta, huber_rms(at_theta, k), comp, data, time.perf_counter() - t0, k)


@dataclass
class Selection:
    """The greedy selection: every candidate alone, then each step that added an effect."""

    base: Fit
    alone: dict[str, Fit]  # each candidate fitted alone on top of f̂
    steps: list[dict[str, Any]] = field(default_factory=list)  # {"added", "before", "after", "share", "ranking"}
    selected: list[str] = field(default_factory=list)
    final: Fit | None = None
    min_share: float = MIN_SHARE


class _Scored(Protocol):
    error: str | None
    seconds: float

    def share_of(self, before: Any) -> float: ...


C = TypeVar("C", bound=Hashable)
F = TypeVar("F", bound=_Scored)


def greedy_rounds(base: F, candidates: list[C], fit: Callable[[list[C], C, F], F], *, max_effects: int,
                  min_share: float, say: Callable[[float, C, list[C]], None], cancel: Cancel | None,
                  record: Callable[[C, F, F, float, list[tuple[C, float]]], dict[str, Any]]
                  ) -> tuple[list[C], F, dict[C, F], list[dict[str, Any]]]:
    """Greedy forward selection: each round fits every remaining candidate beside those selected (``fit(selected,
    candidate, current)``) and adds the one that removes most of the held-out error left, while it removes at least
    ``min_share`` of it. Returns the selected, the last fit, each candidate fitted alone (the first round) and each
    round's record (``record(best, best_fit, current, share, ranking)`` with "candidate", "added" set here);
    ``say(fraction of max_effects rounds done, candidate, selected)`` as each candidate's fit ends. One projector's
    selection and the joint one of several (``gap/shared.py``) run this same loop. A round's fits run side by side
    (:func:`.parallel.run_fits`), the slowest of the last round first; they do not depend on each other, so the
    answer is the same as one after the other."""
    selected: list[C] = []
    alone: dict[C, F] = {}
    steps: list[dict[str, Any]] = []
    current, remaining = base, list(candidates)
    took: dict[C, float] = {}
    for step in range(max_effects):
        def done(i: int, finished: int, count: int = len(remaining), at: int = step) -> None:
            say((at + finished / count) / max_effects, remaining[i], selected)

        order = sorted(range(len(remaining)), key=lambda i: -took.get(remaining[i], 0.0))
        results = run_fits([partial(fit, list(selected), c, current) for c in remaining], cancel=cancel,
                           done=done, order=order)
        fits = dict(zip(remaining, results))
        took = {c: f.seconds for c, f in fits.items()}
        if step == 0:
            alone.update(fits)
        ranking = sorted((c for c in fits if fits[c].error is None), key=lambda c: -fits[c].share_of(current))
        if not ranking:
            break
        best = fits[ranking[0]]
        share = best.share_of(current)
        rec = record(ranking[0], best, current, share, [(c, fits[c].share_of(current)) for c in ranking])
        steps.append({"added": rec["candidate"] if share >= min_share else None, **rec})
        if share < min_share:
            break
        selected.append(ranking[0])
        current = best
        remaining.remove(ranking[0])
        if not remaining:
            break
    return selected, current, alone, steps


def select_effects(data: GapData, candidates: tuple[str, ...] = NAMES, *, min_share: float = MIN_SHARE,
                   max_effects: int = MAX_EFFECTS, progress: Progress | None = None,
                   cancel: Cancel | None = None) -> Selection:
    """Greedy forward selection on held-out RMSE (see the module docstring)."""
    report = progress or (lambda msg, frac: None)
    base = fit_composite(data, ())
    todo = [c for c in candidates if c in MODELS]

    def fit(selected: list[str], name: str, current: Fit) -> Fit:
        start = current.params() if selected else {}
        names = tuple(selected) + (name,)
        # A selected effect whose nested parameters its own round left at identity (its fit with them free was no
        # better) keeps them there in later rounds: tried free again beside each later candidate, they doubled
        # every fit of those rounds and were kept in none (the demo's set, a response and blur set), except beside
        # the camera's tone curve, which the response's S-curve trades against (on a two-projector demo set the
        # fit with both curves kept the S-curve, and the camera's curve then removed less than the threshold).
        hold = current.nested_held() if selected and not any(n in names for n in TRADES_WITH_NESTED) else ()
        return fit_composite(data, names, start={n: np.array(list(v.values())) for n, v in start.items()}, hold=hold)

    def say(fraction: float, name: str, selected: list[str]) -> None:
        report(f"round {len(selected) + 1}: fitted {'+'.join([*selected, name])}", fraction)

    def record(name: str, best: Fit, current: Fit, share: float, ranking: list[tuple[str, float]]
               ) -> dict[str, Any]:
        return {"candidate": name, "before": current.held_rmse, "after": best.held_rmse, "share": share,
                "before_raw": current.held_rmse_raw, "after_raw": best.held_rmse_raw, "ranking": ranking}

    selected, final, alone, steps = greedy_rounds(base, todo, fit, max_effects=max_effects, min_share=min_share,
                                                  say=say, cancel=cancel, record=record)
    return Selection(base, alone, steps, selected, final, min_share)


def compensation_subset(data: GapData, sel: Selection, usable: tuple[str, ...], *, min_share: float = MIN_SHARE,
                        leave_out: dict[str, str] | None = None,
                        held: dict[str, str] | None = None) -> tuple[list[str], dict[str, str]]:
    """The selected effects compensation should invert, and why each other selected effect is left out.

    Compensation inverts only ``usable`` effects, so its model is f̂ with those
    alone, at the parameters fitted together with all the selected ones. An
    effect fitted to share the residual with one compensation cannot invert can
    be wrong without it (on the plane with a glossy surface, a 3 % gamma fitted
    beside the glossy lobe cost 0.18 dB). So the usable effects are eliminated
    backwards on that model: each must still remove ``min_share`` of the
    held-out error the others leave. ``leave_out`` names effects left out
    before that, with the reason; ``held`` names effects stage C holds
    another way (its θ holds a black level): not inverted, but part of the
    model every candidate is scored on (without the demo's ambient black level
    in it, its response and crosstalk removed only 0–2 % of what was left).
    """
    final = sel.final or sel.base
    params = {n: np.array(list(v.values())) for n, v in final.params().items()} if sel.selected else {}
    dropped = {n: "compensation cannot invert it" for n in sel.selected if n not in usable}
    dropped.update((n, why) for n, why in (leave_out or {}).items() if n in sel.selected and n not in dropped)
    held = {n: why for n, why in (held or {}).items() if n in sel.selected and n not in dropped}
    keep = [n for n in sel.selected if n not in dropped and n not in held]

    def scored(names: list[str]) -> Fit:
        comp = Composite(data, tuple(names) + tuple(held))
        theta = comp.initial()
        for n in comp.names:
            theta[comp.slices[n]] = params[n]
        return _scored(comp.names, theta, float("nan"), comp, data, 0.0)

    while keep:
        with_all = scored(keep)
        gains = {n: with_all.share_of(scored([m for m in keep if m != n])) for n in keep}
        weakest = min(keep, key=lambda n: gains[n])
        if gains[weakest] >= min_share:  # (alone, the gain is over f̂ itself)
            break
        dropped[weakest] = (f"without the effects compensation cannot invert, it removes only "
                            f"{max(gains[weakest], 0.0):.0%} of the held-out error (< {min_share:.0%})")
        keep.remove(weakest)
    return keep, {**dropped, **held}
