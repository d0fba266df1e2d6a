"""The built-in demo rig, shaped like the paper's set-up (camera 640×480, projector 800×600 with a
vertical lens shift, projector input 600×600 centred in the frame)."""

from __future__ import annotations

import numpy as np

from .model import (Camera, Intrinsics, Projector, Rig, intrinsics_from_fov, look_at_pose,
                    projector_intrinsics_from_throw)

CAMERA_SIZE = (640, 480)
PROJECTOR_SIZE = (800, 600)
PROJECTOR_INPUT = (600, 600)
#: Projector below and right of the camera, image shifted up by 15 % of its height (cy 10 % + off centre).
PROJECTOR_POSITION = (0.22, 0.12, 0.05)
PROJECTOR_THROW = 1.25
PROJECTOR_SHIFT_Y = 0.15
SURFACE_CENTRE = (0.0, 0.0, 1.7)


def _same_aspect(size: tuple[int, int], base: tuple[int, int]) -> bool:
    return abs(size[0] * base[1] - size[1] * base[0]) <= max(base)  # within a pixel's rounding of the base's


def demo_camera(width: int = CAMERA_SIZE[0], height: int = CAMERA_SIZE[1]) -> Camera:
    """The demo camera (58° across); at another aspect than 4:3 its pixels stay square (the same width's field)."""
    if not _same_aspect((width, height), CAMERA_SIZE):
        return Camera(intrinsics_from_fov(width, height, 58.0))
    return Camera(intrinsics_from_fov(CAMERA_SIZE[0], CAMERA_SIZE[1], 58.0).scaled(width, height))


def _centre_ray(intr: Intrinsics) -> np.ndarray:
    return intr.rays(np.array([[intr.width / 2, intr.height / 2]]))[0]


def demo_projector(width: int = PROJECTOR_SIZE[0], height: int = PROJECTOR_SIZE[1], intensity: float = 2.5,
                   shift: tuple[float, float] = (0.0, PROJECTOR_SHIFT_Y)) -> Projector:
    """The demo projector; ``shift`` (right, up, fractions of the image) changes its lens shift, and it is aimed so
    that the image still lands on the surface. At another aspect than 4:3 (1920×1080) its pixels stay square: the
    same throw and shift at that resolution, the input the same share of the frame (¾ of its width, its height)."""
    other = not _same_aspect((width, height), PROJECTOR_SIZE)
    intr: Intrinsics = projector_intrinsics_from_throw(*((width, height) if other else PROJECTOR_SIZE),
                                                       PROJECTOR_THROW, *shift)
    # Aim so that the *shifted* image centre, not the lens axis, lands on the surface centre: move the look-at target
    # against the centre ray's offset from the axis (its x, y at z = 1).
    pos = np.asarray(PROJECTOR_POSITION)
    centre_ray = _centre_ray(intr)
    aim = np.asarray(SURFACE_CENTRE) - pos
    target = pos + aim / np.linalg.norm(aim) - np.array([centre_ray[0], centre_ray[1], 0.0])
    pose = look_at_pose(pos, target)
    # Light leaves a projector at θ from its axis with intensity ∝ 1/cos³θ (its image plane is lit evenly), so a
    # larger shift brightens the image; keep the image centre as bright as with the demo's own shift.
    default = projector_intrinsics_from_throw(PROJECTOR_SIZE[0], PROJECTOR_SIZE[1], PROJECTOR_THROW, 0.0,
                                              PROJECTOR_SHIFT_Y)
    intensity *= (np.linalg.norm(_centre_ray(intr)) / np.linalg.norm(_centre_ray(default))) ** -3
    if other:
        return Projector(intr, pose, intensity=intensity,
                         input_size=(round(width * PROJECTOR_INPUT[0] / PROJECTOR_SIZE[0]), height))
    proj = Projector(intr, pose, intensity=intensity, input_size=PROJECTOR_INPUT)
    if (width, height) != PROJECTOR_SIZE:
        proj = proj.scaled(width, height)
    return proj


def demo_rig(camera_size: tuple[int, int] = CAMERA_SIZE, projector_size: tuple[int, int] = PROJECTOR_SIZE) -> Rig:
    """The demo rig, optionally at smaller resolutions for tests (same lenses and poses)."""
    return Rig(demo_camera(*camera_size), demo_projector(*projector_size))
