"""Real-time stage C for a live show: the stored approximate inverse, and a solver that turns a frame into frames.

:class:`RealtimeSolver` wraps a stage C opened as ``procam show`` opens it
(:class:`~.stage_c.StageC`, or :class:`~.projectors.JointStage` for several
projectors), so a live show places, maps (``--range``) and adapts
(``--effects``) each picture exactly as a show does, and solves it with
``stages/realtime.py``: the approximate inverse in one pass, then
``refine_steps`` SIRT steps from there, the interreflection taken from the previous frame's answer. A source
frame becomes every projector's native frame in one call (:meth:`RealtimeSolver.solve`). With ``--effects
defocus`` each projector's lens blur is held as stage C holds it (``T B``): the one-pass answer is deblurred by
the blur's regularised inverse and the refinement steps run through the blur.

With ``--surround`` the input outside the display area holds that colour, as stage C holds it: the frames show it
there, and its light on the area (computed once an area) is taken off what the answer gives.

θ: the open loop's model (from the calibration's validation captures) at the
start; :meth:`RealtimeSolver.follow` moves it towards the residual of a camera
image of frames that were shown, ``2·FOLLOW_RATE`` of the way at a time (θ
then reaches 95 % of a change after about 30 camera frames, 3 s at the live
show's 10 a second: slow enough that it does not chase the picture's own
motion, which would flicker).

The inverse is stored beside the operator (``steps/inverse.py``, ``layout.inverse_files(k)``:
``inverse.npz`` and ``inverse.json`` with the calibration's hashes, bounces
and seed), by ``procam precompute --live``; a live show reads it when it
belongs to the calibration and otherwise builds it in memory (saying so),
because a show never writes into a calibration folder.
"""

from __future__ import annotations

import io
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import ProCamError
from ..imageio import read_arrays, write_atomic_bytes
from ..progress import Progress, quiet
from ..stages.display_area import DisplayArea, TargetAspectWarning, fit_target
from ..stages.realtime import ApproximateInverse, FrameGather, InverseError, RealtimeView, build_inverse
from ..stages.transport import BlurredRows, lens_blur
from .inverse import check_memory, load_inverse
from .projectors import JointStage
from .stage_c import StageC

#: θ's step towards each camera image's residual (module doc)
FOLLOW_RATE = 0.05
#: A learned correction needs this many followed camera frames of its display area (:meth:`RealtimeSolver.learned`).
LEARN_MIN_FRAMES = 8
#: The learned gain's ridge towards the model's 1, per frame, in squared light: a pixel (with its neighbours) whose
#: light varied by less than about 0.03 over the frames keeps nearly the model's gain.
LEARN_RIDGE = 1e-3
#: The learned correction is the coarse relation of camera to model: both blurred by this σ (camera pixels) first,
#: and each pixel's regression pools the frames of the pixels within this σ (camera pixels) of it.
LEARN_SIGMA, LEARN_WINDOW = 2.0, 6.0
#: The learned gain is kept within a factor of 3 of the model's.
LEARN_GAIN_RANGE = (1.0 / 3.0, 3.0)
#: SIRT steps after the one-pass inverse: one brings it within 0.15 dB of the full ``transport`` solve on the
#: operator and 0.25 dB captured, on the lab's targets (scripts/bench_live_show.py)
REFINE_STEPS = 1


@dataclass
class RealtimeFrame:
    """One solved source frame: every projector's native frame, and what it cost."""

    #: one per projector: its native frame as the 8-bit levels its window shows, RGBX (H×W×4 uint8, the fourth
    #: byte unused: the layout SDL blits from; no transfer curve)
    frames: list[np.ndarray]
    solve_ms: float
    steps: int
    area: DisplayArea
    #: the compact inputs solved (Dr.Jit arrays), per projector, for :meth:`RealtimeSolver.follow`
    inputs: list[Any] = field(default_factory=list, repr=False)


