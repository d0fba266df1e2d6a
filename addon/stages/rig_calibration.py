"""Projector-camera rig calibration from a printed chessboard and Gray code (Moreno & Taubin 2012).

For each board pose the camera photographs the board under white light (the
chessboard corners come from that image) and under the Gray-code sequence
(every camera pixel decodes to the projector pixel that lights it). The
projector cannot photograph the board, so its view of each corner is inferred:
around each corner, a homography from camera pixels to decoded projector
pixels is fitted to the decoded pixels of a small window (a plane seen by two
pinholes is a homography, and locally lens distortion is negligible), and the
corner is mapped through it. The fit averages many whole-pixel decodes, so
the projector corner is sub-pixel although each decode is quantised to a
whole projector pixel. Then:

1. the camera is calibrated from all its corners (``cv2.calibrateCamera``);
2. the projector from its inferred corners, started from a DLT fitted to the
   board corners placed in 3-D by the camera (see :func:`_projector_start`);
3. the camera → projector pose by ``cv2.stereoCalibrate`` with both
   intrinsics fixed (see :func:`calibrate_rig` for why).

Conventions. Inside this module every pixel coordinate is OpenCV's (pixel
*centres* at integers), because every call here is OpenCV's. The result
carries OpenCV matrices and, in :meth:`RigCalibration.to_dict`, also the
project's convention (pixel *corners* at integers, ``cx = cx_opencv + 0.5``).
The rig frame is the camera's OpenCV frame; lengths are in the unit of
``square`` (metres when the square size is given in metres, which
``metric`` records; board squares with the default 1.0). ``camera_from_projector`` maps projector-frame points
into the camera frame (the inverse of OpenCV's stereo ``R, T``).

The intrinsics are stored as OpenCV matrices with their distortion;
``steps.capture.rig_models`` turns them into the rig model's
:class:`~..rig.model.Intrinsics` (which takes principal points far outside
the frame, as real projectors have) once the photographs are undistorted.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..capture.patterns import decode_gray_code, gray_code_bits
from ..errors import CalibrationError, CaptureError
from ..imageio import unit_float
from ..progress import Cancel, Progress, check, quiet

Size = tuple[int, int]

#: Fewer poses cannot constrain a camera's intrinsics and distortion together with a pose per view; OpenCV's
#: own advice is 10 or more. Three is the floor below which we refuse rather than print a meaningless result.
MIN_POSES = 3

#: Distortion models by name: which of OpenCV's (k1, k2, p1, p2, k3) are estimated; the rest stay 0.
DISTORTION_MODELS: dict[str, tuple[str, ...]] = {
    "none": (),
    "k1": ("k1",),
    "k1k2": ("k1", "k2"),
    "k1k2p1p2": ("k1", "k2", "p1", "p2"),
    "k1k2p1p2k3": ("k1", "k2", "p1", "p2", "k3"),
}
_COEFFICIENTS = ("k1", "k2", "p1", "p2", "k3")
#: ``auto`` (the projector's default) tries these nested models and keeps the one the data support
#: (:func:`_choose_model`).
AUTO_MODELS = ("none", "k1", "k1k2")


def _model_flags(model: str) -> int:
    if model not in DISTORTION_MODELS:
        raise CalibrationError(f"unknown distortion model {model!r}; choose one of {', '.join(DISTORTION_MODELS)}")
    free = DISTORTION_MODELS[model]
    flags = 0
    if "k1" not in free:
        flags |= cv2.CALIB_FIX_K1
    if "k2" not in free:
        flags |= cv2.CALIB_FIX_K2
    if "p1" not in free:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    if "k3" not in free:
        flags |= cv2.CALIB_FIX_K3
    return flags


# -- inputs ------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PoseSource:
    """One board pose's images, read on demand: a pose's 42 camera images are ~200 MB as float32, so the
    stage holds one pose at a time. Each callable returns a grey or colour image, any dtype (8/16-bit or float
    in [0, 1]); ``gray_code`` the Gray-code images in OpenCV's order (each bit followed by its inverse, x bits
    then y bits)."""

    name: str
    white: Callable[[], np.ndarray]
    black: Callable[[], np.ndarray]
    gray_code: Callable[[], Sequence[np.ndarray]]

    @staticmethod
    def from_arrays(name: str, gray_code: Sequence[np.ndarray], white: np.ndarray,
                    black: np.ndarray) -> PoseSource:
        """A pose whose images are already in memory (tests, synthetic data)."""
        images = list(gray_code)
        return PoseSource(name, lambda: white, lambda: black, lambda: images)


def as_grey(image: np.ndarray) -> np.ndarray:
    """A float32 H×W image in [0, 1] from grey or colour, 8-bit, 16-bit or float input."""
    a = unit_float(image)
    if a.ndim == 3:
        a = a[..., :3].mean(axis=2) if a.shape[2] >= 3 else a[..., 0]
    if a.ndim != 2:
        raise CaptureError(f"expected a grey or colour image, got an array of shape {np.shape(image)}")
    return a


# -- results -----------------------------------------------------------------------------------------

@dataclass(frozen=True)
class BoardPose:
    """What one pose contributed: corners in the camera (OpenCV pixels) and in the projector (NaN where the
    Gray code did not decode enough of the corner's window), and how much of the board decoded."""

    name: str
    camera_corners: np.ndarray  # N×2 float64
    projector_corners: np.ndarray  # N×2 float64, NaN rows for corners without a projector position
    decoded_share: float  # decoded camera pixels inside the board's outer corners / all pixels there

    @property
    def decoded(self) -> np.ndarray:
        """Which corners have a projector position."""
        return np.all(np.isfinite(self.projector_corners), axis=1)


@dataclass(frozen=True)
class PoseReport:
    """One pose as the summary shows it: used or skipped (and why), corners, decoded share and residuals."""

    name: str
    used: bool
    reason: str = ""
    corners_found: int = 0
    corners_decoded: int = 0
    decoded_share: float | None = None
    camera_rms: float | None = None  # camera calibration, all corners of this pose (px)
    projector_rms: float | None = None  # projector calibration, this pose's decoded corners (projector px)
    stereo_camera_rms: float | None = None  # stereo calibration residual in the camera image
    stereo_projector_rms: float | None = None  # and in the projector image

    def to_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def _intrinsics_dict(size: Size, K: np.ndarray, dist: np.ndarray, model: str, std: np.ndarray) -> dict[str, Any]:
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    return {
        # The project's convention, the keys of rig.model.Intrinsics.to_dict (pixel corners at integers).
        "width": int(size[0]), "height": int(size[1]), "fx": fx, "fy": fy, "cx": cx + 0.5, "cy": cy + 0.5,
        "convention": "pixel corners at integers",
        # The same K as OpenCV uses it: pixel centres at integers (cx, cy half a pixel less).
        "opencv_matrix": K.tolist(), "opencv_convention": "pixel centres at integers",
        "distortion": {"model": "opencv k1 k2 p1 p2 k3", "coefficients": [float(v) for v in dist],
                       "estimated": list(DISTORTION_MODELS[model])},
        # One standard deviation of fx, fy, cx, cy from OpenCV (assumes the model is right: a lower bound).
        "std": {"fx": float(std[0]), "fy": float(std[1]), "cx": float(std[2]), "cy": float(std[3])},
    }


@dataclass(frozen=True)
class RigCalibration:
    """Camera and projector intrinsics (OpenCV pixel-centre matrices), distortion (k1 k2 p1 p2 k3), the
    projector's pose in the camera frame, residuals and the per-pose account."""

    board: tuple[int, int]
    square: float
    camera_size: Size
    projector_size: Size
    camera_matrix: np.ndarray
    camera_distortion: np.ndarray
    projector_matrix: np.ndarray
    projector_distortion: np.ndarray
    camera_from_projector: np.ndarray  # 4×4: projector-frame points → camera (rig) frame
    camera_rms: float
    projector_rms: float
    stereo_rms: float
    camera_std: np.ndarray  # σ of fx, fy, cx, cy
    projector_std: np.ndarray
    poses: tuple[PoseReport, ...]
    observations: tuple[BoardPose, ...] = field(repr=False, default=())
    camera_model: str = "k1k2p1p2"
    projector_model: str = "k1k2"
    stereo_flags: str = "CALIB_FIX_INTRINSIC"
    window: int = 47
    warnings: tuple[str, ...] = ()
    #: True when ``square`` was given in metres, so that the projector's position is metric
    metric: bool = False
    #: with ``auto``: each candidate projector model's RMS and BIC, and why the chosen one was kept
    projector_model_choice: dict[str, Any] = field(default_factory=dict)

    @property
    def rotation(self) -> np.ndarray:
        """OpenCV's stereo R: camera-frame points → projector frame (with :attr:`translation`)."""
        return self.camera_from_projector[:3, :3].T.copy()

    @property
    def translation(self) -> np.ndarray:
        """OpenCV's stereo T (in the unit of ``square``)."""
        return -self.camera_from_projector[:3, :3].T @ self.camera_from_projector[:3, 3]

    @property
    def used(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.poses if p.used)

    @property
    def skipped(self) -> dict[str, str]:
        return {p.name: p.reason for p in self.poses if not p.used}

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON types: what ``rig.json`` holds besides its format header."""
        return {
            "frame": "camera's OpenCV frame (x right, y down, z forward); lengths in the unit of board.square",
            "board": {"inner_corners": list(self.board), "square": float(self.square),
                      "unit": "m" if self.metric else "board square"},
            "camera": _intrinsics_dict(self.camera_size, self.camera_matrix, self.camera_distortion,
                                       self.camera_model, self.camera_std),
            "projector": _intrinsics_dict(self.projector_size, self.projector_matrix, self.projector_distortion,
                                          self.projector_model, self.projector_std),
            "camera_from_projector": self.camera_from_projector.tolist(),
            "opencv_stereo": {"R": self.rotation.tolist(), "T": self.translation.tolist(),
                              "meaning": "x_projector = R x_camera + T (OpenCV stereoCalibrate)",
                              "flags": self.stereo_flags},
            "rms": {"camera": float(self.camera_rms), "projector": float(self.projector_rms),
                    "stereo": float(self.stereo_rms)},
            "homography_window": int(self.window),
            "poses": [p.to_dict() for p in self.poses],
            "warnings": list(self.warnings),
            **({"projector_model_choice": self.projector_model_choice} if self.projector_model_choice else {}),
        }

    @staticmethod
    def known(camera_size: Size, projector_size: Size, camera_matrix: np.ndarray, camera_distortion: Any,
              projector_matrix: np.ndarray, *, camera_from_projector: np.ndarray | None = None,
              metric: bool = False) -> RigCalibration:
        """A rig whose lenses (and pose) come from elsewhere, not from board photographs: a camera calibrated with
        another tool, or the lab's truth. It keeps no board residuals (0) or σ (NaN); ``rig.json`` holds it as
        ``procam calibrate-rig`` writes one (:func:`..steps.rig.write`), for ``import-captures --rig`` and
        ``undistort-captures``. ``camera_from_projector`` in metres when ``metric``, else in board squares."""
        nan4 = np.full(4, np.nan)
        pose = np.eye(4) if camera_from_projector is None else np.asarray(camera_from_projector, float)
        return RigCalibration((9, 7), 1.0, (int(camera_size[0]), int(camera_size[1])),
                              (int(projector_size[0]), int(projector_size[1])), np.asarray(camera_matrix, float),
                              np.asarray(camera_distortion, float), np.asarray(projector_matrix, float), np.zeros(5),
                              pose, 0.0, 0.0, 0.0, nan4, nan4.copy(), (), metric=metric)

    @staticmethod
    def from_dict(d: dict[str, Any]) -> RigCalibration:
        """The inverse of :meth:`to_dict` (without the per-corner observations)."""
        cam, proj = d["camera"], d["projector"]

        def std(block: dict[str, Any]) -> np.ndarray:
            s = block.get("std", {})
            return np.array([np.nan if s.get(k) is None else float(s[k]) for k in ("fx", "fy", "cx", "cy")])

        models = {v: k for k, v in DISTORTION_MODELS.items()}
        return RigCalibration(
            board=(int(d["board"]["inner_corners"][0]), int(d["board"]["inner_corners"][1])),
            square=float(d["board"]["square"]),
            camera_size=(int(cam["width"]), int(cam["height"])),
            projector_size=(int(proj["width"]), int(proj["height"])),
            camera_matrix=np.asarray(cam["opencv_matrix"], dtype=float).reshape(3, 3),
            camera_distortion=np.asarray(cam["distortion"]["coefficients"], dtype=float),
            projector_matrix=np.asarray(proj["opencv_matrix"], dtype=float).reshape(3, 3),
            projector_distortion=np.asarray(proj["distortion"]["coefficients"], dtype=float),
            camera_from_projector=np.asarray(d["camera_from_projector"], dtype=float).reshape(4, 4),
            camera_rms=float(d["rms"]["camera"]), projector_rms=float(d["rms"]["projector"]),
            stereo_rms=float(d["rms"]["stereo"]), camera_std=std(cam), projector_std=std(proj),
            poses=tuple(PoseReport(**p) for p in d.get("poses", [])),
            camera_model=models.get(tuple(cam["distortion"].get("estimated", [])), "k1k2p1p2k3"),
            projector_model=models.get(tuple(proj["distortion"].get("estimated", [])), "k1k2p1p2k3"),
            stereo_flags=str(d.get("opencv_stereo", {}).get("flags", "")),
            window=int(d.get("homography_window", 0)), warnings=tuple(d.get("warnings", [])),
            metric=d["board"].get("unit") == "m", projector_model_choice=dict(d.get("projector_model_choice", {})))


# -- per pose ----------------------------------------------------------------------------------------

def _to_uint8(grey: np.ndarray) -> np.ndarray:
    """8-bit for the chessboard finder, stretched to the image's 0.5–99.5 % range: a dim 16-bit capture of a
    board lit by a projector would otherwise be a few grey levels."""
    lo, hi = np.percentile(grey, [0.5, 99.5])
    if not hi > lo:
        return np.zeros(grey.shape, np.uint8)
    return np.clip((grey - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)


def find_board(white: np.ndarray, board: tuple[int, int]) -> np.ndarray | None:
    """The board's inner corners (N×2, OpenCV pixels, row by row) in a grey image, or None when not found.

    ``board`` is (corners per row, rows) as OpenCV's ``patternSize``; OpenCV finds a board in either
    orientation, so 9×7 and 7×9 both work (they only order the corners differently).
    """
    img = _to_uint8(white)
    ok, corners = cv2.findChessboardCorners(img, board, cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        return None
    # Sub-pixel refinement on the float image (the 8-bit copy would quantise the edges the refinement fits),
    # over a search window of about a quarter of a square: large enough to average, small enough to stay
    # clear of the neighbouring corners.
    pts = corners.reshape(board[1], board[0], 2)
    spacing = float(np.median(np.linalg.norm(np.diff(pts, axis=1), axis=2))) if board[0] > 1 else 20.0
    half = int(np.clip(spacing / 4, 2, 11))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    refined = cv2.cornerSubPix(np.ascontiguousarray(white, np.float32), corners.astype(np.float32),
                               (half, half), (-1, -1), criteria)
    return refined.reshape(-1, 2).astype(np.float64)


def corner_in_projector(corner: np.ndarray, coords: np.ndarray, valid: np.ndarray, window: int,
                        min_pixels: int, threshold: float) -> np.ndarray | None:
    """A corner's projector position through a local homography fitted to the decoded pixels around it.

    ``coords`` are decoded projector positions (OpenCV pixels) per camera pixel, ``valid`` where they exist.
    RANSAC (``threshold`` projector pixels) drops wrongly decoded pixels (a flipped bit moves a decode by
    hundreds of pixels); OpenCV then refits the homography to the inliers by least squares. None when fewer
    than ``min_pixels`` decoded, or fewer than half of those agree.
    """
    h, w = valid.shape
    r = window // 2
    x0, y0 = int(round(corner[0])), int(round(corner[1]))
    ya, yb, xa, xb = max(y0 - r, 0), min(y0 + r + 1, h), max(x0 - r, 0), min(x0 + r + 1, w)
    if ya >= yb or xa >= xb:
        return None
    ys, xs = np.mgrid[ya:yb, xa:xb]
    ok = valid[ya:yb, xa:xb]
    n = int(ok.sum())
    if n < min_pixels:
        return None
    # Centred on the corner: better conditioned, and the corner maps from (0, 0).
    src = np.stack([xs[ok] - corner[0], ys[ok] - corner[1]], axis=-1).astype(np.float64)
    dst = coords[ya:yb, xa:xb][ok].astype(np.float64)
    H, inliers = cv2.findHomography(src, dst, cv2.RANSAC, threshold, maxIters=500, confidence=0.999)
    if H is None or inliers is None or int(inliers.sum()) < max(n // 2, 8) or abs(H[2, 2]) < 1e-12:
        return None
    p = H[:, 2]
    out = p[:2] / p[2]
    return out if np.all(np.isfinite(out)) else None


def observe_pose(source: PoseSource, board: tuple[int, int], projector_size: Size, *, window: int = 47,
                 black_threshold: float = 0.02, white_threshold: float = 0.004,
                 camera_size: Size | None = None) -> tuple[BoardPose | None, str, Size]:
    """Corners and their projector positions in one pose: (observation or None, why it is unusable, image size).

    A board that is not found is not an error here (the caller skips the pose and says so); images of the
    wrong size or count are (:class:`CaptureError`, naming the pose).
    """
    white = as_grey(source.white())
    size = (white.shape[1], white.shape[0])
    if camera_size is not None and size != tuple(camera_size):
        raise CaptureError(f"pose {source.name}: its images are {size[0]}×{size[1]}, the first pose's "
                           f"{camera_size[0]}×{camera_size[1]}; every pose must come from the same camera")
    black = as_grey(source.black())  # read first: a white image of the wrong size shows here, not as no board
    if black.shape != white.shape:
        raise CaptureError(f"pose {source.name}: the black image is {black.shape[1]}×{black.shape[0]}, the white "
                           f"image {size[0]}×{size[1]}; all images of a pose must have the same size")
    corners = find_board(white, board)
    if corners is None:
        return None, (f"no {board[0]}×{board[1]} chessboard found in its white image (check --board, the "
                      "focus and that the whole board is in view)"), size
    gray = [as_grey(g) for g in source.gray_code()]
    for i, img in enumerate(gray):
        if img.shape != white.shape:
            raise CaptureError(f"pose {source.name}: Gray-code image {i} is {img.shape[1]}×{img.shape[0]}, the white "
                               f"image {size[0]}×{size[1]}; all images of a pose must have the same size")
    dec = decode_gray_code(gray, projector_size, white_capture=white, black_capture=black,
                           black_threshold=black_threshold, white_threshold=white_threshold)
    del gray
    coords = dec.coords - 0.5  # the decoder's pixel centres are index + 0.5 (corner convention); OpenCV's: index
    outline = cv2.convexHull(corners.astype(np.float32)).reshape(-1, 2)
    mask = np.zeros(white.shape, np.uint8)
    cv2.fillConvexPoly(mask, np.round(outline).astype(np.int32), 1)
    inside = mask.astype(bool)
    share = float(dec.valid[inside].mean()) if inside.any() else 0.0
    # A tenth of the window: a corner's window covers two lit and two dark squares, and dark squares often do
    # not decode; a tenth of the window still gives hundreds of pixels for the eight-parameter fit.
    min_pixels = max(window * window // 10, 12)
    proj = np.full(corners.shape, np.nan)
    for i, c in enumerate(corners):
        p = corner_in_projector(c, coords, dec.valid, window, min_pixels, threshold=2.0)
        if p is not None:
            proj[i] = p
    return BoardPose(source.name, corners, proj, share), "", size


# -- the calibration ---------------------------------------------------------------------------------

def _object_points(board: tuple[int, int], square: float) -> np.ndarray:
    """Board corners in the board's frame, in the order findChessboardCorners returns them (row by row)."""
    cols, rows = board
    grid = np.zeros((cols * rows, 3), np.float32)
    grid[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * float(square)
    return grid


def _dlt(points: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """3×4 projection matrix from ≥ 6 non-coplanar 3-D points and their pixels (normalised DLT)."""
    m3, m2 = points.mean(axis=0), pixels.mean(axis=0)
    s3 = np.sqrt(((points - m3) ** 2).sum(axis=1).mean() / 3) or 1.0
    s2 = np.sqrt(((pixels - m2) ** 2).sum(axis=1).mean() / 2) or 1.0
    X, x = (points - m3) / s3, (pixels - m2) / s2
    n = len(X)
    A = np.zeros((2 * n, 12))
    Xh = np.hstack([X, np.ones((n, 1))])
    A[0::2, 0:4], A[0::2, 8:12] = Xh, -x[:, :1] * Xh
    A[1::2, 4:8], A[1::2, 8:12] = Xh, -x[:, 1:] * Xh
    P = np.linalg.svd(A)[2][-1].reshape(3, 4)
    T3 = np.diag([s3, s3, s3, 1.0])
    T3[:3, 3] = m3
    T2 = np.array([[s2, 0, m2[0]], [0, s2, m2[1]], [0, 0, 1.0]])
    return T2 @ P @ np.linalg.inv(T3)


def _projector_start(obj: list[np.ndarray], proj: list[np.ndarray], rvecs: Sequence[np.ndarray],
                     tvecs: Sequence[np.ndarray]) -> np.ndarray | None:
    """A starting K for the projector, or None to let OpenCV start.

    OpenCV's planar start fixes the principal point at the image centre while it solves for the focal
    lengths; a real projector's is often far outside its frame (DESIGN §9), and on real data that start
    falls into a worse minimum (higher residual). Here the camera has already placed every board corner in
    3-D; the corners of several poses are not coplanar, so a DLT from them to the projector's corners gives
    the projector's K with no assumption about its principal point.
    """
    pts, pix = [], []
    for o, p, r, t in zip(obj, proj, rvecs, tvecs):
        R, _ = cv2.Rodrigues(np.asarray(r, np.float64))
        pts.append(o.astype(np.float64) @ R.T + np.asarray(t, np.float64).reshape(1, 3))
        pix.append(p.astype(np.float64))
    X, x = np.vstack(pts), np.vstack(pix)
    if len(X) < 12:
        return None
    P = _dlt(X, x)
    if np.linalg.det(P[:, :3]) < 0:  # P is known up to scale, sign included: choose points in front (depth > 0)
        P = -P
    try:
        K = cv2.decomposeProjectionMatrix(P)[0]
    except cv2.error:
        return None
    K = K @ np.diag(np.sign(np.diag(K)))  # the RQ split leaves signs free between K and R: K's diagonal positive
    K = K / K[2, 2]
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
        return None
    K[0, 1] = 0.0  # OpenCV's calibration has no skew
    return K


def _calibrate_projector(obj: list[np.ndarray], proj: list[np.ndarray], size: Size, start: np.ndarray | None,
                         flags: int, criteria: tuple) -> tuple:
    """OpenCV's calibration of the projector from its inferred corners: rms, K, distortion, rvecs, tvecs, std."""
    pw, ph = size
    if start is None:
        rms, K, d, rv, tv, std, _, _ = cv2.calibrateCameraExtended(obj, proj, (pw, ph), None, None, flags=flags,
                                                                    criteria=criteria)
        return rms, K, d, rv, tv, std
    # OpenCV refuses a starting principal point outside the image, which is where a real projector's is.
    # Shifting every projector coordinate by ``shift`` moves the principal point by the same amount and nothing
    # else (distortion acts before K), so calibrate in a frame that contains it, shift back.
    start = start.copy()
    margin = np.array([pw, ph], float) / 4
    pp = start[:2, 2]
    shift = np.maximum(margin - pp, 0.0)
    frame = np.maximum(np.array([pw, ph], float), pp + margin) + shift
    start[:2, 2] += shift
    shifted = [(p + shift).astype(np.float32) for p in proj]
    rms, K, d, rv, tv, std, _, _ = cv2.calibrateCameraExtended(
        obj, shifted, (int(np.ceil(frame[0])), int(np.ceil(frame[1]))), start, np.zeros(5),
        flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS, criteria=criteria)
    K[:2, 2] -= shift
    return rms, K, d, rv, tv, std


def _choose_model(fits: dict[str, tuple], points: int) -> tuple[str, dict[str, Any]]:
    """The nested distortion model the projector's corners support, by the Bayesian information criterion.

    Why not always k1 k2: a projector with little distortion (the lab's has none) fitted with k1 k2 anyway
    lets its principal point and tilt trade against them (measured: the lab's principal point 2.5 px and its
    axis 0.24° off with k1 k2, 0.2 px and 0.09° without). Why BIC: each extra coefficient must lower the
    residual by more than chance would (n·ln(RSS₀/RSS₁) > Δk·ln n, with n the 2·corners residuals; for
    ~750 residuals, about 0.9 % less RSS per coefficient), so real distortion, which lowers it by far more,
    is kept.
    """
    n = 2 * points
    table: dict[str, dict[str, float]] = {}
    for model, fit in fits.items():
        rss = float(fit[0]) ** 2 * points  # OpenCV's RMS is per point (both coordinates)
        k = len(DISTORTION_MODELS[model])
        table[model] = {"rms": float(fit[0]), "bic": n * float(np.log(max(rss, 1e-300) / n)) + k * float(np.log(n))}
    best = min(table, key=lambda m: (table[m]["bic"], len(DISTORTION_MODELS[m])))
    return best, {"asked": "auto", "chosen": best, "criterion": "BIC over the projector's corner residuals",
                  "residuals": n, "candidates": table}


def _per_view_rms(obj: list[np.ndarray], img: list[np.ndarray], K: np.ndarray, dist: np.ndarray,
                  rvecs: Sequence[np.ndarray], tvecs: Sequence[np.ndarray]) -> list[float]:
    out = []
    for o, i, r, t in zip(obj, img, rvecs, tvecs):
        p, _ = cv2.projectPoints(o, r, t, K, dist)
        out.append(float(np.sqrt(((p.reshape(-1, 2) - i.reshape(-1, 2)) ** 2).sum(axis=1).mean())))
    return out


def calibrate_rig(sessions: Sequence[PoseSource], board: tuple[int, int] = (9, 7), square: float = 1.0,
                  projector_size: Size = (1024, 768), progress: Progress | None = None,
                  cancel: Cancel | None = None, *, window: int = 47, camera_model: str = "k1k2p1p2",
                  projector_model: str = "auto", min_corner_share: float = 0.5, black_threshold: float = 0.02,
                  white_threshold: float = 0.004) -> RigCalibration:
    """Calibrate camera, projector and their relative pose from board poses lit by Gray code.

    ``board`` is the chessboard's inner corners (per row, rows); ``square`` its square size (the unit of the
    translation); ``projector_size`` the Gray-code grid (the projector's native frame). Poses whose board is
    not found, or whose Gray code gives fewer than ``min_corner_share`` of the corners a projector position,
    are skipped with a warning (through ``progress``, as ``warning: …``); fewer than :data:`MIN_POSES` usable
    poses is a :class:`CalibrationError`.

    Distortion models (:data:`DISTORTION_MODELS`). Camera: k1 k2 p1 p2 — k3 is left at 0 because with a
    handful of poses it is not observable (it trades against k1, k2 and the focal length; the published
    calibration of the real data set has k3 = 3.1, a sign of that). Projector: ``auto`` — none, k1 or k1 k2,
    whichever its corners support (:func:`_choose_model`); its tangential terms are never fitted by default, as
    they trade against a principal point that only a few poses barely constrain.

    Stereo: ``cv2.stereoCalibrate`` with ``CALIB_FIX_INTRINSIC``. Each device's intrinsics are better
    determined by its own calibration (the camera's from every corner, not only the decoded ones); refining
    them jointly with the pose from a few poses lets the pose absorb intrinsics errors, and on the real data
    OpenCV's joint refinement ends *above* the fixed-intrinsics residual (it converges to a worse minimum).
    """
    say = progress or quiet
    cols, rows = (int(v) for v in board)
    if cols < 2 or rows < 2:
        raise CalibrationError(f"the chessboard must have at least 2×2 inner corners, got {cols}×{rows}")
    if not square > 0:
        raise CalibrationError(f"the chessboard square size must be positive, got {square}")
    if window < 5:
        raise CalibrationError(f"the homography window must be at least 5 camera pixels, got {window}")
    cam_flags = _model_flags(camera_model)
    proj_flags = 0 if projector_model == "auto" else _model_flags(projector_model)
    pw, ph = (int(v) for v in projector_size)
    gray_code_bits((pw, ph))  # checks the size
    if len(sessions) < MIN_POSES:
        raise CalibrationError(f"{len(sessions)} board pose(s) given; rig calibration needs at least {MIN_POSES} "
                               "(5–10 recommended), each with the board at a different tilt")

    observations: list[BoardPose] = []
    used: list[int] = []  # index in ``sessions`` of each observation
    reports: list[PoseReport] = []
    warnings: list[str] = []
    camera_size: Size | None = None
    n = len(sessions)
    for k, source in enumerate(sessions):
        check(cancel, "rig calibration")
        say(f"pose {source.name}: finding the board and decoding the Gray code", 0.8 * k / n)
        obs, reason, size = observe_pose(source, (cols, rows), (pw, ph), window=window,
                                         black_threshold=black_threshold, white_threshold=white_threshold,
                                         camera_size=camera_size)
        camera_size = camera_size or size
        found = 0 if obs is None else len(obs.camera_corners)
        decoded = 0 if obs is None else int(obs.decoded.sum())
        if obs is not None and decoded < min_corner_share * found:
            reason = (f"the Gray code decoded on only {100 * obs.decoded_share:.0f} % of the board, giving "
                      f"{decoded} of {found} corners a projector position (need {100 * min_corner_share:.0f} %); "
                      "check that the projector lights the whole board, the exposure, and --projector")
        if reason:
            msg = f"pose {source.name} skipped: {reason}"
            warnings.append(msg)
            say(f"warning: {msg}", 0.8 * (k + 1) / n)
            reports.append(PoseReport(source.name, False, reason, found, decoded,
                                      None if obs is None else obs.decoded_share))
            continue
        assert obs is not None
        observations.append(obs)
        used.append(k)
        reports.append(PoseReport(source.name, True, "", found, decoded, obs.decoded_share))
    if len(observations) < MIN_POSES:
        why = "; ".join(warnings) or "no reason recorded"
        raise CalibrationError(f"only {len(observations)} of {n} board poses are usable ({why}); rig calibration "
                               f"needs at least {MIN_POSES}: capture more poses")
    assert camera_size is not None
    check(cancel, "rig calibration")

    obj = _object_points((cols, rows), square)
    cam_obj = [obj for _ in observations]
    cam_img = [o.camera_corners.astype(np.float32) for o in observations]
    sub_obj = [obj[o.decoded] for o in observations]
    sub_cam = [o.camera_corners[o.decoded].astype(np.float32) for o in observations]
    sub_proj = [o.projector_corners[o.decoded].astype(np.float32) for o in observations]
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-10)
    try:
        say("calibrating the camera", 0.82)
        cam_rms, Kc, dc, c_rv, c_tv, c_std, _, _ = cv2.calibrateCameraExtended(
            cam_obj, cam_img, camera_size, None, None, flags=cam_flags, criteria=criteria)
        check(cancel, "rig calibration")
        say("calibrating the projector", 0.88)
        # The camera's board poses for the decoded corners place them in 3-D for the projector's start.
        start = _projector_start(sub_obj, sub_proj, c_rv, c_tv)
        if projector_model == "auto":
            fits = {m: _calibrate_projector(sub_obj, sub_proj, (pw, ph), start, _model_flags(m), criteria)
                    for m in AUTO_MODELS}
            projector_model, choice = _choose_model(fits, sum(len(p) for p in sub_proj))
        else:
            fits = {projector_model: _calibrate_projector(sub_obj, sub_proj, (pw, ph), start, proj_flags, criteria)}
            choice = {}
        proj_rms, Kp, dp, p_rv, p_tv, p_std = fits[projector_model]
        check(cancel, "rig calibration")
        say("calibrating the camera → projector pose", 0.94)
        stereo = cv2.stereoCalibrateExtended(
            sub_obj, sub_cam, sub_proj, Kc, dc, Kp, dp, camera_size, np.eye(3), np.zeros((3, 1)),
            flags=cv2.CALIB_FIX_INTRINSIC, criteria=criteria)
    except cv2.error as exc:
        raise CalibrationError(f"OpenCV's calibration failed ({str(exc).strip().splitlines()[-1]}); check --board "
                               "and --projector, and capture more poses with the board at different tilts") from None
    stereo_rms, R, T, per_view = float(stereo[0]), stereo[5], stereo[6], stereo[-1]
    values = [cam_rms, proj_rms, stereo_rms, *Kc.ravel(), *Kp.ravel(), *R.ravel(), *T.ravel()]
    if not np.all(np.isfinite(values)):
        raise CalibrationError("the calibration did not converge (non-finite result); capture more poses with "
                               "the board at different tilts and check --board and --projector")

    cam_views = _per_view_rms(cam_obj, cam_img, Kc, dc, c_rv, c_tv)
    proj_views = _per_view_rms(sub_obj, sub_proj, Kp, dp, p_rv, p_tv)
    per_view = np.asarray(per_view, dtype=float).reshape(len(observations), -1)
    for i, k in enumerate(used):
        rep = reports[k]
        reports[k] = PoseReport(rep.name, True, "", rep.corners_found, rep.corners_decoded, rep.decoded_share,
                                cam_views[i], proj_views[i], float(per_view[i, 0]), float(per_view[i, 1]))
    pose = np.eye(4)
    pose[:3, :3] = R.T
    pose[:3, 3] = (-R.T @ T).ravel()
    say("done", 1.0)
    return RigCalibration(
        board=(cols, rows), square=float(square), camera_size=camera_size, projector_size=(pw, ph),
        camera_matrix=Kc, camera_distortion=dc.ravel()[:5].copy(), projector_matrix=Kp,
        projector_distortion=dp.ravel()[:5].copy(), camera_from_projector=pose, camera_rms=float(cam_rms),
        projector_rms=float(proj_rms), stereo_rms=stereo_rms, camera_std=c_std.ravel()[:4].copy(),
        projector_std=p_std.ravel()[:4].copy(), poses=tuple(reports),
        observations=tuple(observations), camera_model=camera_model, projector_model=projector_model,
        stereo_flags="CALIB_FIX_INTRINSIC", window=int(window), warnings=tuple(warnings),
        projector_model_choice=choice)


__all__ = ["AUTO_MODELS", "DISTORTION_MODELS", "MIN_POSES", "BoardPose", "PoseReport", "PoseSource", "RigCalibration",
           "as_grey", "calibrate_rig", "corner_in_projector", "find_board", "observe_pose"]
