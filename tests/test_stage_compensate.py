"""Stage C (compensation) and the target display area, on a small lab capture set.

The calibration is built from the lab's truth (rig, surface) and an identity
warp, so these tests do not depend on stages A and B. Sizes are tiny (camera
192×144, input 180×180) and iteration counts short; full-resolution timings are
benchmarks, not tests.
"""

from __future__ import annotations

import importlib.util
import json
import sys
import types
import warnings
from dataclasses import replace

import numpy as np
import pytest

from procam.addon.errors import CaptureError, ImageError
from procam.addon.stages.compensate import (DEFAULT_SCHEDULE, SCHEDULES, BiasModel, Cancelled, CompensationError,
                                            Compensator, Schedule, area_psnr, get_schedule, matched_alpha, plateaued,
                                            split_iterations)
from procam.addon.stages.display_area import (DisplayArea, DisplayAreaError, TargetAspectWarning, choose_area,
                                              fit_target, largest_rectangle, load_target, parse_area)

ITER_Z, ITER_JOINT = 30, 30


def _identity_warp(size):
    if importlib.util.find_spec("procam.addon.stages.warp") is None:
        return None
    from procam.addon.stages.warp import Warp

    return Warp.identity(size)


def _target(w: int = 160, h: int = 120) -> np.ndarray:
    """A smooth colourful target inside what the projector can reach on the lab surface."""
    from procam.addon.capture.patterns import smooth_random

    return (0.05 + 0.4 * smooth_random((w, h), 3, 20.0)).astype(np.float32)


@pytest.fixture(scope="module")
def setup(lab_set):
    from procam.addon.capture.format import CaptureSet
    from procam.addon.lab.truth import LabTruth
    from procam.addon.stages.calibrate import Calibration

    captures_dir, truth_path = lab_set()
    truth = LabTruth.load(truth_path)  # tests are evaluation code: they may read the truth
    cal = Calibration(truth.rig, truth.surface, _identity_warp(truth.rig.projector.input_size), str(captures_dir))
    captures = CaptureSet.load(captures_dir, verify_images=False)
    area = choose_area(cal, aspect=4 / 3, captures=captures)
    comp = Compensator(cal, bounces=1, spp=4, seed=0)
    return types.SimpleNamespace(cal=cal, truth=truth, truth_path=truth_path, captures=captures, area=area,
                                 comp=comp, captures_dir=captures_dir)


@pytest.fixture(scope="module")
def open_loop(setup):
    bias = setup.comp.estimate_bias(setup.captures)
    res = setup.comp.run(_target(), setup.area, schedule="fast", iterations_z=ITER_Z, iterations_joint=ITER_JOINT,
                         open_loop_theta=bias, name="smooth")
    return bias, res


def test_open_loop_theta_leaves_out_capture_values_given_as_nan(setup):
    """Seen through a glossy model, what the camera clipped in the highlight comes as NaN (no light can be read
    back there): θ leaves those values out and stays finite, and every other pixel's θ is unchanged."""
    class WhiteWithHole:
        def __init__(self, captures):
            self._c, self.path, self.camera, self.projector = (captures, captures.path, captures.camera,
                                                               captures.projector)

        def entries_of(self, kind):
            return self._c.entries_of(kind)

        def pattern(self, kind, **filters):
            return self._c.pattern(kind, **filters)

        def image(self, kind, **filters):
            img = np.array(self._c.image(kind, **filters))
            if kind == "white":
                img[40:50, 60:70] = np.nan
            return img

    full = setup.comp.estimate_bias(setup.captures)
    holed = setup.comp.estimate_bias(WhiteWithHole(setup.captures))
    assert holed.kind == full.kind and np.isfinite(holed.theta).all()
    assert holed.gain is None or np.isfinite(holed.gain).all()
    keep = np.ones(full.theta.shape[:2], bool)
    keep[40:50, 60:70] = False
    np.testing.assert_allclose(holed.theta[keep], full.theta[keep], atol=1e-6)
    assert not np.allclose(holed.theta[~keep], full.theta[~keep], atol=1e-4)


# -- display area ----------------------------------------------------------------------------------

