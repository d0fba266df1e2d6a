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

The covariance only measures the noise of a model taken as right: on phone
depth with a bias and a misregistration the fit trades the focal lengths
against the depth while claiming sub-pixel σ. :func:`judge_fit` therefore
reports, for each value and the pose, an uncertainty that adds a jackknife over
blocks of the surface and the depth sensor's own errors, keeps a value at the
spec where the data do not pin it better than the spec's prior or do not find
the spec wrong (the fit within two of its σ of it), and keeps the fit only
where held-out blocks reproject better than with the spec.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..capture.format import CaptureSet
from ..errors import CalibrationError
from ..memo import recent
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
#: Points the pose's uncertainty is judged on with the intrinsics held (:func:`pose_uncertainty`): its σ is the
#: blocks' spread and the systematic errors', which fewer points do not change; the covariance's, the smallest
#: part, grows as 1/√N. Every calibration runs it, so it is kept quick (0.3 → 0.1 s at 320×240).
POSE_POINTS = 8000

#: Largest standard deviation of the camera's focal-length factor for it to count as determined.
CAMERA_FOCAL_STD_MAX = 0.005

#: The spec sheet's standard deviations, the prior each fitted value must beat to replace the spec: a projector's
#: throw ratio is printed to two digits and its lenses vary by a few per cent (3 % of the focal length); its lens
#: shift is set by hand against a printed range (3 % of the image height, both axes); a camera's focal length as
#: a phone or an EXIF header reports it is good to 1–2 % (2 %).
PROJECTOR_FOCAL_PRIOR = 0.03
PRINCIPAL_POINT_PRIOR = 0.03
CAMERA_FOCAL_PRIOR = 0.02
#: The priors of intrinsics a rig calibration gave (the capture set says "calibrated"): a board calibration's own
#: σ on the real board sessions (realdata/kamino410-procam-calibration) is 0.4 % of the projector's focal length,
#: 0.7 and 1.2 % of its height for its principal point and 0.3 % of the camera's focal length, and its error on the
#: lab's board sessions 0.1–0.2 % and under 3 px (docs/results.md, "A rig calibration checked against a known
#: rig"). Judged against the spec sheet's priors instead, a Gray-code fit on those real sessions moved the board's
#: projector focal length by 6.5 % (1897.7 → 1773.4 px, 17 of the board's σ), calling that better than a spec.
CALIBRATED_FOCAL_PRIOR = 0.005
CALIBRATED_PRINCIPAL_POINT_PRIOR = 0.015
CALIBRATED_CAMERA_FOCAL_PRIOR = 0.005
#: The depth sensor's systematic errors the fit cannot see and is tried against: a phone's time-of-flight depth is
#: good to about 1 cm absolute (2 mm once a wall depth image or a given offset has taken its constant bias out),
#: and its registration to the colour camera to about one of its native pixels.
DEPTH_BIAS_STD_M = 0.01
DEPTH_BIAS_STD_MEASURED_M = 0.002
#: The surface is cut into this many blocks across and down (camera image) for the jackknife and the held-out check:
#: depth and decoding errors are correlated over many pixels, so blocks, not pixels, are the independent samples.
BLOCKS = 4
#: A reported ± is one standard deviation; it "covers" a true error no larger than this many of it (≈ 95 %).
COVER_SIGMAS = 2.0

