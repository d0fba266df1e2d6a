"""Stage B (warp): the thin-plate spline as data, its Dr.Jit gradient, W from M, and the fit on lab captures."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from procam.addon.errors import CalibrationError, Cancelled, ImageError, ProCamError
from procam.addon.stages.warp import _DrWarp
from procam.addon.stages.warp_model import (Warp, bending_matrix, grid_image, pixel_basis, pixel_centres,
                                            sample_bilinear, solve_inverse, tps_basis)


def _smooth_shifts(grid: int, amplitude: float, seed: int = 0) -> np.ndarray:
    """A smooth shift field: an affine part plus one gentle bump per axis (pixels)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, grid)
    yy, xx = np.meshgrid(t, t, indexing="ij")
    out = np.zeros((grid, grid, 2))
    for a in range(2):
        c = rng.uniform(-1, 1, 4)
        out[..., a] = amplitude * (c[0] + 0.5 * c[1] * xx + 0.5 * c[2] * yy
                                   + c[3] * np.sin(np.pi * xx) * np.sin(np.pi * yy))
    return out


def _inverse_error(warp: Warp, step: float = 2.0) -> float:
    """max |φ_M(φ_W(p)) − p| over a dense grid of the input where φ_W(p) stays inside (W(M(z)) = z)."""
    w, h = warp.size
    p = np.stack(np.meshgrid(np.arange(0.25, w, step), np.arange(0.25, h, step)), -1).reshape(-1, 2)
    pw = warp.map_w(p)
    inside = (pw[:, 0] >= 0) & (pw[:, 0] <= w) & (pw[:, 1] >= 0) & (pw[:, 1] <= h)
    return float(np.linalg.norm(warp.map_m(pw[inside]) - p[inside], axis=1).max())


# ------------------------------------------------------------------ the spline and the Warp data type

def test_identity_warp_is_exact():
    rng = np.random.default_rng(1)
    img = rng.random((60, 80, 3)).astype(np.float32)
    warp = Warp.identity((80, 60), 8)
    assert warp.is_identity
    assert np.array_equal(warp.apply_m(img), img) and np.array_equal(warp.apply_w(img), img)
    pts = rng.uniform(0, 60, (50, 2))
    assert np.array_equal(warp.map_m(pts), pts) and np.array_equal(warp.map_w(pts), pts)
    # Bilinear sampling at pixel centres is the image itself, so a zero field through the general path is exact too.
    c = pixel_centres((80, 60)).reshape(60, 80, 2)
    assert np.allclose(sample_bilinear(img, c[..., 0], c[..., 1]), img, atol=1e-6)
    assert Warp.from_dict(json.loads(json.dumps(warp.to_dict()))) == warp


def test_tps_interpolates_the_control_shifts_and_reproduces_affine_fields():
    size, n = (120, 90), 6
    shifts = _smooth_shifts(n, 3.0, seed=2)
    ctrl = np.stack(np.meshgrid(np.linspace(0, 120, n), np.linspace(0, 90, n)), -1).reshape(-1, 2)
    warp = Warp(n, size, shifts, np.zeros_like(shifts))
    assert np.allclose(warp.map_m(ctrl) - ctrl, shifts.reshape(-1, 2), atol=1e-8)
    # the same map for an input at half the resolution: positions and shifts in its own pixels
    assert np.allclose(warp.map_m(ctrl / 2, (60, 45)), warp.map_m(ctrl) / 2, atol=1e-8)
    assert np.array_equal(warp.map_m(ctrl, size), warp.map_m(ctrl))
    # An affine field is reproduced everywhere and costs no bending energy.
    affine = np.stack([1.5 + 0.01 * ctrl[:, 0] - 0.02 * ctrl[:, 1], -0.7 + 0.03 * ctrl[:, 1]], 1)
    pts = np.random.default_rng(3).uniform(0, 90, (200, 2))
    d = tps_basis(pts, size, n) @ affine
    assert np.allclose(d, np.stack([1.5 + 0.01 * pts[:, 0] - 0.02 * pts[:, 1], -0.7 + 0.03 * pts[:, 1]], 1), atol=1e-8)
    e = bending_matrix(size, n)
    assert abs(affine[:, 0] @ e @ affine[:, 0]) < 1e-8 and shifts[..., 0].ravel() @ e @ shifts[..., 0].ravel() > 0
    # The cached per-pixel basis is the same spline.
    dense = pixel_basis(120, 90, n).reshape(90, 120, -1)
    assert np.allclose(dense[10, 20], tps_basis(np.array([[20.5, 10.5]]), size, n)[0], atol=1e-6)


