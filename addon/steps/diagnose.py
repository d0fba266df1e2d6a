"""The diagnose step: where and why the calibrated simulation still differs from the captures, into a folder.

The folder, written atomically: ``gap.json`` (residual, effects ranked and
selected, regions, evidence of absorbed effects, what ``--effects auto``
inverts), the residual maps and the region overlay as PNG (the raw maps as
EXR), and ``summary.md``, a one-page report with the images. The analysis is
:mod:`..gap.diagnose`'s; this module reads the calibration and its capture
set and writes what it found.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ProCamError
from ..gap.compensation import HELD_BY_STAGE_C, PROJECTOR_SIDE, SHARED_EFFECT
from ..gap.data import DiagnosisError
from ..gap.diagnose import diagnose, summary_markdown
from ..gap.fit import MAX_EFFECTS, MIN_SHARE
from ..gap.models import MODELS, NAMES, describe_params
from ..gap import shared
from ..gap.overlap import overlap_falloffs
from ..imageio import kept_decoded, write_atomic_bytes, write_image
from ..options import option, validate
from ..outputs import AtomicFolder, check_replaceable, write_manifest, writer_lock
from ..progress import Cancel, Progress, part, quiet
from . import calibrate as calibrate_step
from . import layout
from .summary import Summary, cached, fmt

KIND = layout.DIAGNOSIS


@dataclass(frozen=True)
class DiagnoseOptions:
    """What ``procam diagnose`` and the Diagnose button ask for; each field declares its option once
    (addon/options.py)."""

    calibration: Path
    out: Path
    effects: str = option("all", help=f"candidate effect models, comma-separated, or 'all' (default): "
                                      f"{', '.join(NAMES)}")
    scale: float = option(0.5, min=0.05, max=1.0, label="Working Scale", prop="procam_diagnosis_scale",
                          help="working resolution as a share of the camera image: 1 sees a projector blur of about "
                               "a texel that 0.5 can miss (slower)")
    spp: int = option(32, min=1, help="samples per pixel of the model renders")
    min_share: float = option(MIN_SHARE, min=0.0, max=1.0,
                              help="an effect is selected only if it removes at least this share of the held-out "
                                   "RMSE left")
    max_effects: int = option(MAX_EFFECTS, min=1, soft_max=8, label="Max Effects",
                              help="effects selected at most: rounds of the greedy selection, each slower than the "
                                   "last")
    force: bool = False

    def candidates(self) -> tuple[str, ...]:
        if self.effects.strip().lower() in ("all", "auto", ""):
            return NAMES
        names = tuple(n.strip() for n in self.effects.split(",") if n.strip())
        bad = [n for n in names if n not in NAMES]
        if bad:
            raise ProCamError(f"unknown effect model(s) {', '.join(bad)}; known: {', '.join(NAMES)}")
        return names

    def check(self) -> None:
        validate(self)
        self.candidates()


def run(options: DiagnoseOptions, progress: Progress | None = None, cancel: Cancel | None = None) -> dict[str, Any]:
    """Diagnose the calibration into ``options.out``; returns the ``gap.json`` document."""
    say = progress or quiet
    options.check()
    check_replaceable(options.out, force=options.force, what=KIND.what, replaceable=KIND.holds,
                      inputs=(options.calibration, calibrate_step.capture_set_of(options.calibration)),
                      error=ProCamError)
    # each photograph decoded once for the check, the model's data, the evidence and the session check
    with writer_lock(options.out), kept_decoded():  # another run of this output is refused before any work
        return _run(options, say, cancel)


def _run(options: DiagnoseOptions, say: Progress, cancel: Cancel | None) -> dict[str, Any]:
    cal = calibrate_step.read(options.calibration)
    try:
        captures = calibrate_step.captures_of(cal, verify_images=True)
    except ProCamError as exc:
        raise DiagnosisError(f"{exc}; the diagnosis compares the model with those captures") from None
    folder = AtomicFolder(options.out, force=options.force, what=KIND.what, replaceable=KIND.holds,
                          inputs=(options.calibration, captures.path), error=ProCamError)
    if cal.projector_count > 1:
        try:
            doc = _run_projectors(options, cal, captures, folder.tmp, say, cancel)
        except BaseException:
            folder.abort()
            raise
        folder.commit()
        say("done", 1.0)
        return doc
    try:
        found = diagnose(cal, captures, source=str(Path(options.calibration).absolute()),
                         format=(KIND.format, KIND.version), scale=options.scale, spp=options.spp,
                         candidates=options.candidates(), min_share=options.min_share,
                         max_effects=options.max_effects,
                         progress=part(say, 0.0, 0.98), cancel=cancel)
        write_manifest(folder.tmp / KIND.manifest, found.doc)
        for name, image in found.images.items():
            write_image(folder.tmp / name, image)
        write_atomic_bytes(folder.tmp / layout.DIAGNOSIS_SUMMARY, found.summary.encode())
    except BaseException:
        folder.abort()
        raise
    folder.commit()
    say("done", 1.0)
    return found.doc


def projector_folder(index: int) -> str:
    """The sub-folder of a diagnosis of several projectors that holds projector ``index``'s (0-based) diagnosis."""
    return f"projector_{index + 1}"


