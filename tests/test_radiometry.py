"""Each camera pixel's own radiometric model (stages/radiometry.py): measured from flat captures, judged on held-out
ones, and stage C working through it on a lab of other forms.

The synthetic rig: every pixel has its own colour mixing (drifting across the frame), its own response curve per
channel (a power law whose exponent drifts, which no piecewise-linear curve holds exactly) and its own black; the
model's white is a painted albedo. Pure numpy for the model; the last tests render a small lab.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from procam.addon.capture.targets import natural_target
from procam.addon.cli.app import main
from procam.addon.errors import CalibrationError
from procam.addon.imageio import write_image
from procam.addon.stages.radiometry import RadiometryPatterns, decision_region, fit_pixel_radiometry, inverse3

W, H = 64, 48
LEVELS = (0.25, 0.5, 0.75)


def _rig(seed: int = 0):
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 1.0, W, dtype=np.float32)[None, :, None]
    albedo = (0.5 + 0.4 * rng.random((H, W, 3))).astype(np.float32)  # the model's white ŵ
    gamma = (1.6 + 0.8 * x + np.array([0.0, 0.2, -0.2], np.float32)) * np.ones((H, 1, 1), np.float32)
    mix = np.eye(3, dtype=np.float32)[None, None] + (0.05 + 0.15 * x[..., None]) * \
        np.array([[0, 1, 0.5], [1, 0, 1], [0.3, 1, 0]], np.float32)[None, None]
    mix = mix * albedo[..., :, None] * np.ones((H, W, 1, 1), np.float32)  # camera channel j ← primary k
    black = np.full((H, W, 3), 0.02, np.float32)

    def camera(v: np.ndarray, noise: float = 0.0) -> np.ndarray:
        r = np.power(np.clip(v, 0, 1), gamma)
        c = black + np.einsum("...jk,...k->...j", mix, r)
        return (c + rng.normal(0, noise, c.shape)).astype(np.float32)

    return albedo, camera


def _fit(camera, albedo, noise: float = 0.0):
    ramp = np.broadcast_to(np.linspace(0, 1, W, dtype=np.float32)[None, :], (H, W))
    ramps = {}
    for k in range(3):
        v = np.zeros((H, W, 3), np.float32)
        v[..., k] = ramp
        ramps[k] = (camera(v, noise), ramp)
    greys = {lv: camera(np.full((H, W, 3), lv, np.float32), noise) for lv in LEVELS}
    return fit_pixel_radiometry(camera(np.zeros((H, W, 3)), noise), camera(np.ones((H, W, 3)), noise), greys,
                                ramps, albedo)


def test_the_per_pixel_model_predicts_held_out_patterns_of_a_rig_no_global_model_holds():
    albedo, camera = _rig()
    model = _fit(camera, albedo)
    rng = np.random.default_rng(3)
    v = rng.random((H, W, 3)).astype(np.float32)  # a held-out texture, as input levels
    seen = camera(v)
    err = np.abs(model.to_camera(v * albedo) - seen)[8:-8, 8:-8]
    naive = np.abs(np.clip(v * albedo, 0, 1) - seen)[8:-8, 8:-8]  # the model's light as the camera's
    assert err.mean() < 0.015 < 0.05 < naive.mean(), (err.mean(), naive.mean())  # (a power law between 4 knots)
    # to_light undoes to_camera: the light stage C must simulate for what the camera should see
    light = model.to_light(seen)
    truth = v * albedo
    assert np.abs(light - truth)[8:-8, 8:-8].mean() < 0.25 * np.abs(seen - truth)[8:-8, 8:-8].mean()
    shown = (light > 0).all(axis=2)  # (a colour the model puts outside the primaries' gamut is clipped at 0)
    assert shown.mean() > 0.75  # (uniform random levels: a channel near 0 in a fifth of the pixels)
    assert np.allclose(model.to_camera(light)[shown], np.clip(seen, 0, 1)[shown], atol=1e-4)
    # every curve increases, from 0 to 1
    assert (np.diff(model.curves, axis=-1) > 0).all() and np.allclose(model.curves[..., -1], 1.0)


def test_noise_in_the_flat_captures_is_smoothed_not_carried_into_the_model():
    albedo, camera = _rig(1)
    clean, noisy = _fit(camera, albedo), _fit(camera, albedo, noise=0.01)
    v = np.random.default_rng(4).random((H, W, 3)).astype(np.float32)
    diff = np.abs(clean.to_camera(v * albedo) - noisy.to_camera(v * albedo))[8:-8, 8:-8]
    assert diff.mean() < 0.006, diff.mean()  # below the captures' own noise (0.01 per value)


def test_the_decision_region_keeps_the_well_lit_interior_only():
    white = np.zeros((H, W, 3), np.float32)
    white[10:40, 10:54] = 0.8
    region = decision_region(white)
    assert region.any() and not region[:18].any() and not region[:, :18].any() and region[25, 32]


class _Set:
    """A capture set's entries, as RadiometryPatterns reads them."""

    def __init__(self, entries):
        self.entries = entries

    def entries_of(self, kind):
        return [e for e in self.entries if e.kind == kind]