def test_w_inverts_m_on_a_dense_grid():
    size, n = (600, 600), 8
    m = _smooth_shifts(n, 6.0, seed=4)
    w_shifts, reported = solve_inverse(m, size, n)
    warp = Warp(n, size, m, w_shifts)
    err = _inverse_error(warp)
    assert err < 0.1, err
    assert reported < 0.1
    # And the images: W(M(z)) ≈ z for a smooth z, away from the border where M samples outside z.
    y, x = np.mgrid[0:600, 0:600] / 600.0
    z = np.stack([0.5 + 0.4 * np.sin(6 * x) * np.cos(5 * y), x, y], -1).astype(np.float32)
    back = warp.apply_w(warp.apply_m(z))
    assert np.abs(back - z)[20:-20, 20:-20].max() < 0.02


def test_apply_at_another_resolution_scales_the_shifts():
    n = 5
    m = np.zeros((n, n, 2))
    m[..., 0] = 4.0  # M samples 4 px to the right at 200×100
    warp = Warp(n, (200, 100), m, -m)
    img = np.zeros((50, 100), np.float32)
    img[:, 60:] = 1.0
    out = warp.apply_m(img)  # half resolution: 2 px
    assert out[25, 57] == 0.0 and out[25, 58] == 1.0
    with pytest.raises(ImageError):
        warp.apply_m(np.zeros((100, 100), np.float32))


def test_to_dict_round_trip_and_bad_dicts():
    n = 8
    m = _smooth_shifts(n, 2.0, seed=5)
    warp = Warp(n, (600, 600), m, solve_inverse(m, (600, 600), n)[0])
    back = Warp.from_dict(json.loads(json.dumps(warp.to_dict())))
    assert back.grid == n and back.size == (600, 600)
    assert np.allclose(back.m_shifts, warp.m_shifts, atol=1e-6) and np.allclose(back.w_shifts, warp.w_shifts, atol=1e-6)
    img = np.random.default_rng(6).random((600, 600, 3)).astype(np.float32)
    assert np.allclose(back.apply_w(img), warp.apply_w(img), atol=1e-4)
    d = warp.to_dict()
    for bad in ({**d, "m_shifts": np.zeros((7, 8, 2)).tolist()}, {**d, "grid": 1},
                {k: v for k, v in d.items() if k != "w_shifts"}, {**d, "format": "something-else"},
                {**d, "m_shifts": np.full((8, 8, 2), np.nan).tolist()}, "not a dict"):
        with pytest.raises(CalibrationError):
            Warp.from_dict(bad)


def test_grid_image():
    m = _smooth_shifts(8, 3.0, seed=7)
    img = grid_image(Warp(8, (600, 600), m, np.zeros_like(m)), (300, 300), exaggerate=3)
    assert img.shape == (300, 300, 3) and img.dtype == np.float32
    assert img.min() >= 0.0 and img.max() <= 1.0 and (img > 0.9).any()


def test_drjit_warp_gradient_matches_finite_differences():
    """The bilinear gather in Dr.Jit carries gradients to the shifts (through Bᵀ), as finite differences say."""
    from procam.addon.render import backend

    mi = backend.mitsuba()
    import drjit as dr

    size, n, frame_size, offset = (40, 30), 4, (50, 34), (5, 2)
    y, x = np.mgrid[0:30, 0:40] + 0.5
    pattern = (0.5 + 0.4 * np.sin(x / 4.0) * np.cos(y / 5.0)).astype(np.float32)
    weights = np.random.default_rng(8).random((34, 50, 3)).astype(np.float32)
    basis = pixel_basis(40, 30, n)
    s = _smooth_shifts(n, 1.5, seed=9).reshape(-1, 2)
    warp_dr = _DrWarp(mi, size, frame_size, offset)
    warp_dr.set_pattern(pattern)

    def loss_np(shifts: np.ndarray) -> float:
        warped = Warp(n, size, shifts.reshape(n, n, 2), np.zeros((n, n, 2))).apply_m(pattern)
        frame = np.zeros((34, 50, 3), np.float32)
        frame[2:32, 5:45] = warped[..., None]
        return float((frame * weights).sum())

    d = basis @ s.astype(np.float32)
    dx, dy = mi.Float(np.ascontiguousarray(d[:, 0])), mi.Float(np.ascontiguousarray(d[:, 1]))
    dr.enable_grad(dx, dy)
    frame = warp_dr.frame(dx, dy)
    loss = dr.sum(frame.array * mi.Float(weights.ravel()))
    assert abs(float(loss[0]) - loss_np(s)) < 1e-2
    dr.backward(loss)
    grad = basis.T @ np.stack([np.array(dr.grad(dx)), np.array(dr.grad(dy))], 1)
    fd = np.zeros_like(s)
    for k in range(s.size):
        e = np.zeros(s.size)
        e[k] = 1e-2
        fd.flat[k] = (loss_np(s + e.reshape(s.shape)) - loss_np(s - e.reshape(s.shape))) / 2e-2
    cos = float((grad * fd).sum() / (np.linalg.norm(grad) * np.linalg.norm(fd)))
    assert cos > 0.999, cos
    assert np.allclose(grad, fd, rtol=0.05, atol=0.02 * np.abs(fd).max())


