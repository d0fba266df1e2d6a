"""The lens model the diagnosis fits: OpenCV's distortion (k1, k2 radial; p1, p2 tangential) undone by OpenCV's
fixed-point iteration, on normalised image coordinates.

Where else a lens is modelled, and why not here:

* a lens a rig calibration measured (``rig.model.Projector.undistort``,
  ``capture.devices.RigLens``) goes through OpenCV's own functions, with all
  of its coefficients;
* the lab's camera lens (``lab/effects.py``) is the truth the diagnosis must
  find, and is written apart on purpose: it inverts the lens exactly (Newton
  on the radius), where this iteration stops after a few steps; sharing the
  code would make the diagnosis's approximation part of the truth it is
  measured against.
"""

from __future__ import annotations

import numpy as np


def undistort_normalised(xd: np.ndarray, yd: np.ndarray, k1: float, k2: float, p1: float = 0.0, p2: float = 0.0,
                         *, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Ideal normalised coordinates whose distortion lands on (xd, yd): ``steps`` fixed-point steps of
    ``x_u ← (x_d − tangential(x_u)) / (1 + k1 r² + k2 r⁴)`` from ``x_u = x_d`` (as ``cv2.undistortPoints``)."""
    xu, yu = xd, yd
    for _ in range(steps):
        r2 = xu * xu + yu * yu
        f = 1 + k1 * r2 + k2 * r2 * r2
        if p1 == 0.0 and p2 == 0.0:
            xu, yu = xd / f, yd / f
        else:
            tx = 2 * p1 * xu * yu + p2 * (r2 + 2 * xu * xu)
            ty = p1 * (r2 + 2 * yu * yu) + 2 * p2 * xu * yu
            xu, yu = (xd - tx) / f, (yd - ty) / f
    return xu, yu


__all__ = ["undistort_normalised"]
