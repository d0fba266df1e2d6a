"""The camera's and the surface's effects of a rig of several projectors, fitted once across every projector's patterns.

One camera photographs every projector's patterns, on one surface: its tone curve
or lens, the surface's gloss or bounce light are the same in every projector's
captures. Each projector's own diagnosis (``diagnose`` on its patterns) can only
fit them separately, and may explain the camera's curve by a tone curve of its
projector instead. Here one parameter vector holds the shared effects
(:data:`SHARED_EFFECTS`, fitted once) and each projector its own
(:data:`PROJECTOR_EFFECTS`), and the residual is every projector's fit pixels
together (bounded Levenberg–Marquardt under Huber's loss, as :mod:`.fit`).

Selection is greedy on the held-out patterns of all projectors (the MSE of each
pixel class averaged over the projectors): a shared effect explains every
projector's residual at once, so it wins against a tone curve fitted on one
projector alone when the camera is the cause, and a projector's own effect is
added only where the shared ones leave it something to remove. The pool is
what the projectors' own diagnoses found: the shared effects whose model alone
removed at least the selection's share on some projector, and per projector the
projector effects its diagnosis selected.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np

from ..progress import Cancel, Progress
from .data import GapData
from .fit import MIN_SHARE, FIT_PIXELS, greedy_rounds, huber_levenberg_marquardt, huber_rms, _huber_scale, scores
from .models import MODELS, NAMES, Composite, describe_params
from .parallel import run_fits

#: The camera's effects (its processing and its lens) and the surface's (its gloss, bounce light and shape): every
#: projector's at once.
CAMERA_EFFECTS = ("camera_response", "distortion")
SURFACE_EFFECTS = ("interreflection", "glossy", "depth_noise")
SHARED_EFFECTS = CAMERA_EFFECTS + SURFACE_EFFECTS
#: The effects of one projector's lamp, lens and electronics: each projector's own.
PROJECTOR_EFFECTS = ("response", "crosstalk", "black_level", "vignetting", "defocus")
#: How a shared effect is said to a crew, by whose it is.
WHOSE = {"camera_response": "the camera's tone curve", "distortion": "the camera's lens distortion",
         "interreflection": "the surface's bounce light", "glossy": "the surface's gloss",
         "depth_noise": "the surface's depth error"}


@dataclass(frozen=True)
class Item:
    """One candidate of the joint selection: a shared effect (``projector`` None) or one projector's own."""

    name: str
    projector: int | None = None

    def label(self) -> str:
        return WHOSE.get(self.name, self.name) if self.projector is None else \
            f"projector {self.projector + 1}'s {self.name.replace('_', ' ')}"


@dataclass
class JointFit:
    """Shared and per-projector effects fitted together; held-out scores of every projector."""

    items: tuple[Item, ...]
    shared: dict[str, np.ndarray]
    own: list[dict[str, np.ndarray]]
    held_mse_classes: tuple[float, float]
    held_rmse: float
    fit_rmse: float
    seconds: float
    error: str | None = None

    def share_of(self, before: JointFit) -> float:
        if self.error is not None:
            return float("-inf")
        shares = [(b - a) / b for b, a in zip(before.held_mse_classes, self.held_mse_classes) if b > 0]
        return float(max(shares)) if shares else 0.0

    def params_of(self, k: int) -> dict[str, dict[str, float]]:
        """Projector ``k``'s effects, shared ones included, as a diagnosis writes them."""
        both = {**self.shared, **self.own[k]}
        return {n: describe_params(n, v) for n, v in both.items()}


def _layout(items: tuple[Item, ...], count: int) -> tuple[list[tuple[str, ...]], dict[Item, slice], int]:
    names = [tuple(n for n in NAMES if any(i.name == n and i.projector in (None, k) for i in items))
             for k in range(count)]
    slices, at = {}, 0
    for item in items:
        size = len(MODELS[item.name].params)
        slices[item] = slice(at, at + size)
        at += size
    return names, slices, at


