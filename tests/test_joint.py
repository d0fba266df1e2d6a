"""Joint stage C over several projectors' transport operators: the stacked operator, the derived blend, the
combined reach, the closed loop, the ramp baseline, and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from procam.addon.capture.devices import Device
from procam.addon.capture.patterns import smooth_random
from procam.addon.errors import Cancelled
from procam.addon.lab.truth import make_truth
from procam.addon.rig.model import Camera, Rig
from procam.addon.stages.bias import BiasModel
from procam.addon.stages.calibrate import Calibration
from procam.addon.stages.compensate import CompensationError, Compensator
from procam.addon.stages.display_area import DisplayArea
from procam.addon.stages.joint import (JointCompensator, JointRows, blend_reach, blend_shares, combined_reach,
                                       footprints, masked_psnr, ramp_baseline)
from procam.addon.stages.range import range_ceiling
from procam.addon.stages.transport import BlurredRows, TransportOperator, build_transport

CAMERA = (64, 48)


def _rig(surface: str, layout: str, bounces: int, camera: tuple[int, int] = CAMERA) -> list[Compensator]:
    """One compensator per projector of a two-projector lab, each from its own one-projector calibration (the
    true poses, no warp) with its operator built."""
    truth = make_truth(surface, camera_size=camera, projector_size=(80, 60), projectors=2, layout=layout,
                       overlap=0.3)
    comps = []
    for k in range(2):
        cal = Calibration(Rig(truth.rig.camera, truth.rig.projectors[k]), truth.surface, None, "")
        comp = Compensator(cal, bounces=bounces)
        comp.transport = build_transport(cal, bounces=bounces, spp=4)
        comps.append(comp)
    return comps


@pytest.fixture(scope="module")
def side() -> JointCompensator:
    return JointCompensator(_rig("curve", "side-by-side", 1))


@pytest.fixture(scope="module")
def stacked() -> JointCompensator:
    return JointCompensator(_rig("plane", "stacked", 0))


def _area(joint: JointCompensator) -> DisplayArea:
    """A rectangle inside the union of the footprints (a margin of 3 pixels)."""
    lit = footprints(joint.operators).any(axis=0)
    ys, xs = np.nonzero(lit)
    return DisplayArea(int(xs.min()) + 3, int(ys.min()) + 3, int(xs.max() - xs.min()) - 6,
                       int(ys.max() - ys.min()) - 6)


def _target(area: DisplayArea, seed: int, lo: float = 0.05, span: float = 0.3) -> np.ndarray:
    return (lo + span * smooth_random(area.size, seed, 5.0)).astype(np.float32)


def _shifted(op: TransportOperator, dx: int) -> TransportOperator:
    """The operator of a projector whose light lands ``dx`` camera pixels to the right of the model's."""
    cw, ch = op.camera_size
    k = op.index.shape[1]
    index = np.roll(op.index.reshape(ch, cw, k), dx, axis=1)
    weight = np.roll(op.weight.reshape(ch, cw, k, 3), dx, axis=1).copy()
    weight[:, :dx] = 0.0
    return TransportOperator(op.camera_size, op.input_size, index.reshape(-1, k), weight.reshape(-1, k, 3),
                             op.blocks, op.indirect)


def test_the_stacked_operator_sums_the_projectors_and_its_adjoint_matches(side):
    area = _area(side)
    views = [c.transport_view(area) for c in side.compensators]
    rng = np.random.default_rng(0)
    gains = [rng.uniform(0.5, 1.5, (len(views[0].rows), 3)).astype(np.float32), None]
    joint = JointRows(views, gains)
    zs = [rng.random((v.op.input_size[1], v.op.input_size[0], 3)).astype(np.float32) for v in views]
    zc, fixed = joint.compact(zs), joint.fixed_sums(zs)
    want = gains[0] * views[0].apply(zs[0]) + views[1].apply(zs[1])
    np.testing.assert_allclose(joint.apply_compact(zc, fixed), want, rtol=1e-4, atol=1e-5)
    r = rng.random((len(joint.rows), 3)).astype(np.float32)
    assert float(np.sum(joint.apply_compact(zc) * r)) == pytest.approx(float(np.sum(joint.adjoint_compact(r) * zc)),
                                                                      rel=1e-4)
    np.testing.assert_allclose(joint.row_ones, gains[0] * views[0].row_ones + views[1].row_ones, rtol=1e-5)
    back = joint.expand(zc, [np.zeros_like(z) for z in zs])
    for view, z, b in zip(views, zs, back):
        np.testing.assert_array_equal(b.reshape(-1, 3)[view.texels], z.reshape(-1, 3)[view.texels])


