"""Real-time stage C: the approximate inverse, its storage beside the operator, and the solver a live show runs."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

from procam.addon.capture.targets import natural_target
from procam.addon.cli.app import main
from procam.addon.stages.metrics import area_psnr
from procam.addon.stages.realtime import FrameGather, InverseError, LensBlurBox, deblur_taps, solve_batched
from procam.addon.stages.transport import gaussian_taps, lens_blur
from procam.addon.stages.warp_model import Warp
from procam.addon.steps import calibrate as calibrate_step
from procam.addon.steps import inverse as inverse_step
from procam.addon.steps.projectors import JointStage
from procam.addon.steps.realtime import RealtimeSolver
from procam.addon.steps.stage_c import StageC, StageCOptions, device_pipeline

@pytest.fixture(scope="module")
def calibration(live_calibration, tmp_path_factory):
    """The suite's small lab calibration (the vedge, camera 192×144), copied, with its operator and inverse
    stored."""
    folder = tmp_path_factory.mktemp("realtime") / "cal"
    shutil.copytree(live_calibration(), folder)
    return folder


def _operator_psnr(solver: RealtimeSolver, frame, target) -> float:
    """What the operators say the camera sees of a real-time answer (every projector, less θ), against the placed
    target."""
    rows = solver._plan(frame.area).views[0].view.rows
    seen = np.clip(solver.predicted(frame) - solver.theta(frame.area), 0.0, 1.0)
    cw, ch = solver.camera_size
    image = np.zeros((ch * cw, 3), np.float32)
    image[rows] = seen
    return area_psnr(image.reshape(ch, cw, 3), target, frame.area)


def test_precompute_live_stores_the_inverse_of_this_calibration_only(calibration, tmp_path):
    doc = json.loads((calibration / "inverse.json").read_text())
    assert doc["stencil"] == "3x3" and doc["calibration_sha256"] and doc["bounces"] == 1
    cal = calibrate_step.read(calibration)
    stage = StageC(cal, StageCOptions())
    op = stage.compensator.transport
    assert inverse_step.load_inverse(cal, op, bounces=1, seed=0) is not None
    assert inverse_step.load_inverse(cal, op, bounces=1, seed=3) is None  # another seed: another operator
    # Another calibration's inverse (a copied folder whose calibration changed) is not this one's.
    other = tmp_path / "other"
    shutil.copytree(calibration, other)
    manifest = other / "calibration.json"
    manifest.write_text(manifest.read_text().replace('"version"', '"note": "moved", "version"', 1))
    assert inverse_step.load_inverse(calibrate_step.read(other), op, bounces=1, seed=0) is None
    # A damaged file is said, with the command that makes it again.
    (other / "inverse.npz").write_bytes(b"not an npz")
    (other / "inverse.json").write_text(json.dumps({**doc, **inverse_step._record(other, cal, 1, 0)}))
    with pytest.raises(InverseError, match="precompute .* --live --force"):
        inverse_step.load_inverse(calibrate_step.read(other), op, bounces=1, seed=0)
    # So is one whose weights are no number: a NaN would spread into every live frame.
    with np.load(calibration / "inverse.npz") as stored:
        arrays = {k: stored[k] for k in stored.files}
    arrays["weight"] = arrays["weight"].copy()
    arrays["weight"].flat[7] = np.nan
    np.savez(other / "inverse.npz", **arrays)
    (other / "inverse.json").write_text(json.dumps({**doc, **inverse_step._record(other, cal, 1, 0)}))
    with pytest.raises(InverseError, match="no number.*--live --force"):
        inverse_step.load_inverse(calibrate_step.read(other), op, bounces=1, seed=0)


def test_the_batched_small_solve_is_lapacks_answer_and_pivots():
    """The inverse's 9 × 9 systems are solved by one vectorised elimination (``solve_batched``): the same answer
    as ``np.linalg.solve`` for a batch whose systems need row swaps (a zero or tiny leading pivot) and several
    right-hand sides, and a singular system is refused as numpy refuses it."""
    rng = np.random.default_rng(4)
    a = rng.normal(size=(5, 7, 9, 9))
    a[..., 0, 0] = 0.0  # no system can be eliminated in its own row order
    a[1, 2, 3, 3] = 1e-14
    b = rng.normal(size=(5, 7, 9, 2))
    x = solve_batched(a, b)
    assert x.shape == b.shape
    assert np.allclose(x, np.linalg.solve(a, b), rtol=1e-9, atol=1e-9)
    assert np.allclose(a @ x, b, atol=1e-9)
    singular = a.copy()
    singular[2, 5, 4] = singular[2, 5, 6]  # two equal rows
    with pytest.raises(np.linalg.LinAlgError):
        solve_batched(singular, b)


def test_realtime_solve_is_within_half_a_db_of_the_full_transport_solve(calibration):
    cal = calibrate_step.read(calibration)
    with StageC(cal, StageCOptions()) as stage:
        said: list[str] = []
        solver = RealtimeSolver.for_stage(stage, progress=lambda msg, frac: said.append(msg))
        assert not any("building it now" in m for m in said)  # the stored inverse was read
        image = natural_target("city", (192, 144))
        full = stage.compensate(image, name="city", what="t", verify=False)
        out = solver.solve(image)
        proj = cal.rig.projector
        assert len(out.frames) == 1 and out.frames[0].shape == (proj.intrinsics.height, proj.intrinsics.width, 4)
        assert out.frames[0].dtype == np.uint8 and out.frames[0][..., :3].max() > 10 and out.solve_ms > 0
        ours, theirs = _operator_psnr(solver, out, full.result.target), full.result.report["psnr_operator"]
        assert ours > theirs - 0.5, (ours, theirs)
        # The inverse alone is a fair start, and the refinement step is what closes the gap.
        alone = RealtimeSolver(stage, solver.inverses, refine_steps=0)
        first = _operator_psnr(alone, alone.solve(image), full.result.target)
        assert theirs - 6.0 < first < ours


def test_frame_gather_is_the_warp_and_placement_of_the_input(calibration):
    cal = calibrate_step.read(calibration)
    stage = StageC(cal, StageCOptions())
    comp = stage.compensator
    area = stage.area_for(np.zeros((144, 192, 3), np.float32))
    view = comp.transport.rows(np.flatnonzero(area.mask(comp.camera_size).ravel()))
    proj = cal.rig.projector
    identity = Warp.identity(proj.input_size)
    rng = np.random.default_rng(1)
    warp = replace(identity, w_shifts=rng.normal(0, 0.8, identity.w_shifts.shape))
    zc = rng.random((len(view.texels), 3)).astype(np.float32)
    z = view.expand(zc, np.zeros((proj.input_size[1], proj.input_size[0], 3), np.float32))
    for w in (None, warp):
        expected = proj.frame_from_input(np.clip(z if w is None else w.apply_w(z), 0.0, 1.0))
        gather = FrameGather(view, proj, w)
        assert np.abs(gather(zc) - expected).max() < 1e-5
        levels = gather.levels(zc)
        assert np.abs(levels[..., :3].astype(np.float32) - np.rint(expected * 255)).max() <= 1
        assert (levels[..., 3] == 255).all()


def test_follow_moves_theta_a_small_step_towards_the_cameras_residual(calibration):
    cal = calibrate_step.read(calibration)
    stage = StageC(cal, StageCOptions())
    solver = RealtimeSolver.for_stage(stage)
    out = solver.solve(natural_target("forest", (192, 144)))
    plan = solver._plan(out.area)
    before = solver.theta(out.area).copy()
    predicted = solver.predicted(out)
    cw, ch = solver.camera_size
    capture = np.zeros((ch * cw, 3), np.float32)
    capture[plan.views[0].view.rows] = np.clip(predicted - 0.1, 0.0, 1.0)  # the camera sees 0.1 less than the model
    solver.follow(capture.reshape(ch, cw, 3), out)
    moved = solver.theta(out.area) - before
    lit = predicted.min(axis=1) > 0.2
    assert np.allclose(moved[lit], 0.1 * (0.1 - before[lit]), atol=1e-4)  # 2α(residual − θ), α = 0.05
    with pytest.raises(InverseError, match="must be 192×144"):
        solver.follow(np.zeros((10, 10, 3), np.float32), out)


def test_an_inverse_too_large_for_memory_says_how_much_it_needs(calibration, monkeypatch, tmp_path):
    folder = tmp_path / "cal"
    shutil.copytree(calibration, folder, ignore=shutil.ignore_patterns("inverse.*"))
    monkeypatch.setattr(inverse_step, "free_bytes", lambda: 2 ** 20)
    stage = StageC(calibrate_step.read(folder), StageCOptions())
    with pytest.raises(InverseError, match=r"needs about .* GiB and 0\.0 GiB are free"):
        RealtimeSolver.for_stage(stage)
    assert main(["precompute", str(folder), "--live"]) == 2
    assert not (folder / "inverse.npz").exists()


def test_several_projectors_each_solve_their_share_of_the_blend(two_projector_lab):
    cal_dir = two_projector_lab / "cal"
    assert main(["precompute", str(cal_dir), "--live"]) == 0
    assert (cal_dir / "inverse.npz").is_file() and (cal_dir / "inverse_p2.npz").is_file()
    cal = calibrate_step.read(cal_dir)
    with JointStage(cal, StageCOptions()) as stage:
        solver = RealtimeSolver.for_stage(stage)
        image = natural_target("city", (128, 96))
        full = stage.compensate(image, name="city", what="t")
        out = solver.solve(image)
        assert len(out.frames) == 2
        for frame, proj in zip(out.frames, cal.rig.projectors):
            assert frame.shape == (proj.intrinsics.height, proj.intrinsics.width, 4) and frame[..., :3].max() > 12
        plan = solver._plan(out.area)
        assert plan.keep == [0, 1]
        shares = np.concatenate(plan.shares, axis=1)
        assert np.allclose(shares.sum(axis=1), 1.0) and (shares.min(axis=0) < 0.05).all()  # each fades out
        ours = _operator_psnr(solver, out, full.result.target)
        theirs = full.result.report["psnr_simulated"]
        assert ours > theirs - 1.0, (ours, theirs)


def test_the_lens_blur_box_is_stage_cs_blur_and_its_own_adjoint(calibration):
    """The real-time solve's blur (OpenCV's separable filter on the box around the active texels, between Dr.Jit
    arrays) is the blur stage C's ``T B`` holds; its way back is its adjoint; and its regularised inverse narrows
    it."""
    cal = calibrate_step.read(calibration)
    stage = StageC(cal, StageCOptions())
    comp = stage.compensator
    area = stage.area_for(np.zeros((144, 192, 3), np.float32))
    view = comp.transport.rows(np.flatnonzero(area.mask(comp.camera_size).ravel()))
    sigma = 1.3
    box = LensBlurBox(view, sigma)
    fl = view._float
    iw, ih = comp.transport.input_size
    assert set(view.texels) <= set(box.texels) and len(box.texels) < iw * ih
    rng = np.random.default_rng(2)
    z = rng.random((len(box.texels), 3)).astype(np.float32)
    full = np.zeros((ih * iw, 3), np.float32)
    full[box.texels] = z
    expected = lens_blur(full.reshape(ih, iw, 3), sigma).reshape(-1, 3)[view.texels]
    got = np.asarray(box.to_active(fl(z.ravel()))).reshape(-1, 3)
    assert np.abs(got - expected).max() < 1e-5, np.abs(got - expected).max()
    a = rng.random((len(view.texels), 3)).astype(np.float32)
    back = np.asarray(box.from_active(fl(a.ravel()))).reshape(-1, 3)
    assert float(np.sum(got * a)) == pytest.approx(float(np.sum(z * back)), rel=1e-4)
    g, h = gaussian_taps(sigma), deblur_taps(sigma)
    assert g.sum() == pytest.approx(1.0) and h.sum() == pytest.approx(1.0) and len(g) == len(h) == 11
    spread = np.arange(len(g)) - len(g) // 2
    gh = np.convolve(g, h)
    # g * h is much narrower than g (its second moment: 0.27 of g's at σ 1.3)
    assert float(np.sum((np.arange(len(gh)) - len(gh) // 2) ** 2 * gh)) < 0.4 * float(np.sum(spread ** 2 * g))


def test_a_defocused_projector_is_closer_to_the_target_in_real_time_with_its_blur_held(lab_calibration, tmp_path):
    """The suite's lab with its projector out of focus (σ 1.5 texels, half of it a disk, as the lab blurs), and a
    diagnosis that fitted that blur: ``--effects defocus`` holds it in the real-time solve as in stage C's, and the
    frame it shows is captured measurably closer to the target than the same solve without the blur held."""
    from procam.addon.lab.cycles_device import LabDevice
    from procam.addon.lab.effects import parse_effects
    from procam.addon.lab.truth import LabTruth
    from procam.addon.stages.display_area import fit_target
    from procam.addon.stages.metrics import psnr
    from procam.addon.steps import layout

    cal_dir, _, truth_path = lab_calibration()
    blurred = replace(LabTruth.load(truth_path), effects=parse_effects("defocus=0.5"))
    sigma = float(blurred.effects["defocus"]["sigma"])  # native pixels: the input's texels
    diag = tmp_path / "diag"
    diag.mkdir()
    fitted = {"defocus": {"sigma": sigma}}
    (diag / layout.DIAGNOSIS.manifest).write_text(json.dumps({
        "format": layout.DIAGNOSIS.format, "version": layout.DIAGNOSIS.version, "selected": ["defocus"],
        "selected_params": fitted, "compensation": {"params": fitted},
        "effects": [{"name": "defocus", "params": fitted["defocus"]}]}))
    cal = calibrate_step.read(cal_dir)
    device = device_pipeline(f"lab:{truth_path}", cal, device=LabDevice(blurred))
    image = natural_target("city", (192, 144))
    seen = {}
    try:
        with StageC(cal, StageCOptions(effects="defocus", diagnosis=diag)) as stage:
            said: list[str] = []
            held = RealtimeSolver.for_stage(stage, progress=lambda msg, frac: said.append(msg))
            assert stage.compensator.input_blur == pytest.approx(sigma)
            assert not any("blur" in m for m in said)  # no warning that the blur is left out
            plain = RealtimeSolver(stage, held.inverses, hold_blur=False)
            for name, solver in (("held", held), ("plain", plain)):
                out = solver.solve(image)
                rv = solver._plan(out.area).views[0]
                assert (rv.blur is not None) == (name == "held") and len(rv.texels) > len(rv.view.texels) * (
                    name == "held")
                capture = device.project(out.frames[0][..., :3].astype(np.float32) / 255.0)
                seen[name] = psnr(np.clip(out.area.crop(capture), 0.0, 1.0), fit_target(image, out.area))
    finally:
        device.close()
    # Measured: 26.17 dB held against 25.33 without.
    assert seen["held"] > seen["plain"] + 0.4, seen


def _bench_live_show():
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(
        "procam_bench_live_show", Path(__file__).resolve().parents[1] / "scripts" / "bench_live_show.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    return bench


def test_the_benchmarks_error_flicker_counts_change_beyond_the_targets_own():
    """The live benchmark's flicker measures on a synthetic pan: a capture that moves with its target (a fixed
    error on top) has no error flicker however much the content moves; fresh noise on every capture has
    (E|n₁ − n₂| = 2σ/√π) even on a still target, whose own flicker is nil."""
    bench = _bench_live_show()
    rng = np.random.default_rng(1)
    picture = rng.random((24, 32, 3)).astype(np.float32)
    targets = [np.roll(picture, 3 * i, axis=1) for i in range(6)]
    offset = 0.1 * rng.random(picture.shape).astype(np.float32)
    moving = [t + offset for t in targets]
    assert bench.flicker(targets) > 0.1
    assert bench.flicker(moving) == pytest.approx(bench.flicker(targets), rel=1e-5)
    assert bench.error_flicker(moving, targets) < 1e-7
    sigma = 0.01
    still = [picture] * 40
    noisy = [picture + rng.normal(0.0, sigma, picture.shape).astype(np.float32) for _ in still]
    assert bench.flicker(still) == 0.0
    assert bench.error_flicker(noisy, still) == pytest.approx(2 * sigma / np.sqrt(np.pi), rel=0.05)


def test_a_still_picture_shown_twice_gets_the_same_answer_from_the_first_frame(calibration, monkeypatch):
    """The first frame takes its interreflection from solves of itself before its answer: with one such solve the
    level of the first frames swings (each frame's interreflection is the previous answer's), a flicker of the
    whole picture; with :data:`FIRST_FRAME_SOLVES` the second showing of a still picture changes it far less."""
    from procam.addon.stages import realtime as realtime_stage

    cal = calibrate_step.read(calibration)
    image = natural_target("city", (192, 144))
    swing = {}
    with StageC(cal, StageCOptions()) as stage:
        inverses = RealtimeSolver.for_stage(stage).inverses
        for solves in (1, realtime_stage.FIRST_FRAME_SOLVES):
            monkeypatch.setattr(realtime_stage, "FIRST_FRAME_SOLVES", solves)
            solver = RealtimeSolver(stage, inverses)
            first, second = solver.solve(image), solver.solve(image)
            rv = solver._plan(first.area).views[0]
            swing[solves] = float(np.mean(np.abs(rv.compact(second.inputs[0]) - rv.compact(first.inputs[0]))))
    assert realtime_stage.FIRST_FRAME_SOLVES > 1
    assert swing[realtime_stage.FIRST_FRAME_SOLVES] < 0.3 * swing[1], swing


def test_a_correction_learned_while_following_carries_to_other_pictures(calibration, tmp_path):
    """A camera whose pixels answer with a gain and offset of their own (0.7–1.2, the model's 1 nowhere): followed
    over sixteen frames of a pan over one photograph, the correction it learns (written and read back as
    --correction does) brings another photograph, shown without a camera, far closer to the target than the open
    loop's θ (measured: a mean squared error of 0.00004 against 0.0003)."""
    cal = calibrate_step.read(calibration)
    cw, ch = 192, 144
    yy, xx = np.mgrid[0:ch, 0:cw]
    gain = (0.7 + 0.5 * xx / cw)[..., None] * np.array([1.0, 0.95, 1.05])
    with StageC(cal, StageCOptions()) as stage:
        solver = RealtimeSolver.for_stage(stage)

        def camera(frame) -> np.ndarray:
            rows = solver._plan(frame.area).views[0].view.rows
            image = np.zeros((ch * cw, 3), np.float32)
            image[rows] = solver.predicted(frame)
            return np.clip(gain * image.reshape(ch, cw, 3) + 0.01, 0.0, 1.0).astype(np.float32)

        learn = 0.05 + 0.6 * natural_target("city", (240, 180))  # the camera never clips
        for i in range(16):
            out = solver.solve(np.roll(learn, 4 * i, axis=1))
            solver.follow(camera(out), out)
        sha = calibrate_step.identity(calibration)["sha256"]
        path = solver.save_learned(tmp_path / "learned.npz", sha)
        assert path is not None and path.is_file()
        fresh = RealtimeSolver(stage, solver.inverses)
        assert fresh.load_learned(path, sha) == 1
        other = 0.05 + 0.6 * natural_target("forest", (240, 180))
        plain = RealtimeSolver(stage, solver.inverses)
        errs = {}
        for name, s in (("open", plain), ("learned", fresh)):
            out = s.solve(other)
            target = s._fitted(other, out.area)
            rows = s._plan(out.area).views[0].view.rows
            errs[name] = float(np.mean((camera(out).reshape(-1, 3)[rows] - target) ** 2))
        assert errs["learned"] < 0.3 * errs["open"], errs
        with pytest.raises(InverseError, match="another calibration"):
            fresh.load_learned(path, "0" * 64)
        assert RealtimeSolver(stage, solver.inverses).save_learned(tmp_path / "none.npz", sha) is None
        assert not (tmp_path / "none.npz").exists()


def test_a_surround_is_shown_outside_the_area_and_its_light_counted_inside(calibration):
    """``--surround`` in a live show: the projector's input outside the display area shows the colour (every frame
    pixel of its input region that no texel of the picture reaches, and the picture's own texels whose light lands
    outside the area), and the light that colour spills into the area is taken off what the answer gives there, so
    the picture the model predicts is as close to the target as without a surround."""
    cal = calibrate_step.read(calibration)
    image = natural_target("forest", (192, 144))
    surround = (0.4, 0.2, 0.0)
    results = {}
    for s in (None, surround):
        stage = StageC(cal, StageCOptions(surround=s))
        solver = RealtimeSolver.for_stage(stage)
        out = solver.solve(image)
        plan = solver._plan(out.area)
        results[s] = (solver, out, plan, stage)
    solver, out, plan, stage = results[surround]
    assert plan.surround_light is not None and plan.surround_light.max() > 0.002  # its bounce and edge light
    assert results[None][2].surround_light is None
    proj = cal.rig.projector
    (x0, y0), (iw, ih) = proj.input_offset, proj.input_size
    frame = out.frames[0][..., :3]
    region = frame[y0:y0 + ih, x0:x0 + iw].reshape(-1, 3)
    level = np.rint(np.asarray(surround) * 255).astype(np.uint8)
    # far from the area's texels the input is the surround, exactly; the native frame's margin stays black
    far = ~stage.compensator.area_texels(out.area).reshape(-1)
    assert (region[far] == level).all(axis=1).mean() > 0.9
    margin = np.ones(frame.shape[:2], bool)
    margin[y0:y0 + ih, x0:x0 + iw] = False
    assert margin.any() and (frame[margin] == 0).all()
    # the model's picture inside the area: within 0.3 dB of the one without a surround (the surround's light is
    # counted, not added on top), and the prediction holds that light
    target = results[None][3].compensate(image, name="forest", what="t", verify=False).result.target
    ours = _operator_psnr(solver, out, target)
    plain = _operator_psnr(results[None][0], results[None][1], target)
    assert ours > plain - 0.3, (ours, plain)
    assert np.allclose(solver.predicted(out) - plan.surround_light,
                       sum(rv.light(zc) for rv, zc in zip(plan.views, out.inputs)), atol=1e-5)