#: The judged rule (:func:`judge_fit`); off, every value the covariance calls determined is fitted, as before it
#: (its uncertainties are still recorded): what scripts/bench_calibration_uncertainty.py compares against.
JUDGE = True

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
    #: per value (projector_focal, projector_cx, projector_cy, camera_focal): kept from the fit or the spec, the
    #: uncertainty reported, what the data alone pin it to, the covariance's σ; the pose's; the held-out check
    #: (:func:`judge_fit`); empty from folders written before it
    uncertainty: dict[str, Any] = field(default_factory=dict)

    def summary_of_uncertainty(self) -> str:
        """Plain words on each value: fitted or kept at the spec, and how well the data pin it; the pose's ±."""
        u = self.uncertainty
        if not u:
            return ""
        parts = []
        for name, v in u["values"].items():
            what, unit = _WORDS[name]
            scale = 100.0 if unit == "%" else 1.0
            pin = v.get("data_std")
            pinned = ("not at all" if pin is None or not np.isfinite(pin) or pin > 100 * v["prior_std"] else
                      f"±{scale * pin:.2f}{unit}")
            given = "given" if unit == "%" else u.get("given_by", "spec")
            if v["kept"] == "spec":
                why = {"held-out": f"the data pin it to {pinned}, but the fit does not reproject held-out parts of "
                                   "the surface better",
                       "surface": f"this surface does not determine it (at least {pinned})",
                       "agrees": f"the data pin it to {pinned} and put the fit {v.get('z') or 0.0:.1f} σ from it: "
                                 "no sign it is wrong",
                       "shared": "the camera is every projector's: one projector's Gray code does not move it"}.get(
                    v.get("reason") or "", f"the data pin it only to {pinned}")
                parts.append(f"{what}: kept the {given}'s {v['spec']:.1f} px "
                             f"(±{scale * v['std']:.2f}{unit}); {why}")
            else:
                parts.append(f"{what}: fitted {v['spec']:.1f} → {v['value']:.1f} px "
                             f"±{scale * v['std']:.2f}{unit} (the {given}'s ±{scale * v['prior_std']:.2f}{unit}; "
                             f"the fit's own covariance said ±{scale * v['covariance_std']:.2f}{unit})")
        pose = u["pose"]
        held = u.get("held_out") or {}
        check = ""
        if held.get("rms_fitted_px") is not None:
            worse = f" (not better by {COVER_SIGMAS:g} standard errors over the blocks: the spec is kept)"
            check = (f"; held-out reprojection {held['rms_nominal_px']:.3f} px with the spec, "
                     f"{held['rms_fitted_px']:.3f} px with the fit" + ("" if held["improves"] else worse))
        return ("; ".join(parts) + f"; projector position ±{100 * pose['position_std_m']:.2f} cm, axis "
                f"±{pose['axis_std_deg']:.2f}° (one σ, the depth sensor's own errors included)" + check)

    def camera(self, given: Intrinsics) -> Intrinsics | None:
        """The camera's intrinsics with the fitted focal length, or None when the data do not determine it."""
        if not self.camera_focal.get("determined"):
            return None
        g = float(self.camera_focal["factor"])
        return Intrinsics(given.width, given.height, given.fx * g, given.fy * g, given.cx, given.cy)

    def summary(self) -> str:
        if self.uncertainty:
            return self._judged_summary()
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
                  if lens.get("determined") else f"; camera lens {lens['held']}, not fitted again" if lens.get("held")
                  else "; camera lens distortion not determined by this surface (assumed none)")
        return (f"focal {n.fx:.1f} → {f.fx:.1f} px ({100 * (f.fx / n.fx - 1):+.2f} %), principal point "
                f"({n.cx:.1f}, {n.cy:.1f}) → ({f.cx:.1f}, {f.cy:.1f}) px ({spread}){camera}; reprojection RMS "
                f"{self.rms_nominal_px:.2f} → {self.rms_fitted_px:.2f} px{focal}")

    def _judged_summary(self) -> str:
        text = self.summary_of_uncertainty()
        if not all(self.determined.values()):
            unknown = [name.replace("_", " ") for name, ok in self.determined.items() if not ok]
            return (f"{text}; kept at the spec whole: this surface does not determine the {' and '.join(unknown)} "
                    "(a flat surface never does: use a curved or edged one, or procam calibrate-rig)")
        lens = self.camera_distortion
        camera = (f"; camera lens distortion fitted with them: {lens['edge_displacement_px']:+.2f} px at "
                  f"{lens['edge_radius_px']:.0f} px from the centre (k1 {lens['k1']:+.4f}, k2 {lens['k2']:+.4f})"
                  if lens.get("determined") else f"; camera lens {lens['held']}, not fitted again" if lens.get("held")
                  else "")
        return f"{text}{camera}; reprojection RMS {self.rms_nominal_px:.2f} → {self.rms_fitted_px:.2f} px"

    def to_dict(self) -> dict[str, Any]:
        return {"nominal": self.nominal.to_dict(), "fitted": self.fitted.to_dict(),
                "std_px": {k: float(v) for k, v in self.std.items()}, "determined": dict(self.determined),
                "rms_nominal_px": self.rms_nominal_px, "rms_fitted_px": self.rms_fitted_px,
                "points": self.points, "inliers": self.inliers, "camera_distortion": dict(self.camera_distortion),
                "camera_from_projector": None if self.camera_from_projector is None
                else np.asarray(self.camera_from_projector).tolist(), "camera_focal": dict(self.camera_focal),
                "uncertainty": self.uncertainty, "summary": self.summary()}


