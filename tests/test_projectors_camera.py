"""The camera's effects of a rig of several projectors: fitted once on every projector's patterns, named as the
camera's (not one projector's), and modelled in the joint compensation."""

from __future__ import annotations

import json

import numpy as np
import pytest


def test_the_camera_curve_takes_every_projectors_sum_to_light():
    """Each projector's model is in its own white's units: the shared scale takes the projectors' sum to light
    exactly where they all show white, and where one lights alone."""
    from procam.addon.gap.compensation import SharedCamera
    from procam.addon.gap.models import camera_curve, inverse_camera_curve

    curve = 0.8
    w1 = np.full((2, 3, 3), 0.6, np.float32)
    w2 = np.full((2, 3, 3), 0.3, np.float32)
    w2[:, 0] = 0.0  # projector 2 does not light the first column
    cam = SharedCamera({"camera_response": {"curve": curve}}, [w1, w2])
    # each white is its projector's light through the curve: both at white give the sum of their light
    seen = camera_curve(inverse_camera_curve(w1, curve) + inverse_camera_curve(w2, curve), curve)
    assert cam.to_model(seen) == pytest.approx(w1 + w2, abs=2e-3)


@pytest.fixture(scope="module")
def camera_lab(tmp_path_factory):
    """Two projectors side by side on the curve, the camera with a tone curve (strength 0.7), no projector effect;
    calibrated and diagnosed (the camera curve and each projector's tone curve as candidates)."""
    from procam.addon.capture.targets import natural_target
    from procam.addon.cli.app import main
    from procam.addon.imageio import write_image

    root = tmp_path_factory.mktemp("camera")
    assert main(["lab", "--surface", "curve", "--projectors", "2", "--overlap", "0.2", "--effects",
                 "camera_response=0.7", "--scale", "0.2", "--samples", "4", "--out", str(root / "lab"), "--truth",
                 str(root / "lab.truth.json")]) == 0
    assert main(["calibrate", str(root / "lab"), "--out", str(root / "cal"), "--no-blend-output"]) == 0
    assert main(["diagnose", str(root / "cal"), "--out", str(root / "diag"), "--spp", "8", "--effects",
                 "response,camera_response", "--max-effects", "2"]) == 0
    write_image(root / "city.png", natural_target("city", (120, 90)))
    return root


def test_a_camera_curve_is_named_the_cameras_and_fitted_once(camera_lab):
    doc = json.loads((camera_lab / "diag" / "gap.json").read_text())
    joint = doc["joint"]
    assert joint["shared"] == ["camera_response"]
    assert joint["params"]["camera_response"]["curve"] == pytest.approx(0.7, abs=0.15)
    assert doc["headline"].startswith("The camera's tone curve")
    assert doc["differs"] is None  # not one projector's difference
    assert joint["residual_after"] < 0.7 * joint["residual"]
    assert joint["compensation"]["shared"] == joint["params"]


def test_compensation_with_the_cameras_curve_modelled_is_better(camera_lab, tmp_path, capsys):
    """--effects auto selects the camera's curve fitted once (and naming it works): the capture through the lab is
    closer to the target than without it, and compensation.json records it."""
    from procam.addon.cli.app import main

    root = camera_lab
    scores = {}
    for effects in ("none", "auto", "camera_response"):
        comp, ev = tmp_path / f"comp-{effects}", tmp_path / f"eval-{effects}"
        assert main(["compensate", str(root / "cal"), str(root / "city.png"), "--iterations", "20", "--effects",
                     effects, "--diagnosis", str(root / "diag"), "--out", str(comp)]) == 0
        assert main(["evaluate", str(root / "cal"), "--inputs", str(comp), "--targets", str(root / "city.png"),
                     "--device", f"lab:{root / 'lab.truth.json'}", "--out", str(ev)]) == 0
        scores[effects] = json.loads((ev / "metrics.json").read_text())["mean"]["psnr"]
        record = json.loads((comp / "compensation.json").read_text())["effects"]
        if effects != "none":
            assert record["camera"]["used"] == ["camera_response"]
    assert scores["auto"] > scores["none"] + 2.0, scores
    assert scores["camera_response"] > scores["none"] + 2.0, scores


# -- which projector differs when the camera's curve is fitted with the projectors' tone curves --------------------

