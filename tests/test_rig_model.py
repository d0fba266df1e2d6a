"""Rig model: intrinsics, spec-sheet conversion, poses, validation."""

import json

import numpy as np
import pytest

from procam.addon.errors import ImageError, RigError
from procam.addon.rig import frames
from procam.addon.rig.demo import demo_rig
from procam.addon.rig.model import (Intrinsics, Projector, Rig, intrinsics_from_fov, look_at_pose,
                                    projector_intrinsics_from_throw)


def test_throw_ratio_and_shift_round_trip():
    k = projector_intrinsics_from_throw(800, 600, 1.25, shift_x=-0.05, shift_y=0.15)
    assert k.fx == pytest.approx(1000.0) and k.fy == pytest.approx(1000.0)
    assert k.cx == pytest.approx(440.0) and k.cy == pytest.approx(390.0)
    assert k.throw_ratio == pytest.approx(1.25)
    assert k.shift == pytest.approx((-0.05, 0.15))


def test_shifted_image_sits_above_the_axis():
    # A positive vertical shift puts the image centre above the lens axis (rig y is down).
    k = projector_intrinsics_from_throw(800, 600, 1.0, shift_y=0.2)
    ray = k.rays(np.array([[400.0, 300.0]]))[0]
    assert ray[1] == pytest.approx(-0.2 * 600 / 800)


@pytest.mark.parametrize("kwargs, message", [
    (dict(width=0, height=600, throw_ratio=1.0), "resolution"),
    (dict(width=800, height=600, throw_ratio=0.0), "throw ratio"),
    (dict(width=800, height=600, throw_ratio=-1.0), "throw ratio"),
    (dict(width=800, height=600, throw_ratio=1.0, shift_y=6.0), "principal point"),
    (dict(width=800, height=600, throw_ratio=1.0, shift_x=-80.0), "principal point"),
])
def test_bad_projector_specs_are_named(kwargs, message):
    with pytest.raises(RigError, match=message):
        projector_intrinsics_from_throw(**kwargs)


@pytest.mark.parametrize("shift_x, shift_y", [(0.0, 0.0), (0.0, 0.6), (0.0, 1.27), (0.0, -2.0), (0.6, 0.0),
                                              (-1.5, 1.27)])
def test_principal_point_anywhere_a_lens_puts_it(shift_x, shift_y):
    """Real projectors sit above or below their image: the realdata projector's principal point is at y = 1358 of
    a 768-high frame (1.27 heights off centre)."""
    k = projector_intrinsics_from_throw(1024, 768, 3.86, shift_x=shift_x, shift_y=shift_y)
    assert k.shift == pytest.approx((shift_x, shift_y))
    assert Intrinsics.from_dict(k.to_dict()) == k
    assert k.project(k.rays(np.array([[k.cx, k.cy], [0.0, 0.0]]))) == pytest.approx(np.array([[k.cx, k.cy], [0, 0]]))
    real = Intrinsics(1024, 768, 3953.67, 3893.26, 737.67, 1358.33)  # the published realdata calibration
    assert real.shift[1] == pytest.approx(1.269, abs=1e-3)  # as published: 1.27 heights above the lens axis


def test_opencv_matrix_shifts_half_a_pixel():
    k = intrinsics_from_fov(640, 480, 60.0)
    assert k.opencv_matrix()[0, 2] == pytest.approx(319.5)
    assert k.matrix[0, 2] == pytest.approx(320.0)


def test_projection_and_rays_are_inverse():
    k = Intrinsics(800, 600, 1010.0, 990.0, 410.0, 380.0)
    px = np.array([[0.0, 0.0], [800.0, 600.0], [123.4, 456.7]])
    pts = k.rays(px) * np.array([[1.0], [2.5], [0.7]])
    assert np.abs(k.project(pts) - px).max() < 1e-9


def test_point_behind_device_projects_to_nan():
    k = intrinsics_from_fov(64, 48, 60)
    assert np.all(np.isnan(k.project(np.array([[0.0, 0.0, -1.0]]))))