#: The effects that belong to a projector (its lamp, lens and electronics): the only ones by which one projector of
#: a rig can differ from another. The camera's (camera_response, distortion) and the surface's (interreflection,
#: glossy, depth_noise) are shared by every projector's patterns, however differently each diagnosis ranks them.
PROJECTOR_EFFECTS = ("response", "crosstalk", "black_level", "vignetting", "defocus")
#: An effect is said to differ on one projector when its fitted parameters lie this far from the other projectors'
#: (the largest parameter difference, as a share of that parameter's range in the model): below it they agree.
DIFFERS_BY = 0.05


def _run_projectors(options: DiagnoseOptions, cal: Any, captures: Any, tmp: Path, say: Progress,
                    cancel: Cancel | None) -> dict[str, Any]:
    """Each projector diagnosed on its own patterns (its calibration view and its captures) into
    ``projector_K/``, and ``gap.json`` saying which projector differs and by which effect."""
    count = cal.projector_count
    docs, datas = [], []
    for k in range(count):
        sub = tmp / projector_folder(k)
        sub.mkdir()
        say(f"projector {k + 1}/{count}", k / count)
        found = diagnose(cal.for_projector(k), captures.for_projector(k),
                         source=str(Path(options.calibration).absolute()), format=(KIND.format, KIND.version),
                         scale=options.scale, spp=options.spp, candidates=options.candidates(),
                         min_share=options.min_share, max_effects=options.max_effects,
                         progress=part(say, 0.98 * k / count, 0.98 * (k + 0.5) / count, f"projector {k + 1}: "),
                         cancel=cancel)
        write_manifest(sub / KIND.manifest, found.doc)
        for name, image in found.images.items():
            write_image(sub / name, image)
        write_atomic_bytes(sub / layout.DIAGNOSIS_SUMMARY, found.summary.encode())
        docs.append(found.doc)
        datas.append(found.data)
    say("the overlaps: each projector's vignetting, which calibration took into the albedo", 0.99)
    falloffs = overlap_falloffs(cal, captures)
    joint = joint_effects([d for d in datas if d is not None], docs, options.candidates(),
                          min_share=options.min_share, max_effects=options.max_effects, cancel=cancel,
                          progress=part(say, 0.98 * (count - 0.5) / count, 0.99, "the camera: "),
                          falloffs_measured=_measured(falloffs, count)) \
        if all(d is not None for d in datas) else None
    for k, d in enumerate(docs):  # each projector's diagnosis says what compensation of the rig inverts for it
        d["compensation"] = rig_compensation(d, joint, k)
        d["headline"] = rig_headline(d)
        sub = tmp / projector_folder(k)
        write_manifest(sub / KIND.manifest, d)
        write_atomic_bytes(sub / layout.DIAGNOSIS_SUMMARY, summary_markdown(d).encode())
    verdict = attribute(docs, falloffs)
    if joint is not None:
        # the camera's (or surface's) part fitted once, each projector effect is judged by how well it predicts
        # held-out patterns on one projector alone: a camera curve one projector's diagnosis took for its tone
        # curve is no difference, nor is a tone curve traded against the camera's along a degenerate direction
        verdict = attribute_held_out(joint["whose"], min_share=options.min_share,
                                     params=attribute(joint["attribution_docs"], falloffs))
        if joint["shared"]:
            verdict["headline"] = shared_sentence(joint, count) + " " + verdict["headline"]
    doc = {"format": KIND.format, "version": KIND.version, "source": str(Path(options.calibration).absolute()),
           # which calibration the effects were fitted on: compensation with them refuses another
           "calibration_sha256": calibrate_step.identity(options.calibration)["sha256"],
           "projector_count": count, **verdict, "overlap_vignetting": falloffs,
           "joint": None if joint is None else {k: v for k, v in joint.items()
                                                if k not in ("attribution_docs", "whose")},
           "projectors": [{"folder": projector_folder(k), "headline": d.get("headline"),
                           "selected": d.get("selected") or [], "residual": d.get("residual"),
                           "residual_after": d.get("residual_after")} for k, d in enumerate(docs)]}
    write_manifest(tmp / KIND.manifest, doc)
    lines = [f"# ProCam sim-to-real diagnosis of {count} projectors", "", f"**{doc['headline']}**", ""]
    if joint is not None:
        lines += [f"Fitted once on every projector's patterns: {', '.join(joint['shared']) or 'no shared effect'}; "
                  f"held-out RMSE of all projectors {joint['residual']:.4f} → {joint['residual_after']:.4f}.", ""]
    lines += [f"- projector {k + 1}: {d.get('headline')} ([details]({projector_folder(k)}/{layout.DIAGNOSIS_SUMMARY}))"
              for k, d in enumerate(docs)]
    write_atomic_bytes(tmp / layout.DIAGNOSIS_SUMMARY, ("\n".join(lines) + "\n").encode())
    return doc