def test_the_joint_solve_beats_each_projector_alone_and_the_ramp_baseline(side):
    area = _area(side)
    overlap = side.overlap() & area.mask(CAMERA)
    assert overlap.sum() > 100
    target = _target(area, 3)
    res = side.run(target, area, use_bias=False)
    assert res.report["psnr_overlap"] > 35 and res.report["psnr_simulated"] > 28, res.report
    assert len(res.x_frames) == 2 and res.mode == "none"
    assert res.x_frames[1].shape == (60, 80, 3) != res.x_inputs[1].shape
    assert 0.35 < res.report["share_of_light"][0] < 0.65
    for comp in side.compensators:
        alone = comp.run(target, area, use_bias=False, verify=False)
        assert res.report["psnr_simulated"] > alone.report["psnr_simulated"] + 10
        assert res.report["psnr_overlap"] > masked_psnr(alone.simulated, alone.target, overlap) + 5
    ramps = ramp_baseline(side, target, area, use_bias=False)
    # measured: joint 60.6 dB in the overlap, the ramps 57.5, each alone 21 (the ramps cannot fix the other's edge)
    assert res.report["psnr_overlap"] > ramps.report["psnr_overlap"] + 1.0, (res.report, ramps.report)
    assert ramps.report["blend"] == "ramps" and len(ramps.z) == 2


def test_the_derived_blend_falls_smoothly_and_survives_a_pixel_of_misregistration(side):
    area = _area(side)
    target = _target(area, 5)
    overlap = side.overlap() & area.mask(CAMERA)
    derived = side.run(target, area, use_bias=False, blend="derived")
    plain = side.run(target, area, use_bias=False, blend="none")

    def share_steps(res) -> float:
        """The largest change of projector 1's share between neighbouring overlap pixels along a row."""
        first, second = (c.transport.apply(z).mean(axis=2) for c, z in zip(side.compensators, res.z))
        share = first / np.maximum(first + second, 1e-6)
        both = overlap[:, 1:] & overlap[:, :-1]
        return float(np.abs(np.diff(share, axis=1))[both].max())

    assert share_steps(derived) < 0.2 < share_steps(plain), (share_steps(derived), share_steps(plain))
    shares = blend_shares(side.operators)
    assert np.allclose(shares.sum(axis=0)[footprints(side.operators).any(axis=0)], 1.0)

    def moved(res) -> float:
        ops = [side.compensators[0].transport, _shifted(side.compensators[1].transport, 1)]
        seen = np.clip(sum(op.apply(z) for op, z in zip(ops, res.z)), 0.0, 1.0)
        return masked_psnr(seen, res.target, overlap)

    # measured: 32.8 dB in the overlap with the prior against 31.0 without (60.6 and 100 before the move)
    assert moved(derived) > moved(plain) + 0.5, (moved(derived), moved(plain))


def test_stacked_projectors_reach_twice_one_and_show_targets_one_cannot(stacked):
    black, white = combined_reach(stacked.operators)
    one_black, one = combined_reach(stacked.operators[:1])
    both = footprints(stacked.operators).all(axis=0)
    ratio = np.median(white.mean(axis=2)[both] / one.mean(axis=2)[both])
    assert 1.8 < ratio < 2.2 and not black.any()
    area = _area(stacked)
    cut = area.crop(np.minimum(white, one * 2))
    bright = np.clip(0.8 * cut.min(axis=(0, 1)) + 0.1 * smooth_random(area.size, 2, 5.0), 0, None)
    placed = area.place(bright, CAMERA)
    ceiling_two = range_ceiling(area.crop(placed), area.crop(black), area.crop(white))
    ceiling_one = range_ceiling(area.crop(placed), area.crop(one_black), area.crop(one))
    assert ceiling_two > ceiling_one + 10
    res = stacked.run(bright, area, use_bias=False)
    alone = stacked.compensators[0].run(bright, area, use_bias=False, verify=False)
    assert res.report["psnr_simulated"] > alone.report["psnr_simulated"] + 6, (res.report, alone.report)