def fit_joint(datas: list[GapData], items: tuple[Item, ...], *, start: dict[Item, np.ndarray] | None = None,
              iterations: int = 15, pixels: int = FIT_PIXELS // 2) -> JointFit:
    """Fit ``items`` on every projector's fit patterns at once (``pixels`` random lit pixels a pattern of each)."""
    t0 = time.perf_counter()
    count = len(datas)
    names, slices, size = _layout(items, count)
    comps = [Composite(d, n) for d, n in zip(datas, names)]
    theta = np.concatenate([MODELS[i.name].initial() for i in items]) if items else np.zeros(0)
    lo = np.concatenate([MODELS[i.name].lower for i in items]).astype(float) if items else np.zeros(0)
    hi = np.concatenate([MODELS[i.name].upper for i in items]).astype(float) if items else np.zeros(0)
    for item, v in (start or {}).items():
        if item in slices:
            theta[slices[item]] = v
    theta = np.clip(theta, lo, hi)

    def per_projector(t: np.ndarray, k: int) -> np.ndarray:
        comp = comps[k]
        out = comp.initial()
        for item in items:
            if item.projector in (None, k):
                out[comp.slices[item.name]] = t[slices[item]]
        return out

    rng = np.random.default_rng(0)
    subs, picks, caps = [], [], []
    for d, comp in zip(datas, comps):
        flat = np.flatnonzero(d.mask.ravel())
        if len(flat) > pixels:
            flat = np.sort(rng.choice(flat, pixels, replace=False))
        picks.append(flat)
        subs.append(comp.on_pixels(flat, d.fit_index) if "distortion" not in comp.names else None)
        caps.append(np.concatenate([d.observations[i].capture.reshape(-1, 3)[flat].ravel() for i in d.fit_index]))
    cap = np.concatenate(caps)

    # Each projector's prediction kept with the parameters it was made for: a finite-difference column of one
    # projector's own effect changes that projector's prediction alone, and the others' are reused as they are.
    last: list[tuple[np.ndarray, np.ndarray] | None] = [None] * count

    def predicted(k: int, tk: np.ndarray) -> np.ndarray:
        kept = last[k]
        if kept is not None and np.array_equal(kept[0], tk):
            return kept[1]
        d, comp, sub, flat = datas[k], comps[k], subs[k], picks[k]
        if sub is not None:  # every fit pattern of this projector in one prediction
            pred = sub.predict(tk, sub.data.observations[sub.data.fit_index[0]]).ravel()
        else:
            pred = np.concatenate([comp.predict(tk, d.observations[i]).reshape(-1, 3)[flat].ravel()
                                   for i in d.fit_index])
        last[k] = (tk, pred)
        return pred

    def plain(t: np.ndarray) -> np.ndarray:
        return (np.concatenate([predicted(k, per_projector(t, k)) for k in range(count)]) - cap).astype(np.float64)

    error = None
    at_theta = plain(theta)
    try:
        theta, at_theta = huber_levenberg_marquardt(plain, theta, lo, hi, iterations if size else 0)
    except (FloatingPointError, ValueError, np.linalg.LinAlgError) as exc:
        error = f"{type(exc).__name__}: {exc}"
    # held-out: each pixel class's structured MSE averaged over the projectors, so each projector counts alike
    classes = [scores(comp, per_projector(theta, k), d.held_index) for k, (d, comp) in enumerate(zip(datas, comps))]
    flat_mse = float(np.mean([c["classes"][0] for c in classes]))
    edge_mse = float(np.mean([c["classes"][1] for c in classes]))
    held = float(np.sqrt(np.mean([c["structured"] ** 2 for c in classes])))
    shared = {i.name: np.asarray(theta[slices[i]], float) for i in items if i.projector is None}
    own: list[dict[str, np.ndarray]] = [{} for _ in range(count)]
    for i in items:
        if i.projector is not None:
            own[i.projector][i.name] = np.asarray(theta[slices[i]], float)
    return JointFit(items, shared, own, (flat_mse, edge_mse), held, huber_rms(at_theta, _huber_scale(at_theta)),
                    time.perf_counter() - t0, error)


@dataclass
class JointSelection:
    """The greedy joint selection: its start (nothing), each round's ranking, and the last fit."""

    base: JointFit
    final: JointFit
    selected: list[Item] = field(default_factory=list)
    steps: list[dict[str, Any]] = field(default_factory=list)
    pool: list[Item] = field(default_factory=list)
    #: each candidate fitted alone on every projector's patterns (the first round)
    alone: dict[Item, JointFit] = field(default_factory=dict)

    @property
    def shared(self) -> list[str]:
        return [i.name for i in self.selected if i.projector is None]

    def own(self, k: int) -> list[str]:
        return [i.name for i in self.selected if i.projector == k]


def pool_of(docs: list[dict[str, Any]], candidates: tuple[str, ...], min_share: float = MIN_SHARE) -> list[Item]:
    """The joint selection's candidates from each projector's own diagnosis (module doc)."""
    shared: list[str] = []
    for d in docs:
        for e in d.get("effects") or []:
            if isinstance(e, dict) and e.get("name") in SHARED_EFFECTS and e.get("name") in candidates and \
                    not e.get("error") and float(e.get("reduction") or 0.0) >= min_share:
                shared.append(str(e["name"]))
        shared += [str(n) for n in d.get("modelled") or [] if n in SHARED_EFFECTS and n in candidates]
    items = [Item(n) for n in NAMES if n in shared]
    for k, d in enumerate(docs):
        items += [Item(n, k) for n in NAMES if n in (d.get("modelled") or []) and n in PROJECTOR_EFFECTS]
    return items


def select_joint(datas: list[GapData], pool: list[Item], *, min_share: float = MIN_SHARE, max_effects: int = 6,
                 progress: Progress | None = None, cancel: Cancel | None = None) -> JointSelection:
    """Greedy forward selection of ``pool`` on every projector's held-out patterns (module doc)."""
    report = progress or (lambda msg, frac: None)
    base = fit_joint(datas, ())

    def fit(selected: list[Item], item: Item, current: JointFit) -> JointFit:
        start = {i: v for i in selected
                 for v in [current.shared.get(i.name) if i.projector is None else
                           current.own[i.projector].get(i.name)] if v is not None}
        return fit_joint(datas, tuple(selected) + (item,), start=start)

    def say(fraction: float, item: Item, selected: list[Item]) -> None:
        report(f"every projector's patterns, round {len(selected) + 1}: {item.label()}", fraction)

    def record(item: Item, best: JointFit, current: JointFit, share: float, ranking: list[tuple[Item, float]]
               ) -> dict[str, Any]:
        return {"candidate": item.label(), "share": round(share, 4), "before": current.held_rmse,
                "after": best.held_rmse, "ranking": [[i.label(), round(s, 4)] for i, s in ranking]}

    selected, final, alone, steps = greedy_rounds(base, list(pool), fit, max_effects=max_effects,
                                                  min_share=min_share, say=say, cancel=cancel, record=record)
    return JointSelection(base, final, selected, steps, list(pool), alone)


def attribution_fit(datas: list[GapData], sel: JointSelection) -> JointFit:
    """The shared effects selected with every projector effect any projector selected, free on every projector:
    what each projector's parameters are compared on (its own effects measured with the camera's taken out)."""
    own = sorted({i.name for i in sel.selected if i.projector is not None}, key=NAMES.index)
    items = tuple(Item(n) for n in sel.shared) + tuple(Item(n, k) for k in range(len(datas)) for n in own)
    start = {i: v for i in items for v in [sel.final.shared.get(i.name) if i.projector is None
                                           else sel.final.own[i.projector].get(i.name)] if v is not None}
    return fit_joint(datas, items, start=start) if own else sel.final


@dataclass
class WhoseEffect:
    """One projector effect fitted beside the shared effects (and every other projector effect selected, free on
    every projector) four ways: on no projector (``none``), on projector k alone (``alone[k]``, each in turn), on
    every projector apart (``every``) and alike on every projector, one parameter vector (``tied``). Which
    projector's effect it is, is then a comparison of held-out errors, not of fitted parameters: where a shared
    effect and one projector's trade along a direction the patterns cannot tell apart (a camera curve and a tone
    curve), the parameters can lie anywhere along it, the error cannot move."""

    name: str
    none: JointFit
    alone: list[JointFit]
    every: JointFit
    #: one parameter vector for every projector's effect: the effect alike on all
    tied: JointFit

    def differ(self) -> float:
        """What the effect fitted apart on each projector removes beyond one fit for all (``tied``), as a share of
        ``none``'s held-out error (the larger pixel class): whether the projectors differ by it at all."""
        return self._beyond(self.tied, self.every)

    def _beyond(self, fewer: JointFit, more: JointFit) -> float:
        # on the scale of what each removes from ``none``, so a small error left after both does not make a small
        # difference large (the larger of the two pixel classes, as JointFit.share_of)
        if fewer.error is not None or more.error is not None:
            return float("nan")
        shares = [(a - e) / b for b, a, e in zip(self.none.held_mse_classes, fewer.held_mse_classes,
                                                  more.held_mse_classes) if b > 0]
        return float(max(shares)) if shares else 0.0

    def short(self, k: int) -> float:
        """What the effect on every projector removes beyond it on projector ``k`` alone, as a share of ``none``'s
        held-out error."""
        return self._beyond(self.alone[k], self.every)

    def record(self) -> dict[str, Any]:
        """The comparison as ``gap.json`` keeps it: the share of ``none``'s held-out error that the effect on each
        projector alone removes (``alone``), on every projector (``every``), how far each projector alone falls
        short of every projector (``short``, :meth:`short`), each fit's held-out RMSE and the fits' seconds."""
        fits = (self.none, *self.alone, self.every, self.tied)
        return {"effect": self.name,
                "alone": [round(f.share_of(self.none), 4) for f in self.alone],
                "every": round(self.every.share_of(self.none), 4),
                "tied": round(self.tied.share_of(self.none), 4),
                "differ": round(self.differ(), 4),
                "short": [round(self.short(k), 4) for k in range(len(self.alone))],
                "held_rmse": {"none": round(self.none.held_rmse, 6),
                              "alone": [round(f.held_rmse, 6) for f in self.alone],
                              "every": round(self.every.held_rmse, 6), "tied": round(self.tied.held_rmse, 6)},
                # the held-out MSE of each pixel class (smooth parts, pattern edges): every share above comes from them
                "mse_classes": {"none": [round(float(v), 8) for v in self.none.held_mse_classes],
                                "alone": [[round(float(v), 8) for v in f.held_mse_classes] for f in self.alone],
                                "every": [round(float(v), 8) for v in self.every.held_mse_classes],
                                "tied": [round(float(v), 8) for v in self.tied.held_mse_classes]},
                "seconds": round(sum(f.seconds for f in (self.none, *self.alone, self.tied)), 2),
                "errors": [f.error for f in fits if f.error is not None]}


def whose_effects(datas: list[GapData], sel: JointSelection, *, leave_out: tuple[str, ...] = (),
                  progress: Progress | None = None, cancel: Cancel | None = None
                  ) -> tuple[JointFit, list[WhoseEffect]]:
    """:func:`attribution_fit` (every projector effect selected, free on every projector), and for each of those
    effects but ``leave_out`` a :class:`WhoseEffect`: 1 + E·(N + 2) joint fits for E effects and N projectors.

    Every fit starts where the joint selection ended (an effect it did not select on a projector from the model's
    start), so no projector's fit starts from a point another fit pushed along a degenerate direction."""
    report = progress or (lambda msg, frac: None)
    count = len(datas)
    own = [n for n in NAMES if any(i.name == n and i.projector is not None for i in sel.selected)]
    todo = [n for n in own if n not in leave_out]
    start = {**{Item(n): v for n, v in sel.final.shared.items()},
             **{Item(n, k): v for k in range(count) for n, v in sel.final.own[k].items()}}
    # the attribution fit (the most parameters: first, so both cores stay busy to the end) beside the others
    jobs: list[Callable[[], JointFit]] = [partial(attribution_fit, datas, sel)]
    labels = ["every projector effect on every projector"]
    for name in todo:
        base = tuple(Item(n) for n in sel.shared) + tuple(Item(n, k) for k in range(count) for n in own
                                                           if n != name)
        # on no projector, on each alone, and one vector for all (a projector effect as a shared item)
        for k in [None, *range(count), -1]:
            items = base if k is None else base + (Item(name, k if k >= 0 else None),)
            jobs.append(partial(fit_joint, datas, items, start={i: v for i, v in start.items() if i in items}))
            labels.append(f"whose {name.replace('_', ' ')}: " + ("on no projector" if k is None else
                                                                  "alike on every one" if k < 0 else
                                                                  f"on projector {k + 1} alone"))

    def done(i: int, finished: int) -> None:
        report(labels[i], finished / len(jobs))

    every, *fits = run_fits(jobs, cancel=cancel, done=done)
    per = count + 2
    out = [WhoseEffect(name, fits[j * per], fits[j * per + 1:j * per + per - 1], every, fits[j * per + per - 1])
           for j, name in enumerate(todo)]
    return every, out


__all__ = ["CAMERA_EFFECTS", "Item", "JointFit", "JointSelection", "PROJECTOR_EFFECTS", "SHARED_EFFECTS",
           "SURFACE_EFFECTS", "WHOSE", "WhoseEffect", "attribution_fit", "fit_joint", "pool_of", "select_joint",
           "whose_effects"]
