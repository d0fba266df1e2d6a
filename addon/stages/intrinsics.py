"""The projector's intrinsics from the capture set itself, without a printed board.

A calibration capture set with depth and Gray code holds, for every decoded
camera pixel on the surface, a 3-D point (rig frame) and the projector pixel
that lit it. On a curved or edged surface those points are not coplanar, so a
single view determines the projector's focal length and principal point
together with its pose (a plane does not: it leaves focal length and distance,
or principal point and rotation, trading against each other). We fit them with
OpenCV's camera calibration on that one non-planar view, starting from the
spec sheet (throw ratio, lens shift):

* aspect ratio fixed at the spec's (fx/fy is the pixel shape, which a spec gets
  right), no skew; projector lens distortion is not fitted (stage B's warp takes
  what is left of it);
* outliers (decoding errors at pattern edges) are dropped in two rounds;
* each value's standard deviation comes from the fit's covariance. A value is
  *determined* when its deviation is below :data:`FOCAL_STD_MAX` of the focal
  length or :data:`CENTRE_STD_MAX_PX` pixels. The fit is used only when both
  are; otherwise the spec stays whole, because a value fitted with another
  held at a wrong spec moves to compensate it (measured: on a plane, a
  principal point fitted with the focal length held 10 % off put the pose
  15 cm off, against 23 cm with the spec, and lowered the compensation's PSNR).

The camera's intrinsics stay as given: the 3-D points are made with them (the
depth image is unprojected through the camera's K), so this view cannot tell a
wrong camera K from a wrong surface. A printed board (``procam calibrate-rig``)
is the way to calibrate the camera.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..capture.format import CaptureSet
from ..errors import CalibrationError
from ..rig.model import Intrinsics
from .pose import MIN_CORRESPONDENCES, SurfaceView, graycode_correspondences

#: Largest standard deviation of the focal length (share of it) for it to count as determined.
FOCAL_STD_MAX = 0.005
#: Largest standard deviation of the principal point (pixels of the native frame) for it to count as determined.
CENTRE_STD_MAX_PX = 2.0
#: Points used in the fit (a random subset of the decoded pixels): enough for sub-pixel statistics, fast to fit.
FIT_POINTS = 20000

_NO_DISTORTION = (cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)


@dataclass(frozen=True)
class IntrinsicsFit:
    """The projector's intrinsics found from the captures, and what the data could and could not tell."""

    nominal: Intrinsics
    fitted: Intrinsics
    std: dict[str, float]  # standard deviations of fx, cx, cy from the free fit (pixels)
    determined: dict[str, bool]  # 'focal', 'principal_point'
    rms_nominal_px: float  # reprojection RMS with the spec's K (pose refitted)
    rms_fitted_px: float
    points: int
    inliers: int

    def summary(self) -> str:
        n, f = self.nominal, self.fitted
        spread = (f"focal ±{self.std['fx']:.1f} px, principal point ±{self.std['cx']:.1f}, ±{self.std['cy']:.1f} px")
        if not all(self.determined.values()):
            unknown = [name.replace("_", " ") for name, ok in self.determined.items() if not ok]
            return (f"kept at the spec (focal {n.fx:.1f} px, principal point ({n.cx:.1f}, {n.cy:.1f})): this surface "
                    f"does not determine the {' and '.join(unknown)} (the data leave {spread}; a flat surface never "
                    "does: use a curved or edged one, or procam calibrate-rig)")
        return (f"focal {n.fx:.1f} → {f.fx:.1f} px ({100 * (f.fx / n.fx - 1):+.2f} %), principal point "
                f"({n.cx:.1f}, {n.cy:.1f}) → ({f.cx:.1f}, {f.cy:.1f}) px ({spread}); reprojection RMS "
                f"{self.rms_nominal_px:.2f} → {self.rms_fitted_px:.2f} px")

    def to_dict(self) -> dict[str, Any]:
        return {"nominal": self.nominal.to_dict(), "fitted": self.fitted.to_dict(),
                "std_px": {k: float(v) for k, v in self.std.items()}, "determined": dict(self.determined),
                "rms_nominal_px": self.rms_nominal_px, "rms_fitted_px": self.rms_fitted_px,
                "points": self.points, "inliers": self.inliers, "summary": self.summary()}


