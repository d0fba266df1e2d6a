"""The measured closed loop (stages/closed_loop.py) on a synthetic rig, and the lab of other forms (lab/other_forms.py).

The synthetic rig: the camera sees ``s·q + c + noise`` for the operator's prediction ``q``, with a slope ``s`` and
an offset ``c`` of its own at every pixel, which no model holds; the "solve" reaches whatever it is asked within
[0, 1]. Pure numpy: no renders.
"""

from __future__ import annotations

import numpy as np
import pytest

from procam.addon.errors import LabError
from procam.addon.lab.other_forms import OtherForms, check_strength
from procam.addon.stages.closed_loop import MeasuredCorrection, NoiseModel, RowGrid, noise_variance_model

W, H = 48, 32
NOISE = 0.01


def _rig(seed: int = 0):
    rng = np.random.default_rng(seed)
    rows = np.arange(W * H)
    target = 0.15 + 0.4 * rng.random((W * H, 3))  # (t − c)/s stays inside [0, 1]: every pixel reachable
    slope = rng.uniform(0.6, 1.5, (W * H, 3))
    offset = rng.uniform(-0.05, 0.05, (W * H, 3))

    def camera(q: np.ndarray) -> np.ndarray:
        return np.clip(slope * q + offset + rng.normal(0, NOISE, q.shape), 0, 1)
    return rows, target, camera


def _measured(captures: int, seed: int = 0) -> float:
    rows, target, camera = _rig(seed)
    q = target.copy()
    y1, y2 = camera(q), camera(q)
    corr = MeasuredCorrection(target, RowGrid(rows, (W, H)), noise_variance_model(y1, y2))
    theta = corr.update(0.5 * (y1 + y2), q, repeats=2)
    for _ in range(captures - 2):
        q = np.clip(target + theta, 0, 1)
        theta = corr.update(camera(q), q)
    q = np.clip(target + theta, 0, 1)
    return float(np.mean((camera(q) - target) ** 2))


def _damped(captures: int, seed: int = 0, rate: float = 1 / 3) -> float:
    rows, target, camera = _rig(seed)
    theta = np.zeros_like(target)
    for k in range(captures):
        q = np.clip(target + theta, 0, 1)
        residual = q - camera(q)
        theta = residual if k == 0 else theta + rate * (residual - theta)
    q = np.clip(target + theta, 0, 1)
    return float(np.mean((camera(q) - target) ** 2))


def test_the_noise_model_reads_the_noise_of_two_captures():
    rng = np.random.default_rng(1)
    level = rng.random((5000, 3))
    sd = np.sqrt(0.002 * level + 1e-5)
    model = noise_variance_model(level + rng.normal(0, 1, level.shape) * sd,
                                 level + rng.normal(0, 1, level.shape) * sd)
    for at in (0.1, 0.5, 0.85):
        assert float(model(np.array(at))) == pytest.approx(0.002 * at + 1e-5, rel=0.2)


def test_the_measured_loop_reaches_the_noise_where_the_damped_one_does_not():
    """Slopes 0.6–1.5 and offsets the model lacks: after 15 captures the measured loop's answer is within 20 % of the
    camera's noise; the paper's θ (a third of the way per capture) keeps more."""
    measured, damped = _measured(15), _damped(15)
    assert measured < 1.2 * NOISE ** 2, measured
    assert measured < 0.9 * damped, (measured, damped)


def test_the_loop_says_when_the_rig_changed_under_it():
    rows, target, camera = _rig()
    q = target.copy()
    y = camera(q)
    corr = MeasuredCorrection(target, RowGrid(rows, (W, H)), noise_variance_model(y, camera(q)))
    corr.update(y, q)
    assert corr.check(camera(q), q) is None
    # a noiseless camera whose slope the loop has not learnt yet: a large change of the input is no rig change
    quiet = MeasuredCorrection(target, RowGrid(rows, (W, H)), NoiseModel.flat(1e-10))
    quiet.update(1.3 * q, q)
    assert quiet.check(1.3 * (q + 0.1), q + 0.1) is None
    assert "moved" in corr.check(np.roll(camera(q).reshape(H, W, 3), 5, axis=1).reshape(-1, 3) + 0.1, q)
    assert "black" in corr.check(np.zeros_like(y), q)
    assert "saturated" in corr.check(np.ones_like(y), q)


def test_a_growing_residual_stops_the_loop():
    rows, target, camera = _rig()
    corr = MeasuredCorrection(target, RowGrid(rows, (W, H)), NoiseModel.flat(NOISE ** 2))
    for k in range(5):
        corr.update(np.clip(target - 0.02 * (k + 1), 0, 1), target)
    assert corr.stop_reason() == "diverging"
    done = MeasuredCorrection(target, RowGrid(rows, (W, H)), NoiseModel.flat(NOISE ** 2))
    done.update(target + np.random.default_rng(3).normal(0, 0.5 * NOISE, target.shape), target)
    assert done.stop_reason() == "noise floor"


def test_the_row_grid_blurs_the_area_alone():
    rows = np.array([cy * 20 + cx for cy in range(4, 10) for cx in range(3, 15)])
    grid = RowGrid(rows, (20, 12))
    flat = np.full((len(rows), 3), 0.7)
    assert np.allclose(grid.blur(flat, 2.0), 0.7, atol=1e-5)  # no darkening at the area's border


