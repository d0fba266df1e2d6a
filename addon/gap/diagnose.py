"""The sim-to-real diagnosis of a calibration: where, which effect, how far the gap shrinks.

:func:`diagnose` returns the ``gap.json`` document, the residual maps and
region overlay, and ``summary.md``, a one-page report with the images; the
diagnose step (``steps/diagnose.py``) writes them. Nothing here reads a lab
truth file.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..capture.format import CaptureSet
from ..progress import Cancel, Progress, quiet
from ..stages.calibrate import Calibration
from .data import LEVEL_EFFECTS, MAX_TEXELS_PER_PIXEL, NO_VALIDATION, GapData, load_gap_data
from .compensation import HELD_BY_STAGE_C, INVERTIBLE
from .evidence import calibration_evidence
from .fit import (MAX_EFFECTS, MIN_SHARE, SMOOTH_SIGMA, Selection, compensation_subset, fit_composite,
                  residual_stack, select_effects, structured)
from .models import (MODELS, NAMES, Composite, glossy_at, inverse_camera_curve, local_light,
                     signature_mask)
from .regions import EDGES, LEFT_OVER, SHARE_MEANS, UNEXPLAINED, WHOLE, error_split, find_regions, label_image, \
    residual_maps
from .remainder import Remainder, remainder
from .session import SessionCheck, check_session

#: The effect explains its gain where its signature says when that share of the squared-error reduction falls
#: on its signature pixels, and more than their share of the pixels.
SIGNATURE_ENRICHMENT = 1.2
#: ... and it acts against its signature when under this share of its pixel share falls there: its gain lies where
#: its form matters least, so it stands in for another effect. Over the diagnosis benchmark's four surfaces an
#: ambient black level fitted beside a glossy lobe or a camera curve (18 sets) put 0.05–0.21 of the dark input
#: levels' pixel share of its gain there, a real one (28 sets) 0.76–0.94.
CONTRA_SIGNATURE = 0.5


#: What calibration absorbs of each effect, so that the validation residual cannot show it. All but the camera
#: response are looked for where they were absorbed instead (:mod:`.evidence`).
ABSORBED = {
    "vignetting": "a smooth projector falloff looks exactly like darker surface reflectance in the white capture; "
                  "the albedo holds it, so compensation is not hurt. Found from the room-lit surface photo",
    "glossy": "a highlight the sensor does not clip looks like brighter paint in the white capture; the albedo holds "
              "it for this camera position (it moves with the viewpoint). Found from the room-lit surface photo",
    "camera_response": "its white-balance gains are absorbed by the albedo in the same way; only its tone curve "
                       "(mid levels) is visible",
    "distortion": "camera lens distortion moves the projected pattern smoothly in the camera image; the pose and the "
                  "stage-B warp absorb it. Found from the Gray-code correspondences",
    "depth_noise": "the wall image removes the depth bias (else the pose absorbs it) and the reconstruction smooths "
                   "the noise; only what remains shows, near creases. Found from the depth sensor's wall image",
}


#: Roughnesses of the lobes the evidence tries (interpolated between the model's renders,
#: :data:`.data.GLOSSY_ROUGHNESS`).
EVIDENCE_ROUGHNESS = tuple(round(0.2 + 0.05 * i, 2) for i in range(9))


def _blur_unseen(spans: float, scale: float) -> str:
    """The warning for a working scale too coarse to see a projector blur of about a texel."""
    text = (f"one working pixel spans {spans:.1f} projector input texels here (--scale {scale:g}), so a projector "
            "blur of about a texel can go unseen")
    if scale >= 1.0:
        return text + "; the camera's own pixels are that coarse: a closer camera or a longer lens would show it"
    better = min(1.0, math.ceil(20 * scale * spans / MAX_TEXELS_PER_PIXEL) / 20)
    return text + f"; --scale {better:g} looks at {spans * scale / better:.1f} texels a pixel (slower)"


def _at_the_limit(max_effects: int, runner_up: str, share: float) -> str:
    """The warning for a selection that stopped at its limit while another effect still removed enough."""
    return (f"the selection stopped at its limit of {max_effects} effect{'s' * (max_effects != 1)}, and {runner_up} "
            f"still removed {share:.0%} of what was left in the last round: --max-effects {max_effects + 1} would "
            "try it (slower)")


def _psnr(rmse: float) -> float:
    return float("inf") if rmse <= 0 else 20.0 * math.log10(1.0 / rmse)


def _signature(data: GapData, name: str, b: np.ndarray, a: np.ndarray) -> dict[str, Any]:
    """Where the effect's reduction of squared error falls, against the pixels its signature names (``b``, ``a``:
    the structured held-out residuals before the effect and after it alone)."""
    # Only where the effect helps: a model may also shift error around, which is not "explaining" it.
    gain = np.where(data.mask, np.maximum(((b ** 2) - (a ** 2)).mean(axis=3), 0.0), 0.0)
    sig = np.stack([signature_mask(name, data, data.observations[i]) for i in data.held_index]) & data.mask
    total = float(gain.sum())
    pixel_share = float(sig.sum() / max(data.mask.sum() * len(data.held_index), 1))
    share = float(gain[sig].sum() / total) if total > 0 else 0.0
    return {"where": MODELS[name].signature, "share_of_reduction": round(share, 3),
            "share_of_pixels": round(pixel_share, 3),
            "consistent": bool(total > 0 and share >= 0.5 and share >= SIGNATURE_ENRICHMENT * pixel_share),
            "against": bool(total > 0 and share < CONTRA_SIGNATURE * pixel_share)}


def _confidence(sel: Selection, name: str, sig: dict[str, Any]) -> dict[str, Any]:
    step = next((s for s in sel.steps if s["candidate"] == name), None)
    out: dict[str, Any] = {"signature": sig}
    if step is None or name not in sel.selected:
        return {**out, "level": "not selected"}
    ranking = step["ranking"]  # (name, share of the error it removes), best first
    gain1 = ranking[0][1]
    gain2 = ranking[1][1] if len(ranking) > 1 else 0.0
    margin = (gain1 - max(gain2, 0.0)) / gain1 if gain1 > 0 else 0.0
    runner = ranking[1][0] if len(ranking) > 1 else None
    level = "high" if margin >= 0.3 and sig.get("consistent") else ("medium" if margin >= 0.3 or sig.get("consistent")
                                                                  else "low")
    if sig.get("against"):
        return {**out, "margin": round(margin, 3), "runner_up": runner, "level": "low", "why": _against(sig)}
    return {**out, "margin": round(margin, 3), "runner_up": runner, "level": level}


def _against(sig: dict[str, Any]) -> str:
    return (f"only {sig['share_of_reduction']:.0%} of what it explains falls on its signature ({sig['where']}), "
            f"which is {sig['share_of_pixels']:.0%} of the pixels: it stands in for another effect")


def _temper_confidence(effects: list[dict[str, Any]], modelled: list[str], session: SessionCheck,
                       rem: Remainder) -> None:
    """No effect is named with high confidence when the rig changed during the session (a fitted effect may stand
    for that change) or when the selected effects leave most of the residual unexplained (it stands for part of
    something else at most)."""
    for e in effects:
        conf = e.get("confidence", {})
        if e["name"] not in modelled or conf.get("level") not in ("high", "medium"):
            continue
        if session.changed:
            e["confidence"] = {**conf, "level": "low", "why": "the rig changed during the session: "
                               + session.sentence()}
        elif rem.detected and conf["level"] == "high":
            e["confidence"] = {**conf, "level": "medium",
                               "why": f"the selected effects explain only {rem.explained_share:.0%} of the residual "
                                      "above the noise"}


#: What a show technician can do about each effect, as the end of one sentence.
ACTIONS = {
    "response": "the projector's tone curve is not linear{where}: linearise it in its menu, or compensate with "
                "--effects auto",
    "crosstalk": "the projector's colours mix{where}: compensate with --effects auto",
    "black_level": "light reaches the surface when the projector shows black{where} (room light or the projector's "
                   "black level): darken the room; compensation already allows for it, but nothing shows darker",
    "vignetting": "the projector's image darkens towards its corners: the albedo holds it, nothing to do",
    "defocus": "the projector is out of focus{where}: refocus it, or compensate with --effects auto, which "
               "pre-sharpens what the input range allows",
    "interreflection": "light bounces between parts of the surface{where}: a darker finish on the facing parts "
                       "reduces it; compensation already simulates the first bounce",
    "glossy": "the surface is glossy{where}: a matte finish helps; compensate with --effects auto, which restores "
              "the light the white capture clipped in the highlight",
    "camera_response": "the camera applies a tone curve: shoot linear (raw), or compensate with --effects auto",
    "distortion": "the camera's lens distorts the image: calibrate it with a printed board (procam calibrate-rig), "
                  "then import the photographs with that rig file, which takes the lens out of them and out of a "
                  "live camera's frames (the warp and θ take up only part of it, least through a blurred projector)",
    "depth_noise": "the surface's depth is off: recapture the depth, or take the surface from the Gray code "
                   "(--surface-from graycode)",
}


def _where(bbox: list[int] | None, size: tuple[int, int]) -> str:
    """" towards the bottom edge" etc. for a region's box in the camera image ('' when central or unknown)."""
    if not bbox:
        return ""
    x, y, w, h = bbox
    cx, cy = (x + w / 2) / size[0] - 0.5, (y + h / 2) / size[1] - 0.5
    if max(abs(cx), abs(cy)) < 0.15 or w * h > 0.5 * size[0] * size[1]:
        return ""
    side = ("right" if cx > 0 else "left") if abs(cx) > abs(cy) else ("bottom" if cy > 0 else "top")
    return f" towards the {side} of the camera image"