class _BothAtOnce(Device):
    """Shows every projector's frame at once: the sum of their operators' images plus a smooth offset."""

    def __init__(self, joint: JointCompensator, offset: np.ndarray) -> None:
        self.joint, self.offset, self.shown = joint, offset, 0
        self.projector = joint.compensators[0].rig.projector
        self._all = tuple(c.rig.projector for c in joint.compensators)

    @property
    def projectors(self) -> tuple:
        return self._all

    def project(self, frame: np.ndarray) -> np.ndarray:
        raise AssertionError("the joint closed loop shows every projector at once")

    def project_all(self, frames) -> np.ndarray:
        self.shown += 1
        out = self.offset.copy()
        for comp, frame in zip(self.joint.compensators, self.check_frames(frames)):
            x0, y0 = comp.rig.projector.input_offset
            x = frame[y0:y0 + comp.ih, x0:x0 + comp.iw]
            out += comp.transport.apply(comp.warp_m(x))
        return out.astype(np.float32)


def test_the_closed_loop_finds_the_offset_the_camera_sees(side):
    area = _area(side)
    ys, xs = np.mgrid[0:CAMERA[1], 0:CAMERA[0]]
    offset = np.repeat((0.03 + 0.04 * xs / CAMERA[0] + 0.02 * ys / CAMERA[1])[..., None], 3, axis=2)
    device = _BothAtOnce(side, offset.astype(np.float32))
    target = _target(area, 7, lo=0.1)
    res = side.run(target, area, device=device)
    assert res.mode == "closed-loop" and res.captures == device.shown == 15
    assert res.report["loop"]["rule"] == "measured" and res.report["loop"]["problem"] is None  # several projectors too
    inside = area.mask(CAMERA)
    err = np.abs(res.theta[inside] + offset[inside])  # the model's θ is the light the model lacks, negated
    assert float(np.median(err)) < 0.005, float(np.median(err))
    seen = device.project_all(res.x_frames)
    assert masked_psnr(seen, res.target, inside) > 30


def _broken(comps: list[Compensator]) -> list[Compensator]:
    """The projectors with damaged operators: some camera pixels' light is NaN."""
    out = [Compensator(c.calibration, bounces=0) for c in comps]
    for comp, good in zip(out, comps):
        op = good.transport
        weight = op.weight.copy()
        weight[::7] = np.nan
        comp.transport = TransportOperator(op.camera_size, op.input_size, op.index, weight, op.blocks, op.indirect)
    return out


def test_bad_input(side):
    area = _area(side)
    target = _target(area, 1)
    bad = target.copy()
    bad[2, 2, 0] = np.nan
    with pytest.raises(CompensationError, match="NaN"):
        side.run(bad, area, use_bias=False)
    with pytest.raises(Cancelled):
        side.run(target, area, use_bias=False, cancel=lambda: True)
    with pytest.raises(CompensationError, match="blend"):
        side.run(target, area, use_bias=False, blend="ramps")
    with pytest.raises(CompensationError, match="transport"):
        side.run(target, area, use_bias=False, schedule="fast")

    class OneProjector(Device):
        projector = side.compensators[0].rig.projector

        def project(self, frame: np.ndarray) -> np.ndarray:
            return np.zeros((CAMERA[1], CAMERA[0], 3), np.float32)

    with pytest.raises(CompensationError, match="drives 1 projector"):
        side.run(target, area, device=OneProjector())
    # a diverging solve: an operator holding NaN
    with pytest.raises(CompensationError, match="diverged"):
        JointCompensator(_broken(side.compensators)).run(target, area, use_bias=False, blend="none")
    # projectors calibrated with cameras of different sizes
    cal = side.compensators[1].calibration
    small = Calibration(Rig(Camera(cal.rig.camera.intrinsics.scaled(32, 24)), cal.rig.projector), cal.surface, None, "")
    with pytest.raises(CompensationError, match="same camera"):
        JointCompensator([side.compensators[0], Compensator(small, bounces=0)])