def test_other_forms_off_is_the_identity_and_on_differs_from_every_model_form():
    frame = np.random.default_rng(0).random((60, 80, 3)).astype(np.float32)
    assert OtherForms(0.0).projector_light(frame, 80) is frame
    forms = OtherForms(1.0)
    grey = np.full((60, 80, 3), 0.5, np.float32)
    light = forms.projector_light(grey, 80)
    assert light.min() >= 0 and light.max() <= 1 and light.dtype == np.float32
    # a flat grey is not flat once emitted, and its colour changes across the frame: no global curve or matrix
    ratio_left, ratio_right = light[30, 5] / light[30, 5].mean(), light[30, 74] / light[30, 74].mean()
    assert np.abs(ratio_left - ratio_right).max() > 0.02
    # the same rig every time, another for the second projector
    assert np.array_equal(OtherForms(1.0).projector_light(grey, 80), light)
    assert not np.allclose(OtherForms(1.0, projector=1).projector_light(grey, 80), light)
    seen = forms.camera_record(np.full((40, 50, 3), 0.9, np.float32))
    assert seen.shape == (40, 50, 3) and seen.min() >= 0 and seen.max() <= 1
    assert abs(float(seen[..., 1].mean()) - 0.9) > 0.02  # green keeps its white balance: the knee curve moved it


@pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan"), "strong"])
def test_other_forms_refuses_a_strength_outside_0_to_1(bad):
    with pytest.raises(LabError, match="from 0"):
        check_strength(bad)


def test_the_gamut_clip_keeps_what_the_pixel_can_show_and_moves_what_it_cannot():
    from procam.addon.stages.gamut import gamut_ceiling, gamut_clip

    black = np.full((1, 3, 3), 0.02)
    mix = np.array([[0.8, 0.1, 0.0], [0.1, 0.7, 0.1], [0.0, 0.1, 0.6]])  # column c: what primary c lights
    prims = np.stack([np.broadcast_to(black + mix[:, c], (1, 3, 3)) for c in range(3)])
    inside = black[0, 0] + mix @ np.array([0.3, 0.5, 0.2])
    saturated = np.array([0.02, 0.05, 0.62])  # every channel within [black, white], yet blue without green
    target = np.array([[inside, saturated, [0.5, 0.5, 0.5]]])
    clipped = gamut_clip(target, black, prims)
    assert np.allclose(clipped[0, 0], inside, atol=1e-4)
    white = black[0, 0] + mix.sum(axis=1)
    assert np.all(saturated <= white) and np.linalg.norm(clipped[0, 1] - saturated) > 0.05
    from procam.addon.stages.range import range_ceiling

    white_image = np.broadcast_to(white, (1, 3, 3))
    assert gamut_ceiling(target, black, prims, 0.0) < range_ceiling(target, black, white_image) - 10


def test_the_mean_of_two_captures_reaches_the_noise_floor_only_at_its_own_noise():
    """The first input is captured twice and the mean holds half the noise: a residual at one capture's noise is
    then still a bias of 0.7 σ, which the loop must go on correcting (it stopped there on the realistic lab)."""
    rows, target, _ = _rig()
    rng = np.random.default_rng(5)
    biased = MeasuredCorrection(target, RowGrid(rows, (W, H)), NoiseModel.flat(NOISE ** 2))
    bias = 0.7 * NOISE * np.sign(rng.normal(size=target.shape))
    biased.update(target + bias + rng.normal(0, NOISE / np.sqrt(2), target.shape), target, repeats=2)
    assert biased.stop_reason() is None
    done = MeasuredCorrection(target, RowGrid(rows, (W, H)), NoiseModel.flat(NOISE ** 2))
    done.update(target + rng.normal(0, NOISE / np.sqrt(2), target.shape), target, repeats=2)
    assert done.stop_reason() == "noise floor"


def test_a_perfect_answers_capture_inverts_the_camera_and_keeps_only_its_noise_and_compression():
    """lab/perfect.py: the sensor signal whose noiseless recording is the target is found through white balance,
    tone curves and the knee; a perfect answer's capture then differs from the target by the camera's noise and,
    on a camera that writes JPEG, by its compression of the target's texture, which two captures' difference
    cannot see."""
    from procam.addon.lab.effects import record_signal
    from procam.addon.lab.perfect import perfect_capture, perfect_ceiling, sensor_signal
    from procam.addon.lab.truth import make_truth

    rng = np.random.default_rng(3)
    target = np.clip(0.05 + 0.6 * rng.random((48, 64, 3)), 0, 1).astype(np.float32)
    inside = np.s_[8:40, 8:56]
    quiet = make_truth("plane", effects="camera_response=0.8", camera_size=(64, 48), projector_size=(80, 60),
                       other_forms=1.0)
    other = OtherForms(1.0)
    signal = sensor_signal(quiet, target)
    assert np.abs(other.camera_tone(record_signal(signal, quiet.effects, None)) - target).max() < 1e-4
    # noiseless, the JPEG alone: two captures agree exactly, yet differ from the target by its compression
    a, b = (perfect_capture(quiet, target, np.random.default_rng(k)) for k in (0, 1))
    assert np.array_equal(a, b) and np.mean((a - target) ** 2) > 1e-5
    raw = make_truth("plane", effects="camera_response=0.8", camera_size=(64, 48), projector_size=(80, 60))
    assert perfect_ceiling(raw, target, inside) > 80.0  # 16-bit recording only
    noisy = make_truth("plane", effects="noise=0.4", camera_size=(64, 48), projector_size=(80, 60))
    assert 30.0 < perfect_ceiling(noisy, target, inside) < 60.0
    assert perfect_ceiling(quiet, target, inside) < perfect_ceiling(raw, target, inside) - 20.0
    # against another reference (a clipped target's answer scored against the target): the clip's error counts
    dimmer = target * 0.9
    assert perfect_ceiling(raw, dimmer, inside, target=target[inside]) < 40.0
