"""Real-time stage C for a live show: the stored approximate inverse, and a solver that turns a frame into frames.

:class:`RealtimeSolver` wraps a stage C opened as ``procam show`` opens it
(:class:`~.stage_c.StageC`, or :class:`~.projectors.JointStage` for several
projectors), so a live show places, maps (``--range``) and adapts
(``--effects``) each picture exactly as a show does, and solves it with
``stages/realtime.py``: the approximate inverse in one pass, then
``refine_steps`` SIRT steps warm-started from the previous frame. A source
frame becomes every projector's native frame in one call (:meth:`RealtimeSolver.solve`).

θ: the open loop's model (from the calibration's validation captures) at the
start; :meth:`RealtimeSolver.follow` moves it towards the residual of a camera
image of frames that were shown, a step of :data:`FOLLOW_RATE` at a time (θ
then reaches 95 % of a change after about 30 captures, a second at 30 captures
a second: slow enough that it does not chase the picture's own motion, which
would flicker).

The inverse is stored beside the operator (``layout.inverse_files(k)``:
``inverse.npz`` and ``inverse.json`` with the calibration's hashes, bounces
and seed), by ``procam precompute --live``; a live show reads it when it
belongs to the calibration and otherwise builds it in memory (saying so),
because a show never writes into a calibration folder.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..progress import Progress, quiet
from ..stages.display_area import DisplayArea, TargetAspectWarning, fit_target
from ..stages.realtime import ApproximateInverse, FrameGather, InverseError, RealtimeView, build_inverse
from .inverse import check_memory, load_inverse
from .projectors import JointStage
from .stage_c import StageC

#: θ's step towards each camera image's residual (module doc)
FOLLOW_RATE = 0.05
#: SIRT steps after the one-pass inverse: one recovers what the inverse leaves to within 0.1 dB of the full
#: ``transport`` solve on the lab's targets (scripts/bench_live_show.py)
REFINE_STEPS = 1


@dataclass
class RealtimeFrame:
    """One solved source frame: every projector's native frame, and what it cost."""

    frames: list[np.ndarray]  # H×W×3 float32 in [0, 1], one per projector
    solve_ms: float
    steps: int
    area: DisplayArea
    #: the compact inputs solved (Dr.Jit arrays), per projector, for :meth:`RealtimeSolver.follow`
    inputs: list[Any] = field(default_factory=list, repr=False)