def test_the_blend_reach_fades_the_overlaps_extra_light_in_and_the_solve_keeps_to_it(side):
    # the reach: one projector's white where the other's share is 0, the sum where the shares are even, no cap alone
    lights = [np.full((4, 3), 0.5, np.float32), np.full((4, 3), 0.4, np.float32)]
    shares = np.array([[1.0, 0.99, 0.5, 1.0], [0.0, 0.01, 0.5, 0.0]], np.float32)
    shares[1, 0] = 1e-4  # just inside projector 2's footprint
    reach = blend_reach(lights, shares)
    np.testing.assert_allclose(reach[0], 0.5 + 0.4 * 2e-4, rtol=1e-5)
    np.testing.assert_allclose(reach[1], 0.5 + 0.4 * 0.02, rtol=1e-5)
    np.testing.assert_allclose(reach[2], 0.9, rtol=1e-6)
    shares[1, 3] = 0.0
    assert np.isinf(blend_reach(lights, shares)[3]).all()
    # a target brighter than one projector's white: without the cap the overlap shows all of it from its edge (a
    # step of the error along the edge), with it the data rows ask no more than the blend's reach
    area = _area(side)
    _, one = combined_reach(side.operators[:1])
    lit = area.crop(footprints(side.operators[:1])[0].astype(np.float32)[..., None])[..., 0] > 0
    target = (float(np.median(area.crop(one)[lit])) * (0.7 + 0.5 * smooth_random(area.size, 7, 5.0))).astype(
        np.float32)
    views = [c.transport_view(area) for c in side.compensators]
    joint = JointRows(views)
    cap = blend_reach(joint.light_parts(), side.shares().reshape(2, -1)[:, joint.rows])
    capped = np.isfinite(cap[:, 0])
    over = {}
    for flag in (True, False):
        res = JointCompensator(side.compensators, cap_reach=flag).run(target, area, use_bias=False)
        raw = res.simulated_raw.reshape(-1, 3)[joint.rows]
        over[flag] = float(np.mean(np.maximum(raw - cap, 0.0)[capped]))
    # measured: 2e-6 above the reach with the cap, 0.0027 without
    assert over[True] < 0.5 * over[False], over


def test_every_projector_holds_the_surround_outside_the_area_with_a_lens_blur_held():
    """Issue 50: a joint solve through each projector's held lens blur (T_k B_k) leaves every texel whose light lands
    outside the display area at the surround; before, those reaching it through bounce light alone were solved."""
    joint = JointCompensator(_rig("curve", "side-by-side", 1))
    lit = footprints(joint.operators).any(axis=0)
    ys, xs = np.nonzero(lit)
    # a band across both footprints, well inside them: much of each projector's input lands outside it
    h = int(ys.max() - ys.min()) // 3
    area = DisplayArea(int(xs.min()) + 3, int(ys.min()) + h, int(xs.max() - xs.min()) - 6, h)
    for comp in joint.compensators:
        comp.input_blur = 1.0
        comp.surround = (0.1, 0.0, 0.05)
    res = joint.run(_target(area, 4), area, use_bias=False, iterations_z=30, iterations_joint=0)
    for comp, z in zip(joint.compensators, res.z):
        keep = comp.area_texels(area)
        assert 0 < keep.sum() < keep.size
        np.testing.assert_array_equal(z[~keep], np.broadcast_to(np.float32([0.1, 0.0, 0.05]), z[~keep].shape))