@dataclass
class _Plan:
    """What one display area needs: per projector lit in it, its real-time view, frame gather (None: through the
    effect models) and share of the light (rows × 1; None with one projector), and θ on the rows."""

    keep: list[int]
    views: list[RealtimeView]
    gathers: list[FrameGather | None]
    shares: list[np.ndarray | None]
    theta: np.ndarray
    #: the camera frames followed: count, Σf, Σy, Σf², Σfy per row and channel (f the model's light, y the camera)
    sums: np.ndarray | None = None
    #: a correction learned by following (:meth:`RealtimeSolver.learned`): each row's gain and offset, y = a·f + b
    learned: tuple[np.ndarray, np.ndarray] | None = None
    #: with a surround (``--surround``): the light every projector's surround puts on the rows (rows × 3, through
    #: the open loop's gain), and per projector lit in the area which of its answer's texels hold the surround
    #: (those whose light lands outside the area: :meth:`~..stages.compensate.Compensator.area_texels`)
    surround_light: np.ndarray | None = None
    held: list[Any] = field(default_factory=list)

    def want(self, fitted: np.ndarray) -> np.ndarray:
        """The light the model is asked for, so that the camera sees ``fitted`` (rows × 3)."""
        if self.learned is None:
            return fitted + self.theta
        a, b = self.learned
        return (fitted - b) / a