def headline(doc: dict[str, Any], size: tuple[int, int]) -> str:
    """One plain sentence a show technician can act on, from the ``gap.json`` document."""
    session, left = doc["session"], doc["unexplained"]
    if session["changed"]:
        return (f"The rig changed during the session ({session['sentence']}): fix that and capture again before "
                "trusting any effect named here.")
    tail = ""
    if left["detected"]:
        tail = (f"; {1 - left['explained_share']:.0%} of the residual above the noise stays unexplained"
                + (f", most of it {left['where']}" if left["where"] else ""))
    if doc["modelled"]:
        name = doc["modelled"][0]
        # a place only when the effect's error gathers in one (its first region): a defocus over the whole image
        # is not "left"
        first = next((r for r in doc["regions"] if r.get("cause") == name), None)
        region = first["bbox"] if first and WHOLE not in first.get("tags", []) else None
        text = ACTIONS[name].format(where=_where(region, size))
        return text[0].upper() + text[1:] + tail + "."
    if left["detected"]:
        return ("Something ProCam has no model for remains" + (f" {left['where']}" if left["where"] else "")
                + f" (RMSE {left['unexplained_rmse']:.4f} above the captures' noise): look there for what changed "
                "or what the surface does that a matte, still surface would not.")
    if doc["absorbed"]:
        return (f"Calibration absorbed {', '.join(doc['absorbed'])}; nothing else stands out above the captures' "
                "noise.")
    return "The model matches the captures to within their noise: nothing to fix."


