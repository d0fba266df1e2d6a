"""Depth maps as users have them: file formats, units, holes, and alignment with the colour camera.

A capture set stores depth in metres, aligned with the camera, NaN (0 on disk)
where the sensor saw nothing (:mod:`.format`). Users bring depth in other forms:

* ``.npy`` / ``.exr`` float maps in metres (what ProCam writes);
* 16-bit PNG/TIFF in millimetres, 0 = no measurement: the iPhone, RealSense and
  Azure Kinect convention;
* a PLY point cloud (ASCII or binary) of x y z vertices in the camera's OpenCV
  frame (x right, y down, z forward, metres), which :func:`read_depth` projects
  through the camera's K into a depth map, the nearest point winning each pixel.

:func:`read_depth` reads any of them into a :class:`DepthReading` and says what
it did (format, scale and why, warnings). Units are detected from the values
(``units="auto"``): a map whose median is in the hundreds or thousands was given
in millimetres and is converted, with a warning naming the file; what still lies
outside [0.05 m, 50 m] is refused. A map with too few valid pixels is refused.

:func:`align_depth` finds a depth map shifted against the photographs by a few
pixels (a depth sensor registered to the colour camera with an offset): it
correlates depth edges (large jumps in inverse depth, hole borders) with the
edges of a capture that shows the surface's silhouette, over integer shifts of
±8 px; a clear shift is corrected, an ambiguous one refused. Every failure is a
:class:`~..errors.CaptureError` that names the file and says what to do.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import CaptureError
from ..imageio import DAMAGED_ARRAYS, check_image_file
from ..rig.model import Intrinsics
from .format import MAX_DEPTH_MISSING

DEPTH_UNITS = ("auto", "m", "mm")
DEPTH_FILE_SUFFIXES = (".npy", ".exr", ".png", ".tif", ".tiff", ".ply")
#: Depth a projection-mapping scene can have, in metres; medians outside are a unit mistake, pixels outside holes.
MIN_DEPTH_M, MAX_DEPTH_M = 0.05, 50.0
#: ``units="auto"``: a float map whose median is at least this (hundreds or thousands) is millimetres; between
#: ``MAX_DEPTH_M`` and this it is ambiguous and refused (say --depth-units)
MM_MEDIAN = 100.0
#: The least share of valid pixels a depth map must have (the capture-set format's own limit).
MIN_VALID = 1.0 - MAX_DEPTH_MISSING
#: A point cloud whose footprint (its hit pixels, closed over small gaps) covers less of the image is refused.
MIN_CLOUD_FOOTPRINT = 0.2
#: More than this share of a cloud's points behind the camera (z ≤ 0) means the cloud is in another frame.
MAX_BEHIND = 0.5
#: Alignment search: integer shifts up to this many depth pixels in x and y.
MAX_SHIFT = 8
#: A depth pixel is an edge where inverse depth changes by more than this share of its median per pixel.
EDGE_JUMP = 0.05
#: Alignment decision thresholds (edge-map normalised cross-correlation, see :func:`align_depth`).
MIN_EDGE_SHARE = 0.005   # fewer depth edge pixels than this share of the image: nothing to align on
MIN_PROMINENCE = 0.1     # peak NCC minus the median over all shifts: below, the edges do not match anywhere
MIN_GAIN = 0.15          # share of the peak's prominence lost at zero shift needed to call a shift
RUNNER_UP = 0.9          # a separate peak this close to the best one makes the shift ambiguous

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


@dataclass(frozen=True)
class DepthReading:
    """A depth file read into metres: what it held and what was done to it."""

    path: Path
    #: H×W float32 metres, NaN where there is no measurement
    depth: np.ndarray
    #: "npy", "exr", "png 16-bit", "tiff 16-bit", "tiff float", "ply ascii", "ply binary_little_endian", …
    source_format: str
    #: the factor that turned the file's values into metres
    scale: float
    #: why that factor (detected or given)
    scale_reason: str
    #: True when the map was made by projecting a point cloud through the camera's K (already a pinhole
    #: camera's view: do not undistort it again)
    projected: bool = False
    warnings: tuple[str, ...] = ()

    @property
    def valid_fraction(self) -> float:
        return float(np.isfinite(self.depth).mean()) if self.depth.size else 0.0

    def notes(self) -> dict[str, object]:
        """What the capture set's ``notes["depth"]`` records about this file."""
        return {"file": str(self.path.resolve()), "format": self.source_format, "scale_to_metres": self.scale,
                "units": self.scale_reason, "projected_point_cloud": self.projected,
                "valid": round(self.valid_fraction, 4), "warnings": list(self.warnings)}


