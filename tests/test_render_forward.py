"""The Mitsuba forward model f̂: geometry against an analytic projection, radiometry, texture orientation, gradients."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from procam.addon.errors import ImageError
from procam.addon.render.forward import ForwardModel
from procam.addon.render.pose import apply_pose_delta
from procam.addon.render.scene import border_smoothing, projector_frustum
from procam.addon.rig.demo import demo_projector, demo_rig
from procam.addon.rig.model import Camera, Intrinsics, Projector, Rig, look_at_pose
from procam.addon.surface.mesh import SurfaceMesh
from procam.addon.surface.shapes import builtin_surface

CAMERA = (160, 120)
PROJECTOR = (200, 150)


def uniform(surface: SurfaceMesh, value: float = 0.8) -> SurfaceMesh:
    return replace(surface, albedo=np.full((4, 4, 3), value, dtype=np.float32))


def skewed_rig() -> Rig:
    """Off-centre camera principal point; projector with fx ≠ fy and its principal point off centre in x and y."""
    base = demo_rig(CAMERA, PROJECTOR)
    cam = Intrinsics(CAMERA[0], CAMERA[1], 150.0, 150.0, 0.44 * CAMERA[0], 0.57 * CAMERA[1])
    pi = base.projector.intrinsics
    proj_k = Intrinsics(pi.width, pi.height, pi.fx * 1.04, pi.fy * 0.97, 0.42 * pi.width, 0.64 * pi.height)
    return Rig(Camera(cam), replace(base.projector, intrinsics=proj_k))


def intersect(origin: np.ndarray, dirs: np.ndarray, surface: SurfaceMesh) -> np.ndarray:
    """Nearest hit of rays (common origin) with the mesh (Möller–Trumbore), N×3; NaN where they miss."""
    tri = surface.vertices[surface.faces]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    out = np.full((len(dirs), 3), np.nan)
    for n, d in enumerate(dirs):
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = origin - tri[:, 0]
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        if hit.any():
            out[n] = origin + t[hit].min() * d
    return out


def analytic_pixels(rig: Rig, surface: SurfaceMesh, texels: np.ndarray) -> np.ndarray:
    """Camera pixels (corner convention) where projector positions (corner convention) land on the surface."""
    pose = rig.projector.camera_from_projector
    dirs = rig.projector.intrinsics.rays(texels) @ pose[:3, :3].T
    return rig.camera.intrinsics.project(intersect(pose[:3, 3], dirs, surface))


def spot_centroids(image: np.ndarray, centres: np.ndarray, radius: float = 4.0) -> np.ndarray:
    g = image.sum(axis=2)
    ys, xs = np.mgrid[0:g.shape[0], 0:g.shape[1]] + 0.5
    out = []
    for u, v in centres:
        w = g * ((np.abs(xs - u) < radius) & (np.abs(ys - v) < radius))
        out.append([(w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()] if w.sum() > 0 else [np.nan, np.nan])
    return np.array(out)


def placement_errors(rig: Rig, surface: SurfaceMesh, skip_crease: bool = False) -> np.ndarray:
    """Lit 3×3-texel spots on a 5×5 grid of the frame: |rendered centroid − analytic projection| in camera px."""
    pi = rig.projector.intrinsics
    model = ForwardModel(rig, surface, spp=16, smoothing_eps=0.0)
    frame = np.zeros((pi.height, pi.width, 3), dtype=np.float32)
    centres = []
    for cx in (22, 61, 100, 139, 178):
        for cy in (16, 46, 75, 104, 134):
            if skip_crease and abs(cx - 100) < 6:
                continue  # a spot straddling the crease is folded; its centroid is not a point's projection
            frame[cy - 1:cy + 2, cx - 1:cx + 2] = 1.0
            centres.append((cx + 0.5, cy + 0.5))
    expected = analytic_pixels(rig, surface, np.array(centres))
    inside = np.all((expected > 5) & (expected < np.array(CAMERA) - 5), axis=1)
    assert inside.sum() >= 15
    found = spot_centroids(model.render(frame, seed=1), expected[inside])
    return np.linalg.norm(found - expected[inside], axis=1)


@pytest.mark.parametrize("rig_name,shape", [("demo", "plane"), ("demo", "vedge"), ("skewed", "plane")])
def test_lit_texels_land_where_the_analytic_projection_says(rig_name: str, shape: str) -> None:
    rig = demo_rig(CAMERA, PROJECTOR) if rig_name == "demo" else skewed_rig()
    pi = rig.projector.intrinsics
    assert abs(pi.cy - pi.height / 2) >= 0.1 * pi.height  # the lens shift is really exercised
    err = placement_errors(rig, uniform(builtin_surface(shape, resolution=24)), skip_crease=shape == "vedge")
    assert np.all(err < 0.5), f"max placement error {np.nanmax(err):.3f} px"
    assert np.median(err) < 0.15


@pytest.mark.parametrize("shift", [(0.0, 0.0), (0.0, 0.6), (0.0, 1.27), (0.0, 2.0), (0.6, 0.0), (-0.4, -1.27)],
                         ids=["none", "up60%", "up127%", "up200%", "right60%", "left40%-down127%"])
def test_any_lens_shift_lands_where_the_analytic_projection_says(shift: tuple[float, float]) -> None:
    """Principal points far outside the frame (a real projector sits above or below its image): the symmetric
    frustum grows, the texture stays (W+2)×(H+2), and every lit texel still lands on its analytic pixel."""
    rig = Rig(demo_rig(CAMERA, PROJECTOR).camera, demo_projector(*PROJECTOR, shift=shift))
    k = rig.projector.intrinsics
    assert k.shift == pytest.approx(shift)
    assert projector_frustum(k).padded_size == (PROJECTOR[0] + 2, PROJECTOR[1] + 2)
    err = placement_errors(rig, uniform(builtin_surface("curve", resolution=24)))
    assert np.all(err < 0.5), f"max placement error {np.nanmax(err):.3f} px"
    assert np.median(err) < 0.15


def test_projector_frustum_maps_the_frame_corners_onto_the_padded_texture() -> None:
    k = skewed_rig().projector.intrinsics
    fr = projector_frustum(k)
    t = np.tan(np.radians(fr.fov_x_deg) / 2)
    a = fr.padded_size[0] / fr.padded_size[1]
    for col, row in [(0.0, 0.0), (k.width, k.height), (k.cx, k.cy), (13.0, 141.0)]:
        x, y = (col - k.cx) / k.fx, (row - k.cy) / k.fy
        ue, ve = 0.5 + x / (2 * t), 0.5 + a * y / (2 * t)  # Mitsuba's emitter uv, OpenCV axes
        assert 0 <= ue <= 1 and 0 <= ve <= 1  # inside the symmetric frustum
        up, vp, _ = fr.to_uv @ [ue, ve, 1.0]
        assert up * fr.padded_size[0] == pytest.approx(col + 1, abs=1e-9)
        assert vp * fr.padded_size[1] == pytest.approx(row + 1, abs=1e-9)


def test_white_frame_radiance_matches_the_emitter_formula() -> None:
    """L = ρ · scale · cos θ_s / (z_local² · cos θ_p), from projector.cpp and a Lambertian BSDF (ρ/π · π)."""
    cam = Camera(Intrinsics(CAMERA[0], CAMERA[1], 150.0, 150.0, 80.0, 60.0))
    pk = Intrinsics(PROJECTOR[0], PROJECTOR[1], 220.0, 220.0, 100.0, 75.0)
    pos = np.array([0.25, -0.05, 0.1])
    pose = look_at_pose(pos, (0.05, 0.02, 2.0))  # tilted: cos θ_s ≠ cos θ_p
    rho, scale, dist = 0.6, 3.0, 2.0
    surface = uniform(builtin_surface("plane", distance=dist, width=3.0, height=2.4, resolution=2), rho)
    model = ForwardModel(Rig(cam, Projector(pk, pose, intensity=scale)), surface, spp=4, smoothing_eps=0.0,
                         clamp=False)
    img = model.render(np.ones((PROJECTOR[1], PROJECTOR[0], 3), dtype=np.float32), seed=3)
    ys, xs = np.mgrid[0:CAMERA[1], 0:CAMERA[0]] + 0.5
    rays = cam.intrinsics.rays(np.stack([xs.ravel(), ys.ravel()], 1))
    pts = rays * (dist / rays[:, 2:3])
    to_p = pos - pts
    d = np.linalg.norm(to_p, axis=1)
    cos_s = -to_p[:, 2] / d  # the plane's normal faces the camera (−z)
    local_z = (pts - pos) @ pose[:3, 2]
    cos_p = local_z / d
    expected = (rho * scale * cos_s / (local_z ** 2 * cos_p)).reshape(CAMERA[1], CAMERA[0])
    # Only pixels well inside the lit footprint (the edge pixels are partly lit).
    pix = model.rig.projector.project(pts).reshape(CAMERA[1], CAMERA[0], 2)
    well_inside = np.all((pix > 3) & (pix < np.array(PROJECTOR) - 3), axis=2)
    assert well_inside.sum() > 0.3 * well_inside.size
    ratio = img[..., 1][well_inside] / expected[well_inside]
    assert np.abs(ratio - 1).max() < 0.01, f"radiance off by up to {np.abs(ratio - 1).max():.4f}"
    assert np.allclose(img[..., 0], img[..., 2])
    # Outside the frame no light arrives.
    outside = np.any((pix < -3) | (pix > np.array(PROJECTOR) + 3), axis=2)
    assert outside.sum() > 0 and img[outside].max() == 0.0


def test_albedo_texture_is_not_mirrored() -> None:
    """A dark marker in the upper-left of the albedo image appears where its UV says on the surface."""
    rig = demo_rig(CAMERA, PROJECTOR)
    surface = builtin_surface("plane", resolution=4)
    n = 64
    plain = np.full((n, n, 3), 0.8, dtype=np.float32)
    marked = plain.copy()
    r0, c0 = 20, 24  # rows 20–23 from the top, columns 24–27: upper left, asymmetric both ways
    marked[r0:r0 + 4, c0:c0 + 4] = 0.1
    model = ForwardModel(rig, replace(surface, albedo=plain), spp=16, smoothing_eps=0.0)
    white = np.ones((PROJECTOR[1], PROJECTOR[0], 3), dtype=np.float32)
    base = model.render(white, seed=5)
    model.set_albedo(marked)
    diff = base - model.render(white, seed=5)
    # Marker centre in UV (v = 0 at the bottom row) → rig point on the builtin plane → camera pixel.
    u, v = (c0 + 2) / n, 1 - (r0 + 2) / n
    point = np.array([[(u - 0.5) * 1.6, (0.5 - v) * 1.2, 1.6]])
    expected = rig.camera.intrinsics.project(point)
    found = spot_centroids(diff, expected, radius=6)
    assert np.linalg.norm(found - expected) < 0.5
    mirrored = rig.camera.intrinsics.project(point * [1, -1, 1])
    assert diff.sum(axis=2)[int(mirrored[0, 1]), int(mirrored[0, 0])] < 1e-3


@pytest.mark.parametrize("bounces", [0, 1])
def test_frame_gradient_is_nonzero_exactly_where_light_reaches_the_camera_and_matches_finite_differences(
        bounces: int) -> None:
    import drjit as dr
    import mitsuba as mi

    rig = demo_rig(CAMERA, PROJECTOR)
    surface = uniform(builtin_surface("plane", width=0.7, height=0.5, resolution=2))  # smaller than the image
    model = ForwardModel(rig, surface, spp=4, bounces=bounces)
    pw, ph = PROJECTOR
    rng = np.random.default_rng(0)
    w_np = rng.uniform(0.5, 1.5, size=(CAMERA[1], CAMERA[0], 3)).astype(np.float32)
    weights = mi.TensorXf(w_np)
    base = np.full((ph, pw, 3), 0.5, dtype=np.float32)

    def loss(frame: np.ndarray) -> float:
        # Sum in float64: the difference of two float32 sums of 57 600 pixels would be mostly rounding.
        return float(np.sum(np.array(model.render_dr(mi.TensorXf(frame), seed=7), dtype=np.float64) * w_np))

    z = mi.TensorXf(base)
    dr.enable_grad(z)
    # The adjoint pass samples with seed_grad (Mitsuba wants it ≠ seed); the render is linear in the frame,
    # so finite differences of renders with that seed must agree to rounding.
    dr.backward(dr.sum(model.render_dr(z, seed=6, seed_grad=7) * weights, axis=None))
    grad = np.array(dr.grad(z))

    # Where does each texel centre land? On the plane (|x| < 0.35, |y| < 0.25 at z = 1.6) or not.
    cols, rows = np.meshgrid(np.arange(pw) + 0.5, np.arange(ph) + 0.5)
    pose = rig.projector.camera_from_projector
    d = rig.projector.intrinsics.rays(np.stack([cols.ravel(), rows.ravel()], 1)) @ pose[:3, :3].T
    hit = pose[:3, 3] + d * ((1.6 - pose[2, 3]) / d[:, 2:3])
    margin = 0.02  # three texels (≈ 6.6 mm each) clear of the plane's edge
    on = ((np.abs(hit[:, 0]) < 0.35 - margin) & (np.abs(hit[:, 1]) < 0.25 - margin)).reshape(ph, pw)
    off = ((np.abs(hit[:, 0]) > 0.35 + margin) | (np.abs(hit[:, 1]) > 0.25 + margin)).reshape(ph, pw)
    g = grad.sum(axis=2)
    gamma = border_smoothing(pw, ph, 0.01) == 1
    assert on.sum() > 500 and off.sum() > 500
    assert np.all(g[on & gamma] > 0)
    assert np.all(g[off] == 0)

    direction = rng.normal(size=base.shape).astype(np.float32)
    h = 0.05
    fd = (loss(base + h * direction) - loss(base - h * direction)) / (2 * h)
    ad = float(np.sum(grad * direction))
    assert fd == pytest.approx(ad, rel=2e-3)


def test_indirect_bounces_add_light_only_where_the_surface_sees_itself() -> None:
    rig = demo_rig(CAMERA, PROJECTOR)
    white = np.ones((PROJECTOR[1], PROJECTOR[0], 3), dtype=np.float32)
    plane = uniform(builtin_surface("plane", resolution=2))
    direct = ForwardModel(rig, plane, spp=4).render(white, seed=2)
    assert np.array_equal(ForwardModel(rig, plane, spp=4, integrator="prb").render(white, seed=2), direct)
    assert np.allclose(ForwardModel(rig, plane, spp=4, bounces=1).render(white, seed=2), direct, atol=1e-6)
    vedge = uniform(builtin_surface("vedge", resolution=8))
    d0 = ForwardModel(rig, vedge, spp=16, clamp=False).render(white, seed=2)
    # the diagnosis's indirect light is a path tracer's bounces less its first, which the direct integrator gives
    assert np.array_equal(ForwardModel(rig, vedge, spp=16, clamp=False, integrator="prb").render(white, seed=2), d0)
    d1 = ForwardModel(rig, vedge, spp=16, clamp=False, bounces=1).render(white, seed=2)
    # The concave crease is at camera column 80: one bounce adds ≈ 6 % there, ≈ 1 % far out on the sides.
    crease = d1[40:80, 76:84].mean() / d0[40:80, 76:84].mean()
    sides = d1[40:80, 20:40].mean() / d0[40:80, 20:40].mean()
    assert crease > 1.04 and crease - 1 > 2 * (sides - 1) > 0


def test_pose_gradient_matches_central_differences_with_border_smoothing() -> None:
    import drjit as dr
    import mitsuba as mi

    rig = demo_rig(CAMERA, PROJECTOR)
    surface = uniform(builtin_surface("vedge", resolution=8))
    model = ForwardModel(rig, surface, spp=4, smoothing_eps=0.01)
    pw, ph = PROJECTOR
    white = np.ones((ph, pw, 3), dtype=np.float32)
    # Stage A's situation: the target is the lit mask of a slightly different pose.
    model.set_pose(apply_pose_delta(rig.projector.camera_from_projector, [0.02, -0.01, 0.03, 0.01, -0.015, 0.01]))
    target = mi.TensorXf((model.render(white, seed=11) > 0.1).astype(np.float32))
    model.set_pose(rig.projector.camera_from_projector)
    frame = mi.TensorXf(white)

    def loss(delta: np.ndarray) -> float:
        with dr.suspend_grad():
            img = model.render_dr(frame, mi.Float(delta.astype(np.float32)), seed=13)
            return float(np.array(dr.sum(dr.square(img - target), axis=None)))

    delta = mi.Float(np.zeros(6, dtype=np.float32))
    dr.enable_grad(delta)
    img = model.render_dr(frame, delta, seed=12, seed_grad=13)
    dr.backward(dr.sum(dr.square(img - target), axis=None))
    ad = np.array(dr.grad(delta))

    steps = np.array([1e-3, 1e-3, 2e-3, 5e-4, 5e-4, 5e-4])
    fd = np.zeros(6)
    for i in range(6):
        e = np.zeros(6)
        e[i] = steps[i]
        fd[i] = (loss(e) - loss(-e)) / (2 * steps[i])
    cos = ad @ fd / (np.linalg.norm(ad) * np.linalg.norm(fd))
    assert cos > 0.95, f"AD {ad} vs FD {fd}: cosine {cos:.3f}"
    assert np.linalg.norm(ad) == pytest.approx(np.linalg.norm(fd), rel=0.2)


def test_a_pose_delta_renders_like_the_pose_it_folds_into() -> None:
    """Stages fold optimised deltas back into the rig pose with apply_pose_delta: both paths must agree."""
    import mitsuba as mi

    rig = demo_rig(CAMERA, PROJECTOR)
    delta = [0.03, -0.02, 0.05, 0.04, -0.06, 0.08]
    moved = apply_pose_delta(rig.projector.camera_from_projector, delta)
    r = moved[:3, :3]
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-12) and np.linalg.det(r) == pytest.approx(1.0)
    model = ForwardModel(rig, uniform(builtin_surface("vedge", resolution=8)), spp=4)
    frame = np.ones((PROJECTOR[1], PROJECTOR[0], 3), dtype=np.float32)
    via_delta = np.array(model.render_dr(mi.TensorXf(frame), mi.Float(np.array(delta, np.float32)), seed=4))
    model.set_pose(moved)
    folded = model.render(frame, seed=4)
    assert folded.max() > 0.1  # something is lit
    assert np.abs(via_delta - folded).max() < 1e-3
    model.set_pose(rig.projector.camera_from_projector)
    assert np.abs(model.render(frame, seed=4) - folded).max() > 0.1  # and the delta really moved it


def test_wrong_frame_size_raises_image_error() -> None:
    rig = demo_rig(CAMERA, PROJECTOR)
    model = ForwardModel(rig, uniform(builtin_surface("plane", resolution=2)), spp=1)
    with pytest.raises(ImageError, match="200×150"):
        model.render(np.zeros((PROJECTOR[0], PROJECTOR[1], 3), dtype=np.float32))
    with pytest.raises(ImageError):
        model.render_input(np.zeros((10, 10, 3), dtype=np.float32))
    with pytest.raises(ImageError):
        model.render_dr(np.zeros((PROJECTOR[1], PROJECTOR[0] + 1, 3), dtype=np.float32))
    img = model.render_input(np.ones((rig.projector.input_size[1], rig.projector.input_size[0], 3), dtype=np.float32))
    assert img.shape == (CAMERA[1], CAMERA[0], 3) and img.dtype == np.float32 and img.max() > 0.1
