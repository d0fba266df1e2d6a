"""Several projectors in one show: stage C solved for every projector at once, its folder, and its evaluation.

A calibration of N projectors (``Calibration.projector_count > 1``) reaches
here from ``procam compensate`` and ``procam evaluate``. Every projector has
its own calibration view (``Calibration.for_projector``: its pose, warp and
light-transport operator), and the camera sees their sum; stage C solves all
inputs together on the operators (``stages/joint.py``), so the overlaps are
blended by the optimisation and a blend prior keeps each projector's share
falling smoothly towards its frame edge.

What is shared and what is not:

* the **display area** is the largest rectangle of the target's aspect inside
  the union of the projectors' footprints (model coverage ∩ captured
  white − black of each projector), not inside one projector's;
* the **range** (``--range auto``) is fitted against what the projectors reach
  together: black = the surface lit by every projector's black (the mean of
  their black captures, each taken while the others showed black), white = that
  plus each projector's own white − black (:func:`combined_black_white`);
* **θ** in the open loop is the sum of the projectors' open-loop biases (each
  projector's black level and model error add in light); in the closed loop
  the device shows every projector's frame at once (``Device.project_all``)
  and θ follows those captures.

The compensation folder holds, per target ``NAME``, ``NAME_input_pK.png`` and
``NAME_frame_pK.png`` for projectors K = 1…N (named from 1, as a crew counts
them), the shared ``NAME_simulated.png`` and ``NAME_target.png``, and
``compensation.json`` recording each projector's files, its share of the light
and the rig every input is for. ``procam show`` runs :class:`JointStage` on every
frame (``steps/show.py``: one sequence per projector, warm-started per projector
through :meth:`JointStage.initial_inputs` and :meth:`JointStage.start_from_frames`).
Only the ``transport`` schedule solves several projectors; the render-based ones
are refused with a message.

**Diagnosed effect models** (``--effects auto|NAME,… --diagnosis DIR``, DIR a
diagnosis of this calibration's N projectors, ``projector_K/gap.json`` each):
each projector's own effects are read from its own diagnosis
(:func:`effect_adapters`) and only those of its lamp, lens and electronics
(:data:`..gap.compensation.PROJECTOR_SIDE`): its lens's blur is held in the joint
solve (``T_k B_k``, the answer being the input before the blur, as for one
projector), its tone curve, colour mixing, vignetting and black level's
projector part are inverted on its own frame (g_k⁻¹, in the closed loop through
:class:`..gap.compensation.AdaptedProjectors`). The camera's and the surface's
effects (camera curve, glossy lobe, bounce light, depth error) are every
projector's at once while each projector's diagnosis fits its own parameters for
them: ``auto`` leaves them out (said in the record), naming one is refused.
``compensation.json`` records per projector what was used.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..capture.devices import Device, SomeProjectors
from ..capture.format import CaptureSet
from ..errors import CalibrationError, CaptureError, ProCamError
from ..gap.compensation import (SHARED_INVERTIBLE, AdaptedCaptures, AdaptedProjectors, EffectAdapter, SharedCamera,
                                effects_wanted, projector_adapter)
from ..imageio import write_image
from ..progress import Cancel, Progress, check, part, quiet
from ..stages.bias import BiasModel
from ..stages.calibrate import Calibration
from ..stages.compensate import Compensator, CompensationError
from ..stages.display_area import (DisplayArea, TargetAspectWarning, area_inside, capture_coverage, choose_area,
                                   fit_target, load_target, model_coverage)
from ..stages.joint import JointCompensator, JointResult
from ..stages.metrics import check_capture, psnr, side_by_side, ssim
from ..stages.radiometry import DECISION_MARGIN_SHARE, PixelRadiometry, choose_radiometry
from ..stages import spill as spill_module
from ..stages.range import (RangeError, RangeMap, capture_noise_mse, fit_rule, noise_ceiling, parse_range,
                            range_ceiling)
from . import calibrate as calibrate_step
from . import diagnose as diagnose_step
from . import layout
from . import transport as transport_step
from .stage_c import StageCOptions, device_pipeline, loop_record


def projector_files(name: str, count: int) -> dict[str, Any]:
    """The files ``procam compensate`` writes for target ``name`` with ``count`` projectors."""
    return {"projectors": [{"input": f"{name}_input_p{k + 1}.png", "frame": f"{name}_frame_p{k + 1}.png"}
                           for k in range(count)],
            "simulated": f"{name}_simulated.png", "target": f"{name}_target.png"}


def views_of(calibration: Calibration) -> list[Calibration]:
    """Each projector's one-projector calibration."""
    return [calibration.for_projector(k) for k in range(calibration.projector_count)]


def captures_views(captures: CaptureSet | None, count: int) -> list[CaptureSet] | None:
    """Each projector's one-projector view of the capture set (None when the set cannot be read)."""
    return None if captures is None else [captures.for_projector(k) for k in range(count)]


def footprints(views: list[Calibration], captures: list[CaptureSet] | None = None) -> np.ndarray:
    """(N, H, W) bool: the camera pixels each projector lights, by its model and, when its captures are there,
    by its captured white − black too."""
    out = []
    for k, view in enumerate(views):
        cover = model_coverage(view)
        if captures is not None:
            real = capture_coverage(captures[k].image("white"), captures[k].image("black"))
            if real.shape == cover.shape:
                cover &= real
        out.append(cover)
    return np.stack(out)


def area_shares(cover: np.ndarray, area: DisplayArea) -> list[float]:
    """The share of ``area``'s camera pixels each projector lights (``cover``: (N, H, W) footprints); they add up
    to more than 1 where projectors overlap."""
    crop = np.asarray(cover, bool)[:, area.y:area.y + area.height, area.x:area.x + area.width]
    return [round(float(c.mean()), 4) for c in crop]


def shares_text(shares: list[Any]) -> str:
    """"projector 1 lights 62 % of the area, projector 2 58 %"."""
    parts = [f"{100 * v:.0f} %" if isinstance(v, (int, float)) else "?" for v in shares]
    return "projector 1 lights " + ", ".join(
        f"{p}" if k == 0 else f"projector {k + 1} {p}" for k, p in enumerate(parts)) + " of the area"