# -- reading -------------------------------------------------------------------------------------

def _one_channel(raw: np.ndarray, path: Path) -> np.ndarray:
    a = np.asarray(raw)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim == 3:
        first = a[..., :1]
        same = np.all((a == first) | (np.isnan(a) & np.isnan(first)) if a.dtype.kind == "f" else a == first)
        if not same:
            raise CaptureError(f"depth file {path} has {a.shape[2]} different channels; a depth map has one "
                               "(export the depth channel alone)")
        a = a[..., 0]
    if a.ndim != 2 or min(a.shape) < 2:
        raise CaptureError(f"depth file {path} is not an H×W depth map (shape {a.shape})")
    return a


def _read_raster(path: Path) -> tuple[np.ndarray, str, bool]:
    """Values as stored, the format's name, and whether they are integer millimetres by convention."""
    suffix = path.suffix.lower()
    # Its header is read first: a few bytes can declare 10⁶×10⁶ values (ImageError names the size and the limit).
    check_image_file(path, f"depth file {path}")
    if suffix == ".npy":
        try:
            a = np.load(path, allow_pickle=False)
        except DAMAGED_ARRAYS as exc:
            raise CaptureError(f"cannot read depth file {path}: {exc}") from None
        if a.dtype.kind not in "fiu":
            raise CaptureError(f"depth file {path} holds {a.dtype} values, not numbers")
        return _one_channel(a, path), "npy", a.dtype.kind in "iu"
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise CaptureError(f"cannot read depth file {path}: not an image, or the file is damaged")
    a = _one_channel(raw, path)
    kind = "exr" if suffix == ".exr" else ("png" if suffix == ".png" else "tiff")
    if a.dtype == np.uint8:
        raise CaptureError(f"depth file {path} is an 8-bit image, which cannot hold depth (256 levels); export "
                           "depth as 16-bit PNG/TIFF in millimetres, or as .npy/.exr in metres")
    if a.dtype.kind in "iu":
        return a, f"{kind} {a.dtype.itemsize * 8}-bit", True
    return a, kind if kind == "exr" else f"{kind} float", False


