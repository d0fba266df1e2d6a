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
from ..errors import CalibrationError, ProCamError
from ..imageio import write_atomic_bytes, write_image
from ..outputs import AtomicFolder
from ..rig.model import Rig
from ..surface.mesh import SurfaceMesh
from ..surface.reconstruct import reconstruct_surface

FORMAT = "procam-calibration"
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

    @staticmethod
    def load(folder: str | Path) -> "Calibration":
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


def calibrate(capture_dir: str | Path, out_dir: str | Path, *, init: str = "graycode",
              initial_pose: np.ndarray | None = None, force: bool = False, with_blend: bool = True,
              progress: Progress | None = None, cancel: Callable[[], bool] | None = None,
              seed: int = 0) -> Calibration:
    """Run surface, stage A and stage B on a capture set and write the calibration folder."""
    from .pose import estimate_pose
    from .warp import estimate_warp, grid_image

    say = progress or (lambda msg, frac: None)
    captures = CaptureSet.load(capture_dir)
    for kind in ("white", "black", "checker"):
        if not captures.entries_of(kind):
            raise CalibrationError(f"the capture set {capture_dir} has no '{kind}' capture; calibration needs "
                                   "white, black, checkerboard and depth captures")
    folder = AtomicFolder(out_dir, force=force, what="calibration folder",
                          replaceable=lambda p: (p / "calibration.json").is_file(), error=CalibrationError)
    try:
        seconds: dict[str, float] = {}
        t0 = time.perf_counter()
        say("surface: reconstructing from depth", 0.0)
        try:
            depth = captures.depth()
        except ProCamError as exc:
            raise CalibrationError(f"surface: {exc}") from None
        k = captures.camera.intrinsics
        mesh, surface_report = reconstruct_surface(depth, k, captures.image("surface"))
        seconds["surface"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        say("stage A: projector pose", 0.1)
        pose = estimate_pose(captures, mesh, init=init, initial_pose=initial_pose, cancel=cancel, seed=seed,
                             progress=lambda m, f: say(f"stage A: {m}", 0.1 + 0.4 * f))
        seconds["pose"] = time.perf_counter() - t0
        rig = Rig(captures.camera, captures.projector.with_pose(pose.camera_from_projector))

        t0 = time.perf_counter()
        say("surface: albedo from white − black", 0.5)
        mesh = replace(mesh, albedo=albedo_from_captures(captures, mesh, rig))
        seconds["albedo"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        say("stage B: warp", 0.55)
        warp = estimate_warp(captures, mesh, rig, cancel=cancel, seed=seed,
                             progress=lambda m, f: say(f"stage B: {m}", 0.55 + 0.4 * f))
        seconds["warp"] = time.perf_counter() - t0

        report = {"init": pose.init, "surface_report": surface_report.to_dict(), "pose": pose.to_dict(),
                  "warp_report": {"losses": [float(v) for v in warp.losses[-1:]] if warp.losses else [],
                                  "corners_before_px": warp.corners_before_px,
                                  "corners_after_px": warp.corners_after_px},
                  "losses": {"pose": float(pose.losses[-1]) if pose.losses else None,
                             "warp": float(warp.losses[-1]) if warp.losses else None},
                  "seconds": {k2: round(v, 2) for k2, v in seconds.items()}}
        cal = Calibration(rig, mesh, warp.warp, str(Path(capture_dir).absolute()), report)

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
        images = {**{f"pose_{n}": im for n, im in pose.diagnostics.items()},
                  **{f"warp_{n}": im for n, im in warp.diagnostics.items()},
                  "warp_grid": grid_image(warp.warp, warp.warp.size)}
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