def _gap_data(seed: int, curve: float, s_mix: float):
    """One projector's GapData without rendering (40×30, the model's light path the identity): grey levels and smooth
    random inputs, captured through the camera's curve ``curve`` after the lab's S-curve (``response_scurve``: slope
    9 at 0.4) mixed in at ``s_mix``, with a little noise."""
    from dataclasses import replace
    from types import SimpleNamespace

    import cv2

    from procam.addon.gap.data import GapData, Observation, split_patterns
    from procam.addon.gap.models import Composite

    w, h = 40, 30
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    gain = (0.55 + 0.25 * np.cos(xs / 9 + seed)[..., None] * np.array([1.0, 0.9, 0.8])).astype(np.float32)
    inputs = [("black", "black", np.zeros((h, w, 3))), ("white", "white", np.ones((h, w, 3)))]
    inputs += [(f"grey_{j}", "validation", np.full((h, w, 3), v)) for j, v in enumerate(np.linspace(0.08, 0.92, 10))]
    for j in range(10):
        r = cv2.GaussianBlur(rng.random((h, w, 3)).astype(np.float32), (0, 0), 3)
        inputs.append((f"random_{j}", "validation", (r - r.min()) / (r.max() - r.min())))
    zero = np.zeros((h, w, 3), np.float32)
    obs = [Observation(n, kind, x.astype(np.float32), zero.copy(), gain * x.astype(np.float32), zero,
                       dict.fromkeys((0.2, 0.4, 0.6), zero), x.astype(np.float32)) for n, kind, x in inputs]
    lens = SimpleNamespace(cx=w / 2, cy=h / 2, fx=w, fy=w)
    fit, held = split_patterns(obs)
    projector = SimpleNamespace(input_size=(w, h), intrinsics=lens, input_offset=(0, 0))
    data = GapData(obs, (w, h), np.ones((h, w), bool), gain, np.stack([xs, ys], -1), np.zeros((h, w, 2), np.float32),
                   zero, zero, np.zeros((h, w), np.float32), projector, lens, None, fit, held)

    def s_curve(v: np.ndarray) -> np.ndarray:
        f = 1.0 / (1.0 + np.exp(-9.0 * (np.array([0.0, 1.0]) - 0.4)))
        return (1.0 / (1.0 + np.exp(-9.0 * (v - 0.4))) - f[0]) / (f[1] - f[0])

    for o in obs:
        a = ((1.0 - s_mix) * o.sampled + s_mix * s_curve(o.sampled)).astype(np.float32)
        # a fresh model each: its caches are keyed by the pattern
        seen = Composite(data, ("camera_response",)).predict(np.array([curve]), replace(o, direct=gain * a, sampled=a))
        o.capture[:] = np.clip(seen + rng.normal(0.0, 0.003, seen.shape), 0.0, 1.0)
    return data


def _whose(s_mix: tuple[float, float]) -> dict:
    from procam.addon.gap import shared
    from procam.addon.steps import diagnose as diagnose_step

    datas = [_gap_data(1, 0.3, s_mix[0]), _gap_data(2, 0.3, s_mix[1])]
    pool = [shared.Item("camera_response"), shared.Item("response", 0), shared.Item("response", 1)]
    sel = shared.select_joint(datas, pool, max_effects=3)
    _, whose = shared.whose_effects(datas, sel)
    return diagnose_step.attribute_held_out([w.record() for w in whose])


def test_the_projector_whose_tone_curve_alone_predicts_the_held_out_patterns_is_named():
    """The camera's curve on both projectors, the lab's S-curve on projector 2 only: the effect on projector 2 alone
    removes (nearly) all the held-out error that the effect on every projector does; the same S-curve on both is
    every projector's (named on none)."""
    verdict = _whose((0.0, 0.6))
    assert (verdict["differs"]["projector"], verdict["differs"]["effect"]) == (2, "response")
    record = verdict["held_out"][0]
    assert record["alone"][1] > 0.5 > record["alone"][0] and record["short"][1] < 0.06 and record["differ"] > 0.06
    both = _whose((0.6, 0.6))
    assert both["differs"] is None and both["headline"] == "The projectors agree: each shows response alike."