def joint_area(views: list[Calibration], aspect: float, *, captures: list[CaptureSet] | None = None,
               margin_px: int | None = None) -> DisplayArea:
    """The largest rectangle of ``aspect`` inside the union of the projectors' footprints."""
    return area_inside(footprints(views, captures).any(axis=0), aspect, margin_px=margin_px,
                       what="the projectors together cover")


def combined_black_white(captures: CaptureSet) -> tuple[np.ndarray, np.ndarray]:
    """What the camera sees with every projector black and every projector white, from each projector's own
    white and black captures, taken while the others showed black: each black holds the whole rig's black (the
    room and every projector's black level), so the rig's black is their mean (the noise halved), and each
    projector adds its own white − black to it.

    (Before, the room's light, the darkest black or the surface photo, was added once and each black's excess over
    it once more: with a surface photo every projector's black level counted K times, and without one the
    per-pixel maximum of two noisy blacks read the rig's black about 10 % too bright.)"""
    count = len(captures.projectors)
    views = [captures.for_projector(k) for k in range(count)]
    blacks = [v.image("black") for v in views]
    whites = [v.image("white") for v in views]
    black = np.mean(blacks, axis=0)
    white = black + sum(w - b for w, b in zip(whites, blacks))
    return black.astype(np.float32), white.astype(np.float32)


def overlap_masks(cover: np.ndarray, area: DisplayArea) -> dict[str, np.ndarray]:
    """Inside the display area (area-size masks): ``overlap`` (lit by two projectors or more), ``outside`` (by one)
    and ``border``, a band of 2 px either side of the overlap's edge — where a seam would show."""
    count = area.crop(cover.sum(axis=0).astype(np.float32)[..., None])[..., 0]
    overlap = count >= 2
    single = count == 1
    kernel = np.ones((5, 5), np.uint8)
    edge = cv2.dilate(overlap.astype(np.uint8), kernel) != cv2.erode(overlap.astype(np.uint8), kernel)
    return {"overlap": overlap, "outside": single, "border": edge & (count >= 1)}


def _psnr_in(image: np.ndarray, target: np.ndarray, mask: np.ndarray) -> float | None:
    if mask.sum() < 16:
        return None
    return round(float(psnr(image[mask], target[mask])), 2)


def seam_step(capture: np.ndarray, target: np.ndarray, overlap: np.ndarray, band: int = 3) -> float | None:
    """The error's step across the overlap's edge: the mean over its edge pixels of |e_in − e_out|, e the capture's
    error (capture − target, channels averaged) averaged over ``band`` px inside and outside the edge (linear,
    0–1). A seam shows as a step; a smooth blend has none."""
    err = (np.asarray(capture, np.float32) - np.asarray(target, np.float32)).mean(axis=2)
    ov = overlap.astype(np.uint8)
    kernel = np.ones((2 * band + 1, 2 * band + 1), np.uint8)
    inner = ov.astype(bool) & ~cv2.erode(ov, kernel).astype(bool)
    outer = cv2.dilate(ov, kernel).astype(bool) & ~ov.astype(bool)
    edge = ov.astype(bool) & ~cv2.erode(ov, np.ones((3, 3), np.uint8)).astype(bool)
    if edge.sum() < 8 or inner.sum() < 8 or outer.sum() < 8:
        return None
    win = (4 * band + 1, 4 * band + 1)
    mean_in = cv2.boxFilter(err * inner, -1, win, normalize=False) / np.maximum(
        cv2.boxFilter(inner.astype(np.float32), -1, win, normalize=False), 1e-6)
    mean_out = cv2.boxFilter(err * outer, -1, win, normalize=False) / np.maximum(
        cv2.boxFilter(outer.astype(np.float32), -1, win, normalize=False), 1e-6)
    both = edge & (cv2.boxFilter(outer.astype(np.float32), -1, win, normalize=False) > 0)
    if both.sum() < 8:
        return None
    return round(float(np.mean(np.abs(mean_in - mean_out)[both])), 5)


def region_scores(capture: np.ndarray, target: np.ndarray, masks: dict[str, np.ndarray]) -> dict[str, Any]:
    """PSNR inside the overlap, outside it and on its border band, and the seam step (area crops)."""
    return {"psnr_overlap": _psnr_in(capture, target, masks["overlap"]),
            "psnr_outside": _psnr_in(capture, target, masks["outside"]),
            "psnr_border": _psnr_in(capture, target, masks["border"]),
            "seam_step": seam_step(capture, target, masks["overlap"]),
            "overlap_share": round(float(masks["overlap"].mean()), 4)}


@dataclass
class JointTarget:
    """Stage C's answer for one target on every projector, as a step writes it."""

    result: JointResult
    fitted: np.ndarray  # the target fitted to the area (area size), range-mapped
    area: DisplayArea
    warnings: list[str]


def effect_adapters(options: StageCOptions, calibration: Calibration) -> list[EffectAdapter | None] | None:
    """Each projector's diagnosed effect models for ``options.effects`` (None: none asked for), read from its own
    diagnosis in the folder ``procam diagnose`` wrote for this calibration of several projectors
    (``projector_K/gap.json``); a diagnosis of another number of projectors or of another calibration is refused."""
    if not effects_wanted(options.effects):
        return None
    if options.diagnosis is None:
        raise ProCamError(f"--effects {options.effects} needs --diagnosis DIR: the folder `procam diagnose CALIB "
                          "--out DIR` wrote, where the effects' parameters were fitted")
    folder = Path(options.diagnosis)
    top = diagnose_step.read(folder).doc
    count = calibration.projector_count
    try:
        theirs = int(top.get("projector_count") or 1)
    except (TypeError, ValueError):
        raise ProCamError(f"the diagnosis in {folder} is malformed (projector_count); run procam diagnose again") \
            from None
    again = "diagnose this calibration (procam diagnose CALIB --out DIR) and give that folder to --diagnosis"
    if theirs != count:
        raise ProCamError(f"the diagnosis in {folder} is of {theirs} projector(s), but the calibration has {count}: "
                          + again)
    if calibration.folder is not None:
        sha, source = top.get("calibration_sha256"), top.get("source")
        if sha is not None and sha != calibrate_step.identity(calibration.folder)["sha256"]:
            raise ProCamError(f"the diagnosis in {folder} was made on another calibration ({source}; its "
                              f"calibration.json differs from {calibration.folder}'s): {again}")
        if sha is None and source and Path(str(source)).resolve() != Path(calibration.folder).resolve():
            raise ProCamError(f"the diagnosis in {folder} was made on another calibration ({source}, not "
                              f"{calibration.folder}): {again}")
    joint = top.get("joint") if isinstance(top.get("joint"), dict) else None
    adapters = []
    for k in range(count):
        sub = folder / diagnose_step.projector_folder(k)
        doc = diagnose_step.read(sub).doc
        if joint is not None:  # each projector's own effects as fitted beside the camera's, not its diagnosis alone
            try:
                mine = dict(joint["projectors"][k]["params"])
                auto = dict(joint["compensation"]["projectors"][k])
            except (KeyError, IndexError, TypeError, ValueError):
                raise ProCamError(f"the diagnosis in {folder} is malformed (joint); run procam diagnose again") \
                    from None
            doc = {**doc, "selected_params": {**(doc.get("selected_params") or {}), **mine},
                   "compensation": {**(doc.get("compensation") or {}), "params": auto}}
        adapters.append(projector_adapter(options.effects, doc, calibration.for_projector(k).rig.projector,
                                          where=f"projector {k + 1}'s diagnosis in {sub}"))
    return adapters


