"""A depth image without a depth sensor: the decoded Gray code triangulated with a calibrated rig.

When the camera's and the projector's intrinsics and the projector's pose are
known (a capture set imported with a metric rig file, ``projector_pose_known``),
every camera pixel that decodes a projector pixel is a pair of rays, and their
crossing is the surface point. :func:`triangulate_depth` turns that into a depth
image in the camera (pinhole, the capture set's camera K, NaN where nothing
was decoded), which calibration then meshes exactly like a sensor's depth
(:func:`procam.addon.surface.reconstruct.reconstruct_surface`), so the mesh,
its texture and the albedo take the same path whatever the depth came from.

Two choices, and why:

* The camera pixel is exact and the projector coordinate is the noisy one
  (Gray code resolves whole projector pixels: ±0.5 px, a uniform error of
  0.29 px rms, which at a 9° triangulation angle is ~6 mm of depth per
  pixel on the lab rig). So each point is the one on the camera pixel's ray
  whose projection into the projector comes closest to the decoded position
  (a closed-form 1-D least squares), not the midpoint of two rays that are
  equally trusted; the reprojection error is then the projector-side
  distance, in projector pixels, and it measures the epipolar disagreement.
* The decoded coordinates are used as they are: the whole-pixel staircase
  is averaged by the mesh reconstruction (each grid vertex averages a 4×4
  cell, then Taubin smoothing). Smoothing the coordinates over the camera
  image first (a normalised Gaussian, σ = 1–2 camera px) lowered the
  reprojection RMS from 0.31 to 0.13 px but made the mesh worse at the
  footprint's border, where the average is one-sided (lab curve at half
  resolution: mean distance 0.65 → 0.81 mm, p95 1.6 → 3.5 mm).

Points are rejected when they lie behind the camera or the projector, when
the rays are too parallel to cross (reprojection beyond
``max_reprojection_px``, a bit error across the epipolar line) or outside
``[near, far]``; the local-median outlier test of the mesh reconstruction
catches bit errors along the epipolar line, which no reprojection can see.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..capture.format import CaptureSet
from ..capture.patterns import decode_gray_code_set
from ..errors import CaptureError, SurfaceError

#: Largest projector-side reprojection error (projector pixels) of a kept point.
MAX_REPROJECTION_PX = 1.5
#: Fewest triangulated points that make a surface.
MIN_POINTS = 200


@dataclass(frozen=True)
class TriangulationReport:
    decoded: int  # camera pixels with a decoded projector pixel
    points: int  # of those, triangulated and kept
    rejected: int  # behind a device, too far off the epipolar line, or out of range
    reprojection_rms_px: float  # projector pixels, over the kept points
    triangulation_angle_deg: float  # median angle between the camera and projector rays
    coverage: float  # share of the camera image with a depth

    def to_dict(self) -> dict[str, float | int]:
        return dict(self.__dict__)


def triangulate_depth(captures: CaptureSet, camera_from_projector: np.ndarray | None = None, *,
                      max_reprojection_px: float = MAX_REPROJECTION_PX, near: float = 0.1, far: float = 20.0
                      ) -> tuple[np.ndarray, TriangulationReport]:
    """Depth (H×W metres at the camera's resolution, NaN = none) from the capture set's Gray code and a known rig.

    ``camera_from_projector`` (4×4, rig frame, metres) defaults to the capture
    set's projector pose, which must then be a known one
    (``projector_pose_known``: imported with a metric rig file). Raises
    :class:`SurfaceError` saying what to do when the pose is unknown, the Gray
    code is missing or decodes to too little.
    """
    if camera_from_projector is None:
        if not captures.projector_pose_known:
            raise SurfaceError(
                f"the capture set {captures.path} does not know the projector's pose, so its Gray code cannot be "
                "triangulated; import the captures with a metric rig file (procam import-captures --rig rig.json, "
                "from procam calibrate-rig --square METRES), or give the surface as a mesh (--surface-mesh)")
        camera_from_projector = captures.projector.camera_from_projector
    pose = np.asarray(camera_from_projector, dtype=np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise SurfaceError(f"the projector pose must be a finite 4×4 matrix, got shape {pose.shape}")
    if not captures.entries_of("graycode"):
        raise SurfaceError(f"the capture set {captures.path} holds no Gray-code captures to triangulate; capture "
                           "the Gray code, or give a depth image or a mesh of the surface")
    try:
        dec = decode_gray_code_set(captures)
    except CaptureError as exc:
        raise SurfaceError(f"cannot decode the Gray code of {captures.path}: {exc}") from None
    cam_k, proj_k = captures.camera.intrinsics, captures.projector.intrinsics
    h, w = dec.valid.shape
    if (w, h) != cam_k.size:
        raise SurfaceError(f"the Gray-code captures are {w}×{h} but the camera is {cam_k.width}×{cam_k.height}")
    valid = dec.valid
    decoded = int(valid.sum())
    if decoded < MIN_POINTS:
        raise SurfaceError(f"the Gray code of {captures.path} decodes on only {decoded} camera pixels (need "
                           f"{MIN_POINTS}); capture it again with the projector on and the camera still")
    rows, cols = np.nonzero(valid)
    cam_rays = cam_k.rays(np.stack([cols, rows], axis=1) + 0.5)  # camera pixel centres, z = 1
    # projector pixels, corner convention; where a rig calibration measured the projector's lens, where its pinhole
    # would put the rays the decoded pixels send (the real-board projector's k1 k2 move them by up to ~20 px)
    u = captures.projector.undistort(dec.coords[rows, cols].astype(np.float64))

    # Projector coordinates of a point t·d on the camera ray: homogeneous K_p (R^T (t d − c)) = t·a − b.
    p_from_c = np.linalg.inv(pose)
    m = proj_k.matrix @ p_from_c[:3, :3]
    a = cam_rays @ m.T
    b = -(proj_k.matrix @ p_from_c[:3, 3])
    # (t a_xy − b_xy) − u (t a_z − b_z) = 0 for both axes: least squares in t (algebraic error ≈ pixel error ×
    # the projector-side depth, nearly constant along one ray).
    ax = a[:, :2] - u * a[:, 2:3]
    bx = b[:2][None, :] - u * b[2]
    den = np.sum(ax * ax, axis=1)
    t = np.sum(ax * bx, axis=1) / np.maximum(den, 1e-300)
    pts = cam_rays * t[:, None]
    zp = pts @ p_from_c[2, :3] + p_from_c[2, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        hom = pts @ m.T - b
        reproj = np.linalg.norm(hom[:, :2] / hom[:, 2:3] - u, axis=1)
    ok = (t > 0) & (zp > 1e-6) & np.isfinite(reproj) & (reproj <= max_reprojection_px) & (t > near) & (t < far)
    rms = float(np.sqrt(np.mean(reproj[ok] ** 2))) if ok.any() else float("nan")
    c = pose[:3, 3]
    dc = cam_rays[ok] / np.linalg.norm(cam_rays[ok], axis=1, keepdims=True)
    dp = pts[ok] - c
    dp /= np.maximum(np.linalg.norm(dp, axis=1, keepdims=True), 1e-12)
    angle = float(np.degrees(np.median(np.arccos(np.clip(np.sum(dc * dp, axis=1), -1, 1))))) if ok.any() else 0.0
    depth = np.full((h, w), np.nan, np.float32)
    depth[rows[ok], cols[ok]] = pts[ok, 2]  # z of the point on the pixel's ray: what a depth camera stores
    n = int(ok.sum())
    report = TriangulationReport(decoded, n, decoded - n, rms, angle, n / float(h * w))
    if n < MIN_POINTS:
        raise SurfaceError(f"only {n} of the {decoded} decoded Gray-code pixels triangulate in front of both devices "
                           f"within {max_reprojection_px} projector px; the rig file does not fit these captures "
                           "(another rig, or the projector moved since the rig was calibrated)")
    return depth, report