def test_largest_rectangle_on_a_known_mask():
    mask = np.zeros((100, 160), bool)
    mask[10:90, 20:150] = True  # 130×80 free
    x, y, w, h = largest_rectangle(mask, 4 / 3)
    assert (w, h) == (107, 80) and x >= 20 and x + w <= 150 and y == 10
    assert mask[y:y + h, x:x + w].all()
    assert largest_rectangle(np.zeros((10, 10), bool), 1.0) is None


def test_auto_area_lies_where_the_projector_lights(setup):
    a = setup.area
    assert a.source == "auto" and abs(a.aspect - 4 / 3) < 0.05
    cw, ch = setup.cal.rig.camera.intrinsics.size
    assert a.width * a.height > 0.15 * cw * ch
    lit = setup.comp.white().mean(axis=2) > 0.05
    assert a.crop(lit).all()


def test_area_errors(setup):
    with pytest.raises(DisplayAreaError, match="outside"):
        choose_area(setup.cal, aspect=1.0, user=(150, 100, 100, 100))
    with pytest.raises(DisplayAreaError, match="x,y,width,height"):
        parse_area("10,20,30")
    assert parse_area(" 1, 2,30,40") == (1, 2, 30, 40)
    user = choose_area(setup.cal, aspect=1.0, user=(10, 10, 40, 30))
    assert user == DisplayArea(10, 10, 40, 30, "user")
    from_set = choose_area(setup.cal, aspect=1.0, captures=types.SimpleNamespace(target_area=(5, 6, 70, 50)))
    assert from_set == DisplayArea(5, 6, 70, 50, "capture-set")


def test_targets_fit_and_bad_targets(tmp_path):
    area = DisplayArea(0, 0, 40, 30)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert fit_target(np.full((60, 80, 3), 0.5, np.float32), area).shape == (30, 40, 3)
    with pytest.warns(TargetAspectWarning, match="stretched"):
        fit_target(np.full((80, 80, 3), 0.5, np.float32), area)
    bad = np.full((30, 40, 3), 0.5, np.float32)
    bad[3, 4, 1] = np.nan
    with pytest.raises(ImageError, match="NaN"):
        fit_target(bad, area)
    with pytest.raises(ImageError, match="not found"):
        load_target(tmp_path / "missing.png")
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(ImageError, match="empty"):
        load_target(tmp_path / "empty.png")
    (tmp_path / "junk.png").write_bytes(b"not an image at all")
    with pytest.raises(ImageError, match="cannot read"):
        load_target(tmp_path / "junk.png")
    import cv2

    cv2.imwrite(str(tmp_path / "grey8.png"), np.full((8, 8, 3), 128, np.uint8))
    img, note = load_target(tmp_path / "grey8.png")
    assert "sRGB" in note and abs(float(img.mean()) - 0.2158) < 2e-3  # sRGB 128 → linear 0.216


# -- stage C -------------------------------------------------------------------------------------

def test_open_loop_compensation(setup, open_loop):
    bias, res = open_loop
    area = setup.area
    assert res.mode == "open-loop" and res.captures == 0
    assert bias.kind in ("mean", "affine")
    assert res.report["bias"]["held_out_rmse"][bias.kind] <= res.report["bias"]["held_out_rmse"]["no_bias"]
    losses = np.array(res.losses)
    # The default schedule's z phases may end early on a plateau; the θ-fixed phase runs in full.
    assert len(losses) == res.report["iterations"]["total"] <= ITER_Z + ITER_JOINT and np.all(np.isfinite(losses))
    assert res.report["iterations"]["joint"] == ITER_JOINT
    # The fast schedule's fixed-point start leaves Adam near the noise floor, so compare the model's start and end.
    assert res.report["psnr_simulated"] > res.report["psnr_simulated_start"] + 0.5
    # Closer to the target than the target projected with geometry only (no photometric compensation).
    uncompensated = bias.predict(setup.comp.simulate(setup.comp.initial_input(res.target, how="geometric")))
    before, after = area_psnr(uncompensated, res.target, area), area_psnr(res.simulated, res.target, area)
    print(f"open loop, simulated PSNR: uncompensated {before:.2f} dB, compensated {after:.2f} dB")
    assert after > before + 5.0 and after > 30.0
    # Clamps: 0 ≤ z ≤ 1 and Eq. 14.
    assert res.z.min() >= 0.0 and res.z.max() <= 1.0
    assert np.all(res.theta <= res.simulated_raw + 1e-6) and np.all(res.theta >= res.simulated_raw - 1 - 1e-6)
    # Output geometry: x* at the input size, and in the native frame where the capture set places it.
    proj = setup.cal.rig.projector
    assert res.x_input.shape == (proj.input_size[1], proj.input_size[0], 3)
    assert res.x_frame.shape == (proj.intrinsics.height, proj.intrinsics.width, 3)
    x0, y0 = proj.input_offset
    assert np.array_equal(res.x_frame[y0:y0 + res.x_input.shape[0], x0:x0 + res.x_input.shape[1]], res.x_input)
    assert res.x_frame.sum() == pytest.approx(res.x_input.sum(), rel=1e-6)