def shared_effects(options: StageCOptions) -> dict[str, dict[str, float]] | None:
    """The camera's effects ``--effects`` asks of a diagnosis of several projectors, fitted once on every
    projector's patterns (``gap.json``'s ``joint``): ``auto`` what the diagnosis selected and compensation inverts,
    a name its parameters (selected, else fitted alone); None when none. A diagnosis without a joint fit (made
    before it) has none for ``auto`` and is refused for a name."""
    if not effects_wanted(options.effects) or options.diagnosis is None:
        return None
    spec = (options.effects or "").strip().lower()
    named = [n.strip() for n in spec.split(",") if n.strip() in SHARED_INVERTIBLE]
    if spec != "auto" and not named:
        return None
    folder = Path(options.diagnosis)
    joint = diagnose_step.read(folder).doc.get("joint")
    if not isinstance(joint, dict):
        if named:
            raise ProCamError(f"--effects {', '.join(named)}: the diagnosis in {folder} has no fit of the camera's "
                              "effects on every projector's patterns (made by an older ProCam): run procam diagnose "
                              "again")
        return None
    try:
        if spec == "auto":
            params = dict((joint.get("compensation") or {}).get("shared") or {})
        else:
            fitted = {**(joint.get("fitted_alone") or {}), **(joint.get("params") or {})}
            missing = [n for n in named if n not in fitted]
            if missing:
                raise ProCamError(f"the diagnosis in {folder} has no fitted parameters for {', '.join(missing)} on "
                                  "every projector's patterns (no projector's residual showed it); rerun procam "
                                  "diagnose with it")
            params = {n: dict(fitted[n]) for n in named}
    except (AttributeError, TypeError, ValueError):
        raise ProCamError(f"the diagnosis in {folder} is malformed (joint); run procam diagnose again") from None
    if "camera_response" in params and "curve" not in params["camera_response"]:
        raise ProCamError(f"the diagnosis in {folder} is malformed (camera_response); run procam diagnose again")
    return params or None


