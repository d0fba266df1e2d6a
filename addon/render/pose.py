"""Small pose updates (translation + rotation vector) shared by numpy code and Dr.Jit gradients.

A pose delta ``d = (tx, ty, tz, wx, wy, wz)`` moves a device pose
``camera_from_device = [R | t]`` to ``[ΔR(w) · R | t + (tx, ty, tz)]``: the
device turns about its own centre, with the rotation axis expressed in the rig
frame, and then shifts in the rig frame. Translation is in metres, rotation in
radians.

``ΔR(w)`` is the rotation of the unit quaternion ``normalise(w/2, 1)``. To
first order it equals the exponential map ``exp([w]×)`` (the usual rotation
vector), and unlike Rodrigues' formula it has no ``0/0`` at ``w = 0``, so its
Dr.Jit derivative is finite exactly where optimisers start. For ``|w|`` of a
few degrees the rotation angle ``2·atan(|w|/2)`` differs from ``|w|`` by less
than ``|w|³/12``; code that folds a delta back into a pose uses
:func:`apply_pose_delta`, which uses the same map, so nothing is lost.
"""

from __future__ import annotations

from typing import Any
from collections.abc import Sequence

import numpy as np

from ..errors import RigError


def delta_rotation(w: Sequence[Any]) -> list[list[Any]]:
    """3×3 rotation (nested lists) for a rotation vector; works on floats and Dr.Jit arrays alike."""
    x, y, z = (w[0] * 0.5, w[1] * 0.5, w[2] * 0.5)
    n2 = x * x + y * y + z * z + 1.0
    s = 2.0 / n2  # quaternion (x, y, z, 1)/sqrt(n2): products pick up 1/n2
    return [[1.0 - s * (y * y + z * z), s * (x * y - z), s * (x * z + y)],
            [s * (x * y + z), 1.0 - s * (x * x + z * z), s * (y * z - x)],
            [s * (x * z - y), s * (y * z + x), 1.0 - s * (x * x + y * y)]]


def apply_pose_delta(camera_from_device: np.ndarray, delta: Sequence[float]) -> np.ndarray:
    """The pose moved by a delta (numpy); the same map as the Dr.Jit path in the forward model."""
    d = np.asarray(delta, dtype=np.float64).reshape(-1)
    if d.shape != (6,) or not np.all(np.isfinite(d)):
        raise RigError("a pose delta is 6 finite numbers (translation xyz in m, rotation vector in rad), "
                       f"got {delta!r}")
    pose = np.asarray(camera_from_device, dtype=np.float64).copy()
    r = np.array(delta_rotation(d[3:]), dtype=np.float64)
    pose[:3, :3] = r @ pose[:3, :3]
    pose[:3, 3] += d[:3]
    return pose
