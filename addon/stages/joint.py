"""Joint stage C over several projectors on one camera: every projector's input solved together on the operators.

The camera sees ``y = Σ_k g_k ⊙ T_k z_k − θ``: projector k its own light-transport
operator ``T_k`` (stages/transport.py, made from its own one-projector calibration
on the shared camera), its own virtual input ``z_k`` in [0, 1] of its own input size,
its own gain ``g_k`` from its open-loop bias model (1 without), and one camera-space
bias ``θ``. :class:`JointRows` stacks the operators so that the projected SIRT of
stages/solve_transport.py runs unchanged on the concatenated unknowns: row sums
``Σ_k g_k T_k 1``, column sums per projector, each projector's box [0, 1].

**The blend prior, derived from the operators.** Where several projectors light a
camera pixel the data alone leave the split between them free, and a least-squares
answer is free to use it: at one projector's frame edge (a hard edge of light) the
other fills in a complementary hard edge, and a misregistration of a fraction of a
pixel then shows the two edges apart: a seam. The prior asks each projector to carry a
share ``β_k`` of the light that falls smoothly to 0 at its frame edge:
``b_k = c_k · d_k`` with ``d_k`` the distance (camera pixels) to the edge of the
camera pixels projector k's direct light reaches (read off ``T_k``, so it follows the
real footprint on the surface, occlusions and the surface's edge included) and
``c_k`` its certainty from its warp's residual (:func:`calibration_certainty`),
normalised ``β_k = b_k / Σ_l b_l``: 1 where projector k lights alone, a linear
cross-fade across a strip-shaped overlap, and less of the overlap for the projector
registered less well. Its form is a second set of rows of the least-squares system,
``λ (g_k T_k z_k − β_k Σ_l g_l T_l z_l) = 0`` per projector k and camera pixel, rather
than a penalty on each ``z_k`` such as ``μ Σ_k ‖(1 − b_k) z_k‖²``: a penalty on the
inputs pulls down the total light too (it dims the overlap's sum and, where a
projector lights alone near its edge, fades the image to black), while these rows
vanish for any total once the shares are right, so the prior steers only the split
the data leave free; and they are linear in the inputs, so SIRT takes them as more
rows (their absolute row and column sums added to the preconditioner) at no extra
operator application.

**The reach.** Light adds, so the overlap reaches up to ``Σ_k g_k T_k 1`` while
one projector's area beside it reaches its own white only: a target brighter
than one projector's white is clipped outside the overlap and shown inside it
from the first pixel the second projector lights, a step of the error along the
overlap's edge (on the lab, side by side, six photographs: the range ceiling
itself has a seam step of 0.016, and it was most of the open-loop solve's). With
the blend the data rows ask at most for the blend's reach (:func:`blend_reach`):
each projector's white counted as its share grows, ``min(1, n β_k)`` (n the
projectors sharing the pixel), from 0 at its footprint's edge to all of it where
the shares are even (the overlap's middle, stacked projectors), so the light the
overlap adds fades in as the blend does. ``cap_reach=False`` asks for every bit
of the sum. The start is the prior's too: each projector starts at its
share of the target divided by its white (carried to its input by ray casting, as
one projector's start). ``blend='none'`` solves the plain joint least squares from
the light's own split (each projector's share of the white).

**θ.** Closed loop: as for one projector, from captures of every projector's frame
shown at once (the device's ``project_all``). Open loop: ``θ = Σ_k θ_k`` of the
projectors' open-loop bias models, because light adds: each projector's black
level (what it sends while showing black) and its model error (a response or
colour that differs from the model's) reach the camera on top of the others'. A
part shared by every ``θ_k`` is counted K times by that sum: the room's light and,
when each projector's captures were taken with the others showing black, their
black levels; the camera image with every projector black (``black``) takes
K − 1 of them out.

The baseline users know is :func:`ramp_baseline` (each projector compensated
alone on the target times a linear edge-blend ramp across the overlap), and
:func:`combined_reach` is what all projectors together can show (the range
ceiling of the combined rig, stages/range.py).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any
from collections.abc import Sequence

import cv2
import numpy as np

from ..capture.devices import Device, OneProjector
from ..progress import Cancel, Progress
from .bias import BiasModel
from .compensate import CompensationResult, Compensator
from .display_area import DisplayArea, fit_target
from .metrics import area_psnr
from .schedule import CompensationError, Schedule
from .solve_jit import JitSteps
from .solve_transport import TransportSolve
from .transport import BlurredRows, TransportOperator, TransportRows, adjoint_together, apply_together

View = TransportRows | BlurredRows
#: ``blend`` values of :meth:`JointCompensator.run`.
BLENDS = ("derived", "none")
#: Where the solver's steps run (:meth:`JointCompensator.engine_for`): ``drjit`` all on the operators' Dr.Jit
#: backend (stages/solve_jit.py; ``auto``, the default, unless a view holds a lens blur), ``numpy`` around their
#: gathers (the same answers to float32 rounding; at show scale 4.3× slower on a GPU, 1.2× on 2 cores).
ENGINES = ("auto", "numpy", "drjit")
#: λ of the blend rows (module doc). On the lab (curve, two projectors side by side, 30 % overlap, a bright target
#: partly out of reach) 0.1–0.3 gave the best overlap with one projector moved by a camera pixel (26.2–26.3 dB); 1
#: gave 25.5, 3 gave 23.8: a stronger prior costs the data fit.
BLEND_WEIGHT = 0.25
#: A camera pixel is in a projector's footprint where its direct white is above this share of its brightest.
FOOTPRINT_LEVEL = 0.1


# -- the stacked operator ---------------------------------------------------------------------------------------

class JointRows:
    """``Σ_k g_k T_k z_k`` on the same camera rows, over the concatenated compact vectors of per-projector views
    (:class:`~.transport.TransportRows` or :class:`~.transport.BlurredRows`): the interface of one view, so the
    transport solve's SIRT step runs on it unchanged (``apply_compact``, ``adjoint_compact``, ``row_ones``), and
    per projector where a solver needs the parts (``apply_parts``, ``adjoint_parts``). Inputs of several
    projectors are lists, one input-size image each; ``gains`` are (R, 3) at the rows (None: 1)."""

    def __init__(self, views: Sequence[View], gains: Sequence[np.ndarray | None] | None = None) -> None:
        if not views:
            raise CompensationError("a joint solve needs at least one projector's transport operator")
        first = views[0]
        for k, v in enumerate(views):
            if tuple(v.op.camera_size) != tuple(first.op.camera_size):
                raise CompensationError(_camera_mismatch(k, v.op.camera_size, first.op.camera_size))
            if not np.array_equal(v.rows, first.rows):
                raise CompensationError(f"projector {k + 1}'s operator is restricted to other camera pixels than "
                                        "projector 1's; give every projector the same display area")
        self.views = list(views)
        self.rows = first.rows
        n = len(self.rows)
        gains = list(gains) if gains is not None else [None] * len(views)
        if len(gains) != len(views):
            raise CompensationError(f"{len(gains)} gains for {len(views)} projectors")
        self.gains = [np.ones((n, 3), np.float32) if g is None else np.asarray(g, np.float32).reshape(n, 3)
                      for g in gains]
        self._unit = [g is None for g in gains]  # a gain of 1 is not multiplied in (each solver step, per projector)
        self.bounds = np.cumsum([0] + [len(v.texels) for v in self.views])
        self._row_ones: np.ndarray | None = None

    @property
    def count(self) -> int:
        return len(self.views)

    @property
    def texels(self) -> np.ndarray:
        """Positions in the concatenated compact vector (its length is what a solver sizes by)."""
        return np.arange(int(self.bounds[-1]))

    def split(self, zc: np.ndarray) -> list[np.ndarray]:
        """The concatenated compact vector cut into each projector's (A_k, 3)."""
        return [zc[a:b] for a, b in zip(self.bounds[:-1], self.bounds[1:])]

    def compact(self, zs: Sequence[np.ndarray]) -> np.ndarray:
        return np.concatenate([v.compact(z) for v, z in zip(self.views, zs)], axis=0)

    def expand(self, zc: np.ndarray, zs: Sequence[np.ndarray]) -> list[np.ndarray]:
        return [v.expand(part, z) for v, part, z in zip(self.views, self.split(zc), zs)]

    def fixed_sums(self, zs: Sequence[np.ndarray]) -> list[Any]:
        return [v.fixed_sums(z) for v, z in zip(self.views, zs)]

    def apply_parts(self, zc: np.ndarray, fixed: Sequence[Any] | None = None, *, gained: bool = True
                    ) -> list[np.ndarray]:
        """Each projector's (R, 3) ``g_k T_k z_k`` (``T_k z_k`` without ``gained``)."""
        fixed = list(fixed) if fixed is not None else [None] * self.count
        parts = apply_together(self.views, self.split(zc), fixed)
        return [self._gained(k, p) for k, p in enumerate(parts)] if gained else parts

    def apply_compact(self, zc: np.ndarray, fixed: Sequence[Any] | None = None) -> np.ndarray:
        """(R, 3) ``Σ_k g_k T_k z_k``."""
        return np.sum(self.apply_parts(zc, fixed), axis=0)

    def adjoint_parts(self, rs: Sequence[np.ndarray]) -> np.ndarray:
        """The concatenated ``T_k^T (g_k r_k)``: each projector its own (R, 3) camera vector ``r_k``."""
        return adjoint_together(self.views, [self._gained(k, r) for k, r in enumerate(rs)])

    def _gained(self, k: int, values: np.ndarray) -> np.ndarray:
        """Projector ``k``'s gain times ``values`` (R, 3)."""
        return values if self._unit[k] else self.gains[k] * values

    def adjoint_compact(self, r: np.ndarray) -> np.ndarray:
        """The adjoint of :meth:`apply_compact`: ``T_k^T (g_k r)`` for every projector, concatenated."""
        return self.adjoint_parts([r] * self.count)

    @property
    def row_ones(self) -> np.ndarray:
        """(R, 3) ``Σ_k g_k T_k 1`` (SIRT's row sums)."""
        if self._row_ones is None:
            self._row_ones = np.sum(self.light_parts(), axis=0)
        return self._row_ones

    def light_parts(self) -> list[np.ndarray]:
        """Each projector's (R, 3) ``g_k T_k 1``: its white as the camera sees it."""
        return [self._gained(k, v.row_ones) for k, v in enumerate(self.views)]