def test_the_solve_steps_on_the_dr_jit_backend_give_numpys_answer(side):
    """engine='drjit' (every step on the operators' Dr.Jit backend, the default) against 'numpy': the
    same inputs to float32 rounding with gains and the derived blend, without a blend, and in both closed loops;
    its cancel and its NaN stop as numpy's do."""
    comps = side.compensators
    area = _area(side)
    target = _target(area, 5)
    rng = np.random.default_rng(4)
    shape = (CAMERA[1], CAMERA[0], 3)
    biases = [BiasModel(rng.uniform(0.0, 0.02, shape).astype(np.float32),
                        rng.uniform(0.8, 1.2, shape).astype(np.float32), "test") for _ in comps]
    offset = np.full(shape, 0.03, np.float32)
    runs = {"open loop, gains, derived blend": dict(biases=biases),
            "no θ, no blend": dict(use_bias=False, blend="none"),
            "closed loop, damped": dict(loop="damped"), "closed loop, measured": dict(loop="measured")}
    for name, kwargs in runs.items():
        answers = {}
        for engine in ("numpy", "drjit"):
            joint = JointCompensator(comps, engine=engine)
            device = _BothAtOnce(joint, offset) if "closed" in name else None
            answers[engine] = joint.run(target, area, device=device, **kwargs)
        a, b = answers["numpy"], answers["drjit"]
        for za, zb in zip(a.z, b.z):
            np.testing.assert_allclose(zb, za, atol=2e-4, err_msg=name)
        # (an exact fit reads 160 dB, where float32 rounding moves the last digits)
        assert min(b.report["psnr_simulated"], 60) == pytest.approx(min(a.report["psnr_simulated"], 60), abs=0.01)
        assert len(b.losses) == len(a.losses) and b.captures == a.captures, name
        assert (a.report["steps_on"], b.report["steps_on"]) == ("numpy", "drjit") and b.report["seconds_steps"] > 0
        np.testing.assert_allclose(b.losses, a.losses, rtol=1e-3, atol=1e-9, err_msg=name)
    jit = JointCompensator(comps, engine="drjit")
    with pytest.raises(Cancelled):
        jit.run(target, area, use_bias=False, cancel=lambda: True)
    with pytest.raises(CompensationError, match="diverged"):
        JointCompensator(_broken(comps), engine="drjit").run(target, area, use_bias=False, blend="none")
    with pytest.raises(CompensationError, match="engine"):
        JointCompensator(comps, engine="cuda")
    # a lens blur held in the solve is OpenCV's: those views step in numpy whatever the engine
    views = [c.transport_view(area) for c in comps]
    assert jit.engine_for(JointRows(views)) == "drjit"
    assert jit.engine_for(JointRows([BlurredRows(v, 1.0) for v in views])) == "numpy"
    assert JointCompensator(comps).engine_for(JointRows(views)) == "drjit"  # the default, on a CPU too


class _OneShown(Device):
    """One projector through its own operator plus an offset."""

    def __init__(self, comp: Compensator, offset: np.ndarray) -> None:
        self.comp, self.offset, self.projector = comp, offset, comp.rig.projector

    def project(self, frame: np.ndarray) -> np.ndarray:
        x0, y0 = self.projector.input_offset
        x = frame[y0:y0 + self.comp.ih, x0:x0 + self.comp.iw]
        return (self.offset + self.comp.transport.apply(self.comp.warp_m(x))).astype(np.float32)


def test_one_projectors_solve_steps_on_the_dr_jit_backend_too(side):
    """A projector alone (stages/solve_transport.py) steps on the same device code: numpy's answer to float32
    rounding in the open loop with a gain, without θ and in both closed loops."""
    comp = side.compensators[0]
    area = _area(side)
    target = _target(area, 6)
    rng = np.random.default_rng(5)
    shape = (CAMERA[1], CAMERA[0], 3)
    bias = BiasModel(rng.uniform(0.0, 0.02, shape).astype(np.float32), rng.uniform(0.8, 1.2, shape).astype(np.float32),
                     "test")
    offset = np.full(shape, 0.02, np.float32)
    runs = {"open loop, gain": dict(open_loop_theta=bias), "no θ": dict(use_bias=False),
            "closed loop, damped": dict(loop="damped"), "closed loop, measured": dict(loop="measured")}
    try:
        for name, kwargs in runs.items():
            answers = {}
            for engine in ("numpy", "auto"):
                comp.engine = engine
                device = _OneShown(comp, offset) if "closed" in name else None
                answers[engine] = comp.run(target, area, device=device, verify=False, **kwargs)
            a, b = answers["numpy"], answers["auto"]
            np.testing.assert_allclose(b.z, a.z, atol=2e-4, err_msg=name)
            assert min(b.report["psnr_simulated"], 60) == pytest.approx(min(a.report["psnr_simulated"], 60), abs=0.01)
            assert b.captures == a.captures and len(b.losses) == len(a.losses), name
            assert (a.report["steps_on"], b.report["steps_on"]) == ("numpy", "drjit"), name
            np.testing.assert_allclose(b.losses, a.losses, rtol=1e-3, atol=1e-9, err_msg=name)
    finally:
        comp.engine = "auto"
