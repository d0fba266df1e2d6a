"""Evidence for the effects calibration absorbs, read from the calibration's own inputs.

Some of the lab's effects leave almost no residual on the validation patterns,
because a calibration step absorbs them, so the held-out selection of
:mod:`.fit` cannot see them. A user still needs to know they are there: what a
calibration absorbed is only right for this rig, and comes back as soon as the
projector, the surface or the camera changes. Each is found where it was
absorbed:

* ``vignetting`` (the white-capture albedo holds it): the surface photo is taken
  with the room lights on, so ``(white − black) / projector irradiance`` over
  ``photo / room-light irradiance`` (the ambient occlusion of the calibrated
  surface) is the projector's own falloff, paint cancelling out. It is fitted
  as ``1 − falloff·(r/r_max)²`` about the projector's principal point, ``r``
  the field-angle tangent, like the lab's and the model's ``vignetting``. The
  ratio needs linear light: a camera curve the residual found is inverted
  first, and a glossy lobe it found is taken out of the white capture (both
  otherwise vary with brightness, which falls off from the projector's axis
  too).
* ``glossy`` below the sensor's clipping (the white-capture albedo holds it, for
  this camera position): in the same ratio, a GGX lobe rendered from the
  calibrated geometry, fitted beside the falloff (the two look alike on a
  surface facing the projector, see :func:`vignetting_evidence`).
* ``distortion`` (the pose and the stage-B warp hold it): the Gray-code
  correspondences, lifted to 3-D by the calibrated surface, are fitted by the
  projector pose alone, by the pose plus the camera's radial ``k1, k2``, and
  with the tangential ``p1, p2`` too (a decentred lens, which the radial law
  fits only in part: ``model_share`` says how much).
* ``depth_noise`` (the wall image removes the bias, the reconstruction smooths
  the noise): read off the depth sensor's image of a flat wall, as the median
  offset and the spread about a fitted plane; without a wall image, the spread
  of the scene depth's second differences (a plane's are zero).

Fits use half of the pixels (alternate square blocks) and are scored on the
other half, as effect models are scored on held-out patterns. The thresholds
below were checked on the diagnosis benchmark's sets without the effect (see
docs/results.md, "Diagnosis").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..capture.format import CaptureSet
from ..capture.patterns import decode_gray_code_set
from ..errors import Cancelled, CaptureError, ProCamError, SurfaceError
from ..progress import Cancel
from ..render.backend import mitsuba
from ..render.scene import surface_mesh
from ..rig.lens import undistort_normalised
from ..stages.calibrate import Calibration, SATURATED
from ..stages.pose import full_white_irradiance, surface_view, target_mask
from ..surface.reconstruct import wall_depth_offset

#: Vignetting is found when the fitted falloff at the farthest frame corner reaches this share of the light …
VIGNETTING_MIN_FALLOFF = 0.05
#: … and the radial law removes this share of the held-out spread of the albedo ratio.
VIGNETTING_MIN_SHARE = 0.10
#: A highlight is found when the fitted lobe brightens the white capture by this share at its peak (99th
#: percentile) … (the lab's lobe at 0.25, weight 0.05: 18–24 %; fits on the benchmark's sets without a lobe: < 1 %)
GLOSSY_MIN_PEAK = 0.05
#: … and removes this share of the held-out spread of the albedo ratio that the radial falloff leaves.
GLOSSY_MIN_SHARE = 0.10
#: A surface photo darker than this (median over the lit pixels, linear) was taken without room light.
MIN_PHOTO_LEVEL = 0.01
#: Distortion is found when k1, k2 remove this share of the held-out Gray-code reprojection MSE (whose floor is the
#: code's own ±0.5 px quantisation); on the diagnosis benchmark's 42 sets without it, fits removed at most 0.12 %.
DISTORTION_MIN_SHARE = 0.005
#: Depth bias or noise (1σ at 1 m) the diagnosis reports as ``depth_noise``: a tenth of a phone LiDAR's.
DEPTH_MIN_M = 0.002
#: Pixels a fit uses at most (a fixed random subset of the usable ones).
MAX_PIXELS = 20000
#: Cosine-weighted directions for the room light's ambient occlusion.
AO_DIRECTIONS = 128

Light = Callable[[np.ndarray], np.ndarray]


@dataclass
class Evidence:
    """What the calibration's inputs say about one absorbed effect."""

    name: str
    detected: bool
    params: dict[str, float] = field(default_factory=dict)
    share: float = 0.0  # held-out share of the spread the effect's law removes (vignetting, distortion)
    evidence: str = ""  # in words, with the numbers
    absorbed_by: str = ""
    error: str | None = None  # why it could not be measured
    #: share of ``share`` the diagnosis's own law of the effect reaches (distortion: radial k1, k2 of the lens)
    model_share: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"detected": self.detected, "params": self.params, "heldout_share": round(self.share, 4),
                "evidence": self.evidence, "absorbed_by": self.absorbed_by, "error": self.error,
                "model_share": None if self.model_share is None else round(self.model_share, 3)}


