"""What ProCam hands a media server, derived from a calibration: per projector the geometry warp (projector pixel →
normalised content coordinates of the display area), the alpha map (its share of the light, the blend) and the
beta map (the black level lifted to the overlap's), and in the ``sl`` profile its frustum, pose and the surface
point under each pixel.

**Where a projector pixel's light lands.** Stage B says the real projector shows for an input ``x`` what the model
shows for ``z = M(x)``, ``x = W(z)``: the real pixel ``p`` carries the value of the model's pixel ``φ_W(p)``
(``Warp.map_w``), whose pinhole ray, cast onto the calibrated surface and seen by the camera, lands at a camera
pixel (:func:`trace`). The content is the display area (a rectangle of camera pixels, as for every target ProCam
compensates) stretched over the media server's canvas, so that camera pixel's place in the area is the content
coordinate the projector pixel must show. Pixels outside the projector's input area (ProCam keeps them black), rays
that miss the surface and surface points the camera does not see are unknown: NaN in the warp, 0 in the maps.

**Alpha.** Each projector's share of the light at the camera pixel its pixel lands on: the joint blend's shares
(:func:`..stages.joint.blend_shares`, read off the light-transport operators, weighted by each projector's
registration) when the calibration holds every operator, else the classic geometric ramps: the same distance blend
on each projector's footprint by the model and its captures (said in the file and to the user). The shares sum to
1 wherever a projector lights the area, so the projectors' light adds up to the content's.

**Beta.** With every projector black the camera still sees each one's black level, and where they overlap it adds:
the overlap's black is brighter than the rest (the black uplift edge blending is known for). Beta lifts the rest to
the overlap's floor ``F`` (the 99th percentile of the blurred all-black capture over the area): the deficit
``D = F − B`` at each camera pixel is shared between the projectors by their shares, projector k's part in its
own input levels ``β_k = share_k · D / (white_k − black_k)``. The media server shows ``Pi·α·(1 − β) + β``, so black
content gives ``F`` everywhere. Without captures there is no measured black level: beta is 0, and said so.

**What a static hand-off keeps and loses.** It keeps the geometry (stage A and B), the blend and the black floor.
It loses everything ProCam solves per frame: the surface's texture and colour, the projectors' brightness falling
off across the surface, interreflection, the range map, θ — a media server shows the content as it is, blended.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..errors import Cancelled, MpcdiError
from ..progress import Cancel, Progress, quiet
from ..render.raycast import first_hits
from ..stages.calibrate import Calibration
from ..stages.display_area import DisplayArea
from .format import CoordinateFrame, Frustum, Mpcdi, Region

#: grid samples traced per ray-cast call and warp-map evaluation (the spline's basis is points × grid² floats)
CHUNK = 65536
#: the all-black capture is blurred by this many camera pixels before the floor is read (the camera's noise)
BLACK_BLUR_PX = 2.0
#: below this deficit (linear camera units) the black level counts as flat: no beta
FLAT_BLACK = 0.002
#: the black floor is this percentile of the black level over the area (the overlap's, not a hot pixel's)
FLOOR_PERCENTILE = 99.0
#: the region id of projector K (from 1) and the 2d profile's one buffer
REGION_ID = "projector_{k}"
BUFFER_ID = "display"


@dataclass(frozen=True)
class CameraMaps:
    """What the blend and the black level come from, in camera space (the calibration's camera size)."""

    shares: np.ndarray  # (K, H, W) each projector's share of the light
    blend: str  # how the shares were made (said in the file and to the user)
    black: np.ndarray | None = None  # (H, W, 3) every projector black (captured); None: not measured
    lit: list[np.ndarray] | None = None  # each projector's white − black (H, W, 3), captured


@dataclass
class Traced:
    """Where a set of projector pixels' light lands (:func:`trace`), one row per pixel."""

    camera: np.ndarray  # (N, 2) camera pixel (corner convention); NaN where unknown
    points: np.ndarray  # (N, 3) surface point, rig frame; NaN where unknown
    shown: np.ndarray  # (N, 2) the native-frame pixel of the model whose ray carries the light (after the warp)
    valid: np.ndarray  # (N,) bool


@dataclass
class Derived:
    """The file and what to tell the user about it."""

    mpcdi: Mpcdi
    report: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


def grid_centres(size: tuple[int, int], samples: tuple[int, int]) -> np.ndarray:
    """(rows·cols, 2) native-frame positions of a uniform grid of ``samples`` = (cols, rows) over a raster of
    ``size`` in fill layout (§3.6: sample i covers [i·W/cols, (i+1)·W/cols)), row-major, row 0 at the top."""
    w, h = size
    cols, rows = samples
    x, y = np.meshgrid((np.arange(cols) + 0.5) * w / cols, (np.arange(rows) + 0.5) * h / rows)
    return np.stack([x.ravel(), y.ravel()], axis=1)


def warp_samples(size: tuple[int, int], step: int) -> tuple[int, int]:
    """(cols, rows) of a warp grid about ``step`` projector pixels apart (at least 2×2, §3.6)."""
    return max(2, math.ceil(size[0] / step)), max(2, math.ceil(size[1] / step))


def trace(view: Calibration, pixels: np.ndarray, cancel: Cancel | None = None) -> Traced:
    """Where the real projector's native-frame ``pixels`` (N×2, corner convention) send their light (module doc):
    through the stage-B warp, the pinhole ray onto the surface, and into the camera when it sees that point."""
    proj = view.rig.projector
    px = np.asarray(pixels, np.float64).reshape(-1, 2)
    (x0, y0), (iw, ih) = proj.input_offset, proj.input_size
    q = px - (x0, y0)
    inside = (q[:, 0] >= 0) & (q[:, 0] < iw) & (q[:, 1] >= 0) & (q[:, 1] < ih)
    if view.warp is not None and not view.warp.is_identity:
        scale = np.asarray(view.warp.size, np.float64) / (iw, ih)
        for i in range(0, len(q), CHUNK):  # the spline's basis is points × grid²: a chunk at a time
            if cancel is not None and cancel():
                raise Cancelled("the MPCDI export was cancelled; nothing was written")
            q[i:i + CHUNK] = view.warp.map_w(q[i:i + CHUNK] * scale) / scale
    shown = q + (x0, y0)
    pose = proj.camera_from_projector
    dirs = proj.intrinsics.rays(shown) @ pose[:3, :3].T
    origin = pose[:3, 3]
    t = np.full(len(px), np.inf)
    for i in range(0, len(px), CHUNK * 8):
        if cancel is not None and cancel():
            raise Cancelled("the MPCDI export was cancelled; nothing was written")
        t[i:i + CHUNK * 8] = first_hits(view.surface, origin, dirs[i:i + CHUNK * 8])
    hit = inside & np.isfinite(t)
    points = origin + np.where(hit, t, 1.0)[:, None] * dirs
    seen = np.zeros(len(px), bool)
    idx = np.flatnonzero(hit)
    for i in range(0, len(idx), CHUNK * 8):
        part = idx[i:i + CHUNK * 8]
        # The camera sees the point when nothing lies between: a ray from the camera towards it first hits at t ≈ 1.
        t_cam = first_hits(view.surface, np.zeros(3), points[part])
        seen[part] = np.isfinite(t_cam) & (t_cam > 1.0 - 1e-3)
    camera = view.rig.camera.intrinsics.project(points)
    valid = seen & np.all(np.isfinite(camera), axis=1)
    nan = np.full((len(px), 2), np.nan)
    return Traced(np.where(valid[:, None], camera, nan), np.where(valid[:, None], points, np.nan),
                  np.where(inside[:, None], shown, np.nan), valid)


def content_coords(camera: np.ndarray, area: DisplayArea) -> np.ndarray:
    """(N, 2) normalised content coordinates (s right, t down, the area's corners at 0 and 1) of camera pixels."""
    c = np.asarray(camera, np.float64)
    return np.stack([(c[:, 0] - area.x) / area.width, (c[:, 1] - area.y) / area.height], axis=1)


def sample_camera(image: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """Bilinear samples of a camera-space image (H×W or H×W×C) at (N, 2) camera pixels (corner convention); 0 at
    NaN positions and outside the image."""
    c = np.asarray(camera, np.float32)
    ok = np.all(np.isfinite(c), axis=1)
    mx = np.where(ok, c[:, 0] - 0.5, -1e6).astype(np.float32).reshape(1, -1)
    my = np.where(ok, c[:, 1] - 0.5, -1e6).astype(np.float32).reshape(1, -1)
    out = np.zeros((len(c),) + image.shape[2:], np.float32)
    step = 32000  # remap's maps are images: one row of at most 32k columns at a time (OpenCV's SHRT_MAX limit)
    for i in range(0, len(c), step):
        s = cv2.remap(np.asarray(image, np.float32), mx[:, i:i + step], my[:, i:i + step], cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        out[i:i + step] = s.reshape((-1,) + image.shape[2:])
    return out


def beta_maps(maps: CameraMaps, area: DisplayArea) -> tuple[list[np.ndarray] | None, dict[str, Any]]:
    """Each projector's beta in camera space (module doc, "Beta"), and what was found; None without captures or
    where the black level is flat."""
    if maps.black is None or maps.lit is None:
        return None, {"beta": "no capture set: the black level was not measured, beta is 0"}
    k, h, w = maps.shares.shape
    if maps.black.shape[:2] != (h, w) or any(v.shape[:2] != (h, w) for v in maps.lit):
        return None, {"beta": "the captures are not the calibration's camera size: beta is 0"}
    black = cv2.GaussianBlur(np.asarray(maps.black, np.float32).mean(axis=2), (0, 0), BLACK_BLUR_PX)
    lit_any = maps.shares.sum(axis=0) > 0
    in_area = area.mask((w, h)) & lit_any
    if in_area.sum() < 16:
        return None, {"beta": "the area holds too few lit camera pixels to read the black level: beta is 0"}
    floor = float(np.percentile(black[in_area], FLOOR_PERCENTILE))
    deficit = np.where(lit_any, np.clip(floor - black, 0.0, None), 0.0)
    spread = float(np.percentile(deficit[in_area], 95))
    record = {"black_floor": round(floor, 5), "black_lift_p95": round(spread, 5)}
    if spread < FLAT_BLACK:
        return None, {**record, "beta": f"the black level is flat within {FLAT_BLACK} over the area: beta is 0"}
    out = []
    for share, lit in zip(maps.shares, maps.lit):
        white = cv2.GaussianBlur(np.asarray(lit, np.float32).mean(axis=2), (0, 0), BLACK_BLUR_PX)
        ok = (share > 1e-3) & (white > 0.01)
        out.append(np.clip(np.where(ok, share * deficit / np.maximum(white, 0.01), 0.0), 0.0, 1.0).astype(np.float32))
    return out, {**record, "beta": "lifts every pixel's black to the overlap's floor"}


def _angles(f: np.ndarray, u: np.ndarray) -> tuple[float, float, float]:
    """Yaw, pitch, roll (degrees) of a frame with forward ``f`` and up ``u`` in MPCDI's world (X left, Y up, Z
    forward): yaw turns the view right (towards −X), pitch up, roll clockwise as the viewer sees it, applied in
    that order (§2.2.1)."""
    pitch = math.asin(float(np.clip(f[1], -1.0, 1.0)))
    yaw = math.atan2(-float(f[0]), float(f[2]))
    cy, sy, cp, sp = math.cos(-yaw), math.sin(-yaw), math.cos(-pitch), math.sin(-pitch)
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    m0 = ry @ rx
    up0, left0 = m0[:, 1], m0[:, 0]
    roll = math.atan2(-float(u @ left0), float(u @ up0))
    return math.degrees(yaw), math.degrees(pitch), math.degrees(roll)


#: ProCam's rig frame (OpenCV: x right, y down, z forward) → MPCDI's preferred world (§3.6.3: X left, Y up, Z
#: forward): a half turn about z, so right-handedness is kept.
TO_MPCDI = np.diag([-1.0, -1.0, 1.0])


def frustum_and_frame(view: Calibration, centre: np.ndarray) -> tuple[Frustum, CoordinateFrame]:
    """The projector's frustum (its angles from K, lens shift included) and coordinate frame in MPCDI's world with
    its origin at ``centre`` (rig frame)."""
    proj = view.rig.projector
    k = proj.intrinsics
    w, h = k.size
    r = proj.camera_from_projector[:3, :3]
    left, up, forward = TO_MPCDI @ -r[:, 0], TO_MPCDI @ -r[:, 1], TO_MPCDI @ r[:, 2]
    yaw, pitch, roll = _angles(forward, up)
    deg = math.degrees
    frustum = Frustum(yaw, pitch, roll, deg(math.atan((w - k.cx) / k.fx)), deg(math.atan((0 - k.cx) / k.fx)),
                      deg(math.atan((k.cy - 0) / k.fy)), deg(math.atan((k.cy - h) / k.fy)))
    pos = TO_MPCDI @ (proj.camera_from_projector[:3, 3] - centre)
    return frustum, CoordinateFrame(tuple(pos), tuple(up), tuple(left), tuple(forward))  # type: ignore[arg-type]


def build(calibration: Calibration, area: DisplayArea, maps: CameraMaps, *, content_size: tuple[int, int],
          warp_step: int = 4, profile: str = "2d", progress: Progress | None = None,
          cancel: Cancel | None = None) -> Derived:
    """The MPCDI file of ``calibration``'s projectors for content shown in ``area`` (module doc)."""
    say = progress or quiet
    count = calibration.projector_count
    if maps.shares.shape[0] != count:
        raise MpcdiError(f"{maps.shares.shape[0]} blend shares for {count} projectors")
    betas, beta_record = beta_maps(maps, area)
    centre = np.asarray(calibration.surface.vertices, np.float64).mean(axis=0)
    regions, rows, warnings = [], [], []
    if betas is None:
        warnings.append(str(beta_record["beta"]))
    for k in range(count):
        view = calibration.for_projector(k)
        proj = view.rig.projector
        size = proj.intrinsics.size
        w, h = size
        say(f"projector {k + 1}/{count}: tracing its {w}×{h} pixels", k / count)
        full = trace(view, grid_centres(size, size), cancel)
        st = content_coords(full.camera, area)
        inside = full.valid & np.all((st >= 0) & (st <= 1), axis=1)
        if inside.sum() < 4:
            raise MpcdiError(f"projector {k + 1}'s light misses the display area ({area.width}×{area.height} at "
                             f"{area.x},{area.y} camera pixels): calibrate it again, or give an --area it lights")
        alpha = np.where(inside, sample_camera(maps.shares[k], full.camera), 0.0).reshape(h, w)
        # A beta map always: zero where no black level was measured (readers of v1.0's levels 2 and 4 require one).
        beta = np.zeros((h, w)) if betas is None else \
            np.where(inside, sample_camera(betas[k], full.camera), 0.0).reshape(h, w)
        s0, t0 = np.nanmin(st[inside], axis=0)
        s1, t1 = np.nanmax(st[inside], axis=0)
        if s1 - s0 <= 0 or t1 - t0 <= 0:
            raise MpcdiError(f"projector {k + 1} lights a line of the display area, not a region of it")
        cols, rows_n = warp_samples(size, warp_step)
        say(f"projector {k + 1}/{count}: its {cols}×{rows_n} warp grid", (k + 0.5) / count)
        grid = trace(view, grid_centres(size, (cols, rows_n)), cancel)
        if profile == "2d":
            g = content_coords(grid.camera, area)
            # Region coordinates, v up and the region's y from the buffer's bottom (format module doc).
            x, y, xs, ys = float(s0), float(1.0 - t1), float(s1 - s0), float(t1 - t0)
            u = (g[:, 0] - x) / xs
            v = ((1.0 - g[:, 1]) - y) / ys
            known = grid.valid
            warp = np.stack([np.where(known, u, np.nan), np.where(known, v, np.nan),
                             np.where(known, np.nan, 1.0)], axis=1)
            region = Region(REGION_ID.format(k=k + 1), x, y, xs, ys, (w, h),
                            warp.reshape(rows_n, cols, 3).astype(np.float32), alpha.astype(np.float32),
                            beta.astype(np.float32), buffer=BUFFER_ID)
        else:
            points = (grid.points - centre) @ TO_MPCDI.T  # NaN rows stay NaN
            shown = grid.shown / (w, h)
            distortion = np.stack([shown[:, 0], 1.0 - shown[:, 1],
                                   np.where(np.isfinite(shown[:, 0]), np.nan, 1.0)], axis=1)
            frustum, frame = frustum_and_frame(view, centre)
            rid = REGION_ID.format(k=k + 1)
            region = Region(rid, 0.0, 0.0, 1.0, 1.0, (w, h), points.reshape(rows_n, cols, 3).astype(np.float32),
                            alpha.astype(np.float32), beta.astype(np.float32), frustum=frustum, frame=frame,
                            distortion=distortion.reshape(rows_n, cols, 3).astype(np.float32), buffer=rid)
        regions.append(region)
        rows.append({"projector": k + 1, "region": region.id, "resolution": [w, h], "warp_grid": [cols, rows_n],
                     "place_in_content": [round(float(s0), 5), round(float(t0), 5), round(float(s1 - s0), 5),
                                          round(float(t1 - t0), 5)],
                     "pixels_showing_content": round(float(inside.mean()), 4),
                     "alpha_mean_where_shown": round(float(alpha.reshape(-1)[inside].mean()), 4),
                     "beta_max": round(float(beta.max()), 4)})
    buffers = {BUFFER_ID: tuple(content_size)} if profile == "2d" else {r.id: r.resolution for r in regions}
    extension = {"blend": maps.blend, "contentArea": f"{area.x},{area.y},{area.width},{area.height}",
                 "contentCoordinates": "the display area of the calibration's camera, stretched over the buffer",
                 "calibrationCamera": "{}x{}".format(*calibration.rig.camera.intrinsics.size),
                 "beta": str(beta_record["beta"])}
    if profile == "sl":
        extension["world"] = "rig frame turned to X left, Y up, Z forward, metres, origin the surface's vertex mean"
    m = Mpcdi(profile, buffers, regions, "m" if profile == "sl" else "unknown",
              "centerOfMass" if profile == "sl" else "unknown", extension=extension)  # type: ignore[arg-type]
    say("done", 1.0)
    return Derived(m, {"profile": profile, "blend": maps.blend, "area": area.to_dict(),
                       "content_size": list(content_size), **beta_record, "projectors": rows}, warnings)