def test_closed_loop_improves_the_capture(setup, open_loop):
    from procam.addon.lab.cycles_device import LabDevice

    device = LabDevice(setup.truth)
    comp, area = setup.comp, setup.area
    res = comp.run(_target(), area, device=device, iterations_z=40, iterations_joint=40, capture_every=10,
                   name="smooth")
    assert res.mode == "closed-loop" and res.captures == 4
    assert np.all(res.theta <= res.simulated_raw + 1e-6) and np.all(res.theta >= res.simulated_raw - 1 - 1e-6)
    assert res.z.min() >= 0.0 and res.z.max() <= 1.0
    proj = comp.rig.projector
    captured = device.project(res.x_frame)
    geometric = device.project(proj.frame_from_input(comp.warp_w(comp.initial_input(res.target, how="geometric"))))
    one_shot = device.project(proj.frame_from_input(comp.warp_w(comp.initial_input(res.target))))
    p_comp, p_unc, p_one = (area_psnr(y, res.target, area) for y in (captured, geometric, one_shot))
    print(f"closed loop, captured PSNR: uncompensated {p_unc:.2f} dB, one-shot inverse {p_one:.2f} dB, "
          f"compensated {p_comp:.2f} dB (simulated {res.report['psnr_simulated']:.2f} dB)")
    assert p_comp > p_unc + 5.0
    assert p_comp > p_one


# -- schedules ------------------------------------------------------------------------------------

