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
  white, black and validation captures. Each captured pattern ``x`` is
  simulated as ``f̂(M(x))`` (``M`` the inverse warp, since ``x = W(z)`` means
  ``z = M(x)``), and either the per-pixel mean residual (``pred = f̂ − θ``) or
  a per-pixel, per-channel affine fit (``pred = a·f̂ + b``, ridge towards
  ``a = 1``) is kept, whichever predicts held-out patterns better
  (leave-one-pattern-out). The result says ``mode='open-loop'``.

Speed (issue 5: under 60 s per target on 2 cores at 640×480 with one bounce,
no worse than the paper's 500 steps). An Adam iteration costs a forward and an
adjoint render (~0.75 s at 4 spp over the whole camera), so the paper's
schedule is ~400 s. The ``'fast'`` :class:`Schedule` gets the same quality
from less (and ``'transport'``, the default, from no render at all: it solves
on the calibration's precomputed light-transport operator, ``_run_transport``,
at the same captured PSNR in under a second a target; ``fast`` stays for
scenes the operator does not hold):

* **Fixed-point steps instead of the z phase** (``fixed_point``): direct
  light makes the camera image nearly linear in z, pixel by pixel, with the
  simulated white image as the slope; so
  ``z ← clip(z + η · M_c((y_t − (f̂(z) − θ)) / f̂(1)))``, ``M_c`` the ray-cast
  camera → input correspondence and η = 0.7 (below 1: indirect light adds to
  the direct term; halved for the second half of the steps), is a
  preconditioned (Jacobi) step that needs a forward render only and moves
  every input pixel, where an Adam step moves only the pixels its few
  samples reach (16-spp renders: their noise goes straight into z). Eight
  such steps replace the paper's 200 Adam iterations on z alone; Adam (the
  paper's method, true gradients) then does the rest.
* **Two fixed-point steps after each capture** (``fixed_point_joint``): the
  new θ is taken into z at once, not over the next iterations.
* **Render only the display area** (``crop``): the loss looks nowhere else,
  so the camera film is cropped to the area (a quarter of the demo's
  pixels); θ is then 0 outside it.
* **15 captures spread over fewer joint iterations, α matched**
  (:func:`matched_alpha`): each capture keeps the weight it has in θ with
  the paper's α and a capture every 20.
* **Compiled kernels are reused**: Mitsuba's seeds and Dr.Jit's Adam step
  are opaque, so no iteration recompiles (Dr.Jit's kernel history: every
  launch after the first iteration is a cache hit), and one
  :class:`Compensator` keeps each model (full, cropped, coarse) for every
  target.

Tried and not kept (``scripts/bench_stage_c.py``, row ``coarse``): a coarse
z phase at half the camera resolution, 1 spp in the z phases, a plateau stop
and a cosine learning-rate decay — cheaper, but 0.5 dB below the paper.
Figures: README ("Stage C speed").
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from ..capture.devices import Device
from ..capture.format import CaptureSet
from ..errors import CalibrationError, Cancelled, CaptureError, ProCamError
from ..progress import Cancel, Progress
from ..render.forward import ForwardModel
from ..render.raycast import first_hits
from ..rig.model import square_scaled_size
from .display_area import DisplayArea, fit_target
from .metrics import psnr
from .transport import BlurredRows, TransportOperator, TransportRows, build_transport


#: Defaults of the paper's schedule and of the choices documented above.
ITERATIONS_Z = 200
ITERATIONS_JOINT = 300
ALPHA = 0.01
LEARNING_RATE = 0.01
CAPTURE_EVERY = 20
#: Step of the fixed-point phase (module doc): below 1 because indirect light adds to what the direct term predicts.
FIXED_POINT_STEP = 0.7
#: Samples per pixel of renders that are not inside the loop (θ references, final simulation): less noise.
REFERENCE_SPP = 16
MODES = ("closed-loop", "open-loop", "none")


class CompensationError(ProCamError):
    """Stage C cannot proceed or diverged."""


def matched_alpha(capture_every: int, alpha: float = ALPHA, reference_every: int = CAPTURE_EVERY) -> float:
    """The α that gives each capture the weight it has in θ with ``alpha`` and a capture every ``reference_every``.

    Between captures Eq. 10 pulls θ towards a fixed residual, so after K
    iterations θ has moved ``1 − (1 − 2α)^K`` of the way: capturing more often
    with the same α would average fewer captures, i.e. keep more capture noise.
    """
    return 0.5 * (1.0 - (1.0 - 2.0 * alpha) ** (reference_every / capture_every))


@dataclass(frozen=True)
class Schedule:
    """How stage C spends its iterations and samples (module doc, "Speed").

    Phases, in order: ``coarse`` (z alone, camera at ``coarse`` × its
    resolution, at most ``iterations_coarse`` iterations, counted within
    ``iterations_z``), ``z`` (z alone, full resolution, what is left of
    ``iterations_z``), ``joint`` (``iterations_joint`` iterations; closed loop:
    z and θ with a capture every ``capture_every``, or, when ``captures`` is
    set, ``captures`` captures spread evenly over however many joint iterations
    there are; otherwise z with θ fixed).
    ``plateau`` > 0 ends a z phase once the mean loss of its last ``plateau``
    iterations is less than ``plateau_tol`` (relative) below that of the
    ``plateau`` before. ``alpha`` None: :func:`matched_alpha` of the capture
    interval (the paper's per-capture weight whatever the interval).
    ``lr_end`` set: the learning rate follows a cosine from ``lr`` to
    ``lr_end`` over the joint phase. ``spp_z``: samples per pixel of the z
    phases (None = the compensator's ``spp``, which the joint phase uses).
    ``reference_spp``: samples of the render of each captured z (θ's residual).
    ``spp_joint``: samples of the joint phase (None = the compensator's).
    ``fixed_point``: fixed-point steps on z before the z phases, and
    ``fixed_point_joint`` after each capture, each a ``fixed_point_spp``
    forward render and a step of ``fixed_point_step`` (module doc, "Speed").
    ``crop``: full-resolution renders cover only the display area.
    """

    name: str
    iterations_z: int = ITERATIONS_Z
    iterations_joint: int = ITERATIONS_JOINT
    lr: float = LEARNING_RATE
    lr_end: float | None = None
    alpha: float | None = ALPHA
    capture_every: int = CAPTURE_EVERY
    captures: int | None = None
    plateau: int = 0
    plateau_tol: float = 0.02
    spp_z: int | None = None
    spp_joint: int | None = None
    coarse: float = 1.0
    iterations_coarse: int = 0
    reference_spp: int = REFERENCE_SPP
    fixed_point: int = 0
    fixed_point_joint: int = 0
    fixed_point_spp: int = 4
    fixed_point_step: float = FIXED_POINT_STEP
    crop: bool = False
    #: solve on the precomputed light-transport operator instead of rendering (stages/transport.py): then
    #: ``iterations_z`` solver iterations before the first capture, ``iterations_joint`` spread over ``captures``
    transport: bool = False
    #: with ``transport``: render the answer once with Mitsuba to report what the scene (not the operator)
    #: predicts; costs one render, more than the solve itself at full resolution
    verify: bool = True

    def check(self) -> "Schedule":
        """Self, or a CompensationError naming the first bad value."""
        for what in ("iterations_z", "iterations_joint", "iterations_coarse", "plateau", "fixed_point",
                     "fixed_point_joint"):
            v = getattr(self, what)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise CompensationError(f"{what} must be a whole number ≥ 0, got {v!r}")
        for what in ("capture_every", "reference_spp", "captures", "fixed_point_spp"):
            v = getattr(self, what)
            if (v is not None or what != "captures") and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise CompensationError(f"{what} must be a whole number ≥ 1, got {v!r}")
        for what in ("spp_z", "spp_joint"):
            v = getattr(self, what)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise CompensationError(f"{what} must be a whole number ≥ 1 or None, got {v!r}")
        for what in ("spp_z", "spp_joint", "reference_spp", "fixed_point_spp"):
            # The scene's stratified sampler (a square spp) silently rounds other counts up to a square.
            v = getattr(self, what)
            if v is not None and math.isqrt(v) ** 2 != v:
                raise CompensationError(f"{what} must be a square (1, 4, 9, 16, …), got {v}: the stratified "
                                        "sampler would round it up")
        if not (isinstance(self.lr, (int, float)) and math.isfinite(self.lr) and self.lr > 0):
            raise CompensationError(f"the learning rate must be a positive number, got {self.lr!r}")
        if self.lr_end is not None and not (math.isfinite(self.lr_end) and 0 < self.lr_end <= self.lr):
            raise CompensationError(f"lr_end must lie in (0, lr = {self.lr}], got {self.lr_end!r}")
        if self.alpha is not None and not (math.isfinite(self.alpha) and 0 < self.alpha <= 0.5):
            raise CompensationError(f"α must lie in (0, 0.5] (Eq. 10 overshoots beyond), got {self.alpha!r}")
        if not (math.isfinite(self.coarse) and 0.1 <= self.coarse <= 1.0):
            raise CompensationError(f"coarse must lie in [0.1, 1] (a fraction of the camera resolution), "
                                    f"got {self.coarse!r}")
        if not (isinstance(self.fixed_point_step, (int, float)) and 0 < self.fixed_point_step <= 1):
            raise CompensationError(f"fixed_point_step must lie in (0, 1] (1 is the Newton step of direct light), "
                                    f"got {self.fixed_point_step!r}")
        if not (math.isfinite(self.plateau_tol) and 0 <= self.plateau_tol < 1):
            raise CompensationError(f"plateau_tol must lie in [0, 1), got {self.plateau_tol!r}")
        return self

    @property
    def capture_interval(self) -> int:
        """Joint iterations between captures: from ``captures`` when set, else ``capture_every``."""
        if self.captures is None:
            return int(self.capture_every)
        return max(1, math.ceil(self.iterations_joint / self.captures))

    @property
    def theta_rate(self) -> float:
        """α of Eq. 10 as used: ``alpha``, or matched to the capture interval when None."""
        return matched_alpha(self.capture_interval) if self.alpha is None else float(self.alpha)

    def learning_rate(self, step: int, steps: int) -> float:
        """The joint phase's learning rate at ``step`` of ``steps`` (cosine to ``lr_end``)."""
        if self.lr_end is None or steps <= 1:
            return float(self.lr)
        t = min(max(step / (steps - 1), 0.0), 1.0)
        return float(self.lr_end + 0.5 * (self.lr - self.lr_end) * (1.0 + math.cos(math.pi * t)))


#: The fast schedule (the default; module doc, "Speed") and the paper's.
SCHEDULES: dict[str, Schedule] = {
    "fast": Schedule("fast", iterations_z=0, iterations_joint=150, alpha=None, captures=15, fixed_point=8,
                     fixed_point_joint=2, fixed_point_spp=16, crop=True),
    "paper": Schedule("paper"),
    # As many captures as fast: how many a closed loop needs depends on how far the rig is from the model (3
    # were enough in the lab, the live loopback needed 15: 23.8 against 38.0 dB); two solver steps between them.
    "transport": Schedule("transport", iterations_z=10, iterations_joint=30, alpha=None, captures=15,
                          transport=True, verify=False),
}
#: ``transport`` matched ``fast``'s captured PSNR within 0.1 dB on six targets, closed and open loop, at 40–60×
#: less compute (scripts/bench_transport.py); without a stored operator it renders one first (~25 s at 640×480)
DEFAULT_SCHEDULE = "transport"


def get_schedule(schedule: str | Schedule) -> Schedule:
    """A schedule by name (``'transport'``, ``'fast'``, ``'paper'``) or as given."""
    if isinstance(schedule, Schedule):
        return schedule.check()
    if schedule not in SCHEDULES:
        raise CompensationError(f"unknown schedule {schedule!r}; choose one of {', '.join(SCHEDULES)}")
    return SCHEDULES[schedule]



@dataclass
class BiasModel:
    """How a capture is predicted from the simulation: ``pred = clip(gain · f̂ − theta, 0, 1)``.

    ``gain`` None means 1 (the paper's θ); the bias of Eq. 3 is then
    ``f̂ − pred``, which satisfies Eq. 14 by construction.
    """

    theta: np.ndarray
    gain: np.ndarray | None = None
    kind: str = "mean"  # 'mean', 'affine' or 'zero'
    report: dict[str, Any] = field(default_factory=dict)

    def predict(self, simulated: np.ndarray) -> np.ndarray:
        f = np.asarray(simulated, dtype=np.float32)
        return np.clip((f if self.gain is None else self.gain * f) - self.theta, 0.0, 1.0)

    def bias(self, simulated: np.ndarray) -> np.ndarray:
        """θ of Eq. 3 for a simulation ``f̂`` (within [f̂ − 1, f̂])."""
        return np.asarray(simulated, dtype=np.float32) - self.predict(simulated)


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


def area_psnr(image: np.ndarray, target: np.ndarray, area: DisplayArea) -> float:
    """PSNR (dB, peak 1) of ``image`` against ``target`` inside the area (both camera size)."""
    return psnr(area.crop(image), area.crop(target))


def plateaued(losses: list[float], window: int, tol: float) -> bool:
    """True when the mean of the last ``window`` losses is less than ``tol`` (relative) below the mean of the
    ``window`` before (window means, since each loss is a noisy Monte Carlo estimate); never with window 0."""
    if window <= 0 or len(losses) < 2 * window:
        return False
    return float(np.mean(losses[-window:])) > (1.0 - tol) * float(np.mean(losses[-2 * window:-window]))


def split_iterations(total: int | None, schedule: "str | Schedule" = DEFAULT_SCHEDULE
                     ) -> tuple[int | None, int | None]:
    """Split a total iteration count between z alone and z + θ in the schedule's own ratio (the paper's 200 : 300;
    all joint for ``'fast'``, whose z phase is fixed-point steps). None: the schedule's own counts."""
    if total is None:
        return None, None
    if isinstance(total, bool) or not isinstance(total, int) or total < 0:
        raise CompensationError(f"the iteration count must be a whole number ≥ 0, got {total!r}")
    s = get_schedule(schedule)
    both = s.iterations_z + s.iterations_joint
    z = round(total * s.iterations_z / both) if both else 0
    return z, total - z


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
        self._white: np.ndarray | None = None
        self._coarse_models: dict[tuple[int, int], Any] = {}
        self._crop_models: dict[tuple[int, int, int, int], Any] = {}
        self._transport: TransportOperator | None = None
        self._views: dict[tuple[Any, ...], TransportRows | BlurredRows] = {}
        #: the projector lens's blur of the input (texels, as the diagnosis fitted it): the transport solve then
        #: runs through it (:class:`BlurredRows`) and its answer is the input to send before the blur. It blurs
        #: z, not the real input x: the two differ by the stage-B warp, a fraction of a texel.
        self.input_blur: float | None = None

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

    def camera_to_input(self, image: np.ndarray) -> np.ndarray:
        """Sample a camera-space image at each input pixel's camera location (black where not seen)."""
        import cv2

        mx, my, visible = self.correspondence()
        out = cv2.remap(np.asarray(image, np.float32), mx, my, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return np.where(visible[..., None], out, 0.0).astype(np.float32)

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

    # ------------------------------------------------------------------ open-loop bias

    def estimate_bias(self, captures: Any = None, *, ridge: float = 0.05) -> BiasModel:
        """θ for open-loop compensation, from the calibration's white/black/validation captures (module doc)."""

        if captures is None:
            try:
                captures = CaptureSet.load(self.calibration.capture_dir, verify_images=False)
            except ProCamError as exc:
                raise CalibrationError(f"open-loop compensation needs the calibration's capture set to estimate θ, "
                                       f"but it cannot be read: {exc}") from None
        if captures.camera.intrinsics.size != self.camera_size:
            cw, ch = captures.camera.intrinsics.size
            raise CalibrationError(f"the capture set {captures.path} has {cw}×{ch} camera images, but the "
                                   f"calibration's camera is {self.camera_size[0]}×{self.camera_size[1]}: "
                                   "the calibration comes from another capture set")
        entries = [e for kind in ("black", "white", "validation") for e in captures.entries_of(kind) if e.pattern]
        if len(entries) < 3:
            raise CalibrationError(f"the capture set {captures.path} has {len(entries)} captures of known patterns "
                                   "(white, black, validation); open-loop θ needs at least 3")
        proj = self.rig.projector
        x0, y0 = proj.input_offset
        sims, caps = [], []
        for i, e in enumerate(entries):
            frame = captures.pattern(e.kind, name=e.name)
            if frame.shape[:2] != (self.fh, self.fw):
                raise CalibrationError(f"pattern {e.pattern} is {frame.shape[1]}×{frame.shape[0]}, not the "
                                       f"projector's {self.fw}×{self.fh}: the calibration comes from another "
                                       "capture set")
            virtual = frame.copy()
            region = (slice(y0, y0 + self.ih), slice(x0, x0 + self.iw))
            virtual[region] = self.warp_m(frame[region])
            sims.append(self.model.render(virtual, spp=REFERENCE_SPP, seed=self.seed + 1000 + i))
            caps.append(captures.image(e.kind, name=e.name))
        f = np.stack(sims).astype(np.float64)
        c = np.stack(caps).astype(np.float64)
        # A value given as NaN is left out: captures seen through a glossy model mark so what the camera clipped
        # in the highlight (``gap.compensation.AdaptedCaptures``).
        w = np.isfinite(c).astype(np.float64)
        c = np.where(w > 0, c, 0.0)
        n = len(f)
        lit = np.broadcast_to((self.white().mean(axis=2) > 1e-3)[..., None], c.shape[1:])
        # Mean residual, leave-one-out: θ_{-i} = (Σr − r_i)/(k − 1) over the k values given.
        r = (f - c) * w
        r_sum, k_all = r.sum(axis=0), w.sum(axis=0)
        mean_err = [(r[i] - (r_sum - r[i]) / np.maximum(k_all - w[i], 1))[lit & (w[i] > 0)] for i in range(n)]
        # Affine c = a·f + b per pixel and channel, ridge λ pulling a towards 1; leave-one-out on the sums.
        sf, sc, sff, sfc = (w * f).sum(0), (w * c).sum(0), (w * f * f).sum(0), (w * f * c).sum(0)

        def fit(k: np.ndarray, sf: np.ndarray, sc: np.ndarray, sff: np.ndarray,
                sfc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            k = np.maximum(k, 1e-9)  # (no value left: a = 1, b = 0)
            mf, mc = sf / k, sc / k
            a = (sfc - k * mf * mc + ridge) / (sff - k * mf * mf + ridge)
            return a, mc - a * mf

        aff_err = []
        for i in range(n):
            wi = w[i]
            a, b = fit(k_all - wi, sf - wi * f[i], sc - wi * c[i], sff - wi * f[i] ** 2, sfc - wi * f[i] * c[i])
            aff_err.append((np.clip(a * f[i] + b, 0, 1) - c[i])[lit & (wi > 0)])
        rmse_mean = float(np.sqrt(np.mean(np.concatenate(mean_err) ** 2)))
        rmse_aff = float(np.sqrt(np.mean(np.concatenate(aff_err) ** 2)))
        rmse_zero = float(np.sqrt(np.mean(r[:, lit][w[:, lit] > 0] ** 2)))  # (r is 0 where left out)
        report = {"patterns": [e.name for e in entries], "held_out_rmse": {
            "no_bias": rmse_zero, "mean": rmse_mean, "affine": rmse_aff},
            "left_out_share": round(float(1.0 - w[:, lit].mean()), 4)}
        if rmse_aff < rmse_mean:
            a, b = fit(k_all, sf, sc, sff, sfc)
            return BiasModel((-b).astype(np.float32), a.astype(np.float32), "affine", report)
        return BiasModel((r_sum / np.maximum(k_all, 1)).astype(np.float32), None, "mean", report)

    # ------------------------------------------------------------------ the optimisation

    def run(self, target: np.ndarray, area: DisplayArea, *, device: Device | None = None,
            schedule: str | Schedule = DEFAULT_SCHEDULE, iterations_z: int | None = None,
            iterations_joint: int | None = None, lr: float | None = None, alpha: float | None = None,
            capture_every: int | None = None, progress: Progress | None = None,
            cancel: Cancel | None = None, open_loop_theta: np.ndarray | BiasModel | None = None,
            use_bias: bool = True, init: str = "inverse", theta_init: str = "capture",
            name: str = "target", start: np.ndarray | None = None, verify: bool | None = None
            ) -> CompensationResult:
        """Stage C for one target; see :func:`compensate`. ``start``: the virtual input z to start from (a warm
        start, e.g. the previous frame's answer) instead of ``init``. ``verify``: overrides the schedule's
        ``verify`` (the transport schedule's closing Mitsuba render)."""
        mi, dr = self._mi, self._dr
        t_start = time.perf_counter()
        say = progress or (lambda msg, frac: None)
        given = {"iterations_z": iterations_z, "iterations_joint": iterations_joint, "lr": lr, "alpha": alpha,
                 "capture_every": capture_every}
        for what in ("iterations_z", "iterations_joint", "capture_every"):
            v = given[what]
            if v is not None and (isinstance(v, bool) or not isinstance(v, int)):
                raise CompensationError(f"{what} must be a whole number, got {v!r}")
        for what in ("lr", "alpha"):
            v = given[what]
            if v is not None and not isinstance(v, (int, float)):
                raise CompensationError(f"{what} must be a number, got {v!r}")
        if capture_every is not None:
            given["captures"] = None  # an explicit interval replaces the schedule's number of captures
        sched = replace(get_schedule(schedule), **{k: v for k, v in given.items()
                                                   if v is not None or k == "captures"}).check()
        if theta_init not in ("capture", "zero"):
            raise CompensationError(f"theta_init must be 'capture' or 'zero', got {theta_init!r}")
        if self.input_blur and not sched.transport:
            raise CompensationError(f"the projector lens's blur is held by the transport schedule only, not by "
                                    f"{sched.name!r}: compensate with --schedule transport")
        area = area.check(self.camera_size)
        placed = area.place(fit_target(target, area, what=f"target {name!r}"), self.camera_size)
        mask = area.mask(self.camera_size)

        # -- what θ is and how it moves
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

        z0 = self.initial_input(placed, bias, init) if start is None else self.start_input(start)
        if sched.transport:
            return self._run_transport(placed, area, z0, sched, mode, bias, device, say, cancel, name, t_start,
                                       sched.verify if verify is None else bool(verify))
        opt = mi.ad.Adam(lr=float(sched.lr))
        opt["z"] = mi.TensorXf(z0)
        losses: list[float] = []
        phases: list[dict[str, Any]] = []
        captures = 0
        seconds_device = 0.0  # time spent waiting for the device (Cycles in the lab), reported apart
        n_coarse = min(sched.iterations_coarse, sched.iterations_z) if sched.coarse < 1.0 else 0
        total = sched.iterations_z + sched.iterations_joint  # at most; z phases may stop early
        base_seed = self.seed * 1_000_003 + 17
        psnr_start = area_psnr(self._predict(self.simulate(z0, spp=sched.reference_spp, seed=base_seed - 1), bias,
                                             None), placed, area)
        it = 0  # iterations so far, over all phases (seeds and progress)

        # With ``crop`` the full-resolution renders cover only the display area, the one place the loss looks:
        # targets, weights, θ and captures are cut to it, and θ is 0 outside it at the end.
        window = (area.x, area.y, area.width, area.height) if sched.crop else None

        def cut(image: np.ndarray) -> np.ndarray:
            if window is None:
                return image
            x, y, w, h = window
            return image[y:y + h, x:x + w]

        def uncut(image: np.ndarray) -> np.ndarray:
            if window is None:
                return image
            x, y, w, h = window
            full = np.zeros((self.camera_size[1], self.camera_size[0], 3), np.float32)
            full[y:y + h, x:x + w] = image
            return full

        full_model = self.model if window is None else self.model_cropped(window)
        bias_c = None if bias is None else BiasModel(cut(bias.theta), None if bias.gain is None else cut(bias.gain),
                                                     bias.kind, bias.report)
        placed_c, mask_c = cut(placed), cut(mask)

        def render_np(z: np.ndarray, spp: int, seed: int) -> np.ndarray:
            """``f̂(z)`` over the rendered window (the whole camera without ``crop``)."""
            return full_model.render_input(np.clip(z, 0.0, 1.0), spp=spp, seed=seed)

        def loss_terms(scale: float) -> tuple[Any, Any, Any, Any, Any, float]:
            """Model, target, weights, θ and gain tensors at a camera scale, and 1 / the weights' sum."""
            if scale >= 1.0:
                h, w = placed_c.shape[:2]
                weights = mask_c.astype(np.float32)
                return (full_model, mi.TensorXf(placed_c), mi.TensorXf(np.repeat(weights[..., None], 3, axis=2)),
                        mi.TensorXf(np.zeros((h, w, 3), np.float32) if bias_c is None else bias_c.theta),
                        None if bias_c is None or bias_c.gain is None else mi.TensorXf(bias_c.gain),
                        1.0 / float(3 * weights.sum()))
            model = self.model_at(scale)
            size = model.camera_size
            weights = self.downsample(mask.astype(np.float32), size)
            t = mi.TensorXf(self.downsample(placed, size))
            w = mi.TensorXf(np.repeat(weights[..., None], 3, axis=2))
            th = mi.TensorXf(np.zeros((size[1], size[0], 3), np.float32) if bias is None
                             else self.downsample(bias.theta, size))
            g = None if bias is None or bias.gain is None else mi.TensorXf(self.downsample(bias.gain, size))
            return model, t, w, th, g, 1.0 / float(3 * weights.sum())

        def step(model: Any, target_t: Any, weight_t: Any, theta_t: Any, gain_t: Any, inv_count: float,
                 spp: int | None) -> tuple[float, Any]:
            """One Adam step on z; returns the loss and the (detached) simulation."""
            if cancel is not None and cancel():
                raise Cancelled(f"compensation of {name!r} cancelled at iteration {it}")
            frame = mi.TensorXf(dr.gather(mi.Float, opt["z"].array, self._frame_index, self._frame_inside),
                                (self.fh, self.fw, 3))
            img = model.render_dr(frame, seed=base_seed + 2 * it, seed_grad=base_seed + 2 * it + 1, spp=spp)
            pred = (img if gain_t is None else gain_t * img) - theta_t
            loss = dr.sum(weight_t * dr.square(target_t - pred), axis=None) * inv_count
            dr.backward(loss)
            value = float(np.asarray(loss).ravel()[0])
            if not math.isfinite(value):
                raise self._diverged(name, it, opt["z"], theta_t, img)
            losses.append(value)
            return value, dr.detach(img)

        mask3 = mask_c[..., None]
        reach = self.white() if bias is None or bias.gain is None else bias.gain * self.white()
        inv_reach = cut(1.0 / np.maximum(reach, 0.05))  # the dark rim of the footprint would amplify noise

        def fixed_point(z: np.ndarray, theta: np.ndarray | None, steps: int, label: str) -> np.ndarray:
            """``steps`` preconditioned fixed-point steps on z (module doc, "Speed"): forward renders only."""
            nonlocal it_fp
            for k in range(steps):
                if cancel is not None and cancel():
                    raise Cancelled(f"compensation of {name!r} cancelled ({label})")
                raw = render_np(z, sched.fixed_point_spp, base_seed + 3 * total + 7 * it_fp)
                it_fp += 1
                r = np.where(mask3, placed_c - self._predict(raw, bias_c, theta), 0.0)
                step = sched.fixed_point_step * (1.0 if k < (steps + 1) // 2 else 0.5)
                z = np.clip(z + step * self.camera_to_input(uncut(r * inv_reach)), 0.0, 1.0).astype(np.float32)
            if not np.all(np.isfinite(z)):
                raise CompensationError(f"the virtual input z of {name!r} holds NaN after the {label} steps")
            return z

        it_fp = 0
        if sched.fixed_point:
            t_phase = time.perf_counter()
            opt["z"] = mi.TensorXf(fixed_point(z0, None, sched.fixed_point, "fixed-point"))
            phases.append({"phase": "fixed-point", "camera": list(self.camera_size), "iterations": sched.fixed_point,
                           "spp": sched.fixed_point_spp, "stopped": "limit",
                           "seconds": round(time.perf_counter() - t_phase, 2)})

        # -- z alone: coarse, then full resolution; each ends early on a plateau of its loss
        for label, scale, limit in (("coarse", sched.coarse, n_coarse),
                                    ("z", 1.0, sched.iterations_z - n_coarse)):
            if limit <= 0:
                continue
            t_phase, mine, stop = time.perf_counter(), [], "limit"
            model, target_t, weight_t, theta_t, gain_t, inv_count = loss_terms(scale)
            opt.set_learning_rate(float(sched.lr))
            for _ in range(limit):
                value, _img = step(model, target_t, weight_t, theta_t, gain_t, inv_count, sched.spp_z)
                opt.step()
                opt["z"] = dr.clip(opt["z"], 0.0, 1.0)
                mine.append(value)
                it += 1
                if it % 10 == 0:
                    say(f"{name}: iteration {it} ({label}), loss {value:.5f}", it / max(total, 1))
                if plateaued(mine, sched.plateau, sched.plateau_tol):
                    stop = "plateau"
                    break
            phases.append({"phase": label, "camera": list(model.camera_size), "iterations": len(mine),
                           "spp": sched.spp_z or self.spp, "stopped": stop,
                           "seconds": round(time.perf_counter() - t_phase, 2)})

        # -- z and θ (closed loop), or z with θ fixed
        t_phase, n_joint, alpha_used = time.perf_counter(), sched.iterations_joint, sched.theta_rate
        model, target_t, weight_t, theta_t, gain_t, inv_count = loss_terms(1.0)
        residual_t = None
        seconds_phase_device = 0.0
        for j in range(n_joint):
            joint = mode == "closed-loop"
            if joint and j % sched.capture_interval == 0:
                # A fresh capture of the real input W(z), and the simulation of that same z (module doc).
                z_now = np.array(opt["z"], dtype=np.float32)
                x = self.warp_w(z_now)
                t_dev = time.perf_counter()
                y = cut(self._check_capture(device.project(self.rig.projector.frame_from_input(x))))
                seconds_phase_device += time.perf_counter() - t_dev
                captures += 1
                f_c = render_np(z_now, sched.reference_spp, base_seed + 2 * total + captures)
                residual = f_c - y
                residual_t = mi.TensorXf(residual.astype(np.float32))
                if captures == 1 and theta_init == "capture":
                    theta_t = mi.TensorXf(np.clip(residual, f_c - 1.0, f_c).astype(np.float32))
                if sched.fixed_point_joint:
                    # Bring z to the θ this capture revealed at once instead of over the next iterations.
                    opt["z"] = mi.TensorXf(fixed_point(np.array(opt["z"], dtype=np.float32),
                                                       np.array(theta_t, dtype=np.float32),
                                                       sched.fixed_point_joint, "joint fixed-point"))
                say(f"{name}: capture {captures} at iteration {it}", it / max(total, 1))
            opt.set_learning_rate(sched.learning_rate(j, n_joint))
            value, f_now = step(model, target_t, weight_t, theta_t, gain_t, inv_count, sched.spp_joint)
            if joint:
                # Eq. 10, then Eq. 14 against the current simulation.
                theta_t = theta_t + 2.0 * alpha_used * (residual_t - theta_t)
                theta_t = dr.clip(theta_t, f_now - 1.0, f_now)
                dr.eval(theta_t)
            opt.step()
            opt["z"] = dr.clip(opt["z"], 0.0, 1.0)
            it += 1
            if it % 10 == 0 or j == n_joint - 1:
                phase = "z and θ" if mode == "closed-loop" else "z (θ fixed)"
                say(f"{name}: iteration {it} ({phase}), loss {value:.5f}", it / max(total, 1))
        seconds_device += seconds_phase_device
        if n_joint:
            phases.append({"phase": "joint" if mode == "closed-loop" else "z, θ fixed",
                           "camera": list(full_model.camera_size), "window": window, "iterations": n_joint,
                           "spp": sched.spp_joint or self.spp, "captures": captures,
                           "seconds": round(time.perf_counter() - t_phase, 2),
                           "seconds_device": round(seconds_phase_device, 2)})

        z = np.array(opt["z"], dtype=np.float32)
        if not np.all(np.isfinite(z)):
            raise CompensationError(f"the virtual input z of {name!r} holds NaN after the optimisation")
        raw = self.simulate(z, seed=base_seed - 2)
        if mode == "closed-loop":
            theta = uncut(np.array(theta_t, dtype=np.float32)) if captures else np.zeros_like(raw)
            # Eq. 14 against this (less noisy) final simulation rather than the last 4-spp one.
            theta = np.clip(theta, raw - 1.0, raw)
            simulated = np.clip(raw - theta, 0.0, 1.0)
        else:
            simulated = self._predict(raw, bias, None)
            theta = raw - simulated
        if not (np.all(np.isfinite(theta)) and np.all(np.isfinite(simulated))):
            raise CompensationError(f"the bias θ of {name!r} diverged (NaN); lower α or check the device's captures")
        x_input = self.warp_w(z)
        seconds = time.perf_counter() - t_start
        report = {"schedule": asdict(sched), "phases": phases,
                  "iterations": {"z": it - n_joint, "joint": n_joint, "total": it, "fixed_point": it_fp},
                  "lr": sched.lr, "alpha": sched.theta_rate,
                  "capture_every": sched.capture_interval if mode == "closed-loop" else None, "init": init,
                  "theta_init": theta_init if mode == "closed-loop" else None,
                  "bounces": self.bounces, "spp": self.spp, "seed": self.seed,
                  "bias": None if bias is None else {"kind": bias.kind, **bias.report},
                  "psnr_simulated_start": psnr_start, "psnr_simulated": area_psnr(simulated, placed, area),
                  "warp": self.warp is not None, "seconds_device": round(seconds_device, 2),
                  "seconds_compute": round(seconds - seconds_device, 2)}
        say(f"{name}: done in {seconds:.1f} s ({seconds - seconds_device:.1f} s without the device)", 1.0)
        return CompensationResult(x_input, self.rig.projector.frame_from_input(x_input), z, theta, simulated, raw,
                                  placed, area, losses, seconds, mode, captures, report)

    # ------------------------------------------------------------------ stage C on the transport operator

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

    def _run_transport(self, placed: np.ndarray, area: DisplayArea, z: np.ndarray, sched: Schedule, mode: str,
                       bias: BiasModel | None, device: Device | None, say: Progress, cancel: Cancel | None,
                       name: str, t_start: float, verify: bool) -> CompensationResult:
        """Stage C as a box-constrained least-squares problem on ``T`` (schedule ``transport``).

        min over 0 ≤ z ≤ 1 of Σ_area ‖g·T z − θ − y_t‖², solved by projected SIRT
        with Nesterov momentum: each step moves every texel by the back-projected
        residual, normalised by the operator's row and column sums (what the
        fixed-point steps of ``fast`` do with renders, here with the exact
        adjoint, so it converges where blur and indirect light mix texels).
        Why SIRT rather than CG: the box constraint (a projected method needs no
        active-set bookkeeping) and the row/column-sum preconditioner that makes
        a step of 1 safe whatever the overlap of footprints. The unknowns are the
        texels whose direct light reaches the area (``TransportRows``); the
        others keep their start and reach the area through interreflection only.
        Closed loop: θ starts at the first capture's residual ``T z − y`` (Eq. 14
        clipped) and follows each later capture's by Eq. 10 on every solver step,
        with α matched to the steps between captures; the solve continues from
        the same z. With
        ``verify`` Mitsuba renders the answer once, to report what the scene
        (not the operator) predicts; without, the report is the operator's (the
        display area only). With :attr:`input_blur` the operator is ``T B`` and z the input before the lens's
        blur (:class:`BlurredRows`)."""
        view = self.transport_view(area)
        rows = view.rows
        gain = np.ones((len(rows), 3), np.float32) if bias is None or bias.gain is None else \
            bias.gain.reshape(-1, 3)[rows]
        target = placed.reshape(-1, 3)[rows]
        theta = np.zeros_like(target) if bias is None else bias.theta.reshape(-1, 3)[rows]
        fixed = view.fixed_sums(z)
        zc = view.compact(z)
        row_sums = np.maximum(gain * view.row_ones, 1e-3)
        col_sums = np.maximum(view.adjoint_compact(gain), 1e-3)
        losses: list[float] = []
        captures, seconds_device, done = 0, 0.0, 0
        total = sched.iterations_z + sched.iterations_joint
        cw, ch = self.camera_size

        def on_camera(values: np.ndarray) -> np.ndarray:
            """Rows' values as a camera image, black outside the area."""
            out = np.zeros((ch * cw, 3), np.float32)
            out[rows] = values
            return out.reshape(ch, cw, 3)

        def predicted(f: np.ndarray, theta: np.ndarray) -> np.ndarray:
            """What the operator says the camera sees for ``f = T z`` (camera size, black outside the area)."""
            return on_camera(np.clip(gain * f - theta, 0.0, 1.0))

        psnr_start = area_psnr(predicted(view.apply_compact(zc, fixed), theta), placed, area)

        alpha = sched.theta_rate

        def solve(zc: np.ndarray, theta: np.ndarray, steps: int, residual: np.ndarray | None = None,
                  f_start: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
            """``steps`` solver steps from ``zc``; with the last capture's ``residual``, θ follows Eq. 10 towards
            it on every step, then Eq. 14 against the current prediction (as ``fast`` does between captures).
            ``f_start``: ``T zc`` when the caller has it already."""
            nonlocal done
            prev, y = zc, zc
            for k in range(steps):
                if cancel is not None and cancel():
                    raise Cancelled(f"compensation of {name!r} cancelled at solver step {done}")
                f = f_start if k == 0 and f_start is not None else view.apply_compact(y, fixed)
                if residual is not None:
                    theta = np.clip(theta + 2.0 * alpha * (residual - theta), f - 1.0, f)
                resid = target + theta - gain * f
                z_new = np.clip(y + view.adjoint_compact(gain * resid / row_sums) / col_sums, 0.0, 1.0)
                y = z_new + (k / (k + 3.0)) * (z_new - prev)
                prev = z_new
                done += 1
                if k % 10 == 0 or k == steps - 1:
                    value = float(np.mean(resid ** 2))
                    if not math.isfinite(value):
                        raise CompensationError(f"the solve of {name!r} diverged (NaN); check the calibration")
                    losses.append(value)
                    say(f"{name}: solver step {done}, loss {value:.6f}", done / max(total, 1))
            return prev, theta

        zc, theta = solve(zc, theta, sched.iterations_z)
        if mode == "closed-loop":
            n_capt = sched.captures or max(1, sched.iterations_joint // sched.capture_interval)
            per = max(1, sched.iterations_joint // max(n_capt, 1))
            for _ in range(n_capt):
                x = self.warp_w(view.expand(zc, z))
                t_dev = time.perf_counter()
                y = self._check_capture(device.project(self.rig.projector.frame_from_input(x))).reshape(-1, 3)[rows]
                seconds_device += time.perf_counter() - t_dev
                captures += 1
                f_now = view.apply_compact(zc, fixed)
                residual = np.clip(f_now - y, f_now - 1.0, f_now).astype(np.float32)
                if captures == 1:
                    # θ starts at the first residual (fast's theta_init='capture'); later captures move it by
                    # Eq. 10, a third of the way each. Replacing θ by every residual diverged on a rig whose
                    # captures sit a little off the model (the live loopback: 14 dB against 23 uncompensated):
                    # an image that is shifted against the model makes θ chase its own edges.
                    theta = residual
                say(f"{name}: capture {captures}", done / max(total, 1))
                zc, theta = solve(zc, theta, per, residual, f_now)
        elif sched.iterations_joint:
            zc, theta = solve(zc, theta, sched.iterations_joint)
        t_verify = time.perf_counter()
        operator_raw = view.apply_compact(zc, fixed)
        z = view.expand(zc, z)
        agreement = None
        if verify:
            light = view.blur(z) if isinstance(view, BlurredRows) else z
            raw = self.simulate(light, seed=self.seed * 1_000_003 + 15)
            agreement = round(min(float(psnr(np.clip(operator_raw, 0.0, 1.0), raw.reshape(-1, 3)[rows])), 99.0), 2)
        else:
            raw = on_camera(operator_raw)
        if mode == "closed-loop":
            th = np.clip(on_camera(theta), raw - 1.0, raw)
            simulated = np.clip(raw - th, 0.0, 1.0)
        else:
            simulated = self._predict(raw, bias, None)
            th = raw - simulated
        seconds_verify = time.perf_counter() - t_verify if verify else 0.0
        x_input = self.warp_w(z)
        seconds = time.perf_counter() - t_start
        report = {"schedule": asdict(sched), "solver": "projected SIRT with Nesterov momentum on the transport "
                  "operator", "alpha": alpha if mode == "closed-loop" else None,
                  "iterations": {"z": sched.iterations_z, "joint": done - sched.iterations_z, "total": done},
                  "operator": view.op.report, "texels_solved": int(len(view.texels)), "input_blur": self.input_blur,
                  "bias": None if bias is None else {"kind": bias.kind, **bias.report},
                  "psnr_simulated_start": psnr_start,
                  "psnr_operator": area_psnr(predicted(operator_raw, theta), placed, area),
                  "psnr_simulated": area_psnr(simulated, placed, area), "warp": self.warp is not None,
                  "simulated_by": "mitsuba" if verify else "operator",
                  "operator_vs_mitsuba_psnr": agreement, "bounces": self.bounces, "seed": self.seed,
                  "seconds_device": round(seconds_device, 2), "seconds_verify": round(seconds_verify, 2),
                  "seconds_compute": round(seconds - seconds_device, 2)}
        say(f"{name}: done in {seconds:.1f} s ({seconds - seconds_device:.1f} s without the device)", 1.0)
        return CompensationResult(x_input, self.rig.projector.frame_from_input(x_input), z, th, simulated, raw,
                                  placed, area, losses, seconds, mode, captures, report)

    @staticmethod
    def _predict(raw: np.ndarray, bias: BiasModel | None, theta: np.ndarray | None) -> np.ndarray:
        if bias is not None:
            return bias.predict(raw)
        return np.clip(raw - (0.0 if theta is None else theta), 0.0, 1.0)

    def _diverged(self, name: str, it: int, z: Any, theta: Any, img: Any) -> CompensationError:
        """Say which quantity went non-finite first."""
        def bad(v: Any) -> bool:
            return not np.all(np.isfinite(np.asarray(v)))

        culprit = ("the virtual input z" if bad(z) else "the bias θ" if bad(theta)
                   else "the simulation f̂(z)" if bad(img) else "the loss")
        return CompensationError(f"stage C diverged on {name!r} at iteration {it}: {culprit} became NaN or "
                                 "infinite; lower the learning rate (--lr) or α, or check the calibration")


def compensate(calibration: Any, target: np.ndarray, *, area: DisplayArea, device: Device | None = None,
               schedule: str | Schedule = DEFAULT_SCHEDULE, iterations_z: int | None = None,
               iterations_joint: int | None = None, lr: float | None = None, alpha: float | None = None,
               bounces: int = 1, spp: int = 4, capture_every: int | None = None, progress: Progress | None = None,
               cancel: Cancel | None = None, seed: int = 0,
               open_loop_theta: np.ndarray | BiasModel | None = None, use_bias: bool = True,
               init: str = "inverse", theta_init: str = "capture",
               compensator: Compensator | None = None, name: str = "target") -> CompensationResult:
    """Find the projector input ``x* = W(z)`` whose projection looks like ``target`` inside ``area``.

    ``target``: H×W×3 linear float in [0, 1], any size (fitted to the area,
    see :func:`.display_area.fit_target`). ``device`` given: closed loop
    (θ from captures every ``capture_every`` joint iterations); else open loop
    (θ from the calibration's validation captures, or ``open_loop_theta``);
    ``use_bias=False``: no θ at all (mode ``'none'``, the paper's ablation).
    ``schedule``: ``'transport'`` (default), ``'fast'``, ``'paper'`` or a :class:`Schedule`;
    ``iterations_z``, ``iterations_joint``, ``lr``, ``alpha`` and
    ``capture_every`` override its values when given.
    ``compensator`` reuses a loaded scene across targets (``bounces``,
    ``spp`` and ``seed`` are then its own). Raises :class:`CompensationError`
    when the optimisation diverges, :class:`Cancelled` when ``cancel()``
    turns true.
    """
    comp = compensator or Compensator(calibration, bounces=bounces, spp=spp, seed=seed)
    return comp.run(target, area, device=device, schedule=schedule, iterations_z=iterations_z,
                    iterations_joint=iterations_joint, lr=lr, alpha=alpha, capture_every=capture_every,
                    progress=progress, cancel=cancel, open_loop_theta=open_loop_theta, use_bias=use_bias, init=init,
                    theta_init=theta_init, name=name)


__all__ = ["ALPHA", "BiasModel", "CAPTURE_EVERY", "Cancelled", "CompensationError", "CompensationResult",
           "Compensator", "DEFAULT_SCHEDULE", "ITERATIONS_JOINT", "ITERATIONS_Z", "LEARNING_RATE", "MODES",
           "SCHEDULES", "Schedule", "area_psnr", "compensate", "get_schedule", "matched_alpha", "plateaued",
           "split_iterations"]