#: The shared effects ``--effects auto`` inverts for several projectors: the camera's tone curve, taken out of the
#: target and of every capture (``gap/compensation.py`` SharedCamera). The others are reported, not inverted.
SHARED_INVERTED = ("camera_response",)
SHARED_LEFT_OUT = {
    "distortion": "the display area is not remapped; θ absorbs the shift",
    "interreflection": "stage C already simulates the first bounce",
    "glossy": "the highlight's clipped white is one projector's view; not inverted for several projectors",
    "depth_noise": "the surface is not moved for several projectors; θ holds what it leaves"}


def joint_effects(datas: list[Any], docs: list[dict[str, Any]], candidates: tuple[str, ...], *, min_share: float,
                  max_effects: int, progress: Progress, cancel: Cancel | None,
                  falloffs_measured: bool = False) -> dict[str, Any]:
    """The camera's and the surface's effects fitted once on every projector's patterns, each projector's own
    beside them (:mod:`..gap.shared`): what was selected, the parameters, what ``--effects auto`` inverts, and
    each projector's own effects as a diagnosis document (for :func:`attribute`)."""
    pool = shared.pool_of(docs, candidates, min_share)
    sel = shared.select_joint(datas, pool, min_share=min_share, max_effects=max_effects, progress=progress,
                              cancel=cancel)
    # the vignetting is judged in the overlaps where they measure it (calibration took it into the albedo)
    fit, whose = shared.whose_effects(datas, sel, leave_out=("vignetting",) if falloffs_measured else (),
                                      cancel=cancel)
    final = sel.final
    params = {n: describe_params(n, v) for n, v in final.shared.items()}
    own = [{n: describe_params(n, v) for n, v in final.own[k].items()} for k in range(len(datas))]
    attribution_docs = [{"modelled": sel.own(k), "selected": sel.own(k),
                         "effects": [{"name": n, "params": describe_params(n, v)} for n, v in fit.own[k].items()]}
                        for k in range(len(datas))]
    return {"pool": [i.label() for i in sel.pool], "shared": sel.shared,
            "shared_says": {n: shared.WHOSE[n] for n in sel.shared},
            "params": params, "projectors": [{"selected": sel.own(k), "params": own[k]} for k in range(len(datas))],
            "steps": sel.steps, "residual": round(sel.base.held_rmse, 6), "residual_after": round(final.held_rmse, 6),
            "fitted_alone": {i.name: describe_params(i.name, f.shared[i.name]) for i, f in sel.alone.items()
                             if i.projector is None and f.error is None},
            "compensation": {"shared": {n: v for n, v in params.items() if n in SHARED_INVERTED},
                             "projectors": [{n: v for n, v in own[k].items() if n not in HELD_BY_STAGE_C}
                                            for k in range(len(datas))],
                             "left_out": {n: SHARED_LEFT_OUT[n] for n in sel.shared if n in SHARED_LEFT_OUT}},
            "whose": [w.record() for w in whose], "attribution_docs": attribution_docs}