def test_look_at_pose_is_rigid_and_aims():
    pose = look_at_pose([0.2, 0.1, 0.0], [0.0, 0.0, 2.0])
    r = pose[:3, :3]
    assert np.allclose(r @ r.T, np.eye(3)) and np.linalg.det(r) == pytest.approx(1.0)
    aim = np.array([-0.2, -0.1, 2.0])
    assert np.allclose(r[:, 2], aim / np.linalg.norm(aim))
    assert r[1, 1] > 0.9  # y stays (mostly) down


def test_projector_rejects_non_rigid_pose_and_bad_input_placement():
    k = projector_intrinsics_from_throw(800, 600, 1.2)
    with pytest.raises(RigError, match="rigid"):
        Projector(k, np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(RigError, match="fit"):
        Projector(k, input_size=(900, 600))
    with pytest.raises(RigError, match="intensity"):
        Projector(k, intensity=0.0)


def test_input_placement_and_frame():
    rig = demo_rig()
    p = rig.projector
    assert p.input_size == (600, 600) and p.input_offset == (100, 0)
    frame = p.frame_from_input(np.ones((600, 600, 3)))
    assert frame.shape == (600, 800, 3)
    assert frame[:, :100].max() == 0 and frame[:, 700:].max() == 0 and frame[:, 100:700].min() == 1
    with pytest.raises(ImageError, match="600×600"):
        p.frame_from_input(np.ones((10, 10, 3)))


def test_demo_projector_is_lens_shifted_and_lands_on_camera_image():
    rig = demo_rig()
    k = rig.projector.intrinsics
    assert abs(k.cy - k.height / 2) >= 0.1 * k.height
    # Projector frame corners hit a plane at 1.7 m inside the camera image.
    p = rig.projector
    rays = p.camera_from_projector[:3, :3] @ k.rays(np.array([[0, 0], [800, 0], [0, 600], [800, 600]])).T
    t = (1.7 - p.position[2]) / rays[2]
    pts = p.position[:, None] + rays * t
    px = rig.camera.intrinsics.project(pts.T)
    assert np.all((px >= 0) & (px <= [640, 480]))
    # and back: projecting those points into the projector gives the corners again
    assert np.abs(p.project(pts.T) - [[0, 0], [800, 0], [0, 600], [800, 600]]).max() < 1e-6


def test_rig_dict_round_trip():
    rig = demo_rig((64, 48), (80, 60))
    back = Rig.from_dict(rig.to_dict())
    assert back.camera.intrinsics == rig.camera.intrinsics
    assert np.allclose(back.projector.camera_from_projector, rig.projector.camera_from_projector)
    assert back.projector.input_size == rig.projector.input_size


def test_one_projector_rig_dict_is_unchanged_and_several_round_trip():
    rig = demo_rig((64, 48), (80, 60))
    one = rig.to_dict()
    assert set(one) == {"frame", "camera", "projector"}  # as before several projectors existed
    assert len(rig.projectors) == 1 and rig.projectors[0] is rig.projector and Rig.from_dict(one).others == ()
    second = Projector(projector_intrinsics_from_throw(64, 40, 1.6), look_at_pose((-0.3, 0.1, 0.0), (0, 0, 1.7)),
                       intensity=1.5)
    two = Rig(rig.camera, rig.projector, (second,))
    d = two.to_dict()
    assert d["projector"] == one["projector"] and len(d["projectors"]) == 2  # a one-projector reader reads the first
    back = Rig.from_dict(json.loads(json.dumps(d)))
    assert len(back.projectors) == 2 and back.projector_at(1).intrinsics.size == (64, 40)  # sizes may differ
    assert np.allclose(back.projectors[1].camera_from_projector, second.camera_from_projector)
    assert back.projectors[1].intensity == 1.5
    assert Rig.from_dict({k: v for k, v in d.items() if k != "projector"}).to_dict() == d  # the list alone suffices
    assert two.with_projectors(two.projectors[::-1]).projector.intensity == 1.5


@pytest.mark.parametrize("change, message", [
    (lambda d: d.update(projectors=[]), "list of one or more"),
    (lambda d: d.update(projectors=[3]), "list of one or more"),
    (lambda d: d["projectors"][0].update(intensity=9.0), "'projector' differs from the first"),
    (lambda d: d["projectors"][1].update(camera_from_projector=d["projectors"][0]["camera_from_projector"]),
     "projectors 1 and 2 .* same pose"),
    (lambda d: d["projectors"][1].pop("intrinsics"), "lacks 'intrinsics'"),
])
def test_bad_projector_lists_are_refused(change, message):
    rig = demo_rig((64, 48), (80, 60))
    other = rig.projector.with_pose(look_at_pose((-0.3, 0.1, 0.0), (0, 0, 1.7)))
    d = json.loads(json.dumps(Rig(rig.camera, rig.projector, (other,)).to_dict()))
    change(d)
    with pytest.raises(RigError, match=message):
        Rig.from_dict(d)


def test_projector_index_out_of_range_is_named():
    rig = demo_rig((64, 48), (80, 60))
    with pytest.raises(RigError, match="1 projector.*no projector 1"):
        rig.projector_at(1)


def test_scaled_keeps_the_lens():
    k = projector_intrinsics_from_throw(800, 600, 1.25, shift_y=0.15)
    s = k.scaled(200, 150)
    assert s.throw_ratio == pytest.approx(k.throw_ratio) and s.shift == pytest.approx(k.shift)


def test_blender_frame_is_z_up_with_camera_looking_along_y():
    cam = frames.blender_matrix_world(np.eye(4))
    assert np.allclose(cam[:3, 2], [0, -1, 0])  # Blender cameras look down local -Z → world +Y
    assert np.allclose(cam[:3, 1], [0, 0, 1])  # local +Y (up) → world +Z
    pose = look_at_pose([0.3, -0.1, 0.2], [0.0, 0.2, 2.0])
    assert np.allclose(frames.pose_from_blender_matrix(frames.blender_matrix_world(pose)), pose)
    pts = np.random.default_rng(0).normal(size=(5, 3))
    assert np.allclose(frames.rig_points(frames.blender_points(pts)), pts)


def test_blender_camera_params_round_trip():
    k = Intrinsics(640, 480, 580.0, 580.0, 300.0, 270.0)
    p = frames.blender_camera_params(k)
    back = frames.intrinsics_from_blender_camera(p["lens"], p["sensor_width"], 24.0, p["sensor_fit"],
                                                 p["shift_x"], p["shift_y"], 640, 480)
    assert np.allclose(back.matrix, k.matrix)
    with pytest.raises(RigError, match="square"):
        frames.blender_camera_params(Intrinsics(640, 480, 580.0, 590.0, 320.0, 240.0))


def test_a_scaled_working_size_keeps_square_pixels():
    from procam.addon.rig.model import Intrinsics, square_scaled_size

    assert square_scaled_size(320, 240, 0.5) == (160, 120)  # exact sizes are kept
    assert square_scaled_size(640, 480, 0.3) == (192, 144)
    # 1280×1024 at 0.1 rounds to 128×102 axis by axis: rows 0.4 % taller than columns, which the renderer refuses
    w, h = square_scaled_size(1280, 1024, 0.1)
    assert (w, h) == (130, 104)
    k = Intrinsics.from_opencv_matrix(1280, 1024, np.array([[3448.0, 0, 640], [0, 3448.0, 512], [0, 0, 1]]))
    assert k.scaled(w, h).square_pixels
    for size in ((1279, 1023), (1920, 1080), (1000, 750)):
        w, h = square_scaled_size(*size, 0.1)
        assert abs(w - 0.1 * size[0]) <= 0.1 * 0.1 * size[0] and abs(w * size[1] / size[0] - h) <= 0.05


def test_two_projectors_at_one_pose_are_named_from_1():
    rig = demo_rig()
    with pytest.raises(RigError, match=r"projectors 1 and 2 have the same pose") as refused:
        Rig(rig.camera, rig.projector, (rig.projector,))
    assert "numbered from 0" not in str(refused.value)
