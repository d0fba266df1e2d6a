"""The rig in Blender: camera K, projector light, surface, read-back, Cycles render, operators."""

from __future__ import annotations

import math
import tempfile

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from procam.addon.errors import ImageError, RigError, SurfaceError  # noqa: E402
from procam.addon.lab.cycles import render_cycles  # noqa: E402
from procam.addon.blender import rig as blender_rig  # noqa: E402
from procam.addon.rig import frames  # noqa: E402
from procam.addon.rig.demo import demo_rig  # noqa: E402
from procam.addon.rig.model import (Intrinsics, Projector, look_at_pose,  # noqa: E402
                                    projector_intrinsics_from_throw)
from procam.addon.surface.mesh import SurfaceMesh  # noqa: E402
from procam.addon.surface.shapes import builtin_surface  # noqa: E402

pytestmark = pytest.mark.blender


def _points_in_view(intr: Intrinsics, n: int = 50, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    px = rng.uniform([0, 0], intr.size, size=(n, 2))
    return intr.rays(px) * rng.uniform(0.5, 5.0, size=(n, 1))


def _blender_pixels(scene, cam, points_rig: np.ndarray) -> np.ndarray:
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    w, h = scene.render.resolution_x, scene.render.resolution_y
    out = []
    for p in frames.blender_points(points_rig):
        ndc = world_to_camera_view(scene, cam, Vector(p))
        out.append((ndc.x * w, (1.0 - ndc.y) * h))  # NDC y is up from the bottom; pixel rows go down
    return np.array(out)


@pytest.mark.parametrize("intr", [
    Intrinsics(160, 120, 150.0, 150.0, 80.0, 60.0),
    Intrinsics(160, 120, 150.0, 150.0, 60.3, 91.7),  # lens-shifted both ways
    Intrinsics(120, 160, 210.0, 210.0, 70.0, 40.0),  # portrait
], ids=["centred", "shifted", "portrait"])
def test_camera_reproduces_intrinsics(bpy_scene, intr):
    cam = blender_rig.create_camera(bpy_scene, intr)
    assert (bpy_scene.render.resolution_x, bpy_scene.render.resolution_y) == intr.size
    assert bpy_scene.camera == cam
    pts = _points_in_view(intr)
    err = np.abs(_blender_pixels(bpy_scene, cam, pts) - intr.project(pts)).max()
    assert err < 0.01, f"Blender and the model disagree by {err:.4f} px"


def test_read_rig_round_trip_is_exact(bpy_scene):
    rig = demo_rig()
    blender_rig.create_rig(bpy_scene, rig)
    back = blender_rig.read_rig(bpy_scene)
    np.testing.assert_allclose(back.camera.intrinsics.matrix, rig.camera.intrinsics.matrix, rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.projector.intrinsics.matrix, rig.projector.intrinsics.matrix, rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.projector.camera_from_projector, rig.projector.camera_from_projector,
                               rtol=0, atol=1e-9)
    assert back.camera.intrinsics.size == rig.camera.intrinsics.size
    assert back.projector.intrinsics.size == rig.projector.intrinsics.size
    assert back.projector.input_size == rig.projector.input_size
    assert back.projector.input_offset == rig.projector.input_offset
    assert back.projector.intensity == pytest.approx(rig.projector.intensity, rel=1e-12)


def test_read_rig_follows_user_edits(bpy_scene):
    """Moving the light or changing the render size in Blender changes what read_rig returns."""
    from mathutils import Vector

    rig = demo_rig((160, 120), (200, 150))
    objs = blender_rig.create_rig(bpy_scene, rig)
    objs.projector.location += Vector((0.1, 0.0, 0.0))  # Blender +X = rig +x
    bpy_scene.render.resolution_percentage = 50
    bpy.context.view_layer.update()
    back = blender_rig.read_rig(bpy_scene)
    expected = rig.projector.camera_from_projector.copy()
    expected[0, 3] += 0.1
    np.testing.assert_allclose(back.projector.camera_from_projector, expected, atol=1e-6)
    np.testing.assert_allclose(back.camera.intrinsics.matrix, rig.camera.intrinsics.scaled(80, 60).matrix, atol=1e-4)


def test_spot_cone_and_pyramid_enclose_the_frustum(bpy_scene):
    proj = demo_rig().projector  # 15 % vertical lens shift: an asymmetric frustum
    obj = blender_rig.create_projector(bpy_scene, proj)
    light = obj.data
    assert light.type == "SPOT" and light.spot_blend == 0.0 and light.shadow_soft_size == 0.0
    assert light.energy == pytest.approx(4 * math.pi ** 2 * proj.intensity, rel=1e-6)
    w, h = proj.intrinsics.size
    corners = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
    rays = proj.intrinsics.rays(corners)
    angles = np.arctan(np.hypot(rays[:, 0], rays[:, 1]))
    assert light.spot_size / 2 >= angles.max()
    assert light.spot_size / 2 < angles.max() + 1e-3  # just enclosing, not wasteful
    # The viewport pyramid's base corners lie on the frame's corner rays.
    (pyramid,) = obj.children
    assert pyramid.hide_render
    bpy.context.view_layer.update()
    mw = np.array(pyramid.matrix_world)
    local = np.array([v.co for v in pyramid.data.vertices])
    world = local @ mw[:3, :3].T + mw[:3, 3]
    px = proj.project(frames.rig_points(world[1:]))
    np.testing.assert_allclose(px, corners, atol=1e-3)


def test_spot_size_rejects_frustum_wider_than_180_degrees():
    # Wide lens, principal point far outside the image: the asymmetric frustum reaches past 90° from the axis.
    assert blender_rig.spot_size_for(Intrinsics(100, 100, 1.0, 1.0, 50.0, 50.0)) < math.pi
    with pytest.raises(RigError, match="180"):
        blender_rig.spot_size_for(Intrinsics(100000, 100000, 1e-3, 1e-3, 50000.0, 50000.0))


def test_projector_light_lands_where_predicted(bpy_scene):
    """Cycles puts a bright rectangle of the projector frame where the model predicts, at the model's level."""
    rig = demo_rig((160, 120), (200, 150))
    plane = builtin_surface("plane", resolution=2, texture_size=4)
    albedo = 0.5
    plane = SurfaceMesh(plane.vertices, plane.faces, plane.uvs, np.full((4, 4, 3), albedo, np.float32))
    objs = blender_rig.create_rig(bpy_scene, rig, plane)
    proj, cam = rig.projector, rig.camera.intrinsics
    x0, y0 = proj.input_offset
    rect = (x0 + 10, y0 + 15, x0 + 60, y0 + 50)  # u0, v0, u1, v1 in projector pixels, upper left of the input
    colour = np.array([1.0, 0.8, 0.6])
    frame = np.zeros((150, 200, 3), np.float32)
    frame[rect[1]:rect[3], rect[0]:rect[2]] = colour
    blender_rig.set_projector_image(objs.projector, frame)
    img = render_cycles(bpy_scene, samples=16)
    assert img.shape == (120, 160, 3) and img.dtype == np.float32

    # Prediction: camera pixel centre → plane z = 1.6 → projector pixel; Lambertian radiance of a pinhole projector.
    w, h = cam.size
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    x = cam.rays(np.stack([u.ravel(), v.ravel()], 1))
    x *= 1.6 / x[:, 2:3]
    pp = proj.project(x)
    inside = ((pp[:, 0] > rect[0]) & (pp[:, 0] < rect[2]) & (pp[:, 1] > rect[1]) & (pp[:, 1] < rect[3])).reshape(h, w)
    d = x - proj.position
    r = np.linalg.norm(d, axis=1)
    cos_in, cos_axis = np.abs(d[:, 2]) / r, d @ proj.direction / r
    level = (albedo * proj.intensity * cos_in / (r ** 2 * cos_axis ** 3)).reshape(h, w)

    lit = img[..., 0] > 0.5 * level.max()
    rows, cols = np.nonzero(lit)
    prow, pcol = np.nonzero(inside)
    assert abs(cols.mean() - pcol.mean()) < 0.5 and abs(rows.mean() - prow.mean()) < 0.5
    assert abs(lit.sum() - inside.sum()) < 0.1 * inside.sum()
    shifted = [np.roll(inside, s, axis) for s in (1, -1) for axis in (0, 1)]
    core = inside & np.logical_and.reduce(shifted)
    ratio = img[core] / (level[core][:, None] * colour)
    np.testing.assert_allclose(ratio.mean(axis=0), 1.0, atol=0.02)  # 4π² W per unit intensity (DESIGN §4)
    near = inside.copy()
    for _ in range(2):  # bilinear texture lookup softens the edge by half a projector pixel
        near |= np.logical_or.reduce([np.roll(near, s, axis) for s in (1, -1) for axis in (0, 1)])
    assert img[~near].max() < 1e-3  # black elsewhere: nothing from the world or the rest of the frame


def test_render_cycles_restores_scene_and_leaves_no_files(bpy_scene, tmp_path, monkeypatch):
    # A temporary folder of this test's own: other test processes' renders come and go in the shared one.
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    blender_rig.create_rig(bpy_scene, demo_rig((32, 24), (40, 30)), builtin_surface("plane", resolution=2,
                                                                                     texture_size=4))
    engine, samples, path, world = (bpy_scene.render.engine, bpy_scene.cycles.samples, bpy_scene.render.filepath,
                                    bpy_scene.world)
    img = render_cycles(bpy_scene, samples=2, size=(16, 12))
    assert img.shape == (12, 16, 3) and img.max() > 0.05
    assert not list(tmp_path.iterdir())
    assert (bpy_scene.render.engine, bpy_scene.cycles.samples, bpy_scene.render.filepath, bpy_scene.world) == (
        engine, samples, path, world)
    assert (bpy_scene.render.resolution_x, bpy_scene.render.resolution_y) == (32, 24)
    assert "ProCam Dark Room" not in bpy.data.worlds


def test_surface_round_trip(bpy_scene):
    mesh = builtin_surface("curve", resolution=6, texture_size=16)
    blender_rig.create_camera(bpy_scene, demo_rig().camera.intrinsics)
    obj = blender_rig.create_surface(bpy_scene, mesh)
    assert blender_rig.find_rig_objects(bpy_scene).surface == obj
    back = blender_rig.read_surface(bpy_scene)
    assert back.faces.shape == mesh.faces.shape
    # Same triangles (as vertex positions and UVs), whatever the vertex order.
    np.testing.assert_allclose(np.sort(back.vertices[back.faces].reshape(-1, 9), axis=0),
                               np.sort(mesh.vertices[mesh.faces].reshape(-1, 9), axis=0), atol=1e-6)
    np.testing.assert_allclose(np.sort(back.uvs, axis=0), np.sort(mesh.uvs, axis=0), atol=1e-6)
    np.testing.assert_allclose(back.albedo, mesh.albedo, atol=1e-6)
    # Winding kept: normals still face the camera.
    assert np.mean(back.face_normals()[:, 2]) < -0.5


def test_set_surface_on_any_mesh_triangulates_and_splits_seams(bpy_scene):
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0.0, 2.0, 0.0))  # 6 quads with a UV layout
    cube = bpy.context.active_object
    blender_rig.set_surface(bpy_scene, cube)
    surf = blender_rig.read_surface(bpy_scene)
    assert surf.faces.shape == (12, 3)
    assert len(surf.vertices) > 8  # UV seams split vertices
    centre = (surf.vertices.min(axis=0) + surf.vertices.max(axis=0)) / 2
    np.testing.assert_allclose(centre, [0.0, 0.0, 2.0], atol=1e-6)  # Blender +Y = rig +z
    assert surf.albedo.shape == (1, 1, 3)  # no material: grey
    # A second surface replaces the first.
    bpy.ops.mesh.primitive_plane_add()
    blender_rig.set_surface(bpy_scene, bpy.context.active_object)
    assert blender_rig.role(cube) is None


