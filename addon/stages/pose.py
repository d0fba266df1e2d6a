"""Stage A: the projector's pose in the rig frame (the paper's Sec. IV-A and V-B).

The camera sits at the origin of the rig frame; the surface mesh is known
(reconstructed from depth). What is left of the scene parameters is the
projector's position and direction, ``camera_from_projector``. Two sources
of information pin it down:

Gray-code correspondences (``init='graycode'``)
    Decoding the Gray-code captures gives, for each camera pixel, the projector
    pixel it sees. Casting the camera ray of that pixel against the surface
    lifts it to a 3-D point, so every decoded pixel is a 3-D ↔ projector-pixel
    pair and the pose is a Perspective-n-Point problem, solved with OpenCV
    (``solvePnPRansac`` with EPnP, and IPPE on a plane, for a start, then Levenberg–Marquardt on the
    inliers). This uses tens of thousands of points spread over the whole
    footprint and needs no starting pose.

The mask (the paper's stage A)
    The white and black captures give a binary target mask (``|white − black|
    > 0.1``, the paper's threshold). The virtual projector shows the same white
    area, direct light only, and Adam moves a 6-vector pose delta (translation,
    rotation vector, see :mod:`..render.pose`) through the differentiable
    render until the rendered footprint matches the mask.

Soft rendered mask
    The render of a white frame is not a mask: it is ``albedo · E``, with the
    irradiance ``E`` falling with distance and slant. Its albedo is set to 1,
    and the image is divided, per camera pixel, by the irradiance a *fully*
    white texel would give at the surface point that pixel sees,
    ``E_ref = scale · cos θ_s / (z² cos θ)`` (the emitter's own law, see
    :mod:`..render.scene`), computed from the camera's depth map of the
    surface at the current pose and treated as a constant in the gradient.
    The quotient is the projector texel value the pixel receives, averaged over
    the pixel: exactly 1 inside the footprint, 0 outside, and between them the
    edge profile of the frame — a soft mask with no free constants. It is
    clipped at 1 so the interior gives no gradient; only the footprint's
    outline does.

Border smoothing Γ and its bias
    The frame's edge is a one-texel bilinear ramp; a pose error of a few pixels
    puts it where the mask error is flat, and the gradient no longer says how
    far to go. Γ (Eq. 11–12) widens the ramp to ε·W texels, which is what gives
    the search a basin (docs/developer.md, "Facts about the dependencies"). But Γ ramps *inside* the frame, so the
    squared loss against a binary mask is minimal with the ramp's midpoint on
    the mask edge — the rendered footprint ends up ε·W/2 texels too large on
    every side (≈ 1 cm at 2 m). We therefore apply Γ to the white *area*
    (the projector input rectangle when the capture used ``area='input'``; the
    paper's Γ acts on the input image) and anneal ε: the paper's ε = 0.01
    for the coarse phase (rendered 320 pixels wide), then ε = 0 for the fine
    phase at full resolution, where the one-texel bilinear ramp is centred on
    the true frame edge and so unbiased.

Debiased target
    The paper's binary mask is biased too: its edge is where ``white − black``
    crosses 0.1, which on a white level of ~0.5 is a fifth of the way up the
    edge, ~0.5–1 camera pixel outside the frame edge. :func:`soft_target`
    divides by the local white level instead, giving each pixel's coverage,
    whose half level is the frame edge. (Binary target at 0.3 resolution:
    18 mm after PnP + refinement; soft target: 4 mm.)

Preconditioning
    A footprint outline separates a sideways shift from the turn that keeps
    the footprint in place only through perspective: the loss is a long,
    flat, diagonal valley, along which Adam (per-coordinate scaling) crawls.
    From a rough start Adam runs in coordinates whitened by the Gauss–Newton
    metric ``JᵀJ`` of the soft mask (:func:`_whitening`), refreshed every
    :data:`REFRESH` steps.

Measured (``scripts/bench_pose.py``, lab data with ``realistic`` effects,
camera 640×480, projector 800×600, 2 shared CPU cores; position error mm /
direction error degrees / seconds; the nominal start is 160 mm / 5.4° off)::

    surface  PnP (default)     PnP + 60 mask steps  mask alone, nominal  paper's stage A, nominal
    plane    4.0 / 0.09 / 4    6.3 / 0.07 / 27      6.8 / 0.09 / 69      44.7 / 1.36 / 161
    curve    5.8 / 0.18 / 4    7.7 / 0.17 / 54      7.5 / 0.08 / 123     47.1 / 1.31 / 144
    vedge    4.4 / 0.10 / 4    6.7 / 0.10 / 30      7.1 / 0.05 / 60      46.1 / 1.30 / 87
    hedge    4.1 / 0.07 / 4    6.5 / 0.09 / 55      6.7 / 0.02 / 91      44.3 / 1.25 / 161

("paper": binary mask, Γ with ε = 0.01 throughout, plain Adam, 200 steps.)
At half resolution the mask alone reaches 7–12 mm / 0.12–0.27° and PnP
2.4–3.5 mm / 0.03–0.10°. What limits both is not the optimiser: PnP with the
lab's *true* surface is as far off as with the reconstructed one (4.7 mm on
vedge at full resolution; 2.2 mm at 0.3 resolution, where switching the
camera's lens distortion off brings it to 0.4 mm). Our camera model has no
distortion, so the lab's barrel distortion (k1 = −0.036 at ``realistic``)
shifts the decoded correspondences by up to ±0.45 projector pixels across
the image and pulls the footprint's outline in by about a camera pixel; both
sources are biased by it. Refining a PnP pose on the mask moves it ~2 mm
*further* off along the mask's flat valley (loss 4.61e-4 after PnP + mask vs
4.64e-4 for the mask alone, vedge), so after Gray code the mask only checks
the pose by default (``iterations = 0``; ``info['mask_check']``). The mask
refinement is the way in when there is no Gray code (``--init nominal`` or
``blender``), and needs full resolution for the 1 cm figure.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from ..capture.format import CaptureSet
from ..capture.patterns import decode_gray_code_set
from ..errors import CalibrationError, Cancelled, CaptureError, ProCamError
from ..outputs import jsonable
from ..progress import Cancel, Progress
from ..render.backend import mitsuba
from ..render.forward import ForwardModel
from ..render.pose import apply_pose_delta
from ..render.scene import border_smoothing, surface_mesh
from ..rig.model import Intrinsics, Projector, Rig
from ..surface.mesh import SurfaceMesh

#: The paper's mask threshold on |white − black| (linear camera units).
MASK_THRESHOLD = 0.1
#: The paper's border smoothing ε (Eq. 12).
PAPER_EPS = 0.01
#: A mask covering less than this share of the camera image is "touching nothing" …
MIN_MASK_FRACTION = 0.005
#: … and one covering more hides the footprint's outline, which is what stage A fits.
MAX_MASK_FRACTION = 0.97
#: Least overlap (intersection over union) of the final simulated footprint with the mask that counts as found.
MIN_IOU = 0.5
#: Fewest decoded Gray-code pixels with a surface point that PnP accepts.
MIN_CORRESPONDENCES = 50
INITS = ("graycode", "nominal", "blender", "given")
#: Stage-A methods: ours (soft debiased target, annealed Γ, preconditioned) or the paper's (binary mask, Γ with
#: ε = 0.01 throughout, plain Adam, 200 steps), kept to reproduce the paper and its ablations.
METHODS = ("ours", "paper")
#: Adam steps on the mask from a rough start (no Gray code).
DEFAULT_ITERATIONS = 200
#: Camera width rendered in the coarse phase: enough pixels for the footprint, 4× fewer than full resolution.
COARSE_WIDTH = 320
#: Adam steps between refreshes of the preconditioning metric.
REFRESH = 25




@dataclass
class PoseResult:
    """What stage A found, how, and the images that show it."""

    camera_from_projector: np.ndarray  # 4×4, rig frame, metres
    init: str  # 'graycode' | 'nominal' | 'blender' | 'given'
    steps: dict[str, np.ndarray]  # pose after each sub-step, in order ('initial', 'graycode_pnp', 'mask_coarse', ...)
    losses: list[float]  # mask loss per Adam iteration
    seconds: float
    diagnostics: dict[str, np.ndarray] = field(default_factory=dict)  # 'mask', 'rendered_mask', ... (H×W float32)
    info: dict[str, Any] = field(default_factory=dict)  # PnP inliers, reprojection error, phase timings
    #: the camera's rays cast at the surface and the lit mask stage A worked on, for what judges the pose after it
    #: (not saved)
    view: SurfaceView | None = field(default=None, repr=False)
    mask: np.ndarray | None = field(default=None, repr=False)

    @property
    def position(self) -> np.ndarray:
        return self.camera_from_projector[:3, 3].copy()

    @property
    def direction(self) -> np.ndarray:
        return self.camera_from_projector[:3, 2].copy()

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe summary (no images)."""
        return {"camera_from_projector": np.asarray(self.camera_from_projector).tolist(),
                "init": self.init,
                "steps": {k: np.asarray(v).tolist() for k, v in self.steps.items()},
                "losses": [float(v) for v in self.losses],
                "final_loss": float(self.losses[-1]) if self.losses else None,
                "seconds": float(self.seconds),
                "info": jsonable(self.info)}


