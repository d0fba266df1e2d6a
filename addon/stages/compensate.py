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
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..capture.devices import Device
from ..errors import CalibrationError, Cancelled, CaptureError, ProCamError
from .display_area import DisplayArea, fit_target
from .metrics import psnr

Progress = Callable[[str, float], None]

#: Defaults of the paper's schedule and of the choices documented above.
ITERATIONS_Z = 200
ITERATIONS_JOINT = 300
ALPHA = 0.01
LEARNING_RATE = 0.01
CAPTURE_EVERY = 20
#: Samples per pixel of renders that are not inside the loop (θ references, final simulation): less noise.
REFERENCE_SPP = 16
MODES = ("closed-loop", "open-loop", "none")


class CompensationError(ProCamError):
    """Stage C cannot proceed or diverged."""



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


def _split_iterations(total: int) -> tuple[int, int]:
    """Split a total iteration count 200 : 300 like the paper."""
    if total < 0:
        raise CompensationError(f"the iteration count must be ≥ 0, got {total}")
    z = round(total * ITERATIONS_Z / (ITERATIONS_Z + ITERATIONS_JOINT))
    return z, total - z


class Compensator:
    """Stage C for one calibration: holds the loaded Mitsuba scene so that many targets reuse it.

    Loading the scene and compiling the render kernels is the slow start;
    Dr.Jit caches the compiled kernels, so the second target starts at once.
    """

    def __init__(self, calibration: Any, *, bounces: int = 1, spp: int = 4, seed: int = 0,
                 variant: str | None = None) -> None:
        from ..render.forward import ForwardModel

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

    # ------------------------------------------------------------------ helpers

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
            from ..render.raycast import first_hits

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

    # ------------------------------------------------------------------ open-loop bias

    def estimate_bias(self, captures: Any = None, *, ridge: float = 0.05) -> BiasModel:
        """θ for open-loop compensation, from the calibration's white/black/validation captures (module doc)."""
        from ..capture.format import CaptureSet

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
        n = len(f)
        lit = self.white().mean(axis=2) > 1e-3
        # Mean residual, leave-one-out: θ_{-i} = (Σr − r_i)/(n − 1).
        r = f - c
        r_sum = r.sum(axis=0)
        mean_err = [(r[i] - (r_sum - r[i]) / (n - 1))[lit] for i in range(n)]
        # Affine c = a·f + b per pixel and channel, ridge λ pulling a towards 1; leave-one-out on the sums.
        sf, sc, sff, sfc = f.sum(0), c.sum(0), (f * f).sum(0), (f * c).sum(0)

        def fit(k: int, sf: np.ndarray, sc: np.ndarray, sff: np.ndarray,
                sfc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            mf, mc = sf / k, sc / k
            a = (sfc - k * mf * mc + ridge) / (sff - k * mf * mf + ridge)
            return a, mc - a * mf

        aff_err = []
        for i in range(n):
            a, b = fit(n - 1, sf - f[i], sc - c[i], sff - f[i] ** 2, sfc - f[i] * c[i])
            aff_err.append((np.clip(a * f[i] + b, 0, 1) - c[i])[lit])
        rmse_mean = float(np.sqrt(np.mean(np.concatenate(mean_err) ** 2)))
        rmse_aff = float(np.sqrt(np.mean(np.concatenate(aff_err) ** 2)))
        rmse_zero = float(np.sqrt(np.mean((f - c)[:, lit] ** 2)))
        report = {"patterns": [e.name for e in entries], "held_out_rmse": {
            "no_bias": rmse_zero, "mean": rmse_mean, "affine": rmse_aff}}
        if rmse_aff < rmse_mean:
            a, b = fit(n, sf, sc, sff, sfc)
            return BiasModel((-b).astype(np.float32), a.astype(np.float32), "affine", report)
        return BiasModel((r_sum / n).astype(np.float32), None, "mean", report)

    # ------------------------------------------------------------------ the optimisation

    def run(self, target: np.ndarray, area: DisplayArea, *, device: Device | None = None,
            iterations_z: int = ITERATIONS_Z, iterations_joint: int = ITERATIONS_JOINT, lr: float = LEARNING_RATE,
            alpha: float = ALPHA, capture_every: int = CAPTURE_EVERY, progress: Progress | None = None,
            cancel: Callable[[], bool] | None = None, open_loop_theta: np.ndarray | BiasModel | None = None,
            use_bias: bool = True, init: str = "inverse", theta_init: str = "capture",
            name: str = "target") -> CompensationResult:
        """Stage C for one target; see :func:`compensate`."""
        mi, dr = self._mi, self._dr
        t_start = time.perf_counter()
        say = progress or (lambda msg, frac: None)
        for what, v in (("iterations_z", iterations_z), ("iterations_joint", iterations_joint)):
            if not isinstance(v, int) or v < 0:
                raise CompensationError(f"{what} must be a whole number ≥ 0, got {v!r}")
        if not (isinstance(capture_every, int) and capture_every >= 1):
            raise CompensationError(f"capture_every must be a whole number ≥ 1, got {capture_every!r}")
        if not (math.isfinite(lr) and lr > 0):
            raise CompensationError(f"the learning rate must be a positive number, got {lr!r}")
        if not (math.isfinite(alpha) and 0 < alpha <= 0.5):
            raise CompensationError(f"α must lie in (0, 0.5] (Eq. 10 overshoots beyond), got {alpha!r}")
        if theta_init not in ("capture", "zero"):
            raise CompensationError(f"theta_init must be 'capture' or 'zero', got {theta_init!r}")
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

        z0 = self.initial_input(placed, bias, init)
        opt = mi.ad.Adam(lr=float(lr))
        opt["z"] = mi.TensorXf(z0)
        target_t = mi.TensorXf(placed)
        mask_t = mi.TensorXf(np.repeat(mask[..., None], 3, axis=2).astype(np.float32))
        inv_count = 1.0 / float(3 * mask.sum())
        theta_t = mi.TensorXf(np.zeros_like(placed)) if bias is None else mi.TensorXf(bias.theta)
        gain_t = None if bias is None or bias.gain is None else mi.TensorXf(bias.gain)
        residual_t = None
        losses: list[float] = []
        captures = 0
        seconds_device = 0.0  # time spent waiting for the device (Cycles in the lab), reported apart
        total = iterations_z + iterations_joint
        base_seed = self.seed * 1_000_003 + 17
        psnr_start = area_psnr(self._predict(self.simulate(z0, seed=base_seed - 1), bias, None), placed, area)

        for it in range(total):
            if cancel is not None and cancel():
                raise Cancelled(f"compensation of {name!r} cancelled at iteration {it}")
            joint = it >= iterations_z and mode == "closed-loop"
            if joint and (it - iterations_z) % capture_every == 0:
                # A fresh capture of the real input W(z), and the simulation of that same z (module doc).
                z_now = np.array(opt["z"], dtype=np.float32)
                x = self.warp_w(z_now)
                t_dev = time.perf_counter()
                y = self._check_capture(device.project(self.rig.projector.frame_from_input(x)))
                seconds_device += time.perf_counter() - t_dev
                captures += 1
                f_c = self.simulate(z_now, seed=base_seed + 2 * total + captures)
                residual = f_c - y
                residual_t = mi.TensorXf(residual.astype(np.float32))
                if captures == 1 and theta_init == "capture":
                    theta_t = mi.TensorXf(np.clip(residual, f_c - 1.0, f_c).astype(np.float32))
                say(f"{name}: capture {captures} at iteration {it}", it / max(total, 1))
            frame = mi.TensorXf(dr.gather(mi.Float, opt["z"].array, self._frame_index, self._frame_inside),
                                (self.fh, self.fw, 3))
            img = self.model.render_dr(frame, seed=base_seed + 2 * it, seed_grad=base_seed + 2 * it + 1)
            pred = (img if gain_t is None else gain_t * img) - theta_t
            diff = (target_t - pred) * mask_t
            loss = dr.sum(dr.square(diff), axis=None) * inv_count
            dr.backward(loss)
            value = float(np.asarray(loss).ravel()[0])
            if not math.isfinite(value):
                raise self._diverged(name, it, opt["z"], theta_t, img)
            losses.append(value)
            if joint:
                # Eq. 10, then Eq. 14 against the current simulation.
                f_now = dr.detach(img)
                theta_t = theta_t + 2.0 * alpha * (residual_t - theta_t)
                theta_t = dr.clip(theta_t, f_now - 1.0, f_now)
                dr.eval(theta_t)
            opt.step()
            opt["z"] = dr.clip(opt["z"], 0.0, 1.0)
            if it % 10 == 0 or it == total - 1:
                phase = "z" if it < iterations_z else ("z and θ" if mode == "closed-loop" else "z (θ fixed)")
                say(f"{name}: iteration {it + 1}/{total} ({phase}), loss {value:.5f}", (it + 1) / max(total, 1))

        z = np.array(opt["z"], dtype=np.float32) if total else z0
        if not np.all(np.isfinite(z)):
            raise CompensationError(f"the virtual input z of {name!r} holds NaN after the optimisation")
        raw = self.simulate(z, seed=base_seed - 2)
        if mode == "closed-loop":
            theta = np.array(theta_t, dtype=np.float32) if captures else np.zeros_like(raw)
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
        report = {"iterations": {"z": iterations_z, "joint": iterations_joint}, "lr": lr, "alpha": alpha,
                  "capture_every": capture_every if mode == "closed-loop" else None, "init": init,
                  "theta_init": theta_init if mode == "closed-loop" else None,
                  "bounces": self.bounces, "spp": self.spp, "seed": self.seed,
                  "bias": None if bias is None else {"kind": bias.kind, **bias.report},
                  "psnr_simulated_start": psnr_start, "psnr_simulated": area_psnr(simulated, placed, area),
                  "warp": self.warp is not None, "seconds_device": round(seconds_device, 2)}
        say(f"{name}: done in {seconds:.1f} s", 1.0)
        return CompensationResult(x_input, self.rig.projector.frame_from_input(x_input), z, theta, simulated, raw,
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
               iterations_z: int = ITERATIONS_Z, iterations_joint: int = ITERATIONS_JOINT,
               lr: float = LEARNING_RATE, alpha: float = ALPHA, bounces: int = 1, spp: int = 4,
               capture_every: int = CAPTURE_EVERY, progress: Progress | None = None,
               cancel: Callable[[], bool] | None = None, seed: int = 0,
               open_loop_theta: np.ndarray | BiasModel | None = None, use_bias: bool = True,
               init: str = "inverse", theta_init: str = "capture",
               compensator: Compensator | None = None, name: str = "target") -> CompensationResult:
    """Find the projector input ``x* = W(z)`` whose projection looks like ``target`` inside ``area``.

    ``target``: H×W×3 linear float in [0, 1], any size (fitted to the area,
    see :func:`.display_area.fit_target`). ``device`` given: closed loop
    (θ from captures every ``capture_every`` joint iterations); else open loop
    (θ from the calibration's validation captures, or ``open_loop_theta``);
    ``use_bias=False``: no θ at all (mode ``'none'``, the paper's ablation).
    ``compensator`` reuses a loaded scene across targets (``bounces``,
    ``spp`` and ``seed`` are then its own). Raises :class:`CompensationError`
    when the optimisation diverges, :class:`Cancelled` when ``cancel()``
    turns true.
    """
    comp = compensator or Compensator(calibration, bounces=bounces, spp=spp, seed=seed)
    return comp.run(target, area, device=device, iterations_z=iterations_z, iterations_joint=iterations_joint,
                    lr=lr, alpha=alpha, capture_every=capture_every, progress=progress, cancel=cancel,
                    open_loop_theta=open_loop_theta, use_bias=use_bias, init=init, theta_init=theta_init, name=name)


__all__ = ["ALPHA", "BiasModel", "CAPTURE_EVERY", "Cancelled", "CompensationError", "CompensationResult",
           "Compensator", "ITERATIONS_JOINT", "ITERATIONS_Z", "LEARNING_RATE", "MODES", "area_psnr", "compensate"]