def test_set_surface_rejects_non_meshes_and_faceless_meshes(bpy_scene):
    bpy.ops.object.empty_add()
    with pytest.raises(SurfaceError, match="not a mesh"):
        blender_rig.set_surface(bpy_scene, bpy.context.active_object)
    mesh = bpy.data.meshes.new("points")
    mesh.vertices.add(3)
    obj = bpy.data.objects.new("points", mesh)
    bpy_scene.collection.objects.link(obj)
    with pytest.raises(SurfaceError, match="no faces"):
        blender_rig.set_surface(bpy_scene, obj)
    assert blender_rig.find_rig_objects(bpy_scene).surface is None


def test_set_projector_image_sizes(bpy_scene, tmp_path):
    proj = Projector(projector_intrinsics_from_throw(40, 30, 1.2, 0.0, 0.1), input_size=(30, 30))
    obj = blender_rig.create_projector(bpy_scene, proj)
    ramp = np.linspace(0, 1, 40 * 30 * 3, dtype=np.float32).reshape(30, 40, 3)
    blender_rig.set_projector_image(obj, ramp)
    np.testing.assert_allclose(blender_rig.projector_image(obj), ramp, atol=1e-7)  # float, no colour transfer
    image = obj.data.node_tree.nodes["ProCam Frame"].image
    assert image.is_float and image.colorspace_settings.name == "Non-Color"
    # An input-sized image lands at the input offset inside a black frame.
    blender_rig.set_projector_image(obj, np.ones((30, 30, 3), np.float32))
    np.testing.assert_array_equal(blender_rig.projector_image(obj), proj.frame_from_input(np.ones((30, 30, 3))))
    with pytest.raises(ImageError, match="40×30"):
        blender_rig.set_projector_image(obj, np.ones((10, 10, 3), np.float32))
    from procam.addon.imageio import write_image

    path = write_image(tmp_path / "frame.png", ramp)
    blender_rig.set_projector_image(obj, path)
    np.testing.assert_allclose(blender_rig.projector_image(obj), ramp, atol=1 / 65535)
    assert len([i for i in bpy.data.images if i.name.startswith(blender_rig.PROJECTOR_IMAGE_NAME)]) == 1


