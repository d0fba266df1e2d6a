"""Stage C: the projector input that makes the camera see a target (the paper's Sec. IV-C, V-C).

The real projection is modelled as ``f(x) ≈ f̂(z) − θ`` with ``x = W(z)``
(Eq. 3–4): ``f̂`` the calibrated Mitsuba model, ``W`` the stage-B warp, ``θ`` a
per-pixel bias in camera space. Stage C finds the virtual input ``z`` by
gradient descent through ``f̂`` on (Eq. 9)::

    L(z) = mean over the display area of ‖y_t − (clamp(f̂(z)) − θ)‖²

with the paper's schedule: ``iterations_z`` (200) Adam steps on ``z`` alone,
then ``iterations_joint`` (300) steps on ``z`` and ``θ``, θ following Eq. 10
(``θ ← θ + 2α(f̂ − y − θ)``, α = 0.01) from captures ``y`` of the real input
``W(z)``. Clamps: ``0 ≤ z ≤ 1`` after each step, ``0 ≤ f̂ ≤ 1`` in the model,
``f̂ − 1 ≤ θ ≤ f̂`` (Eq. 13–14). Direct + indirect light (``bounces ≥ 1``).
The answer is ``x* = W(z)``.

Choices beyond the paper, and why:

* **Captures every K iterations** (``capture_every``, default 20). The paper
  captures every iteration, which a real rig does in ~0.1 s; the Cycles lab
  needs seconds a frame (640×480). θ is a slow exponential average (time
  constant 1/(2α) = 50 iterations), so a capture every 20 iterations loses
  little: 15 captures over the 300 joint iterations. For real hardware pass
  ``capture_every=1``.
* **Eq. 10 with a consistent residual.** Between captures ``y`` is stale, so
  ``f̂(z_i) − y`` would compare the current simulation with an image of an
  older input. At each capture we render ``f̂`` of exactly the captured ``z``
  (at 4× the samples, so its noise does not leak into θ) and use that
  residual ``r = f̂(z_c) − y`` in Eq. 10 until the next capture. With
  ``capture_every=1`` this is the paper's rule up to render noise.
* **θ starts at the first residual** (``theta_init='capture'``) instead of
  0: otherwise θ would need ~100 of the 300 joint iterations (1 − 0.98ⁿ) to
  reach the bias it averages, and ``z`` would chase it meanwhile.
  ``theta_init='zero'`` gives the paper's behaviour.
* **Start from a one-shot photometric + geometric inverse** (``init='inverse'``):
  each projector input pixel is traced to the surface and into the camera, and
  starts at target / (simulated white) there (clipped to [0, 1]); pixels whose
  light misses the display area start black. Gradient descent then fixes what
  that ignores (indirect light, texture edges, clamping). It also gives pixels
  that a 4-spp render rarely samples a sensible value, since Adam only moves a
  pixel when a camera sample reaches it. ``init='grey'`` starts at 0.5.
* **Open loop** (no device): θ is estimated once from the calibration's
  white, black and validation captures (stages/bias.py). The result says
  ``mode='open-loop'``.

Where each part lives: ``stages/schedule.py`` (the schedules, their
constants, and why ``fast`` and ``transport`` are fast: "Speed"),
``stages/bias.py`` (θ's model and the open-loop estimate),
``stages/solve_render.py`` (fixed-point and Adam steps on Mitsuba renders),
``stages/solve_transport.py`` (the solve on the precomputed light-transport
operator). This module holds the :class:`Compensator`, which loads the
models, maps inputs through the warp, finds the start, and hands a target
to the schedule's solver.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..capture.devices import Device
from ..errors import Cancelled, CaptureError
from ..progress import Cancel, Progress
from ..render.forward import ForwardModel
from ..render.raycast import first_hits
from ..rig.model import square_scaled_size
from .bias import BiasModel, estimate_bias
from .display_area import DisplayArea, fit_target
from .metrics import area_psnr
from .schedule import (ALPHA, CAPTURE_EVERY, DEFAULT_SCHEDULE, ITERATIONS_JOINT, ITERATIONS_Z, LEARNING_RATE, MODES,
                       REFERENCE_SPP, SCHEDULES, CompensationError, Schedule, get_schedule, matched_alpha, plateaued,
                       split_iterations, with_held_blur)
from .solve_render import RenderSolve
from .solve_transport import TransportSolve
from .transport import BlurredRows, TransportOperator, TransportRows, build_transport


@dataclass
class CompensationResult:
    """The answer of stage C for one target."""

    x_input: np.ndarray  # x* = W(z), projector input size (H×W×3)
    x_frame: np.ndarray  # x* placed in the native projector frame
    z: np.ndarray  # the virtual input (input size)
    theta: np.ndarray  # camera-space bias θ at the end (Eq. 14 holds against ``simulated_raw``)
    simulated: np.ndarray  # clip(f̂(z) − θ): what the camera should see (camera size)
    simulated_raw: np.ndarray  # f̂(z) alone
    target: np.ndarray  # the target placed in its area (camera size, black elsewhere)
    area: DisplayArea
    losses: list[float]
    seconds: float
    mode: str
    captures: int = 0
    report: dict[str, Any] = field(default_factory=dict)



#: camera pixels beyond the display area's edge within which a texel's light may still land and be solved for:
#: an edge pixel shares texels with the surround, and holding those black would darken the area's edge
SURROUND_PAD = 0.5


class Compensator:
    """Stage C for one calibration: holds the loaded Mitsuba scene so that many targets reuse it.

    Loading the scene and compiling the render kernels is the slow start;
    Dr.Jit caches the compiled kernels, so the second target starts at once.
    """

    def __init__(self, calibration: Any, *, bounces: int = 1, spp: int = 4, seed: int = 0,
                 variant: str | None = None) -> None:

        if not isinstance(bounces, int) or bounces < 0:
            raise CompensationError(f"bounces must be a whole number ≥ 0, got {bounces!r}")
        self.calibration = calibration
        self.rig = calibration.rig
        self.warp = calibration.warp
        self.bounces, self.spp, self.seed = int(bounces), int(spp), int(seed)
        #: where the transport solve's steps run (stages/joint.py's ENGINES): ``auto``, Dr.Jit; ``numpy`` the old steps
        self.engine = "auto"
        # No border smoothing Γ: it only helps the pose search (stage A) and would dim the input's outer rows.
        self.model = ForwardModel(self.rig, calibration.surface, bounces=bounces, spp=spp, smoothing_eps=0.0,
                                  clamp=True, seed=seed, variant=variant)
        self._mi, self._dr = self.model._mi, self.model._dr
        proj = self.rig.projector
        (self.iw, self.ih), (self.fw, self.fh) = proj.input_size, proj.intrinsics.size
        self.camera_size = self.model.camera_size
        # Frame texel → input texel, so the frame is a differentiable gather of z (black outside the input).
        x0, y0 = proj.input_offset
        rows, cols, ch = np.meshgrid(np.arange(self.fh), np.arange(self.fw), np.arange(3), indexing="ij")
        r, c = rows - y0, cols - x0
        inside = (r >= 0) & (r < self.ih) & (c >= 0) & (c < self.iw)
        index = np.where(inside, (r * self.iw + c) * 3 + ch, 0)
        self._frame_index = self._mi.UInt32(index.astype(np.uint32).ravel())
        self._frame_inside = self._mi.Bool(inside.ravel())
        self._correspondence: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        #: the last display area's :meth:`area_texels` (a solve asks for them at its start, its step and its end)
        self._area_texels: tuple[DisplayArea, np.ndarray] | None = None
        #: the flat indices of the texels that area's :meth:`area_texels` leaves out, and of the texels the camera
        #: does not see (:meth:`correspondence`): written per target on whole inputs, by index (3× faster than a
        #: masked ``np.where`` over every texel at 1920×1080)
        self._surround_texels: np.ndarray | None = None
        self._hidden_texels: np.ndarray | None = None
        self._white: np.ndarray | None = None
        self._coarse_models: dict[tuple[int, int], Any] = {}
        self._crop_models: dict[tuple[int, int, int, int], Any] = {}
        self._transport: TransportOperator | None = None
        self._views: dict[tuple[Any, ...], TransportRows | BlurredRows] = {}
        #: the projector lens's blur of the input (texels, as the diagnosis fitted it): the transport solve then
        #: runs through it (:class:`BlurredRows`) and its answer is the input to send before the blur. It blurs
        #: z, not the real input x: the two differ by the stage-B warp, a fraction of a texel.
        self.input_blur: float | None = None
        #: the light (a share of white, R, G, B) the input holds outside the display area: texels whose light lands
        #: more than :data:`SURROUND_PAD` camera pixels outside it are not solved for but held at this (black
        #: by default), whatever the solve would gain from them through a blur's tail or bounce light
        self.surround: tuple[float, float, float] = (0.0, 0.0, 0.0)

    # ------------------------------------------------------------------ helpers

    def model_at(self, scale: float) -> Any:
        """The forward model with the camera at ``scale`` × its resolution (built once, then reused: the
        coarse phase's scene and kernels serve every later target)."""
        if scale >= 1.0:
            return self.model
        cw, ch = self.camera_size
        size = square_scaled_size(cw, ch, scale)
        if size not in self._coarse_models:

            self._coarse_models[size] = ForwardModel(self.rig, self.calibration.surface, camera_size=size,
                                                     bounces=self.bounces, spp=self.spp, smoothing_eps=0.0,
                                                     clamp=True, seed=self.seed, variant=self.model.variant)
        return self._coarse_models[size]

    def model_cropped(self, window: tuple[int, int, int, int]) -> Any:
        """The full-resolution forward model rendering only ``window`` = (x, y, width, height) of the camera
        (built once per window: every target in the same display area reuses its scene and kernels)."""
        key = tuple(int(v) for v in window)
        if key not in self._crop_models:

            self._crop_models[key] = ForwardModel(self.rig, self.calibration.surface, bounces=self.bounces,
                                                  spp=self.spp, smoothing_eps=0.0, clamp=True, seed=self.seed,
                                                  variant=self.model.variant, crop=key)
        return self._crop_models[key]

    @staticmethod
    def downsample(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """Area average of a camera-space image to ``size`` = (width, height) (as a coarser camera sees it)."""
        import cv2

        img = np.asarray(image, dtype=np.float32)
        if (img.shape[1], img.shape[0]) == tuple(size):
            return img
        return cv2.resize(img, tuple(size), interpolation=cv2.INTER_AREA).reshape(size[1], size[0], *img.shape[2:])

    def warp_w(self, z: np.ndarray) -> np.ndarray:
        """The real input ``x = W(z)`` (identity without a warp), clipped to [0, 1]."""
        x = z if self.warp is None else self.warp.apply_w(np.asarray(z, np.float32))
        return np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)

    def warp_m(self, x: np.ndarray) -> np.ndarray:
        """The virtual input ``z = M(x)`` whose real projection is ``x``."""
        z = x if self.warp is None else self.warp.apply_m(np.asarray(x, np.float32))
        return np.clip(np.asarray(z, dtype=np.float32), 0.0, 1.0)

    def simulate(self, z: np.ndarray, *, spp: int = REFERENCE_SPP, seed: int | None = None) -> np.ndarray:
        """``f̂(z)`` (camera size, clamped) of a virtual input."""
        return self.model.render_input(np.clip(z, 0.0, 1.0), spp=spp, seed=seed)

    def white(self) -> np.ndarray:
        """``f̂`` of a white input (cached): the most light each camera pixel can get."""
        if self._white is None:
            self._white = self.simulate(np.ones((self.ih, self.iw, 3), np.float32), seed=self.seed + 101)
        return self._white

    def correspondence(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For each input pixel, the camera pixel (x, y, pixel-centre coordinates) its light lands on, and
        whether the camera sees that surface point (ray cast through the calibrated model)."""
        if self._correspondence is None:

            proj = self.rig.projector
            x0, y0 = proj.input_offset
            ys, xs = np.mgrid[0:self.ih, 0:self.iw] + 0.5
            pix = np.stack([xs.ravel() + x0, ys.ravel() + y0], axis=1)
            pose = proj.camera_from_projector
            dirs = proj.intrinsics.rays(pix) @ pose[:3, :3].T
            origin = pose[:3, 3]
            t = first_hits(self.calibration.surface, origin, dirs)
            hit = np.isfinite(t)
            points = origin + np.where(hit, t, 1.0)[:, None] * dirs
            # The camera sees the point when nothing lies between: a ray towards it first hits at t ≈ 1.
            t_cam = first_hits(self.calibration.surface, np.zeros(3), points)
            visible = hit & np.isfinite(t_cam) & (t_cam > 1.0 - 1e-3)
            cam = self.model.camera.project(points)
            cam = np.where(np.isfinite(cam), cam, -1e6)
            shape = (self.ih, self.iw)
            self._correspondence = ((cam[:, 0] - 0.5).reshape(shape).astype(np.float32),
                                    (cam[:, 1] - 0.5).reshape(shape).astype(np.float32), visible.reshape(shape))
        return self._correspondence

    def area_texels(self, area: DisplayArea) -> np.ndarray:
        """(ih, iw) bool: the input texels stage C solves for in ``area``: those whose light lands on the camera
        inside it or within :data:`SURROUND_PAD` pixels of its edge (the texels an edge pixel shares with the
        surround); the others hold the :attr:`surround`."""
        if self._area_texels is not None and self._area_texels[0] == area:
            return self._area_texels[1]
        mx, my, visible = self.correspondence()
        pad = SURROUND_PAD
        keep = (visible & (mx >= area.x - 0.5 - pad) & (mx <= area.x + area.width - 0.5 + pad)
                & (my >= area.y - 0.5 - pad) & (my <= area.y + area.height - 0.5 + pad))
        keep.setflags(write=False)  # shared by every caller of this area
        self._area_texels = (area, keep)
        self._surround_texels = np.flatnonzero(~keep)
        return keep

    def hold_surround(self, z: np.ndarray, area: DisplayArea) -> np.ndarray:
        """``z`` (input size) with every texel outside :meth:`area_texels` at the :attr:`surround`."""
        self.area_texels(area)
        out = np.array(z, np.float32).reshape(self.ih, self.iw, 3)
        out.reshape(-1, 3)[self._surround_texels] = np.asarray(self.surround, np.float32)
        return out

    def camera_to_input(self, image: np.ndarray) -> np.ndarray:
        """Sample a camera-space image at each input pixel's camera location (black where not seen)."""
        import cv2

        mx, my, visible = self.correspondence()
        if self._hidden_texels is None:
            self._hidden_texels = np.flatnonzero(~visible)
        out = cv2.remap(np.asarray(image, np.float32), mx, my, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        out.reshape(-1, out.shape[-1] if out.ndim == 3 else 1)[self._hidden_texels] = 0.0
        return out

    def initial_input(self, target: np.ndarray, bias: BiasModel | None = None, how: str = "inverse") -> np.ndarray:
        """Starting ``z``: ``'inverse'`` = target / simulated white mapped into the projector, ``'geometric'`` =
        the target mapped into the projector as is, ``'grey'`` = 0.5 everywhere."""
        if how == "grey":
            return np.full((self.ih, self.iw, 3), 0.5, np.float32)
        if how == "geometric":
            return np.clip(self.camera_to_input(target), 0.0, 1.0)
        if how != "inverse":
            raise CompensationError(f"init must be 'inverse', 'geometric' or 'grey', got {how!r}")
        white = self.white()
        want = target
        gain = None
        if bias is not None:
            # Solve pred = gain·f̂ − θ = target for f̂ (θ is in camera space like the target).
            want = target + bias.theta
            gain = bias.gain
        reach = white if gain is None else gain * white
        ratio = np.where(reach > 1e-3, want / np.maximum(reach, 1e-3), 0.0)
        ratio = np.where(target > 0, ratio, 0.0)  # outside the area: leave the projector dark
        return np.clip(self.camera_to_input(np.clip(ratio, 0.0, 1.0)), 0.0, 1.0)

    def start_input(self, z: np.ndarray) -> np.ndarray:
        """A given starting ``z`` (a warm start), checked: input size, finite, clipped to [0, 1]."""
        a = np.asarray(z, dtype=np.float32)
        if a.shape != (self.ih, self.iw, 3) or not np.all(np.isfinite(a)):
            raise CompensationError(f"a starting input must be a finite {self.iw}×{self.ih}×3 image, got shape "
                                    f"{a.shape}")
        return np.clip(a, 0.0, 1.0)

    def _check_capture(self, y: np.ndarray) -> np.ndarray:
        img = np.asarray(y, dtype=np.float32)
        cw, ch = self.camera_size
        if img.shape != (ch, cw, 3):
            raise CaptureError(f"the capture device returned a {img.shape[1] if img.ndim > 1 else '?'}×"
                               f"{img.shape[0]} image (shape {img.shape}), but the calibration's camera is "
                               f"{cw}×{ch}×3; is the device the rig that was calibrated?")
        if not np.all(np.isfinite(img)):
            raise CaptureError("the capture device returned an image with NaN or infinite values")
        return img

    def check_device(self, device: Device) -> None:
        """Refuse a device whose projector does not match the calibrated one."""
        proj = getattr(device, "projector", None)
        mine = self.rig.projector
        if proj is not None and (proj.intrinsics.size != mine.intrinsics.size or proj.input_size != mine.input_size
                                 or proj.input_offset != mine.input_offset):
            raise CompensationError(
                f"the device's projector ({proj.intrinsics.width}×{proj.intrinsics.height}, input "
                f"{proj.input_size[0]}×{proj.input_size[1]} at {proj.input_offset}) is not the calibrated one "
                f"({mine.intrinsics.width}×{mine.intrinsics.height}, input {mine.input_size[0]}×{mine.input_size[1]} "
                f"at {mine.input_offset}); calibrate with captures from this device")
        cam = getattr(device, "camera_size", None)  # known before any capture only for a live camera
        want = self.rig.camera.intrinsics.size
        if cam is not None and tuple(cam) != tuple(want):
            raise CompensationError(f"the device's camera delivers {cam[0]}×{cam[1]} frames but the calibration's "
                                    f"camera is {want[0]}×{want[1]}: set the camera to the resolution the capture "
                                    "set was taken at (live: size=WxH), or calibrate with captures from this camera")


    # ------------------------------------------------------------------ θ and the run

    def estimate_bias(self, captures: Any = None, *, ridge: float = 0.05) -> BiasModel:
        """θ for open-loop compensation, from the calibration's white/black/validation captures (stages/bias.py)."""
        return estimate_bias(self, captures, ridge=ridge)

    def run(self, target: np.ndarray, area: DisplayArea, *, device: Device | None = None,
            schedule: str | Schedule = DEFAULT_SCHEDULE, iterations_z: int | None = None,
            iterations_joint: int | None = None, lr: float | None = None, alpha: float | None = None,
            capture_every: int | None = None, loop: str | None = None, progress: Progress | None = None,
            cancel: Cancel | None = None, open_loop_theta: np.ndarray | BiasModel | None = None,
            use_bias: bool = True, init: str = "inverse", theta_init: str = "capture",
            name: str = "target", start: np.ndarray | None = None, verify: bool | None = None
            ) -> CompensationResult:
        """Find the projector input ``x* = W(z)`` whose projection looks like ``target`` inside ``area``.

        ``target``: H×W×3 linear float in [0, 1], any size (fitted to the area,
        see :func:`.display_area.fit_target`). ``device`` given: closed loop
        (θ from captures every ``capture_every`` joint iterations); else open loop
        (θ from the calibration's validation captures, or ``open_loop_theta``);
        ``use_bias=False``: no θ at all (mode ``'none'``, the paper's ablation).
        ``schedule``: ``'transport'`` (default), ``'fast'``, ``'paper'`` or a :class:`Schedule`;
        ``iterations_z``, ``iterations_joint``, ``lr``, ``alpha`` and
        ``capture_every`` override its values when given; ``loop`` the closed loop's rule (``measured`` or
        ``damped``, :attr:`~.schedule.Schedule.loop`). ``start``: the virtual input z to start from (a warm
        start, e.g. the previous frame's answer) instead of ``init``. ``verify``: overrides the schedule's
        ``verify`` (the transport schedule's closing Mitsuba render). Raises :class:`CompensationError`
        when the optimisation diverges, :class:`Cancelled` when ``cancel()`` turns true.
        """
        t_start = time.perf_counter()
        say = progress or (lambda msg, frac: None)
        sched = self.schedule_for(schedule, held_blur=bool(self.input_blur), iterations_z=iterations_z,
                                  iterations_joint=iterations_joint, lr=lr, alpha=alpha, capture_every=capture_every,
                                  loop=loop)
        if not sched.transport and sched.loop != "damped":  # the schedules that render follow Eq. 10: say so
            sched = replace(sched, loop="damped")
        if theta_init not in ("capture", "zero"):
            raise CompensationError(f"theta_init must be 'capture' or 'zero', got {theta_init!r}")
        if self.input_blur and not sched.transport:
            raise CompensationError(f"the projector lens's blur is held by the transport schedule only, not by "
                                    f"{sched.name!r}: compensate with --schedule transport")
        area = area.check(self.camera_size)
        placed = area.place(fit_target(target, area, what=f"target {name!r}"), self.camera_size)
        mode, bias = self.bias_for(placed, device, use_bias, open_loop_theta, say, name)
        z0 = self.initial_input(placed, bias, init) if start is None else self.start_input(start)
        z0 = self.hold_surround(z0, area)  # the surround is not solved for: it holds its colour from the start
        if sched.transport:
            solve = TransportSolve(self, placed, area, z0, sched, mode, bias, device, say, cancel, name)
            return solve.run(sched.verify if verify is None else bool(verify), t_start)
        return RenderSolve(self, placed, area, z0, sched, mode, bias, device, say, cancel, name).run(
            z0, init, theta_init, t_start)

    @staticmethod
    def schedule_for(schedule: str | Schedule, *, held_blur: bool = False, **given: Any) -> Schedule:
        """The schedule a run follows: ``schedule`` with the values ``given`` (None: the schedule's) over it, and
        with ``held_blur`` (a lens blur held in the solve) :func:`~.schedule.with_held_blur`'s steps."""
        for what in ("iterations_z", "iterations_joint", "capture_every"):
            v = given[what]
            if v is not None and (isinstance(v, bool) or not isinstance(v, int)):
                raise CompensationError(f"{what} must be a whole number, got {v!r}")
        for what in ("lr", "alpha"):
            v = given[what]
            if v is not None and not isinstance(v, (int, float)):
                raise CompensationError(f"{what} must be a number, got {v!r}")
        if given["capture_every"] is not None:
            given["captures"] = None  # an explicit interval replaces the schedule's number of captures
        sched = replace(get_schedule(schedule), **{k: v for k, v in given.items()
                                                   if v is not None or k == "captures"}).check()
        return with_held_blur(sched, schedule, given["iterations_joint"]) if held_blur else sched

    def bias_for(self, placed: np.ndarray, device: Device | None, use_bias: bool,
                 open_loop_theta: np.ndarray | BiasModel | None, say: Progress, name: str
                 ) -> tuple[str, BiasModel | None]:
        """The mode (closed-loop, open-loop or none) and, in the open loop, θ's model: the one given, a θ image
        given, else estimated from the validation captures."""
        bias: BiasModel | None = None
        if device is not None and use_bias:
            mode = "closed-loop"
            self.check_device(device)
        elif use_bias:
            mode = "open-loop"
            if isinstance(open_loop_theta, BiasModel):
                bias = open_loop_theta
            elif open_loop_theta is not None:
                theta = np.asarray(open_loop_theta, dtype=np.float32)
                cw, ch = self.camera_size
                if theta.shape != (ch, cw, 3) or not np.all(np.isfinite(theta)):
                    raise CompensationError(f"open_loop_theta must be a finite {cw}×{ch}×3 camera-space image, "
                                            f"got shape {theta.shape}")
                bias = BiasModel(theta, None, "given")
            else:
                say(f"{name}: estimating θ from the validation captures (open loop)", 0.0)
                bias = self.estimate_bias()
        else:
            mode = "none"
        if bias is not None and (bias.theta.shape[:2] != placed.shape[:2]):
            raise CompensationError("the open-loop θ does not have the camera's size")
        return mode, bias

    def result(self, z: np.ndarray, theta: np.ndarray, simulated: np.ndarray, raw: np.ndarray, placed: np.ndarray,
               area: DisplayArea, losses: list[float], mode: str, captures: int, report: dict[str, Any], *,
               t_start: float, seconds_device: float, name: str, say: Progress) -> CompensationResult:
        """A solver's answer for the virtual input ``z`` as stage C gives it: the real input ``W(z)``, its native
        frame, and the report closed with the seconds of compute (all since ``t_start`` but the device's)."""
        # The solves on the operator never move the surround; a solve that renders may have (its gradient reaches
        # texels whose light lands just outside the area): they are put back to the surround here.
        z = self.hold_surround(z, area)
        x_input = self.warp_w(z)
        seconds = time.perf_counter() - t_start
        report["seconds_compute"] = round(seconds - seconds_device, 2)
        say(f"{name}: done in {seconds:.1f} s ({seconds - seconds_device:.1f} s without the device)", 1.0)
        return CompensationResult(x_input, self.rig.projector.frame_from_input(x_input), z, theta, simulated, raw,
                                  placed, area, losses, seconds, mode, captures, report)

    # ------------------------------------------------------------------ the transport operator

    @property
    def transport(self) -> TransportOperator:
        """The light-transport operator ``T`` (stages/transport.py): the one given, else rendered now (once)."""
        if self._transport is None:
            self._transport = build_transport(self.calibration, bounces=self.bounces, seed=self.seed,
                                              variant=self.model.variant)
        return self._transport

    @transport.setter
    def transport(self, op: TransportOperator | None) -> None:
        if op is not None and (op.camera_size != tuple(self.camera_size) or op.input_size != (self.iw, self.ih)):
            raise CompensationError(f"the transport operator is for a {op.camera_size} camera and {op.input_size} "
                                    "input, not this calibration's: run procam precompute again")
        self._transport = op
        self._views.clear()

    def transport_view(self, area: DisplayArea) -> TransportRows | BlurredRows:
        """``T`` on the display area's camera pixels (``T B`` with :attr:`input_blur`), built once per area:
        building it (regrouping the entries by texel for the adjoint) costs as much as a whole solve at full
        resolution."""
        key = (area.x, area.y, area.width, area.height, self.input_blur)
        if key not in self._views:
            if len(self._views) >= 4:  # a show has one area per aspect ratio; keep memory bounded all the same
                self._views.pop(next(iter(self._views)))
            rows = np.flatnonzero(area.mask(self.camera_size).ravel())
            view = self.transport.rows(rows, self.model.variant)
            self._views[key] = view if not self.input_blur else BlurredRows(view, self.input_blur)
        return self._views[key]


__all__ = ["ALPHA", "BiasModel", "CAPTURE_EVERY", "Cancelled", "CompensationError", "CompensationResult",
           "Compensator", "DEFAULT_SCHEDULE", "ITERATIONS_JOINT", "ITERATIONS_Z", "LEARNING_RATE", "MODES",
           "REFERENCE_SPP", "SCHEDULES", "Schedule", "area_psnr", "get_schedule", "matched_alpha", "plateaued",
           "split_iterations"]