class JointStage:
    """Stage C of one calibration of several projectors for a run of targets (module doc); a context manager that
    closes the device it opened."""

    def __init__(self, calibration: Calibration, options: StageCOptions, *, device: Device | None = None,
                 progress: Progress | None = None) -> None:
        say = progress or quiet
        count = calibration.projector_count
        schedule = options.check()
        if not schedule.transport:
            raise CompensationError(f"several projectors are solved together on their light-transport operators "
                                    f"only: compensate with --schedule transport (the {schedule.name!r} schedule "
                                    "renders one projector)")
        self.calibration, self.options, self.schedule = calibration, options, schedule
        #: each projector's diagnosed effect models (module doc), None without --effects
        self.adapters = effect_adapters(options, calibration)
        self.views = views_of(calibration)
        full = calibrate_step.captures_of(calibration, required=False)
        self.captures = full
        self.capture_views = captures_views(full, count)
        self.user_area = choose_area(calibration, aspect=1.0, user=options.area) if options.area else None
        self.areas: dict[str, DisplayArea] = {}
        self._cover: np.ndarray | None = None
        given = parse_range(options.range)
        self.range_map: RangeMap | None = given if isinstance(given, RangeMap) else None
        self._owned = device is None
        self.device: Any = device_pipeline(options.device, calibration, device=device,
                                           progress=part(say, 0.0, 0.0, "device: ")) \
            if options.mode == "closed-loop" else None
        #: what the run says of each projector's stored operator (one rendered in memory, and why), for its record
        self.transport_notes: list[str] = []
        try:
            if self.device is not None and len(getattr(self.device, "projectors", (None,))) != count:
                raise CaptureError(f"the device {options.device} shows {len(self.device.projectors)} projector(s), "
                                   f"but the calibration has {count}: give a device of this rig")
            self.compensators = []
            for k, view in enumerate(self.views):
                say(f"projector {k + 1}/{count}: loading the calibrated scene", 0.0)
                comp = Compensator(view, bounces=options.bounces, spp=options.spp, seed=options.seed)
                comp.surround = options.surround or (0.0, 0.0, 0.0)  # held outside the display area, not solved
                found = transport_step.find(view, bounces=options.bounces, seed=options.seed)
                if found.operator is None:  # said unthrottled and recorded: every run pays for it until stored
                    note = f"projector {k + 1}: " + transport_step.rebuild_note(view, found, bounces=options.bounces,
                                                                                seed=options.seed)
                    self.transport_notes.append(note)
                    say(f"note: {note}", 0.0)
                else:
                    comp.transport = found.operator
                adapter = None if self.adapters is None else self.adapters[k]
                if adapter is not None:
                    adapter.blur_in_solve(comp)  # its lens's blur held in the joint solve: T_k B_k
                self.compensators.append(comp)
            camera = shared_effects(options)
            #: the camera's tone curve fitted once on every projector's patterns (None: not modelled)
            self.camera = None if camera is None else SharedCamera(camera, [c.white() for c in self.compensators])
            if self.camera is not None and self.adapters is None:
                self.adapters = [None] * count
            if self.device is not None and self.adapters is not None:
                self.device = AdaptedProjectors(self.device, self.adapters, self.camera)
            self.joint = JointCompensator(self.compensators)
            self._subsets: dict[tuple[int, ...], JointCompensator] = {}
            self.biases: list[BiasModel] | None = None
            self.black: np.ndarray | None = None
            #: each projector's per-pixel radiometric model when :meth:`choose_radiometry` chose them, and the record
            self.pixels: list[PixelRadiometry] | None = None
            self.radiometry: dict[str, Any] | None = None
        except BaseException:
            self.close()
            raise

    @property
    def count(self) -> int:
        return len(self.views)

    def coverage(self) -> np.ndarray:
        """(N, H, W) each projector's footprint in the camera, computed once."""
        if self._cover is None:
            self._cover = footprints(self.views, self.capture_views)
        return self._cover

    def choose_radiometry(self) -> dict[str, Any]:
        """Whether the open loop works through each camera pixel's own model of each projector (``--radiometry``,
        stages/radiometry.py; docs/methods.md, "Several projectors"), decided once for the run; the record.

        Each projector's model comes from its own flats (the others black) and is judged on its own held-out
        captures, as one projector's is; ``auto`` uses them when, pooled over the projectors, they predict those
        captures better than the global models (one answer for the rig: a projector whose global models hold it
        well and one they do not, on the suite's lab 0.0089 against 0.0072 and 0.0122 against 0.0742, take the
        per-pixel models together). A closed loop keeps the global models with ``auto`` (it learns each pixel
        itself); with ``pixel`` it starts from the per-pixel models' answer and corrects it in the camera's units,
        as one projector's does. A run with ``--effects`` keeps them (``pixel`` refused): the effect models'
        camera curve is shared by every projector, which the per-projector models cannot split."""
        if self.radiometry is not None:
            return self.radiometry
        rule = self.options.radiometry
        if rule == "global":
            self.radiometry = {"used": "global", "rule": rule}
            return self.radiometry
        closed = self.options.mode != "open-loop"
        if closed and rule == "auto":
            self.radiometry = {"used": "global", "rule": rule, "reason": "a closed loop learns each pixel's response "
                               "from its own captures (--radiometry pixel starts it from the per-pixel models' answer)"}
            return self.radiometry
        why = ("with --effects the rig's shared camera curve and each projector's effect models stay global"
               if self.adapters is not None or self.camera is not None
               else "the calibration's capture set cannot be read" if self.capture_views is None else None)
        if why is not None:
            if rule == "pixel":
                raise CompensationError(f"--radiometry pixel cannot be used here: {why}; use --radiometry auto or "
                                        "global")
            self.radiometry = {"used": "global", "rule": rule, "reason": why}
            return self.radiometry
        assert self.capture_views is not None
        models, records = [], []
        for comp, view in zip(self.compensators, self.capture_views):
            try:
                model, record = choose_radiometry(comp, view, "pixel")
            except CalibrationError as exc:
                if rule == "pixel":
                    raise
                self.radiometry = {"used": "global", "rule": rule, "reason": str(exc)}
                return self.radiometry
            assert model is not None
            models.append(model)
            records.append({k: v for k, v in record.items() if k not in ("used", "rule")})
        rmse = [r["held_out_rmse"] for r in records]
        pooled = {m: float(np.sqrt(np.mean([r[m] ** 2 for r in rmse]))) for m in ("pixel", "global")}
        better = pooled["pixel"] < DECISION_MARGIN_SHARE * pooled["global"]
        used = "pixel" if rule == "pixel" or better else "global"
        self.radiometry = {"used": used, "rule": rule, "projectors": records,
                           "held_out_rmse_pooled": {m: round(v, 5) for m, v in pooled.items()}}
        if rule == "auto":
            said = "; ".join(f"projector {k + 1}: RMS {r['pixel']:.4f} against {r['global']:.4f}"
                             for k, r in enumerate(rmse))
            self.radiometry["reason"] = (f"the projectors' per-pixel models predict their held-out captures "
                                         f"{'better' if better else 'no better'} than the global models (pooled RMS "
                                         f"{pooled['pixel']:.4f} against {pooled['global']:.4f}; {said})")
        if used == "pixel":
            if closed:
                self.radiometry["closed_loop"] = ("starts from the per-pixel models' answer, corrects in the "
                                                  "camera's units")
            self.pixels = models
            cw, ch = self.compensators[0].camera_size
            self.use_biases([BiasModel(np.zeros((ch, cw, 3), np.float32), None, "pixel",
                                       {"radiometry": "each camera pixel's own model; θ = 0"})] * self.count)
            self.black = None  # each projector's model holds the rig's black (its black capture)
        return self.radiometry

    def keep_global_radiometry(self, why: str) -> None:
        """Use the global models whatever ``--radiometry`` says (a path that cannot take the per-pixel models)."""
        if self.radiometry is None:
            self.radiometry = {"used": "global", "rule": self.options.radiometry, "reason": why}

    def model_target(self, fitted: np.ndarray, area: DisplayArea, joint: JointCompensator, keep: list[int]
                     ) -> np.ndarray:
        """A target fitted to the display area in the units the joint solve compares with its model's light: through
        each projector's per-pixel model (:meth:`pixel_target`), else through the rig's camera curve when
        ``--effects`` inverts it, else as it is (the same for :meth:`compensate` and a show's warm starts,
        :meth:`initial_inputs`)."""
        if self.pixels is not None:
            return self.pixel_target(fitted, area, joint, keep)
        return fitted if self.camera is None else self.camera.to_model(fitted, area)

    def pixel_target(self, fitted: np.ndarray, area: DisplayArea, joint: JointCompensator, keep: list[int]
                     ) -> np.ndarray:
        """The light the joint solve is asked for through each projector's per-pixel model: projector k gives its
        blend share β_k of the target above the rig's black, ``to_light_k(b + β_k (t − b))``, and the solve is asked
        for their sum (where one projector lights alone, its own model's answer). Split in the camera's values, not
        in light: on the lab of other forms the light split scored 1.9 dB less in the overlap (docs/methods.md)."""
        assert self.pixels is not None
        shares = joint.shares()
        total = np.zeros_like(np.asarray(fitted, np.float32))
        for i, k in enumerate(keep):
            model = self.pixels[k].crop(area)
            beta = area.crop(shares[i])[..., None]
            total += model.to_light(model.black + beta * (fitted - model.black))
        return total

    def estimate_bias(self) -> list[BiasModel]:
        """Each projector's open-loop θ model, from its own white, black and validation captures (θ = 0 through the
        per-pixel models, :meth:`choose_radiometry`)."""
        if self.pixels is not None:
            assert self.biases is not None
            return self.biases
        if self.capture_views is None:
            raise CompensationError(f"open-loop compensation needs the calibration's capture set to estimate θ, "
                                    f"but it cannot be read at {self.calibration.capture_dir!r}: put it back")
        views: list[Any] = list(self.capture_views)
        if self.camera is not None:  # each projector's captures seen through the camera's curve in its own units
            views = [AdaptedCaptures(v, self.camera.for_projector(k, a, comp.rig.projector))
                     for k, (v, a, comp) in enumerate(zip(views, self.adapters or [None] * self.count,
                                                          self.compensators))]
        elif self.adapters is not None:  # each projector's captures paired with the light it emitted
            views = [v if a is None else AdaptedCaptures(v, a) for v, a in zip(views, self.adapters)]
        self.use_biases([comp.estimate_bias(view) for comp, view in zip(self.compensators, views)])
        assert self.biases is not None
        return self.biases

    def use_biases(self, biases: list[BiasModel]) -> None:
        """Open-loop θ models estimated before (a show's, read back when it resumes) instead of estimating them."""
        if len(biases) != self.count:
            raise CompensationError(f"{len(biases)} open-loop θ model(s) for {self.count} projectors")
        if self.capture_views is None:
            raise CompensationError(f"open-loop compensation needs the calibration's capture set, but it cannot be "
                                    f"read at {self.calibration.capture_dir!r}: put it back")
        self.biases = list(biases)
        # What every θ_k holds once and their sum K times: the darkest black capture (the room's light, with the
        # other projectors' black levels where they showed black while it was taken).
        self.black = np.min([v.image("black") for v in self.capture_views], axis=0)
        if self.camera is not None:
            self.black = self.camera.to_model(self.black)

    def initial_inputs(self, image: np.ndarray) -> list[np.ndarray]:
        """Each projector's z that :meth:`compensate` starts a target from on its own (its share of target + θ
        over its white, the joint solve's own start): with :meth:`start_from_frames`, a warm start carries the
        previous frame's correction over, per projector."""
        o = self.options
        open_loop = o.mode == "open-loop"
        self.choose_radiometry()
        if open_loop and self.biases is None:
            self.estimate_bias()
        area = self.area_for(image)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TargetAspectWarning)  # said when the target is compensated
            fitted = self.fitted(image, area)
        # The joint solve's own start, built by its own steps (no second copy of them to drift): θ is zero in the
        # closed loop's start as in no-bias mode. A projector dark in the area starts (and stays) black.
        _, keep, joint, _, biases = self._solver(area)
        area, placed = joint._place(self.model_target(fitted, area, joint, keep), area, "the target")
        _, gains, theta = joint._mode(None, open_loop, biases if open_loop else None,
                                      self.black if open_loop else None)
        out = [np.zeros((comp.ih, comp.iw, 3), np.float32) for comp in self.compensators]
        for k, z in zip(keep, joint._starts(placed, theta, gains, joint.shares())):
            out[k] = z
        return out

    def start_from_frames(self, frames: list[np.ndarray]) -> list[np.ndarray]:
        """Each projector's virtual input z whose native frame is ``frames[k]`` (as :meth:`compensate` made it):
        its input area cut out, its warp undone (z = M(x))."""
        if len(frames) != self.count:
            raise CompensationError(f"{len(frames)} frames to start from for {self.count} projectors")
        out = []
        for k, (comp, frame) in enumerate(zip(self.compensators, frames)):
            proj = comp.rig.projector
            (x0, y0), (w, h) = proj.input_offset, proj.input_size
            if frame.shape[:2] != tuple(proj.intrinsics.size)[::-1]:
                raise CompensationError(f"a frame of projector {k + 1} to start from must be "
                                        f"{proj.intrinsics.size[0]}×{proj.intrinsics.size[1]}, got "
                                        f"{frame.shape[1]}×{frame.shape[0]}")
            x = np.asarray(frame[y0:y0 + h, x0:x0 + w, :3], np.float32)
            adapter = None if self.adapters is None else self.adapters[k]
            if adapter is not None:  # the light the frame makes (before the lens's blur when the solve holds it)
                x = np.clip(adapter.emitted(x, blur=not adapter.defocus_in_solver), 0.0, 1.0)
            out.append(comp.warp_m(x))
        return out

    def area_for(self, image: np.ndarray) -> DisplayArea:
        """The user's area, the capture set's, else the largest of the target's aspect the projectors cover; an
        area no projector lights is refused (:meth:`dark_in`), before any folder is made."""
        if self.user_area is not None:
            area = self.user_area
        elif self.captures is not None and self.captures.target_area is not None:
            area = choose_area(self.calibration, aspect=1.0, captures=self.captures)
        else:
            aspect = image.shape[1] / image.shape[0]
            key = f"{aspect:.4f}"
            if key not in self.areas:
                self.areas[key] = joint_area(self.views, aspect, captures=self.capture_views)
            area = self.areas[key]
        self.dark_in(area)
        return area

    def lit_in(self, area: DisplayArea) -> list[int]:
        """How many camera pixels of ``area`` each projector lights (its footprint, :meth:`coverage`)."""
        cover = self.coverage()[:, area.y:area.y + area.height, area.x:area.x + area.width]
        return [int(n) for n in cover.sum(axis=(1, 2))]

    def dark_in(self, area: DisplayArea) -> list[int]:
        """The projectors (0-based) whose light misses ``area``: fewer than :data:`MIN_LIT` of its pixels lit. All of
        them: refused (:class:`CompensationError`), as no projector can show the target there."""
        lit = self.lit_in(area)
        dark = [k for k, n in enumerate(lit) if n < MIN_LIT]
        if len(dark) == self.count:
            raise CompensationError(f"none of the {self.count} projectors lights the display area "
                                    f"({area.width}×{area.height} at {area.x},{area.y}; pixels lit: "
                                    f"{', '.join(map(str, lit))}): choose an area inside their footprints")
        return dark

    def fix_range(self, images: list[np.ndarray]) -> RangeMap | None:
        """``--range auto`` fitted against what the projectors reach together (:func:`combined_black_white`)."""
        rule = parse_range(self.options.range)
        if not isinstance(rule, str) or rule == "none":
            return self.range_map
        if self.captures is None:
            raise RangeError(f"--range {rule} needs the white and black captures of the calibration's capture set, "
                             f"which cannot be read at {self.calibration.capture_dir!r}: put it back, or give "
                             "--range GAIN,OFFSET")
        black, white = combined_black_white(self.captures)
        fitted, blacks, whites, areas = [], [], [], []
        for image in images:
            area = self.area_for(image)
            areas.append(area)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", TargetAspectWarning)
                fitted.append(fit_target(image, area))
            blacks.append(area.crop(black))
            whites.append(area.crop(white))
        self.range_map = fit_rule(rule, fitted, blacks, whites, areas, self.calibration.rig.camera.intrinsics)
        return self.range_map

    def fitted(self, image: np.ndarray, area: DisplayArea, what: str = "the target") -> np.ndarray:
        out = fit_target(image, area, what=what)
        return out if self.range_map is None else self.range_map.apply(out, area)

    def _solver(self, area: DisplayArea) -> tuple[list[int], list[int], JointCompensator, Any,
                                                  list[BiasModel] | None]:
        """The projectors dark in ``area`` and those kept, and the joint solve, device and θ models of the kept."""
        dark = self.dark_in(area)
        keep = [k for k in range(self.count) if k not in dark]
        joint, device, biases = self.joint, self.device, self.biases
        if dark:
            joint = self._subsets.get(tuple(keep)) or self._subsets.setdefault(
                tuple(keep), JointCompensator([self.compensators[k] for k in keep]))
            device = None if device is None else SomeProjectors(device, keep)
            biases = None if biases is None else [biases[k] for k in keep]
        return dark, keep, joint, device, biases

    def compensate(self, image: np.ndarray, *, name: str, what: str, progress: Progress | None = None,
                   cancel: Cancel | None = None, blend: str = "derived",
                   start: list[np.ndarray] | None = None) -> JointTarget:
        """Stage C for one target on every projector at once; ``start``: each projector's z to start from (a warm
        start, :meth:`initial_inputs`), else the joint solve's own start."""
        o = self.options
        self.choose_radiometry()
        if o.mode == "open-loop" and self.biases is None:
            self.estimate_bias()
        area = self.area_for(image)
        args = o.run_arguments()
        args.pop("lr", None)
        args.pop("alpha", None)
        # A projector whose light misses the area has nothing to solve for there: the others are solved together
        # and it shows black (its operator holds no light in the area, so it cannot join the solve).
        dark, keep, joint, device, biases = self._solver(area)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", TargetAspectWarning)
            fitted = self.fitted(image, area, what)
            model_target = self.model_target(fitted, area, joint, keep)
            if self.pixels is not None and device is not None:
                # the closed loop starts from the per-pixel models' open-loop answer, then corrects it in the
                # camera's units (as one projector's: stage_c.StageC.compensate; no --effects, so no camera curve)
                assert self.biases is not None
                first = joint.run(model_target, area, biases=[self.biases[k] for k in keep], blend=blend,
                                  cancel=cancel, name=name, start=None if start is None else [start[k] for k in keep],
                                  **{**args, "iterations_z": self.schedule.iterations_z, "iterations_joint": 0})
                start = [np.zeros((c.ih, c.iw, 3), np.float32) for c in self.compensators]
                for k, z in zip(keep, first.z):
                    start[k] = z
                args["iterations_z"] = 0
                model_target = fitted
            res = joint.run(model_target, area, device=device, biases=biases if o.mode == "open-loop" else None,
                            black=self.black if o.mode == "open-loop" else None, use_bias=o.use_bias, blend=blend,
                            progress=progress, cancel=cancel, name=name,
                            start=None if start is None else [start[k] for k in keep], **args)
        notes = [str(w.message) for w in caught]
        if self.adapters is not None and any(a is not None for a in self.adapters):
            # the inputs the solve answered are light: each projector sends g_k⁻¹ of it
            inputs, frames = list(res.x_inputs), list(res.x_frames)
            for i, k in enumerate(keep):
                if (adapter := self.adapters[k]) is not None:
                    inputs[i], frames[i] = adapter.input_for(res.x_inputs[i]), adapter.frame_to_send(res.x_inputs[i])
            res = replace(res, x_inputs=inputs, x_frames=frames)
        if dark:
            res = _with_black(res, keep, list(self.calibration.rig.projectors))
            notes += [f"projector {k + 1} lights nothing inside the display area ({area.width}×{area.height} at "
                      f"{area.x},{area.y}): its frame is black, the other projectors show the target there"
                      for k in dark]
        return JointTarget(res, fitted, area, notes)

    def settings(self) -> dict[str, Any]:
        """What decides the pixels of every target."""
        o, s = self.options, self.schedule
        return {"mode": o.mode, "device": o.device_spec, "schedule": s.name,
                "iterations": {"total": s.iterations_z + s.iterations_joint, "z": s.iterations_z,
                               "joint": s.iterations_joint},
                "bounces": o.bounces, "spp": o.spp, "seed": o.seed, "area_given": list(o.area) if o.area else None,
                "surround": list(o.surround or (0.0, 0.0, 0.0)),
                "target_encoding": o.target_encoding, "blend": "derived", "projector_count": self.count,
                "range": None if self.range_map is None else self.range_map.to_dict(), "effects": self.effects(),
                "radiometry": self.radiometry or {"used": "global", "rule": o.radiometry},
                **({"transport_notes": list(self.transport_notes)} if self.transport_notes else {})}

    def load(self, path: str | Path) -> tuple[np.ndarray, str]:
        """A target image as stage C reads it (linear light; the note says how it was decoded)."""
        return load_target(path, encoding=self.options.target_encoding)

    def target_files(self, name: str) -> list[str]:
        """Every file a target ``name`` writes (a target cut short leaves none)."""
        files = projector_files(name, self.count)
        return [files["simulated"], files["target"], *(v for e in files["projectors"] for v in e.values()),
                layout.correction_file(name)]

    def bias_record(self) -> list[dict[str, Any]] | None:
        """Each projector's open-loop θ model as the manifest records it (None in the closed loop)."""
        return None if self.biases is None else [{"kind": b.kind, **b.report} for b in self.biases]

    def effects(self) -> dict[str, Any] | None:
        """The diagnosed effect models used, per projector (None without --effects): the diagnosis folder, and for
        projector K the effects used, those not inverted and why, their parameters and the blur held in the solve."""
        if self.adapters is None:
            return None
        camera = None if self.camera is None else {"used": list(self.camera.params), "params": self.camera.params}
        return {"diagnosis": str(Path(self.options.diagnosis or "").absolute()), "camera": camera, "projectors": [
            {"used": [], "not_inverted": {}, "params": {}, "input_blur": None} if a is None else
            {"used": a.used, "not_inverted": a.not_used, "params": a.params,
             "input_blur": comp.input_blur} for a, comp in zip(self.adapters, self.compensators)]}

    def rig_record(self) -> dict[str, Any]:
        """The rig the inputs are for: every projector's frame, input size and offset, and the camera's size."""
        projectors = [layout.projector_record(p) for p in self.calibration.rig.projectors]
        return {"projector": projectors[0], "projectors": projectors,
                "camera_size": list(self.calibration.rig.camera.intrinsics.size)}

    def close(self) -> None:
        if self._owned and self.device is not None:
            self.device.close()
        self.device = None

    def __enter__(self) -> JointStage:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