# ------------------------------------------------------------------ the fit on lab captures

def _perturbed(pose: np.ndarray, offset_m: float = 0.005, angle_deg: float = 0.2) -> np.ndarray:
    """The residual stage A might leave: 5 mm sideways and 0.2° about the vertical axis."""
    a = math.radians(angle_deg)
    rot = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    out = pose.copy()
    out[:3, :3] = rot @ pose[:3, :3]
    out[:3, 3] += (offset_m, 0.0, 0.0)
    return out


@pytest.fixture(scope="module")
def warp_set(lab_set):
    captures_dir, truth_path = lab_set("vedge", "realistic", graycode=False)
    return captures_dir, truth_path


@pytest.fixture(scope="module")
def fitted(warp_set):
    """Stage B from a slightly wrong pose on the surface reconstructed from the set's depth."""
    from procam.addon.capture.format import CaptureSet
    from procam.addon.lab.truth import LabTruth
    from procam.addon.rig.model import Rig
    from procam.addon.stages.warp import estimate_warp
    from procam.addon.surface.reconstruct import reconstruct_surface

    captures_dir, truth_path = warp_set
    captures = CaptureSet.load(captures_dir)
    truth = LabTruth.load(truth_path)  # tests may read the truth: here only for the pose stage A would give
    surface, _ = reconstruct_surface(captures.depth(), captures.camera.intrinsics, captures.image("surface"))
    rig = Rig(captures.camera, captures.projector.with_pose(_perturbed(truth.rig.projector.camera_from_projector)))
    calls: list[tuple[str, float]] = []
    result = estimate_warp(captures, surface, rig, progress=lambda m, f: calls.append((m, f)), seed=0)
    return result, calls, captures, surface, rig


def test_warp_absorbs_a_wrong_pose_and_aligns_corners(fitted):
    result, calls, *_ = fitted
    before, after = result.corners_before_px, result.corners_after_px
    assert after["n"] >= 40 and before["n"] == after["n"]
    assert before["median"] > 0.5  # 0.2° and 5 mm off are visible at this scale…
    assert after["median"] < 0.35 and after["median"] < 0.4 * before["median"]  # …and the warp removes them
    assert after["max"] < 1.0
    assert result.losses[-1] < 0.5 * result.losses[0]
    assert result.inverse_error_px < 0.1
    assert _inverse_error(result.warp) < 0.1
    fr = [f for _, f in calls]
    assert fr == sorted(fr) and fr[-1] == 1.0 and fr[0] >= 0.0
    h, w = fitted[2].camera.intrinsics.height, fitted[2].camera.intrinsics.width
    for name in ("checker_capture", "checker_target", "render_before", "render_after", "compare_before",
                 "compare_after"):
        img = result.diagnostics[name]
        assert img.shape == (h, w, 3) and np.isfinite(img).all()
    assert result.diagnostics["grid"].shape[:2] == result.warp.size[::-1]
    assert json.loads(json.dumps(result.to_dict()))["corners_after_px"]["median"] == after["median"]


def test_warp_with_the_true_pose_and_surface_does_no_harm(warp_set):
    from procam.addon.capture.format import CaptureSet
    from procam.addon.lab.truth import LabTruth
    from procam.addon.rig.model import Rig
    from procam.addon.stages.warp import estimate_warp

    captures_dir, truth_path = warp_set
    captures = CaptureSet.load(captures_dir)
    truth = LabTruth.load(truth_path)
    rig = Rig(captures.camera, captures.projector.with_pose(truth.rig.projector.camera_from_projector))
    result = estimate_warp(captures, truth.surface, rig, iterations=40, seed=1)
    assert result.corners_after_px["median"] < 0.3
    assert result.corners_after_px["median"] <= result.corners_before_px["median"] + 0.05
    assert np.abs(result.warp.m_shifts).max() < 1.5  # nothing big to absorb


# ------------------------------------------------------------------ bad input