def _entry(kind, name, **params):
    from procam.addon.capture.format import Entry

    return Entry(f"{name}.png", kind, name, params, pattern=f"{name}.png")


def test_a_set_without_ramps_says_why_the_model_cannot_be_measured():
    full = [_entry("black", "black"), _entry("white", "white"),
            *[_entry("validation", f"g{lv}", pattern="grey", level=lv) for lv in (*LEVELS, 1.0)],
            *[_entry("validation", f"r{c}", pattern="ramp", channel=c) for c in "rgb"],
            _entry("validation", "rand", pattern="random", seed=0)]
    got = RadiometryPatterns.of(_Set(full))
    assert not isinstance(got, str) and sorted(got.greys) == list(LEVELS) and sorted(got.ramps) == [0, 1, 2]
    assert [e.name for e in got.held_out] == ["rand"]
    why = RadiometryPatterns.of(_Set([e for e in full if not e.name.startswith("r")]))
    assert why == "the capture set lacks a ramp in each of r, g and b and random textures to judge it on", why


@pytest.fixture(scope="module")
def other_forms_calibration(tmp_path_factory):
    """A small lab of other forms (lab/other_forms.py) and its calibration from the truth (tests may read it)."""
    from procam.addon.lab.lab import run_lab
    from procam.addon.lab.truth import LabTruth, make_truth
    from procam.addon.stages.calibrate import Calibration
    from procam.addon.stages.warp_model import Warp
    from procam.addon.steps import calibrate as calibrate_step

    root = tmp_path_factory.mktemp("other-forms")
    truth = make_truth("curve", effects="noise=0.4", samples=4, camera_size=(160, 120), projector_size=(200, 150),
                       other_forms=1.0)
    run_lab(truth, root / "captures", truth_path=root / "truth.json", graycode=False)
    truth = LabTruth.load(root / "truth.json")
    cal = Calibration(truth.rig, truth.surface, Warp.identity(truth.rig.projector.input_size), str(root / "captures"))
    (root / "cal").mkdir()
    calibrate_step.write(root / "cal", cal, {})
    return root


def _target(path):
    y, x = np.mgrid[0:90, 0:120].astype(np.float32)
    img = np.stack([0.3 + 0.25 * np.sin(x / 9), 0.35 + 0.2 * np.cos(y / 7), 0.3 + 0.002 * (x + y)], axis=2)
    write_image(path, np.clip(img, 0, 1))
    return path


def _compensate_and_evaluate(root, radiometry, target):
    from procam.addon.steps import compensate as compensate_step
    from procam.addon.steps import evaluate as evaluate_step
    from procam.addon.steps.stage_c import StageCOptions

    out = root / f"comp-{radiometry}"
    compensate_step.run(compensate_step.CompensateOptions(
        root / "cal", (target,), out, stage_c=StageCOptions(radiometry=radiometry, iterations=40, range="auto")))
    ev = root / f"eval-{radiometry}"
    evaluate_step.run(evaluate_step.EvaluateOptions(root / "cal", out, (target,), device=f"lab:{root / 'truth.json'}",
                                                    out=ev, repeat=False))
    doc = json.loads((out / "compensation.json").read_text())
    return doc, json.loads((ev / "metrics.json").read_text())["mean"]["psnr"]


def test_on_a_rig_of_other_forms_the_open_loop_chooses_and_gains_from_the_per_pixel_model(other_forms_calibration):
    root = other_forms_calibration
    target = _target(root / "target.png")
    doc, psnr_auto = _compensate_and_evaluate(root, "auto", target)
    rec = doc["radiometry"]
    assert rec["used"] == "pixel" and rec["rule"] == "auto", rec
    assert rec["held_out_rmse"]["pixel"] < rec["held_out_rmse"]["global"] and rec["held_out"], rec
    assert doc["open_loop_bias"]["kind"] == "pixel"
    from procam.addon.steps import compensate as compensate_step

    lines = compensate_step.summary(root / "comp-auto").lines
    assert any(line.startswith("radiometry: each camera pixel's own") for line in lines), lines
    doc, psnr_global = _compensate_and_evaluate(root, "global", target)
    assert doc["radiometry"] == {"used": "global", "rule": "global"}
    assert psnr_auto > psnr_global + 1.0, (psnr_auto, psnr_global)


def test_pixel_radiometry_is_refused_clearly_where_the_captures_cannot_give_it(other_forms_calibration):
    from procam.addon.stages.compensate import Compensator
    from procam.addon.stages.radiometry import choose_radiometry
    from procam.addon.steps import calibrate as calibrate_step

    cal = calibrate_step.read(other_forms_calibration / "cal")
    captures = calibrate_step.captures_of(cal)
    stripped = _Set([e for e in captures.entries if e.params.get("pattern") != "ramp"])
    with pytest.raises(CalibrationError, match="--radiometry global"):
        choose_radiometry(Compensator(cal, spp=2), stripped, "pixel")
    model, record = choose_radiometry(Compensator(cal, spp=2), stripped, "auto")
    assert model is None and record["used"] == "global" and "ramp" in record["reason"]