def test_create_rig_replaces_previous_rig(bpy_scene):
    blender_rig.create_rig(bpy_scene, demo_rig((32, 24), (40, 30)))
    blender_rig.create_rig(bpy_scene, demo_rig((64, 48), (40, 30)))
    assert len([o for o in bpy_scene.objects if blender_rig.role(o) in ("camera", "projector")]) == 2
    assert len(bpy.data.lights) == 1 and len(bpy.data.cameras) == 1
    assert blender_rig.read_rig(bpy_scene).camera.intrinsics.size == (64, 48)


def _datablock_counts() -> dict[str, int]:
    return {name: len(getattr(bpy.data, name))
            for name in ("objects", "cameras", "lights", "meshes", "materials", "images", "worlds")}


def test_failed_build_leaves_scene_and_data_unchanged(bpy_scene, monkeypatch):
    blender_rig.create_rig(bpy_scene, demo_rig((32, 24), (40, 30)))
    before, objects = _datablock_counts(), sorted(o.name for o in bpy_scene.objects)

    def broken(*args, **kwargs):
        raise SurfaceError("boom")

    monkeypatch.setattr(blender_rig, "_build_surface", broken)
    with pytest.raises(SurfaceError):
        blender_rig.create_rig(bpy_scene, demo_rig(), builtin_surface("plane", resolution=2, texture_size=4))
    assert _datablock_counts() == before
    assert sorted(o.name for o in bpy_scene.objects) == objects