#: Fewer camera pixels of the display area than this lit by a projector, and it is left out of the solve (black).
MIN_LIT = 16


def _black_input(projector: Any) -> np.ndarray:
    w, h = projector.input_size
    return np.zeros((h, w, 3), np.float32)


def _with_black(res: JointResult, keep: list[int], projectors: list[Any]) -> JointResult:
    """A joint answer of the projectors ``keep`` as one of all ``projectors``: the others' inputs black, share 0."""
    inputs = [_black_input(p) for p in projectors]
    frames = [p.frame_from_input(x) for p, x in zip(projectors, inputs)]
    zs = [x.copy() for x in inputs]
    shares: list[Any] = [0.0] * len(projectors)
    for i, k in enumerate(keep):
        inputs[k], frames[k], zs[k] = res.x_inputs[i], res.x_frames[i], res.z[i]
        shares[k] = (res.report.get("share_of_light") or [None] * len(keep))[i]
    report = {**res.report, "projectors": len(projectors), "share_of_light": shares,
              "dark_projectors": [k + 1 for k in range(len(projectors)) if k not in keep]}
    return replace(res, x_inputs=inputs, x_frames=frames, z=zs, report=report)


def write_target(stage: JointStage, tmp: Path, done: JointTarget, name: str) -> dict[str, Any]:
    """One target's files into ``tmp`` and its record (the first projector's files also under the one-projector
    keys, so a reader of one projector's folder finds projector 1's)."""
    res = done.result
    files = projector_files(name, stage.count)
    for k, entry in enumerate(files["projectors"]):
        write_image(tmp / entry["input"], res.x_inputs[k])
        write_image(tmp / entry["frame"], res.x_frames[k])
    write_image(tmp / files["simulated"], res.simulated)
    write_image(tmp / files["target"], done.fitted)
    shares = res.report.get("share_of_light") or [None] * stage.count
    lit = area_shares(stage.coverage(), done.area)  # what each projector lights of the area, besides its light
    projectors = [{**entry, "share": shares[k], "area_share": lit[k]} for k, entry in enumerate(files["projectors"])]
    if stage.adapters is not None:  # the lens's blur each projector's solve held (its σ, input texels)
        for entry, comp in zip(projectors, stage.compensators):
            entry["input_blur"] = comp.input_blur
    loop = loop_record(tmp, name, res)
    return {"name": name, "status": "done", "warnings": done.warnings, "mode": res.mode,
            "area": done.area.to_dict(), "area_shares": lit, "input": projectors[0]["input"],
            "frame": projectors[0]["frame"],
            "simulated": files["simulated"], "target": files["target"], "projectors": projectors,
            "seconds": round(res.seconds, 2), "captures": res.captures,
            "losses": [round(float(v), 7) for v in res.losses],
            "psnr_simulated_start": res.report.get("psnr_simulated_start"),
            "psnr_simulated": res.report.get("psnr_simulated"),
            "psnr_simulated_overlap": res.report.get("psnr_overlap"),
            "psnr_simulated_outside": res.report.get("psnr_outside_overlap"),
            **({"loop": loop} if loop else {})}