def test_schedule_rules():
    assert not plateaued([1.0, 0.9, 0.8, 0.7], 2, 0.02)
    assert plateaued([1.0, 0.8, 0.5, 0.5, 0.49, 0.5], 2, 0.02)
    assert not plateaued([0.5] * 3, 2, 0.02) and not plateaued([0.5] * 10, 0, 0.02)
    # α matched to the capture interval gives each capture the weight it has in the paper's rule.
    assert matched_alpha(20) == pytest.approx(0.01)
    assert (1 - 2 * matched_alpha(5)) ** 5 == pytest.approx(0.98 ** 20)
    fast = get_schedule("fast")
    assert fast.theta_rate == matched_alpha(fast.capture_interval)
    assert Schedule("t", alpha=None, capture_every=20).theta_rate == pytest.approx(0.01)
    cosine = Schedule("t", lr=0.01, lr_end=0.001)
    lrs = [cosine.learning_rate(i, 50) for i in range(50)]
    assert lrs[0] == pytest.approx(0.01) and lrs[-1] == pytest.approx(0.001)
    assert all(a >= b for a, b in zip(lrs, lrs[1:]))
    assert fast.learning_rate(149, 150) == fast.lr  # no decay in the fast schedule
    # A number of captures is spread over whatever joint iterations there are.
    assert fast.capture_interval == 10 and replace(fast, iterations_joint=120).capture_interval == 8
    assert Schedule("t", iterations_joint=7, captures=3).capture_interval == 3
    assert (fast.fixed_point, fast.fixed_point_joint, fast.fixed_point_spp, fast.crop, fast.iterations_z) == \
        (8, 2, 16, True, 0)
    assert DEFAULT_SCHEDULE == "transport" and get_schedule(DEFAULT_SCHEDULE) is get_schedule("transport")
    # Splitting a total iteration count follows the schedule: the paper's 200:300, all joint for fast.
    assert split_iterations(100, "paper") == (40, 60) and split_iterations(100, "fast") == (0, 100)
    assert split_iterations(None) == (None, None)
    # The paper's schedule stays reachable by name, unchanged.
    paper = get_schedule("paper")
    assert (paper.iterations_z, paper.iterations_joint, paper.lr, paper.alpha, paper.lr_end) == (200, 300, 0.01,
                                                                                                  0.01, None)
    assert (paper.plateau, paper.coarse, paper.spp_z, paper.reference_spp, paper.captures) == (0, 1.0, None, 16,
                                                                                                None)
    assert (paper.fixed_point, paper.fixed_point_joint, paper.crop) == (0, 0, False)
    assert paper.capture_interval == 20 and paper.theta_rate == 0.01
    assert set(SCHEDULES) == {"fast", "paper", "transport"}
    # Stage C on the light-transport operator: solver steps before the first capture, then 2 after each of 15,
    # θ moving a third of the way to each new residual as in fast; Mitsuba verifies only when asked.
    transport = get_schedule("transport")
    assert transport.transport and not fast.transport and not paper.transport
    assert (transport.iterations_z, transport.iterations_joint, transport.captures) == (10, 30, 15)
    assert transport.capture_interval == 2 and 1 - (1 - 2 * transport.theta_rate) ** 2 == pytest.approx(1 - 0.98 ** 20)
    assert not transport.verify and fast.verify
    assert split_iterations(100, "transport") == (25, 75)
    for bad, msg in ((dict(iterations_z=-1), "iterations_z"), (dict(capture_every=0), "capture_every"),
                     (dict(lr_end=0.1), "lr_end"), (dict(coarse=0.01), "coarse"), (dict(spp_z=0), "spp_z"),
                     (dict(captures=0), "captures"), (dict(reference_spp=8), "square"),
                     (dict(alpha=0.7), "α")):
        with pytest.raises(CompensationError, match=msg):
            get_schedule(Schedule("bad", **bad))
    with pytest.raises(CompensationError, match="unknown schedule"):
        get_schedule("fastest")


def test_paper_schedule_runs_every_iteration(setup):
    res = setup.comp.run(_target(), setup.area, schedule="paper", iterations_z=4, iterations_joint=3,
                         use_bias=False)
    assert len(res.losses) == 7 and [p["phase"] for p in res.report["phases"]] == ["z", "z, θ fixed"]
    assert res.report["schedule"]["name"] == "paper" and res.report["phases"][0]["stopped"] == "limit"