def rig_compensation(doc: dict[str, Any], joint: dict[str, Any] | None, k: int) -> dict[str, Any]:
    """What compensation of the whole rig with ``--effects auto`` inverts for projector ``k`` (0-based), as
    ``steps/projectors.py`` reads this diagnosis: its own projector effects (:data:`PROJECTOR_SIDE`) as the fit on
    every projector's patterns kept them (``joint``; without it, as its own diagnosis selected them), the camera's
    curve of that fit once for every projector; ``effects``, ``params``, ``left_out`` (why the others its own
    diagnosis would invert are not) and ``alone`` (what its own diagnosis alone would invert)."""
    own = doc.get("compensation") or {}
    alone = [str(n) for n in own.get("effects") or []]
    if joint is not None:
        comp = joint.get("compensation") or {}
        params = {n: v for n, v in (comp.get("projectors") or [{}] * (k + 1))[k].items() if n in PROJECTOR_SIDE}
        shared_ones = [str(n) for n in comp.get("shared") or {}]
    else:
        params = {n: v for n, v in (own.get("params") or {}).items() if n in PROJECTOR_SIDE}
        shared_ones = []
    left = dict(own.get("left_out") or {})
    for n in alone:
        if n in params or n in shared_ones:
            continue
        if n in PROJECTOR_SIDE:
            left[n] = ("not selected for this projector when fitted on every projector's patterns together"
                       if joint is not None else "not among its fitted parameters")
        else:
            left[n] = SHARED_LEFT_OUT.get(n, SHARED_EFFECT)
    return {"effects": [*params, *shared_ones], "params": params, "left_out": left, "alone": alone}


#: The advice of a one-projector headline (gap/diagnose.py ACTIONS) to invert its effect around stage C.
_INVERT_ADVICE = re.compile(r"(, or |; |: )compensate with --effects auto(, which [^;.]*)?")


def rig_headline(doc: dict[str, Any]) -> str:
    """Projector ``doc``'s headline as compensation of the whole rig reads it: where its own diagnosis advises
    ``--effects auto`` for an effect that the rig's run does not invert for it (``doc['compensation']['left_out']``,
    :func:`rig_compensation`), the advice says so and why instead."""
    text = str(doc.get("headline") or "")
    named = (doc.get("modelled") or [None])[0]
    why = ((doc.get("compensation") or {}).get("left_out") or {}).get(named)
    if not why:
        return text
    return _INVERT_ADVICE.sub(lambda m: f"{'; ' if m.group(1) == ', or ' else m.group(1)}compensation of the rig "
                              f"with --effects auto does not invert it ({why})", text, count=1)


def shared_sentence(joint: dict[str, Any], count: int) -> str:
    """What the rig's projectors share, said once: "The camera's tone curve (curve 0.31) is every projector's …"."""
    parts = []
    for n in joint["shared"]:
        values = ", ".join(f"{k} {v:.2f}" for k, v in (joint["params"].get(n) or {}).items())
        parts.append(f"{shared.WHOSE[n]} ({values})")
    said = ", ".join(parts)
    return (f"{said[0].upper() + said[1:]} {'is' if len(parts) == 1 else 'are'} every projector's, not one "
            f"projector's: fitted once on the {count} projectors' patterns together.")


def _fitted(doc: dict[str, Any]) -> dict[str, np.ndarray]:
    """Each effect's parameters as one projector's diagnosis fitted it alone, in its model's order."""
    out = {}
    for e in doc.get("effects") or []:
        if not isinstance(e, dict) or e.get("error") or e.get("name") not in MODELS:
            continue
        params, model = e.get("params"), MODELS[str(e["name"])]
        if isinstance(params, dict) and all(isinstance(params.get(n), (int, float)) for n in model.params):
            out[model.name] = np.array([float(params[n]) for n in model.params])
    return out


def _measured(falloffs: list[float | None] | None, count: int) -> bool:
    """Whether the overlaps measured every projector's vignetting (:func:`..gap.overlap.overlap_falloffs`)."""
    return falloffs is not None and len(falloffs) == count and all(f is not None for f in falloffs)


def _by_parameters(top: dict[str, Any]) -> str:
    return (f"Projector {top['projector']} differs from the others by its {top['effect'].replace('_', ' ')}: "
            f"its fitted parameters lie {top['difference']:.0%} of their range from the others'; see "
            f"projector_{top['projector']}/summary.md for what to do.")