def _colour_signed(r: np.ndarray, scale: float) -> np.ndarray:
    return np.clip(0.5 + r / (2 * scale), 0, 1)


def _heat(v: np.ndarray, scale: float) -> np.ndarray:
    u8 = (np.clip(v / scale, 0, 1) * 255).astype(np.uint8)
    return cv2.applyColorMap(u8, cv2.COLORMAP_INFERNO)[..., ::-1].astype(np.float32) / 255.0


def _overlay(base: np.ndarray, regions: list[Any], size: tuple[int, int]) -> np.ndarray:
    img = cv2.resize(np.clip(base, 0, 1) ** (1 / 2.2), size, interpolation=cv2.INTER_LINEAR)
    img = (img * 255).astype(np.uint8).copy()
    for k, r in enumerate(regions):
        x, y, w, h = r.bbox
        if r.mask is not None and WHOLE not in r.tags:  # the region's outline, not its box
            sel = cv2.resize(r.mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
            contours, _ = cv2.findContours(sel, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            cv2.drawContours(img, contours, -1, (255, 60, 60), 2)
        else:
            cv2.rectangle(img, (x, y), (x + w - 1, y + h - 1), (255, 60, 60), 2)
        # whole-area regions share one box: their labels go one under the other
        cv2.putText(img, f"{k + 1}: {r.cause} {r.share:.0%}", (x + 3, y + 16 + 14 * k), cv2.FONT_HERSHEY_SIMPLEX,
                    0.45, (255, 255, 80), 1)
    return img.astype(np.float32) / 255.0


def summary_markdown(doc: dict[str, Any]) -> str:
    """``summary.md`` of a ``gap.json`` document."""
    res, after = doc["residual"], doc["residual_after"]
    lines = ["# ProCam sim-to-real diagnosis", "", f"**{doc['headline']}**", "",
             f"Calibration `{doc['calibration']}`; {len(doc['patterns']['fit'])} patterns fitted, "
             f"{len(doc['patterns']['held_out'])} held out.", "",
             *[f"**Warning:** {w}." for w in doc.get("warnings", [])], *([""] if doc.get("warnings") else []),
             f"**Held-out residual of the calibrated model:** RMSE {res['rmse']:.4f} ({res['psnr']:.1f} dB PSNR); "
             f"without pixel noise {res['rmse_structured']:.4f}.",
             f"**With the selected effects:** RMSE {after['rmse']:.4f} ({after['psnr']:.1f} dB); without pixel noise "
             f"{after['rmse_structured']:.4f}.", "",
             "Effects are ranked and selected on the residual without pixel noise (smoothed by "
             f"{doc['smooth_sigma_px']} px except on pattern edges), on patterns they were not fitted on.", "",
             *([f"**The rig changed during the session:** {doc['session']['sentence']}. Effects fitted to these "
                "captures may stand for that change: fix it and capture again.", ""]
               if doc["session"]["changed"] else []),
             *([f"**Unexplained:** the selected effects explain {doc['unexplained']['explained_share']:.0%} of the "
                f"residual above the captures' noise (smooth parts); RMSE {doc['unexplained']['unexplained_rmse']:.4f} "
                "is left that no effect model accounts for"
                + (f", most of it {doc['unexplained']['where']}" if doc['unexplained']['where'] else "") + ".", ""]
               if doc["unexplained"]["detected"] else []),
             "**Selected:** " + (", ".join(doc["selected"]) if doc["selected"] else
                                 "none: no effect model removes a significant share of the residual, and calibration "
                                 "absorbed none"), "",
             *([f"**Absorbed by calibration** (found from its inputs, nothing left to model): "
                f"{', '.join(doc['absorbed'])}", ""] if doc["absorbed"] else []),
             *([f"**Compensation {'of the rig ' if 'alone' in doc['compensation'] else ''}with `--effects auto` "
                f"inverts{' for this projector' if 'alone' in doc['compensation'] else ''}:** "
                f"{', '.join(doc['compensation']['effects']) or 'none'}"
                + "".join(f"; not {n}: {why}" for n, why in doc["compensation"]["left_out"].items()), ""]
               if doc["modelled"] else []),
             "## Which effect", "",
             "| rank | effect | held-out RMSE alone | removes | confidence | "
             "signature (share of gain where expected) |",
             "|---|---|---|---|---|---|"]
    for k, e in enumerate(doc["effects"]):
        if e.get("error"):
            lines.append(f"| – | {e['name']} | failed to fit: {e['error']} | | | |")
            continue
        sig = e["confidence"].get("signature", {})
        lines.append(f"| {k + 1} | {e['name']} | {e['heldout_rmse_after']:.4f} | {e['reduction']:.0%} | "
                     f"{e['confidence']['level']} | {sig.get('share_of_reduction', 0):.0%} "
                     f"{sig.get('where', '')} |")
    lines += ["", "## How far the gap shrinks (greedy steps, held-out RMSE without pixel noise)", ""]
    for s in doc["steps"]:
        verdict = f"added **{s['added']}**" if s["added"] else f"stopped: best candidate {s['candidate']} removes " \
                                                              f"only {s['share']:.0%} (< {doc['min_share']:.0%})"
        lines.append(f"- {s['before']:.4f} → {s['after']:.4f} ({s['share']:.0%}): {verdict}")
    if doc["modelled"]:
        lines += ["", "Fitted parameters: " + "; ".join(
            f"{n} {doc['selected_params'][n]}" for n in doc["modelled"])]
    lines += ["", "## Effects calibration absorbs", "",
              "Looked for where calibration absorbed them, fitted on half the pixels and scored on the other half.", "",
              "| effect | found | absorbed by | evidence | parameters |", "|---|---|---|---|---|"]
    for n, e in doc["evidence"].items():
        what = e["evidence"] if not e["error"] else f"not measured: {e['error']}"
        lines.append(f"| {n} | {'**yes**' if e['detected'] else 'no'} | {e['absorbed_by']} | {what} | "
                     f"{e['params'] or ''} |")
    lines += ["", "## Where", "", "![regions](regions.png) ![residual](residual_abs.png)", "",
              "Each region belongs to one cause: the part of the error a modelled effect removes there, or what "
              "the selected effects leave (unexplained when above the captures' noise). `regions_label.png` holds "
              "their pixels (region numbers when read as 8 bits).", "",
              f"Shares: {SHARE_MEANS}. The error splits by cause as "
              + ", ".join(f"{k} {v:.0%}" for k, v in doc["error_split"].items())
              + f"; the {EDGES}' part (sub-pixel misregistration) lies in no region.", "",
              "| region | cause | bbox (x, y, w, h) | share of the error | description |", "|---|---|---|---|---|"]
    for k, r in enumerate(doc["regions"]):
        lines.append(f"| {k + 1} | {r.get('cause', '')} | {tuple(r['bbox'])} | {r['share']:.0%} | "
                     f"{r['description']} |")
    lines += ["", "Maps: `residual_signed.png` (per channel, grey = 0, ±scale in the JSON), `residual_abs.png`, "
                  "`residual_after_abs.png` (with the selected effects).", "",
              "What calibration absorbs: " + "; ".join(f"**{k}**: {v}" for k, v in ABSORBED.items()), ""]
    return "\n".join(lines)


@dataclass
class Diagnosis:
    """What :func:`diagnose` found: the ``gap.json`` document, its images by file name, and ``summary.md``."""

    doc: dict[str, Any]
    images: dict[str, np.ndarray]
    summary: str
    #: the model's renders and the captures it was diagnosed on (a rig of several projectors fits the camera's
    #: effects once on every projector's, :mod:`.shared`)
    data: GapData | None = field(default=None, repr=False)


def diagnose(calibration: Calibration, captures: CaptureSet, *, source: str, format: tuple[str, int],
             scale: float = 0.5, spp: int = 32, candidates: tuple[str, ...] = NAMES, min_share: float = MIN_SHARE,
             max_effects: int = MAX_EFFECTS, progress: Progress | None = None,
             cancel: Cancel | None = None) -> Diagnosis:
    """Diagnose a calibration on its capture set's held-out patterns.

    ``source`` names the calibration in the report (its folder); ``format`` is the document's (tag, version).
    """
    say = progress or quiet
    t0 = time.perf_counter()
    data = load_gap_data(calibration, captures, source=source, scale=scale, spp=spp, cancel=cancel,
                         progress=lambda m, f: say(f"model: {m}", 0.4 * f))
    t_render = time.perf_counter() - t0
    t0 = time.perf_counter()
    warnings = [] if data.report["validation"] else [NO_VALIDATION]
    if warnings:
        candidates = tuple(c for c in candidates if c not in LEVEL_EFFECTS)
    # An albedo read from the white capture holds the projector's falloff exactly, so a vignetting model on
    # top of it can only fit something else (on vedge with crosstalk and glossy it fitted the lobe's
    # leftovers, and inverting it cost 0.12 dB): it is fitted and shown, but found from the evidence alone.
    evidence_only = ("vignetting",) if _albedo_from_white(calibration) else ()
    sel = select_effects(data, tuple(c for c in candidates if c not in evidence_only), min_share=min_share,
                         max_effects=max_effects, cancel=cancel,
                         progress=lambda m, f: say(f"effects: {m}", 0.4 + 0.5 * f))
    next_up = sel.steps[-1]["ranking"][1] if len(sel.selected) == max_effects and sel.steps and \
        len(sel.steps[-1]["ranking"]) > 1 and sel.steps[-1]["ranking"][1][1] >= min_share else None
    if next_up is not None:
        warnings.append(_at_the_limit(max_effects, *next_up))
    for name in (n for n in evidence_only if n in candidates):
        sel.alone[name] = fit_composite(data, (name,))
    t_fit = time.perf_counter() - t0
    spans = data.spans
    if spans is not None and spans > MAX_TEXELS_PER_PIXEL and "defocus" in candidates and \
            "defocus" not in sel.selected and (next_up is None or next_up[0] != "defocus"):  # (seen, left out)
        warnings.append(_blur_unseen(spans, scale))
    say("evidence of absorbed effects", 0.9)
    t0 = time.perf_counter()
    evidence = calibration_evidence(calibration, captures, cancel=cancel, **_linear_light(data, sel))
    t_evidence = time.perf_counter() - t0
    found = [n for n, e in evidence.items() if e.detected and n in candidates and n not in sel.selected]
    base, final = sel.base, sel.final or sel.base
    effects = []
    # Selected on the residual first, then found where calibration absorbed them, then the rest by share.
    # Absorbed effects keep the order ``absorbed`` lists them in: what their models still remove of the residual
    # is a leftover's share, not their size.
    ranked = sorted(sel.alone.items(), key=lambda kv: (0, -kv[1].share_of(base)) if kv[0] in sel.selected else
                    (1, found.index(kv[0])) if kv[0] in found else (2, -kv[1].share_of(base)))
    def smooth(res: np.ndarray) -> np.ndarray:
        return np.stack([structured(r, data.observations[i].edges) for r, i in zip(res, data.held_index)])
    res_base = residual_stack(Composite(data, ()), base.theta, data.held_index)
    smooth_base = smooth(res_base)
    smooth_alone: dict[str, np.ndarray] = {}

    def alone(name: str) -> np.ndarray:
        """The structured held-out residual after one effect fitted alone (the signature and the regions both
        read it: computed once)."""
        if name not in smooth_alone:
            f = sel.alone[name]
            smooth_alone[name] = smooth(residual_stack(Composite(data, f.names), f.theta, data.held_index))
        return smooth_alone[name]

    for name, f in ranked:
        if f.error is not None:
            effects.append({"name": name, "error": f.error, "params": None, "heldout_rmse_before": base.held_rmse,
                            "heldout_rmse_after": None, "confidence": {"level": "failed"}})
            continue
        sig = _signature(data, name, smooth_base, alone(name)) if name in sel.selected or name == ranked[0][0] else {}
        effects.append({"name": name, "params": f.params()[name], "heldout_rmse_before": base.held_rmse,
                        "heldout_rmse_after": f.held_rmse, "heldout_rmse_raw_before": base.held_rmse_raw,
                        "heldout_rmse_raw_after": f.held_rmse_raw,
                        "heldout_mse_classes_before": list(base.held_mse_classes),
                        "heldout_mse_classes_after": list(f.held_mse_classes),
                        "reduction": f.share_of(base),
                        "fit_seconds": round(f.seconds, 2), "confidence": _confidence(sel, name, sig)})
        if name in evidence:
            effects[-1]["absorbed"] = evidence[name].to_dict()
            if name in found:
                effects[-1]["confidence"] = {**effects[-1]["confidence"], "level": "absorbed by calibration",
                                             "evidence": evidence[name].evidence}
    # An effect acting against its signature is reported, not inverted: on the curve with a glossy lobe an ambient
    # black level fitted beside the lobe cost compensation 0.10 dB.
    stand_ins = {e["name"]: _against(e["confidence"]["signature"]) for e in effects
                 if (e["confidence"].get("signature") or {}).get("against") and e["name"] in sel.selected}
    inverted, left_out = compensation_subset(data, sel, INVERTIBLE, min_share=min_share, leave_out=stand_ins,
                                             held=HELD_BY_STAGE_C)
    res_final = residual_stack(Composite(data, final.names), final.theta, data.held_index)
    cam_full = calibration.rig.camera.intrinsics.size
    session = check_session(captures)
    rem = remainder(data, base, final)
    # the error split by cause: what each modelled effect removes alone, and what all of them leave
    causes = {n: alone(n) for n in sel.selected}
    lights = {n: local_light(n, sel.alone[n].theta, data) for n in sel.selected if MODELS[n].local}
    # A highlight the albedo absorbed is a place too, where the evidence's lobe puts its light: what the residual
    # still holds there (its clipped core, a lobe the albedo holds only in part) is counted in that place.
    lobe = evidence["glossy"].params if "glossy" in found else None
    absorbed = {"glossy": local_light("glossy", np.array([lobe["weight"], lobe["roughness"]]), data)} if lobe else {}
    smooth_final, rest = smooth(res_final), UNEXPLAINED if rem.detected else LEFT_OVER
    regions = find_regions(data, smooth_base, cam_full, data.held_index, causes=causes, lights=lights,
                           remainder=smooth_final, remainder_cause=rest, absorbed=absorbed)
    split = error_split(data, smooth_base, data.held_index, causes=causes, lights=lights, remainder=smooth_final,
                        remainder_cause=rest)
    left = next((r for r in regions if r.cause == UNEXPLAINED and WHOLE not in r.tags), None)
    unexplained = {**rem.to_dict(), "where": left.description if left else "",
                   "where_bbox": list(left.bbox) if left else None}
    _temper_confidence(effects, sel.selected, session, rem)
    doc = {"format": format[0], "version": format[1], "calibration": data.report["calibration"],
           "capture_set": data.report["capture_set"], "working_size": list(data.size),
           "texels_per_pixel": None if spans is None else round(spans, 2), "warnings": warnings,
           "patterns": {"fit": [data.names[i] for i in data.fit_index],
                        "held_out": [data.names[i] for i in data.held_index]},
           "lit_pixels": int(data.mask.sum()),
           # rmse/psnr: plain simulation vs capture on the held-out patterns; *_structured: without the
           # pixel noise (what ranking and selection use, see gap/fit.py).
           "residual": {"rmse": base.held_rmse_raw, "psnr": _psnr(base.held_rmse_raw),
                        "rmse_structured": base.held_rmse, "psnr_structured": _psnr(base.held_rmse),
                        "mse_classes": list(base.held_mse_classes)},
           "residual_after": {"rmse": final.held_rmse_raw, "psnr": _psnr(final.held_rmse_raw),
                              "rmse_structured": final.held_rmse, "psnr_structured": _psnr(final.held_rmse),
                              "mse_classes": list(final.held_mse_classes)},
           "smooth_sigma_px": SMOOTH_SIGMA,
           "mse_classes": ["smooth parts (smoothed residual)", "pattern edges"],
           "regions": [r.to_dict() for r in regions],
           # what the regions' shares are of: each cause's part of the error and the pattern edges' (sum 1)
           "error_split": {k: round(v, 4) for k, v in split.items()}, "share_means": SHARE_MEANS,
           "effects": effects,
           # whether the rig stayed the same during the session, and what the selected effects leave unexplained
           "session": session.to_dict(),
           "unexplained": unexplained,
           "steps": [dict(s) for s in sel.steps],
           # selected: on the residual (modelled, fitted jointly: ``selected_params``), then found where
           # calibration absorbed them (nothing left to model: ``absorbed``).
           "selected": list(sel.selected) + found,
           "modelled": list(sel.selected),
           "absorbed": found,
           "selected_params": final.params() if sel.selected else {},
           # what --effects auto inverts around stage C, and why the other selected effects are not
           "compensation": {"effects": inverted,
                            "params": {n: v for n, v in final.params().items() if n in inverted},
                            "left_out": left_out},
           "evidence": {n: e.to_dict() for n, e in evidence.items()},
           "min_share": min_share, "max_effects": max_effects,
           "what_calibration_absorbs": ABSORBED,
           "seconds": {"render": round(t_render, 1), "fit": round(t_fit, 1),
                       "evidence": round(t_evidence, 1)}}
    doc["clipped_white"] = _clipped_white_gain(data, sel, cam_full)
    doc["headline"] = headline(doc, cam_full)
    maps = residual_maps(res_base, data.mask)
    after = residual_maps(res_final, data.mask)
    scale_abs = max(float(np.percentile(maps["abs"][data.mask], 99)), 1e-3)
    doc["map_scale"] = scale_abs
    white = data.observations[next(i for i, o in enumerate(data.observations) if o.kind == "white")].capture
    images = {"residual_signed.png": _colour_signed(maps["signed"], scale_abs),
              "residual_abs.png": _heat(maps["abs"].mean(axis=2), scale_abs),
              "residual_abs_rgb.png": np.clip(maps["abs"] / scale_abs, 0, 1),
              "residual_after_abs.png": _heat(after["abs"].mean(axis=2), scale_abs),
              "residual_signed.exr": maps["signed"], "residual_abs.exr": maps["abs"],
              "regions.png": _overlay(white, regions, cam_full),
              # 8-bit readers get the region numbers (1 = the first region, 0 = none)
              "regions_label.png": label_image(regions, data.mask.shape, cam_full).astype(np.float32) / 255.0}
    say("done", 1.0)
    return Diagnosis(doc, images, summary_markdown(doc), data)


def _clipped_white_gain(data: GapData, sel: Selection, camera_size: tuple[int, int]) -> dict[str, Any] | None:
    """The glossy model's gain where the white capture clipped, for compensation (``gap/compensation.py``):
    at the parameters fitted with the selected effects, else at those fitted alone; None without a lobe."""
    fit = sel.final if "glossy" in sel.selected else sel.alone.get("glossy")
    if fit is None or fit.error is not None:
        return None
    weight, rough = fit.params()["glossy"].values()
    gain = Composite(data, ("glossy",)).clipped_white_gain(float(weight), float(rough))
    ys, xs = np.nonzero((gain != 1.0).any(axis=2))
    if not len(xs):
        return None
    return {"working_size": list(data.size), "camera_size": list(camera_size),
            "pixels": [[int(x), int(y), *(round(float(v), 4) for v in gain[y, x])] for x, y in zip(xs, ys)]}


def _linear_light(data: GapData, sel: Selection) -> dict[str, Any]:
    """What the selected effects say about the light in the captures, for :func:`.evidence.calibration_evidence`."""
    params = (sel.final or sel.base).params() if sel.selected else {}
    out: dict[str, Any] = {}
    if "camera_response" in params:
        curve = float(params["camera_response"]["curve"])
        out["light"] = lambda img: inverse_camera_curve(img, curve)
    if "glossy" in params:
        weight, rough = params["glossy"]["weight"], params["glossy"]["roughness"]
        out["white_extra"] = float(weight) * glossy_at(data.white, float(rough))
    else:
        out["lobes"] = {r: glossy_at(data.white, r) for r in EVIDENCE_ROUGHNESS}
    return out


def _albedo_from_white(calibration: Calibration) -> bool:
    """Whether calibration read the albedo from the white and black captures (its albedo step ran)."""
    return "albedo" in (calibration.report.get("seconds") or {})