def _ply_header(data: bytes, path: Path) -> tuple[str, list[tuple[str, int, list[tuple[str, str, str | None]]]], int]:
    """The format, the elements (name, count, [(property, type, list count type)]) and the body's offset."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise CaptureError(f"depth file {path} is not a PLY file (no 'ply' … 'end_header' header)")
    nl = data.find(b"\n", end)
    body = nl + 1 if nl >= 0 else len(data)
    fmt = ""
    elements: list[tuple[str, int, list[tuple[str, str, str | None]]]] = []
    for line in data[:end].decode("ascii", "replace").splitlines()[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and words[1] == "list":
                elements[-1][2].append((words[4], _PLY_TYPES[words[3]], _PLY_TYPES[words[2]]))
            elif words[0] == "property":
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]], None))
        except (IndexError, KeyError, ValueError):
            raise CaptureError(f"depth file {path}: cannot understand the PLY header line {line.strip()!r}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise CaptureError(f"depth file {path}: unknown PLY format {fmt!r}")
    return fmt, elements, body


def read_ply_points(path: str | Path) -> tuple[np.ndarray, str]:
    """The x y z vertices of a PLY file (ASCII or binary) as N×3 float64, and its format's name."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CaptureError(f"cannot read depth file {path}: {exc.strerror or exc}") from None
    fmt, elements, body = _ply_header(data, path)
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise CaptureError(f"depth file {path}: the PLY file has no vertex element")
    vi = names.index("vertex")
    count, props = elements[vi][1], elements[vi][2]
    prop_names = [p[0] for p in props]
    if not {"x", "y", "z"} <= set(prop_names):
        raise CaptureError(f"depth file {path}: PLY vertices need x, y and z properties, have {', '.join(prop_names)}")
    if any(p[2] is not None for p in props):
        raise CaptureError(f"depth file {path}: PLY vertices with list properties are not supported")
    cols = [prop_names.index(c) for c in ("x", "y", "z")]
    truncated = f"depth file {path} is truncated (fewer vertices than its PLY header announces); export it again"
    if fmt == "ascii":
        lines = data[body:].decode("ascii", "replace").splitlines()
        skip = sum(e[1] for e in elements[:vi])
        rows = lines[skip:skip + count]
        if len(rows) < count:
            raise CaptureError(truncated)
        try:
            values = np.array(" ".join(rows).split(), dtype=np.float64)
            values = values.reshape(count, len(props))
        except ValueError:
            raise CaptureError(f"depth file {path}: PLY vertex lines do not hold {len(props)} numbers each") from None
        return values[:, cols], "ply ascii"
    order = "<" if fmt == "binary_little_endian" else ">"
    offset = body
    for name, n, ps in elements[:vi]:
        if any(p[2] is not None for p in ps):
            raise CaptureError(f"depth file {path}: a PLY element with lists ({name}) before the vertices is not "
                               "supported; put the vertex element first")
        offset += n * sum(np.dtype(p[1]).itemsize for p in ps)
    dtype = np.dtype([(p[0], order + p[1]) for p in props])
    if len(data) < offset + count * dtype.itemsize:
        raise CaptureError(truncated)
    verts = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
    return np.stack([verts[c].astype(np.float64) for c in ("x", "y", "z")], axis=1), f"ply {fmt}"