# --------------------------------------------------------------------------- operators


def test_operator_create_rig(registered):
    scene = bpy.context.scene
    result = bpy.ops.procam.create_rig(projector_width=400, projector_height=300, throw_ratio=1.5, shift_x=5.0,
                                       shift_y=10.0, camera_width=320, camera_height=240, surface="plane")
    assert result == {"FINISHED"}
    rig = blender_rig.read_rig(scene)
    expected = projector_intrinsics_from_throw(400, 300, 1.5, 0.05, 0.10)
    np.testing.assert_allclose(rig.projector.intrinsics.matrix, expected.matrix, atol=1e-9)
    assert rig.camera.intrinsics.size == (320, 240)
    assert blender_rig.find_rig_objects(scene).surface is not None
    result = bpy.ops.procam.create_rig(use_explicit_k=True, projector_width=100, projector_height=80,
                                       fx=120.0, fy=120.0, cx=40.0, cy=70.0, input_width=0, input_height=0)
    assert result == {"FINISHED"}
    proj = blender_rig.read_rig(scene).projector
    assert (proj.intrinsics.cx, proj.intrinsics.cy) == (40.0, 70.0) and proj.input_size == (100, 80)
    # A real projector's shift: the image 127 % of its height above the lens axis, and 60 % to the left.
    assert bpy.ops.procam.create_rig(projector_width=400, projector_height=300, throw_ratio=1.5, shift_x=-60.0,
                                     shift_y=127.0, camera_width=320, camera_height=240) == {"FINISHED"}
    expected = projector_intrinsics_from_throw(400, 300, 1.5, -0.6, 1.27)
    np.testing.assert_allclose(blender_rig.read_rig(scene).projector.intrinsics.matrix, expected.matrix, atol=1e-6)