def test_several_projectors_each_get_their_own_per_pixel_model_in_the_open_loop(two_projector_lab):
    """Two projectors side by side, projector 2 alone with a tone curve no global model holds: each projector's
    model is measured from its own flats and judged on its own held-out captures, the rig takes them together
    (pooled), θ is zero, and the picture through the lab is better than through the global models. A closed loop
    keeps the global models unless asked (then it starts from the per-pixel answer); --effects keeps them and refuses
    --radiometry pixel with the reason."""
    from procam.addon.stages.compensate import CompensationError
    from procam.addon.steps import calibrate as calibrate_step
    from procam.addon.steps.projectors import JointStage
    from procam.addon.steps.stage_c import StageCOptions

    root = two_projector_lab
    cal = calibrate_step.read(root / "cal")
    with JointStage(cal, StageCOptions(spp=2)) as stage:
        record = stage.choose_radiometry()
        assert record["used"] == "pixel" and len(record["projectors"]) == 2 and stage.pixels is not None
        per = [r["held_out_rmse"] for r in record["projectors"]]
        assert per[1]["pixel"] < 0.5 * per[1]["global"]  # the tone curve: the global models miss it
        assert record["held_out_rmse_pooled"]["pixel"] < record["held_out_rmse_pooled"]["global"]
        assert stage.estimate_bias() is stage.biases and all(b.kind == "pixel" and not b.theta.any()
                                                             for b in stage.biases)
        assert stage.black is None
    target = root / "city.png"
    write_image(target, natural_target("city", (96, 72)))
    psnr = {}
    for rule in ("global", "auto"):
        assert main(["compensate", str(root / "cal"), str(target), "--radiometry", rule, "--spp", "2",
                     "--out", str(root / f"comp-{rule}")]) == 0
        doc = json.loads((root / f"comp-{rule}" / "compensation.json").read_text())
        assert doc["radiometry"]["used"] == ("global" if rule == "global" else "pixel")
        assert main(["evaluate", str(root / "cal"), "--inputs", str(root / f"comp-{rule}"), "--targets", str(target),
                     "--device", f"lab:{root / 'lab.truth.json'}", "--out", str(root / f"eval-{rule}")]) == 0
        psnr[rule] = json.loads((root / f"eval-{rule}" / "metrics.json").read_text())["targets"][0]["psnr"]
    assert psnr["auto"] > psnr["global"], psnr
    device = f"lab:{root / 'lab.truth.json'}"
    with JointStage(cal, StageCOptions(device=device, spp=2)) as stage:
        record = stage.choose_radiometry()
        assert record["used"] == "global" and "closed loop" in record["reason"] and stage.pixels is None
    with JointStage(cal, StageCOptions(device=device, spp=2, radiometry="pixel")) as stage:
        record = stage.choose_radiometry()
        assert record["used"] == "pixel" and "starts from the per-pixel" in record["closed_loop"]
    with JointStage(cal, StageCOptions(spp=2, radiometry="pixel")) as stage:
        stage.adapters = [None, None]  # as --effects leaves them when it inverts only the rig's camera curve
        with pytest.raises(CompensationError, match="--radiometry pixel cannot be used here: with --effects"):
            stage.choose_radiometry()


def test_a_closed_loop_keeps_the_global_models_unless_asked(other_forms_calibration):
    from procam.addon.steps import calibrate as calibrate_step
    from procam.addon.steps.stage_c import StageC, StageCOptions

    root = other_forms_calibration
    cal = calibrate_step.read(root / "cal")
    with StageC(cal, StageCOptions(device=f"lab:{root / 'truth.json'}", spp=2)) as stage:
        record = stage.choose_radiometry()
        assert record["used"] == "global" and "its own captures" in record["reason"] and stage.pixel is None
    with StageC(cal, StageCOptions(device=f"lab:{root / 'truth.json'}", spp=2, radiometry="pixel")) as stage:
        assert stage.choose_radiometry()["used"] == "pixel" and stage.pixel is not None
        assert stage.bias_record() is None  # θ = 0 is the open loop's; the closed loop records its loop instead


def test_each_pixels_mixing_is_inverted_as_numpy_does_and_a_singular_one_by_its_diagonal():
    rng = np.random.default_rng(3)
    mix = ((np.eye(3) + 0.3 * rng.random((H, W, 3, 3))) * rng.random((H, W, 1, 3))).astype(np.float32)
    mix[0, 0] = np.diag([2.0, 0.0, 4.0])  # singular: a channel with no light of its own
    got = inverse3(mix).astype(np.float32)
    want = np.linalg.inv(mix[1:])
    assert np.abs(got[1:] - want).max() <= 1e-6 * np.abs(want).max()
    assert np.allclose(got[0, 0], np.diag([0.5, 1.0, 0.25]))