def project_points(points: np.ndarray, camera: Intrinsics, size: tuple[int, int] | None = None, *,
                   name: str = "the point cloud") -> np.ndarray:
    """A depth map (H×W float32 z, NaN holes) of N×3 camera-frame points: the nearest point wins each pixel.

    ``size`` (width, height) projects through K scaled to that size; default the camera's.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) == 0:
        raise CaptureError(f"{name} holds no points")
    behind = float(np.mean(p[:, 2] <= 0))
    if behind > MAX_BEHIND:
        raise CaptureError(f"{name} lies behind the camera ({behind:.0%} of its points have z ≤ 0): its points must "
                           "be in the camera's OpenCV frame (x right, y down, z forward, metres). A cloud in "
                           "OpenGL/Blender camera axes (y up, z backward) needs y and z negated; a cloud in world "
                           "coordinates needs the camera's pose taken out")
    w, h = size or camera.size
    k = camera.scaled(int(w), int(h)) if (w, h) != camera.size else camera
    p = p[p[:, 2] > 0]
    u = np.floor(k.fx * p[:, 0] / p[:, 2] + k.cx)  # corner convention: pixel i covers [i, i+1)
    v = np.floor(k.fy * p[:, 1] / p[:, 2] + k.cy)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    depth = np.full((h, w), np.nan, np.float32)
    if inside.any():
        idx = (v[inside] * w + u[inside]).astype(np.int64)
        z = p[inside, 2]
        order = np.lexsort((z, idx))  # by pixel, nearest first
        first = np.unique(idx[order], return_index=True)[1]
        depth.reshape(-1)[idx[order][first]] = z[order][first]
    hit = np.isfinite(depth)
    footprint = cv2.morphologyEx(hit.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((9, 9), np.uint8)).mean()
    if footprint < MIN_CLOUD_FOOTPRINT:
        raise CaptureError(f"{name} projects onto only {footprint:.0%} of the {w}×{h} image ({int(inside.sum())} of "
                           f"{len(p)} points in front of the camera fall inside it; at least "
                           f"{MIN_CLOUD_FOOTPRINT:.0%} needed): is it in the camera's frame and metres, and does the "
                           "camera's K (--camera-fov, --rig) fit the camera that saw it?")
    if hit.mean() < MIN_VALID and footprint >= MIN_VALID:
        # The cloud covers the image but is too sparse for this many pixels.
        n = max(int(hit.sum()), 1)
        scale = np.sqrt(n / max(footprint * w * h, 1.0))
        raise CaptureError(f"{name} is too sparse for a {w}×{h} depth map: only {hit.mean():.0%} of the pixels get "
                           f"a point; project it at a smaller size, about {max(2, int(w * scale))}×"
                           f"{max(2, int(h * scale))} (--depth-native-width/--depth-native-height)")
    return depth


def _units(values: np.ndarray, units: str, integer_mm: bool, path: Path) -> tuple[float, str, list[str]]:
    """The factor to metres, why, and warnings, from the valid values (> 0) and the units asked for."""
    warnings: list[str] = []
    if units == "m":
        return 1.0, "metres (given)", warnings
    if units == "mm":
        return 0.001, "millimetres (given)", warnings
    med = float(np.median(values)) if values.size else float("nan")
    if integer_mm:
        return 0.001, "millimetres (16-bit integer depth, the iPhone/RealSense/Azure Kinect convention)", warnings
    if med >= MM_MEDIAN and MIN_DEPTH_M <= med * 0.001 <= MAX_DEPTH_M:
        warnings.append(f"depth file {path.name}: values have a median of {med:.4g}, which is millimetres, not "
                        f"metres: converted to metres (median {med * 0.001:.3g} m). Pass --depth-units m or mm to "
                        "say which")
        return 0.001, f"millimetres (detected: median {med:.4g})", warnings
    return 1.0, "metres", warnings


def read_depth(path: str | Path, camera: Intrinsics, *, units: str = "auto",
               size: tuple[int, int] | None = None) -> DepthReading:
    """Read a depth map or point cloud into metres (see the module's docstring for formats and units).

    ``camera`` is the colour camera's intrinsics (a point cloud is projected
    through them); ``size`` (width, height) is the size to project a point cloud
    at, default the camera's; a raster keeps its own size.
    """
    path = Path(path)
    if units not in DEPTH_UNITS:
        raise CaptureError(f"depth units must be one of {', '.join(DEPTH_UNITS)}, got {units!r}")
    if not path.is_file():
        raise CaptureError(f"depth file {path} does not exist")
    suffix = path.suffix.lower()
    if suffix not in DEPTH_FILE_SUFFIXES:
        raise CaptureError(f"depth file {path}: unknown type {suffix!r}; give .npy/.exr in metres, 16-bit "
                           ".png/.tif in millimetres, or a .ply point cloud in the camera's frame")
    warnings: list[str] = []
    projected = False
    if suffix == ".ply":
        points, fmt = read_ply_points(path)
        raw = project_points(points, camera, size, name=f"point cloud {path}").astype(np.float64)
        integer_mm, projected = False, True
    else:
        raw_values, fmt, integer_mm = _read_raster(path)
        raw = raw_values.astype(np.float64)
    finite = np.isfinite(raw)
    if np.any(raw[finite] < 0):
        raise CaptureError(f"depth file {path} holds negative values (min {float(raw[finite].min()):.4g}): depth is "
                           "a distance and must be positive; is this disparity or a signed format?")
    if np.any(np.isinf(raw)):
        warnings.append(f"depth file {path.name}: {int(np.isinf(raw).sum())} infinite values taken as holes")
    valid = finite & (raw > 0)
    if valid.mean() < MIN_VALID:
        raise CaptureError(f"depth file {path} is mostly holes: only {valid.mean():.0%} of its pixels hold a depth "
                           f"(at least {MIN_VALID:.0%} needed); capture the depth again closer to the surface or "
                           "with fewer reflections, or import without --depth")
    scale, reason, unit_warnings = _units(raw[valid], units, integer_mm, path)
    warnings += unit_warnings
    depth = np.where(valid, raw * scale, np.nan)
    med = float(np.nanmedian(depth))
    if not MIN_DEPTH_M <= med <= MAX_DEPTH_M:
        raise CaptureError(f"depth file {path}: its median depth is {med:.4g} m in {reason}, outside "
                           f"[{MIN_DEPTH_M:g}, {MAX_DEPTH_M:g}] m: not a depth map in metres or millimetres "
                           "(disparity, centimetres, a normalised image?); give --depth-units, or export depth in "
                           "metres (.npy/.exr) or 16-bit millimetres (.png)")
    out_of_range = valid & ((depth < MIN_DEPTH_M) | (depth > MAX_DEPTH_M))
    if out_of_range.any():
        warnings.append(f"depth file {path.name}: {int(out_of_range.sum())} pixels ({out_of_range.mean():.1%}) outside "
                        f"[{MIN_DEPTH_M:g}, {MAX_DEPTH_M:g}] m taken as holes")
        depth[out_of_range] = np.nan
        if np.isfinite(depth).mean() < MIN_VALID:
            raise CaptureError(f"depth file {path} is mostly holes once the pixels outside [{MIN_DEPTH_M:g}, "
                               f"{MAX_DEPTH_M:g}] m are removed ({np.isfinite(depth).mean():.0%} valid); "
                               "check its units")
    return DepthReading(path, depth.astype(np.float32), fmt, scale, reason, projected, tuple(warnings))


# -- alignment -----------------------------------------------------------------------------------

def shift_image(a: np.ndarray, dx: int, dy: int, fill: float = np.nan) -> np.ndarray:
    """``a`` moved by (dx, dy) pixels (content at x goes to x + dx); uncovered borders get ``fill``."""
    out = np.full_like(a, fill)
    h, w = a.shape[:2]
    if abs(dx) >= w or abs(dy) >= h:
        return out
    src_y, dst_y = (slice(0, h - dy), slice(dy, h)) if dy >= 0 else (slice(-dy, h), slice(0, h + dy))
    src_x, dst_x = (slice(0, w - dx), slice(dx, w)) if dx >= 0 else (slice(-dx, w), slice(0, w + dx))
    out[dst_y, dst_x] = a[src_y, src_x]
    return out


def depth_edges(depth: np.ndarray) -> np.ndarray:
    """Where depth jumps (H×W in [0, 1]): relative changes of inverse depth, large holes taken as far away.

    Small holes (sensor dropouts) are closed first and the map median-filtered, so that only silhouettes and
    the borders of large holes (background out of range) count as edges.
    """
    d = np.asarray(depth, dtype=np.float32)
    valid = np.isfinite(d) & (d > 0)
    inv = np.where(valid, 1.0 / np.where(valid, d, 1.0), 0.0).astype(np.float32)
    if not valid.any():
        return np.zeros_like(inv)
    inv = inv / float(np.median(inv[valid]))
    inv = cv2.morphologyEx(inv, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    inv = cv2.medianBlur(inv, 5)
    gx = cv2.Sobel(inv, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(inv, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    return np.clip(np.hypot(gx, gy) / EDGE_JUMP, 0.0, 1.0)


def image_edges(image: np.ndarray, size: tuple[int, int] | None = None) -> np.ndarray:
    """Edges of a capture (H×W in [0, 1]) at ``size`` (width, height): gradient of the smoothed grey image."""
    g = np.asarray(image, dtype=np.float32)
    g = g.mean(axis=2) if g.ndim == 3 else g
    if size is not None and (g.shape[1], g.shape[0]) != tuple(size):
        g = cv2.resize(g, tuple(int(v) for v in size), interpolation=cv2.INTER_AREA)
    g = cv2.GaussianBlur(g, (0, 0), 1.0)
    top = float(np.percentile(g, 99))
    if top <= 0:
        return np.zeros_like(g)
    g = g / top
    e = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)) / 8.0
    top = float(np.percentile(e, 99))
    return np.clip(e / top, 0.0, 1.0) if top > 0 else np.zeros_like(e)


def _scores(de: np.ndarray, ie: np.ndarray, r: int) -> np.ndarray:
    """Normalised cross-correlation of the depth edges moved by every (dx, dy) in ±r with the image edges.

    Over the whole frame (what a shift uncovers counts as no edge): silhouettes often run close to the border.
    """
    de = cv2.GaussianBlur(de, (0, 0), 1.0)
    b = cv2.GaussianBlur(ie, (0, 0), 1.0)
    b = b - b.mean()
    nb = float(np.sqrt((b * b).sum()))
    s = np.zeros((2 * r + 1, 2 * r + 1))
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            a = shift_image(de, dx, dy, 0.0)
            a = a - a.mean()
            na = float(np.sqrt((a * a).sum()))
            s[dy + r, dx + r] = float((a * b).sum()) / (na * nb) if na > 0 and nb > 0 else 0.0
    return s


@dataclass(frozen=True)
class Alignment:
    """What :func:`align_depth` found, for the capture set's notes."""

    shift: tuple[int, int]
    confidence: float
    checked: bool
    #: NCC at zero shift and at the best shift, and the median over all shifts
    score_zero: float = 0.0
    score_best: float = 0.0
    score_median: float = 0.0
    best: tuple[int, int] = (0, 0)
    reason: str = ""

    def notes(self) -> dict[str, object]:
        return {"checked": self.checked, "shift_px": list(self.shift), "confidence": round(self.confidence, 3),
                "best_shift_px": list(self.best), "ncc_zero": round(self.score_zero, 3),
                "ncc_best": round(self.score_best, 3), "ncc_median": round(self.score_median, 3),
                "reason": self.reason}


