"""The classical baseline (per-pixel 3×3 colour mixing + offset, Gray-code geometry): fit and inversion.

Synthetic data for the maths (exact recovery), the small lab capture set for the fit on real captures.
"""

from __future__ import annotations

import numpy as np
import pytest

from procam.addon.errors import CalibrationError
from procam.addon.stages.classical import ClassicalModel, Response, fit_classical, fit_mixing, fit_response


def _random_mixing(rng: np.random.Generator, p: int) -> tuple[np.ndarray, np.ndarray]:
    m = np.eye(3)[None] * rng.uniform(0.4, 0.9, (p, 1, 1)) + rng.uniform(0.0, 0.15, (p, 3, 3))
    b = rng.uniform(0.0, 0.08, (p, 3))
    return m, b


def test_fit_recovers_a_known_mixing_exactly():
    rng = np.random.default_rng(1)
    p, n = 500, 9
    m, b = _random_mixing(rng, p)
    x = rng.uniform(0, 1, (n, p, 3))
    y = np.einsum("pci,npi->npc", m, x) + b[None]
    m_fit, b_fit, rms = fit_mixing(x, y, ridge=0.0)
    assert np.allclose(m_fit, m, atol=1e-5) and np.allclose(b_fit, b, atol=1e-5)
    assert rms.shape == (p,) and rms.max() < 1e-5
    # The default ridge (towards the median matrix) barely moves a well-posed fit.
    m_r, b_r, _ = fit_mixing(x, y)
    assert np.abs(m_r - m).max() < 1e-2 and np.abs(b_r - b).max() < 1e-2
    with pytest.raises(CalibrationError, match="at least 4"):
        fit_mixing(x[:3], y[:3])
    with pytest.raises(CalibrationError, match="same"):
        fit_mixing(x, y[:, :10])


def test_response_is_recovered_and_inverted():
    levels = np.array([0.25, 0.5, 0.75])
    gamma = np.array([1.8, 1.5, 1.2])
    resp = fit_response(levels, levels[:, None] ** gamma[None])
    assert np.allclose(resp.gamma, gamma, atol=0.01)
    v = np.random.default_rng(0).uniform(0, 1, (50, 3))
    assert np.allclose(resp(v), v ** gamma, atol=0.01)
    assert np.allclose(resp.inverse(resp(v)), v, atol=1e-3)
    assert np.allclose(Response.linear()(v), v)


def test_compensation_inverts_the_model_through_the_correspondence():
    """A synthetic rig: camera pixel (x, y) sees projector input pixel (x, y) (identity geometry, same sizes)."""
    rng = np.random.default_rng(2)
    w, h = 40, 30
    m, b = _random_mixing(rng, w * h)
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    model = ClassicalModel(Response(np.array([1.4, 1.4, 1.4]), np.array([0.0, 1.0]), np.array([[0.0] * 3, [1.0] * 3])),
                           m.reshape(h, w, 3, 3).astype(np.float32), b.reshape(h, w, 3).astype(np.float32),
                           np.ones((h, w), bool), np.stack([xs, ys], axis=-1).astype(np.float32), (w, h))
    target = rng.uniform(0.2, 0.45, (h, w, 3)).astype(np.float32)
    area = np.zeros((h, w), bool)
    area[5:25, 5:35] = True
    x = model.compensate(target, area)
    assert x.shape == (h, w, 3) and np.all(x[~area] == 0)
    seen = np.einsum("hwci,hwi->hwc", model.mixing, model.response(x)) + model.offset
    assert np.abs(seen - target)[area].max() < 2e-3  # no clipping needed: the model reproduces the target
    # A target no pixel can reach is clipped to full white, not extrapolated.
    assert np.all(model.compensate(np.full((h, w, 3), 5.0, np.float32), area)[area] == 1.0)


def test_fit_on_lab_captures(lab_set):
    from procam.addon.capture.format import CaptureSet

    captures_dir, _ = lab_set()
    model = fit_classical(CaptureSet.load(captures_dir, verify_images=False))
    rep = model.report
    assert rep["flat_colours_captured"] == 0 and "val_grey_0.5" in rep["patterns"] and rep["samples"] >= 10
    assert rep["pixels"] > 0.2 * model.valid.size and rep["fit_rms"] < 0.03
    # No lab effects: the projector is linear, so the fitted gamma is near 1.
    assert np.all(np.abs(np.array(rep["response_gamma"]) - 1.0) < 0.15)
    mx, my, seen = model.inverse_map()
    assert seen.mean() > 0.2 and np.all(np.isfinite(mx[seen]))
