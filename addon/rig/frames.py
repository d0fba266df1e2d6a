"""The one place that converts between the rig (OpenCV) frame, Blender and Mitsuba.

* Rig frame: the camera's OpenCV frame (x right, y down, z forward, metres).
* Blender world: z up. We place the rig so that the camera looks along +Y
  with +Z up, which is how an artist expects a scene to stand:
  ``blender = (x_rig, z_rig, -y_rig)``.
* Blender camera and light objects look down their local −Z with +Y up:
  local axes = OpenCV axes · diag(1, −1, −1).
* Mitsuba world = rig frame; Mitsuba sensors/emitters look along local +z with
  +y up and +x to the *left*: ``to_world = [R · diag(−1, −1, 1) | t]``.
* Blender camera intrinsics: sensor fit HORIZONTAL, so focal length and shift
  are both in units of the image width (Blender's ``viewfac``).
"""

from __future__ import annotations

import numpy as np

from ..errors import RigError
from .model import Intrinsics

BLENDER_FROM_RIG = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0], [0, 0, 0, 1.0]])
RIG_FROM_BLENDER = BLENDER_FROM_RIG.T.copy()
_CV_TO_BLENDER_LOCAL = np.diag([1.0, -1.0, -1.0, 1.0])
_CV_TO_MITSUBA_LOCAL = np.diag([-1.0, -1.0, 1.0, 1.0])

#: Nominal sensor width (mm) of Blender cameras we create; only lens/sensor matters.
SENSOR_WIDTH_MM = 36.0


def blender_matrix_world(camera_from_device: np.ndarray) -> np.ndarray:
    """Blender ``matrix_world`` of a camera/light object for a device pose in the rig frame."""
    return BLENDER_FROM_RIG @ np.asarray(camera_from_device, dtype=np.float64) @ _CV_TO_BLENDER_LOCAL


def pose_from_blender_matrix(matrix_world: np.ndarray) -> np.ndarray:
    """Rig-frame pose (camera_from_device) of a Blender camera/light object; scale is removed."""
    m = np.asarray(matrix_world, dtype=np.float64).copy()
    norms = np.linalg.norm(m[:3, :3], axis=0)
    if np.any(norms < 1e-12):
        raise RigError("the object's transform has zero scale")
    m[:3, :3] /= norms
    pose = RIG_FROM_BLENDER @ m @ _CV_TO_BLENDER_LOCAL
    u, _, vt = np.linalg.svd(pose[:3, :3])  # re-orthonormalise shear from non-uniform parent scale
    pose[:3, :3] = u @ vt
    return pose


def blender_points(points_rig: np.ndarray) -> np.ndarray:
    """N×3 rig-frame points to Blender world coordinates."""
    p = np.asarray(points_rig, dtype=np.float64).reshape(-1, 3)
    return p @ BLENDER_FROM_RIG[:3, :3].T


def rig_points(points_blender: np.ndarray) -> np.ndarray:
    """N×3 Blender world points to the rig frame."""
    p = np.asarray(points_blender, dtype=np.float64).reshape(-1, 3)
    return p @ RIG_FROM_BLENDER[:3, :3].T


def mitsuba_to_world(camera_from_device: np.ndarray) -> np.ndarray:
    """Mitsuba ``to_world`` (4×4) of a sensor/emitter for a device pose in the rig frame."""
    return np.asarray(camera_from_device, dtype=np.float64) @ _CV_TO_MITSUBA_LOCAL


def blender_camera_params(intr: Intrinsics) -> dict[str, float | str]:
    """Blender camera data settings (with render resolution = intrinsics size) that reproduce K."""
    if not intr.square_pixels:
        raise RigError(f"Blender cameras need square pixels; this camera has fx={intr.fx:.3f}, fy={intr.fy:.3f}")
    w, h = intr.size
    return {"sensor_fit": "HORIZONTAL", "sensor_width": SENSOR_WIDTH_MM,
            "lens": intr.fx * SENSOR_WIDTH_MM / w,
            "shift_x": (w / 2 - intr.cx) / w, "shift_y": (intr.cy - h / 2) / w}


def intrinsics_from_blender_camera(lens: float, sensor_width: float, sensor_height: float, sensor_fit: str,
                                   shift_x: float, shift_y: float, width: int, height: int,
                                   pixel_aspect: float = 1.0) -> Intrinsics:
    """K of a Blender camera at a render resolution (inverse of :func:`blender_camera_params`)."""
    if abs(pixel_aspect - 1.0) > 1e-9:
        raise RigError("non-square render pixels (pixel aspect ≠ 1) are not supported")
    fit = sensor_fit
    if fit == "AUTO":
        fit = "HORIZONTAL" if width >= height else "VERTICAL"
    if fit == "HORIZONTAL":
        viewfac, sensor = width, sensor_width
    else:
        viewfac, sensor = height, sensor_height
    f = lens / sensor * viewfac
    return Intrinsics(int(width), int(height), f, f, width / 2 - shift_x * viewfac, height / 2 + shift_y * viewfac)