#: How the summary names each judged value, and its unit ("%" for a factor's share, else pixels).
_WORDS = {"projector_focal": ("projector focal length", " px"), "projector_cx": ("projector principal point x", " px"),
          "projector_cy": ("projector principal point y", " px"), "camera_focal": ("camera focal length", "%")}


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
        #: the last few sets of points, by (k1, k2, focal factor): :meth:`points`
        self._seen: dict[tuple[float, float, float], np.ndarray] = {}

    #: a systematic depth error to try (metres added; the depth map read that many camera pixels right, down)
    bias: float = 0.0
    shift: tuple[float, float] = (0.0, 0.0)

    def perturbed(self, bias: float = 0.0, shift: tuple[float, float] = (0.0, 0.0)) -> _GrayCodeView:
        """The same view with a depth sensor wrong by ``bias`` metres and misregistered by ``shift`` pixels."""
        out = object.__new__(_GrayCodeView)
        out.__dict__.update(self.__dict__, bias=float(bias), shift=(float(shift[0]), float(shift[1])), _seen={})
        return out

    def subset(self, rows: np.ndarray) -> _GrayCodeView:
        """The view of the correspondences ``rows`` only."""
        out = self.perturbed(self.bias, self.shift)
        out.centres, out.target = self.centres[rows], self.target[rows]
        return out

    def points(self, k1: float, k2: float, focal: float = 1.0) -> np.ndarray:
        """N×3 surface points (rig frame) the decoded pixels see through a lens with k1, k2 and the camera's focal
        length ``focal`` times the given one; NaN where none (read-only: the last few are kept).

        The depth is looked up at the undistorted pixel, which does not depend on the focal length: the surface
        was made from the depth with the given K and is seen through the same K, so each pixel keeps its depth.
        """
        # Nine of a fit's twelve parameters are the projector's: every Jacobian column of those, and every trial
        # step that keeps the camera's, sees the same points (they were 40 % of a fit's time, recomputed).
        def make() -> np.ndarray:
            pts = self._points(k1, k2, focal)
            pts.flags.writeable = False
            return pts

        return recent(self._seen, (float(k1), float(k2), float(focal)), make, keep=4)

    def _points(self, k1: float, k2: float, focal: float) -> np.ndarray:
        crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 30, 1e-12)
        kc = self.kc.copy()
        kc[0, 0] *= focal
        kc[1, 1] *= focal
        xn = cv2.undistortPointsIter(self.centres, kc, np.array([k1, k2, 0.0, 0.0]), None, None,
                                     crit).reshape(-1, 2)
        u = xn[:, 0] * kc[0, 0] + kc[0, 2]
        v = xn[:, 1] * kc[1, 1] + kc[1, 2]
        z = cv2.remap(self.depth, (u + self.shift[0]).astype(np.float32)[None, :],
                      (v + self.shift[1]).astype(np.float32)[None, :], cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan")).ravel().astype(np.float64)
        z = z + self.bias
        return np.column_stack([xn * z[:, None], z])

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Projector-pixel residuals (2N) for x = f, cx, cy (OpenCV), rvec, tvec, camera k1, k2, camera focal
        factor."""
        return self._project(x, derivatives=False)[0]

    def _project(self, x: np.ndarray, derivatives: bool) -> tuple[np.ndarray, np.ndarray | None]:
        km = _projector_matrix(x, self.aspect)
        pts = self.points(x[9], x[10], x[11])
        ok = np.isfinite(pts[:, 2])
        proj, jac = cv2.projectPoints(np.where(ok[:, None], pts, 1.0), x[3:6], x[6:9], km, None)
        r = proj.reshape(-1, 2) - self.target
        r[~ok] = 0.0  # a point that leaves the surface adds nothing (rare: the set is fixed at the start)
        if not derivatives:
            return r.ravel(), None
        # OpenCV's columns: rvec (3), tvec (3), fx, fy, cx, cy, then the distortion's; ours: f (fy = f · aspect),
        # cx, cy, rvec, tvec
        j = np.column_stack([jac[:, 6] + self.aspect * jac[:, 7], jac[:, 8], jac[:, 9], jac[:, 0:6]])
        j[np.repeat(~ok, 2)] = 0.0
        return r.ravel(), j

    def jacobian(self, x: np.ndarray, r: np.ndarray, steps: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The residuals' derivatives at ``x`` (whose residuals are ``r``) in the columns ``cols``: the
        projector's nine from the projection's own derivatives, the camera's (k1, k2, focal factor) by forward
        differences of ``steps`` (they move the points through the depth image)."""
        analytic = self._project(x, derivatives=True)[1] if any(i < 9 for i in cols) else None
        out = np.empty((r.size, len(cols)))
        for c, i in enumerate(cols):
            if i < 9 and analytic is not None:
                out[:, c] = analytic[:, i]
            else:
                e = np.zeros_like(x)
                e[i] = steps[i]
                out[:, c] = (self.residuals(x + e) - r) / steps[i]
        return out


def _levenberg_marquardt(view: _GrayCodeView, x0: np.ndarray, steps: np.ndarray, free: np.ndarray,
                         iterations: int = 60) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Minimise the view's |residuals(x)|² over ``x[free]`` from x0 (its Jacobian, Marquardt's damping); returns
    x, the residuals and the Jacobian (free columns) at x."""
    fun = view.residuals
    x = np.asarray(x0, np.float64).copy()
    r = fun(x)
    lam = 1e-3
    j = view.jacobian(x, r, steps, free)
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
        j = view.jacobian(x, r, steps, free)
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
    # the rigid inverse of [R | t] is [Rᵀ | −Rᵀt] (a general 4×4 inverse was most of the pose σ's time)
    r = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = r.T, -r.T @ np.ravel(tvec)
    return pose


@dataclass(frozen=True)
class _Consistent:
    """The Gray code's correspondences that agree with one pinhole projector (decoding errors dropped), and the
    fit's start and finite-difference steps: where the intrinsics fit and the pose's uncertainty both begin."""

    view: _GrayCodeView
    camera_px: np.ndarray  # the kept correspondences' camera pixels
    points: int  # correspondences before the outliers were dropped
    x0: np.ndarray  # the spec's K and the start pose
    x: np.ndarray  # after the outlier rounds
    steps: np.ndarray
    aspect: float


def _consistent(captures: CaptureSet, view: SurfaceView, mask: np.ndarray, *, seed: int, free: np.ndarray,
                too_few: str, camera_from_projector: np.ndarray | None = None,
                points: int = FIT_POINTS) -> _Consistent:
    """Gray-code correspondences with 3-D points from the surface, the outliers dropped while fitting ``free``
    (from the spec's K and ``camera_from_projector``, or a pose found here); ``too_few`` ends the error's sentence
    when too few agree; ``points``: at most this many, drawn at random."""
    nominal = captures.projector.intrinsics
    obj, img, cam_px, _ = graycode_correspondences(captures, view, mask, max_points=points, seed=seed)
    depth, camera, aspect = view.points[..., 2], captures.camera.intrinsics, nominal.fy / nominal.fx
    if camera_from_projector is None:
        rvec, tvec = _start_pose(obj, img, nominal, seed)
    else:
        p_from_c = np.linalg.inv(np.asarray(camera_from_projector, np.float64))
        rvec, tvec = cv2.Rodrigues(p_from_c[:3, :3])[0].ravel(), p_from_c[:3, 3]
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
        x, _, _ = _levenberg_marquardt(_GrayCodeView(cam_px[keep], img[keep], depth, camera, aspect),
                                       x, steps, free)
        res = np.linalg.norm(everything.residuals(x).reshape(-1, 2), axis=1)
        spread = 1.4826 * np.median(np.abs(res - np.median(res)))
        keep = res < max(1.0, np.median(res) + 4.0 * spread)
        if keep.sum() < MIN_CORRESPONDENCES:
            raise CalibrationError(f"too few consistent Gray-code correspondences in {captures.path} "
                                   f"({int(keep.sum())}) {too_few}")
    return _Consistent(_GrayCodeView(cam_px[keep], img[keep], depth, camera, aspect), cam_px[keep], len(obj), x0, x,
                       steps, aspect)


def _blocks(camera_px: np.ndarray, n: int = BLOCKS) -> list[np.ndarray]:
    """The correspondences cut into an n×n grid over the decoded part of the camera image (non-empty cells)."""
    lo, hi = camera_px.min(axis=0), camera_px.max(axis=0) + 1e-9
    cell = np.minimum(((camera_px - lo) / (hi - lo) * n).astype(int), n - 1)
    key = cell[:, 1] * n + cell[:, 0]
    return [np.flatnonzero(key == k) for k in range(n * n) if np.any(key == k)]


def _pose_of(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pose = _camera_from_projector(x[3:6], x[6:9])
    return pose[:3, 3], pose[:3, 2]


@dataclass
class _Spread:
    """What the data say of a fit's free values: the covariance's σ, the jackknife over blocks, and how far the
    depth sensor's errors and the values held at their spec move them; each as deviations of the whole x."""

    free: np.ndarray
    covariance_std: np.ndarray
    jackknife: np.ndarray  # K × len(x): leaving block k out moves x by this
    systematic: dict[str, np.ndarray]  # name → how far x moves under that error at one σ

    def std(self) -> np.ndarray:
        """Per free value: the larger of the covariance's and the jackknife's σ, with every systematic part."""
        k = len(self.jackknife)
        jack = np.sqrt((k - 1) / k * np.sum((self.jackknife - self.jackknife.mean(axis=0)) ** 2, axis=0))[self.free]
        sys2 = np.sum([d[self.free] ** 2 for d in self.systematic.values()], axis=0) if self.systematic else 0.0
        return np.sqrt(np.maximum(self.covariance_std, jack) ** 2 + sys2)

    def pose_parts(self, x: np.ndarray) -> dict[str, tuple[float, float]]:
        """How far each part moves the projector's position (metres) and axis (degrees) at one σ: ``data`` (the
        larger of the jackknife's and the covariance's spread) and each systematic error by its name."""
        pos0, axis0 = _pose_of(x)

        def moved(d: np.ndarray) -> np.ndarray:
            pos, axis = _pose_of(x + d)
            return np.array([np.linalg.norm(pos - pos0), np.arccos(np.clip(axis @ axis0, -1.0, 1.0))])

        k = len(self.jackknife)
        mean = self.jackknife.mean(axis=0)
        jack2 = (k - 1) / k * np.sum([moved(d - mean) ** 2 for d in self.jackknife], axis=0)
        cov = np.zeros(len(x))
        cov[self.free] = self.covariance_std
        cov2 = np.sum([moved(np.eye(len(x))[i] * cov[i]) ** 2 for i in self.free], axis=0)
        parts = {"data": np.sqrt(np.maximum(jack2, cov2)), **{n: moved(d) for n, d in self.systematic.items()}}
        return {n: (float(v[0]), float(np.degrees(v[1]))) for n, v in parts.items()}


def _pose_std(parts: dict[str, tuple[float, float]]) -> tuple[float, float]:
    """The projector's position (metres, root of the expected squared error) and axis (degrees) σ: every part of
    :meth:`_Spread.pose_parts` together."""
    total = np.sqrt(np.sum(np.square(list(parts.values())), axis=0))
    return float(total[0]), float(total[1])


def _spread(view: _GrayCodeView, x: np.ndarray, steps: np.ndarray, free: np.ndarray, blocks: list[np.ndarray],
            errors: dict[str, _GrayCodeView], held: dict[str, float]) -> _Spread:
    """The :class:`_Spread` of the fit at ``x`` over ``free``: ``errors`` are the views with the depth sensor
    wrong by one σ, ``held`` the values fixed at their spec (index name → prior σ, see :data:`_INDEX`)."""
    r = view.residuals(x)
    j = view.jacobian(x, r, steps, free)
    normal = j.T @ j
    n = len(x)

    def moves(dr: np.ndarray) -> np.ndarray:
        d = np.zeros(n)
        d[free] = -np.linalg.lstsq(normal, j.T @ dr, rcond=None)[0]
        return d

    def change(r1: np.ndarray) -> np.ndarray:
        dr = r1 - r
        dr[(r1 == 0.0) | (r == 0.0)] = 0.0  # a point off the surface in either adds nothing
        return dr

    jack = []
    for rows in blocks:
        idx = np.r_[2 * rows, 2 * rows + 1]
        jk = j[idx]
        d = np.zeros(n)
        # Leaving block k out: a Gauss-Newton step of the rest from x, whose gradient there is −J_kᵀ r_k.
        d[free] = np.linalg.lstsq(normal - jk.T @ jk, jk.T @ r[idx], rcond=None)[0]
        jack.append(d)
    systematic = {name: moves(change(v.residuals(x))) for name, v in errors.items()}
    for name, sigma in held.items():
        i = _INDEX[name]
        systematic[f"{name} at its spec"] = moves(change(view.residuals(x + np.eye(n)[i] * sigma)))
    return _Spread(free, _covariance_std(j, r), np.array(jack), systematic)


#: The judged values' places in the fit's parameters.
_INDEX = {"projector_focal": 0, "projector_cx": 1, "projector_cy": 2, "camera_focal": 11}


def _depth_wrong(view: _GrayCodeView, bias: float, shift: float) -> dict[str, _GrayCodeView]:
    """The view with the depth sensor wrong by one σ of each of its errors: its bias, its registration across, down."""
    return {"depth bias": view.perturbed(bias=bias), "misregistration across": view.perturbed(shift=(shift, 0.0)),
            "misregistration down": view.perturbed(shift=(0.0, shift))}


def judge_fit(view: _GrayCodeView, camera_px: np.ndarray, x_fit: np.ndarray, x_nominal: np.ndarray,
              steps: np.ndarray, free: np.ndarray, priors: dict[str, float], depth_bias_std: float,
              shift_std_px: float) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Which fitted values to keep, and the uncertainty of each and of the pose, honestly.

    The covariance of a least-squares fit measures only the noise of a model taken as right; a depth sensor's
    bias or misregistration is not noise and moves the values far beyond it (measured: 7 σ on the lab's curve).
    So a value's uncertainty here is the larger of the covariance's σ and a jackknife's over :data:`BLOCKS`²
    blocks of the surface, with, added, how far the fit moves when the depth is wrong by the sensor's σ (bias,
    misregistration across and down) and when each value held at its spec is wrong by its prior σ. A value whose
    uncertainty is not below its prior (``priors``, in the fit's units) goes back to the spec, the worst first,
    and the rest are fitted again, unless the data contradict the spec (the fit farther from it than
    :data:`COVER_SIGMAS` of both σ together). Then a value whose fit lies within :data:`COVER_SIGMAS` of its own
    σ of the spec goes back to it too, the least significant first: the data do not find that spec wrong.
    Then the fit is kept only when it reprojects the blocks it was not
    fitted to better than the spec does, by :data:`COVER_SIGMAS` standard errors over the blocks (each half of a
    checkerboard of blocks fitted, the other measured); else the spec stays whole.
    Returns the x and free set kept and the record."""
    blocks = _blocks(camera_px)
    errors = _depth_wrong(view, depth_bias_std, shift_std_px)
    judged = [name for name, i in _INDEX.items() if i in free]
    record: dict[str, dict[str, Any]] = {}
    first = _spread(view, x_fit, steps, free, blocks, errors, {})  # the covariance's σ as the fit had it
    cov_first = dict(zip(free.tolist(), first.covariance_std))
    # Every judged value not free is held at its spec, which is wrong by up to its prior σ: that moves the rest.
    x, held = x_fit.copy(), {n: priors[n] for n, i in _INDEX.items() if i not in free}
    reasons: dict[str, str] = {}  # held value → why: "prior" or "agrees" (the held-out check adds its own below)
    while True:
        spread = _spread(view, x, steps, free, blocks, errors, held)
        sd = dict(zip(free.tolist(), spread.std()))
        ratios = {n: sd[_INDEX[n]] / priors[n] for n in judged if n not in held}
        for n in list(ratios):
            i = _INDEX[n]
            record[n] = {"data_std": sd[i], "z": float(abs(x[i] - x_nominal[i]) / max(sd[i], 1e-300))}
            # A spec the data contradict (χ²: the fit farther from it than COVER_SIGMAS of the two σ together) is
            # not a prior to fall back to, however loosely the data pin the value: the fit stays.
            if abs(x[i] - x_nominal[i]) > COVER_SIGMAS * np.hypot(sd[i], priors[n]):
                ratios.pop(n)
                record[n]["spec_contradicted"] = True
        worst = max(ratios, key=lambda n: ratios[n]) if ratios else None
        if worst is not None and ratios[worst] >= 1.0:
            hold, why = worst, "prior"
        else:
            # Then the spec is moved only where the data reject it: a value whose fit lies within COVER_SIGMAS of
            # its own σ of the spec is held there, the least significant first. σ below the prior says the fit
            # would do better on average over specs as wrong as the prior allows; it is no sign that *this* spec
            # is wrong, and where it is not, fitting the value only imports the depth's systematic errors (which
            # σ bounds but does not remove). That matters most for the principal point: a shift of it and a turn
            # of the projector are nearly one and the same to the Gray code, so a principal point moved by the
            # depth's errors turns the pose's axis with it (measured on the lab's hedge with phone depth 5 mm too
            # far: the spec's cx was right, the fit moved it 2.2 px, 0.9 σ, and the axis went from 0.26° off with
            # the spec to 0.32°; with the focal length and cx held, cy alone fitted, 0.02°). The same two-σ level
            # as every other check here, not a new one.
            z = {n: record[n]["z"] for n in judged if n not in held}
            hold = min(z, key=lambda n: z[n]) if z else None
            if hold is None or z[hold] >= COVER_SIGMAS:
                break
            why = "agrees"
        if not JUDGE:
            break
        i = _INDEX[hold]
        # A spec held because the data agree with it is wrong by no more than the data allow: its error, the truth
        # taken as the fit ± its σ, is √(Δ² + σ²), below the prior's. Counting the prior's σ instead would move
        # the values still fitted by a spec error the data rule out, and make them look unpinned.
        held[hold] = priors[hold] if why == "prior" else min(priors[hold], float(np.hypot(x[i] - x_nominal[i],
                                                                                          sd[i])))
        reasons[hold] = why
        x = x.copy()
        x[_INDEX[hold]] = x_nominal[_INDEX[hold]]
        free = free[free != _INDEX[hold]]
        x, _, _ = _levenberg_marquardt(view, x, steps, free)
    fitted = [n for n in judged if n not in held]
    fitted_before = list(fitted)
    held_out: dict[str, Any] = {"rms_nominal_px": None, "rms_fitted_px": None, "improves": None}
    if fitted and JUDGE:
        # Held-out reprojection: a checkerboard of blocks, each half fitted and the other measured, the fit kept
        # against the spec (same pose parameters, the judged values at the spec).
        n = BLOCKS
        lo, hi = camera_px.min(axis=0), camera_px.max(axis=0) + 1e-9
        cell = np.minimum(((camera_px - lo) / (hi - lo) * n).astype(int), n - 1)
        half = (cell[:, 0] + cell[:, 1]) % 2 == 0
        spec_free = free[~np.isin(free, [_INDEX[m] for m in fitted])]
        x_spec = x.copy()
        for m in fitted:
            x_spec[_INDEX[m]] = x_nominal[_INDEX[m]]
        sums = {"fit": 0.0, "spec": 0.0}
        gains = []  # per held-out block: its mean squared residual with the spec minus with the fit
        key = cell[:, 1] * n + cell[:, 0]
        for part in (half, ~half):
            train = view.subset(np.flatnonzero(part))
            per_block: dict[str, list[float]] = {"fit": [], "spec": []}
            for name, start, cols in (("fit", x, free), ("spec", x_spec, spec_free)):
                xt, _, _ = _levenberg_marquardt(train, start, steps, cols)
                for b in np.unique(key[~part]):
                    rt = view.subset(np.flatnonzero(key == b)).residuals(xt)
                    sums[name] += float(rt @ rt)
                    per_block[name].append(float(rt @ rt) / max(1, len(rt) // 2))
            gains += list(np.subtract(per_block["spec"], per_block["fit"]))
        count = len(camera_px)
        # Blocks are the independent samples: the fit counts as better only when its mean gain over the held-out
        # blocks stands COVER_SIGMAS standard errors above nothing (a one-sided t-test over the blocks).
        g = np.asarray(gains)
        t = float(g.mean() / max(g.std(ddof=1) / np.sqrt(len(g)), 1e-30)) if len(g) > 1 else 0.0
        held_out = {"rms_nominal_px": float(np.sqrt(sums["spec"] / max(count, 1))),
                    "rms_fitted_px": float(np.sqrt(sums["fit"] / max(count, 1))),
                    "t": t, "blocks": len(g), "improves": bool(t >= COVER_SIGMAS)}
        if not held_out["improves"]:
            for m in fitted:
                held[m] = priors[m]
            x, free, fitted = x_spec, spec_free, []
            x, _, _ = _levenberg_marquardt(view, x, steps, free)
            spread = _spread(view, x, steps, free, blocks, errors, held)
            sd = dict(zip(free.tolist(), spread.std()))
    pose_parts = spread.pose_parts(x)
    pos_std, axis_std = _pose_std(pose_parts)
    values = {}
    for name in judged:
        i = _INDEX[name]
        values[name] = {"kept": "spec" if name in held else "fit", "prior_std": priors[name],
                        "reason": None if name not in held else "held-out" if name in fitted_before
                        else reasons.get(name, "prior"),
                        "data_std": record.get(name, {}).get("data_std"), "z": record.get(name, {}).get("z"),
                        "covariance_std": float(cov_first[i]),
                        "std": held[name] if name in held else float(sd[i]),
                        "value": float(x_nominal[i] if name in held else x[i]), "spec": float(x_nominal[i])}
    doc = {"values": values, "pose": {"position_std_m": pos_std, "axis_std_deg": axis_std},
           "held_out": held_out, "blocks": len(blocks),
           "depth_errors_tried": {"bias_m": depth_bias_std, "misregistration_px": shift_std_px},
           "parts_std": {name: {m: float(d[_INDEX[m]]) for m in fitted} for name, d in spread.systematic.items()},
           "pose_parts": {name: {"position_m": pos, "axis_deg": axis} for name, (pos, axis) in pose_parts.items()},
           "cover_sigmas": COVER_SIGMAS}
    return x, free, doc


def pose_uncertainty(captures: CaptureSet, view: SurfaceView, mask: np.ndarray, camera_from_projector: np.ndarray, *,
                     seed: int = 0, depth_bias_known: bool = False) -> dict[str, Any]:
    """How well the capture set pins the projector's pose when its intrinsics are held as given (the default,
    ``--projector-intrinsics spec``): one σ of its position (metres) and axis (degrees), as :func:`judge_fit` states
    it for a fit, from the Gray code's spread over blocks of the surface, the depth sensor's errors, and each
    intrinsic value wrong by its prior σ (a spec sheet's, or a rig calibration's); and what each part moves it by
    (``parts``). A pose from spec intrinsics used to come with no ± at all: on the lab's edged surface with two
    projectors it was 0.9 cm and 0.34° off with nothing to say so."""
    nominal = captures.projector.intrinsics
    c = _consistent(captures, view, mask, seed=seed, free=_POSE, camera_from_projector=camera_from_projector,
                    too_few="to judge the projector's pose by", points=POSE_POINTS)
    x, _, _ = _levenberg_marquardt(c.view, c.x, c.steps, _POSE)
    bias, shift = depth_errors(captures, bias_known=depth_bias_known)
    # judge_fit's spread with every judged value held at its prior (nothing of the intrinsics is free)
    blocks = _blocks(c.camera_px)
    spread = _spread(c.view, x, c.steps, _POSE, blocks, _depth_wrong(c.view, bias, shift),
                     intrinsic_priors(captures, nominal.fx, nominal.height))
    parts = spread.pose_parts(x)
    position, axis = _pose_std(parts)
    return {"position_std_m": position, "axis_std_deg": axis,
            "parts": {n: {"position_m": p, "axis_deg": a} for n, (p, a) in parts.items()},
            "depth_errors_tried": {"bias_m": bias, "misregistration_px": shift},
            "given_by": "rig calibration" if captures.projector_status == "calibrated" else "spec",
            "camera_lens": "none calibrated" if getattr(captures, "camera_lens", None) is None else "taken out",
            "points": len(c.camera_px), "blocks": len(blocks)}


#: What each part of a pose's uncertainty is in words, and what narrows it.
_POSE_PARTS = {
    "data": ("the Gray code's spread over the surface", "light and show more of the surface"),
    "depth bias": ("the depth sensor's bias", "a wall depth image or a measured --depth-offset takes it out"),
    "misregistration across": ("the depth sensor's registration to the camera", ""),
    "misregistration down": ("the depth sensor's registration to the camera", ""),
    "projector_focal at its spec": ("the {given}'s projector focal length",
                                    "a board calibration (procam calibrate-rig) narrows it"),
    "projector_cx at its spec": ("the {given}'s lens shift", "a board calibration (procam calibrate-rig) narrows it"),
    "projector_cy at its spec": ("the {given}'s lens shift", "a board calibration (procam calibrate-rig) narrows it"),
    "camera_focal at its spec": ("the camera's focal length as given",
                                 "a board calibration of the camera (procam calibrate-rig) narrows it"),
}


def pose_summary(u: dict[str, Any]) -> str:
    """:func:`pose_uncertainty`'s record in words: the ±, the parts that make most of the position's and the
    axis's, what narrows them, and whether the camera's lens is in it."""
    if not u.get("position_std_m"):
        return f"not measured: {u.get('why', 'no Gray code and depth to judge it by')}"
    given = u.get("given_by") or "spec"
    text = f"position ±{100 * u['position_std_m']:.1f} cm, axis ±{u['axis_std_deg']:.2f}° (one σ)"
    parts = u.get("parts") or {}
    if parts:
        pos = max(parts, key=lambda n: parts[n]["position_m"])
        axis = max(parts, key=lambda n: parts[n]["axis_deg"])
        words = {n: _POSE_PARTS.get(n, (n, ""))[0].format(given=given) for n in (pos, axis)}
        text += (f": most of the position from {words[pos]} (±{100 * parts[pos]['position_m']:.1f} cm), of the "
                 f"axis from {words[axis]} (±{parts[axis]['axis_deg']:.2f}°)")
        advice = dict.fromkeys(a for a in (_POSE_PARTS.get(pos, ("", ""))[1], _POSE_PARTS.get(axis, ("", ""))[1])
                               if a)
        text += "".join(f"; {a}" for a in advice)
    if u.get("camera_lens") == "none calibrated":
        text += ("; not in it: the camera's lens, taken as distortion-free (a lens that bends the photographs turns "
                 "the pose; procam calibrate-rig, then import with --rig)")
    return text


def _point_rms(r: np.ndarray) -> float:
    return float(np.sqrt(2.0 * np.mean(r ** 2)))


def depth_errors(captures: CaptureSet, *, bias_known: bool = False) -> tuple[float, float]:
    """The depth sensor's systematic errors the fit is tried against (:data:`DEPTH_BIAS_STD_M`): bias σ in metres
    (smaller when a wall depth image or a given offset took the constant bias out) and misregistration σ in camera
    pixels (one native depth pixel)."""
    known = bias_known or bool(captures.depth_walls())
    bias = DEPTH_BIAS_STD_MEASURED_M if known else DEPTH_BIAS_STD_M
    info = captures.depth_info
    shift = 1.0 if info is None else max(1.0, captures.camera.intrinsics.width / max(1, info.native_size[0]))
    return bias, float(shift)


def intrinsic_priors(captures: CaptureSet, focal_px: float, height: int) -> dict[str, float]:
    """Each judged value's prior σ (the fit's units: pixels, the camera's a factor): the spec sheet's, or a rig
    calibration's where the capture set's projector or camera intrinsics came from one."""
    projector = getattr(captures, "projector_status", "nominal") == "calibrated"
    camera = getattr(captures, "camera_status", "nominal") == "calibrated"
    centre = (CALIBRATED_PRINCIPAL_POINT_PRIOR if projector else PRINCIPAL_POINT_PRIOR) * height
    return {"projector_focal": (CALIBRATED_FOCAL_PRIOR if projector else PROJECTOR_FOCAL_PRIOR) * focal_px,
            "projector_cx": centre, "projector_cy": centre,
            "camera_focal": CALIBRATED_CAMERA_FOCAL_PRIOR if camera else CAMERA_FOCAL_PRIOR}


def estimate_projector_intrinsics(captures: CaptureSet, view: SurfaceView, mask: np.ndarray, *,
                                  seed: int = 0, depth_bias_known: bool = False,
                                  camera_shared: bool = False) -> IntrinsicsFit:
    """Fit the projector's focal length and principal point, and the camera's radial distortion, to the capture
    set's Gray code (module doc), and judge what the data pin down (:func:`judge_fit`): ``depth_bias_known`` when
    the depth's constant bias was given (a wall depth image in the set counts too). ``camera_shared``: the camera
    is other projectors' too (a rig of several), so its focal length is held as given: one projector's Gray code
    must not move what every projector's pose and the surface rest on."""
    nominal = captures.projector.intrinsics
    c = _consistent(captures, view, mask, seed=seed, free=_NO_LENS,
                    too_few="to fit the projector's intrinsics; keep the spec (--projector-intrinsics spec)")
    gv, x0, x, steps, aspect, camera = c.view, c.x0, c.x, c.steps, c.aspect, captures.camera.intrinsics
    km = nominal.opencv_matrix()
    cam_px = c.camera_px
    _, r_nominal, _ = _levenberg_marquardt(gv, x0, steps, _POSE)  # the spec's K, its best pose
    x, r, j = _levenberg_marquardt(gv, x, steps, _NO_LENS)
    sd = _covariance_std(j, r)
    lens: dict[str, Any] = {"k1": 0.0, "k2": 0.0, "std_k1": None, "std_k2": None, "determined": False}
    # Then the camera's radial distortion with them: the photographs' lens bends the decoded pixels' rays, and a
    # projector fitted without it takes the bend into its focal length (measured: -2.6 % on the lab's curve with
    # its realistic k1 = -0.036).
    used = _NO_LENS
    # A lens a rig calibration took out of the photographs (procam undistort-captures, import-captures --rig) is not
    # fitted again: the board measured it, and freed here it would trade against the projector's focal length and
    # distance as an uncalibrated one does.
    if getattr(captures, "camera_lens", None) is not None:
        lens["held"] = "taken out of the photographs by a rig calibration"
    else:
        x_lens, r_lens, j_lens = _levenberg_marquardt(gv, x, steps, _LENS)
        sd_lens = _covariance_std(j_lens, r_lens)
        lens.update(std_k1=float(sd_lens[9]), std_k2=float(sd_lens[10]))
        if sd_lens[9] < DISTORTION_STD_MAX and np.isfinite(x_lens).all():
            x, r, sd, used = x_lens, r_lens, sd_lens, _LENS
            # k1 and k2 trade against each other over the lit part of the image; the displacement they give at its
            # edge is what the data pin down, so that is what the report leads with.
            xn = (cam_px - (camera.cx, camera.cy)) / (camera.fx, camera.fy)
            r_max = float(np.sqrt(np.max(np.sum(xn ** 2, axis=1))))
            shift = r_max * (x[9] * r_max ** 2 + x[10] * r_max ** 4) * camera.fx
            lens.update(k1=float(x[9]), k2=float(x[10]), determined=True, edge_radius_px=r_max * camera.fx,
                        edge_displacement_px=float(shift))
    # Then the camera's focal length. A wrong one scales the depth's points across the view (X, Y, not Z). For a
    # projector looking the same way as the camera that is the same as a projector focal length and baseline
    # scaled by as much (no data can tell them apart); the more the two axes converge, the more it bends the
    # projector's view of a non-planar surface in ways no pinhole K can take up, which is what pins it here.
    free = _CAMERA_FOCAL if lens["determined"] else np.r_[_NO_LENS, 11]
    x_cam, r_cam, j_cam = _levenberg_marquardt(gv, x, steps, free)
    sd_cam = _covariance_std(j_cam, r_cam)
    focal: dict[str, Any] = {"factor": 1.0, "std": float(sd_cam[-1]), "determined": False,
                             "given_fx": camera.fx, **({"held": "shared"} if camera_shared else {})}
    if not camera_shared and sd_cam[-1] < CAMERA_FOCAL_STD_MAX and np.isfinite(x_cam).all():
        x, r, sd, used = x_cam, r_cam, sd_cam, free
        focal.update(factor=float(x[11]), determined=True)
        if lens["determined"]:
            lens.update(k1=float(x[9]), k2=float(x[10]))
    focal["fitted_fx"] = camera.fx * focal["factor"]
    std_d = {"fx": float(sd[0]), "cx": float(sd[1]), "cy": float(sd[2])}
    k = Intrinsics.from_opencv_matrix(nominal.width, nominal.height, _projector_matrix(x, aspect))
    determined = {"focal": std_d["fx"] < FOCAL_STD_MAX * k.fx,
                  "principal_point": max(std_d["cx"], std_d["cy"]) < CENTRE_STD_MAX_PX}
    pose: np.ndarray | None = _camera_from_projector(x[3:6], x[6:9])
    bias_std, shift_std = depth_errors(captures, bias_known=depth_bias_known)
    priors = intrinsic_priors(captures, km[0, 0], nominal.height)
    x_nom = x0.copy()
    x_nom[3:9] = x[3:9]
    if not all(determined.values()):
        # Measured on the lab's plane: its principal point looks determined alone, but only given the focal
        # length; fitted with a wrong spec's focal length it moves to compensate it and the pose gets worse than
        # with the spec. So either the data determine both, or the spec stays as it is.
        k, pose, r = nominal, None, r_nominal
        lens["determined"] = False
        focal.update(factor=1.0, determined=False, fitted_fx=camera.fx)
        x_pose, _, _ = _levenberg_marquardt(gv, x_nom, steps, _POSE)
        _, _, judged = judge_fit(gv, cam_px, x_pose, x_nom, steps, _POSE, priors, bias_std, shift_std)
        for name, i in list(_INDEX.items())[:3]:
            judged["values"][name] = {"kept": "spec", "reason": "surface", "prior_std": priors[name],
                                      "data_std": float(sd[i]),
                                      "covariance_std": float(sd[i]), "std": priors[name]}
        free_kept: list[str] = []
    else:
        x, free, judged = judge_fit(gv, cam_px, x, x_nom, steps, used, priors, bias_std, shift_std)
        free_kept = [n for n, v in judged["values"].items() if v["kept"] == "fit"]
        r = gv.residuals(x)
        k = Intrinsics.from_opencv_matrix(nominal.width, nominal.height, _projector_matrix(x, aspect))
        if not free_kept:
            k, pose, r = nominal, None, r_nominal
            lens["determined"] = False
        else:
            pose = _camera_from_projector(x[3:6], x[6:9])
            if lens["determined"]:
                lens.update(k1=float(x[9]), k2=float(x[10]))
        if "camera_focal" in free_kept:
            focal.update(factor=float(x[11]), fitted_fx=camera.fx * float(x[11]))
        else:
            focal.update(factor=1.0, determined=False, fitted_fx=camera.fx)
    if camera_shared:  # held as given whatever the data say (the docstring): judged as such
        judged["values"].pop("camera_focal", None)
    if "camera_focal" not in judged["values"]:  # held as given from the start: the covariance alone refused it
        judged["values"]["camera_focal"] = {"kept": "spec", "reason": "shared" if camera_shared else "surface",
                                            "prior_std": priors["camera_focal"], "data_std": focal["std"],
                                            "covariance_std": focal["std"], "std": priors["camera_focal"]}
    # whose values the fit was judged against: a spec sheet's, or a rig calibration's (its tighter priors)
    judged["given_by"] = "rig calibration" if captures.projector_status == "calibrated" else "spec"
    # Values in the units a user reads: the projector's K as stored, the camera's focal length in pixels.
    for name, v in judged["values"].items():
        if name == "camera_focal":
            v.update(spec=camera.fx, value=camera.fx * focal["factor"])
        else:
            attr = {"projector_focal": "fx", "projector_cx": "cx", "projector_cy": "cy"}[name]
            v.update(spec=float(getattr(nominal, attr)), value=float(getattr(k, attr)))
    return IntrinsicsFit(nominal, k, std_d, determined, _point_rms(r_nominal), _point_rms(r), c.points,
                         len(cam_px), lens, pose, focal, judged)
