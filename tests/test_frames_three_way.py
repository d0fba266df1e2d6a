"""The same 3-D points projected through the rig model, Blender and Mitsuba land on the same pixels."""

import numpy as np
import pytest

from procam.addon.render.backend import mitsuba
from procam.addon.render.scene import build_scene, projector_frustum
from procam.addon.rig.demo import demo_rig
from procam.addon.rig.model import Camera, Intrinsics, Rig
from procam.addon.surface.shapes import builtin_surface

CAMERA = Intrinsics(640, 480, 560.0, 560.0, 300.0, 262.0)  # lens-shifted camera


@pytest.fixture(scope="module")
def points():
    return np.random.default_rng(3).uniform([-0.7, -0.45, 1.2], [0.7, 0.45, 2.6], (200, 3))


@pytest.fixture(scope="module")
def mitsuba_scene():
    mi = mitsuba()
    rig = Rig(Camera(CAMERA), demo_rig().projector)
    return mi, rig, build_scene(mi, rig, builtin_surface("plane"), CAMERA)


def _interaction(mi, pts):
    it = mi.Interaction3f()
    it.p = mi.Point3f(*pts.T.astype(np.float32))
    return it


def test_mitsuba_camera_matches_rig_camera(points, mitsuba_scene):
    mi, rig, scene = mitsuba_scene
    ds, _ = scene.sensors()[0].sample_direction(_interaction(mi, points), mi.Point2f(0.5, 0.5))
    uv = np.array(ds.uv).reshape(2, -1).T
    assert np.abs(uv - CAMERA.project(points)).max() < 0.01


def test_mitsuba_projector_matches_rig_projector(points, mitsuba_scene):
    mi, rig, scene = mitsuba_scene
    proj = rig.projector
    px = proj.project(points)
    w, h = proj.intrinsics.size
    inside = np.all((px > 1) & (px < [w - 1, h - 1]), axis=1)
    assert inside.sum() > 20
    ds, _ = scene.emitters()[0].sample_direction(_interaction(mi, points[inside]), mi.Point2f(0.5, 0.5))
    uv_e = np.array(ds.uv).reshape(2, -1).T  # the emitter's symmetric-frustum coordinates
    f = projector_frustum(proj.intrinsics)
    uv_p = (np.c_[uv_e, np.ones(len(uv_e))] @ np.asarray(f.to_uv, dtype=np.float64).T)[:, :2]
    pw, ph = f.padded_size
    texel = uv_p * [pw, ph] - 1.0  # padded texture → native frame pixels (one-texel border)
    assert np.abs(texel - px[inside]).max() < 0.01


def test_blender_camera_matches_rig_camera(points, bpy_scene):
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    from procam.addon.blender import rig as blender_rig
    from procam.addon.rig import frames

    cam = blender_rig.create_camera(bpy_scene, CAMERA)
    bpy_scene.view_layers.update()
    got = []
    for p in frames.blender_points(points):
        v = world_to_camera_view(bpy_scene, cam, Vector(p))
        got.append((v.x * CAMERA.width, (1.0 - v.y) * CAMERA.height))
    assert np.abs(np.array(got) - CAMERA.project(points)).max() < 0.01