class RealtimeSolver:
    """Real-time stage C on an open stage (module doc). Build with :meth:`for_stage`."""

    def __init__(self, stage: StageC | JointStage, inverses: list[ApproximateInverse], *,
                 refine_steps: int = REFINE_STEPS, progress: Progress | None = None) -> None:
        self.stage, self.inverses, self.refine_steps = stage, inverses, int(refine_steps)
        self.say = progress or quiet
        self._views: dict[tuple[int, int, int, int], Any] = {}
        self._frames: dict[tuple[int, int, int, int], FrameGather | None] = {}
        #: what the camera sees beyond the model, per area (rows × 3): θ, moved by :meth:`follow`
        self._theta: dict[tuple[int, int, int, int], np.ndarray] = {}
        self.said: list[str] = []
        self.last: RealtimeFrame | None = None

    @classmethod
    def for_stage(cls, stage: StageC | JointStage, *, refine_steps: int = REFINE_STEPS,
                  progress: Progress | None = None) -> "RealtimeSolver":
        """The solver for ``stage`` (open loop, ``transport`` operators loaded): every projector's stored inverse,
        or one built now (saying so; ``procam precompute --live`` stores it)."""
        say = progress or quiet
        if isinstance(stage, JointStage):
            raise InverseError("a live show of several projectors is not implemented yet: show one projector's "
                               "calibration")
        comp = stage.compensator
        view = stage.calibration
        opts = stage.options
        op = comp.transport
        # With effect models the operator is the moved scene's (rendered by the stage), not the stored one's.
        inv = None if stage.adapter is not None else load_inverse(view, op, bounces=opts.bounces, seed=opts.seed)
        if inv is None:
            check_memory(op.camera_size)
            say("no stored approximate inverse for this calibration: building it now (procam precompute --live "
                "stores it once)", 0.0)
            inv = build_inverse(op, say)
        if comp.input_blur:
            say(f"warning: the real-time solve does not hold the projector lens's blur (σ {comp.input_blur:.2f} "
                "texels, --effects defocus); it holds the other effects", 0.0)
        if stage.bias is None:
            stage.estimate_bias()
        return cls(stage, [inv], refine_steps=refine_steps, progress=say)

    @property
    def camera_size(self) -> tuple[int, int]:
        return tuple(self.stage.compensator.camera_size)  # type: ignore[return-value]

    def _view(self, area: DisplayArea) -> RealtimeView:
        key = (area.x, area.y, area.width, area.height)
        if key not in self._views:
            stage = self.stage
            comp, bias = stage.compensator, stage.bias
            rows = np.flatnonzero(area.mask(comp.camera_size).ravel())  # the area's pixels, row by row
            view = comp.transport.rows(rows, comp.model.variant)
            gain = None if bias is None or bias.gain is None else bias.gain.reshape(-1, 3)[rows]
            self._views[key] = RealtimeView(view, self.inverses[0], gain)
            self._frames[key] = FrameGather(view, comp.rig.projector, comp.warp) if stage.adapter is None else None
            self._theta[key] = np.zeros((len(rows), 3), np.float32) if bias is None else \
                bias.theta.reshape(-1, 3)[rows].astype(np.float32)
        return self._views[key]

    def _fitted(self, image: np.ndarray, area: DisplayArea) -> np.ndarray:
        """The picture as stage C takes a target, on the area's pixels row by row (rows × 3): fitted to the area
        (a size or aspect other than the area's said once), mapped by ``--range``, through the effect models'
        camera side."""
        stage = self.stage
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", TargetAspectWarning)
            fitted = fit_target(image, area, what="the live source's frame")
        for w in caught:
            if str(w.message) not in self.said:
                self.said.append(str(w.message))
                self.say(f"warning: {w.message}", 0.0)
        if stage.range_map is not None:
            fitted = stage.range_map.apply(fitted)
        if stage.adapter is not None:
            fitted = fit_target(stage.adapter.model_target(fitted, area), area)
        return fitted.reshape(-1, 3)

    def solve(self, image: np.ndarray) -> RealtimeFrame:
        """Every projector's native frame for a source frame ``image`` (H×W×3 linear, any size)."""
        t0 = time.perf_counter()
        stage = self.stage
        comp = stage.compensator
        area = stage.area_for(image)
        rv = self._view(area)
        key = (area.x, area.y, area.width, area.height)
        zc = rv.solve(self._fitted(image, area), self._theta[key], self.refine_steps)
        gather = self._frames[key]
        if gather is not None:
            frame = gather(zc)
        else:  # the effect models' projector side works on the input image
            x = comp.warp_w(rv.view.expand(rv.compact(zc), np.zeros((comp.ih, comp.iw, 3), np.float32)))
            frame = np.clip(stage.adapter.frame_to_send(x), 0.0, 1.0).astype(np.float32)
        out = RealtimeFrame([frame], (time.perf_counter() - t0) * 1000.0, self.refine_steps, area, [zc])
        self.last = out
        return out

    def follow(self, capture: np.ndarray, shown: RealtimeFrame | None = None) -> None:
        """Move θ a step (:data:`FOLLOW_RATE`) towards the residual of ``capture`` (camera size, linear), a camera
        image of ``shown`` (default: the last solve's frames) on the projector."""
        shown = shown or self.last
        if shown is None:
            return
        area = shown.area
        key = (area.x, area.y, area.width, area.height)
        rv = self._view(area)
        y = np.asarray(capture, np.float32)
        cw, ch = self.camera_size
        if y.shape[:2] != (ch, cw):
            raise InverseError(f"a camera image for the live show's closed loop must be {cw}×{ch}, got "
                               f"{y.shape[1]}×{y.shape[0]}")
        f = rv.light(shown.inputs[0])
        residual = np.clip(f - y.reshape(-1, 3)[rv.view.rows], f - 1.0, f)
        theta = self._theta[key]
        self._theta[key] = theta + 2.0 * FOLLOW_RATE * (residual - theta)


__all__ = ["FOLLOW_RATE", "InverseError", "REFINE_STEPS", "RealtimeFrame", "RealtimeSolver"]