def test_a_tone_curve_traded_against_the_cameras_curve_blames_no_other_projector():
    """The vedge's figures (lab: camera curve 0.3 on both, S-curve 0.6 on projector 2): fitted beside the camera's
    curve (0.19) on both projectors, projector 1's tone curve was pushed 50 % of its range from none and projector
    2's 19 %, so the parameters blamed projector 1. Held out, projector 1's alone made things worse, projector 2's
    alone removed 96 % of the error, every projector's 96 % (fitted apart, far more than one curve for both): projector
    2 is named; the black level, which fitted apart removes hardly more than alike, on none."""
    from procam.addon.steps import diagnose as diagnose_step

    def gap(gamma: float, contrast: float) -> dict:
        params = {"gamma_r": gamma, "gamma_g": gamma, "gamma_b": gamma, "contrast": contrast, "pivot": 0.6}
        return {"selected": ["response"], "effects": [{"name": "response", "params": params}]}

    by_parameters = diagnose_step.attribute([gap(0.3, 2.0), gap(0.56, 0.53)])
    assert by_parameters["differs"]["projector"] == 1  # what the parameters said
    whose = [{"effect": "response", "alone": [-0.1884, 0.9565], "every": 0.9619, "differ": 0.9},
             {"effect": "black_level", "alone": [0.1617, 0.2803], "every": 0.453, "differ": 0.02}]
    verdict = diagnose_step.attribute_held_out(whose, params=by_parameters)
    assert (verdict["differs"]["projector"], verdict["differs"]["effect"]) == (2, "response")
    assert verdict["headline"].startswith("Projector 2 differs from the others by its response")
    assert [j["one_projector"] for j in verdict["held_out"]] == [2, None]
    assert verdict["ranking"] == by_parameters["ranking"]  # the parameters' figures kept for the reader
    # no effect any projector alone explains: the overlaps' vignetting, measured there, is named
    flat = [{"effect": "black_level", "alone": [0.16, 0.28], "every": 0.45, "differ": 0.02}]
    overlap = diagnose_step.attribute([{"selected": [], "effects": []}] * 2, [0.0, 0.15])
    assert diagnose_step.attribute_held_out(flat, params=overlap)["differs"]["effect"] == "vignetting"
    assert diagnose_step.attribute_held_out(flat)["differs"] is None
    # the curve's figures (camera curve 0.6 alone): projector 1's black level of −0.15 % removed 7 % of the last
    # error left, held out; its parameters lie 0.3 % of their range from projector 2's: too small to name
    tiny = [{"effect": "black_level", "alone": [0.0665, 0.0003], "every": 0.0689, "differ": 0.0691}]
    levels = [{"selected": ["black_level"], "effects": [{"name": "black_level", "params": {
        "projector": 0.0, "ambient_r": a, "ambient_g": a, "ambient_b": a}}]} for a in (-0.0015, 0.0)]
    assert diagnose_step.attribute_held_out(tiny)["differs"]["projector"] == 1
    assert diagnose_step.attribute_held_out(tiny, params=diagnose_step.attribute(levels))["differs"] is None


def test_the_headline_names_every_projector_whose_tone_curve_differs_as_its_parameter_lines_do():
    """Both projectors had a tone curve: projector 1's alone removed a little more of the held-out error, projector
    2's fit lies further from none, so the headline named projector 1 and the parameter lines under it projector 2.
    Each alone removes far more than the bar and lies far from none: the headline names both, with the figures of
    the lines under it, and the lines of the projectors it names come first."""
    from pathlib import Path

    from procam.addon.steps import diagnose as diagnose_step

    def gap(gamma: float) -> dict:
        params = {"gamma_r": gamma, "gamma_g": gamma, "gamma_b": gamma, "contrast": 0.0, "pivot": 0.5}
        return {"selected": ["response"], "effects": [{"name": "response", "params": params}]}

    by_parameters = diagnose_step.attribute([gap(1.4), gap(0.4)])
    whose = [{"effect": "response", "alone": [0.62, 0.55], "every": 0.9, "differ": 0.3}]
    verdict = diagnose_step.attribute_held_out(whose, params=by_parameters)
    head = verdict["headline"]
    assert head.startswith("Projectors 1 and 2 differ from each other by their response"), head
    assert verdict["differs"]["projectors"] == [1, 2] and verdict["held_out"][0]["projectors"] == [1, 2]
    far = {r["projector"]: r["from_none"] for r in by_parameters["ranking"]}
    for k in (1, 2):
        assert f"projector {k}'s alone removes {whose[0]['alone'][k - 1]:.0%} (its fit lies {far[k]:.0%} of its " \
               f"range from none)" in head
        assert f"projector_{k}/summary.md" in head
    lines = diagnose_step._summary(Path("/nowhere"), {"projector_count": 2, "headline": head, **verdict,
                                                      "projectors": [{}, {}]}).lines
    assert "response held out: removes projector 1 alone 62%, projector 2 alone 55%, every projector apart 90%, " \
           "alike – of the error without it: projectors 1 and 2's" in lines
    # a projector whose curve alone predicts nothing is not named beside the one that does
    alone = diagnose_step.attribute_held_out([{**whose[0], "alone": [0.01, 0.9]}], params=by_parameters)
    assert alone["headline"].startswith("Projector 2 differs from the others by its response")
    assert alone["differs"]["projectors"] == [2]
