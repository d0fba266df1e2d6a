"""The calibration pipeline: capture set → surface (S_g, S_c) → projector pose (stage A) → warp (stage B).

It writes one calibration folder, atomically (nothing is left behind when a
stage fails or is cancelled):

``calibration.json``
    camera and projector models (pose as a 4×4 ``camera_from_projector`` in
    the rig frame, metres), warp parameters, losses and seconds per stage.
``surface.npz`` / ``surface.obj`` + ``albedo.png``
    the reconstructed mesh (rig frame) and its camera-aligned diffuse texture.
``diagnostics/``
    mask vs rendered mask, checkerboard capture vs render before/after the warp,
    the deformed grid of the warp.
``scene.blend``
    the rig, the textured surface and those images, to open in Blender.

The albedo is read where the projector reaches, as DESIGN.md §1 advises for a
dark room: (white − black) divided by the simulated irradiance of the white
frame once the pose is known; elsewhere the unlit surface photo, scaled to
match, fills in.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..capture.format import CaptureSet
from ..errors import CalibrationError, ProCamError, SurfaceError
from ..imageio import read_image, write_atomic_bytes, write_image
from ..outputs import AtomicFolder
from ..rig.model import Rig
from ..surface.mesh import SurfaceMesh
from ..surface.reconstruct import reconstruct_surface, wall_depth_offset

FORMAT = "procam-calibration"
#: The calibration stages, in order; each needs the ones before it.
STAGES = ("surface", "pose", "warp")
VERSION = 1
Progress = Callable[[str, float], None]


@dataclass
class Calibration:
    """A calibrated projector-camera rig and surface, ready for compensation."""

    rig: Rig
    surface: SurfaceMesh
    warp: Any  # stages.warp.Warp
    capture_dir: str
    report: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"format": FORMAT, "version": VERSION, "capture_set": self.capture_dir,
                "rig": self.rig.to_dict(),
                "camera_from_projector": self.rig.projector.camera_from_projector.tolist(),
                "warp": self.warp.to_dict() if self.warp is not None else None,
                "surface": {"mesh": "surface.npz", "obj": "surface.obj", "albedo": "albedo.png",
                            "vertices": int(len(self.surface.vertices)), "faces": int(len(self.surface.faces))},
                **self.report}

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

    @staticmethod
    def load(folder: str | Path, *, complete: bool = True) -> "Calibration":
        """Read a calibration folder; with ``complete`` (for compensation, diagnosis, evaluation) one that
        has not run every stage is refused, saying which to run."""
        cal = Calibration._read(folder)
        missing = cal.missing_stages
        if complete and missing:
            raise CalibrationError(f"the calibration in {folder} has not run {', '.join(missing)} yet; run "
                                   f"procam calibrate {cal.capture_dir} --out {folder} --stages {','.join(missing)}")
        return cal

    @staticmethod
    def _read(folder: str | Path) -> "Calibration":
        from .warp import Warp

        folder = Path(folder)
        path = folder / "calibration.json"
        if not path.is_file():
            raise CalibrationError(f"{folder} is not a calibration folder (no calibration.json); run procam calibrate")
        try:
            doc = json.loads(path.read_text())
            if doc.get("format") != FORMAT:
                raise CalibrationError(f"{path} is not a ProCam calibration")
            data = np.load(folder / doc["surface"]["mesh"])
            surface = SurfaceMesh(data["vertices"], data["faces"], data["uvs"], data["albedo"], name="surface")
            warp = Warp.from_dict(doc["warp"]) if doc.get("warp") else None
            report = {k: v for k, v in doc.items() if k not in ("format", "version", "capture_set", "rig",
                                                                 "camera_from_projector", "warp", "surface")}
            return Calibration(Rig.from_dict(doc["rig"]), surface, warp, doc.get("capture_set", ""), report)
        except (OSError, ValueError, KeyError) as exc:
            raise CalibrationError(f"cannot read calibration {folder}: {exc}") from None


def _obj_text(mesh: SurfaceMesh) -> str:
    lines = ["# ProCam surface, rig frame (OpenCV camera frame, metres)", "mtllib surface.mtl", "usemtl albedo"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in mesh.vertices]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in mesh.uvs]
    lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in mesh.faces]
    return "\n".join(lines) + "\n"


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


def albedo_from_captures(captures: CaptureSet, surface: SurfaceMesh, rig: Rig, *, floor: float = 0.05) -> np.ndarray:
    """Camera-aligned albedo: (white − black) / simulated irradiance of the white frame where lit."""
    from ..render.forward import ForwardModel

    white, black = captures.image("white"), captures.image("black")
    flat = SurfaceMesh(surface.vertices, surface.faces, surface.uvs, np.ones((4, 4, 3), np.float32), surface.name)
    model = ForwardModel(rig, flat, spp=4, smoothing_eps=0.0, clamp=False)
    irradiance = model.render(captures.pattern("white"))
    lit = irradiance.mean(axis=2) > floor * max(float(irradiance.mean(axis=2).max()), 1e-9)
    albedo = np.where(lit[..., None], (white - black) / np.maximum(irradiance, 1e-6), np.nan)
    photo = captures.image("surface")
    # Outside the projector's reach only the unlit photo is known: scale it to the lit albedo where both exist.
    both = lit & (photo.mean(axis=2) > 1e-4)
    if both.sum() > 100:
        scale = np.nanmedian(albedo[both] / np.maximum(photo[both], 1e-6), axis=0)
        # The unlit photo is dark and noisy (ambient light only): smooth it before scaling it up.
        fill = cv2.GaussianBlur(photo, (0, 0), 2.0) * scale
    else:
        fill = np.full_like(photo, np.nanmedian(albedo[lit]) if lit.any() else 0.5)
    return np.clip(np.where(lit[..., None], albedo, fill), 0.0, 1.0).astype(np.float32)


def scene_depth(captures: CaptureSet, depth_offset: float | None = None) -> tuple[np.ndarray, float, str]:
    """The depth image of the scene, the sensor bias to subtract from it, and where that bias comes from.

    The scene's depth is the one ``depth`` entry without ``wall_distance_m``;
    entries with it are the sensor's images of a flat wall at that distance,
    each giving the bias (:func:`wall_depth_offset`, their median when
    several). A given ``depth_offset`` wins; with neither the bias is 0 and
    the surface keeps whatever the sensor's bias is (module doc of
    :mod:`procam.addon.surface.reconstruct`: no image can reveal it).
    """
    depth = captures.depth()
    if depth_offset is not None:
        return depth, float(depth_offset), "given"
    walls = captures.depth_walls()
    if not walls:
        return depth, 0.0, "none (no wall depth image in the capture set)"
    offsets = []
    for e, distance in walls:
        try:
            offsets.append(wall_depth_offset(captures.depth(name=e.name), distance))
        except SurfaceError as exc:
            raise CalibrationError(f"depth wall image {e.file}: {exc}") from None
    return depth, float(np.median(offsets)), f"wall depth image{'s' if len(walls) > 1 else ''} " + \
        ", ".join(f"{e.file} at {distance} m" for e, distance in walls)


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


def _previous(out_dir: Path, capture_dir: str | Path, needed: tuple[str, ...]) -> "Calibration":
    """The calibration at ``out_dir`` whose ``needed`` stages a partial run reuses (same capture set)."""
    if not (out_dir / "calibration.json").is_file():
        raise CalibrationError(f"running from stage {STAGES[len(needed)]!r} reuses the {', '.join(needed)} of the "
                               f"calibration in {out_dir}, but there is none; run the earlier stages first "
                               f"(--stages {','.join(STAGES[:len(needed) + 1])})")
    prev = Calibration.load(out_dir, complete=False)
    if Path(prev.capture_dir).resolve() != Path(capture_dir).resolve():
        raise CalibrationError(f"the calibration in {out_dir} was made from {prev.capture_dir}, not {capture_dir}; "
                               "run every stage (--stages all) or choose another output folder")
    missing = [n for n in needed if prev.stages.get(n) not in ("run", "reused")]
    if missing:
        raise CalibrationError(f"the calibration in {out_dir} has not run stage(s) {', '.join(missing)}; "
                               f"run --stages {','.join(STAGES[:len(needed) + 1])}")
    return prev


def calibrate(capture_dir: str | Path, out_dir: str | Path, *, init: str = "graycode",
              initial_pose: np.ndarray | None = None, force: bool = False, with_blend: bool = True,
              progress: Progress | None = None, cancel: Callable[[], bool] | None = None,
              seed: int = 0, depth_offset: float | None = None,
              stages: str | tuple[str, ...] | list[str] | None = None, stage_a: str = "ours") -> Calibration:
    """Run surface, stage A and stage B on a capture set and write the calibration folder.

    ``depth_offset`` (metres, + = the depth sensor reads too far) overrides
    the bias read from the capture set's wall depth image (:func:`scene_depth`).
    ``stages`` (:func:`stage_plan`) runs some stages only: the ones before
    come from the calibration already at ``out_dir`` (same capture set; it is
    then replaced, no ``force`` needed), the ones after are left "not run"
    and the folder cannot be used to compensate until they are.
    ``stage_a='paper'`` runs the paper's mask-only stage A (binary mask, Γ,
    plain Adam; :func:`.pose.estimate_pose`) instead of ours, to reproduce
    the paper's pipeline and its ablations.
    """
    from .pose import estimate_pose
    from .warp import estimate_warp, grid_image

    say = progress or (lambda msg, frac: None)
    plan = stage_plan(stages)
    captures = CaptureSet.load(capture_dir)
    for kind in ("white", "black", "checker"):
        if not captures.entries_of(kind):
            raise CalibrationError(f"the capture set {capture_dir} has no '{kind}' capture; calibration needs "
                                   "white, black, checkerboard and depth captures")
    reused = STAGES[:STAGES.index(plan[0])]
    prev = _previous(Path(out_dir), capture_dir, reused) if reused else None
    folder = AtomicFolder(out_dir, force=force or prev is not None, what="calibration folder",
                          replaceable=lambda p: (p / "calibration.json").is_file(), error=CalibrationError)
    try:
        seconds: dict[str, float] = dict(prev.report.get("seconds", {})) if prev else {}
        state = {n: ("reused" if n in reused else "run" if n in plan else "not run") for n in STAGES}
        report: dict[str, Any] = {k: v for k, v in (prev.report if prev else {}).items()
                                  if k in ("init", "surface_report", "pose")}
        saturated = white_saturation(captures)
        report["white_saturated_share"] = saturated
        if saturated > SATURATED_WARN_SHARE:
            report["warnings"] = [
                f"the white capture {captures.entry('white').file} is saturated on {saturated:.0%} of the lit area "
                "(a glossy highlight or too long an exposure): the surface's albedo there is too dark; recapture "
                "with a shorter exposure"]
            say(f"warning: {report['warnings'][0]}", 0.0)
        images: dict[str, np.ndarray] = {}
        if prev is not None:  # the reused stages' diagnostic images travel with them
            kept = tuple(f"{n}_" for n in reused)
            for png in sorted((Path(out_dir) / "diagnostics").glob("*.png")):
                if png.stem.startswith(kept):
                    images[png.stem] = read_image(png)

        if "surface" in plan:
            t0 = time.perf_counter()
            say("surface: reconstructing from depth", 0.0)
            try:
                depth, offset, offset_source = scene_depth(captures, depth_offset)
            except ProCamError as exc:
                raise CalibrationError(f"surface: {exc}") from None
            mesh, surface_report = reconstruct_surface(depth, captures.camera.intrinsics, captures.image("surface"),
                                                       depth_offset=offset)
            seconds["surface"] = time.perf_counter() - t0
            report["surface_report"] = {**surface_report.to_dict(), "depth_offset_source": offset_source}
        else:
            mesh = prev.surface

        rig = Rig(captures.camera, captures.projector)  # the capture set's nominal pose until stage A runs
        if "pose" in plan:
            t0 = time.perf_counter()
            say("stage A: projector pose", 0.1)
            pose = estimate_pose(captures, mesh, init=init, initial_pose=initial_pose, cancel=cancel, seed=seed,
                                 method=stage_a, progress=lambda m, f: say(f"stage A: {m}", 0.1 + 0.4 * f))
            seconds["pose"] = time.perf_counter() - t0
            rig = Rig(captures.camera, captures.projector.with_pose(pose.camera_from_projector))
            report.update(init=pose.init, pose=pose.to_dict())
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
            say("stage B: warp", 0.55)
            fit = estimate_warp(captures, mesh, rig, cancel=cancel, seed=seed,
                                progress=lambda m, f: say(f"stage B: {m}", 0.55 + 0.4 * f))
            seconds["warp"] = time.perf_counter() - t0
            warp = fit.warp
            report["warp_report"] = {"losses": [float(v) for v in fit.losses[-1:]] if fit.losses else [],
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
        cal = Calibration(rig, mesh, warp, str(Path(capture_dir).absolute()), report)

        say("writing the calibration folder", 0.95)
        tmp = folder.tmp
        write_atomic_bytes(tmp / "calibration.json", (json.dumps(cal.to_dict(), indent=1) + "\n").encode())
        import io
        buf = io.BytesIO()
        np.savez_compressed(buf, vertices=mesh.vertices, faces=mesh.faces, uvs=mesh.uvs, albedo=mesh.albedo)
        write_atomic_bytes(tmp / "surface.npz", buf.getvalue())
        write_image(tmp / "albedo.png", mesh.albedo)
        write_atomic_bytes(tmp / "surface.mtl", b"newmtl albedo\nKd 1 1 1\nmap_Kd albedo.png\n")
        write_atomic_bytes(tmp / "surface.obj", _obj_text(mesh).encode())
        diag = tmp / "diagnostics"
        diag.mkdir()
        for name, im in images.items():
            write_image(diag / f"{name}.png", np.clip(im, 0, 1))
        if with_blend:
            from ..rig.blender_file import save_calibration_blend
            save_calibration_blend(tmp / "scene.blend", rig, mesh, {n: np.clip(i, 0, 1) for n, i in images.items()})
    except BaseException:
        folder.abort()
        raise
    folder.commit()
    say("done", 1.0)
    return cal
