"""The calibration pipeline's optimisations: capture set → surface (S_g, S_c) → projector pose (stage A)
→ warp (stage B).

:func:`calibrate_captures` runs the stages and returns a :class:`Calibration`
with its diagnostic images; writing and reading the calibration folder is
``steps/calibrate.py``'s. The albedo is read where the projector reaches, as
the method advises for a dark room: (white − black) divided by the simulated
irradiance of the white frame once the pose is known; elsewhere the room-lit
surface photo, scaled to match, fills in.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..capture.format import CaptureSet
from ..capture.others_black import check_projector_captures
from ..errors import CalibrationError, ProCamError, RigError
from ..progress import Cancel, Progress, quiet
from ..render.forward import ForwardModel
from ..rig.model import Camera, Intrinsics, Rig
from ..surface.mesh import SurfaceMesh
from .graycode_warp import warp_from_graycode
from .intrinsics import estimate_projector_intrinsics, pose_uncertainty
from .pose import PoseResult, estimate_pose, surface_view, target_mask
from .surface import surface_from_captures, surface_photo
from .warp import estimate_warp
from .warp_model import Warp, grid_image

#: The calibration stages, in order; each needs the ones before it.
STAGES = ("surface", "pose", "warp")
#: Where the projector's K comes from: the capture set (spec sheet, or a rig calibration), or a fit to the Gray code.
PROJECTOR_INTRINSICS = ("spec", "fit")


#: The report's keys each projector has its own of (the rest, the surface's and the run's, all share); with
#: several projectors they are listed per projector in ``report["projectors"]``, projector 1's also at the top.
PER_PROJECTOR = ("init", "pose", "projector_intrinsics", "pose_uncertainty", "white_saturated_share",
                 "warp_report", "losses")
#: The seconds each projector spends on its own (the surface and the albedo are shared).
PER_PROJECTOR_SECONDS = ("intrinsics", "pose", "pose_uncertainty", "warp")


@dataclass
class Calibration:
    """A calibrated camera, projector(s) and surface, ready for compensation.

    With several projectors ``rig`` holds them all (``rig.projector`` is the
    first) and ``warp`` is the first's; ``other_warps`` are the warps of
    ``rig.others`` and ``report["projectors"]`` each projector's own report
    (:data:`PER_PROJECTOR`, and its ``seconds``). :meth:`for_projector` is the
    one-projector calibration of one of them, which every one-projector step
    reads unchanged.
    """

    rig: Rig
    surface: SurfaceMesh
    warp: Warp | None
    capture_dir: str
    report: dict[str, Any] = field(default_factory=dict)
    #: the folder it was read from (None for one in memory): where its precomputed transport operator lies
    folder: str | None = None
    #: which projector of its folder's calibration this one is (0 = the first; see :meth:`for_projector`)
    projector_index: int = 0
    #: the warps of projectors 2…N (``rig.others``), in order; empty with one projector
    other_warps: tuple[Warp | None, ...] = ()

    @property
    def projector_count(self) -> int:
        """How many projectors the calibration holds."""
        return len(self.rig.projectors)

    @property
    def warps(self) -> tuple[Warp | None, ...]:
        """Every projector's warp, the first's first."""
        return (self.warp, *self.other_warps)

    def for_projector(self, k: int) -> Calibration:
        """The one-projector calibration of projector ``k`` (0 = the first): the camera and that projector alone,
        its warp, the shared surface, a report of its own pose and warp reports with the shared ones, the same
        ``folder`` and ``capture_dir``. A one-projector calibration is its own ``for_projector(0)``."""
        count = self.projector_count
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 0 <= k < count:
            raise CalibrationError(f"the calibration has {count} projector(s), numbered 0 to {count - 1} (projector 1 "
                                   f"to {count} in messages); there is no projector {k!r}")
        if count == 1:
            return self
        k = int(k)
        entries = self.report.get("projectors") or []
        own = dict(entries[k]) if k < len(entries) and isinstance(entries[k], dict) else {}
        shared = {n: v for n, v in self.report.items() if n not in PER_PROJECTOR and n != "projectors"}
        report = {**shared, **{n: v for n, v in own.items() if n != "seconds"},
                  "seconds": {**(shared.get("seconds") or {}), **(own.get("seconds") or {})}}
        return Calibration(Rig(self.rig.camera, self.rig.projectors[k]), self.surface, self.warps[k],
                           self.capture_dir, report, self.folder, projector_index=k)

    @property
    def stages(self) -> dict[str, str]:
        """Each stage's state: ``run`` or ``reused`` (done), or ``not run`` (folders from before stages
        existed ran all three)."""
        return dict(self.report.get("stages") or dict.fromkeys(STAGES, "run"))

    @property
    def warnings(self) -> list[str]:
        return list(self.report.get("warnings") or [])

    @property
    def missing_stages(self) -> list[str]:
        return [n for n, v in self.stages.items() if v == "not run"]


#: A linear camera value at or above this counts as saturated …
SATURATED = 0.99
#: … and a white capture saturated on more than this share of the lit area gets a warning.
SATURATED_WARN_SHARE = 0.01


def white_saturation(captures: CaptureSet) -> float:
    """Share of the lit area (white − black > 0.1, stage A's mask) where the white capture is saturated.

    There the albedo read from the white capture is only a lower bound, so the
    model is too dark at every lower level: a glossy highlight or too long an
    exposure. Measured on lab glossy surfaces (strength 0.5): 5 % (vedge) and
    23 % (plane) of the lit area, where the diagnosis finds its largest region
    "in mid input levels, simulation too dark".
    """
    white, black = captures.image("white"), captures.image("black")
    lit = (white - black).max(axis=2) > 0.1
    return float(np.mean((white[lit] >= SATURATED).any(axis=1))) if lit.any() else 0.0


#: An albedo texel above this multiple of the lit surface's 99th percentile (per channel) is capped there.
ALBEDO_SPIKE = 1.5


def albedo_from_captures(captures: CaptureSet, surface: SurfaceMesh, rig: Rig, *, floor: float = 0.05) -> np.ndarray:
    """Camera-aligned albedo: (white − black) / simulated irradiance of the white frame where lit."""
    return albedo_from_projectors([(captures, rig)], surface, floor=floor)


def _lit_albedo(captures: CaptureSet, surface: SurfaceMesh, rig: Rig,
                floor: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One projector's (albedo, NaN where it does not light; where it lights; its simulated white irradiance)."""
    white, black = captures.image("white"), captures.image("black")
    flat = SurfaceMesh(surface.vertices, surface.faces, surface.uvs, np.ones((4, 4, 3), np.float32), surface.name)
    model = ForwardModel(rig, flat, spp=4, smoothing_eps=0.0, clamp=False)
    irradiance = model.render(captures.pattern("white"))
    lit = irradiance.mean(axis=2) > floor * max(float(irradiance.mean(axis=2).max()), 1e-9)
    return np.where(lit[..., None], (white - black) / np.maximum(irradiance, 1e-6), np.nan), lit, irradiance


def albedo_from_projectors(lit_by: list[tuple[CaptureSet, Rig]], surface: SurfaceMesh, *,
                           floor: float = 0.05) -> np.ndarray:
    """Camera-aligned albedo from every projector: each one's (white − black) / its simulated irradiance where it
    lights (``lit_by``: each projector's one-projector capture set and rig), their mean weighted by irradiance
    where several light (the brighter projector's reading is the less noisy one), the surface photo elsewhere."""
    parts = [_lit_albedo(c, surface, r, floor) for c, r in lit_by]
    if len(parts) == 1:
        albedo, lit = parts[0][:2]
    else:
        weights = [np.where(m, irr.mean(axis=2), 0.0) for _, m, irr in parts]
        total = np.sum(weights, axis=0)
        lit = total > 0
        summed = np.sum([w[..., None] * np.nan_to_num(a) for (a, _, _), w in zip(parts, weights)], axis=0)
        albedo = np.where(lit[..., None], summed / np.maximum(total, 1e-12)[..., None], np.nan)
    # Outside the projectors' reach only the unlit photo is known: scale it to the lit albedo where both exist (a
    # session without the photo, such as OpenCV's sequence, gets the lit albedo's median there).
    photo = surface_photo(lit_by[0][0])  # the surface photo is every projector's (taken once)
    photo = np.zeros(albedo.shape, np.float32) if photo is None else photo
    both = lit & (photo.mean(axis=2) > 1e-4)
    if both.sum() > 100:
        scale = np.nanmedian(albedo[both] / np.maximum(photo[both], 1e-6), axis=0)
        # The unlit photo is dark and noisy (ambient light only): smooth it before scaling it up.
        fill = cv2.GaussianBlur(photo, (0, 0), 2.0) * scale
    else:
        fill = np.full_like(photo, np.nanmedian(albedo[lit]) if lit.any() else 0.5)
    # Not clipped at 1: in camera units an albedo exceeds 1 where the camera is brighter than the simulated
    # irradiance (with the lab's camera response at 0.5, 31 % of the lit red albedo did; clipped, the model was
    # too dark in red at every level and the diagnosis named a projector response instead). Capped per channel
    # at ALBEDO_SPIKE × the brightest lit percent: above that it is noise where the irradiance is near the floor
    # (up to 7.9 at the border of the projector's reach), not paint.
    cap = np.maximum(1.0, ALBEDO_SPIKE * np.nanpercentile(albedo[lit], 99, axis=0)) if lit.any() else 1.0
    return np.clip(np.where(lit[..., None], albedo, fill), 0.0, cap).astype(np.float32)


def _with_camera(captures: CaptureSet, k: Intrinsics) -> CaptureSet:
    """The capture set with camera intrinsics ``k`` (its depth image's too, at the depth's own size)."""
    if k == captures.camera.intrinsics:
        return captures
    depth = captures.depth_info
    return replace(captures, camera=Camera(k), depth_info=None if depth is None else
                   replace(depth, intrinsics=k.scaled(*depth.intrinsics.size)))


def stage_plan(stages: str | tuple[str, ...] | list[str] | None) -> tuple[str, ...]:
    """The stages to run, in pipeline order: a contiguous run of :data:`STAGES` (``None``/``'all'``: every one).

    Contiguous because each stage uses the ones before it: running the pose
    but not the warp drops the old warp (fitted for the old pose) rather than
    keep a stale one; skipping the pose between surface and warp is refused.
    """
    if stages is None or stages == "all":
        return STAGES
    names = [n.strip() for n in (stages.split(",") if isinstance(stages, str) else stages) if n.strip()]
    unknown = [n for n in names if n not in STAGES]
    if unknown or not names:
        raise CalibrationError(f"unknown calibration stage(s) {', '.join(unknown) or '(none given)'}; choose from "
                               f"{', '.join(STAGES)}")
    idx = sorted({STAGES.index(n) for n in names})
    if idx != list(range(idx[0], idx[-1] + 1)):
        raise CalibrationError(f"stages {', '.join(STAGES[i] for i in idx)} skip one in between; each stage needs "
                               f"the ones before it ({' → '.join(STAGES)})")
    return tuple(STAGES[i] for i in idx)


@dataclass
class CalibrationRun:
    """What :func:`calibrate_captures` made: the calibration and the diagnostic images of the stages it ran
    (and of the reused ones, passed in)."""

    calibration: Calibration
    images: dict[str, np.ndarray]


def image_prefix(k: int) -> str:
    """The prefix of projector ``k``'s diagnostic images: none for the first (the one-projector names), ``p2_`` …
    for the others (``p2_pose_mask``)."""
    return f"p{k + 1}_" if k else ""


def _stage_of_image(name: str) -> str:
    """A diagnostic image's name without its projector prefix (``p2_pose_mask`` → ``pose_mask``)."""
    return re.sub(r"^p\d+_", "", name)


@dataclass
class _ProjectorRun:
    """One projector's part of a calibration run: its capture set (with its intrinsics as fitted or reused), its
    own report and seconds (the shared ones themselves with one projector), its rig once stage A ran, its warp."""

    index: int
    captures: CaptureSet
    report: dict[str, Any]
    seconds: dict[str, float]
    previous: Calibration | None
    warp_source: str | None
    rig: Rig | None = None
    warp: Warp | None = None


@contextmanager
def _naming(k: int, many: bool) -> Iterator[None]:
    """With several projectors, what a projector's stage refuses says which projector (numbered from 1)."""
    try:
        yield
    except ProCamError as exc:
        if not many:
            raise
        raise CalibrationError(f"projector {k + 1}: {exc}") from None


def calibrate_captures(captures: CaptureSet, *, plan: tuple[str, ...] = STAGES, previous: Calibration | None = None,
                       previous_images: dict[str, np.ndarray] | None = None, init: str = "graycode",
                       initial_pose: np.ndarray | None = None, seed: int = 0, depth_offset: float | None = None,
                       stage_a: str = "ours", projector_intrinsics: str = "spec", surface_from: str = "auto",
                       surface_mesh: SurfaceMesh | str | Path | None = None, progress: Progress | None = None,
                       cancel: Cancel | None = None) -> CalibrationRun:
    """Run the stages of ``plan`` (:func:`stage_plan`) on a capture set.

    The stages before the plan come from ``previous`` (a calibration of the
    same capture set), the ones after are left "not run". ``depth_offset``
    (metres, + = the depth sensor reads too far) overrides the bias read from
    the capture set's wall depth image (:func:`scene_depth`).
    ``stage_a='paper'`` runs the paper's mask-only stage A (binary mask, Γ,
    plain Adam; :func:`.pose.estimate_pose`) instead of ours, to reproduce
    the paper's pipeline and its ablations. ``projector_intrinsics='fit'``
    fits the projector's focal length and principal point to the Gray code
    before stage A (:mod:`.intrinsics`) and uses them from there on; ``'spec'``
    keeps the capture set's. ``surface_from`` picks the surface's source
    (:data:`.surface.SURFACE_SOURCES`, :func:`.surface.surface_from_captures`); ``surface_mesh``
    is the user's mesh (a file or a mesh in its own frame) for ``'mesh'``.

    A capture set of several projectors gets the surface once (from the shared
    depth, the first projector's Gray code when the set knows the poses, or
    the mesh), then stage A for each projector on its own captures
    (:meth:`.CaptureSet.for_projector`), the albedo from all of them
    (:func:`albedo_from_projectors`), and stage B for each. What one projector's
    stage refuses names it ("projector 2: …"). ``projector_intrinsics='fit'``
    fits each projector's own K to its own Gray code, the camera's focal length
    held as given (it is every projector's); a given start pose is one
    projector's and is refused there. A set in
    which a projector was not black while another's sequence was taken, or one projector's photographs stand for
    another's, is refused first, naming both (:func:`~..capture.others_black.check_projector_captures`).
    """
    if projector_intrinsics not in PROJECTOR_INTRINSICS:
        raise CalibrationError(f"unknown projector intrinsics {projector_intrinsics!r}; choose one of "
                               f"{', '.join(PROJECTOR_INTRINSICS)}")
    say = progress or quiet
    count = len(captures.projectors)
    many = count > 1
    if many and init == "given" and "pose" in plan:
        raise CalibrationError(f"a given start pose (init 'given', or the scene's projector) is one projector's; "
                               f"for the {count} projectors of this capture set it is not implemented yet: start "
                               "stage A from the Gray code (the default) or the nominal poses")
    views = [captures.for_projector(k) for k in range(count)] if many else [captures]
    for k, view in enumerate(views):
        for kind in ("white", "black"):
            if not view.entries_of(kind):
                raise CalibrationError(("", "projector {k}: ")[many].format(k=k + 1) +
                                       f"the capture set {captures.path} has no '{kind}' capture; calibration "
                                       "needs white and black captures, and a checkerboard or Gray code for stage B")
    if many:  # each sequence its own projector's, taken with the others black: else it is refused by name
        check_projector_captures(captures)
    # Stage B fits its warp to a projected checkerboard by rendering; a session without one (OpenCV's
    # structured-light sequence: Gray code, white, black) gets it from the decoded Gray code instead.
    warp_sources = ["checker" if v.entries_of("checker") else "graycode" if v.entries_of("graycode") else None
                    for v in views]
    for k, source in enumerate(warp_sources):
        if "warp" in plan and source is None:
            raise CalibrationError(("", "projector {k}: ")[many].format(k=k + 1) +
                                   f"the capture set {captures.path} has neither a checkerboard nor Gray-code "
                                   "captures; stage B (warp) needs one of them")
    reused = STAGES[:STAGES.index(plan[0])]
    if reused and previous is None:
        raise CalibrationError(f"stage {plan[0]!r} reuses the {', '.join(reused)} of an earlier calibration; "
                               "none was given")
    prev = previous
    if prev is not None and prev.projector_count != count:
        raise CalibrationError(f"the calibration to continue holds {prev.projector_count} projector(s), the capture "
                               f"set {count}; run every stage (--stages all)")
    if many and "pose" in plan:
        # Before minutes of surface work: a projector whose light reaches nothing the camera sees is refused now.
        for k, view in enumerate(views):
            with _naming(k, many):
                target_mask(view)
    own_keys = ("init", "pose", "projector_intrinsics", "pose_uncertainty")
    seconds: dict[str, float] = dict(prev.report.get("seconds", {})) if prev else {}
    report: dict[str, Any] = {k: v for k, v in (prev.report if prev else {}).items()
                              if k in ("surface_report", *own_keys) and not (many and k in own_keys)}
    runs = []
    for k, view in enumerate(views):
        before = prev.for_projector(k) if prev is not None else None
        if not many:
            runs.append(_ProjectorRun(k, view, report, seconds, before, warp_sources[k]))
            continue
        own = {n: v for n, v in (before.report if before else {}).items() if n in own_keys}
        own_seconds = {n: v for n, v in ((before.report.get("seconds") or {}) if before else {}).items()
                       if n in PER_PROJECTOR_SECONDS}
        runs.append(_ProjectorRun(k, view, own, own_seconds, before, warp_sources[k]))
    if many:
        seconds = {n: v for n, v in seconds.items() if n not in PER_PROJECTOR_SECONDS}
    state = {n: ("reused" if n in reused else "run" if n in plan else "not run") for n in STAGES}
    for run in runs:
        run.report["white_saturated_share"] = white_saturation(run.captures)
    if captures.camera_lens is not None:
        # The camera lens import took out of the photographs: a live camera's frames must go through it too
        # (capture/devices.LensRemovedDevice), also where the capture set is no longer beside the calibration.
        report["camera_lens_removed"] = captures.camera_lens
    for run in runs:
        saturated = run.report["white_saturated_share"]
        if saturated > SATURATED_WARN_SHARE:
            report.setdefault("warnings", []).append(
                ("", f"projector {run.index + 1}: ")[many] +
                f"the white capture {run.captures.entry('white').file} is saturated on {saturated:.0%} of the lit "
                "area (a glossy highlight or too long an exposure): the surface's albedo there is too dark; "
                "recapture with a shorter exposure")
            say(f"warning: {report['warnings'][-1]}", 0.0)
    kept = tuple(f"{n}_" for n in reused)  # the reused stages' diagnostic images travel with them
    images = {k: v for k, v in (previous_images or {}).items() if _stage_of_image(k).startswith(kept)} if kept else {}

    if "surface" in plan:
        t0 = time.perf_counter()
        # The surface photo and the depth are every projector's; the Gray code triangulated is the first's.
        mesh, report["surface_report"], surface_warnings = surface_from_captures(
            views[0], surface_from, surface_mesh=surface_mesh, depth_offset=depth_offset,
            pose=initial_pose if init == "given" else None, progress=say)
        for w in surface_warnings:
            report.setdefault("warnings", []).append(w)
            say(f"warning: {w}", 0.0)
        seconds["surface"] = time.perf_counter() - t0
    else:
        assert prev is not None  # reused stages come from a previous calibration (checked above)
        mesh = prev.surface

    for run in runs:
        with _naming(run.index, many):
            mesh = _pose_stage(run, mesh, report, plan, state, init=init, initial_pose=initial_pose, seed=seed,
                               stage_a=stage_a, projector_intrinsics=projector_intrinsics, surface_from=surface_from,
                               surface_mesh=surface_mesh, depth_offset=depth_offset, camera_shared=many,
                               say=_span(say, 0.1, 0.5, run.index, count, many), cancel=cancel, images=images)
    if "pose" in plan:
        t0 = time.perf_counter()
        say("surface: albedo from white − black" + (" of every projector" if many else ""), 0.5)
        mesh = replace(mesh, albedo=albedo_from_projectors([(r.captures, r.rig) for r in runs if r.rig], mesh))
        seconds["albedo"] = time.perf_counter() - t0
    elif state["pose"] != "reused":
        seconds.pop("albedo", None)

    for run in runs:
        with _naming(run.index, many):
            _warp_stage(run, mesh, plan, seed=seed, say=_span(say, 0.55, 1.0, run.index, count, many), cancel=cancel,
                        images=images)
        pose_doc, warp_doc = run.report.get("pose"), run.report.get("warp_report")
        run.report["losses"] = {"pose": (pose_doc or {}).get("final_loss"),
                                "warp": ((warp_doc or {}).get("losses") or [None])[-1]}
    report["stages"] = state
    path = str(captures.path.absolute())
    if not many:
        run = runs[0]
        assert run.rig is not None
        report["seconds"] = {k: round(v, 2) for k, v in seconds.items()}
        return CalibrationRun(Calibration(run.rig, mesh, run.warp, path, report), images)
    totals = dict(seconds)
    for name in PER_PROJECTOR_SECONDS:
        spent = [r.seconds[name] for r in runs if name in r.seconds]
        if spent:
            totals[name] = sum(spent)
    entries = [{**r.report, "seconds": {k: round(v, 2) for k, v in r.seconds.items()}} for r in runs]
    # At the top, the first projector's report as a one-projector reader expects it, and every projector's below.
    top = {**report, **runs[0].report, "seconds": {k: round(v, 2) for k, v in totals.items()}, "projectors": entries}
    projectors = [r.rig.projector for r in runs if r.rig is not None]
    try:
        rig = Rig(views[0].camera, projectors[0], tuple(projectors[1:]))
    except RigError as exc:
        raise CalibrationError(f"the capture set's projectors cannot be told apart before stage A ({exc}); run the "
                               "pose too (--stages surface,pose)") from None
    return CalibrationRun(Calibration(rig, mesh, runs[0].warp, path, top,
                                      other_warps=tuple(r.warp for r in runs[1:])), images)


def _span(say: Progress, lo: float, hi: float, k: int, count: int, many: bool) -> Progress:
    """Projector ``k``'s share of the progress from ``lo`` to ``hi``, its messages naming it when there are several."""
    width = (hi - lo) / count
    name = f"projector {k + 1}: " if many else ""
    # The stages report fractions of the whole run (their one-projector range): map that range onto this share.
    return lambda m, f: say(f"{name}{m}" if many and not m.startswith("warning: ") else m,
                            lo + k * width + (min(max(f, lo), hi) - lo) / (hi - lo) * width)


def _pose_stage(run: _ProjectorRun, mesh: SurfaceMesh, report: dict[str, Any], plan: tuple[str, ...],
                state: dict[str, str], *, init: str, initial_pose: np.ndarray | None, seed: int, stage_a: str,
                projector_intrinsics: str, surface_from: str, surface_mesh: SurfaceMesh | str | Path | None,
                depth_offset: float | None, say: Progress, cancel: Cancel | None,
                images: dict[str, np.ndarray], camera_shared: bool = False) -> SurfaceMesh:
    """Stage A of one projector (after the intrinsics fit when asked): sets ``run.rig`` and ``run.captures``; the
    surface it returns is the one given unless the fit found the camera's focal length and made it again (never
    with ``camera_shared``: the camera of several projectors is held as given, each projector's own K fitted)."""
    captures, previous, own, seconds = run.captures, run.previous, run.report, run.seconds
    pose_iterations, start_label = None, None  # stage A's default for its start
    if "pose" in plan and projector_intrinsics == "fit":
        if (report.get("surface_report") or {}).get("source") == "graycode":
            # Triangulated from this Gray code with the given intrinsics, the surface holds nothing those
            # intrinsics did not put there; a fit against it only trades the focal length against the camera's
            # lens (on the real board sessions it moved a board-calibrated focal length by 6.5 %).
            raise CalibrationError("the projector's intrinsics cannot be fitted against a surface triangulated from "
                                   "its own Gray code with those same intrinsics: give a depth image or a mesh of "
                                   "the surface (--surface-from depth|mesh), or keep the given intrinsics "
                                   "(--projector-intrinsics spec)")
        t0 = time.perf_counter()
        say("projector intrinsics: fitting focal length and principal point to the Gray code", 0.1)
        fit = estimate_projector_intrinsics(captures, surface_view(mesh, captures.camera.intrinsics),
                                            target_mask(captures)[0], seed=seed,
                                            depth_bias_known=depth_offset is not None, camera_shared=camera_shared)
        say(f"projector intrinsics: {fit.summary()}", 0.1)
        own["projector_intrinsics"] = fit.to_dict()
        # From here on the capture set's projector is the fitted one: stage A, the albedo and stage B all use it.
        captures = replace(captures, projector=replace(captures.projector, intrinsics=fit.fitted))
        camera = fit.camera(captures.camera.intrinsics)
        if camera is not None:
            # And its camera: the surface was made with the given K, so it is made again with the fitted one.
            captures = _with_camera(captures, camera)
            say("surface: again, with the fitted camera focal length", 0.1)
            mesh, report["surface_report"], _ = surface_from_captures(
                captures, surface_from, surface_mesh=surface_mesh, depth_offset=depth_offset,
                pose=initial_pose if init == "given" else None, progress=say)
        if fit.camera_from_projector is not None and init == "graycode" and stage_a == "ours":
            # The fit's pose is Gray-code PnP with the fitted K and the camera's lens in the loop: stage A keeps it
            # (its mask only checks it), as it keeps plain Gray-code PnP.
            init, initial_pose, pose_iterations = "given", fit.camera_from_projector, 0
            start_label = "graycode (with the intrinsics fit)"
        seconds["intrinsics"] = time.perf_counter() - t0
    elif "pose" in plan:
        own.pop("projector_intrinsics", None)
        seconds.pop("intrinsics", None)
    elif previous is not None:
        # The reused pose came with the reused intrinsics (the camera's too, when they were fitted).
        captures = replace(_with_camera(captures, previous.rig.camera.intrinsics),
                           projector=replace(captures.projector, intrinsics=previous.rig.projector.intrinsics))
    run.captures = captures
    run.rig = Rig(captures.camera, captures.projector)  # the capture set's nominal pose until stage A runs
    if "pose" in plan:
        t0 = time.perf_counter()
        say("stage A: projector pose", 0.1)
        pose = estimate_pose(captures, mesh, init=init, initial_pose=initial_pose, cancel=cancel, seed=seed,
                             method=stage_a, iterations=pose_iterations,
                             progress=lambda m, f: say(f"stage A: {m}", 0.1 + 0.4 * f))
        seconds["pose"] = time.perf_counter() - t0
        run.rig = Rig(captures.camera, captures.projector.with_pose(pose.camera_from_projector))
        own.update(init=start_label or pose.init, pose=pose.to_dict())
        t0 = time.perf_counter()
        own["pose_uncertainty"] = _pose_uncertainty(captures, pose, report.get("surface_report") or {},
                                                    own.get("projector_intrinsics"), seed=seed,
                                                    depth_bias_known=depth_offset is not None)
        seconds["pose_uncertainty"] = time.perf_counter() - t0
        images.update({f"{image_prefix(run.index)}pose_{n}": im for n, im in pose.diagnostics.items()})
    elif state["pose"] == "reused":
        assert previous is not None
        run.rig = previous.rig
    else:
        for k in ("init", "pose", "pose_uncertainty"):
            own.pop(k, None)
        seconds.pop("pose", None)
        seconds.pop("pose_uncertainty", None)
    return mesh


def _pose_uncertainty(captures: CaptureSet, pose: PoseResult, surface_report: dict[str, Any],
                      intrinsics_fit: dict[str, Any] | None, *, seed: int, depth_bias_known: bool) -> dict[str, Any]:
    """The pose's one-σ uncertainty (:func:`.intrinsics.pose_uncertainty`): what ``--projector-intrinsics fit``
    judged with the intrinsics, else judged here with them held as given, on the surface view and mask stage A
    made; or why it is not measured."""
    judged = (intrinsics_fit or {}).get("uncertainty") or {}
    if judged.get("pose"):
        return {**judged["pose"], "parts": judged.get("pose_parts") or {}, "given_by": judged.get("given_by"),
                "intrinsics": "fitted and judged"}
    if not captures.entries_of("graycode"):
        return {"why": "the capture set holds no Gray code to judge the pose by"}
    if surface_report.get("source") == "graycode":
        return {"why": "the surface was triangulated from this Gray code with these intrinsics, so it shares "
                       "their errors and cannot judge the pose; a depth image or a mesh of the surface can"}
    try:
        assert pose.view is not None and pose.mask is not None  # estimate_pose returns both
        return {**pose_uncertainty(captures, pose.view, pose.mask, pose.camera_from_projector, seed=seed,
                                   depth_bias_known=depth_bias_known), "intrinsics": "held as given"}
    except (CalibrationError, np.linalg.LinAlgError) as exc:  # the pose stands; only its ± is not known
        return {"why": str(exc)}


def _warp_stage(run: _ProjectorRun, mesh: SurfaceMesh, plan: tuple[str, ...], *, seed: int, say: Progress,
                cancel: Cancel | None, images: dict[str, np.ndarray]) -> None:
    """Stage B of one projector: sets ``run.warp`` (None when the plan leaves it out) and its report."""
    captures, rig, seconds = run.captures, run.rig, run.seconds
    assert rig is not None
    if "warp" not in plan:
        seconds.pop("warp", None)
        return
    t0 = time.perf_counter()
    if run.warp_source == "checker":
        say("stage B: warp", 0.55)
        fit = estimate_warp(captures, mesh, rig, cancel=cancel, seed=seed,
                            progress=lambda m, f: say(f"stage B: {m}", 0.55 + 0.45 * f))
    else:
        say("stage B: warp from the Gray code (no checkerboard in the capture set)", 0.55)
        fit = warp_from_graycode(captures, mesh, rig, seed=seed)
    seconds["warp"] = time.perf_counter() - t0
    run.warp = warp = fit.warp
    run.report["warp_report"] = {"source": run.warp_source,
                                 "losses": [float(v) for v in fit.losses[-1:]] if fit.losses else [],
                                 "corners_before_px": fit.corners_before_px,
                                 "corners_after_px": fit.corners_after_px}
    prefix = image_prefix(run.index)
    images.update({f"{prefix}warp_{n}": im for n, im in fit.diagnostics.items()})
    images[f"{prefix}warp_grid"] = grid_image(warp, warp.size)
