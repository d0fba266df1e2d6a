"""The simulated projection f̂(z, Ω̂): projector frame in, camera image out, differentiable with Dr.Jit.

One :class:`ForwardModel` holds one loaded Mitsuba scene (loading is the slow
part); each render only updates scene parameters: the projector texture (the
frame, multiplied by the border smoothing Γ and padded with a black border,
see :mod:`.scene`), and, for pose gradients, the projector's ``to_world``.

Mitsuba declares the projector's ``to_world`` non-differentiable, but a
transform built from Dr.Jit variables that carry gradients and assigned to
``params['projector.to_world']`` still propagates them, because the emitter
evaluates ``to_world.inverse() · p`` inside the differentiated computation.
Measured at 640×480 / 800×600 on 'vedge' with a stage-A mask loss, AD against
central differences: with Γ (ε = 0.01) cosine 0.999999, norms within 0.5 %;
without Γ still cosine 0.9996, norms within 6 %, because the black border
and bilinear lookup already make the frame edge a one-texel ramp. Γ widens
that ramp to ε·W texels, which is what widens the basin of the pose search.

Integrator choice for direct light. llvm_ad_rgb, 2 shared cores, 640×480
camera, 800×600 projector, 4 spp, best of 7, seconds (wall)::

                                      render   frame-grad step   pose-grad step
    direct, 'plane'                    0.10         0.29              0.32
    prb max_depth 2, 'plane'           0.17         0.33              0.31
    direct, 'vedge'                    0.08–0.11    0.27–0.34         0.26–0.32
    prb max_depth 2, 'vedge'           0.18         0.42–0.45         0.38–0.47
    prb max_depth 3 (1 bounce), 'vedge' 0.19–0.22   0.42–0.53         0.44–0.49

(peak RSS ≈ 235 MB in every case). ``direct`` with one emitter sample per
camera ray renders the same image as ``prb`` with ``max_depth = 2`` and is
faster, so it is used for ``bounces = 0``; ``emitter_samples = spp`` would
repeat the deterministic delta-light lookup spp times (measured: twice the
time at spp 4, and a 3× too bright image with ``bsdf_samples = 0``).
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np

from ..errors import ImageError, RenderError
from ..rig.frames import mitsuba_to_world
from ..rig.model import Intrinsics, Rig
from ..surface.mesh import SurfaceMesh
from . import backend
from .pose import delta_rotation
from .scene import (EMITTER_ID, SURFACE_ID, border_smoothing, build_scene, check_image, pad_index)

_IRRADIANCE = f"{EMITTER_ID}.irradiance.data"
_TO_WORLD = f"{EMITTER_ID}.to_world"


class ForwardModel:
    """Mitsuba forward model of one rig and surface: ``render(frame) -> camera image``.

    ``camera_size`` (width, height) renders the camera at another resolution
    than its calibration (same lens); ``bounces`` is the number of indirect
    bounces (0 = direct light only, the paper's stages A and B); ``spp``
    samples per pixel; ``smoothing_eps`` the border smoothing ε of Eq. 11–12
    (0 turns it off); ``clamp`` clips the output to [0, 1] (Eq. 13);
    ``variant`` a Mitsuba variant (default: ``backend.default_variant()``);
    ``seed`` the first of the seeds used when a render gets none; ``crop``
    (x, y, width, height) renders only that window of the camera image (what
    a loss restricted to it needs: the cost falls with the pixels rendered).
    """

    def __init__(self, rig: Rig, surface: SurfaceMesh, *, camera_size: tuple[int, int] | None = None,
                 bounces: int = 0, spp: int = 4, smoothing_eps: float = 0.01, clamp: bool = True,
                 variant: str | None = None, seed: int = 0, integrator: str = "auto",
                 glossy_roughness: float | None = None, crop: tuple[int, int, int, int] | None = None) -> None:
        self.variant = variant or backend.default_variant()
        mi = self._mi = backend.mitsuba(self.variant)
        import drjit as dr

        self._dr = dr
        self.rig = rig
        self.surface = surface
        intr = rig.camera.intrinsics
        if camera_size is not None and tuple(camera_size) != intr.size:
            intr = intr.scaled(int(camera_size[0]), int(camera_size[1]))
        #: Intrinsics of the rendered camera image (the rig camera, rescaled to ``camera_size``).
        self.camera: Intrinsics = intr
        #: (x, y, width, height) of the camera window rendered (None: the whole image); renders have its size.
        self.crop = None if crop is None else tuple(int(v) for v in crop)
        self.bounces = int(bounces)
        self.spp = int(spp)
        self.clamp = bool(clamp)
        self._seeds = itertools.count(int(seed))
        try:
            self.scene = build_scene(mi, rig, surface, intr, bounces=bounces, spp=spp, integrator=integrator,
                                     glossy_roughness=glossy_roughness, crop=self.crop)
        except RuntimeError as exc:  # Mitsuba reports plugin/parameter problems as RuntimeError
            raise RenderError(f"Mitsuba could not build the scene: {exc}") from None
        self.params = mi.traverse(self.scene)
        self._albedo_key = next((k for k in self.params.keys()  # noqa: SIM118 (Mitsuba's SceneParameters)
                                 if k.startswith(SURFACE_ID) and k.endswith("reflectance.data")), None)
        pw, ph = self.projector_size
        self.set_smoothing(smoothing_eps)
        index, inside = pad_index(pw, ph)
        self._pad_index = mi.UInt32(index)
        self._pad_mask = mi.Bool(inside)
        self._padded_shape = (ph + 2, pw + 2, 3)
        self.set_pose(rig.projector.camera_from_projector)

    # ------------------------------------------------------------------ properties and setters

    @property
    def projector_size(self) -> tuple[int, int]:
        """(width, height) of the projector's native frame."""
        return self.rig.projector.intrinsics.size

    @property
    def camera_size(self) -> tuple[int, int]:
        """(width, height) of the rendered camera image."""
        return self.camera.size

    def set_pose(self, camera_from_projector: np.ndarray) -> None:
        """Move the projector (4×4 OpenCV pose in the rig frame); later renders use it."""
        proj = self.rig.projector.with_pose(camera_from_projector)  # validates (RigError)
        self.rig = Rig(self.rig.camera, proj)
        self._to_world = mitsuba_to_world(proj.camera_from_projector)
        self.params[_TO_WORLD] = self._mi.Transform4f(self._to_world.astype(np.float32))
        self.params.update()

    def set_albedo(self, image: np.ndarray) -> None:
        """Replace the surface's diffuse albedo (H×W×3, linear, row 0 = top; any resolution)."""
        img = np.asarray(image, dtype=np.float32)
        if img.ndim != 3 or img.shape[2] != 3 or min(img.shape[:2]) < 1:
            raise ImageError(f"an albedo must be an H×W×3 image, got shape {img.shape}")
        img = check_image(img, (img.shape[1], img.shape[0]), "the albedo", "give a linear RGB image (≥ 0)")
        if self._albedo_key is None:
            raise RenderError("this forward model's surface is a white glossy lobe; it has no albedo to set")
        self.params[self._albedo_key] = self._mi.TensorXf(np.maximum(img, 0.0))  # may exceed 1 (SurfaceMesh)
        self.params.update()

    def set_smoothing(self, eps: float) -> None:
        """Change the border smoothing ε (0 = off). Stage A wants it; stages B and C usually do not,
        since it dims the outer ε of the frame (with the paper's 600×600 input in an 800×600 frame,
        the input's top and bottom rows)."""
        pw, ph = self.projector_size
        self._gamma = self._mi.TensorXf(np.repeat(border_smoothing(pw, ph, eps)[..., None], 3, axis=2))
        self.smoothing_eps = float(eps)

    # ------------------------------------------------------------------ rendering

    def render(self, frame: np.ndarray, *, seed: int | None = None, spp: int | None = None) -> np.ndarray:
        """Camera image (H×W×3 float32) of a projector frame (native size, H×W×3, values clipped to [0, 1])."""
        pw, ph = self.projector_size
        img = check_image(frame, (pw, ph), "the projector frame",
                          "give the projector's native frame, or use render_input for its input image")
        mi, dr = self._mi, self._dr
        with dr.suspend_grad():
            out = self.render_dr(mi.TensorXf(np.clip(img, 0.0, 1.0)), seed=seed, spp=spp)
            result = np.array(out, dtype=np.float32)
        if not np.all(np.isfinite(result)):
            raise RenderError("the simulation produced NaN or infinite pixels; check the surface mesh for "
                              "degenerate triangles and the projector pose (is it inside the surface?)")
        return result

    def render_input(self, z: np.ndarray, *, seed: int | None = None, spp: int | None = None) -> np.ndarray:
        """Camera image of a projector *input* image (``input_size``), placed in a black native frame."""
        return self.render(self.rig.projector.frame_from_input(z), seed=seed, spp=spp)

    def render_dr(self, frame: Any, pose_delta: Any = None, *, seed: int | None = None,
                  seed_grad: int | None = None, spp: int | None = None) -> Any:
        """Differentiable render: ``mi.TensorXf`` frame (H_p×W_p×3) → ``mi.TensorXf`` image (H×W×3).

        Gradients flow to ``frame`` and, when given, to ``pose_delta``: six
        Dr.Jit values (an ``mi.Float`` of width 6, or a sequence of six) — a
        translation (m) and a rotation vector (rad) applied to the current
        pose as described in :mod:`.pose`. The frame is not clipped here
        (keep ``0 ≤ z ≤ 1`` in the optimiser); the output is when ``clamp``.
        ``seed`` defaults to the next of the model's seeds, so successive
        calls decorrelate their noise. ``seed_grad`` seeds the adjoint pass
        (by default Mitsuba derives it from ``seed``); Mitsuba insists that it
        differs from ``seed``, which keeps gradients of nonlinear losses
        unbiased. The gradient is therefore that of a render with seed
        ``seed_grad``: compare it with finite differences of renders seeded
        so.
        """
        mi, dr = self._mi, self._dr
        pw, ph = self.projector_size
        if not isinstance(frame, mi.TensorXf):
            frame = mi.TensorXf(check_image(frame, (pw, ph), "the projector frame", "give an H×W×3 frame"))
        if tuple(frame.shape) != (ph, pw, 3):
            raise ImageError(f"the projector frame must be {pw}×{ph}×3 (the projector's native size), "
                             f"got shape {tuple(frame.shape)}")
        if self._mi.variant() != self.variant:
            self._mi.set_variant(self.variant)
        lit = frame * self._gamma if self.smoothing_eps > 0 else frame
        padded = dr.gather(mi.Float, lit.array, self._pad_index, self._pad_mask)
        self.params[_IRRADIANCE] = mi.TensorXf(padded, self._padded_shape)
        if pose_delta is None:
            self.params[_TO_WORLD] = mi.Transform4f(self._to_world.astype(np.float32))
        else:
            self.params[_TO_WORLD] = self._to_world_dr(pose_delta)
        self.params.update()
        seed = next(self._seeds) if seed is None else int(seed)
        extra = {}
        if seed_grad is not None:
            if int(seed_grad) == seed:
                raise RenderError("seed_grad must differ from seed (Mitsuba decorrelates the adjoint pass)")
            extra["seed_grad"] = int(seed_grad)
        try:
            image = mi.render(self.scene, self.params, spp=int(spp or self.spp), seed=seed, **extra)
        except RuntimeError as exc:
            raise RenderError(f"Mitsuba failed to render ({exc}); if it ran out of memory, lower the camera "
                              "size or the samples per pixel") from None
        if self.clamp:
            image = dr.clip(image, 0.0, 1.0)
        return image

    def _to_world_dr(self, pose_delta: Any) -> Any:
        """Mitsuba ``to_world`` of the current pose moved by a Dr.Jit pose delta (see :mod:`.pose`)."""
        mi, dr = self._mi, self._dr
        if isinstance(pose_delta, mi.Float):
            if dr.width(pose_delta) != 6:
                raise RenderError(f"pose_delta must hold 6 values (translation, rotation vector), "
                                  f"got {dr.width(pose_delta)}")
            d = [dr.gather(mi.Float, pose_delta, i) for i in range(6)]
        else:
            d = [v if isinstance(v, mi.Float) else mi.Float(float(v)) for v in pose_delta]
            if len(d) != 6:
                raise RenderError(f"pose_delta must hold 6 values (translation, rotation vector), got {len(d)}")
        r = delta_rotation(d[3:])
        a = self._to_world  # [R·C | t] with C the OpenCV → Mitsuba local flip (frames.mitsuba_to_world)
        rows = []
        for i in range(3):
            row = [sum((r[i][k] * float(a[k, j]) for k in range(3)), mi.Float(0.0)) for j in range(3)]
            rows.append(row + [d[i] + float(a[i, 3])])
        m = mi.Matrix4f(*[v for row in rows for v in row], 0.0, 0.0, 0.0, 1.0)
        return mi.Transform4f(m)