@pytest.mark.parametrize("spec, message", [
    ({"projector_width": 0}, "resolution must be positive"),
    ({"camera_height": 0}, "height must be a positive"),
    ({"throw_ratio": 0.0}, "throw ratio must be a positive"),
    ({"throw_ratio": -1.0}, "throw ratio must be a positive"),
    ({"shift_y": 800.0}, "principal point"),
    ({"use_explicit_k": True, "cx": 5000.0}, "principal point"),
    ({"intensity": 0.0}, "intensity must be positive"),
    ({"input_width": 5000}, "must be positive and fit"),
])
def test_operator_create_rig_rejects_bad_specs(registered, spec, message):
    bpy.ops.procam.create_rig(camera_width=32, camera_height=24, projector_width=40, projector_height=30,
                              input_width=30, input_height=30)
    before, objects = _datablock_counts(), sorted(o.name for o in bpy.context.scene.objects)
    args = {"camera_width": 32, "camera_height": 24, "projector_width": 40, "projector_height": 30,
            "input_width": 30, "input_height": 30, **spec}
    with pytest.raises(RuntimeError, match=message):  # bpy.ops turns an ERROR report into RuntimeError
        bpy.ops.procam.create_rig(**args)
    assert _datablock_counts() == before
    assert sorted(o.name for o in bpy.context.scene.objects) == objects


def test_operator_set_surface(registered):
    bpy.ops.procam.create_rig(camera_width=32, camera_height=24, projector_width=40, projector_height=30,
                              input_width=30, input_height=30)
    scene = bpy.context.scene
    projector = blender_rig.find_rig_objects(scene).projector
    bpy.context.view_layer.objects.active = projector
    props_before = {o.name: blender_rig.role(o) for o in scene.objects}
    with pytest.raises(RuntimeError, match="not a mesh"):
        bpy.ops.procam.set_surface()
    assert {o.name: blender_rig.role(o) for o in scene.objects} == props_before
    bpy.ops.mesh.primitive_plane_add(location=(0.0, 2.0, 0.0), rotation=(math.pi / 2, 0.0, 0.0))
    assert bpy.ops.procam.set_surface() == {"FINISHED"}
    assert blender_rig.find_rig_objects(scene).surface == bpy.context.active_object


def test_operator_set_projector_image(registered, tmp_path):
    bpy.ops.procam.create_rig(camera_width=32, camera_height=24, projector_width=40, projector_height=30,
                              input_width=30, input_height=30)
    projector = blender_rig.find_rig_objects(bpy.context.scene).projector
    shown = blender_rig.projector_image(projector)
    with pytest.raises(RuntimeError, match="image not found"):
        bpy.ops.procam.set_projector_image(filepath=str(tmp_path / "missing.png"))
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not a png")
    with pytest.raises(RuntimeError, match="cannot read"):
        bpy.ops.procam.set_projector_image(filepath=str(bad))
    with pytest.raises(RuntimeError, match="no image chosen"):
        bpy.ops.procam.set_projector_image(filepath="")
    np.testing.assert_array_equal(blender_rig.projector_image(projector), shown)
    from procam.addon.imageio import write_image

    path = write_image(tmp_path / "half.png", np.full((30, 30, 3), 0.5, np.float32))
    assert bpy.ops.procam.set_projector_image(filepath=str(path)) == {"FINISHED"}
    assert blender_rig.projector_image(projector).max() == pytest.approx(0.5, abs=1e-4)


def test_panel_draws_state(registered):
    bpy.ops.procam.create_rig(camera_width=32, camera_height=24, projector_width=40, projector_height=30,
                              input_width=30, input_height=30)
    state = blender_rig.rig_summary(bpy.context.scene)
    assert "32×24" in state["camera"] and "40×30" in state["projector"] and state["surface"] == "none"
    assert "error" not in state
    assert hasattr(bpy.types, "PROCAM_PT_rig")


def test_projector_pose_from_look_at_is_reproduced(bpy_scene):
    """A projector looking sideways and down still lands its principal ray where the model says."""
    pose = look_at_pose([0.5, -0.3, 0.2], [0.0, 0.2, 2.0])
    proj = Projector(projector_intrinsics_from_throw(80, 60, 1.0, 0.1, 0.2), pose)
    obj = blender_rig.create_projector(bpy_scene, proj)
    np.testing.assert_allclose(frames.pose_from_blender_matrix(np.array(obj.matrix_world)), pose, atol=1e-6)


