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

The camera's focal length is fitted with them too, and used only where the
data determine it (σ below :data:`CAMERA_FOCAL_STD_MAX`): the 3-D points are
made with it, and a wrong one scales them across the view, which only a
projector whose axis converges with the camera's can see (see the fit's
comment). Its principal point stays as given. A printed board
(``procam calibrate-rig``) is the way to calibrate the camera fully.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..capture.format import CaptureSet
from ..errors import CalibrationError
from ..rig.model import Intrinsics
from .pose import MIN_CORRESPONDENCES, SurfaceView, graycode_correspondences, pnp_ransac

#: Largest standard deviation of the focal length (share of it) for it to count as determined.
FOCAL_STD_MAX = 0.005
#: Largest standard deviation of the principal point (pixels of the native frame) for it to count as determined.
CENTRE_STD_MAX_PX = 2.0
#: Largest standard deviation of the camera's k1 for the camera's distortion to count as determined.
DISTORTION_STD_MAX = 0.005
#: Points used in the fit (a random subset of the decoded pixels): enough for sub-pixel statistics, fast to fit.
FIT_POINTS = 20000

#: Largest standard deviation of the camera's focal-length factor for it to count as determined.
CAMERA_FOCAL_STD_MAX = 0.005

#: Parameter order of the fit: projector f, cx, cy (OpenCV), pose (rvec, tvec), camera k1, k2, camera focal factor.
_NO_LENS = np.arange(9)
_LENS = np.arange(11)
_CAMERA_FOCAL = np.arange(12)
_POSE = np.arange(3, 9)


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
    #: the camera's radial distortion fitted with them: k1, k2, their std, and whether the data determine it
    camera_distortion: dict[str, Any] = field(default_factory=dict)
    #: the projector's pose from the same fit (None when the spec is kept): stage A starts and stays there
    camera_from_projector: np.ndarray | None = None
    #: the camera's focal length fitted with them: factor on the given one, its std, whether determined
    camera_focal: dict[str, Any] = field(default_factory=dict)

    def camera(self, given: Intrinsics) -> Intrinsics | None:
        """The camera's intrinsics with the fitted focal length, or None when the data do not determine it."""
        if not self.camera_focal.get("determined"):
            return None
        g = float(self.camera_focal["factor"])
        return Intrinsics(given.width, given.height, given.fx * g, given.fy * g, given.cx, given.cy)

    def summary(self) -> str:
        n, f = self.nominal, self.fitted
        spread = (f"focal ±{self.std['fx']:.1f} px, principal point ±{self.std['cx']:.1f}, ±{self.std['cy']:.1f} px")
        if not all(self.determined.values()):
            unknown = [name.replace("_", " ") for name, ok in self.determined.items() if not ok]
            return (f"kept at the spec (focal {n.fx:.1f} px, principal point ({n.cx:.1f}, {n.cy:.1f})): this surface "
                    f"does not determine the {' and '.join(unknown)} (the data leave {spread}; a flat surface never "
                    "does: use a curved or edged one, or procam calibrate-rig)")
        lens, cf = self.camera_distortion, self.camera_focal
        focal = ""
        if cf:
            focal = (f"; camera focal length fitted with them: {cf['given_fx']:.1f} → {cf['fitted_fx']:.1f} px "
                     f"({100 * (cf['factor'] - 1):+.2f} % ±{100 * cf['std']:.2f} %)" if cf.get("determined") else
                     f"; camera focal length not determined by this surface (±{100 * cf['std']:.1f} %: kept as "
                     "given; if it is wrong the projector's focal length takes it up, so calibrate the camera "
                     "with a board)")
        camera = (f"; camera lens distortion fitted with them: {lens['edge_displacement_px']:+.2f} px at "
                  f"{lens['edge_radius_px']:.0f} px from the centre (k1 {lens['k1']:+.4f}, k2 {lens['k2']:+.4f})"
                  if lens.get("determined") else
                  "; camera lens distortion not determined by this surface (assumed none)")
        return (f"focal {n.fx:.1f} → {f.fx:.1f} px ({100 * (f.fx / n.fx - 1):+.2f} %), principal point "
                f"({n.cx:.1f}, {n.cy:.1f}) → ({f.cx:.1f}, {f.cy:.1f}) px ({spread}){camera}; reprojection RMS "
                f"{self.rms_nominal_px:.2f} → {self.rms_fitted_px:.2f} px{focal}")

    def to_dict(self) -> dict[str, Any]:
        return {"nominal": self.nominal.to_dict(), "fitted": self.fitted.to_dict(),
                "std_px": {k: float(v) for k, v in self.std.items()}, "determined": dict(self.determined),
                "rms_nominal_px": self.rms_nominal_px, "rms_fitted_px": self.rms_fitted_px,
                "points": self.points, "inliers": self.inliers, "camera_distortion": dict(self.camera_distortion),
                "camera_from_projector": None if self.camera_from_projector is None
                else np.asarray(self.camera_from_projector).tolist(), "camera_focal": dict(self.camera_focal),
                "summary": self.summary()}