def attribute(docs: list[dict[str, Any]], falloffs: list[float | None] | None = None) -> dict[str, Any]:
    """Which projector differs, and by which effect, from each projector's own diagnosis.

    For each projector effect (:data:`PROJECTOR_EFFECTS`) some projector's diagnosis selected, each projector's
    fitted parameters are compared with the median of the others', as a share of each parameter's range: the
    camera's and the room's share in what every fit absorbs cancels in that difference (on the plane, projector
    1's tone curve fitted γ 0.78 with the camera's curve alone, projector 2's 1.3 with its own on top), which
    shares of each projector's residual do not (both fits remove ~97 % of theirs). With two projectors the
    difference is the same for both; the one whose parameters lie further from no effect at all is named. The
    effect and projector of the largest difference are named when it reaches :data:`DIFFERS_BY`. Returns
    ``headline``, ``differs`` ({projector (1-based), effect, difference, from_none}, or None), ``ranking`` (first =
    the one named) and ``selected``. ``falloffs``: each projector's vignetting as the overlaps measured it
    (:func:`..gap.overlap.overlap_falloffs`), which replaces the fits of a projector's own patterns, where
    calibration took the falloff into the albedo."""
    fitted = [_fitted(d) for d in docs]
    names = {str(n) for d in docs for n in d.get("selected") or [] if n in PROJECTOR_EFFECTS}
    if _measured(falloffs, len(docs)):
        for f, fit in zip(falloffs, fitted):
            fit["vignetting"] = np.array([float(f), 2.0])
        names.add("vignetting")
    ranking: list[dict[str, Any]] = []
    for name in sorted(names):
        have = [f.get(name) for f in fitted]
        if any(v is None for v in have) or len(have) < 2:
            continue
        model = MODELS[name]
        span = np.maximum(np.asarray(model.upper) - np.asarray(model.lower), 1e-9)
        for k, mine in enumerate(have):
            others = np.median([v for j, v in enumerate(have) if j != k], axis=0)
            ranking.append({"projector": k + 1, "effect": name,
                            "difference": round(float(np.max(np.abs(mine - others) / span)), 4),
                            "from_none": round(float(np.max(np.abs(mine - np.asarray(model.identity)) / span)), 4)})
    ranking.sort(key=lambda r: (-r["difference"], -r["from_none"]))
    top = ranking[0] if ranking and ranking[0]["difference"] >= DIFFERS_BY else None
    if top is not None:
        head = _by_parameters(top)
    else:
        head = _agree(sorted({str(r["effect"]) for r in ranking}))
    return {"headline": head, "differs": top, "ranking": ranking,
            "selected": list(dict.fromkeys(r["effect"] for r in ranking))}