def one_target(stage: JointStage, tmp: Path, image: np.ndarray, note: str, name: str, path: Path, i: int, n: int,
               say: Progress, cancel: Cancel | None) -> dict[str, Any]:
    """Compensate one target on every projector and write its files into ``tmp``; returns its record (the
    compensate step's loop, ``steps/compensate.py``, runs it for several projectors)."""
    check(cancel, "compensation was cancelled")
    area = stage.area_for(image)
    say(f"target {i + 1}/{n}: {name} on {stage.count} projectors ({area.width}×{area.height} at "
        f"{area.x},{area.y}; {shares_text(area_shares(stage.coverage(), area))})", 0.05 + 0.95 * i / n)
    done = stage.compensate(image, name=name, what=f"target {path.name}", cancel=cancel,
                            progress=part(say, 0.05 + 0.95 * i / n, 0.05 + 0.95 * (i + 1) / n,
                                          f"target {i + 1}/{n} {name}: "))
    for w in done.warnings:
        say(f"warning: {w}", 0.05 + 0.95 * (i + 1) / n)
    return {**write_target(stage, tmp, done, name), "file": str(path.absolute()), "encoding": note}


# -- evaluation -------------------------------------------------------------------------------------------------

def uncompensated_frames(stage_views: list[Compensator], placed: np.ndarray, cover: np.ndarray) -> list[np.ndarray]:
    """The uncompensated baseline of several projectors: each shows the target carried into it by the calibrated
    geometry, divided where it overlaps by the number of projectors lighting the pixel (a hard split, no blend),
    so that the overlap is not twice as bright."""
    count = np.maximum(cover.sum(axis=0), 1).astype(np.float32)[..., None]
    frames = []
    for k, comp in enumerate(stage_views):
        share = placed * cover[k][..., None] / count
        x = comp.warp_w(comp.initial_input(share.astype(np.float32), how="geometric"))
        frames.append(comp.rig.projector.frame_from_input(x))
    return frames