def _fit(obj: np.ndarray, img: np.ndarray, k: Intrinsics, flags: int) -> tuple[Intrinsics, np.ndarray, float]:
    """One calibration of a single non-planar view from ``k``: (intrinsics, std devs of f cx cy, rms px)."""
    try:
        rms, km, _, rvecs, tvecs = cv2.calibrateCamera(
            [obj.astype(np.float32)], [img.astype(np.float32)], k.size, k.opencv_matrix(), np.zeros(5), flags=flags,
            criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-10))
    except cv2.error as exc:
        raise CalibrationError(f"fitting the projector's intrinsics failed in OpenCV: {exc.msg.strip()}") from None
    fitted = Intrinsics(k.width, k.height, float(km[0, 0]), float(km[1, 1]), float(km[0, 2]) + 0.5,
                        float(km[1, 2]) + 0.5)
    return fitted, _std(obj, img, km, rvecs[0], tvecs[0]), float(rms)


def _std(obj: np.ndarray, img: np.ndarray, km: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """Standard deviations of (f, cx, cy) with the pose free, from the reprojection Jacobian.

    OpenCV's own (``calibrateCameraExtended``) inverts JᵀJ by SVD, which zeroes
    the variance along a degenerate direction, so a flat surface would look as
    if it determined everything; we invert the 9×9 normal matrix ourselves and
    let a degenerate direction show as a huge deviation.
    """
    proj, jac = cv2.projectPoints(obj, rvec, tvec, km, np.zeros(5))
    resid = proj.reshape(-1, 2) - img
    sigma2 = float(np.sum(resid ** 2) / max(1, resid.size - 9))
    # Columns: rvec 3, tvec 3, fx, fy, cx, cy, distortion…; f moves fx and fy together (aspect ratio fixed).
    j = np.concatenate([jac[:, :6], (jac[:, 6] * km[0, 0] + jac[:, 7] * km[1, 1])[:, None] / km[0, 0],
                        jac[:, 8:10]], axis=1)
    normal = j.T @ j
    scale = np.sqrt(np.diag(normal))
    try:
        cov = np.linalg.inv(normal / np.outer(scale, scale)) / np.outer(scale, scale)
    except np.linalg.LinAlgError:
        return np.full(3, np.inf)
    return np.sqrt(np.maximum(np.diag(cov)[6:9], 0.0) * sigma2)


def _residuals(obj: np.ndarray, img: np.ndarray, k: Intrinsics) -> np.ndarray:
    """Reprojection error (px) of each point after PnP with ``k`` (the pose refitted for this K)."""
    km = k.opencv_matrix()
    ok, rvec, tvec = cv2.solvePnP(obj, img, km, None, flags=cv2.SOLVEPNP_EPNP)
    if not ok:
        raise CalibrationError("the Gray-code correspondences admit no projector pose; check the captures")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, km, None, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, km, None)
    return np.linalg.norm(proj.reshape(-1, 2) - img, axis=1)


def estimate_projector_intrinsics(captures: CaptureSet, view: SurfaceView, mask: np.ndarray, *,
                                  seed: int = 0) -> IntrinsicsFit:
    """Fit the projector's focal length and principal point to the capture set's Gray code (module doc)."""
    nominal = captures.projector.intrinsics
    obj, img, _ = graycode_correspondences(captures, view, mask, max_points=FIT_POINTS, seed=seed)
    keep = np.ones(len(obj), bool)
    free = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_ASPECT_RATIO | _NO_DISTORTION
    k = nominal
    # Two rounds of outlier rejection: a wrong spec leaves residuals of several pixels, so the first threshold is
    # loose and set by the data (robust spread), the second tight.
    for _ in range(2):
        k, std, _ = _fit(obj[keep], img[keep], k, free)
        res = _residuals(obj, img, k)
        spread = 1.4826 * np.median(np.abs(res - np.median(res)))
        keep = res < max(1.0, np.median(res) + 4.0 * spread)
        if keep.sum() < MIN_CORRESPONDENCES:
            raise CalibrationError(f"too few consistent Gray-code correspondences in {captures.path} "
                                   f"({int(keep.sum())}) to fit the projector's intrinsics; use the spec's")
    k, std, _ = _fit(obj[keep], img[keep], k, free)
    std_d = {"fx": float(std[0]), "cx": float(std[1]), "cy": float(std[2])}
    determined = {"focal": std_d["fx"] < FOCAL_STD_MAX * k.fx,
                  "principal_point": max(std_d["cx"], std_d["cy"]) < CENTRE_STD_MAX_PX}
    if not all(determined.values()):
        # Measured on the lab's plane: its principal point looks determined alone, but only given the focal
        # length; fitted with a wrong spec's focal length it moves to compensate it and the pose gets worse than
        # with the spec. So either the data determine both, or the spec stays as it is.
        k = nominal
    rms = lambda kk: float(np.sqrt(np.mean(_residuals(obj[keep], img[keep], kk) ** 2)))  # noqa: E731
    return IntrinsicsFit(nominal, k, std_d, determined, rms(nominal), rms(k), int(len(obj)), int(keep.sum()))
