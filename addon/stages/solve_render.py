"""Stage C on Mitsuba renders (schedules ``fast`` and ``paper``): fixed-point steps, then Adam through ``f̂``.

Phases, in order (stages/schedule.py says why, under "Speed"): preconditioned
fixed-point steps on z (forward renders only), z alone by Adam (a coarse
camera first when the schedule asks), then ``iterations_joint`` Adam steps on
z with θ following Eq. 10 from a capture every few iterations (closed loop)
or fixed (open loop, no θ). With the schedule's ``crop`` the full-resolution
renders cover only the display area, the one place the loss looks: targets,
weights, θ and captures are cut to it, and θ is 0 outside it at the end.
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
from .display_area import DisplayArea
from .metrics import area_psnr
from .schedule import CompensationError, Schedule, plateaued


def diverged(name: str, it: int, z: Any, theta: Any, img: Any) -> CompensationError:
    """Say which quantity went non-finite first."""
    def bad(v: Any) -> bool:
        return not np.all(np.isfinite(np.asarray(v)))

    culprit = ("the virtual input z" if bad(z) else "the bias θ" if bad(theta)
               else "the simulation f̂(z)" if bad(img) else "the loss")
    return CompensationError(f"stage C diverged on {name!r} at iteration {it}: {culprit} became NaN or "
                             "infinite; lower the learning rate (--lr) or α, or check the calibration")


class RenderSolve:
    """One target's solve on renders (module doc) for the :class:`~.compensate.Compensator` ``comp``, from the
    virtual input ``z0``; :meth:`run` gives its ``CompensationResult``."""

    def __init__(self, comp: Any, placed: np.ndarray, area: DisplayArea, z0: np.ndarray, sched: Schedule,
                 mode: str, bias: BiasModel | None, device: Device | None, say: Progress, cancel: Cancel | None,
                 name: str) -> None:
        self.comp, self.placed, self.area, self.sched, self.mode = comp, placed, area, sched, mode
        self.bias, self.device, self.say, self.cancel, self.name = bias, device, say, cancel, name
        self.mi, self.dr = comp._mi, comp._dr
        self.mask = area.mask(comp.camera_size)
        self.opt = self.mi.ad.Adam(lr=float(sched.lr))
        self.opt["z"] = self.mi.TensorXf(z0)
        self.losses: list[float] = []
        self.phases: list[dict[str, Any]] = []
        self.captures = 0
        self.seconds_device = 0.0  # time spent waiting for the device (Cycles in the lab), reported apart
        self.n_coarse = min(sched.iterations_coarse, sched.iterations_z) if sched.coarse < 1.0 else 0
        self.total = sched.iterations_z + sched.iterations_joint  # at most; z phases may stop early
        self.base_seed = comp.seed * 1_000_003 + 17
        start = comp.simulate(z0, spp=sched.reference_spp, seed=self.base_seed - 1)
        self.psnr_start = area_psnr(predict_capture(start, bias, None), placed, area)
        self.it = 0  # iterations so far, over all phases (seeds and progress)
        self.it_fp = 0  # fixed-point steps so far (seeds)
        self.window = (area.x, area.y, area.width, area.height) if sched.crop else None
        self.full_model = comp.model if self.window is None else comp.model_cropped(self.window)
        self.bias_c = None if bias is None else BiasModel(self.cut(bias.theta), None if bias.gain is None
                                                          else self.cut(bias.gain), bias.kind, bias.report)
        self.placed_c, self.mask_c = self.cut(placed), self.cut(self.mask)
        self.mask3 = self.mask_c[..., None]
        reach = comp.white() if bias is None or bias.gain is None else bias.gain * comp.white()
        self.inv_reach = self.cut(1.0 / np.maximum(reach, 0.05))  # the dark rim of the footprint would amplify noise

    # -- the rendered window

    def cut(self, image: np.ndarray) -> np.ndarray:
        """A camera-size image cut to the rendered window."""
        if self.window is None:
            return image
        x, y, w, h = self.window
        return image[y:y + h, x:x + w]

    def uncut(self, image: np.ndarray) -> np.ndarray:
        """A window-size image back in the camera, black outside the window."""
        if self.window is None:
            return image
        x, y, w, h = self.window
        full = np.zeros((self.comp.camera_size[1], self.comp.camera_size[0], 3), np.float32)
        full[y:y + h, x:x + w] = image
        return full

    def render_np(self, z: np.ndarray, spp: int, seed: int) -> np.ndarray:
        """``f̂(z)`` over the rendered window (the whole camera without ``crop``)."""
        return self.full_model.render_input(np.clip(z, 0.0, 1.0), spp=spp, seed=seed)

    def loss_terms(self, scale: float) -> tuple[Any, Any, Any, Any, Any, float]:
        """Model, target, weights, θ and gain tensors at a camera scale, and 1 / the weights' sum."""
        mi, comp, bias, bias_c = self.mi, self.comp, self.bias, self.bias_c
        if scale >= 1.0:
            h, w = self.placed_c.shape[:2]
            weights = self.mask_c.astype(np.float32)
            return (self.full_model, mi.TensorXf(self.placed_c), mi.TensorXf(np.repeat(weights[..., None], 3, axis=2)),
                    mi.TensorXf(np.zeros((h, w, 3), np.float32) if bias_c is None else bias_c.theta),
                    None if bias_c is None or bias_c.gain is None else mi.TensorXf(bias_c.gain),
                    1.0 / float(3 * weights.sum()))
        model = comp.model_at(scale)
        size = model.camera_size
        weights = comp.downsample(self.mask.astype(np.float32), size)
        t = mi.TensorXf(comp.downsample(self.placed, size))
        w = mi.TensorXf(np.repeat(weights[..., None], 3, axis=2))
        th = mi.TensorXf(np.zeros((size[1], size[0], 3), np.float32) if bias is None
                         else comp.downsample(bias.theta, size))
        g = None if bias is None or bias.gain is None else mi.TensorXf(comp.downsample(bias.gain, size))
        return model, t, w, th, g, 1.0 / float(3 * weights.sum())

    # -- the steps

    def step(self, model: Any, target_t: Any, weight_t: Any, theta_t: Any, gain_t: Any, inv_count: float,
             spp: int | None) -> tuple[float, Any]:
        """One Adam gradient on z (the caller steps); returns the loss and the (detached) simulation."""
        mi, dr, comp, opt, it = self.mi, self.dr, self.comp, self.opt, self.it
        if self.cancel is not None and self.cancel():
            raise Cancelled(f"compensation of {self.name!r} cancelled at iteration {it}")
        frame = mi.TensorXf(dr.gather(mi.Float, opt["z"].array, comp._frame_index, comp._frame_inside),
                            (comp.fh, comp.fw, 3))
        img = model.render_dr(frame, seed=self.base_seed + 2 * it, seed_grad=self.base_seed + 2 * it + 1, spp=spp)
        pred = (img if gain_t is None else gain_t * img) - theta_t
        loss = dr.sum(weight_t * dr.square(target_t - pred), axis=None) * inv_count
        dr.backward(loss)
        value = float(np.asarray(loss).ravel()[0])
        if not math.isfinite(value):
            raise diverged(self.name, it, opt["z"], theta_t, img)
        self.losses.append(value)
        return value, dr.detach(img)

    def fixed_point(self, z: np.ndarray, theta: np.ndarray | None, steps: int, label: str) -> np.ndarray:
        """``steps`` preconditioned fixed-point steps on z (stages/schedule.py, "Speed"): forward renders only."""
        sched = self.sched
        for k in range(steps):
            if self.cancel is not None and self.cancel():
                raise Cancelled(f"compensation of {self.name!r} cancelled ({label})")
            raw = self.render_np(z, sched.fixed_point_spp, self.base_seed + 3 * self.total + 7 * self.it_fp)
            self.it_fp += 1
            r = np.where(self.mask3, self.placed_c - predict_capture(raw, self.bias_c, theta), 0.0)
            step = sched.fixed_point_step * (1.0 if k < (steps + 1) // 2 else 0.5)
            z = np.clip(z + step * self.comp.camera_to_input(self.uncut(r * self.inv_reach)), 0.0, 1.0
                        ).astype(np.float32)
        if not np.all(np.isfinite(z)):
            raise CompensationError(f"the virtual input z of {self.name!r} holds NaN after the {label} steps")
        return z

    # -- the phases

    def fixed_point_phase(self, z0: np.ndarray) -> None:
        """The fixed-point steps that replace the z phase (``fixed_point``)."""
        t_phase = time.perf_counter()
        self.opt["z"] = self.mi.TensorXf(self.fixed_point(z0, None, self.sched.fixed_point, "fixed-point"))
        self.phases.append({"phase": "fixed-point", "camera": list(self.comp.camera_size),
                            "iterations": self.sched.fixed_point, "spp": self.sched.fixed_point_spp,
                            "stopped": "limit", "seconds": round(time.perf_counter() - t_phase, 2)})

    def z_phase(self, label: str, scale: float, limit: int) -> None:
        """Adam on z alone at a camera scale, at most ``limit`` iterations; ends early on a plateau of its loss."""
        sched, opt, dr = self.sched, self.opt, self.dr
        t_phase, mine, stop = time.perf_counter(), [], "limit"
        model, target_t, weight_t, theta_t, gain_t, inv_count = self.loss_terms(scale)
        opt.set_learning_rate(float(sched.lr))
        for _ in range(limit):
            value, _img = self.step(model, target_t, weight_t, theta_t, gain_t, inv_count, sched.spp_z)
            opt.step()
            opt["z"] = dr.clip(opt["z"], 0.0, 1.0)
            mine.append(value)
            self.it += 1
            if self.it % 10 == 0:
                self.say(f"{self.name}: iteration {self.it} ({label}), loss {value:.5f}", self.it / max(self.total, 1))
            if plateaued(mine, sched.plateau, sched.plateau_tol):
                stop = "plateau"
                break
        self.phases.append({"phase": label, "camera": list(model.camera_size), "iterations": len(mine),
                            "spp": sched.spp_z or self.comp.spp, "stopped": stop,
                            "seconds": round(time.perf_counter() - t_phase, 2)})

    def capture(self, theta_t: Any, theta_init: str) -> tuple[Any, Any, float]:
        """A fresh capture of the real input W(z), and the simulation of that same z (stages/compensate.py):
        the residual tensor, θ (its start after the first capture) and the seconds waited for the device."""
        comp, sched, mi = self.comp, self.sched, self.mi
        assert self.device is not None
        z_now = np.array(self.opt["z"], dtype=np.float32)
        x = comp.warp_w(z_now)
        t_dev = time.perf_counter()
        y = self.cut(comp._check_capture(self.device.project(comp.rig.projector.frame_from_input(x))))
        waited = time.perf_counter() - t_dev
        self.captures += 1
        f_c = self.render_np(z_now, sched.reference_spp, self.base_seed + 2 * self.total + self.captures)
        residual = f_c - y
        residual_t = mi.TensorXf(residual.astype(np.float32))
        if self.captures == 1 and theta_init == "capture":
            theta_t = mi.TensorXf(np.clip(residual, f_c - 1.0, f_c).astype(np.float32))
        if sched.fixed_point_joint:
            # Bring z to the θ this capture revealed at once instead of over the next iterations.
            self.opt["z"] = mi.TensorXf(self.fixed_point(np.array(self.opt["z"], dtype=np.float32),
                                                         np.array(theta_t, dtype=np.float32),
                                                         sched.fixed_point_joint, "joint fixed-point"))
        self.say(f"{self.name}: capture {self.captures} at iteration {self.it}", self.it / max(self.total, 1))
        return residual_t, theta_t, waited

    def joint_phase(self, theta_init: str) -> Any:
        """z and θ (closed loop), or z with θ fixed; returns θ's tensor at the end."""
        sched, opt, dr, mode = self.sched, self.opt, self.dr, self.mode
        t_phase, n_joint, alpha_used = time.perf_counter(), sched.iterations_joint, sched.theta_rate
        model, target_t, weight_t, theta_t, gain_t, inv_count = self.loss_terms(1.0)
        residual_t = None
        seconds_phase_device = 0.0
        for j in range(n_joint):
            joint = mode == "closed-loop"
            if joint and j % sched.capture_interval == 0:
                residual_t, theta_t, waited = self.capture(theta_t, theta_init)
                seconds_phase_device += waited
            opt.set_learning_rate(sched.learning_rate(j, n_joint))
            value, f_now = self.step(model, target_t, weight_t, theta_t, gain_t, inv_count, sched.spp_joint)
            if joint:
                # Eq. 10, then Eq. 14 against the current simulation.
                theta_t = theta_t + 2.0 * alpha_used * (residual_t - theta_t)
                theta_t = dr.clip(theta_t, f_now - 1.0, f_now)
                dr.eval(theta_t)
            opt.step()
            opt["z"] = dr.clip(opt["z"], 0.0, 1.0)
            self.it += 1
            if self.it % 10 == 0 or j == n_joint - 1:
                phase = "z and θ" if mode == "closed-loop" else "z (θ fixed)"
                self.say(f"{self.name}: iteration {self.it} ({phase}), loss {value:.5f}", self.it / max(self.total, 1))
        self.seconds_device += seconds_phase_device
        if n_joint:
            self.phases.append({"phase": "joint" if mode == "closed-loop" else "z, θ fixed",
                                "camera": list(self.full_model.camera_size), "window": self.window,
                                "iterations": n_joint, "spp": sched.spp_joint or self.comp.spp,
                                "captures": self.captures, "seconds": round(time.perf_counter() - t_phase, 2),
                                "seconds_device": round(seconds_phase_device, 2)})
        return theta_t

    def run(self, z0: np.ndarray, init: str, theta_init: str, t_start: float) -> Any:
        """All phases from ``z0``, then the answer (``t_start``: when the target's stage C began)."""
        sched = self.sched
        if sched.fixed_point:
            self.fixed_point_phase(z0)
        for label, scale, limit in (("coarse", sched.coarse, self.n_coarse),
                                    ("z", 1.0, sched.iterations_z - self.n_coarse)):
            if limit > 0:
                self.z_phase(label, scale, limit)
        theta_t = self.joint_phase(theta_init)
        return self.answer(theta_t, init, theta_init, t_start)

    def answer(self, theta_t: Any, init: str, theta_init: str, t_start: float) -> Any:
        """The result: z, a less noisy final simulation, and θ against it (Eq. 14)."""
        comp, sched, mode, bias, name = self.comp, self.sched, self.mode, self.bias, self.name
        z = np.array(self.opt["z"], dtype=np.float32)
        if not np.all(np.isfinite(z)):
            raise CompensationError(f"the virtual input z of {name!r} holds NaN after the optimisation")
        raw = comp.simulate(z, seed=self.base_seed - 2)
        if mode == "closed-loop":
            theta = self.uncut(np.array(theta_t, dtype=np.float32)) if self.captures else np.zeros_like(raw)
            # Eq. 14 against this (less noisy) final simulation rather than the last 4-spp one.
            theta = np.clip(theta, raw - 1.0, raw)
            simulated = np.clip(raw - theta, 0.0, 1.0)
        else:
            simulated = predict_capture(raw, bias, None)
            theta = raw - simulated
        if not (np.all(np.isfinite(theta)) and np.all(np.isfinite(simulated))):
            raise CompensationError(f"the bias θ of {name!r} diverged (NaN); lower α or check the device's captures")
        it, n_joint = self.it, sched.iterations_joint
        report = {"schedule": asdict(sched), "phases": self.phases,
                  "iterations": {"z": it - n_joint, "joint": n_joint, "total": it, "fixed_point": self.it_fp},
                  "lr": sched.lr, "alpha": sched.theta_rate,
                  "capture_every": sched.capture_interval if mode == "closed-loop" else None, "init": init,
                  "theta_init": theta_init if mode == "closed-loop" else None,
                  "bounces": comp.bounces, "spp": comp.spp, "seed": comp.seed,
                  "bias": None if bias is None else {"kind": bias.kind, **bias.report},
                  "psnr_simulated_start": self.psnr_start,
                  "psnr_simulated": area_psnr(simulated, self.placed, self.area),
                  "warp": comp.warp is not None, "seconds_device": round(self.seconds_device, 2)}
        return comp.result(z, theta, simulated, raw, self.placed, self.area, self.losses, mode, self.captures,
                           report, t_start=t_start, seconds_device=self.seconds_device, name=name, say=self.say)