def _projector_matrix(x: np.ndarray, aspect: float) -> np.ndarray:
    """The projector's OpenCV K from the fit's parameters (f, cx, cy first; fy = f · aspect)."""
    f, cx, cy = x[:3]
    return np.array([[f, 0.0, cx], [0.0, f * aspect, cy], [0.0, 0.0, 1.0]])


class _GrayCodeView:
    """Decoded Gray code with the camera's radial lens distortion in the loop.

    The capture set's depth is a pinhole camera's image (``DepthInfo``'s K), the
    photographs are the real lens's: a decoded camera pixel sees the surface
    point on the ray of its *undistorted* position, at the depth found there.
    """

    def __init__(self, camera_px: np.ndarray, projector_px: np.ndarray, depth: np.ndarray, camera: Intrinsics,
                 aspect: float) -> None:
        self.centres = (np.asarray(camera_px, np.float64) - 0.5).reshape(-1, 1, 2)  # OpenCV's pixel centres
        self.target = np.asarray(projector_px, np.float64)
        self.depth = np.ascontiguousarray(depth, dtype=np.float32)
        self.kc = camera.opencv_matrix()
        self.aspect = aspect

    def points(self, k1: float, k2: float, focal: float = 1.0) -> np.ndarray:
        """N×3 surface points (rig frame) the decoded pixels see through a lens with k1, k2 and the camera's focal
        length ``focal`` times the given one; NaN where none.

        The depth is looked up at the undistorted pixel, which does not depend on the focal length: the surface
        was made from the depth with the given K and is seen through the same K, so each pixel keeps its depth.
        """
        crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 30, 1e-12)
        kc = self.kc.copy()
        kc[0, 0] *= focal
        kc[1, 1] *= focal
        xn = cv2.undistortPointsIter(self.centres, kc, np.array([k1, k2, 0.0, 0.0]), None, None,
                                     crit).reshape(-1, 2)
        u = xn[:, 0] * kc[0, 0] + kc[0, 2]
        v = xn[:, 1] * kc[1, 1] + kc[1, 2]
        z = cv2.remap(self.depth, u.astype(np.float32)[None, :], v.astype(np.float32)[None, :], cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan")).ravel().astype(np.float64)
        return np.column_stack([xn * z[:, None], z])

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Projector-pixel residuals (2N) for x = f, cx, cy (OpenCV), rvec, tvec, camera k1, k2, camera focal
        factor."""
        km = _projector_matrix(x, self.aspect)
        pts = self.points(x[9], x[10], x[11])
        ok = np.isfinite(pts[:, 2])
        proj, _ = cv2.projectPoints(np.where(ok[:, None], pts, 1.0), x[3:6], x[6:9], km, None)
        r = proj.reshape(-1, 2) - self.target
        r[~ok] = 0.0  # a point that leaves the surface adds nothing (rare: the set is fixed at the start)
        return r.ravel()


def _levenberg_marquardt(fun, x0: np.ndarray, steps: np.ndarray, free: np.ndarray, iterations: int = 60
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Minimise |fun(x)|² over ``x[free]`` from x0 (forward-difference Jacobian with ``steps``, Marquardt's
    damping); returns x, the residuals and the Jacobian (free columns) at x."""
    x = np.asarray(x0, np.float64).copy()
    r = fun(x)
    lam = 1e-3

    def jacobian(x: np.ndarray, r: np.ndarray) -> np.ndarray:
        cols = []
        for i in free:
            e = np.zeros_like(x)
            e[i] = steps[i]
            cols.append((fun(x + e) - r) / steps[i])
        return np.column_stack(cols)

    j = jacobian(x, r)
    for _ in range(iterations):
        a, g = j.T @ j, j.T @ r
        improved = False
        while lam < 1e10:
            dx = np.zeros_like(x)
            dx[free] = np.linalg.solve(a + lam * np.diag(np.diag(a) + 1e-300), -g)
            r_new = fun(x + dx)
            if r_new @ r_new < r @ r:
                x, r, lam, improved = x + dx, r_new, lam / 3.0, True
                break
            lam *= 4.0
        if not improved or np.all(np.abs(dx[free]) < 1e-3 * steps[free]):
            break
        j = jacobian(x, r)
    return x, r, j


def _covariance_std(j: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Standard deviations of the parameters from the Jacobian (degenerate directions show as huge ones)."""
    sigma2 = float(r @ r) / max(1, len(r) - j.shape[1])
    normal = j.T @ j
    scale = np.sqrt(np.maximum(np.diag(normal), 1e-300))
    try:
        cov = np.linalg.inv(normal / np.outer(scale, scale)) / np.outer(scale, scale)
    except np.linalg.LinAlgError:
        return np.full(j.shape[1], np.inf)
    return np.sqrt(np.maximum(np.diag(cov), 0.0) * sigma2)


def _start_pose(obj: np.ndarray, img: np.ndarray, k: Intrinsics, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A first projector pose with the spec's K (robust: Gray code has decoding outliers; the K may be off, so the
    inlier threshold is loose)."""
    ok, rvec, tvec, inliers = pnp_ransac(obj, img, k.opencv_matrix(), max(2.0, 0.02 * k.width), seed)
    if not ok or inliers is None or len(inliers) < MIN_CORRESPONDENCES:
        raise CalibrationError("the Gray-code correspondences admit no projector pose to start the intrinsics fit "
                               "from; check the captures, or keep the spec (--projector-intrinsics spec)")
    return np.ravel(rvec), np.ravel(tvec)


def _camera_from_projector(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    p_from_c = np.eye(4)
    p_from_c[:3, :3], p_from_c[:3, 3] = cv2.Rodrigues(np.asarray(rvec, np.float64))[0], np.ravel(tvec)
    pose = np.linalg.inv(p_from_c)
    pose[3] = (0.0, 0.0, 0.0, 1.0)
    return pose


def _point_rms(r: np.ndarray) -> float:
    return float(np.sqrt(2.0 * np.mean(r ** 2)))


def estimate_projector_intrinsics(captures: CaptureSet, view: SurfaceView, mask: np.ndarray, *,
                                  seed: int = 0) -> IntrinsicsFit:
    """Fit the projector's focal length and principal point, and the camera's radial distortion, to the capture
    set's Gray code (module doc)."""
    nominal = captures.projector.intrinsics
    obj, img, cam_px, _ = graycode_correspondences(captures, view, mask, max_points=FIT_POINTS, seed=seed)
    depth, camera, aspect = view.points[..., 2], captures.camera.intrinsics, nominal.fy / nominal.fx
    rvec, tvec = _start_pose(obj, img, nominal, seed)
    km = nominal.opencv_matrix()
    x0 = np.concatenate([[km[0, 0], km[0, 2], km[1, 2]], rvec, tvec, [0.0, 0.0, 1.0]])
    scale = float(np.nanmedian(np.abs(obj[:, 2])))
    steps = np.array([1e-4 * km[0, 0], 0.01, 0.01, 1e-6, 1e-6, 1e-6, 1e-6 * scale, 1e-6 * scale, 1e-6 * scale,
                      1e-5, 1e-5, 1e-5])
    everything = _GrayCodeView(cam_px, img, depth, camera, aspect)
    x, keep = x0, np.ones(len(obj), bool)
    # Two rounds of outlier rejection (decoding errors at pattern edges): a wrong spec leaves residuals of several
    # pixels, so the first threshold is loose and set by the data (robust spread), the second tight.
    for _ in range(2):
        x, _, _ = _levenberg_marquardt(_GrayCodeView(cam_px[keep], img[keep], depth, camera, aspect).residuals,
                                       x, steps, _NO_LENS)
        res = np.linalg.norm(everything.residuals(x).reshape(-1, 2), axis=1)
        spread = 1.4826 * np.median(np.abs(res - np.median(res)))
        keep = res < max(1.0, np.median(res) + 4.0 * spread)
        if keep.sum() < MIN_CORRESPONDENCES:
            raise CalibrationError(f"too few consistent Gray-code correspondences in {captures.path} "
                                   f"({int(keep.sum())}) to fit the projector's intrinsics; keep the spec "
                                   "(--projector-intrinsics spec)")
    gv = _GrayCodeView(cam_px[keep], img[keep], depth, camera, aspect)
    _, r_nominal, _ = _levenberg_marquardt(gv.residuals, x0, steps, _POSE)  # the spec's K, its best pose
    x, r, j = _levenberg_marquardt(gv.residuals, x, steps, _NO_LENS)
    sd = _covariance_std(j, r)
    lens: dict[str, Any] = {"k1": 0.0, "k2": 0.0, "std_k1": None, "std_k2": None, "determined": False}
    # Then the camera's radial distortion with them: the photographs' lens bends the decoded pixels' rays, and a
    # projector fitted without it takes the bend into its focal length (measured: -2.6 % on the lab's curve with
    # its realistic k1 = -0.036).
    x_lens, r_lens, j_lens = _levenberg_marquardt(gv.residuals, x, steps, _LENS)
    sd_lens = _covariance_std(j_lens, r_lens)
    lens.update(std_k1=float(sd_lens[9]), std_k2=float(sd_lens[10]))
    if sd_lens[9] < DISTORTION_STD_MAX and np.isfinite(x_lens).all():
        x, r, sd = x_lens, r_lens, sd_lens
        # k1 and k2 trade against each other over the lit part of the image; the displacement they give at its
        # edge is what the data pin down, so that is what the report leads with.
        xn = (cam_px[keep] - (camera.cx, camera.cy)) / (camera.fx, camera.fy)
        r_max = float(np.sqrt(np.max(np.sum(xn ** 2, axis=1))))
        shift = r_max * (x[9] * r_max ** 2 + x[10] * r_max ** 4) * camera.fx
        lens.update(k1=float(x[9]), k2=float(x[10]), determined=True, edge_radius_px=r_max * camera.fx,
                    edge_displacement_px=float(shift))
    # Then the camera's focal length. A wrong one scales the depth's points across the view (X, Y, not Z). For a
    # projector looking the same way as the camera that is the same as a projector focal length and baseline
    # scaled by as much (no data can tell them apart); the more the two axes converge, the more it bends the
    # projector's view of a non-planar surface in ways no pinhole K can take up, which is what pins it here.
    free = _CAMERA_FOCAL if lens["determined"] else np.r_[_NO_LENS, 11]
    x_cam, r_cam, j_cam = _levenberg_marquardt(gv.residuals, x, steps, free)
    sd_cam = _covariance_std(j_cam, r_cam)
    focal: dict[str, Any] = {"factor": 1.0, "std": float(sd_cam[-1]), "determined": False,
                             "given_fx": camera.fx}
    if sd_cam[-1] < CAMERA_FOCAL_STD_MAX and np.isfinite(x_cam).all():
        x, r, sd = x_cam, r_cam, sd_cam
        focal.update(factor=float(x[11]), determined=True)
        if lens["determined"]:
            lens.update(k1=float(x[9]), k2=float(x[10]))
    focal["fitted_fx"] = camera.fx * focal["factor"]
    std_d = {"fx": float(sd[0]), "cx": float(sd[1]), "cy": float(sd[2])}
    k = Intrinsics.from_opencv_matrix(nominal.width, nominal.height, _projector_matrix(x, aspect))
    determined = {"focal": std_d["fx"] < FOCAL_STD_MAX * k.fx,
                  "principal_point": max(std_d["cx"], std_d["cy"]) < CENTRE_STD_MAX_PX}
    pose: np.ndarray | None = _camera_from_projector(x[3:6], x[6:9])
    if not all(determined.values()):
        # Measured on the lab's plane: its principal point looks determined alone, but only given the focal
        # length; fitted with a wrong spec's focal length it moves to compensate it and the pose gets worse than
        # with the spec. So either the data determine both, or the spec stays as it is.
        k, pose, r = nominal, None, r_nominal
        lens["determined"] = False
        focal.update(factor=1.0, determined=False, fitted_fx=camera.fx)
    return IntrinsicsFit(nominal, k, std_d, determined, _point_rms(r_nominal), _point_rms(r), int(len(obj)),
                         int(keep.sum()), lens, pose, focal)