def _copy_set(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _setup(warp_set, tmp_path):
    from procam.addon.capture.format import CaptureSet
    from procam.addon.lab.truth import LabTruth
    from procam.addon.rig.model import Rig

    captures_dir, truth_path = warp_set
    truth = LabTruth.load(truth_path)
    folder = _copy_set(captures_dir, tmp_path / "captures")
    captures = CaptureSet.load(folder)
    return folder, truth.surface, Rig(captures.camera,
                                      captures.projector.with_pose(truth.rig.projector.camera_from_projector))


def _fit(folder: Path, surface, rig, **kw):
    from procam.addon.capture.format import CaptureSet
    from procam.addon.stages.warp import estimate_warp

    return estimate_warp(CaptureSet.load(folder), surface, rig, iterations=2, **kw)


def test_dark_checkerboard_is_refused_naming_the_capture(warp_set, tmp_path):
    from procam.addon.capture.format import CaptureSet
    from procam.addon.imageio import write_image

    folder, surface, rig = _setup(warp_set, tmp_path)
    captures = CaptureSet.load(folder)
    entry = captures.entries_of("checker")[1]
    write_image(folder / entry.file, captures.image("black"))  # the projector was off for this one
    with pytest.raises(CalibrationError, match=Path(entry.file).name):
        _fit(folder, surface, rig)
    write_image(folder / entry.file, 0.5 * (captures.image("black") + captures.image("white")))  # no contrast
    with pytest.raises(CalibrationError, match="cannot be binarised"):
        _fit(folder, surface, rig)


def test_white_no_brighter_than_black_is_refused(warp_set, tmp_path):
    from procam.addon.capture.format import CaptureSet
    from procam.addon.imageio import write_image

    folder, surface, rig = _setup(warp_set, tmp_path)
    captures = CaptureSet.load(folder)
    write_image(folder / captures.entry("white").file, captures.image("black"))
    with pytest.raises(CalibrationError, match=Path(captures.entry("white").file).name):
        _fit(folder, surface, rig)


def test_missing_checkerboard_and_size_mismatch_are_refused(warp_set, tmp_path):
    from procam.addon.rig.model import Camera, Rig

    folder, surface, rig = _setup(warp_set, tmp_path)
    doc = json.loads((folder / "capture.json").read_text())
    doc["images"] = [e for e in doc["images"] if e["kind"] != "checker"]
    small = Rig(Camera(rig.camera.intrinsics.scaled(96, 72)), rig.projector)
    with pytest.raises(CalibrationError, match="96×72"):
        _fit(folder, surface, small)
    (folder / "capture.json").write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match="no checkerboard"):
        _fit(folder, surface, rig)


def test_cancel_stops_stage_b(warp_set, tmp_path):
    folder, surface, rig = _setup(warp_set, tmp_path)
    with pytest.raises(Cancelled, match="cancelled") as err:
        _fit(folder, surface, rig, cancel=lambda: True)
    assert not isinstance(err.value, ProCamError)  # a cancel, not an error the user can fix


# --------------------------------------------------------------------------- stage B from the Gray code

def test_the_graycode_warp_finds_a_known_shift_and_leaves_a_true_model_alone(lab_set):
    """Sessions without a checkerboard (OpenCV's sequence) get stage B from the decoded Gray code: with the true
    rig the warp stays near the identity; with the model's projector 2 texels off it finds the 2 texels."""
    from dataclasses import replace

    from procam.addon.capture.format import CaptureSet
    from procam.addon.lab.truth import LabTruth
    from procam.addon.stages.graycode_warp import warp_from_graycode

    captures_dir, truth_path = lab_set("plane")
    captures, truth = CaptureSet.load(captures_dir), LabTruth.load(truth_path)
    rig = truth.rig
    exact = warp_from_graycode(captures, truth.surface, rig)
    assert float(np.abs(exact.warp.m_shifts).max()) < 0.5
    assert exact.corners_after_px["median"] < 0.6  # the decoded texel is whole: ±0.5 in each axis
    k = rig.projector.intrinsics
    off = replace(rig, projector=replace(rig.projector, intrinsics=replace(k, cx=k.cx + 2.0)))
    fit = warp_from_graycode(captures, truth.surface, off)
    # the model puts every point 2 texels right of the real projector's texel: M takes them back
    inside = fit.warp.map_m(np.array([[k.width / 2, k.height / 2]]))[0] - np.array([k.width / 2, k.height / 2])
    assert inside[0] == pytest.approx(-2.0, abs=0.3) and abs(inside[1]) < 0.3
    assert fit.corners_before_px["median"] > 1.5 and fit.corners_after_px["median"] < 0.6
    assert fit.inverse_error_px < 0.05