def _camera_mismatch(k: int, size: Any, first: Any) -> str:
    return (f"projector {k + 1}'s calibration is for a {size[0]}×{size[1]} camera but projector 1's for a "
            f"{first[0]}×{first[1]} one: a joint compensation needs every projector calibrated with the same "
            "camera at the same resolution (calibrate them from one multi-projector capture set)")


# -- footprints, overlap, the derived blend, the combined range ---------------------------------------------------

def white_of(op: TransportOperator) -> np.ndarray:
    """``T 1``: the camera image (H×W×3) of a white input, direct and indirect light."""
    iw, ih = op.input_size
    return op.apply(np.ones((ih, iw, 3), np.float32))


def footprints(operators: Sequence[TransportOperator], level: float = FOOTPRINT_LEVEL) -> np.ndarray:
    """(K, H, W) bool: the camera pixels each projector's direct light reaches (its direct white above ``level``
    of its 99th percentile; interreflected light lights everything a little and is no footprint)."""
    out = []
    for op in operators:
        iw, ih = op.input_size
        white = op.direct(np.ones((ih, iw, 3), np.float32)).mean(axis=2)
        lit = white[white > 0]
        top = float(np.percentile(lit, 99)) if lit.size else 0.0
        out.append(white > level * top if top > 0 else np.zeros_like(white, bool))
    return np.asarray(out)


