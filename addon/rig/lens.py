"""Camera lenses: the calibrated lens taken out of photographs (:class:`RigLens`), and the lens model the
diagnosis fits: OpenCV's distortion (k1, k2 radial; p1, p2 tangential) undone by OpenCV's fixed-point iteration,
on normalised image coordinates.

Where else a lens is modelled, and why not here:

* a lens a rig calibration measured (``rig.model.Projector.undistort``,
  :class:`RigLens` below) goes through OpenCV's own functions, with all of its
  coefficients;
* the lab's camera lens (``lab/effects.py``) is the truth the diagnosis must
  find, and is written apart on purpose: it inverts the lens exactly (Newton
  on the radius), where this iteration stops after a few steps; sharing the
  code would make the diagnosis's approximation part of the truth it is
  measured against.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np

from .model import Intrinsics


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


@dataclass(frozen=True)
class RigLens:
    """A calibrated camera lens to take out of photographs: its pinhole intrinsics and OpenCV's k1 k2 p1 p2 k3."""

    camera: Intrinsics
    distortion: np.ndarray
    source: str  # where it comes from, for the capture set's notes
    pose_known: bool = False  # the rig file also gives the projector's metric pose

    @property
    def pinhole(self) -> Intrinsics:
        """The pinhole camera the photographs become: the lens's K with square pixels (f = √(fx·fy)), because the
        renderer's camera has them; a calibrated fx and fy differ a little (0.05 % on the real board photos)."""
        f = math.sqrt(self.camera.fx * self.camera.fy)
        return replace(self.camera, fx=f, fy=f)

    def image(self, img: np.ndarray, *, nearest: bool = False) -> np.ndarray:
        """``img`` as the :attr:`pinhole` camera would see it (pixels from outside the frame are 0).

        A depth map smaller than the photographs (same lens, aligned) gets K scaled to its size."""
        a = np.asarray(img, dtype=np.float32)
        h, w = a.shape[:2]
        k = self.camera.scaled(w, h).opencv_matrix()
        mx, my = cv2.initUndistortRectifyMap(k, self.distortion, None, self.pinhole.scaled(w, h).opencv_matrix(),
                                             (w, h), cv2.CV_32FC1)
        out = cv2.remap(a, mx, my, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return out.reshape(a.shape)

    def to_dict(self) -> dict[str, Any]:
        """As a capture set records it (``camera_lens_removed``)."""
        return {"camera": self.camera.to_dict(), "distortion": [float(v) for v in np.ravel(self.distortion)],
                "source": self.source}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> RigLens:
        return RigLens(Intrinsics.from_dict(d["camera"]), np.asarray(d["distortion"], np.float64), str(d["source"]))
