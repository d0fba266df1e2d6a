"""Stage C on the precomputed light-transport operator ``T`` (schedule ``transport``; stages/transport.py).

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
display area only). With the compensator's ``input_blur`` the operator is ``T B`` and z the input before the
lens's blur (:class:`BlurredRows`).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict
from typing import Any

import numpy as np

from ..capture.devices import Device
from ..errors import Cancelled
from ..progress import Cancel, Progress
from .bias import BiasModel, predict_capture
from .closed_loop import MeasuredCorrection, RowGrid, check_first_capture, noise_variance_model
from .display_area import DisplayArea
from .metrics import area_psnr, psnr
from .schedule import CompensationError, Schedule
from .solve_jit import JitSteps
from .transport import BlurredRows, TransportRows


class TransportSolve:
    """One target's solve on ``T`` (module doc) for the :class:`~.compensate.Compensator` ``comp``, from the
    virtual input ``z``; :meth:`run` gives its ``CompensationResult``."""

    #: the measured loop's record (stages/closed_loop.py), and why it stopped early when the captures say the rig
    #: changed under it (None: it did not)
    loop: dict[str, Any] | None = None
    loop_problem: str | None = None

    def __init__(self, comp: Any, placed: np.ndarray, area: DisplayArea, z: np.ndarray, sched: Schedule, mode: str,
                 bias: BiasModel | None, device: Device | None, say: Progress, cancel: Cancel | None,
                 name: str) -> None:
        self.comp, self.placed, self.area, self.z0, self.sched, self.mode = comp, placed, area, z, sched, mode
        self.bias, self.device, self.say, self.cancel, self.name = bias, device, say, cancel, name
        view = self.view = comp.transport_view(area)
        rows = self.rows = view.rows
        self.gain = np.ones((len(rows), 3), np.float32) if bias is None or bias.gain is None else \
            bias.gain.reshape(-1, 3)[rows]
        self.target = placed.reshape(-1, 3)[rows]
        self.theta0 = np.zeros_like(self.target) if bias is None else bias.theta.reshape(-1, 3)[rows]
        self.fixed = view.fixed_sums(z)
        self.zc0 = view.compact(z)
        #: the unknowns held at the surround (their light lands outside the area: Compensator.area_texels)
        self.held = ~np.take(comp.area_texels(area).reshape(-1), view.texels)
        self.row_sums = np.maximum(self.gain * view.row_ones, 1e-3)
        unit = bias is None or bias.gain is None
        #: the steps on the device (stages/solve_jit.py; the compensator's ``engine``, as the joint solve's), None:
        #: in numpy (a lens blur held: its blur is OpenCV's)
        self.jit = JitSteps(self, [view], [None if unit else self.gain], [self.fixed], [np.ones_like(self.target)]) \
            if isinstance(view, TransportRows) and comp.engine != "numpy" else None
        #: θ's update may step on the device: its clip to the light is the same there (a gain of 1)
        self.device_theta = unit
        if self.jit is None or not unit:
            self.col_sums = np.maximum(view.adjoint_compact(self.gain), 1e-3)
        self.losses: list[float] = []
        self.captures, self.seconds_device, self.done = 0, 0.0, 0
        self.seconds_steps = 0.0
        self.total = sched.iterations_z + sched.iterations_joint
        self.psnr_start = area_psnr(self.predicted(view.apply_compact(self.zc0, self.fixed), self.theta0), placed,
                                    area)
        self.alpha = sched.theta_rate

    def on_camera(self, values: np.ndarray) -> np.ndarray:
        """Rows' values as a camera image, black outside the area."""
        cw, ch = self.comp.camera_size
        out = np.zeros((ch * cw, 3), np.float32)
        out[self.rows] = values
        return out.reshape(ch, cw, 3)

    def predicted(self, f: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """What the operator says the camera sees for ``f = T z`` (camera size, black outside the area)."""
        return self.on_camera(np.clip(self.gain * f - theta, 0.0, 1.0))

    def solve(self, zc: np.ndarray, theta: np.ndarray, steps: int, residual: np.ndarray | None = None,
              f_start: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``steps`` solver steps from ``zc``; with the last capture's ``residual``, θ follows Eq. 10 towards
        it on every step, then Eq. 14 against the current prediction (as ``fast`` does between captures).
        ``f_start``: ``T zc`` when the caller has it already. On the device when :attr:`jit` is set; the time
        they take is kept (:attr:`seconds_steps`, the report's ``seconds_steps``)."""
        t0 = time.perf_counter()
        try:
            if self.jit is not None and (residual is None or self.device_theta):
                return self.jit.steps(self, zc, theta, steps, residual)
            return self.numpy_steps(zc, theta, steps, residual, f_start)
        finally:
            self.seconds_steps += time.perf_counter() - t0

    def numpy_steps(self, zc: np.ndarray, theta: np.ndarray, steps: int, residual: np.ndarray | None,
                    f_start: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`solve`'s steps in numpy around the operator's gathers."""
        prev, y = zc, zc
        for k in range(steps):
            if self.cancel is not None and self.cancel():
                raise Cancelled(f"compensation of {self.name!r} cancelled at solver step {self.done}")
            f = f_start if k == 0 and f_start is not None else self.forward(y)
            if residual is not None:
                theta = np.clip(theta + 2.0 * self.alpha * (residual - theta), f - 1.0, f)
            resid = self.target + theta - self.gain * f
            z_new = np.clip(self.update(y, resid), 0.0, 1.0)
            z_new[self.held] = self.zc0[self.held]
            y = z_new + (k / (k + 3.0)) * (z_new - prev)
            prev = z_new
            self.done += 1
            if k % 10 == 0 or k == steps - 1:
                self.report_loss(float(np.mean(resid ** 2)))
        return prev, theta

    def report_loss(self, value: float) -> None:
        """A step's loss (mean squared residual) kept and said; NaN stops the solve."""
        if not math.isfinite(value):
            raise CompensationError(f"the solve of {self.name!r} diverged (NaN); check the calibration")
        self.losses.append(value)
        self.say(f"{self.name}: solver step {self.done}, loss {value:.6f}", self.done / max(self.total, 1))

    def forward(self, zc: np.ndarray) -> np.ndarray:
        """``T z`` on the rows for the compact ``zc`` (the others' block sums held at the start's)."""
        return self.view.apply_compact(zc, self.fixed)

    def update(self, y: np.ndarray, resid: np.ndarray) -> np.ndarray:
        """One SIRT step from ``y`` for the rows' residual ``resid`` (before the box clip): the back-projected
        residual normalised by the row and column sums. A joint solve over several operators replaces it
        (stages/joint.py)."""
        return y + self.view.adjoint_compact(self.gain * resid / self.row_sums) / self.col_sums

    def capture(self, zc: np.ndarray) -> np.ndarray:
        """The device's capture of the real input ``W(z)`` for the compact ``zc``, on the rows."""
        comp, device = self.comp, self.device
        assert device is not None
        x = comp.warp_w(self.view.expand(zc, self.z0))
        return comp._check_capture(device.project(comp.rig.projector.frame_from_input(x))).reshape(-1, 3)[self.rows]

    def closed_loop(self, zc: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The joint phase: a capture of the real input, then the solver steps up to the next capture."""
        sched = self.sched
        n_capt = sched.captures or max(1, sched.iterations_joint // sched.capture_interval)
        per = max(1, sched.iterations_joint // max(n_capt, 1))
        for _ in range(n_capt):
            t_dev = time.perf_counter()
            y = self.capture(zc)
            self.seconds_device += time.perf_counter() - t_dev
            self.captures += 1
            f_now = self.forward(zc)
            residual = np.clip(f_now - y, f_now - 1.0, f_now).astype(np.float32)
            if self.captures == 1:
                # one capture, no noise measured: the check's level floor keeps a dim target from failing on noise
                check_first_capture(y, self.gain * f_now, self.name)
                # θ starts at the first residual (fast's theta_init='capture'); later captures move it by
                # Eq. 10, a third of the way each. Replacing θ by every residual diverged on a rig whose
                # captures sit a little off the model (the live loopback: 14 dB against 23 uncompensated):
                # an image that is shifted against the model makes θ chase its own edges.
                theta = residual
            self.say(f"{self.name}: capture {self.captures}", self.done / max(self.total, 1))
            zc, theta = self.solve(zc, theta, per, residual, f_now)
        return zc, theta

    def measured_loop(self, zc: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The joint phase of the measured loop (stages/closed_loop.py): the first input captured twice for the
        noise, then after each capture θ from the measured correction and the solver steps up to the next one,
        until the residual reaches the noise floor, the capture budget is spent, or the captures say the rig
        changed (then the best answer captured is kept)."""
        sched = self.sched
        budget = max(2, sched.captures or max(1, sched.iterations_joint // sched.capture_interval))
        per = max(1, sched.iterations_joint // budget)
        corr: MeasuredCorrection | None = None
        best: tuple[float, np.ndarray, np.ndarray] | None = None
        stopped = "capture budget"
        while self.captures < budget:
            t_dev = time.perf_counter()
            y = self.capture(zc)
            repeats = 1
            first = corr is None
            if corr is None:
                second = self.capture(zc)
                corr = MeasuredCorrection(self.target, RowGrid(self.rows, self.comp.camera_size),
                                          noise_variance_model(y, second))
                noise = float(np.mean((y - second) ** 2)) / 4.0  # the variance of their mean
                y, repeats = 0.5 * (y + second), 2
            self.seconds_device += time.perf_counter() - t_dev
            self.captures += repeats
            q = self.gain * self.forward(zc)
            if first:  # a device of another rig: refused before the loop chases its light (stages/closed_loop.py)
                check_first_capture(y, q, self.name, noise)
            changed = corr.check(y, q)
            if changed is not None:
                self.loop_problem = changed
                stopped = "the rig changed"
                break
            mse = float(np.mean((self.target - y) ** 2))
            if best is None or mse < best[0]:
                best = (mse, zc, theta)
            theta = corr.update(y, q, repeats=repeats)
            h = corr.history[-1]
            self.say(f"{self.name}: capture {self.captures}, residual RMS {h['residual_rms']:.4f} (noise "
                     f"{np.sqrt(corr.floor):.4f})", self.done / max(self.total, 1))
            reason = corr.stop_reason()
            if reason == "diverging":
                self.loop_problem = ("the residual grew over the last captures (the correction diverges): the rig "
                                     "differs from the calibration more than the loop can follow; calibrate again")
            if reason is not None:
                stopped = reason
                break
            zc, _ = self.solve(zc, theta, per)
        if self.loop_problem is not None and best is not None:
            _, zc, theta = best
        self.loop = {"rule": "measured", "captures": self.captures, "stopped": stopped, "problem": self.loop_problem,
                     "noise_rms": None if corr is None else round(float(np.sqrt(corr.floor)), 5),
                     "per_capture": [] if corr is None else corr.history}
        return zc, theta

    def run(self, verify: bool, t_start: float) -> Any:
        """The solve, its answer and report (``t_start``: when the target's stage C began)."""
        sched = self.sched
        zc, theta = self.solve(self.zc0, self.theta0, sched.iterations_z)
        if self.mode == "closed-loop":
            zc, theta = (self.measured_loop if sched.loop == "measured" else self.closed_loop)(zc, theta)
        elif sched.iterations_joint:
            zc, theta = self.solve(zc, theta, sched.iterations_joint)
        return self.answer(zc, theta, verify, t_start)

    def answer(self, zc: np.ndarray, theta: np.ndarray, verify: bool, t_start: float) -> Any:
        """The result for the solved ``zc``: rendered by Mitsuba with ``verify``, else the operator's."""
        comp, sched, view, bias, mode = self.comp, self.sched, self.view, self.bias, self.mode
        t_verify = time.perf_counter()
        operator_raw = view.apply_compact(zc, self.fixed)
        z = view.expand(zc, self.z0)
        agreement = None
        if verify:
            light = view.blur(z) if isinstance(view, BlurredRows) else z
            raw = comp.simulate(light, seed=comp.seed * 1_000_003 + 15)
            agreement = round(min(float(psnr(np.clip(operator_raw, 0.0, 1.0), raw.reshape(-1, 3)[self.rows])),
                                  99.0), 2)
        else:
            raw = self.on_camera(operator_raw)
        if mode == "closed-loop":
            th = np.clip(self.on_camera(theta), raw - 1.0, raw)
            simulated = np.clip(raw - th, 0.0, 1.0)
        else:
            simulated = predict_capture(raw, bias, None)
            th = raw - simulated
        seconds_verify = time.perf_counter() - t_verify if verify else 0.0
        placed, area = self.placed, self.area
        report = {"schedule": asdict(sched), "solver": "projected SIRT with Nesterov momentum on the transport "
                  "operator", "alpha": self.alpha if mode == "closed-loop" else None,
                  "iterations": {"z": sched.iterations_z, "joint": self.done - sched.iterations_z, "total": self.done},
                  "operator": view.op.report, "texels_solved": int(len(view.texels)), "input_blur": comp.input_blur,
                  "bias": None if bias is None else {"kind": bias.kind, **bias.report},
                  "psnr_simulated_start": self.psnr_start,
                  "psnr_operator": area_psnr(self.predicted(operator_raw, theta), placed, area),
                  "psnr_simulated": area_psnr(simulated, placed, area), "warp": comp.warp is not None,
                  "simulated_by": "mitsuba" if verify else "operator",
                  "operator_vs_mitsuba_psnr": agreement, "bounces": comp.bounces, "seed": comp.seed,
                  "seconds_device": round(self.seconds_device, 2), "seconds_verify": round(seconds_verify, 2),
                  "steps_on": "numpy" if self.jit is None else "drjit", "seconds_steps": round(self.seconds_steps, 3),
                  **({"loop": self.loop} if self.loop is not None else {})}
        return comp.result(z, th, simulated, raw, placed, area, self.losses, mode, self.captures, report,
                           t_start=t_start, seconds_device=self.seconds_device, name=self.name, say=self.say)
