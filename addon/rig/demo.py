"""The built-in demo rig, shaped like the paper's set-up (camera 640×480, projector 800×600 with a
vertical lens shift, projector input 600×600 centred in the frame)."""

from __future__ import annotations

import numpy as np

from .model import Camera, Intrinsics, Projector, Rig, intrinsics_from_fov, look_at_pose, projector_intrinsics_from_throw

CAMERA_SIZE = (640, 480)
PROJECTOR_SIZE = (800, 600)
PROJECTOR_INPUT = (600, 600)
#: Projector below and right of the camera, image shifted up by 15 % of its height (cy 10 % + off centre).
PROJECTOR_POSITION = (0.22, 0.12, 0.05)
PROJECTOR_THROW = 1.25
PROJECTOR_SHIFT_Y = 0.15
SURFACE_CENTRE = (0.0, 0.0, 1.7)


def demo_camera(width: int = CAMERA_SIZE[0], height: int = CAMERA_SIZE[1]) -> Camera:
    return Camera(intrinsics_from_fov(CAMERA_SIZE[0], CAMERA_SIZE[1], 58.0).scaled(width, height))


def demo_projector(width: int = PROJECTOR_SIZE[0], height: int = PROJECTOR_SIZE[1], intensity: float = 2.5) -> Projector:
    intr: Intrinsics = projector_intrinsics_from_throw(PROJECTOR_SIZE[0], PROJECTOR_SIZE[1], PROJECTOR_THROW,
                                                       0.0, PROJECTOR_SHIFT_Y)
    # Aim so that the *shifted* image centre, not the lens axis, lands on the surface centre.
    pos = np.asarray(PROJECTOR_POSITION)
    centre_ray = intr.rays(np.array([[intr.width / 2, intr.height / 2]]))[0]
    axis_to_centre = np.arctan2(-centre_ray[1], 1.0)  # image centre is above the axis
    aim = np.asarray(SURFACE_CENTRE) - pos
    dist = np.linalg.norm(aim)
    # Tilt the look-at target down by the shift angle so the image centre hits SURFACE_CENTRE.
    target = pos + aim / dist + np.array([0.0, np.tan(axis_to_centre), 0.0])
    pose = look_at_pose(pos, target)
    proj = Projector(intr, pose, intensity=intensity, input_size=PROJECTOR_INPUT)
    if (width, height) != PROJECTOR_SIZE:
        proj = proj.scaled(width, height)
    return proj


def demo_rig(camera_size: tuple[int, int] = CAMERA_SIZE, projector_size: tuple[int, int] = PROJECTOR_SIZE) -> Rig:
    """The demo rig, optionally at smaller resolutions for tests (same lenses and poses)."""
    return Rig(demo_camera(*camera_size), demo_projector(*projector_size))