def find_alignment(depth: np.ndarray, reference_image: np.ndarray | Sequence[np.ndarray], *,
                   name: str = "the depth map", max_shift: int = MAX_SHIFT) -> Alignment:
    """Find the integer shift that puts the depth edges on the edges of the reference capture(s).

    ``reference_image`` is a capture that shows the surface's silhouette (the
    surface photograph, or white − black), or a list of candidates: the one whose
    edges match the depth edges best is used. Decision, on the normalised
    cross-correlation S of the two edge maps over all shifts:

    * too few depth edges, or no shift where S stands out from its median by
      ``MIN_PROMINENCE``: not checked (shift 0);
    * the zero shift loses less than ``MIN_GAIN`` of the peak's prominence: aligned;
    * otherwise the best shift is taken, unless it sits at the border of the search (misaligned by
      ``max_shift`` or more) or a separate peak comes within ``RUNNER_UP`` of it: then the evidence is
      ambiguous and a :class:`CaptureError` is raised.

    ``confidence`` is the prominence of the chosen shift's match, (S − median) / (1 − median), in [0, 1].
    """
    d = np.asarray(depth, dtype=np.float32)
    h, w = d.shape
    r = int(max_shift)
    refs = [reference_image] if isinstance(reference_image, np.ndarray) else list(reference_image)
    de = depth_edges(d)
    if (de > 0.5).mean() < MIN_EDGE_SHARE or min(h, w) <= 4 * r:
        return Alignment((0, 0), 0.0, False, reason="too few depth edges (or too small a map) to check alignment")
    best_s: np.ndarray | None = None
    for ref in refs:
        ie = image_edges(ref, (w, h))
        if not np.any(ie > 0):
            continue
        s = _scores(de, ie, r)
        if best_s is None or s.max() > best_s.max():
            best_s = s
    if best_s is None:
        return Alignment((0, 0), 0.0, False, reason="the reference captures show no edges")
    s = best_s
    peak, zero, med = float(s.max()), float(s[r, r]), float(np.median(s))
    iy, ix = np.unravel_index(int(np.argmax(s)), s.shape)
    best = (int(ix) - r, int(iy) - r)

    def result(shift: tuple[int, int], checked: bool, reason: str) -> Alignment:
        score = float(s[shift[1] + r, shift[0] + r])
        conf = float(np.clip((score - med) / max(1.0 - med, 1e-9), 0.0, 1.0)) if checked else 0.0
        return Alignment(shift, conf, checked, zero, peak, med, best, reason)

    prominence = peak - med
    if prominence < MIN_PROMINENCE:
        return result((0, 0), False, f"the depth edges match the photographs nowhere (NCC peak {peak:.2f}, "
                                     f"median {med:.2f})")
    gain = (peak - zero) / prominence
    if best == (0, 0) or gain < MIN_GAIN:
        return result((0, 0), True, f"aligned (zero shift within {gain:.0%} of the best match)")
    chosen = best
    if max(abs(best[0]), abs(best[1])) >= r:
        raise CaptureError(f"{name} does not line up with the photographs: its edges match best shifted by "
                           f"{best[0]:+d}, {best[1]:+d} px, the edge of the ±{r} px search, so it is misaligned by "
                           f"{r} px or more (or matches by chance). Register the depth to the colour camera (most "
                           "capture apps have an 'align depth to colour' option) and import again")
    # a separate peak (local maximum ≥ 2 px from the best) nearly as high: repetitive or unrelated edges
    dil = cv2.dilate(s.astype(np.float32), np.ones((3, 3), np.uint8))
    for y, x in zip(*np.nonzero((s >= dil) & (s >= med + RUNNER_UP * prominence))):
        other = (int(x) - r, int(y) - r)
        if max(abs(other[0] - best[0]), abs(other[1] - best[1])) >= 2:
            raise CaptureError(f"cannot tell how {name} lines up with the photographs: its edges match about as "
                               f"well shifted by {best[0]:+d}, {best[1]:+d} px as by {other[0]:+d}, {other[1]:+d} px. "
                               "Register the depth to the colour camera in the capture app (or pass a depth map "
                               "aligned with the photographs) and import again")
    return result(chosen, True, f"shifted by {chosen[0]:+d}, {chosen[1]:+d} px (zero shift loses {gain:.0%} "
                                f"of the edge match)")


def align_depth(depth: np.ndarray, reference_image: np.ndarray | Sequence[np.ndarray], *,
                name: str = "the depth map", max_shift: int = MAX_SHIFT
                ) -> tuple[np.ndarray, tuple[int, int], float]:
    """Detect and correct a depth map shifted against the photographs by a few pixels.

    Returns the depth moved by ``shift`` = (dx, dy) depth pixels (NaN where the
    shift uncovers the border; unchanged when (0, 0)), the shift, and the
    confidence of the match (see :func:`find_alignment`, which also says when
    the check could not be made). Ambiguous evidence raises a :class:`CaptureError`.
    """
    a = find_alignment(depth, reference_image, name=name, max_shift=max_shift)
    d = np.asarray(depth, dtype=np.float32)
    if a.shift != (0, 0):
        d = shift_image(d, a.shift[0], a.shift[1], np.nan)
    return d, a.shift, a.confidence


__all__ = ["Alignment", "DEPTH_UNITS", "DepthReading", "align_depth", "depth_edges", "find_alignment",
           "image_edges", "project_points", "read_depth", "read_ply_points", "shift_image"]