def project_all(device: Device, frames: list[np.ndarray], camera_size: tuple[int, int]) -> np.ndarray:
    """Every projector's frame shown at once; the capture, checked."""
    return check_capture(device.project_all(frames), camera_size)


def score(capture: np.ndarray, fitted: np.ndarray, area: DisplayArea, masks: dict[str, np.ndarray]
          ) -> dict[str, Any]:
    """PSNR/SSIM of a capture in the area, and inside/outside the overlap and along its border."""
    crop = area.crop(capture)
    return {"psnr": round(float(psnr(crop, fitted)), 4), "ssim": round(float(ssim(crop, fitted)), 5),
            **region_scores(crop, fitted, masks)}


def evaluate(calibration: Calibration, inputs: Any, targets: list[tuple[str, np.ndarray, str]], device: Device,
             out: Path, *, notes: list[str], repeat: bool = True, progress: Progress | None = None,
             cancel: Cancel | None = None) -> tuple[dict[str, Any], ProCamError | None]:
    """``procam evaluate`` of a compensation of several projectors: every projector's frame shown at once through
    ``device``, the capture scored over the area, inside the overlaps, outside them and along their borders, next to
    the uncompensated baseline, and the range ceiling of the projectors together. Writes the comparison images
    into ``out``; returns ``metrics.json``'s document and the failure that stopped it (finished targets kept)."""
    say = progress or quiet
    inputs.check_projectors(calibration)
    cam = calibration.rig.camera.intrinsics.size
    projectors = list(calibration.rig.projectors)
    for name, _, _ in targets:
        inputs.record(name)
        inputs.frames(name, projectors)  # every frame read before the first projection
    if len(getattr(device, "projectors", (None,))) != len(projectors):
        raise CaptureError(f"the device shows {len(getattr(device, 'projectors', (None,)))} projector(s), but the "
                           f"calibration has {len(projectors)}: give the device of this rig")
    views = views_of(calibration)
    comps = [Compensator(v, bounces=0, spp=4) for v in views]
    captures = calibrate_step.captures_of(calibration)
    assert captures is not None
    cover = footprints(views, captures_views(captures, len(views)))
    black, white = combined_black_white(captures)
    reach = cover.any(axis=0)
    range_map = RangeMap.from_dict(inputs.doc.get("range"))
    rows: list[dict[str, Any]] = []
    failure: ProCamError | None = None
    for i, (name, image, note) in enumerate(targets):
        rec = inputs.record(name)
        area = rec.area.check(cam)
        files = {k: v.format(name=name) for k, v in layout.EVALUATION_FILES.items() if k != "classical"}
        check(cancel, "evaluation was cancelled; nothing was written")
        say(f"target {i + 1}/{len(targets)}: {name} on {len(projectors)} projectors", 0.05 + 0.95 * i / len(targets))
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", TargetAspectWarning)
                fitted = fit_target(image, area, what=f"target {name!r}")
            if range_map is not None:
                fitted = range_map.apply(fitted, area)
            masks = overlap_masks(cover, area)
            frames = inputs.frames(name, projectors)
            got = project_all(device, frames, cam)
            placed = area.place(fitted, cam)
            plain = project_all(device, uncompensated_frames(comps, placed, cover), cam)
            row: dict[str, Any] = {"name": name, **score(got, fitted, area, masks),
                                   "uncompensated": score(plain, fitted, area, masks),
                                   "range_ceiling": round(range_ceiling(fitted, area.crop(black), area.crop(white)),
                                                          2)}
            again = None
            if repeat:
                again = project_all(device, frames, cam)
                if not np.array_equal(again, got):
                    noise = capture_noise_mse(area.crop(got), area.crop(again))
                    row["capture_noise_rmse"] = round(noise ** 0.5, 5)
                    row["noise_ceiling"] = round(noise_ceiling(fitted, area.crop(black), area.crop(white), noise), 2)
                else:
                    again = None
            spill_module.record(row, got, plain, black, area, reach, again=again)
            row["area_shares"] = area_shares(cover, area)
        except ProCamError as exc:
            failure = exc
            rows.append({"name": name, "status": "failed", "error": str(exc)})
            say(f"{name}: failed: {exc}", 1.0)
            break
        row.update(warnings=[str(w.message) for w in caught], target_encoding=note, area=area.to_dict(),
                   mode=rec.mode, image=files["image"], status="done")
        write_image(out / files["image"], side_by_side(fitted, area.crop(plain), area.crop(got)))
        write_image(out / files["capture"], got)
        write_image(out / files["uncompensated"], plain)
        rows.append(row)
    done = [r for r in rows if r.get("status") == "done"]

    def mean(key: str, of: str | None = None) -> float | None:
        vals = [(r[of] if of else r).get(key) for r in done]
        vals = [v for v in vals if isinstance(v, (int, float))]
        return round(float(np.mean(vals)), 4) if vals else None

    keys = ("psnr", "ssim", "psnr_overlap", "psnr_outside", "psnr_border", "seam_step")
    doc = {"format": layout.EVALUATION.format, "version": layout.EVALUATION.version,
           "inputs": str(inputs.path.absolute()), "capture_set": calibration.capture_dir, "notes": notes,
           "projector_count": len(projectors),
           "measure": "PSNR (dB, peak 1) and SSIM of the capture with every projector's frame shown at once, inside "
                      "the display area against the target fitted to it (and range-mapped); psnr_overlap / "
                      "psnr_outside: inside the area where two or more projectors light the surface / where one "
                      "does; psnr_border: a 2-px band either side of the overlap's edge; seam_step: the mean "
                      "absolute step of the capture's error across the overlap's edge (linear 0–1; a seam is a "
                      "step); uncompensated: each projector showing the target as is, split evenly where they "
                      "overlap; range_ceiling: the target clipped to what the projectors reach together; "
                      "area_shares: the share of the area's pixels each projector lights; " + spill_module.MEASURE,
           "range": None if range_map is None else range_map.to_dict(),
           "targets": rows, "mean": {k: mean(k) for k in keys},
           "mean_uncompensated": {k: mean(k, "uncompensated") for k in keys},
           "mean_range_ceiling": mean("range_ceiling"), "mean_noise_ceiling": mean("noise_ceiling"),
           "flicker": None, "spill": spill_module.summarise(done, cam[0]), "complete": failure is None}
    return doc, failure
