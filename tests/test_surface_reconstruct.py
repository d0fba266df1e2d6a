"""RGBD → mesh: accuracy against a known surface, noise and holes handled, unusable depth rejected."""

import numpy as np
import pytest

from procam.addon.errors import SurfaceError
from procam.addon.render.raycast import depth_map
from procam.addon.rig.demo import demo_camera
from procam.addon.surface.mesh import ray_intersect
from procam.addon.surface.reconstruct import reconstruct_surface
from procam.addon.surface.shapes import builtin_surface

W, H = 96, 72


def true_depth(surface):
    cam = demo_camera(W, H).intrinsics
    return cam, depth_map(surface, cam).astype(np.float64)


def test_mitsuba_depth_map_agrees_with_numpy_ray_casting():
    surface = builtin_surface("vedge", resolution=12)
    cam = demo_camera(32, 24).intrinsics
    ys, xs = np.mgrid[0:24, 0:32] + 0.5
    t = ray_intersect(surface, np.zeros(3), cam.rays(np.stack([xs.ravel(), ys.ravel()], 1))).reshape(24, 32)
    d = depth_map(surface, cam)
    assert np.array_equal(np.isfinite(t), np.isfinite(d))
    assert np.nanmax(np.abs(d - t)) < 1e-5


@pytest.fixture(scope="module", params=["plane", "vedge"])
def scene(request):
    s = builtin_surface(request.param, resolution=24)
    cam, depth = true_depth(s)
    return s, cam, depth


def test_noisy_depth_with_holes_and_outliers_gives_sub_centimetre_surface(scene):
    surface, cam, depth = scene
    rng = np.random.default_rng(1)
    noisy = depth + rng.normal(0, 0.01, depth.shape)
    noisy[rng.random(depth.shape) < 0.03] = np.nan
    spikes = rng.random(depth.shape) < 0.01
    noisy[spikes] += 0.5
    rgb = rng.random((H, W, 3)).astype(np.float32)
    mesh, report = reconstruct_surface(noisy, cam, rgb, step=2)
    assert report.outliers >= 0.5 * np.sum(spikes & np.isfinite(depth))
    along = mesh.vertices / mesh.vertices[:, 2:3]
    t = ray_intersect(surface, np.zeros(3), along)
    err = np.abs(mesh.vertices[:, 2] - t)[np.isfinite(t)]
    assert len(err) > 0.9 * len(mesh.vertices)
    assert err.mean() < 0.01
    # Normals face the camera, and UVs put each vertex where the camera sees it.
    assert mesh.face_normals()[:, 2].mean() < -0.5
    px = cam.project(mesh.vertices)
    assert np.allclose(mesh.uvs[:, 0], np.clip(px[:, 0] / W, 0, 1))
    assert np.allclose(mesh.uvs[:, 1], np.clip(1 - px[:, 1] / H, 0, 1))
    assert mesh.albedo.shape == (H, W, 3)


def test_mostly_empty_depth_is_a_clear_error(scene):
    _, cam, depth = scene
    sparse = depth.copy()
    sparse[np.random.default_rng(0).random(depth.shape) < 0.8] = np.nan
    with pytest.raises(SurfaceError, match="mostly empty"):
        reconstruct_surface(sparse, cam)


def test_depth_of_other_aspect_ratio_is_rejected(scene):
    _, cam, depth = scene
    with pytest.raises(SurfaceError, match="aspect"):
        reconstruct_surface(depth[:, : W // 2], cam)


def test_lower_resolution_depth_of_same_aspect_is_accepted(scene):
    surface, cam, depth = scene
    mesh, _ = reconstruct_surface(depth[::2, ::2], cam, step=1)
    t = ray_intersect(surface, np.zeros(3), mesh.vertices / mesh.vertices[:, 2:3])
    assert np.nanmean(np.abs(mesh.vertices[:, 2] - t)[np.isfinite(t)]) < 0.01


def test_constant_depth_bias_survives_smoothing_and_a_known_offset_removes_it(scene):
    surface, cam, depth = scene
    rng = np.random.default_rng(2)
    biased = depth + 0.012 + rng.normal(0, 0.004, depth.shape)

    def signed_errors(mesh):
        along = mesh.vertices / mesh.vertices[:, 2:3]
        t = ray_intersect(surface, np.zeros(3), along)
        ok = np.isfinite(t)
        assert ok.mean() > 0.9
        return mesh.vertices[ok, 2] - t[ok]

    mesh, report = reconstruct_surface(biased, cam, step=2)
    err = signed_errors(mesh)
    # Smoothing averages the noise away but keeps the offset: every part of the surface is ~12 mm too far.
    assert abs(err.mean() - 0.012) < 0.0015
    assert np.percentile(err, 5) > 0.006
    assert report.depth_offset == 0.0
    mesh, report = reconstruct_surface(biased, cam, step=2, depth_offset=0.012)
    err = signed_errors(mesh)
    assert abs(err.mean()) < 0.0015 and np.abs(err).mean() < 0.003
    assert report.depth_offset == 0.012 and report.to_dict()["depth_offset"] == 0.012


@pytest.mark.parametrize("offset", [float("nan"), 0.8, -1.0, True, "0.01"])
def test_unusable_depth_offset_is_a_clear_error(scene, offset):
    _, cam, depth = scene
    with pytest.raises(SurfaceError, match="depth offset"):
        reconstruct_surface(depth, cam, depth_offset=offset)