def attribute_held_out(whose: list[dict[str, Any]], *, min_share: float = MIN_SHARE,
                       params: dict[str, Any] | None = None) -> dict[str, Any]:
    """Which projector differs, and by which effect, from held-out errors (:class:`..gap.shared.WhoseEffect`
    records; every share is of the held-out error the fits leave without the effect).

    The projectors differ by an effect when fitting it apart on each projector removes at least ``min_share``
    (the selection's bar for adding an effect) beyond one fit alike for all (``differ``): a room's ambient light
    that every projector's black level takes up alike is no difference. The projector named is the one whose
    effect alone removes most (``alone``): with the others at no effect, it is the hypothesis "only this
    projector has it" that predicts the patterns no fit saw best; where every projector has the effect in some
    measure (a camera curve no shared effect took, in each projector's tone curve), it is the one that departs
    furthest from none, measured in error rather than parameters. A difference is named only when the fitted
    parameters also lie at least :data:`DIFFERS_BY` of their range apart (``params``' ranking): the held-out
    shares are of the error the last fits leave, where a negligible effect can pass the bar. Of the effects the
    projectors differ by, the one whose difference removes most is named. Who differs is decided by how well
    each hypothesis predicts, so parameters pushed along a direction the patterns cannot tell apart (a shared
    camera curve against one projector's tone curve) cannot name the wrong projector, as their distance from the
    other projectors' did (:func:`attribute`). ``params``:
    :func:`attribute`'s verdict on the same fits, whose ``ranking`` is kept for the reader and whose vignetting
    measured in the overlaps (judged there, not here) is named when no effect is named here. Returns
    ``headline``, ``differs`` ({projector (1-based), effect, differ, alone, every} or :func:`attribute`'s),
    ``held_out`` (each effect's figures, ``one_projector`` its verdict), ``ranking`` and ``selected``."""
    ranking = list((params or {}).get("ranking") or [])
    judged = []
    for w in whose:
        alone = [float(a) for a in w["alone"]]
        best = int(np.argmax(alone)) if alone else 0
        differ = float(w["differ"])
        # how far apart the fitted parameters lie decides nothing here, but a difference must be that large to be
        # named at all: a black level of −0.15 % on one projector removed 7 % of the last error left
        apart = max((float(r["difference"]) for r in ranking if r["effect"] == w["effect"]), default=None)
        named = bool(alone) and not w.get("errors") and np.isfinite(differ) and differ >= min_share and \
            alone[best] >= min_share and (apart is None or apart >= DIFFERS_BY)
        # beside the one named, every projector whose effect alone also removes the bar's share and whose fit lies
        # as far from none: both projectors' own tone curves are a difference of both
        far = {int(r["projector"]): float(r["from_none"]) for r in ranking if r["effect"] == w["effect"]}
        every = [k + 1 for k, a in enumerate(alone)
                 if k == best or (a >= min_share and far.get(k + 1, 1.0) >= DIFFERS_BY)]
        judged.append({**w, "one_projector": best + 1 if named else None, "projectors": every if named else [],
                       "parameters_apart": apart})
    differing = sorted((j for j in judged if j["one_projector"] is not None), key=lambda j: -float(j["differ"]))
    selected = list(dict.fromkeys([*(j["effect"] for j in judged), *(r["effect"] for r in ranking)]))
    base = {"held_out": judged, "ranking": ranking, "selected": selected}
    if differing and len(differing[0]["projectors"]) > 1:
        top = differing[0]
        named = [int(k) for k in top["projectors"]]
        far = {int(r["projector"]): float(r["from_none"]) for r in ranking if r["effect"] == top["effect"]}
        each = ", ".join(f"projector {k}'s alone removes {top['alone'][k - 1]:.0%}"
                         + (f" (its fit lies {far[k]:.0%} of its range from none)" if k in far else "")
                         for k in named)
        whom = "each other" if len(named) == len(top["alone"]) else "the others"
        head = (f"Projectors {_and(named)} differ from {whom} by their {str(top['effect']).replace('_', ' ')}: fitted "
                f"apart on each projector it removes {top['differ']:.0%} more of the held-out error than alike on all; "
                f"{each}; see {_and([f'projector_{k}/summary.md' for k in named])} for what to do.")
        k = int(top["one_projector"])
        differs = {"projector": k, "projectors": named, "effect": top["effect"], "differ": top["differ"],
                   "alone": top["alone"][k - 1], "every": top["every"]}
        return {"headline": head, "differs": differs, **base}
    if differing:
        top = differing[0]
        k = int(top["one_projector"])
        others = [a for i, a in enumerate(top["alone"]) if i != k - 1]
        effect = str(top["effect"]).replace("_", " ")
        elsewhere = (f"on projector {3 - k} alone {others[0]:.0%}" if len(others) == 1 else
                     f"on any other projector alone at most {max(others):.0%}")
        head = (f"Projector {k} differs from the others by its {effect}: fitted apart on each projector it removes "
                f"{top['differ']:.0%} more of the held-out error than alike on all; on projector {k} alone "
                f"{top['alone'][k - 1]:.0%} ({elsewhere}); see projector_{k}/summary.md for what to do.")
        differs = {"projector": k, "projectors": [k], "effect": top["effect"], "differ": top["differ"],
                   "alone": top["alone"][k - 1], "every": top["every"]}
        return {"headline": head, "differs": differs, **base}
    overlap = next((r for r in ranking if r["effect"] == "vignetting" and r["difference"] >= DIFFERS_BY
                    and all(j["effect"] != "vignetting" for j in judged)), None)
    if overlap is not None:
        return {"headline": _by_parameters(overlap), "differs": overlap, **base}
    alike = [str(j["effect"]).replace("_", " ") for j in judged if float(j["every"]) >= min_share]
    return {"headline": _agree(alike), "differs": None, **base}


def _and(items: list[Any]) -> str:
    """"1", "1 and 2", "1, 2 and 3"."""
    said = [str(i) for i in items]
    return said[0] if len(said) == 1 else f"{', '.join(said[:-1])} and {said[-1]}"


def _agree(alike: list[str]) -> str:
    """The headline when no projector differs: the effects every projector shows alike, if any."""
    return ("The projectors agree: " + (f"each shows {', '.join(alike)} alike" if alike else
                                         "none shows an effect the others do not") + ".")