class RealtimeSolver:
    """Real-time stage C on an open stage (module doc). Build with :meth:`for_stage`.

    Several projectors (a :class:`~.projectors.JointStage`): each projector lit in the display area solves its
    share ``β_k`` of the light wanted, the derived blend the joint solve's prior steers towards (its share falls
    smoothly to its footprint's edge), with its own inverse and refinement step; θ is the rig's (the sum of
    the projectors' open-loop θ with the shared black counted once) and follows the camera as with one. Why
    not the joint solve's coupled step: one coupled step costs every projector's adjoint for each projector's
    update, twice a frame's budget, where the blend alone left the overlaps within a few tenths of a dB of
    the joint solve's on the lab (scripts/bench_live_show.py)."""

    def __init__(self, stage: StageC | JointStage, inverses: list[ApproximateInverse | None], *,
                 refine_steps: int = REFINE_STEPS, hold_blur: bool = True, progress: Progress | None = None) -> None:
        self.stage, self.inverses, self.refine_steps = stage, inverses, int(refine_steps)
        #: solve through each projector's lens blur where stage C holds one (``--effects defocus``); off, the blur is
        #: left out of the solve, as before it was held (the benchmark's comparison)
        self.hold_blur = bool(hold_blur)
        self.say = progress or quiet
        self._plans: dict[tuple[int, int, int, int], _Plan] = {}
        self.said: list[str] = []
        self.last: RealtimeFrame | None = None

    @staticmethod
    def _compensators(stage: StageC | JointStage) -> list[Any]:
        return list(stage.compensators) if isinstance(stage, JointStage) else [stage.compensator]

    @staticmethod
    def _adapters(stage: StageC | JointStage) -> list[Any]:
        if isinstance(stage, JointStage):
            return list(stage.adapters) if stage.adapters is not None else [None] * stage.count
        return [stage.adapter]

    @classmethod
    def for_stage(cls, stage: StageC | JointStage, *, refine_steps: int = REFINE_STEPS,
                  progress: Progress | None = None) -> RealtimeSolver:
        """The solver for ``stage`` (open loop, ``transport`` operators loaded): every projector's stored inverse,
        or one built now (saying so; ``procam precompute --live`` stores it)."""
        say = progress or quiet
        stage.keep_global_radiometry("the real-time solver works through the global models")
        if (stage.pixel if isinstance(stage, StageC) else stage.pixels) is not None:
            raise ProCamError("the real-time solver cannot work through the per-pixel radiometric model this "
                              "stage already chose: run it with --radiometry global")
        comps, adapters = cls._compensators(stage), cls._adapters(stage)
        opts = stage.options
        inverses: list[ApproximateInverse | None] = []
        for k, (comp, adapter) in enumerate(zip(comps, adapters)):
            whose = f"projector {k + 1}: " if len(comps) > 1 else ""
            op = comp.transport
            # With effect models the operator may be the moved scene's (rendered by the stage), not the stored one.
            inv = None if adapter is not None else load_inverse(comp.calibration, op, bounces=opts.bounces,
                                                                seed=opts.seed)
            if inv is None:
                check_memory(op.camera_size)
                say(f"{whose}no stored approximate inverse for this calibration: building it now (procam "
                    "precompute --live stores it once)", 0.0)
                inv = build_inverse(op, say)
            inverses.append(inv)
        if isinstance(stage, JointStage):
            if stage.biases is None:
                stage.estimate_bias()
        elif stage.bias is None:
            stage.estimate_bias()
        return cls(stage, inverses, refine_steps=refine_steps, progress=say)

    @property
    def camera_size(self) -> tuple[int, int]:
        return tuple(self._compensators(self.stage)[0].camera_size)  # type: ignore[return-value]

    def _plan(self, area: DisplayArea) -> _Plan:
        key = (area.x, area.y, area.width, area.height)
        if key in self._plans:
            return self._plans[key]
        stage = self.stage
        comps, adapters = self._compensators(stage), self._adapters(stage)
        rows = np.flatnonzero(area.mask(comps[0].camera_size).ravel())  # the area's pixels, row by row
        if isinstance(stage, JointStage):
            dark, keep, joint, _, biases = stage._solver(area)
            gains, theta = joint._open_loop(biases, stage.black)
            shares = joint.shares().reshape(len(keep), -1)[:, rows]
            total = shares.sum(axis=0)
            # every lit pixel of the area is some projector's: where the footprints' edges leave none a share,
            # the projectors that reach it split it evenly
            shares = np.where(total > 0, shares / np.maximum(total, 1e-12), 1.0 / len(keep))
            share_rows: list[np.ndarray | None] = [s[:, None].astype(np.float32) for s in shares]
            for k in dark:
                self.say(f"warning: projector {k + 1} lights nothing inside the display area: its frame is black",
                         0.0)
        else:
            keep, bias = [0], stage.bias
            gains = [None if bias is None or bias.gain is None else bias.gain]
            theta = np.zeros((*comps[0].camera_size[::-1], 3), np.float32) if bias is None else bias.theta
            share_rows = [None]
        surround = self.surround
        views, gathers, held_texels = [], [], []
        row_views: dict[int, Any] = {}
        for k, gain in zip(keep, gains):
            comp = comps[k]
            view = row_views[k] = comp.transport.rows(rows, comp.model.variant)
            inverse = self.inverses[k]
            assert inverse is not None
            # --effects defocus: the lens's blur held as stage C holds it (T B), through its own regularised inverse
            blurred = BlurredRows(view, comp.input_blur) if comp.input_blur and self.hold_blur else view
            rv = RealtimeView(blurred, inverse, None if gain is None else gain.reshape(-1, 3)[rows])
            views.append(rv)
            gathers.append(FrameGather(view, comp.rig.projector, comp.warp, rv.texels, surround=surround)
                           if adapters[k] is None else None)
            if surround is not None:
                outside = ~comp.area_texels(area).reshape(-1)[rv.texels]
                held_texels.append(rv.hold_mask(outside) if outside.any() else None)
        plan = self._plans[key] = _Plan(keep, views, gathers, share_rows,
                                        np.asarray(theta, np.float32).reshape(-1, 3)[rows].copy(), held=held_texels)
        if surround is not None:
            plan.surround_light = self._surround_light(area, rows, dict(zip(keep, gains)), row_views)
        return plan

    @property
    def surround(self) -> tuple[float, float, float] | None:
        """The input outside the display area (``--surround``, every projector's; None: black)."""
        s = tuple(float(v) for v in self._compensators(self.stage)[0].surround)
        return s if any(s) else None  # type: ignore[return-value]

    def _surround_light(self, area: DisplayArea, rows: np.ndarray, gains: dict[int, np.ndarray | None],
                        views: dict[int, Any]) -> np.ndarray:
        """(rows × 3) the light on the area's rows of every projector's input held at the surround outside its
        area texels (a projector that lights nothing of the area: its whole input), through each one's open-loop
        gain: what the answer inside need not give (stage C's solve holds those texels so, in its model).
        ``views``: the operators on these rows the plan already made (a projector dark in the area gets its own)."""
        total = np.zeros((len(rows), 3), np.float32)
        for k, comp in enumerate(self._compensators(self.stage)):
            z = comp.hold_surround(np.zeros((*comp.transport.input_size[::-1], 3), np.float32), area)
            if comp.input_blur and self.hold_blur:  # the lens blurs the surround's edge as it does the picture's
                z = lens_blur(z, comp.input_blur)
            view = views.get(k) or comp.transport.rows(rows, comp.model.variant)
            light = view.apply(z)
            gain = gains.get(k)
            total += light if gain is None else gain.reshape(-1, 3)[rows] * light
        return total

    def _fitted(self, image: np.ndarray, area: DisplayArea) -> np.ndarray:
        """The picture as stage C takes a target, on the area's pixels row by row (rows × 3): fitted to the area
        (a size or aspect other than the area's said once), mapped by ``--range``, through the effect models'
        camera side (one projector's)."""
        stage = self.stage
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", TargetAspectWarning)
            fitted = fit_target(image, area, what="the live source's frame")
        for w in caught:
            if str(w.message) not in self.said:
                self.said.append(str(w.message))
                self.say(f"warning: {w.message}", 0.0)
        if stage.range_map is not None:
            fitted = stage.range_map.apply(fitted, area)
        if isinstance(stage, StageC) and stage.adapter is not None:
            fitted = fit_target(stage.adapter.model_target(fitted, area), area)
        return fitted.reshape(-1, 3)

    def solve(self, image: np.ndarray) -> RealtimeFrame:
        """Every projector's native frame for a source frame ``image`` (H×W×3 linear, any size)."""
        t0 = time.perf_counter()
        stage = self.stage
        comps, adapters = self._compensators(stage), self._adapters(stage)
        area = stage.area_for(image)
        plan = self._plan(area)
        want = plan.want(self._fitted(image, area))
        if plan.surround_light is not None:
            want = want - plan.surround_light
        surround = self.surround
        frames = [self._dark_frame(comp, surround) for comp in comps]
        inputs = []
        for j, (k, rv, gather, share) in enumerate(zip(plan.keep, plan.views, plan.gathers, plan.shares)):
            zc = rv.solve(want if share is None else share * want, None, self.refine_steps)
            mask = plan.held[j] if plan.held else None
            # the texels held at the surround: shown at it, their light already counted in the surround's
            inputs.append(zc if mask is None else rv.hold(zc, mask, (0.0, 0.0, 0.0)))
            if mask is not None:
                zc = rv.hold(zc, mask, surround)
            if gather is not None:
                frames[k] = gather.levels(zc)
            else:  # the effect models' projector side works on the input image
                comp = comps[k]
                x = comp.warp_w(rv.expand(zc, surround))
                levels = np.rint(np.clip(adapters[k].frame_to_send(x), 0.0, 1.0) * 255.0).astype(np.uint8)
                frames[k][..., :3] = levels
        out = RealtimeFrame(frames, (time.perf_counter() - t0) * 1000.0, self.refine_steps, area, inputs)
        self.last = out
        return out

    @staticmethod
    def _dark_frame(comp: Any, surround: tuple[float, float, float] | None) -> np.ndarray:
        """A native frame (RGBX levels) that shows nothing of the picture: black, its input region at the
        ``surround`` when one is given."""
        proj = comp.rig.projector
        frame = np.zeros((*proj.intrinsics.size[::-1], 4), np.uint8)
        if surround is not None:
            (x0, y0), (iw, ih) = proj.input_offset, proj.input_size
            frame[y0:y0 + ih, x0:x0 + iw, :3] = np.rint(np.clip(surround, 0.0, 1.0) * 255.0).astype(np.uint8)
        return frame

    def predicted(self, shown: RealtimeFrame) -> np.ndarray:
        """(rows × 3) the light the model says the camera gets from ``shown``'s frames, before θ."""
        plan = self._plan(shown.area)
        start = np.zeros_like(plan.theta) if plan.surround_light is None else plan.surround_light
        return sum((rv.light(zc) for rv, zc in zip(plan.views, shown.inputs)), start)

    def theta(self, area: DisplayArea) -> np.ndarray:
        """(rows × 3) θ of ``area`` now."""
        return self._plan(area).theta

    def follow(self, capture: np.ndarray, shown: RealtimeFrame | None = None) -> None:
        """Move θ a step (:data:`FOLLOW_RATE`) towards the residual of ``capture`` (camera size, linear), a camera
        image of ``shown`` (default: the last solve's frames) on the projectors."""
        shown = shown or self.last
        if shown is None:
            return
        y = np.asarray(capture, np.float32)
        cw, ch = self.camera_size
        if y.shape[:2] != (ch, cw):
            raise InverseError(f"a camera image for the live show's closed loop must be {cw}×{ch}, got "
                               f"{y.shape[1]}×{y.shape[0]}")
        plan = self._plan(shown.area)
        f = self.predicted(shown)
        seen = y.reshape(-1, 3)[plan.views[0].view.rows]
        residual = np.clip(f - seen, f - 1.0, f)
        plan.theta += 2.0 * FOLLOW_RATE * (residual - plan.theta)
        # The correction to keep is what holds for any picture: the coarse relation of camera to model at each
        # pixel. What a picture's own edges add (a blur or a shift the model lacks) moves with the picture.
        f64, y64 = (cv2.GaussianBlur(v.reshape(shown.area.height, shown.area.width, 3).astype(np.float64), (0, 0),
                                     LEARN_SIGMA).reshape(-1, 3) for v in (f, seen))
        if plan.sums is None:
            plan.sums = np.zeros((5, *f.shape), np.float64)
        plan.sums += np.stack([np.ones_like(f64), f64, y64, f64 * f64, f64 * y64])

    def learned(self, area: DisplayArea) -> tuple[np.ndarray, np.ndarray] | None:
        """Each row's gain and offset (y = a·f + b, rows × 3) from the camera frames followed in ``area``: what
        the model gets wrong at every pixel and level, learned while the picture moved (a ridge pulls the gain
        towards the model's 1 where the frames did not vary). None before :data:`LEARN_MIN_FRAMES` frames."""
        plan = self._plan(area)
        if plan.sums is None or plan.sums[0].max() < LEARN_MIN_FRAMES:
            return None
        # The camera's departures from the model change slowly over the surface (a response, a vignette, a colour
        # mixing that drifts): each pixel's regression pools its neighbours' frames (LEARN_WINDOW), so a pan that
        # barely changes one pixel's light still pins its gain through the pixels around it.
        h, w = area.height, area.width
        n, sf, sy, sff, sfy = (cv2.GaussianBlur(v.reshape(h, w, 3), (0, 0), LEARN_WINDOW).reshape(-1, 3)
                               for v in plan.sums)
        ridge = LEARN_RIDGE * n
        a = np.clip((sfy - sf * sy / n + ridge) / (sff - sf * sf / n + ridge), *LEARN_GAIN_RANGE)
        return a.astype(np.float32), ((sy - a * sf) / n).astype(np.float32)

    def save_learned(self, path: str | Path, calibration_sha256: str) -> Path | None:
        """Write every display area's learned correction (:meth:`learned`) to ``path`` (npz, atomically) with the
        calibration's hash; None (nothing written) when no area has followed enough frames."""
        keys, gains, offsets = [], [], []
        for key in list(self._plans):
            got = self.learned(DisplayArea(*key))
            if got is not None:
                keys.append(key)
                gains.append(got[0])
                offsets.append(got[1])
        if not keys:
            return None
        arrays = {"calibration_sha256": np.asarray(calibration_sha256), "areas": np.asarray(keys, np.int64),
                  "camera_size": np.asarray(self.camera_size, np.int64),
                  **{f"gain_{i}": g for i, g in enumerate(gains)}, **{f"offset_{i}": o for i, o in enumerate(offsets)}}
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        write_atomic_bytes(Path(path), buf.getvalue())
        return Path(path)

    def load_learned(self, path: str | Path, calibration_sha256: str) -> int:
        """Use the corrections of ``path`` (written by :meth:`save_learned` for this calibration) for their display
        areas from now on; how many areas it holds. :class:`InverseError` when it is another calibration's or
        another camera's."""
        data = read_arrays(path, None, error=InverseError,
                           remedy="follow the camera in a live show with --correction to learn it again")
        if str(data.get("calibration_sha256")) != calibration_sha256:
            raise InverseError(f"the learned correction {path} was learned on another calibration: follow the camera "
                               "with this calibration to learn it again")
        if tuple(int(v) for v in data["camera_size"]) != tuple(self.camera_size):
            raise InverseError(f"the learned correction {path} is for a {data['camera_size'][0]}×"
                               f"{data['camera_size'][1]} camera, not this calibration's")
        for i, key in enumerate(np.asarray(data["areas"]).reshape(-1, 4)):
            plan = self._plan(DisplayArea(*(int(v) for v in key)))
            gain, offset = np.asarray(data[f"gain_{i}"], np.float32), np.asarray(data[f"offset_{i}"], np.float32)
            if gain.shape != plan.theta.shape or offset.shape != plan.theta.shape:
                raise InverseError(f"the learned correction {path} does not fit its display area; learn it again")
            plan.learned = (gain, offset)
        return len(np.asarray(data["areas"]).reshape(-1, 4))


__all__ = ["FOLLOW_RATE", "InverseError", "LEARN_MIN_FRAMES", "REFINE_STEPS", "RealtimeFrame", "RealtimeSolver"]