def overlap_mask(operators: Sequence[TransportOperator], level: float = FOOTPRINT_LEVEL) -> np.ndarray:
    """(H, W) bool: camera pixels lit by the direct light of two projectors or more."""
    return footprints(operators, level).sum(axis=0) >= 2


def calibration_certainty(calibration: Any) -> float:
    """How much a projector's registration is trusted, ``1 / (1 + r)`` with ``r`` its stage-B residual (median
    corner distance after the warp, camera pixels; recorded in the calibration's report): 1 when unknown (no
    warp fitted, or a calibration made in memory). A projector off by r pixels gets its blend ramp scaled by that,
    so it hands over to a better-registered neighbour sooner."""
    report = getattr(calibration, "report", None) or {}
    try:
        r = float(((report.get("warp_report") or {}).get("corners_after_px") or {}).get("median"))
    except (TypeError, ValueError):
        return 1.0
    return 1.0 / (1.0 + r) if math.isfinite(r) and r >= 0 else 1.0


def blend_shares(operators: Sequence[TransportOperator], certainties: Sequence[float] | None = None) -> np.ndarray:
    """(K, H, W) the derived blend (module doc): each projector's share ``β_k`` of the light at each camera pixel,
    ``c_k d_k / Σ_l c_l d_l`` with ``d_k`` the distance to the edge of its footprint; 0 where no projector lights."""
    return distance_shares(footprints(operators), certainties)


def distance_shares(masks: np.ndarray, certainties: Sequence[float] | None = None) -> np.ndarray:
    """:func:`blend_shares` of footprints given as (K, H, W) masks (from the operators there; from the model's
    coverage and the captures where a calibration has no operator: the classic geometric ramps)."""
    masks = np.asarray(masks, bool)
    c = [1.0] * len(masks) if certainties is None else [float(v) for v in certainties]
    if len(c) != len(masks) or not all(math.isfinite(v) and v > 0 for v in c):
        raise CompensationError(f"certainties must be {len(masks)} positive numbers, got {certainties!r}")
    # distanceTransform: each lit pixel's distance to the nearest unlit one (the image's border is not an edge:
    # the camera's frame is no projector's)
    b = np.asarray([ck * cv2.distanceTransform(m.astype(np.uint8), cv2.DIST_L2, 5) for ck, m in zip(c, masks)])
    total = b.sum(axis=0)
    return np.where(total > 0, b / np.maximum(total, 1e-12), 0.0).astype(np.float32)


def blend_reach(lights: Sequence[np.ndarray], shares: np.ndarray) -> np.ndarray:
    """(R, 3) the most light the blend lets the projectors show together at each row (module doc, "The reach"):
    ``Σ_k L_k min(1, n β_k)`` with ``L_k`` projector k's white at the rows (``g_k T_k 1``), ``β_k`` its share (K, R)
    and ``n`` the projectors whose share is above 0 there. Each projector's light enters as its share grows from 0 at
    its footprint's edge, so the reach has no step there, and it is all of ``Σ_k L_k`` where the shares are even.
    Infinite (no cap) where fewer than two projectors share the pixel: there the reach is one projector's white,
    which a target above it cannot pass anyway, and asking for more lets its neighbours' texels lend light (capping
    it cost 0.12 dB outside the overlap on the lab)."""
    b = np.asarray(shares, np.float32)
    n = (b > 0).sum(axis=0)
    reach = sum(np.asarray(light, np.float32) * np.minimum(1.0, n * bk)[:, None] for light, bk in zip(lights, b))
    return np.where((n > 1)[:, None], reach, np.inf).astype(np.float32)