@dataclass
class DiagnosisView:
    """A diagnosis folder: its ``gap.json`` and the figures its readers use."""

    folder: Path
    doc: dict[str, Any]

    @property
    def selected(self) -> list[str]:
        """The effects selected, those found on the residual first, then those calibration absorbed."""
        return [str(s) for s in self.doc.get("selected") or []]

    @property
    def absorbed(self) -> list[str]:
        return [str(s) for s in self.doc.get("absorbed") or []]

    @property
    def headline(self) -> str:
        return str(self.doc.get("headline") or "")

    @property
    def warnings(self) -> list[str]:
        return [str(w) for w in self.doc.get("warnings") or []]

    @property
    def effects(self) -> list[dict[str, Any]]:
        """Every candidate effect as the diagnosis ranked it."""
        return [e for e in self.doc.get("effects") or [] if isinstance(e, dict) and "name" in e]

    @property
    def regions(self) -> list[dict[str, Any]]:
        return [r for r in self.doc.get("regions") or [] if isinstance(r, dict)]


def read(folder: str | Path) -> DiagnosisView:
    """A diagnosis folder and its ``gap.json``; a clear error when the folder holds none."""
    return DiagnosisView(Path(folder), KIND.read(folder, DiagnosisError))


def _lines(root: Path, doc: dict[str, Any], notes: list[str], brief: list[int]) -> tuple[str, ...]:
    """What ``procam diagnose`` prints and the sidebar shows under the headline; ``brief[0]`` is set to the number
    of lines before the top effects and regions are listed."""
    view = DiagnosisView(root, doc)
    res, after = doc.get("residual") or {}, doc.get("residual_after") or {}
    lines = list(notes)
    if after:
        lines.append(f"held-out residual: RMSE {fmt(res.get('rmse'), '.4f')} ({fmt(res.get('psnr'), '.1f', ' dB')})"
                     f" → {fmt(after.get('rmse'), '.4f')} ({fmt(after.get('psnr'), '.1f', ' dB')}) with the selected "
                     f"effects; without pixel noise {fmt(res.get('rmse_structured'), '.4f')} → "
                     f"{fmt(after.get('rmse_structured'), '.4f')}")
    absorbed = (f" ({', '.join(view.absorbed)} absorbed by calibration, found from its inputs)"
                if view.absorbed else "")
    lines.append("selected: " + (", ".join(view.selected) or "none") + absorbed)
    left = doc.get("unexplained") or {}
    if left.get("detected"):
        lines.append(f"unexplained: the selected effects explain {fmt(left.get('explained_share'), '.0%')}"
                     f" of the residual above the captures' noise; RMSE {fmt(left.get('unexplained_rmse'), '.4f')} is"
                     " left" + (f", most of it {left['where']}" if left.get("where") else ""))
    elif left and doc.get("modelled"):
        lines.append(f"explained: {fmt(left.get('explained_share'), '.0%')} of the residual above "
                     "the captures' noise")
    elif left:
        lines.append(f"left: RMSE {fmt(left.get('unexplained_rmse'), '.4f')} above the captures' noise, too little "
                     "to model")
    brief[0] = len(lines)  # the panel lists every effect and region itself: it shows the lines up to here
    for e in [e for e in view.effects[:3] if not e.get("error")]:
        conf = e.get("confidence")
        level = conf.get("level", "–") if isinstance(conf, dict) else fmt(conf, ".2f")
        lines.append(f"{e['name']:<16} alone: RMSE {fmt(e.get('heldout_rmse_after'), '.4f')} "
                     f"({fmt(e.get('reduction'), '.0%')} less), confidence {level}")
    for k, r in enumerate(view.regions[:3]):
        lines.append(f"region {k + 1} ({r.get('cause', '?')}): {fmt(r.get('share'), '.0%')} "
                     f"of the error, {r.get('description', '')}")
    if view.regions[:3] and doc.get("share_means"):
        lines.append(f"({doc['share_means']})")
    if (root / layout.DIAGNOSIS_SUMMARY).is_file():
        lines.append(f"summary: {root / layout.DIAGNOSIS_SUMMARY}")
    return tuple(lines)