def test_coarse_to_fine_and_plateau_stop(setup):
    comp = setup.comp
    # A tolerance no loss can meet (halving every 2 iterations): each z phase stops after 2 windows.
    sched = Schedule("t", iterations_z=20, iterations_joint=3, plateau=2, plateau_tol=0.5, spp_z=1, coarse=0.5,
                     iterations_coarse=10)
    res = comp.run(_target(), setup.area, schedule=sched, use_bias=False)
    cw, ch = comp.camera_size
    coarse, fine, last = res.report["phases"]
    assert coarse["phase"] == "coarse" and coarse["camera"] == [round(cw / 2), round(ch / 2)]
    assert coarse["iterations"] == 4 and coarse["stopped"] == "plateau" and coarse["spp"] == 1
    assert fine["camera"] == [cw, ch] and fine["iterations"] == 4 and fine["stopped"] == "plateau"
    assert last["iterations"] == 3 and len(res.losses) == 11 == res.report["iterations"]["total"]
    # The answer has the input's and the camera's sizes whatever resolution the optimisation ran at.
    assert res.z.shape == (comp.ih, comp.iw, 3) and res.simulated.shape == (ch, cw, 3)
    # The coarse model is built once per compensator (its scene and kernels serve every target).
    assert comp.model_at(0.5) is comp.model_at(0.5) and comp.model_at(1.0) is comp.model
    small = comp.downsample(np.ones((ch, cw, 3), np.float32), (cw // 2, ch // 2))
    assert small.shape == (ch // 2, cw // 2, 3) and np.allclose(small, 1.0)


def test_fixed_point_phases(setup):
    """Forward-only fixed-point steps bring the model closer to the target than the one-shot inverse alone, and
    in the joint phase they run after every capture."""
    from procam.addon.lab.cycles_device import LabDevice

    comp, area = setup.comp, setup.area
    sched = Schedule("t", iterations_z=0, iterations_joint=0, fixed_point=6)
    start = comp.run(_target(), area, schedule=replace(sched, fixed_point=0), use_bias=False)
    res = comp.run(_target(), area, schedule=sched, use_bias=False)
    assert res.report["phases"][0]["phase"] == "fixed-point" and res.report["iterations"]["fixed_point"] == 6
    print(f"model PSNR: one-shot inverse {start.report['psnr_simulated']:.2f} dB, after 6 fixed-point steps "
          f"{res.report['psnr_simulated']:.2f} dB")
    assert res.report["psnr_simulated"] > start.report["psnr_simulated"] + 0.5
    with LabDevice(setup.truth) as device:
        res = comp.run(_target(), area, device=device, schedule=replace(sched, fixed_point=2, iterations_joint=4,
                                                                        captures=2, fixed_point_joint=1))
    assert res.captures == 2 and res.report["iterations"]["fixed_point"] == 2 + 2 * 1
    # Rendering only the display area: the same optimisation on the pixels the loss sees; θ is 0 outside it.
    with LabDevice(setup.truth) as device:
        cropped = comp.run(_target(), area, device=device, schedule=replace(sched, fixed_point=2, iterations_joint=4,
                                                                            captures=2, fixed_point_joint=1,
                                                                            crop=True))
    assert cropped.report["phases"][-1]["window"] == (area.x, area.y, area.width, area.height)
    outside = ~area.mask(comp.camera_size)
    assert np.all(cropped.theta[outside] == 0) and np.any(cropped.theta[~outside] != 0)
    assert cropped.report["psnr_simulated"] > start.report["psnr_simulated"]
    for bad in (0.0, 1.5):
        with pytest.raises(CompensationError, match="fixed_point_step"):
            get_schedule(replace(sched, fixed_point_step=bad))


def test_no_bias_ablation_and_reused_kernels(setup):
    res = setup.comp.run(_target(), setup.area, iterations_z=5, iterations_joint=5, use_bias=False)
    assert res.mode == "none" and np.array_equal(res.theta, np.zeros_like(res.theta))


def test_bad_inputs_are_clear_errors(setup):
    comp, area = setup.comp, setup.area
    bad = _target()
    bad[5, 5] = np.nan
    with pytest.raises(ImageError, match="NaN"):
        comp.run(bad, area, iterations_z=1, iterations_joint=0, use_bias=False)
    with pytest.raises(DisplayAreaError, match="outside"):
        comp.run(_target(), DisplayArea(150, 100, 100, 80), iterations_z=1, iterations_joint=0, use_bias=False)
    with pytest.raises(CompensationError, match="learning rate"):
        comp.run(_target(), area, lr=float("nan"), use_bias=False)

    class Broken:
        projector = comp.rig.projector

        def __init__(self, image):
            self.image = image

        def project(self, frame):
            return self.image

        def close(self):
            pass

    cw, ch = comp.camera_size
    with pytest.raises(CaptureError, match="NaN"):
        comp.run(_target(), area, device=Broken(np.full((ch, cw, 3), np.nan, np.float32)), iterations_z=0,
                 iterations_joint=1)
    with pytest.raises(CaptureError, match="calibration's camera"):
        comp.run(_target(), area, device=Broken(np.zeros((ch + 1, cw, 3), np.float32)), iterations_z=0,
                 iterations_joint=1)
    # A simulation that diverges: the error names what went non-finite.
    real, calls = comp.model.render_dr, []

    def diverging(frame, **kw):  # the first render (the starting point's simulation) is fine, later ones are not
        calls.append(1)
        return real(frame, **kw) * (1.0 if len(calls) == 1 else float("nan"))

    comp.model.render_dr = diverging
    try:
        with pytest.raises(CompensationError, match="simulation"):
            comp.run(_target(), area, schedule="paper", iterations_z=2, iterations_joint=0, use_bias=False)
    finally:
        comp.model.render_dr = real
    with pytest.raises(Cancelled, match="cancelled"):
        comp.run(_target(), area, iterations_z=3, iterations_joint=0, use_bias=False, cancel=lambda: True)
    with pytest.raises(CompensationError, match="open_loop_theta"):
        comp.run(_target(), area, iterations_z=1, iterations_joint=0, open_loop_theta=np.zeros((3, 3, 3)))


def test_run_with_given_theta(setup, open_loop):
    bias, _ = open_loop
    theta = np.zeros_like(bias.theta)
    res = setup.comp.run(_target(), setup.area, schedule="fast", iterations_z=3, iterations_joint=2,
                         open_loop_theta=theta)
    assert res.mode == "open-loop" and res.report["bias"]["kind"] == "given" and len(res.losses) == 5
    assert isinstance(BiasModel(theta).predict(res.simulated_raw), np.ndarray)


# -- the command ---------------------------------------------------------------------------------

def _write_calibration(cal, folder):
    from procam.addon.steps import calibrate as calibrate_step

    folder.mkdir()
    calibrate_step.write(folder, cal, {})


def test_cli_round_trip(setup, tmp_path, monkeypatch, capsys):
    from procam.addon.cli.app import main
    from procam.addon.imageio import read_image, write_image

    if importlib.util.find_spec("procam.addon.stages.warp") is None:  # stage B not merged yet: a stub suffices
        stub = types.ModuleType("procam.addon.stages.warp")
        stub.Warp = type("Warp", (), {"from_dict": staticmethod(lambda d: None)})
        monkeypatch.setitem(sys.modules, "procam.addon.stages.warp", stub)
    cal_dir = tmp_path / "cal"
    _write_calibration(setup.cal, cal_dir)
    write_image(tmp_path / "a.png", _target())
    write_image(tmp_path / "b.png", _target(120, 120) * 0.9)
    out = tmp_path / "out"
    args = ["compensate", str(cal_dir), str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--out", str(out),
            "--iterations", "6", "--spp", "1", "--seed", "3", "--schedule", "fast"]
    assert main(args) == 0
    doc = json.loads((out / "compensation.json").read_text())
    assert doc["mode"] == "open-loop" and doc["complete"] and doc["iterations"] == {"total": 6, "z": 0, "joint": 6}
    proj, cam = setup.cal.rig.projector, setup.cal.rig.camera.intrinsics
    for t, name in zip(doc["targets"], ("a", "b")):
        assert t["name"] == name and t["status"] == "done" and len(t["losses"]) == 6 and t["seconds"] > 0
        assert read_image(out / t["input"]).shape == (proj.input_size[1], proj.input_size[0], 3)
        assert read_image(out / t["frame"]).shape == (proj.intrinsics.height, proj.intrinsics.width, 3)
        assert read_image(out / t["simulated"]).shape == (cam.height, cam.width, 3)
    # b is square: its automatic area has another aspect ratio than a's.
    assert doc["targets"][1]["area"]["width"] == doc["targets"][1]["area"]["height"]
    capsys.readouterr()
    # Never overwritten without --force; a missing target or an area outside the image: exit 2, nothing written.
    assert main(args) == 2 and "--force" in capsys.readouterr().err
    for extra, msg in ((["--area", "180,10,50,50"], "outside"), ([], "not found")):
        bad = ["compensate", str(cal_dir), str(tmp_path / ("a.png" if extra else "missing.png")),
               "--out", str(tmp_path / "bad"), "--iterations", "2", *extra]
        assert main(bad) == 2 and msg in capsys.readouterr().err
        assert not (tmp_path / "bad").exists()
    # Closed loop through the lab device, replacing the folder with --force.
    assert main(args + ["--force", "--iterations", "3", "--area", "40,30,100,75", "--capture-every", "1",
                        "--device", f"lab:{setup.truth_path}"]) == 0
    doc = json.loads((out / "compensation.json").read_text())
    assert doc["mode"] == "closed-loop" and doc["device"].startswith("lab:") and doc["capture_every"] == 1
    assert doc["area"] == {"x": 40, "y": 30, "width": 100, "height": 75, "source": "user"}
    assert [t["captures"] for t in doc["targets"]] == [3, 3]  # the fast schedule's 3 iterations are all joint
