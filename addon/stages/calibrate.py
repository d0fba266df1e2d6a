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

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..capture.format import CaptureSet
from ..errors import CalibrationError
from ..progress import Cancel, Progress, quiet
from ..render.forward import ForwardModel
from ..rig.model import Camera, Intrinsics, Rig
from ..surface.mesh import SurfaceMesh
from .graycode_warp import warp_from_graycode
from .intrinsics import estimate_projector_intrinsics
from .pose import estimate_pose, surface_view, target_mask
from .surface import surface_from_captures, surface_photo
from .warp import estimate_warp
from .warp_model import Warp, grid_image

#: The calibration stages, in order; each needs the ones before it.
STAGES = ("surface", "pose", "warp")
#: Where the projector's K comes from: the capture set (spec sheet, or a rig calibration), or a fit to the Gray code.
PROJECTOR_INTRINSICS = ("spec", "fit")


@dataclass
class Calibration:
    """A calibrated projector-camera rig and surface, ready for compensation."""

    rig: Rig
    surface: SurfaceMesh
    warp: Warp | None
    capture_dir: str
    report: dict[str, Any] = field(default_factory=dict)
    #: the folder it was read from (None for one in memory): where its precomputed transport operator lies
    folder: str | None = None

    @property
    def stages(self) -> dict[str, str]:
        """Each stage's state: ``run`` or ``reused`` (done), or ``not run`` (folders from before stages
        existed ran all three)."""
        return dict(self.report.get("stages") or {n: "run" for n in STAGES})

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
    white, black = captures.image("white"), captures.image("black")
    flat = SurfaceMesh(surface.vertices, surface.faces, surface.uvs, np.ones((4, 4, 3), np.float32), surface.name)
    model = ForwardModel(rig, flat, spp=4, smoothing_eps=0.0, clamp=False)
    irradiance = model.render(captures.pattern("white"))
    lit = irradiance.mean(axis=2) > floor * max(float(irradiance.mean(axis=2).max()), 1e-9)
    albedo = np.where(lit[..., None], (white - black) / np.maximum(irradiance, 1e-6), np.nan)
    # Outside the projector's reach only the unlit photo is known: scale it to the lit albedo where both exist (a
    # session without the photo, such as OpenCV's sequence, gets the lit albedo's median there).
    photo = surface_photo(captures)
    photo = np.zeros_like(white) if photo is None else photo
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
    """
    if projector_intrinsics not in PROJECTOR_INTRINSICS:
        raise CalibrationError(f"unknown projector intrinsics {projector_intrinsics!r}; choose one of "
                               f"{', '.join(PROJECTOR_INTRINSICS)}")
    say = progress or quiet
    for kind in ("white", "black"):
        if not captures.entries_of(kind):
            raise CalibrationError(f"the capture set {captures.path} has no '{kind}' capture; calibration needs "
                                   "white and black captures, and a checkerboard or Gray code for stage B")
    # Stage B fits its warp to a projected checkerboard by rendering; a session without one (OpenCV's
    # structured-light sequence: Gray code, white, black) gets it from the decoded Gray code instead.
    warp_source = "checker" if captures.entries_of("checker") else "graycode" if captures.entries_of("graycode") \
        else None
    if "warp" in plan and warp_source is None:
        raise CalibrationError(f"the capture set {captures.path} has neither a checkerboard nor Gray-code captures; "
                               "stage B (warp) needs one of them")
    reused = STAGES[:STAGES.index(plan[0])]
    if reused and previous is None:
        raise CalibrationError(f"stage {plan[0]!r} reuses the {', '.join(reused)} of an earlier calibration; "
                               "none was given")
    prev = previous
    seconds: dict[str, float] = dict(prev.report.get("seconds", {})) if prev else {}
    state = {n: ("reused" if n in reused else "run" if n in plan else "not run") for n in STAGES}
    report: dict[str, Any] = {k: v for k, v in (prev.report if prev else {}).items()
                              if k in ("init", "surface_report", "pose", "projector_intrinsics")}
    saturated = white_saturation(captures)
    report["white_saturated_share"] = saturated
    if captures.camera_lens is not None:
        # The camera lens import took out of the photographs: a live camera's frames must go through it too
        # (capture/devices.LensRemovedDevice), also where the capture set is no longer beside the calibration.
        report["camera_lens_removed"] = captures.camera_lens
    if saturated > SATURATED_WARN_SHARE:
        report["warnings"] = [
            f"the white capture {captures.entry('white').file} is saturated on {saturated:.0%} of the lit area "
            "(a glossy highlight or too long an exposure): the surface's albedo there is too dark; recapture "
            "with a shorter exposure"]
        say(f"warning: {report['warnings'][0]}", 0.0)
    kept = tuple(f"{n}_" for n in reused)  # the reused stages' diagnostic images travel with them
    images = {k: v for k, v in (previous_images or {}).items() if k.startswith(kept)} if kept else {}

    if "surface" in plan:
        t0 = time.perf_counter()
        mesh, report["surface_report"], surface_warnings = surface_from_captures(
            captures, surface_from, surface_mesh=surface_mesh, depth_offset=depth_offset,
            pose=initial_pose if init == "given" else None, progress=say)
        for w in surface_warnings:
            report.setdefault("warnings", []).append(w)
            say(f"warning: {w}", 0.0)
        seconds["surface"] = time.perf_counter() - t0
    else:
        mesh = prev.surface

    pose_iterations, start_label = None, None  # stage A's default for its start
    if "pose" in plan and projector_intrinsics == "fit":
        t0 = time.perf_counter()
        say("projector intrinsics: fitting focal length and principal point to the Gray code", 0.1)
        fit = estimate_projector_intrinsics(captures, surface_view(mesh, captures.camera.intrinsics),
                                            target_mask(captures)[0], seed=seed)
        say(f"projector intrinsics: {fit.summary()}", 0.1)
        report["projector_intrinsics"] = fit.to_dict()
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
        report.pop("projector_intrinsics", None)
        seconds.pop("intrinsics", None)
    elif previous is not None:
        # The reused pose came with the reused intrinsics (the camera's too, when they were fitted).
        captures = replace(_with_camera(captures, previous.rig.camera.intrinsics),
                           projector=replace(captures.projector, intrinsics=previous.rig.projector.intrinsics))
    rig = Rig(captures.camera, captures.projector)  # the capture set's nominal pose until stage A runs
    if "pose" in plan:
        t0 = time.perf_counter()
        say("stage A: projector pose", 0.1)
        pose = estimate_pose(captures, mesh, init=init, initial_pose=initial_pose, cancel=cancel, seed=seed,
                             method=stage_a, iterations=pose_iterations,
                             progress=lambda m, f: say(f"stage A: {m}", 0.1 + 0.4 * f))
        seconds["pose"] = time.perf_counter() - t0
        rig = Rig(captures.camera, captures.projector.with_pose(pose.camera_from_projector))
        report.update(init=start_label or pose.init, pose=pose.to_dict())
        images.update({f"pose_{n}": im for n, im in pose.diagnostics.items()})

        t0 = time.perf_counter()
        say("surface: albedo from white − black", 0.5)
        mesh = replace(mesh, albedo=albedo_from_captures(captures, mesh, rig))
        seconds["albedo"] = time.perf_counter() - t0
    elif state["pose"] == "reused":
        rig = prev.rig
    else:
        for k in ("init", "pose"):
            report.pop(k, None)
        for k in ("pose", "albedo"):
            seconds.pop(k, None)

    warp = None
    if "warp" in plan:
        t0 = time.perf_counter()
        if warp_source == "checker":
            say("stage B: warp", 0.55)
            fit = estimate_warp(captures, mesh, rig, cancel=cancel, seed=seed,
                                progress=lambda m, f: say(f"stage B: {m}", 0.55 + 0.45 * f))
        else:
            say("stage B: warp from the Gray code (no checkerboard in the capture set)", 0.55)
            fit = warp_from_graycode(captures, mesh, rig, seed=seed)
        seconds["warp"] = time.perf_counter() - t0
        warp = fit.warp
        report["warp_report"] = {"source": warp_source,
                                 "losses": [float(v) for v in fit.losses[-1:]] if fit.losses else [],
                                 "corners_before_px": fit.corners_before_px,
                                 "corners_after_px": fit.corners_after_px}
        images.update({f"warp_{n}": im for n, im in fit.diagnostics.items()})
        images["warp_grid"] = grid_image(warp, warp.size)
    else:
        seconds.pop("warp", None)

    pose_doc, warp_doc = report.get("pose"), report.get("warp_report")
    report["losses"] = {"pose": (pose_doc or {}).get("final_loss"),
                        "warp": ((warp_doc or {}).get("losses") or [None])[-1]}
    report["stages"] = state
    report["seconds"] = {k: round(v, 2) for k, v in seconds.items()}
    cal = Calibration(rig, mesh, warp, str(captures.path.absolute()), report)
    return CalibrationRun(cal, images)