def _summary_projectors(root: Path, doc: dict[str, Any]) -> Summary:
    lines = []
    for k, p in enumerate(doc.get("projectors") or []):
        res, after = (p or {}).get("residual") or {}, (p or {}).get("residual_after") or {}
        lines.append(f"projector {k + 1}: residual RMSE {fmt(res.get('rmse'), '.4f')} → "
                     f"{fmt(after.get('rmse'), '.4f')}, selected {', '.join(p.get('selected') or []) or 'none'}; "
                     f"{p.get('headline', '')}")
    for h in doc.get("held_out") or []:
        alone = ", ".join(f"projector {k + 1} alone {fmt(a, '.0%')}" for k, a in enumerate(h.get("alone") or []))
        named = [int(k) for k in h.get("projectors") or []] or ([int(h["one_projector"])] if h.get("one_projector")
                                                                 else [])
        whose = (f"projector{'s' if len(named) > 1 else ''} {_and(named)}'s" if named else "no one projector's")
        lines.append(f"{h.get('effect')} held out: removes {alone}, every projector apart "
                     f"{fmt(h.get('every'), '.0%')}, alike {fmt(h.get('tied'), '.0%')} of the error without it: "
                     f"{whose}")
    differs = (doc.get("differs") or {}) if isinstance(doc.get("differs"), dict) else {}
    first = [int(k) for k in differs.get("projectors") or ([differs["projector"]] if differs.get("projector") else [])]
    # the parameters of the projectors the headline names first, as it says them
    ranking = sorted(doc.get("ranking") or [], key=lambda r: not (r.get("effect") == differs.get("effect")
                                                                    and r.get("projector") in first))
    for r in ranking[:4]:
        lines.append(f"{r.get('effect')} on projector {r.get('projector')}: fitted {fmt(r.get('difference'), '.0%')} "
                     f"of its range from the others', {fmt(r.get('from_none'), '.0%')} from none")
    head = str(doc.get("headline") or "")
    maps = [str(p.relative_to(root)) for p in sorted(root.rglob("*.png"))]
    return Summary(True, head, tuple(lines), {"effects": [], "selected": doc.get("selected") or [], "regions": [],
                                              "projector_count": int(doc.get("projector_count") or 1),
                                              "maps": maps, "summary": layout.DIAGNOSIS_SUMMARY,
                                              "notes": [head], "brief": len(lines)})


def _summary(root: Path, doc: dict[str, Any]) -> Summary:
    if doc.get("projector_count", 1) > 1:
        return _summary_projectors(root, doc)
    residual = doc.get("residual") or {}
    effects = [e for e in doc.get("effects", []) if isinstance(e, dict) and "name" in e]
    selected = [str(s) for s in doc.get("selected", [])]

    def gain(e: dict[str, Any]) -> float:
        try:
            return float(e.get("heldout_rmse_before")) - float(e.get("heldout_rmse_after"))
        except (TypeError, ValueError):
            return float("-inf")

    # Selected in the diagnosis's order (found on the residual, then absorbed by calibration), then by gain.
    effects.sort(key=lambda e: (0, selected.index(e["name"])) if e["name"] in selected else (1, -gain(e)))
    regions = [r for r in doc.get("regions", []) if isinstance(r, dict)]
    regions.sort(key=lambda r: -float(r.get("share", 0) or 0))
    head = (f"Residual RMSE {fmt(residual.get('rmse'), '.4f')}, PSNR {fmt(residual.get('psnr'), '.1f', ' dB')}; "
            f"{len(selected)} effect{'s' if len(selected) != 1 else ''} selected"
            + (f" ({len(doc['absorbed'])} absorbed by calibration)" if doc.get("absorbed") else ""))
    maps = [str(p.relative_to(root)) for p in sorted(root.rglob("*.png"))]
    text = layout.DIAGNOSIS_SUMMARY if (root / layout.DIAGNOSIS_SUMMARY).is_file() else None
    # What a technician reads first: the plain sentence, a rig that changed, what is left unexplained.
    notes = (([str(doc["headline"])] if doc.get("headline") else [])
             + [f"Warning: {w}." for w in doc.get("warnings", [])])
    session = doc.get("session") or {}
    if session.get("changed"):
        notes.append(f"The rig changed during the session: {session.get('sentence', '')}.")
    brief = [0]
    lines = _lines(root, doc, notes, brief)  # the residual left is said in the lines' own words, with its RMSE
    left = doc.get("unexplained") or {}
    if left.get("detected"):
        notes.append(f"Unexplained: the selected effects explain {fmt(100 * left.get('explained_share', 0), '.0f')}% "
                     "of the residual above the noise" + (f"; most of the rest {left['where']}"
                                                          if left.get("where") else "") + ".")
    return Summary(True, head, lines, {"effects": effects, "selected": selected, "regions": regions, "maps": maps,
                                    "summary": text, "notes": notes, "brief": brief[0]})


def summary(folder: str | Path) -> Summary:
    """A diagnosis folder: residual, effects ranked (selected first, then held-out gain), regions, maps."""
    return cached(KIND, folder, _summary, "run Diagnose or choose a diagnosis folder")
