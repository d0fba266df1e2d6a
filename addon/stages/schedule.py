"""Stage C's schedules: how it spends its iterations, samples and captures, and the paper's constants.

A :class:`Schedule` is named (``SCHEDULES``: ``'transport'``, the default, ``'fast'`` and ``'paper'``) or given;
the values a run passes (``iterations_z``, ``lr``, …) replace the named schedule's. The solvers that follow a
schedule are ``stages/solve_render.py`` (Mitsuba renders) and ``stages/solve_transport.py`` (the precomputed
light-transport operator); ``stages/compensate.py`` says what stage C solves and picks the solver.

Speed (issue 5: under 60 s per target on 2 cores at 640×480 with one bounce,
no worse than the paper's 500 steps). An Adam iteration costs a forward and an
adjoint render (~0.75 s at 4 spp over the whole camera), so the paper's
schedule is ~400 s. The ``'fast'`` :class:`Schedule` gets the same quality
from less (and ``'transport'``, the default, from no render at all: it solves
on the calibration's precomputed light-transport operator, ``stages/solve_transport.py``,
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
Figures: docs/results.md ("Stage C speed").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..errors import ProCamError


#: Defaults of the paper's schedule and of the choices documented here and in stages/compensate.py.
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
#: The closed loop's rules (:attr:`Schedule.loop`).
LOOPS = ("measured", "damped")


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
    #: closed loop with ``transport`` (the schedules that render follow Eq. 10): ``measured`` learns each pixel's
    #: slope and averages against the camera's noise, stopping at its noise floor (stages/closed_loop.py);
    #: ``damped`` follows each capture by Eq. 10 (the paper's θ)
    loop: str = "measured"

    def check(self) -> Schedule:
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
        if self.loop not in LOOPS:
            raise CompensationError(f"the closed loop's rule must be one of {', '.join(LOOPS)}, got {self.loop!r}")
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


#: With a lens blur held in the transport solve (``--effects defocus``) every step deconvolves, which SIRT does
#: slowly: the joint phase of a named schedule takes this many times its steps, over the same captures. Two
#: projectors stacked, blur held, closed loop: 30 → 150 steps over 15 captures +0.63 dB on forest, +0.38 on city
#: (docs/results.md, "What the closed loop leaves between ours and the oracle").
HELD_BLUR_STEPS = 5


def with_held_blur(sched: Schedule, schedule: str | Schedule, iterations_joint: int | None) -> Schedule:
    """The schedule of a solve that holds a lens blur: :data:`HELD_BLUR_STEPS` times the joint steps of the named
    transport schedule ``schedule``, unless the run named its steps (``iterations_joint``) or gave a schedule of
    its own."""
    if not sched.transport or not isinstance(schedule, str) or iterations_joint is not None:
        return sched
    return replace(sched, iterations_joint=sched.iterations_joint * HELD_BLUR_STEPS)


def get_schedule(schedule: str | Schedule) -> Schedule:
    """A schedule by name (``'transport'``, ``'fast'``, ``'paper'``) or as given."""
    if isinstance(schedule, Schedule):
        return schedule.check()
    if schedule not in SCHEDULES:
        raise CompensationError(f"unknown schedule {schedule!r}; choose one of {', '.join(SCHEDULES)}")
    return SCHEDULES[schedule]


def plateaued(losses: list[float], window: int, tol: float) -> bool:
    """True when the mean of the last ``window`` losses is less than ``tol`` (relative) below the mean of the
    ``window`` before (window means, since each loss is a noisy Monte Carlo estimate); never with window 0."""
    if window <= 0 or len(losses) < 2 * window:
        return False
    return float(np.mean(losses[-window:])) > (1.0 - tol) * float(np.mean(losses[-2 * window:-window]))


def split_iterations(total: int | None, schedule: str | Schedule = DEFAULT_SCHEDULE
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