def pose_error(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(position error in metres, angle between the optical axes in degrees) of two poses."""
    e, t = np.asarray(estimate, float), np.asarray(truth, float)
    pos = float(np.linalg.norm(e[:3, 3] - t[:3, 3]))
    cos = float(np.clip(np.dot(e[:3, 2], t[:3, 2]), -1.0, 1.0))
    return pos, math.degrees(math.acos(cos))


# ------------------------------------------------------------------ the target mask

def _grey(img: np.ndarray) -> np.ndarray:
    return np.asarray(img, dtype=np.float32).mean(axis=2)


def target_mask(captures: CaptureSet, threshold: float = MASK_THRESHOLD) -> tuple[np.ndarray, np.ndarray]:
    """(binary mask, white − black difference) from the white and black captures; checks both.

    A white capture that is not brighter than the black one (projector off,
    lens cap on, wrong files) and a mask that touches (nearly) nothing are
    :class:`CalibrationError` naming the capture.
    """
    try:
        white_e, black_e = captures.entry("white"), captures.entry("black")
        white, black = captures.image("white"), captures.image("black")
    except CaptureError as exc:
        raise CalibrationError(f"stage A needs one white and one black capture: {exc}") from None
    diff = _grey(white) - _grey(black)
    wf, bf = captures.file(white_e), captures.file(black_e)
    # The brightest 0.1 % of the difference: a few hot or noisy pixels do not count as light.
    top = float(np.percentile(diff, 99.9))
    if top <= threshold:
        raise CalibrationError(
            f"the white capture {wf} is no brighter than the black capture {bf} (the brightest 0.1 % of the "
            f"difference reach only {top:.3f}, threshold {threshold}); was the projector off, its lens capped, or "
            "the captures swapped? Capture white and black again with the projector on")
    mask = np.abs(_grey(white) - _grey(black)) > threshold
    frac = float(mask.mean())
    if frac < MIN_MASK_FRACTION:
        raise CalibrationError(
            f"the mask from the white capture {wf} touches almost nothing ({100 * frac:.2f} % of the camera "
            f"image brighter than the black capture by more than {threshold}); the projector does not reach the "
            "surface in the camera's view — aim it at the surface and capture again")
    if frac > MAX_MASK_FRACTION:
        raise CalibrationError(
            f"the mask from the white capture {wf} covers {100 * frac:.1f} % of the camera image: the footprint's "
            "outline must be visible for stage A; widen the camera's view or move it back, and capture again")
    return mask, diff


def soft_target(mask: np.ndarray, diff: np.ndarray, radius: float = 2.0) -> np.ndarray:
    """The share of full white each camera pixel receives: ``diff`` over the local white level, in [0, 1].

    The binary mask's edge sits where ``diff`` crosses the threshold 0.1, not
    where the frame edge is: with a white level of ~0.5 and a slightly blurred
    projector, a pixel a fifth covered already counts, so the mask is dilated
    by ~0.5–1 camera pixel (≈ 5 mm at 1.7 m on a 192-pixel-wide test image).
    Dividing ``diff`` by the local interior level (a normalised Gaussian
    average over pixels that are surely inside: the mask eroded by two pixels)
    gives the pixel's coverage instead, whose half level lies on the frame
    edge for any symmetric blur — the counterpart of the soft rendered mask.
    """
    m = mask.astype(np.uint8)
    inside = cv2.erode(m, np.ones((5, 5), np.uint8)).astype(np.float32)
    if inside.sum() < 1:
        inside = m.astype(np.float32)
    sigma = max(radius, 0.5)
    num = cv2.GaussianBlur(np.where(inside > 0, diff, 0).astype(np.float32), (0, 0), sigma)
    den = cv2.GaussianBlur(inside, (0, 0), sigma)
    # Far from the footprint (beyond the blur's reach) there is no interior level: those pixels are outside.
    level = np.where(den > 1e-4, num / np.maximum(den, 1e-6), np.inf)
    return np.clip(diff / level, 0.0, 1.0).astype(np.float32)


def white_frame(captures: CaptureSet, projector: Projector, eps: float) -> np.ndarray:
    """The white frame the white capture showed (native size, H×W), with Γ(ε) over its white area.

    Γ belongs to the *white area* — the projector input rectangle when the
    capture used ``area='input'`` — so that all four of its edges are smoothed,
    not only those on the frame border.
    """
    entry = captures.entry("white")
    area = entry.params.get("area", "input")
    w, h = projector.intrinsics.size
    if area == "frame":
        return border_smoothing(w, h, eps)
    iw, ih = projector.input_size
    x0, y0 = projector.input_offset
    frame = np.zeros((h, w), np.float32)
    frame[y0:y0 + ih, x0:x0 + iw] = border_smoothing(iw, ih, eps)
    return frame


# ------------------------------------------------------------------ geometry of the camera's view of the surface

@dataclass(frozen=True)
class SurfaceView:
    """Per camera pixel (centre): the surface point it sees and that point's normal; NaN where it sees none."""

    points: np.ndarray  # H×W×3, rig frame
    normals: np.ndarray  # H×W×3, unit, facing the camera
    camera: Intrinsics

    @property
    def hit(self) -> np.ndarray:
        return np.isfinite(self.points[..., 2])


def surface_view(surface: SurfaceMesh, camera: Intrinsics) -> SurfaceView:
    """Cast every camera pixel's ray against the surface (Mitsuba's BVH)."""

    mi = mitsuba()
    w, h = camera.size
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    d = camera.rays(np.stack([xs.ravel(), ys.ravel()], axis=1))
    scene = mi.load_dict({"type": "scene", "surface": surface_mesh(mi, surface)})
    unit = d / np.linalg.norm(d, axis=1, keepdims=True)
    ray = mi.Ray3f(mi.Point3f(0.0, 0.0, 0.0), mi.Vector3f(*(unit.T.astype(np.float32))))
    si = scene.ray_intersect(ray)
    ok = np.array(si.is_valid(), dtype=bool)
    t = np.where(ok, np.array(si.t, dtype=np.float64), np.nan)
    n = np.stack([np.array(c, dtype=np.float64) for c in (si.n.x, si.n.y, si.n.z)], axis=1)
    n = np.where((np.sum(n * unit, axis=1) > 0)[:, None], -n, n)  # face the camera
    pts = unit * t[:, None]
    n[~ok] = np.nan
    return SurfaceView(pts.reshape(h, w, 3), n.reshape(h, w, 3), camera)


def full_white_irradiance(view: SurfaceView, projector: Projector, pose: np.ndarray) -> np.ndarray:
    """Radiance (albedo 1) a fully white texel gives each camera pixel's surface point: ``E_ref`` of the module doc.

    Zero where the point is behind the projector or the light reaches the side the camera does not see.
    """
    c = pose[:3, 3]
    r = pose[:3, :3]
    d = view.points - c  # projector → point, rig frame
    z = d @ r[:, 2]
    dist = np.linalg.norm(d, axis=-1)
    cos_s = -np.sum(view.normals * d, axis=-1) / np.maximum(dist, 1e-12)  # normals face the camera
    with np.errstate(invalid="ignore", divide="ignore"):
        e = projector.intensity * cos_s / (z * z * (z / dist))
    ok = np.isfinite(e) & (z > 1e-6) & (cos_s > 0)
    return np.where(ok, e, 0.0).astype(np.float32)


# ------------------------------------------------------------------ Gray code + PnP

def graycode_correspondences(captures: CaptureSet, view: SurfaceView, mask: np.ndarray, *, max_points: int = 40000,
                             seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Decoded Gray code lifted to 3-D by the surface: N×3 rig-frame points, N×2 projector pixels (OpenCV's pixel
    centres), the N×2 camera pixels they were decoded at (centres, corner convention), and how many camera pixels
    decoded on the surface (before picking at most ``max_points``)."""
    entries = captures.entries_of("graycode")
    if not entries:
        raise CalibrationError(f"capture set {captures.path} holds no Gray-code captures, so init='graycode' "
                               "cannot find a starting pose; use --init nominal (or blender), or capture Gray code")
    try:
        dec = decode_gray_code_set(captures)
    except CaptureError as exc:
        raise CalibrationError(f"cannot decode the Gray-code captures of {captures.path}: {exc}") from None
    use = dec.valid & view.hit & mask
    n_use = int(use.sum())
    if n_use < MIN_CORRESPONDENCES:
        raise CalibrationError(
            f"the Gray-code captures of {captures.path} ({entries[0].file} …) decode to only {n_use} camera pixels "
            f"on the surface (need {MIN_CORRESPONDENCES}); were they captured with the projector on and the "
            "camera still? Use --init nominal, or capture Gray code again")
    obj = view.points[use]
    img = dec.coords[use].astype(np.float64) - 0.5  # corner convention → OpenCV's pixel centres
    rows, cols = np.nonzero(use)
    cam = np.stack([cols, rows], axis=1).astype(np.float64) + 0.5
    if len(obj) > max_points:
        pick = np.random.default_rng(seed).choice(len(obj), max_points, replace=False)
        obj, img, cam = obj[pick], img[pick], cam[pick]
    return obj, img, cam, n_use


#: Points whose thinnest extent is below this share of their widest are a plane to PnP (a wall, a flat screen).
PLANAR_SHARE = 0.02


def pnp_ransac(obj: np.ndarray, img: np.ndarray, k: np.ndarray, thresh: float, seed: int
               ) -> tuple[bool, np.ndarray, np.ndarray, np.ndarray | None]:
    """``solvePnPRansac`` with EPnP, and on (near-)planar points also with IPPE; each answer refined by
    Levenberg–Marquardt on its inliers, and the one that then agrees with more points kept.

    EPnP alone fails on a flat wall: on a planar live capture its RANSAC pose
    had every point within 1 px, yet refining it settled on the mirror-image
    pose of the planar PnP ambiguity, which only 2 % of the points agree with.
    IPPE, made for planes, starts from the right one of the two."""
    spread = np.linalg.svd(obj - obj.mean(axis=0), compute_uv=False)
    flags = [cv2.SOLVEPNP_EPNP] + ([cv2.SOLVEPNP_IPPE] if spread[2] < PLANAR_SHARE * spread[0] else [])
    best: tuple[bool, np.ndarray, np.ndarray, np.ndarray | None] = (False, np.zeros(3), np.zeros(3), None)
    for flag in flags:
        cv2.setRNGSeed(int(seed))
        try:
            ok, rvec, tvec, inliers = cv2.solvePnPRansac(obj, img, k, None, iterationsCount=200,
                                                         reprojectionError=thresh, confidence=0.999, flags=flag)
        except cv2.error:
            continue
        if not ok or inliers is None or len(inliers) < 6:
            continue
        rvec, tvec = cv2.solvePnPRefineLM(obj[inliers.ravel()], img[inliers.ravel()], k, None, rvec, tvec)
        resid = np.linalg.norm(cv2.projectPoints(obj, rvec, tvec, k, None)[0].reshape(-1, 2) - img, axis=1)
        inliers = np.flatnonzero(resid < thresh).reshape(-1, 1)
        if best[3] is None or len(inliers) > len(best[3]):
            best = (True, rvec, tvec, inliers)
    return best


def graycode_pnp(captures: CaptureSet, view: SurfaceView, mask: np.ndarray, *, max_points: int = 40000,
                 seed: int = 0) -> tuple[np.ndarray, dict[str, Any]]:
    """Pose from decoded Gray-code correspondences lifted to 3-D by the surface (PnP with the projector's K)."""
    obj, img, _, n_use = graycode_correspondences(captures, view, mask, max_points=max_points, seed=seed)
    proj = captures.projector
    k = proj.intrinsics.opencv_matrix()
    # A projector pixel covers ~1/800 of the frame; Gray code is exact to ±0.5 px, the 3-D points to ~mm.
    thresh = max(1.0, 2.0 * proj.intrinsics.width / 800.0)
    ok, rvec, tvec, inliers = pnp_ransac(obj, img, k, thresh, seed)
    if not ok or inliers is None or len(inliers) < MIN_CORRESPONDENCES:
        raise CalibrationError(f"PnP on the Gray-code correspondences of {captures.path} found no consistent "
                               "projector pose; check the Gray-code captures and the surface, or use --init nominal")
    idx = inliers.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img[idx], k, None, rvec, tvec)
    # A second pass with the refined pose: re-select inliers, refine again.
    proj_pts, _ = cv2.projectPoints(obj, rvec, tvec, k, None)
    resid = np.linalg.norm(proj_pts.reshape(-1, 2) - img, axis=1)
    idx = np.flatnonzero(resid < thresh)
    rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img[idx], k, None, rvec, tvec)
    proj_pts, _ = cv2.projectPoints(obj[idx], rvec, tvec, k, None)
    rms = float(np.sqrt(np.mean(np.sum((proj_pts.reshape(-1, 2) - img[idx]) ** 2, axis=1))))
    rot, _ = cv2.Rodrigues(rvec)
    p_from_c = np.eye(4)
    p_from_c[:3, :3], p_from_c[:3, 3] = rot, tvec.ravel()
    pose = np.linalg.inv(p_from_c)
    pose[3] = (0.0, 0.0, 0.0, 1.0)
    return pose, {"decoded_pixels": n_use, "points": int(len(obj)), "inliers": int(len(idx)),
                  "reprojection_rms_px": rms}


# ------------------------------------------------------------------ mask refinement (the paper's stage A)

@dataclass(frozen=True)
class Phase:
    """One phase of the mask refinement: camera resolution, smoothing, and an exponentially decaying step."""

    name: str
    iterations: int
    camera_width: int | None  # camera width rendered (same lens, proportional height); None = full resolution
    eps: float  # border smoothing ε of the white area
    lr_start: float  # Adam step, in units of ~1 cm of footprint motion
    lr_end: float


def paper_phases(iterations: int = 200) -> list[Phase]:
    """The paper's stage A: one phase at full resolution with Γ at ε = 0.01 and an exponentially decaying step."""
    return [Phase("paper", iterations, None, PAPER_EPS, 1.0, 0.05)]


def default_phases(iterations: int, rough: bool) -> list[Phase]:
    """The schedule: a coarse phase with the paper's Γ (only from a rough start), then a sharp full-resolution one."""
    if iterations <= 0:
        return []
    if not rough:
        return [Phase("mask_fine", iterations, None, 0.0, 0.1, 0.01)]
    n_coarse = max(1, int(round(0.6 * iterations)))
    return [Phase("mask_coarse", n_coarse, COARSE_WIDTH, PAPER_EPS, 1.0, 0.1),
            Phase("mask_fine", max(0, iterations - n_coarse), None, 0.0, 0.15, 0.01)]


class _Adam:
    """Adam on a small numpy vector (the re-linearised pose delta); state survives the re-linearisation."""

    def __init__(self, n: int, beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-8) -> None:
        self.m = np.zeros(n)
        self.v = np.zeros(n)
        self.t = 0
        self.b1, self.b2, self.eps = beta1, beta2, eps

    def step(self, grad: np.ndarray, lr: float) -> np.ndarray:
        self.t += 1
        self.m = self.b1 * self.m + (1 - self.b1) * grad
        self.v = self.b2 * self.v + (1 - self.b2) * grad * grad
        mhat = self.m / (1 - self.b1 ** self.t)
        vhat = self.v / (1 - self.b2 ** self.t)
        return -lr * mhat / (np.sqrt(vhat) + self.eps)


def _resize_mask(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Area-average a (binary or soft) mask to another camera resolution: the coverage of each coarse pixel."""
    m = mask.astype(np.float32)
    if (m.shape[1], m.shape[0]) == tuple(size):
        return m
    return cv2.resize(m, size, interpolation=cv2.INTER_AREA)


def _check_pose(pose: np.ndarray, start: np.ndarray, scene_depth: float, where: str) -> None:
    if not np.all(np.isfinite(pose)):
        raise CalibrationError(f"stage A diverged ({where}): the projector pose became NaN; check the white "
                               "capture and the starting pose")
    moved = float(np.linalg.norm(pose[:3, 3] - start[:3, 3]))
    if moved > max(1.0, 0.5 * scene_depth):
        raise CalibrationError(f"stage A diverged ({where}): the projector moved {moved:.2f} m from its start, "
                               "out of any plausible bound; start closer (--init graycode, or place the projector "
                               "in Blender) and check that the white capture shows the projector's footprint")


def _soft_render(model: Any, frame_t: Any, view: SurfaceView, projector: Projector, base: np.ndarray,
                 delta: np.ndarray, seed: int) -> np.ndarray:
    """The soft rendered mask (numpy, no gradient) at ``base`` moved by ``delta``: render ÷ E_ref, clipped at 1."""

    mi = mitsuba()
    import drjit as dr

    with dr.suspend_grad():
        img = np.array(model.render_dr(frame_t, mi.Float(np.asarray(delta, np.float32)), seed=seed),
                       dtype=np.float64)[..., 0]
    eref = full_white_irradiance(view, projector, apply_pose_delta(base, delta))
    return np.minimum(np.where(eref > 0, img / np.maximum(eref, 1e-12), 0.0), 1.0)


def _frame_tensor(frame: np.ndarray) -> Any:

    return mitsuba().TensorXf(np.repeat(frame[..., None], 3, axis=2))


def _soft_render_at(captures: CaptureSet, surface: SurfaceMesh, pose: np.ndarray, view: SurfaceView, *, seed: int,
                    spp: int = 16) -> np.ndarray:
    """The soft rendered mask at full camera resolution with sharp edges (ε = 0): the final check's image
    (``view``: :func:`surface_view` of the surface at that resolution)."""

    proj = captures.projector
    white_surface = replace(surface, albedo=np.ones((2, 2, 3), np.float32))
    model = ForwardModel(Rig(captures.camera, proj.with_pose(pose)), white_surface, bounces=0, spp=spp,
                         smoothing_eps=0.0, clamp=False, seed=seed)
    frame_t = _frame_tensor(white_frame(captures, proj, 0.0))
    return _soft_render(model, frame_t, view, proj, pose, np.zeros(6), seed).astype(np.float32)


def _whitening(model: Any, frame_t: Any, view: SurfaceView, projector: Projector, base: np.ndarray,
               delta: np.ndarray, units: np.ndarray, *, seed: int, h: float = 0.3,
               floor: float = 1e-2) -> np.ndarray:
    """A 6×6 change of variables that makes the mask loss round near the current pose (Gauss–Newton metric).

    The mask pins the footprint's place and size firmly, but a sideways shift
    and the turn that keeps the footprint where it is change the outline only
    through perspective — a valley a hundred times flatter than its walls.
    Adam scales each coordinate on its own and crawls along such a diagonal
    valley. With ``J`` the Jacobian of the soft mask in the ``units``
    coordinates (central differences of plain renders, ``h`` units apart, one
    seed for all so that their noise cancels), ``JᵀJ`` is the loss's
    curvature; Adam then runs in coordinates ``y`` with ``δ = units · W · y``,
    ``W = (JᵀJ)^{-1/2}`` scaled to the mean curvature, where the valley is
    round. Directions flatter than ``floor`` × the steepest are amplified no
    further (10× at most): they carry mostly noise.
    """
    cols = []
    for i in range(6):
        e = units[:, i] * h
        plus = _soft_render(model, frame_t, view, projector, base, delta + e, seed)
        minus = _soft_render(model, frame_t, view, projector, base, delta - e, seed)
        cols.append(((plus - minus) / (2 * h)).ravel())
    jac = np.stack(cols, axis=1)
    vals, vecs = np.linalg.eigh(jac.T @ jac)
    if not np.all(np.isfinite(vals)) or vals[-1] <= 0:
        return np.eye(6)
    vals = np.maximum(vals, floor * vals[-1])
    return vecs @ np.diag(np.sqrt(float(np.mean(vals)) / vals)) @ vecs.T


def refine_pose_mask(captures: CaptureSet, surface: SurfaceMesh, pose: np.ndarray, target: np.ndarray,
                     phases: list[Phase], *, spp: int = 4, seed: int = 0, progress: Progress | None = None,
                     progress_span: tuple[float, float] = (0.0, 1.0), cancel: Cancel | None = None,
                     steps: dict[str, np.ndarray] | None = None, losses: list[float] | None = None,
                     info: dict[str, Any] | None = None, precondition: bool = True) -> np.ndarray:
    """Adam on the pose delta against the target mask through the differentiable render, phase by phase.

    ``target`` is the camera-resolution mask (binary or soft). Within a phase
    the forward model keeps the phase's starting pose and the optimised delta
    stays a Dr.Jit input: folding each step into the pose would bake new
    constants into the kernels and recompile them every step (3× slower,
    measured). Returns the final pose; ``steps``, ``losses`` and ``info`` (if
    given) collect each phase's result, every loss, and each phase's seconds
    and camera size.
    """

    mi = mitsuba()
    import drjit as dr

    proj = captures.projector
    cam = captures.camera.intrinsics
    white_surface = replace(surface, albedo=np.ones((2, 2, 3), np.float32))
    steps = {} if steps is None else steps
    losses = [] if losses is None else losses
    info = {} if info is None else info
    start = pose.copy()
    total = sum(p.iterations for p in phases) or 1
    done = 0
    white_name = captures.entry("white").file
    for phase in phases:
        if phase.iterations <= 0:
            continue
        t_phase = time.perf_counter()
        width = min(cam.width, phase.camera_width or cam.width)
        size = (int(width), max(8, round(cam.height * width / cam.width)))
        view = surface_view(surface, cam.scaled(*size))
        tgt = _resize_mask(target, size)
        target_t = mi.TensorXf(np.repeat(tgt[..., None], 3, axis=2))
        target_sum = float(tgt.sum())
        base = pose.copy()
        model = ForwardModel(Rig(captures.camera, proj.with_pose(base)), white_surface, camera_size=size,
                             bounces=0, spp=spp, smoothing_eps=0.0, clamp=False, seed=seed)
        frame_t = _frame_tensor(white_frame(captures, proj, phase.eps))
        # Units of the optimised vector: 1 cm of translation, and the turn that moves the footprint 1 cm.
        lit = view.hit & (tgt > 0.5)
        depth = float(np.median(np.linalg.norm(view.points[lit] - base[:3, 3], axis=1))) if lit.any() else 2.0
        scale = np.diag([0.01] * 3 + [0.01 / depth] * 3)
        units = scale
        adam = _Adam(6)
        delta = np.zeros(6)
        for it in range(phase.iterations):
            if cancel is not None and cancel():
                raise Cancelled("stage A (projector pose) was cancelled")
            eref = full_white_irradiance(view, proj, pose)
            inv = np.where(eref > 0, 1.0 / np.maximum(eref, 1e-12), 0.0).astype(np.float32)
            inv_t = mi.TensorXf(np.repeat(inv[..., None], 3, axis=2))
            delta_dr = mi.Float(delta.astype(np.float32))
            dr.enable_grad(delta_dr)
            s = seed * 1_000_003 + 2 * (done + it) + 1
            img = model.render_dr(frame_t, delta_dr, seed=s, seed_grad=s + 1)
            soft = dr.minimum(img * inv_t, 1.0)
            loss = dr.mean(dr.square(soft - target_t), axis=None)
            covered = dr.sum(soft, axis=None)
            dr.backward(loss)
            grad = np.array(dr.grad(delta_dr), dtype=np.float64)
            value = float(np.array(loss).ravel()[0])
            footprint = float(np.array(covered).ravel()[0]) / 3.0
            if not (np.all(np.isfinite(grad)) and math.isfinite(value)):
                raise CalibrationError(f"stage A diverged ({phase.name}, iteration {it}): the loss or its gradient "
                                       f"became NaN; check the white capture {white_name} and the starting pose")
            if footprint < 0.05 * target_sum:
                raise CalibrationError(
                    f"stage A diverged ({phase.name}, iteration {it}): the simulated footprint left the camera "
                    f"image (it covers {footprint / max(target_sum, 1):.0%} of the mask from {white_name}); "
                    "start closer (--init graycode) or check the white capture")
            losses.append(value)
            if precondition and it % REFRESH == 0:
                # The valley turns as the pose moves: refresh the metric now and then (and restart Adam's moments,
                # which live in the old coordinates).
                units = scale @ _whitening(model, frame_t, view, proj, base, delta, scale,
                                           seed=seed * 1_000_003 + 2 * (done + it))
                adam = _Adam(6)
            frac = (it + 1) / phase.iterations
            lr = phase.lr_start * (phase.lr_end / phase.lr_start) ** frac
            delta = delta + units @ adam.step(units.T @ grad, lr)
            pose = apply_pose_delta(base, delta)
            _check_pose(pose, start, depth, phase.name)
            if progress is not None:
                a, b = progress_span
                progress(f"stage A: {phase.name} {it + 1}/{phase.iterations}, loss {value:.5f}",
                         a + (b - a) * (done + it + 1) / total)
        done += phase.iterations
        steps[phase.name] = pose.copy()
        info[f"{phase.name}_seconds"] = time.perf_counter() - t_phase
        info[f"{phase.name}_camera_size"] = list(size)
    return pose


# ------------------------------------------------------------------ the stage

def estimate_pose(captures: CaptureSet, surface: SurfaceMesh, *, init: str = "graycode",
                  initial_pose: np.ndarray | None = None, iterations: int | None = None,
                  progress: Progress | None = None, cancel: Cancel | None = None,
                  seed: int = 0, spp: int = 4, phases: list[Phase] | None = None,
                  target: str | None = None, precondition: bool | None = None,
                  method: str = "ours") -> PoseResult:
    """Stage A: the projector's ``camera_from_projector`` from a capture set and the reconstructed surface.

    ``init`` picks the start: ``'graycode'`` (PnP on decoded Gray-code
    correspondences), ``'nominal'`` (the capture set's projector pose),
    ``'blender'``/``'given'`` (``initial_pose``, e.g. the projector object an
    artist placed). A nominal pose the capture set marks as known (imported
    with a metric rig calibration) is kept like a Gray-code one. ``iterations`` is the number of Adam steps on the mask:
    by default 0 after Gray code (the mask then only checks the pose, see the
    module doc for why) and 200 from a rough start (120 coarse + 80 fine).
    ``phases`` overrides the schedule, ``target`` picks the debiased soft
    target (default) or the paper's binary mask, ``precondition`` the
    Gauss–Newton change of variables (default: on from a rough start).
    ``method='paper'`` sets all three as the paper does (:func:`paper_phases`,
    the binary mask, no preconditioning), from whichever start ``init`` gives.
    Every result ends with a check: the footprint rendered at full resolution
    at the final pose against the mask (``info['mask_check']``: loss and
    intersection over union; below 50 % overlap is an error).

    ``progress(message, fraction)`` is called as it goes; ``cancel()``
    returning True stops it with :class:`Cancelled`. Bad captures, a start
    that loses the footprint, and divergence raise :class:`CalibrationError`.
    """
    t0 = time.perf_counter()
    if init not in INITS:
        raise CalibrationError(f"unknown stage-A start {init!r}; choose one of {', '.join(INITS)}")
    if method not in METHODS:
        raise CalibrationError(f"unknown stage-A method {method!r}; choose one of {', '.join(METHODS)}")
    if method == "paper":
        if phases is None:
            phases = paper_phases(DEFAULT_ITERATIONS if iterations is None else int(iterations))
        target = target or "binary"
        precondition = False if precondition is None else precondition
    target = target or "soft"
    if target not in ("soft", "binary"):
        raise CalibrationError(f"unknown stage-A target {target!r}; choose 'soft' (debiased) or 'binary' (the paper's)")
    report = progress or (lambda message, fraction: None)
    mask, diff = target_mask(captures)
    soft = soft_target(mask, diff)
    steps: dict[str, np.ndarray] = {}
    info: dict[str, Any] = {"mask_fraction": float(mask.mean()), "method": method}
    cam = captures.camera.intrinsics
    known = init == "nominal" and captures.projector_pose_known
    view = surface_view(surface, cam)  # for the Gray code's PnP and the final check alike
    if init == "graycode":
        report("stage A: decoding Gray code and solving PnP", 0.0)
        steps["initial"] = captures.projector.camera_from_projector.copy()
        pose, pnp = graycode_pnp(captures, view, mask, seed=seed)
        info["pnp"] = pnp
        steps["graycode_pnp"] = pose.copy()
    elif init == "nominal":
        pose = captures.projector.camera_from_projector.copy()
        info["pose_known"] = known
        steps["initial"] = pose.copy()
    else:
        if initial_pose is None:
            raise CalibrationError(f"init={init!r} needs the starting pose (the projector object's pose in the rig "
                                   "frame); pass initial_pose, or use --init graycode or nominal")
        try:
            pose = captures.projector.with_pose(np.asarray(initial_pose, dtype=np.float64)).camera_from_projector
        except ProCamError as exc:
            raise CalibrationError(f"the starting pose is not usable: {exc}") from None
        steps["initial"] = pose.copy()
    if cancel is not None and cancel():
        raise Cancelled("stage A (projector pose) was cancelled")
    if iterations is None:
        # After Gray code the mask is a check, not a refinement: measured on lab data, PnP is 2–4 mm off and the
        # mask's own optimum 10–13 mm (module doc), so refining on it only pulls the pose away.
        # A pose from a rig calibration (a printed board, sub-pixel corners) is kept the same way.
        iterations = 0 if init == "graycode" or known else DEFAULT_ITERATIONS
    rough = not (init == "graycode" or known)
    if phases is None:
        phases = default_phases(int(iterations), rough=rough)
    if precondition is None:
        precondition = rough
    losses: list[float] = []
    if phases:
        pose = refine_pose_mask(captures, surface, pose, soft if target == "soft" else mask, phases, spp=spp,
                                seed=seed, progress=report, progress_span=(0.05, 0.95), cancel=cancel,
                                steps=steps, losses=losses, info=info, precondition=precondition)
    report("stage A: rendering the footprint at the final pose", 0.98)
    rendered = _soft_render_at(captures, surface, pose, view, seed=seed)
    inter = float(np.sum(mask & (rendered > 0.5)))
    union = float(np.sum(mask | (rendered > 0.5)))
    iou = inter / max(union, 1.0)
    info["mask_check"] = {"loss": float(np.mean((rendered - soft) ** 2)), "iou": iou}
    if iou < MIN_IOU:
        raise CalibrationError(
            f"stage A did not find the projector: at the {'PnP' if init == 'graycode' and not phases else 'final'} "
            f"pose the simulated footprint overlaps the mask from the white capture {captures.entry('white').file} "
            f"by only {100 * iou:.0f} % (intersection over union); check the projector's intrinsics (throw ratio, "
            "lens shift) and the starting pose, or capture Gray code and use --init graycode")
    diagnostics = {"mask": mask.astype(np.float32), "soft_target": soft, "rendered_mask": rendered}
    report("stage A: done", 1.0)
    return PoseResult(pose, init, steps, losses, time.perf_counter() - t0, diagnostics, info, view, mask)