def _blocks(xs: np.ndarray, ys: np.ndarray, width: int) -> np.ndarray:
    """True on the fit half: alternate square blocks, about 1/16 of the image wide."""
    b = max(8, width // 16)
    return ((xs // b) + (ys // b)) % 2 == 0


def _subset(n: int, seed: int = 0) -> np.ndarray:
    idx = np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(idx, MAX_PIXELS, replace=False)) if n > MAX_PIXELS else idx


# ------------------------------------------------------------------ vignetting

def ambient_occlusion(surface: Any, points: np.ndarray, normals: np.ndarray, *, directions: int = AO_DIRECTIONS,
                      seed: int = 0) -> np.ndarray:
    """Share of an even room light each surface point receives (cosine-weighted visibility of the sky)."""

    mi = mitsuba()
    scene = mi.load_dict({"type": "scene", "surface": surface_mesh(mi, surface)})
    rng = np.random.default_rng(seed)
    u1, u2 = rng.random(directions), rng.random(directions)
    local = np.stack([np.sqrt(u1) * np.cos(2 * np.pi * u2), np.sqrt(u1) * np.sin(2 * np.pi * u2), np.sqrt(1 - u1)], 1)
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    # Each point turns the direction set by its own random angle about its normal. With one set for all, every
    # point of a plane shares the same few directions, and the set's luck becomes that plane's error (measured on
    # the lab's hedge: its two planes' occlusion 6 % apart with 128 shared directions, equal with 1024, which read
    # as an 11 % projector falloff); turned per point, the errors differ from point to point and average out.
    turn = rng.random(len(points))[:, None] * 2 * np.pi
    c, s = np.cos(turn), np.sin(turn)
    origin = mi.Point3f(*((points + n * 1e-3).T.astype(np.float32)))
    seen = np.zeros(len(points))
    for d in local:
        dirs = t1 * (c * d[0] - s * d[1]) + t2 * (s * d[0] + c * d[1]) + n * d[2]
        seen += ~np.array(scene.ray_test(mi.Ray3f(origin, mi.Vector3f(*(dirs.T.astype(np.float32))))), dtype=bool)
    return seen / directions


def _tukey_fit(a: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Robust least squares y ≈ a·coef (iteratively reweighted, Tukey's biweight): paint edges are outliers."""
    w = np.ones_like(y)
    coef = np.zeros(a.shape[1])
    for _ in range(15):
        coef = np.linalg.lstsq(a * w[:, None], y * w, rcond=None)[0]
        r = y - a @ coef
        scale = 1.4826 * np.median(np.abs(r)) + 1e-9
        u = r / (4.685 * scale)
        w = np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)
    return coef


def vignetting_evidence(captures: Any, cal: Any, view: Any, mask: np.ndarray, *, light: Light | None = None,
                        white_extra: np.ndarray | None = None,
                        lobes: dict[float, np.ndarray] | None = None) -> tuple[Evidence, Evidence]:
    """Evidence for ``vignetting`` and for ``glossy``, both read from the albedo ratio.

    ``light`` takes captured values back to linear light (a fitted camera curve); ``white_extra`` is light the
    diagnosis's models put in the white capture besides the projector's diffuse light (a glossy lobe);
    ``lobes``: white GGX lobe renders at unit weight by roughness (camera size, from the calibrated geometry).

    A highlight peaks where the mirror direction meets the camera, near the projector's axis on a surface facing
    both, so a radial falloff fitted alone takes it for vignetting (the lab's lobe at weight 0.05 read as a 16–20 %
    falloff on the curve and the plane). Its share of the white light is a second, free regressor, at the
    roughness that fits best, so that only the falloff it cannot explain counts; and a lobe that brightens its
    peak by ≥ :data:`GLOSSY_MIN_PEAK` and explains ≥ :data:`GLOSSY_MIN_SHARE` of what the falloff leaves is a
    highlight the albedo absorbed. With ``white_extra`` (a lobe the residual found) what is left of it after its
    fitted weight is the regressor.
    """

    ev = Evidence("vignetting", False, absorbed_by="the albedo estimated from the white capture")
    gl = Evidence("glossy", False, absorbed_by="the albedo estimated from the white capture (for this camera "
                  "position only: a highlight moves with the viewpoint)")
    if not captures.entries_of("surface"):
        ev.error = gl.error = "no photo of the surface (projector off, room lights on) in the capture set"
        return ev, gl
    proj = cal.rig.projector
    raw_white = captures.image("white")
    linear = light or (lambda img: img)
    white, black, photo = linear(raw_white), linear(captures.image("black")), linear(captures.image("surface"))
    size = (white.shape[1], white.shape[0])
    if white_extra is not None:
        white = white - cv2.resize(white_extra, size, interpolation=cv2.INTER_LINEAR)
    irradiance = full_white_irradiance(view, proj, proj.camera_from_projector)
    # Both images are smoothed a little: the photo is dim, and the ratio need not be sharp.
    lit_light = cv2.GaussianBlur(white - black, (0, 0), 1.5).mean(axis=2)
    room = cv2.GaussianBlur(photo, (0, 0), 1.5).mean(axis=2)
    ok = mask & view.hit & (irradiance > 0) & (raw_white.max(axis=2) < SATURATED)  # clipped white holds no ratio
    ok = cv2.erode(ok.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    if ok.sum() < 500:
        ev.error = gl.error = "too few lit surface pixels below saturation"
        return ev, gl
    level = float(np.median(room[ok]))
    if level < MIN_PHOTO_LEVEL:
        ev.error = gl.error = (f"the surface photo is dark (median {level:.3f} where the projector lights the "
                               "surface): take it with the room lights on, so that paint can be told from projector "
                               "falloff")
        return ev, gl
    ok &= (room > 0.1 * level) & (lit_light > 0)
    ys, xs = np.nonzero(ok)
    pick = _subset(len(xs))
    ys, xs = ys[pick], xs[pick]
    pts, nrm = view.points[ys, xs], view.normals[ys, xs]
    ao = ambient_occlusion(cal.surface, pts, nrm)
    good = ao > 0.05
    ys, xs, pts, ao = ys[good], xs[good], pts[good], ao[good]
    if len(xs) < 500:
        ev.error = gl.error = "too few surface pixels lit by both the projector and the room"
        return ev, gl
    # log of (projector light / model irradiance) over (room light / occlusion): the paint cancels.
    y = np.log(lit_light[ys, xs] / irradiance[ys, xs]) - np.log(room[ys, xs] / ao)
    one, s = np.ones(len(xs)), _radius_share(proj, pts)
    shapes = {None: white_extra} if white_extra is not None else dict(lobes or {})
    regressors = {r: cv2.resize(img, size, interpolation=cv2.INTER_LINEAR).mean(axis=2)[ys, xs] / lit_light[ys, xs]
                  for r, img in shapes.items()}
    fit = _blocks(xs, ys, captures.camera.intrinsics.width)
    held = ~fit

    def spread(columns: list[np.ndarray]) -> tuple[float, np.ndarray]:
        """Held-out spread (median absolute deviation) of the ratio after a robust fit on the other half."""
        a = np.stack(columns, axis=1)
        coef = _tukey_fit(a[fit], y[fit])
        r = y[held] - a[held] @ coef
        return float(np.median(np.abs(r - np.median(r)))), coef

    flat, _ = spread([one])
    radial, radial_coef = spread([one, s])
    # the lobe's roughness: the one that fits best together with the falloff
    best = min(((spread([one, lobe, s]), r) for r, lobe in regressors.items()), key=lambda v: v[0][0], default=None)
    if best is None:
        both, coef, without = radial, radial_coef, flat
    else:
        (both, coef), rough = best
        without, _ = spread([one, regressors[rough]])
        peak = float(coef[1] * np.percentile(regressors[rough], 99))
        gl.share = 1.0 - (both / radial) ** 2 if radial > 0 else 0.0
        gl.params = {"peak": round(peak, 4)} if rough is None else \
            {"weight": round(float(coef[1]), 4), "roughness": round(float(rough), 2), "peak": round(peak, 4)}
        gl.detected = bool(white_extra is None and peak >= GLOSSY_MIN_PEAK and gl.share >= GLOSSY_MIN_SHARE)
        gl.evidence = (f"a projector highlight (GGX lobe at roughness {rough:.2f} from the calibrated geometry) "
                       if rough is not None else "what is left of the fitted highlight ") + \
            (f"brightens the white capture by {peak:.1%} at its peak and removes {gl.share:.0%} of the held-out "
             f"spread the radial falloff leaves (found at ≥ {GLOSSY_MIN_PEAK:.0%} and ≥ {GLOSSY_MIN_SHARE:.0%})")
    ev.share = 1.0 - (both / without) ** 2 if without > 0 else 0.0
    falloff = float(1.0 - np.exp(coef[-1]))
    ev.params = {"falloff": round(falloff, 4), "exponent": 2.0}
    ev.detected = bool(falloff >= VIGNETTING_MIN_FALLOFF and ev.share >= VIGNETTING_MIN_SHARE)
    ev.evidence = (f"projector light over room light (paint cancels) falls by {falloff:.1%} towards the farthest frame "
                   f"corner; the radial law removes {ev.share:.0%} of its held-out spread "
                   f"(found at ≥ {VIGNETTING_MIN_FALLOFF:.0%} and ≥ {VIGNETTING_MIN_SHARE:.0%})")
    return ev, gl


def _radius_share(proj: Any, points: np.ndarray) -> np.ndarray:
    """(r / r_max)² of rig-frame points about the projector's principal point (r: field-angle tangent)."""
    p_from_c = np.linalg.inv(proj.camera_from_projector)
    q = points @ p_from_c[:3, :3].T + p_from_c[:3, 3]
    k = proj.intrinsics.opencv_matrix()
    f = np.array([k[0, 0], k[1, 1]])
    w, h = proj.intrinsics.size
    corners = (np.array([[0, 0], [w, 0], [0, h], [w, h]], float) - k[:2, 2]) / f
    return np.sum((q[:, :2] / q[:, 2:3]) ** 2, axis=1) / float(np.max(np.sum(corners ** 2, axis=1)))


# ------------------------------------------------------------------ distortion

def _bilinear(img: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """``img`` (H×W×C) at pixel positions ``pts`` (pixel-centre convention); NaN outside."""
    h, w = img.shape[:2]
    x, y = pts[:, 0] - 0.5, pts[:, 1] - 0.5
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    v = (img[y0, x0] * (1 - fx) * (1 - fy) + img[y0, x0 + 1] * fx * (1 - fy) + img[y0 + 1, x0] * (1 - fx) * fy
         + img[y0 + 1, x0 + 1] * fx * fy)
    v[(x < 0) | (y < 0) | (x > w - 1) | (y > h - 1)] = np.nan
    return v


def _levenberg_marquardt(residual: Callable[[np.ndarray], np.ndarray], theta: np.ndarray, free: list[int],
                         steps: np.ndarray, iterations: int = 30) -> np.ndarray:
    r = residual(theta)
    cost, lam = float(r @ r), 1e-3
    for _ in range(iterations):
        jac = np.empty((r.size, len(free)))
        for j, k in enumerate(free):
            t = theta.copy()
            t[k] += steps[k]
            jac[:, j] = (residual(t) - r) / steps[k]
        a, g = jac.T @ jac, jac.T @ r
        for _ in range(8):
            t = theta.copy()
            t[free] -= np.linalg.lstsq(a + lam * np.diag(np.maximum(np.diag(a), 1e-12)), g, rcond=None)[0]
            rt = residual(t)
            c = float(rt @ rt)
            if np.isfinite(c) and c < cost:
                done = (cost - c) / max(cost, 1e-30) < 1e-8
                theta, r, cost, lam = t, rt, c, lam / 3
                break
            lam *= 4
        else:
            break
        if done:
            break
    return theta


def distortion_evidence(captures: Any, cal: Any, view: Any, mask: np.ndarray) -> Evidence:

    ev = Evidence("distortion", False, absorbed_by="the projector pose (Gray-code PnP) and the stage-B warp")
    if not captures.entries_of("graycode"):
        ev.error = "no Gray-code captures in the capture set"
        return ev
    try:
        dec = decode_gray_code_set(captures)
    except CaptureError as exc:
        ev.error = f"cannot decode the Gray code: {exc}"
        return ev
    use = dec.valid & view.hit & mask
    ys, xs = np.nonzero(use)
    if len(xs) < 500:
        ev.error = f"only {len(xs)} decoded surface pixels"
        return ev
    pick = _subset(len(xs))
    ys, xs = ys[pick], xs[pick]
    cam, proj = cal.rig.camera.intrinsics, cal.rig.projector
    k, kp = cam.opencv_matrix(), proj.intrinsics.opencv_matrix()
    f = np.array([k[0, 0], k[1, 1]])
    seen = (np.stack([xs + 0.5, ys + 0.5], axis=1) - k[:2, 2]) / f  # normalised, as the lens distorted them
    code = dec.coords[ys, xs].astype(np.float64) - 0.5
    # A projector lens a rig calibration measured is known, not looked for: without it the camera's terms take it
    # up (on the real board photos p1, p2 "removed" 58 % of the reprojection error that way).
    lens = None if proj.lens_distortion is None else np.asarray(proj.lens_distortion, np.float64)
    p_from_c = np.linalg.inv(proj.camera_from_projector)
    rvec, _ = cv2.Rodrigues(p_from_c[:3, :3])
    start = np.concatenate([rvec.ravel(), p_from_c[:3, 3], [0.0, 0.0, 0.0, 0.0]])

    def residual(theta: np.ndarray, sel: np.ndarray) -> np.ndarray:
        xd = seen[sel]
        # undistort OpenCV's x_d = x_u (1 + k1 r² + k2 r⁴) + tangential(p1, p2), fixed point
        xu = np.concatenate(undistort_normalised(xd[:, :1], xd[:, 1:], theta[6], theta[7], theta[8], theta[9],
                                                 steps=6), axis=1)
        pts = _bilinear(view.points, xu * f + k[:2, 2])
        proj_pts, _ = cv2.projectPoints(np.nan_to_num(pts), theta[:3], theta[3:6], kp, lens)
        r = proj_pts.reshape(-1, 2) - code[sel]
        r[~np.isfinite(pts[:, 0])] = 0.0
        return r.ravel()

    steps = np.array([1e-6] * 6 + [1e-4] * 4)
    everything = np.ones(len(xs), bool)
    pose = _levenberg_marquardt(lambda t: residual(t, everything), start, list(range(6)), steps)
    # Decoding errors (defocused stripes, grazing light) are outliers to both laws.
    thresh = max(1.0, 2.0 * proj.intrinsics.width / 800.0)
    inlier = np.hypot(*residual(pose, everything).reshape(-1, 2).T) < thresh
    fit = _blocks(xs, ys, cam.width) & inlier
    held = ~_blocks(xs, ys, cam.width) & inlier
    if fit.sum() < 200 or held.sum() < 200:
        ev.error = "too few consistent Gray-code correspondences"
        return ev
    mse = {}
    thetas = {}
    # radial k1, k2 (what the diagnosis's distortion model holds), then OpenCV's tangential p1, p2 as well: a
    # decentred lens that the radial law fits only in part
    # Each law starts where the one before it ended, so what it adds is its own terms, not a better-converged pose
    # (started alike, a longer run of the same pose had "found" 0.6 % on the real photos with k1 = k2 = 0).
    start = pose
    for name, free in (("pose", list(range(6))), ("pose+k", list(range(8))), ("pose+k+p", list(range(10)))):
        thetas[name] = start = _levenberg_marquardt(lambda t: residual(t, fit), start, free, steps)
        mse[name] = float(np.mean(residual(thetas[name], held) ** 2)) * 2  # per correspondence (x and y)
    radial = (mse["pose"] - mse["pose+k"]) / mse["pose"] if mse["pose"] > 0 else 0.0
    lens = (mse["pose"] - min(mse["pose+k"], mse["pose+k+p"])) / mse["pose"] if mse["pose"] > 0 else 0.0
    ev.share = lens
    t = thetas["pose+k+p"] if mse["pose+k+p"] < mse["pose+k"] else thetas["pose+k"]
    # Four significant digits, not decimals: behind a long lens (the real board camera's f ≈ 3450 px) the
    # normalised image is small and a lens that matters has coefficients that four decimals round to 0.
    ev.params = {k: float(f"{float(v):.4g}") for k, v in (("k1", thetas["pose+k"][6]), ("k2", thetas["pose+k"][7]),
                                                          ("p1", t[8]), ("p2", t[9]))}
    ev.detected = bool(lens >= DISTORTION_MIN_SHARE)
    ev.evidence = (f"the camera lens lowers the held-out Gray-code reprojection error from {np.sqrt(mse['pose']):.3f} "
                   f"to {np.sqrt(mse['pose'] * (1 - lens)):.3f} projector px ({lens:.1%} of its MSE; found at ≥ "
                   f"{DISTORTION_MIN_SHARE:.1%}); radial k1, k2 alone remove {max(radial, 0.0):.1%}"
                   + (f", so the radial model fits {max(radial, 0.0) / lens:.0%} of it (a decentred lens: "
                      "tangential p1, p2)" if lens > 0 and radial < 0.8 * lens and ev.detected else "")
                   + "; k1 trades with the pose's distance, k2 less")
    ev.model_share = float(np.clip(radial / lens, 0.0, 1.0)) if lens > 0 else None
    return ev


# ------------------------------------------------------------------ depth

def _plane_spread(depth: np.ndarray) -> tuple[float, int]:
    """Robust spread (1σ, metres) of a depth image about its best plane, and the valid pixel count."""
    valid = np.isfinite(depth) & (depth > 0)
    if valid.sum() < 100:
        return float("nan"), int(valid.sum())
    ys, xs = np.nonzero(valid)
    a = np.stack([np.ones(len(xs)), xs, ys], axis=1).astype(np.float64)
    z = depth[valid].astype(np.float64)
    r = z - a @ np.linalg.lstsq(a, z, rcond=None)[0]
    return float(1.4826 * np.median(np.abs(r - np.median(r)))), int(valid.sum())


def depth_evidence(captures: Any, cal: Any) -> Evidence:
    ev = Evidence("depth_noise", False, absorbed_by="the wall image's bias correction (or the pose), and the "
                                                      "reconstruction's smoothing")
    walls = captures.depth_walls()
    report = cal.report.get("surface_report") or {}
    if not walls and captures.depth_info is None:
        ev.absorbed_by = ""
        ev.error = (f"no depth image (the surface came from {report.get('source', 'elsewhere')}): there is no depth "
                    "sensor whose noise could be read")
        return ev
    if walls:

        entry, distance = walls[0]
        wall = captures.depth(name=entry.name).astype(np.float64)
        try:
            bias = wall_depth_offset(wall, distance)  # the bias calibration corrects, read the same way
        except SurfaceError as exc:
            ev.error = f"wall depth image {entry.file}: {exc}"
            return ev
        spread, n = _plane_spread(wall)
        missing = 1.0 - n / wall.size
        noise_1m = spread / float(distance)
        ev.params = {"bias_m": round(bias, 4), "noise_m_at_1m": round(noise_1m, 4), "missing": round(missing, 4)}
        ev.detected = bool(abs(bias) >= DEPTH_MIN_M or noise_1m >= DEPTH_MIN_M)
        ev.evidence = (f"the sensor's image of a flat wall at {distance} m reads {100 * bias:+.2f} cm off, spreads "
                       f"{100 * spread:.2f} cm about its plane ({100 * noise_1m:.2f} cm at 1 m) and misses "
                       f"{missing:.1%} of returns (found at ≥ {100 * DEPTH_MIN_M:.1f} cm)")
        return ev
    depth = captures.depth().astype(np.float64)
    # Second differences along rows: zero on any plane, noise·√6 where the sensor is noisy.
    d2 = depth[:, 2:] - 2 * depth[:, 1:-1] + depth[:, :-2]
    ok = np.isfinite(d2)
    if ok.sum() < 100:
        ev.error = "the scene depth image is nearly empty"
        return ev
    spread = float(1.4826 * np.median(np.abs(d2[ok]))) / np.sqrt(6.0)
    noise_1m = spread / float(np.nanmedian(depth))
    ev.params = {"noise_m_at_1m": round(noise_1m, 4), "bias_m": float(report.get("depth_offset", 0.0))}
    ev.detected = bool(noise_1m >= DEPTH_MIN_M)
    ev.evidence = (f"no wall depth image, so the bias cannot be seen; the scene depth's pixel-to-pixel noise is "
                   f"{100 * noise_1m:.2f} cm at 1 m (found at ≥ {100 * DEPTH_MIN_M:.1f} cm)")
    return ev


# ------------------------------------------------------------------ all three

def calibration_evidence(cal: Calibration, captures: CaptureSet, *, light: Light | None = None,
                         white_extra: np.ndarray | None = None, lobes: dict[float, np.ndarray] | None = None,
                         cancel: Cancel | None = None) -> dict[str, Evidence]:
    """Evidence for ``vignetting``, ``glossy``, ``distortion`` and ``depth_noise`` from a calibration and its
    capture set (``light``, ``white_extra`` and ``lobes``: see :func:`vignetting_evidence`)."""
    view = surface_view(cal.surface, cal.rig.camera.intrinsics)
    mask, _ = target_mask(captures)
    out: dict[str, Evidence] = {}
    for names, run in ((("vignetting", "glossy"), lambda: vignetting_evidence(captures, cal, view, mask, light=light,
                                                                              white_extra=white_extra, lobes=lobes)),
                       (("distortion",), lambda: (distortion_evidence(captures, cal, view, mask),)),
                       (("depth_noise",), lambda: (depth_evidence(captures, cal),))):
        if cancel is not None and cancel():
            raise Cancelled("diagnosis cancelled")
        try:
            out.update(zip(names, run()))
        except (ProCamError, np.linalg.LinAlgError, ValueError, FloatingPointError) as exc:
            out.update((name, Evidence(name, False, error=f"{type(exc).__name__}: {exc}")) for name in names)
    return out