def combined_reach(operators: Sequence[TransportOperator], *, gains: Sequence[np.ndarray | None] | None = None,
                   theta: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """What all projectors together can make the camera see: (black, white) camera images, every projector black
    and every projector white, ``max(−θ, 0)`` and ``Σ_k g_k T_k 1 − θ`` (not clipped at 1, so a target's range
    ceiling, :func:`.range.range_ceiling`, counts what stacked projectors add beyond one's white)."""
    if not operators:
        raise CompensationError("the combined reach needs at least one projector's transport operator")
    first = operators[0].camera_size
    for k, op in enumerate(operators):
        if tuple(op.camera_size) != tuple(first):
            raise CompensationError(_camera_mismatch(k, op.camera_size, first))
    gains = list(gains) if gains is not None else [None] * len(operators)
    white = np.sum([white_of(op) * (1.0 if g is None else np.asarray(g, np.float32))
                    for op, g in zip(operators, gains)], axis=0)
    th = 0.0 if theta is None else np.asarray(theta, np.float32)
    black = np.maximum(-th + np.zeros_like(white), 0.0).astype(np.float32)
    return black, np.maximum(white - th, black).astype(np.float32)


def masked_psnr(image: np.ndarray, target: np.ndarray, mask: np.ndarray) -> float | None:
    """PSNR (dB, peak 1) over the pixels of ``mask``; None when it holds none."""
    m = np.asarray(mask, bool)
    if not m.any():
        return None
    mse = float(np.mean((np.asarray(image, np.float64)[m] - np.asarray(target, np.float64)[m]) ** 2))
    return 100.0 if mse <= 1e-10 else round(10.0 * math.log10(1.0 / mse), 3)


# -- the result ---------------------------------------------------------------------------------------------------

@dataclass
class JointResult:
    """The answer of joint stage C for one target: per projector (lists in projector order) and for the rig."""

    x_inputs: list[np.ndarray]  # each projector's x* = W_k(z_k), its input size
    x_frames: list[np.ndarray]  # each x* in its native frame
    z: list[np.ndarray]  # each projector's virtual input
    theta: np.ndarray  # camera-space θ at the end (Eq. 14 holds against ``simulated_raw``)
    simulated: np.ndarray  # what the camera should see with every projector on (camera size, black off the area)
    simulated_raw: np.ndarray  # Σ_k T_k z_k
    target: np.ndarray  # the target placed in its area
    area: DisplayArea
    losses: list[float]
    seconds: float
    mode: str
    captures: int = 0
    report: dict[str, Any] = field(default_factory=dict)


def _on_camera(rows: np.ndarray, values: np.ndarray, camera_size: tuple[int, int]) -> np.ndarray:
    cw, ch = camera_size
    out = np.zeros((ch * cw, 3), np.float32)
    out[rows] = values
    return out.reshape(ch, cw, 3)


def _finish(comps: Sequence[Compensator], joint: JointRows, zs: Sequence[np.ndarray], theta_rows: np.ndarray,
            placed: np.ndarray, area: DisplayArea, overlap: np.ndarray, losses: list[float], mode: str,
            captures: int, report: dict[str, Any], t_start: float, seconds_device: float,
            solved: tuple[np.ndarray, Sequence[Any]] | None = None) -> JointResult:
    """The :class:`JointResult` of the inputs ``zs`` as the operators see them, with the figures every joint answer
    reports (the area's PSNR overall, inside the overlap and outside it, each projector's share of the light).
    ``solved``: the compact vector and held block sums ``zs`` were expanded from (the solve's own), so that they
    are not gathered again from the whole inputs (a block sum over every texel of every projector's input)."""
    camera = comps[0].camera_size
    zc, fixed = solved if solved is not None else (joint.compact(zs), joint.fixed_sums(zs))
    raw_parts = joint.apply_parts(zc, fixed, gained=False)
    lit_parts = [joint._gained(k, p) for k, p in enumerate(raw_parts)]
    lit = np.sum(lit_parts, axis=0)
    raw = _on_camera(joint.rows, np.sum(raw_parts, axis=0), camera)
    simulated = _on_camera(joint.rows, np.clip(lit - theta_rows, 0.0, 1.0), camera)
    theta = raw - simulated  # as one projector's answer: simulated = clip(raw − θ) holds
    in_area = area.mask(camera)
    total = float(np.sum(lit))
    report.update({
        "projectors": len(comps), "mode": mode,
        "share_of_light": [round(float(np.sum(p)) / total, 4) if total > 0 else None for p in lit_parts],
        "psnr_simulated": area_psnr(simulated, placed, area),
        "psnr_overlap": masked_psnr(simulated, placed, in_area & overlap),
        "psnr_outside_overlap": masked_psnr(simulated, placed, in_area & ~overlap),
        "overlap_share_of_area": round(float((in_area & overlap).sum()) / max(int(in_area.sum()), 1), 4),
        "simulated_by": "operator", "seconds_device": round(seconds_device, 2)})
    x_inputs = [comp.warp_w(z) for comp, z in zip(comps, zs)]
    frames = [comp.rig.projector.frame_from_input(x) for comp, x in zip(comps, x_inputs)]
    seconds = time.perf_counter() - t_start
    report["seconds_compute"] = round(seconds - seconds_device, 2)
    return JointResult(x_inputs, frames, [np.asarray(z, np.float32) for z in zs], theta, simulated, raw, placed,
                       area, losses, seconds, mode, captures, report)


# -- the solve ----------------------------------------------------------------------------------------------------

class JointSolve(TransportSolve):
    """The transport solve (its SIRT steps, θ's closed loop) on a :class:`JointRows`, with the blend rows of the
    module doc in its step (``shares`` (K, R) at the rows, None for none)."""

    def __init__(self, owner: JointCompensator, joint: JointRows, placed: np.ndarray, area: DisplayArea,
                 zs: Sequence[np.ndarray], sched: Schedule, mode: str, theta0: np.ndarray,
                 shares: np.ndarray | None, device: Device | None, say: Progress, cancel: Cancel | None,
                 name: str) -> None:
        self.owner, self.comps = owner, owner.compensators
        self.comp = self.comps[0]  # the camera's size, for on_camera
        self.placed, self.area, self.zs0, self.sched, self.mode = placed, area, list(zs), sched, mode
        self.bias, self.device, self.say, self.cancel, self.name = None, device, say, cancel, name
        self.view = self.joint = joint
        self.rows = joint.rows
        self.gain = np.ones((len(self.rows), 3), np.float32)  # the gains are inside the stacked operator
        self.target = placed.reshape(-1, 3)[self.rows]
        self.theta0 = theta0
        self.fixed = joint.fixed_sums(zs)
        self.zc0 = joint.compact(zs)
        #: the unknowns held at each projector's surround (TransportSolve.held)
        self.held = ~np.concatenate([np.take(comp.area_texels(area).reshape(-1), v.texels)
                                     for comp, v in zip(self.comps, joint.views)])
        self.row_sums = np.maximum(joint.row_ones, 1e-3)
        self.weight = owner.blend_weight if shares is not None else 0.0
        lights = joint.light_parts()
        col_weights = [np.ones_like(self.target)] * joint.count
        if self.weight > 0 and shares is not None:
            lam = self.weight
            self.shares = [s[:, None].astype(np.float32) for s in shares]
            everything = np.sum(lights, axis=0)
            # the blend rows' absolute row sums, Σ_j |δ_kj − β_k| g_j T_j 1, and what each projector's column adds
            rows = [lam * ((1.0 - b) * light + b * (everything - light)) for b, light in zip(self.shares, lights)]
            # λ over each blend row's sum, 0 where the row is empty (a pixel one projector lights alone)
            self.blend_scale = [np.where(r > 1e-6, lam / np.maximum(r, 1e-6), 0.0).astype(np.float32) for r in rows]
            col_weights = [1.0 + lam * sum(np.abs(float(j == k) - b) for k, b in enumerate(self.shares))
                           for j in range(joint.count)]
        col_weights = [np.broadcast_to(w, self.target.shape) for w in col_weights]
        # the most light the data rows ask for, the blend's reach (module doc, "The reach"): None without a blend
        self.reach = blend_reach(lights, shares) if owner.cap_reach and self.weight > 0 and shares is not None \
            and joint.count > 1 else None
        self._parts: list[np.ndarray] = []
        self._total = np.zeros((0, 3), np.float32)  # Σ of the parts, from the last forward
        self.losses: list[float] = []
        self.captures, self.seconds_device, self.done = 0, 0.0, 0
        self.seconds_steps = 0.0
        self.total = sched.iterations_z + sched.iterations_joint
        self.alpha = sched.theta_rate
        #: the steps on the device (stages/solve_jit.py), None: in numpy; θ's clip is to the gained light in both
        self.device_theta = True
        self.jit = JitSteps(self, joint.views, [None if unit else g for g, unit in zip(joint.gains, joint._unit)],
                            self.fixed, col_weights) if owner.engine_for(joint) == "drjit" else None
        if self.jit is None:
            self.col_sums = np.maximum(joint.adjoint_parts(col_weights), 1e-3)
            light = np.sum(joint.apply_parts(self.zc0, self.fixed), axis=0)
        else:
            light = self.jit.back(self.jit.forward(self.jit.start)[1])
        self.psnr_start = area_psnr(self.on_camera(np.clip(light - theta0, 0.0, 1.0)), placed, area)

    def forward(self, zc: np.ndarray) -> np.ndarray:
        self._parts = parts = self.joint.apply_parts(zc, self.fixed)
        self._total = sum(parts[1:], parts[0])
        return self._total

    def update(self, y: np.ndarray, resid: np.ndarray) -> np.ndarray:
        """The SIRT step on the data rows and, with a blend, on the blend rows: each projector back-projects the
        data residual plus ``λ (q_j − Σ_k β_k q_k)``, ``q_k`` blend row k's residual over its row sum; one adjoint
        per projector either way."""
        if not self.weight:
            return y + self.joint.adjoint_parts([resid / self.row_sums] * self.joint.count) / self.col_sums
        lam, parts, total = self.weight, self._parts, self._total
        # target + θ above the blend's reach asks for the reach: min(t + θ, r) − f
        u = (resid if self.reach is None else np.minimum(resid, self.reach - total)) / self.row_sums
        # In place, each a whole camera-row image per projector and solver step: the same values as written out.
        q = []
        for p, b, scale in zip(parts, self.shares, self.blend_scale):
            qk = b * total
            qk -= p
            qk *= scale
            q.append(qk)
        mixed = self.shares[0] * q[0]
        for b, qk in zip(self.shares[1:], q[1:]):
            mixed += b * qk
        for qj in q:  # u + λ (q_j − mixed)
            qj -= mixed
            qj *= lam
            qj += u
        return y + self.joint.adjoint_parts(q) / self.col_sums

    def capture(self, zc: np.ndarray) -> np.ndarray:
        """Every projector's frame shown at once (the device's ``project_all``), the camera's image on the rows."""
        assert self.device is not None
        frames = [comp.rig.projector.frame_from_input(comp.warp_w(z))
                  for comp, z in zip(self.comps, self.joint.expand(zc, self.zs0))]
        return self.comp._check_capture(self.device.project_all(frames)).reshape(-1, 3)[self.rows]

    def answer(self, zc: np.ndarray, theta: np.ndarray, verify: bool, t_start: float) -> JointResult:
        sched = self.sched
        report = {"schedule": {"name": sched.name, "iterations_z": sched.iterations_z,
                               "iterations_joint": sched.iterations_joint, "captures": sched.captures},
                  "solver": "projected SIRT with Nesterov momentum on the stacked transport operators",
                  "blend": self.owner.last_blend, "blend_weight": self.weight or None,
                  "certainties": list(self.owner.certainties), "alpha": self.alpha if self.mode == "closed-loop"
                  else None, "iterations": {"z": sched.iterations_z, "joint": self.done - sched.iterations_z,
                                            "total": self.done},
                  "texels_solved": [int(len(v.texels)) for v in self.joint.views],
                  "psnr_simulated_start": self.psnr_start, "bias": self.owner.last_bias,
                  "steps_on": "numpy" if self.jit is None else "drjit", "seconds_steps": round(self.seconds_steps, 3),
                  **({"loop": self.loop} if self.loop is not None else {})}
        return _finish(self.comps, self.joint, self.joint.expand(zc, self.zs0), theta, self.placed, self.area,
                       self.owner.overlap(), self.losses, self.mode, self.captures, report, t_start,
                       self.seconds_device, solved=(zc, self.fixed))


class JointCompensator:
    """Joint stage C for several projectors on one camera (module doc): one :class:`~.compensate.Compensator` per
    projector, each made from that projector's calibration (its ``transport`` set or rendered on first use).
    ``certainties``: per projector, how much its registration is trusted (default
    :func:`calibration_certainty` of each calibration)."""

    def __init__(self, compensators: Sequence[Compensator], *, certainties: Sequence[float] | None = None,
                 blend_weight: float = BLEND_WEIGHT, cap_reach: bool = True, engine: str = "auto") -> None:
        comps = list(compensators)
        if not comps:
            raise CompensationError("a joint compensation needs at least one projector's compensator")
        first = tuple(comps[0].camera_size)
        for k, comp in enumerate(comps):
            if tuple(comp.camera_size) != first:
                raise CompensationError(_camera_mismatch(k, comp.camera_size, first))
        if not (math.isfinite(blend_weight) and blend_weight > 0):
            raise CompensationError(f"the blend weight must be a positive number, got {blend_weight!r}")
        self.compensators = comps
        self.camera_size = first
        self.blend_weight = float(blend_weight)
        self.cap_reach = bool(cap_reach)
        if engine not in ENGINES:
            raise CompensationError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
        self.engine = engine
        self.certainties = [calibration_certainty(c.calibration) for c in comps] if certainties is None else \
            [float(v) for v in certainties]
        if len(self.certainties) != len(comps) or not all(math.isfinite(v) and v > 0 for v in self.certainties):
            raise CompensationError(f"certainties must be {len(comps)} positive numbers, got {certainties!r}")
        self._overlap: np.ndarray | None = None
        self._white: dict[int, tuple[TransportOperator, np.ndarray]] = {}
        self._shares: np.ndarray | None = None
        self.last_blend: str | None = None
        self.last_bias: Any = None

    def engine_for(self, joint: JointRows) -> str:
        """Where the solver's steps run on these views (:data:`ENGINES`): numpy where a view holds a lens blur
        (its blur is OpenCV's), else as :attr:`engine` says, ``auto`` being Dr.Jit."""
        if not all(isinstance(v, TransportRows) for v in joint.views):
            return "numpy"
        return "drjit" if self.engine == "auto" else self.engine

    @property
    def operators(self) -> list[TransportOperator]:
        return [c.transport for c in self.compensators]

    def white(self, comp: Compensator) -> np.ndarray:
        """A projector's ``T 1`` (:func:`white_of`; computed once per operator)."""
        op = comp.transport
        if self._white.get(id(comp), (None,))[0] is not op:
            self._white[id(comp)] = (op, white_of(op))
        return self._white[id(comp)][1]

    def overlap(self) -> np.ndarray:
        """(H, W) camera pixels two projectors' direct light reach or more (computed once)."""
        if self._overlap is None:
            self._overlap = overlap_mask(self.operators)
        return self._overlap

    def shares(self) -> np.ndarray:
        """(K, H, W) the derived blend, :func:`blend_shares` (computed once)."""
        if self._shares is None:
            self._shares = blend_shares(self.operators, self.certainties)
        return self._shares

    def combined_reach(self, biases: Sequence[BiasModel] | None = None, black: np.ndarray | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
        """:func:`combined_reach` of these projectors, through their open-loop bias models when given."""
        gains, theta = self._open_loop(biases, black) if biases is not None else (None, None)
        return combined_reach(self.operators, gains=gains, theta=theta)

    def _open_loop(self, biases: Sequence[BiasModel] | None, black: np.ndarray | None
                   ) -> tuple[list[np.ndarray | None], np.ndarray]:
        """Each projector's gain and the rig's θ (module doc: the sum, less K − 1 shared black images)."""
        comps = self.compensators
        if biases is None:
            biases = [comp.estimate_bias() for comp in comps]
        biases = list(biases)
        cw, ch = self.camera_size
        if len(biases) != len(comps) or not all(isinstance(b, BiasModel) for b in biases):
            raise CompensationError(f"biases must be {len(comps)} BiasModel, one per projector")
        for k, b in enumerate(biases):
            if b.theta.shape != (ch, cw, 3) or (b.gain is not None and b.gain.shape != (ch, cw, 3)):
                raise CompensationError(f"projector {k + 1}'s open-loop θ is not {cw}×{ch}×3, the camera's size")
        theta = np.sum([np.asarray(b.theta, np.float32) for b in biases], axis=0)
        if black is not None:
            shared = np.asarray(black, np.float32)
            if shared.shape != (ch, cw, 3) or not np.all(np.isfinite(shared)):
                raise CompensationError(f"the black capture must be a finite {cw}×{ch}×3 image, got {shared.shape}")
            theta = theta + (len(biases) - 1) * shared
        self.last_bias = [{"kind": b.kind, **b.report} for b in biases]
        return [b.gain for b in biases], theta

    def _check_device(self, device: Device) -> None:
        projectors = getattr(device, "projectors", None)
        if not callable(getattr(device, "project_all", None)) or projectors is None:
            raise CompensationError("this device shows one projector at a time; the joint closed loop needs one "
                                    "that shows every projector's frame at once (project_all): compensate in the "
                                    "open loop, or capture with a multi-projector device")
        if len(projectors) != len(self.compensators):
            raise CompensationError(f"the device drives {len(projectors)} projector(s) but the joint compensation "
                                    f"has {len(self.compensators)}: the closed loop shows every projector's frame at "
                                    "once; give it the rig that was calibrated, or compensate in the open loop")
        for k, (proj, comp) in enumerate(zip(projectors, self.compensators)):
            mine = comp.rig.projector
            if (proj.intrinsics.size != mine.intrinsics.size or proj.input_size != mine.input_size
                    or proj.input_offset != mine.input_offset):
                raise CompensationError(f"the device's projector {k + 1} ({proj.intrinsics.width}×"
                                        f"{proj.intrinsics.height}, input {proj.input_size[0]}×{proj.input_size[1]}) "
                                        f"is not the calibrated one ({mine.intrinsics.width}×"
                                        f"{mine.intrinsics.height}, input {mine.input_size[0]}×"
                                        f"{mine.input_size[1]}); calibrate with captures from this device")
        cam = getattr(device, "camera_size", None)
        if cam is not None and tuple(cam) != tuple(self.camera_size):
            raise CompensationError(f"the device's camera delivers {cam[0]}×{cam[1]} frames but the calibration's "
                                    f"camera is {self.camera_size[0]}×{self.camera_size[1]}")

    def _place(self, target: np.ndarray, area: DisplayArea, name: str) -> tuple[DisplayArea, np.ndarray]:
        img = np.asarray(target, np.float32)
        if not np.all(np.isfinite(img)):
            raise CompensationError(f"target {name!r} holds NaN or infinite values; give a finite image")
        area = area.check(self.camera_size)
        return area, area.place(fit_target(img, area, what=f"target {name!r}"), self.camera_size)

    def _mode(self, device: Device | None, use_bias: bool, biases: Sequence[BiasModel] | None,
              black: np.ndarray | None) -> tuple[str, list[np.ndarray | None], np.ndarray]:
        cw, ch = self.camera_size
        none: list[np.ndarray | None] = [None] * len(self.compensators)
        self.last_bias = None
        if device is not None and use_bias:
            self._check_device(device)
            return "closed-loop", none, np.zeros((ch, cw, 3), np.float32)
        if use_bias:
            gains, theta = self._open_loop(biases, black)
            return "open-loop", gains, theta
        return "none", none, np.zeros((ch, cw, 3), np.float32)

    def _starts(self, placed: np.ndarray, theta: np.ndarray, gains: Sequence[np.ndarray | None],
                shares: np.ndarray) -> list[np.ndarray]:
        """Each projector's start: its share of (target + θ) over its white, carried to its texels."""
        want = np.where(placed > 0, placed + theta, 0.0)
        out = []
        for comp, g, share in zip(self.compensators, gains, shares):
            reach = self.white(comp) * (1.0 if g is None else g)
            ratio = np.where(reach > 1e-3, share[..., None] * want / np.maximum(reach, 1e-3), 0.0)
            out.append(np.clip(comp.camera_to_input(np.clip(ratio, 0.0, 1.0)), 0.0, 1.0))
        return out

    def run(self, target: np.ndarray, area: DisplayArea, *, device: Device | None = None,
            schedule: str | Schedule = "transport", biases: Sequence[BiasModel] | None = None,
            use_bias: bool = True, blend: str = "derived", iterations_z: int | None = None,
            iterations_joint: int | None = None, capture_every: int | None = None, loop: str | None = None,
            progress: Progress | None = None, cancel: Cancel | None = None, name: str = "target",
            start: Sequence[np.ndarray] | None = None, black: np.ndarray | None = None) -> JointResult:
        """Every projector's input ``x*_k = W_k(z_k)`` so that together they look like ``target`` in ``area``.

        ``device`` given: closed loop (it must show every projector at once: ``projectors`` and
        ``project_all``); else open loop with θ the sum of ``biases`` (one per projector; estimated from each
        calibration's captures when None; ``black``: the camera image with every projector black, module doc);
        ``use_bias=False``: no θ. ``blend``: ``'derived'`` (the prior, module doc) or ``'none'``. Only the
        ``transport`` schedule (or one with ``transport=True``): the operators are what make the solve joint.
        ``start``: each projector's starting virtual input; ``loop``: the closed loop's rule (``measured`` or
        ``damped``, :attr:`~.schedule.Schedule.loop`; None: the schedule's). Raises :class:`CompensationError`
        (a bad target, a diverging solve), :class:`~procam.addon.errors.Cancelled` when ``cancel()`` turns true."""
        t_start = time.perf_counter()
        say = progress or (lambda msg, frac: None)
        if blend not in BLENDS:
            raise CompensationError(f"blend must be one of {', '.join(BLENDS)}, got {blend!r}")
        comps = self.compensators
        sched = Compensator.schedule_for(schedule, held_blur=any(c.input_blur for c in comps),
                                         iterations_z=iterations_z, iterations_joint=iterations_joint, lr=None,
                                         alpha=None, capture_every=capture_every, loop=loop)
        if not sched.transport:
            raise CompensationError(f"several projectors are solved jointly on their transport operators; the "
                                    f"schedule {sched.name!r} renders instead: compensate with --schedule transport")
        area, placed = self._place(target, area, name)
        mode, gains, theta = self._mode(device, use_bias, biases, black)
        views = [comp.transport_view(area) for comp in comps]
        joint = JointRows(views, [None if g is None else g.reshape(-1, 3)[views[0].rows] for g in gains])
        if blend == "derived":
            split = self.shares()
        else:  # the light's own split: each projector's share of the white
            whites = np.asarray([self.white(c).mean(axis=2) * (1.0 if g is None else g.mean(axis=2))
                                 for c, g in zip(comps, gains)])
            split = whites / np.maximum(whites.sum(axis=0), 1e-9)
        if start is None:
            zs = self._starts(placed, theta, gains, split)
        else:
            if len(start) != len(comps):
                raise CompensationError(f"{len(start)} starting inputs for {len(comps)} projectors")
            zs = [comp.start_input(z) for comp, z in zip(comps, start)]
        # Every projector's surround holds its colour: it is not solved for (Compensator.area_texels)
        zs = [comp.hold_surround(z, area) for comp, z in zip(comps, zs)]
        self.last_blend = blend
        shares = None if blend == "none" else split.reshape(len(comps), -1)[:, joint.rows]
        solve = JointSolve(self, joint, placed, area, zs, sched, mode, theta.reshape(-1, 3)[joint.rows], shares,
                           device, say, cancel, name)
        return solve.run(False, t_start)


def ramp_baseline(joint: JointCompensator, target: np.ndarray, area: DisplayArea, *,
                  schedule: str | Schedule = "transport", biases: Sequence[BiasModel] | None = None,
                  use_bias: bool = True, black: np.ndarray | None = None, iterations_z: int | None = None,
                  iterations_joint: int | None = None, progress: Progress | None = None,
                  cancel: Cancel | None = None, name: str = "target", device: Device | None = None,
                  loop: str | None = None) -> JointResult:
    """The blend users know, for comparison: each projector compensated alone (its own transport solve) on the
    target times a linear edge-blend ramp across the overlap, in the open loop or with no θ. The ramps are the
    classic distance blend (:func:`blend_shares` with every certainty 1): across a strip-shaped overlap each falls
    linearly from 1 to 0, they sum to 1, and outside the overlap the one projector lighting a pixel has all of it.
    Projector k's solve asks for its ramp's share of target + θ, so the sum of what they show is the target. The
    answer is a :class:`JointResult`, measured as the joint solve's. With ``device`` (one showing every projector)
    each projector runs its own closed loop with the others black (:class:`~..capture.devices.OneProjector`), as
    projectors are compensated one by one before they are blended: each loop's θ then holds the others' black
    level and the room once more, which the overlap shows K times (the black uplift edge blending is known for)."""
    t_start = time.perf_counter()
    say = progress or (lambda msg, frac: None)
    comps = joint.compensators
    area, placed = joint._place(target, area, name)
    if device is not None:
        joint._check_device(device)
    mode, gains, theta = joint._mode(None, use_bias and device is None, biases, black)
    if device is not None and use_bias:
        mode = "closed-loop"
    ramps = blend_shares(joint.operators)
    zs, losses, seconds_device, captures = [], [], 0.0, 0
    for k, (comp, g, ramp) in enumerate(zip(comps, gains, ramps)):
        share = np.asarray(ramp, np.float32)[..., None]
        own = BiasModel(share * theta, g, "ramp share")
        res: CompensationResult = comp.run(area.crop(share * placed), area, schedule=schedule,
                                           iterations_z=iterations_z, iterations_joint=iterations_joint, loop=loop,
                                           open_loop_theta=None if mode == "closed-loop" else own,
                                           device=OneProjector(device, k) if mode == "closed-loop" else None,
                                           use_bias=mode != "none", progress=say,
                                           cancel=cancel, name=f"{name}, projector {k + 1}", verify=False)
        zs.append(res.z)
        losses.extend(res.losses)
        captures += res.captures
        seconds_device += float(res.report.get("seconds_device") or 0.0)
    views = [comp.transport_view(area) for comp in comps]
    stacked = JointRows(views, [None if g is None else g.reshape(-1, 3)[views[0].rows] for g in gains])
    report = {"solver": "each projector alone on its edge-blend ramp of the target (transport schedule)",
              "blend": "ramps", "bias": joint.last_bias}
    return _finish(comps, stacked, zs, theta.reshape(-1, 3)[stacked.rows], placed, area, joint.overlap(), losses,
                   mode, captures, report, t_start, seconds_device)


__all__ = ["BLENDS", "BLEND_WEIGHT", "ENGINES", "JointCompensator", "JointResult", "JointRows", "JointSolve",
           "blend_reach", "blend_shares", "calibration_certainty", "combined_reach", "distance_shares", "footprints",
           "masked_psnr", "overlap_mask", "ramp_baseline", "white_of"]