def test_projector_frame_survives_save_and_reload(bpy_scene, tmp_path):
    obj = blender_rig.create_projector(bpy_scene, Projector(projector_intrinsics_from_throw(40, 30, 1.2)))
    frame = np.random.default_rng(1).uniform(0, 1, (30, 40, 3)).astype(np.float32)
    blender_rig.set_projector_image(obj, frame)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "rig.blend"))
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "rig.blend"))
    obj = blender_rig.find_rig_objects(bpy.context.scene).projector
    np.testing.assert_array_equal(blender_rig.projector_image(obj), frame)


def _two_projector_rig():
    rig = demo_rig((64, 48), (40, 30))
    moved = rig.projector.camera_from_projector.copy()
    moved[0, 3] += 0.4
    other = Projector(projector_intrinsics_from_throw(50, 40, 1.1, 0.0, 0.1), moved, 1.7)
    return rig.with_projectors((rig.projector, other))


def test_rig_of_two_projectors_round_trips_in_order(bpy_scene):
    rig = _two_projector_rig()
    objs = blender_rig.create_rig(bpy_scene, rig)
    assert len(objs.projectors) == 2 and objs.projector is objs.projectors[0]
    names = [o.name for o in objs.projectors]
    assert names == ["ProCam Projector", "ProCam Projector 2"]
    # each its own light, frustum and frame image
    assert len({o.data.name for o in objs.projectors}) == 2
    assert len([o for o in bpy_scene.objects if blender_rig.role(o) == "frustum"]) == 2
    assert blender_rig.projector_image(objs.projectors[1]).shape == (40, 50, 3)
    # the order is the stored index, not the name: renaming does not reorder
    objs.projectors[0].name = "Zed"
    objs.projectors[1].name = "Alpha"
    back = blender_rig.read_rig(bpy_scene)
    assert len(back.projectors) == 2
    for got, want in zip(back.projectors, rig.projectors):
        np.testing.assert_allclose(got.camera_from_projector, want.camera_from_projector, atol=1e-9)
        assert got.intrinsics == want.intrinsics and got.intensity == pytest.approx(want.intensity)
    assert blender_rig.read_projector(bpy_scene, 1).intrinsics.size == (50, 40)
    with pytest.raises(RigError, match="no projector 2"):
        blender_rig.read_projector(bpy_scene, 2)
    # a one-projector rig replaces both, and stores no index (as before several existed)
    objs = blender_rig.create_rig(bpy_scene, demo_rig((64, 48), (40, 30)))
    assert len(objs.projectors) == 1 and "index" not in objs.projector[blender_rig.PROP].to_dict()
    assert blender_rig.read_rig(bpy_scene).others == ()


def test_active_projector_is_the_one_the_panel_shows(bpy_scene):
    rig = _two_projector_rig()
    objs = blender_rig.create_rig(bpy_scene, rig)
    assert "(1 of 2)" in blender_rig.rig_summary(bpy_scene)["projector"]
    bpy.context.view_layer.objects.active = objs.projectors[1]
    assert blender_rig.find_rig_objects(bpy_scene).projector == objs.projectors[1]
    assert blender_rig.read_projector(bpy_scene).intrinsics.size == (50, 40)
    assert "(2 of 2)" in blender_rig.rig_summary(bpy_scene)["projector"]
    bpy.context.view_layer.objects.active = objs.projectors[0].children[0]  # its frustum
    assert blender_rig.find_rig_objects(bpy_scene).projector == objs.projectors[0]
    assert blender_rig.read_rig(bpy_scene).projector.intrinsics.size == (40, 30)  # rig order, whatever is active


def test_operator_add_projector(registered):
    scene = bpy.context.scene
    assert bpy.ops.procam.create_rig(camera_width=32, camera_height=24, projector_width=40,
                                     projector_height=30) == {"FINISHED"}
    first = blender_rig.read_rig(scene).projector
    assert bpy.ops.procam.add_projector(offset=0.3) == {"FINISHED"}
    rig = blender_rig.read_rig(scene)
    assert len(rig.projectors) == 2 and rig.others[0].intrinsics == first.intrinsics
    np.testing.assert_allclose(rig.projector.camera_from_projector, first.camera_from_projector, atol=1e-9)
    np.testing.assert_allclose(rig.others[0].position - first.position, first.camera_from_projector[:3, 0] * 0.3,
                               atol=1e-6)
    assert "(2 of 2)" in blender_rig.rig_summary(scene)["projector"]  # the new one is active
    with pytest.raises(RuntimeError, match="same pose"):
        bpy.ops.procam.add_projector(offset=0.0)
    assert len(blender_rig.find_rig_objects(scene).projectors) == 2
