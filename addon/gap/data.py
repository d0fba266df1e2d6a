"""What the diagnosis compares: captured patterns beside the calibrated model's renders of them.

For each pattern of the capture set that the diagnosis uses (black, white,
checkerboards, the coarser Gray-code bits, the validation patterns) this holds,
at a working resolution of the camera image:

* the capture (area-averaged down to the working size),
* ``direct``: the calibrated model ``f̂`` of the real input ``x`` (through the
  inverse warp, ``f̂(M(x))``), direct light only, as calibration uses it,
* ``indirect``: what three more bounces of light add to it,
* ``glossy``: renders with the surface replaced by a white GGX lobe at a few
  roughnesses (for the ``glossy`` effect model).

Effect models (``models.py``) act on the real input or on the camera image; to
evaluate them without re-rendering for every parameter value, this also holds the
model's *light path* per camera pixel: where in the real input the light that
reaches it comes from (``corr``, input pixels, pixel-centre convention of
``cv2.remap``), the gain ``f̂`` gives a white input there, the 3-D point and
depth. Direct light is (up to the projector pixel footprint) ``gain · x(corr)``,
so an input-side change ``x → g(x)`` changes the image by ``gain · (g(x) − x)(corr)``.
Where a working pixel spans more than two input texels (the default half
scale on a camera that already sees two texels a pixel), a projector blur's
change is measured on the input averaged over the pixel's footprint
(:func:`footprint_sigma`), as the capture's pixel averages it: read at one point,
a pattern finer than the pixel aliases, and a blur of about a texel hides in that.

Only the capture set and the calibration are read; never a lab truth file.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from ..capture.format import CaptureSet, Entry
from ..errors import Cancelled, ProCamError
from ..progress import Cancel, Progress, quiet
from ..render.forward import ForwardModel
from ..render.raycast import first_hits
from ..rig.model import square_scaled_size
from ..stages.calibrate import Calibration


#: Roughnesses (Blender convention, α = r²) of the glossy-lobe renders the ``glossy`` model interpolates.
GLOSSY_ROUGHNESS = (0.2, 0.4, 0.6)
#: Indirect bounces rendered for the ``interreflection`` model (most energy is in the first two).
INDIRECT_BOUNCES = 3
#: Gray-code bits whose stripes are narrower than this (input pixels) are left out: at the working
#: resolution they alias, and stage B has already used them.
MIN_STRIPE_PX = 8
#: A camera pixel is "lit" when a white input gives it at least this share of the brightest pixel.
LIT_SHARE = 0.08


class DiagnosisError(ProCamError):
    """The diagnosis cannot run on this calibration / capture set."""


@dataclass
class Observation:
    """One projected pattern: its real input, its capture and the model's renders (working resolution)."""

    name: str
    kind: str
    x: np.ndarray  # real projector input (input size, H×W×3, [0, 1])
    capture: np.ndarray  # h×w×3 linear
    direct: np.ndarray  # f̂(M(x)), direct light
    indirect: np.ndarray  # extra light of INDIRECT_BOUNCES bounces
    glossy: dict[float, np.ndarray]  # white GGX lobe renders by roughness
    sampled: np.ndarray  # x(corr): the input value on each camera pixel's light path
    edges: np.ndarray | None = None  # h×w bool: on an edge of the projected pattern (see fit.structured)
    #: x averaged over each pixel's footprint, then read at its light path (None where a pixel spans at most
    #: :data:`MAX_TEXELS_PER_PIXEL` texels): what a blur's change is measured against (``models.Composite``)
    averaged: np.ndarray | None = None
    #: a stack of several patterns' pixels (:meth:`GapData.stacked`): each part's input, in row order (``x`` is
    #: the first's); None for one pattern
    inputs: tuple[np.ndarray, ...] | None = None

    @property
    def fine(self) -> bool:
        """Binary patterns with sharp edges (checker, Gray code): where blur and misregistration show."""
        return self.kind in ("checker", "graycode")

    def on_pixels(self, pixels: np.ndarray) -> Observation:
        """This pattern at some working pixels only (:func:`column`); the input stays whole."""
        return replace(self, capture=column(self.capture, pixels), direct=column(self.direct, pixels),
                       indirect=column(self.indirect, pixels), sampled=column(self.sampled, pixels),
                       glossy={r: column(g, pixels) for r, g in self.glossy.items()},
                       edges=column(self.edges, pixels), averaged=column(self.averaged, pixels))


@dataclass
class GapData:
    """Everything the effect models and the residual analysis need; no truth."""

    observations: list[Observation]
    size: tuple[int, int]  # working (width, height)
    mask: np.ndarray  # h×w bool: lit by the projector and seen by the camera
    gain: np.ndarray  # h×w×3: f̂ of a white input
    corr: np.ndarray  # h×w×2 float32: real-input position (cv2.remap convention) of each camera pixel's light
    corr_per_metre: np.ndarray  # h×w×2: how ``corr`` moves when the surface point moves 1 m further along its ray
    points: np.ndarray  # h×w×3 rig-frame surface points (NaN where no surface)
    rays: np.ndarray  # h×w×3 unit camera rays
    crease: np.ndarray  # h×w float: how sharply the surface normal turns there (0 flat … 1 crease)
    projector: Any  # rig.model.Projector (calibrated)
    camera: Any  # rig.model.Intrinsics at the working size
    warp: Any
    fit_index: list[int] = field(default_factory=list)
    held_index: list[int] = field(default_factory=list)
    spans: float | None = None  # input texels a working pixel spans (:func:`texels_per_pixel`)
    report: dict[str, Any] = field(default_factory=dict)

    @property
    def footprint(self) -> float:
        """The Gaussian a blur's change is averaged by (:func:`footprint_sigma`; 0: none)."""
        return footprint_sigma(self.spans)

    @property
    def names(self) -> list[str]:
        return [o.name for o in self.observations]

    @property
    def white(self) -> Observation:
        """The white pattern: calibration estimated the albedo from it."""
        return next(o for o in self.observations if o.kind == "white")

    def on_pixels(self, pixels: np.ndarray) -> GapData:
        """These data at some working pixels only (flat indices into the working image), each a row of a
        one-pixel-wide image: what a fit's per-pixel models need, at a fraction of the whole image's cost.
        Anything spatial (smoothing, regions, a lens distortion) needs the whole image."""
        def col(a: np.ndarray) -> np.ndarray:
            return column(a, pixels)

        return replace(self, observations=[o.on_pixels(pixels) for o in self.observations], size=(1, len(pixels)),
                       mask=col(self.mask), gain=col(self.gain), corr=col(self.corr),
                       corr_per_metre=col(self.corr_per_metre), points=col(self.points), rays=col(self.rays),
                       crease=col(self.crease))

    def stacked(self, pixels: np.ndarray, index: list[int]) -> GapData:
        """The patterns ``index`` at the working pixels ``pixels`` as one observation (the second; the first is
        white, repeated to its length), its rows the pixels of the first pattern, then of the second…, each
        pixel's own data repeated as often: a fit predicts all its patterns in one call instead of one call a
        pattern (per-pixel models give row for row what :meth:`on_pixels` gives; measured on the demo's
        diagnosis: most of a fit's time was numpy's overhead on 8,000-pixel arrays, twelve times over)."""
        n = len(index)

        def col(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else column(a, pixels)

        def tile(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else np.concatenate([col(a)] * n)

        def cat(arrays: list[np.ndarray | None]) -> np.ndarray | None:
            return None if any(a is None for a in arrays) else np.concatenate([col(a) for a in arrays])

        parts = [self.observations[i] for i in index]
        w = self.white
        white = replace(w, capture=tile(w.capture), direct=tile(w.direct), indirect=tile(w.indirect),
                        sampled=tile(w.sampled), glossy={r: tile(g) for r, g in w.glossy.items()},
                        edges=tile(w.edges), averaged=tile(w.averaged))
        stack = Observation("+".join(o.name for o in parts), "stack", parts[0].x,
                            cat([o.capture for o in parts]), cat([o.direct for o in parts]),
                            cat([o.indirect for o in parts]),
                            {r: cat([o.glossy[r] for o in parts]) for r in parts[0].glossy},
                            cat([o.sampled for o in parts]), cat([o.edges for o in parts]),
                            cat([o.averaged for o in parts]), inputs=tuple(o.x for o in parts))
        return replace(self, observations=[white, stack], size=(1, n * len(pixels)), mask=tile(self.mask),
                       gain=tile(self.gain), corr=tile(self.corr), corr_per_metre=tile(self.corr_per_metre),
                       points=tile(self.points), rays=tile(self.rays), crease=tile(self.crease), fit_index=[1],
                       held_index=[])


def column(a: np.ndarray | None, pixels: np.ndarray) -> np.ndarray | None:
    """A per-pixel image (h×w or h×w×c) at the flat indices ``pixels``, as a one-pixel-wide image (n×1[×c])."""
    if a is None:
        return None
    h, w = a.shape[:2]
    return a.reshape(h * w, 1, *a.shape[2:])[pixels]


def _run_lengths(row: np.ndarray) -> int:
    """Shortest run of equal values along a 1-D binary signal (the stripe width)."""
    edges = np.flatnonzero(np.diff(row > 0.5)) + 1
    runs = np.diff(np.concatenate([[0], edges, [len(row)]]))
    return int(runs.min()) if len(runs) else len(row)


def choose_entries(captures: CaptureSet, input_of: Callable[[Entry], np.ndarray]) -> list[Entry]:
    """The patterns the diagnosis uses, in a fixed order: black, white, checkers, Gray code, validation."""
    chosen: list[Entry] = []
    for kind in ("black", "white", "checker"):
        chosen += captures.entries_of(kind)
    for e in captures.entries_of("graycode"):
        if e.params.get("inverted"):
            continue
        x = input_of(e)[..., 0]
        line = x[x.shape[0] // 2] if e.params.get("axis") == "x" else x[:, x.shape[1] // 2]
        if _run_lengths(line) >= MIN_STRIPE_PX:
            chosen.append(e)
    validation = captures.entries_of("validation")
    if not validation and not any(e.kind in ("checker", "graycode") for e in chosen):
        raise DiagnosisError(
            f"the capture set {captures.path} has no validation, checkerboard or Gray-code captures; the diagnosis "
            "needs patterns to test the model on that calibration did not fit: recapture with validation patterns "
            "(procam lab does by default; for a real session `procam patterns` exports them: grey levels "
            "0.25/0.5/0.75, red/green/blue ramps and smooth random images)")
    return chosen + validation


#: Effects only grey levels show: on black-and-white patterns they act at stripe edges alone, where a blur fits too.
LEVEL_EFFECTS = ("response", "camera_response")
#: What the diagnosis says when a capture set has no validation patterns (OpenCV's sequence: Gray code, white, black).
NO_VALIDATION = ("the capture set has no validation patterns (grey levels, colour ramps, smooth random images): every "
                 "other Gray-code or checkerboard pattern is held out instead. Those are black and white, so the "
                 f"effects only grey levels show ({', '.join(LEVEL_EFFECTS)}) are not tested, and colour mixing is "
                 "tested on white light only; capture the validation patterns (procam patterns) to test them")


def split_patterns(observations: list[Observation]) -> tuple[list[int], list[int]]:
    """Fit / held-out split: alternate within each kind so both halves see every kind of pattern.

    Black and white go to the fit half (calibration already used them); each
    kind's patterns alternate, starting on the held-out side for validation.
    """
    fit: list[int] = []
    held: list[int] = []
    by_kind: dict[str, list[int]] = {}
    for i, o in enumerate(observations):
        by_kind.setdefault(o.kind, []).append(i)
    for kind, idx in by_kind.items():
        if kind in ("black", "white"):
            fit += idx
            continue
        start = 1 if kind == "validation" else 0
        for j, i in enumerate(idx):
            (fit if (j + start) % 2 == 0 else held).append(i)
    if not held or not fit:
        raise DiagnosisError("too few patterns to hold some out: the capture set needs at least two validation "
                             "captures")
    return sorted(fit), sorted(held)


def _downsize(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    if image.shape[1] == size[0] and image.shape[0] == size[1]:
        return np.asarray(image, np.float32)
    return cv2.resize(np.asarray(image, np.float32), size, interpolation=cv2.INTER_AREA)


def _check_levels(captures: CaptureSet) -> None:
    white, black = captures.image("white"), captures.image("black")
    if float(np.mean(white >= 0.999)) > 0.25:
        raise DiagnosisError(f"the white capture of {captures.path} is saturated on {np.mean(white >= 0.999):.0%} of "
                             "the image: recapture with a shorter exposure (the diagnosis compares light levels)")
    if float(np.percentile(white - black, 99)) < 0.02:
        raise DiagnosisError(f"the white capture of {captures.path} is hardly brighter than the black one: the "
                             "captures are all dark (projector off or lens cap on?); recapture")


#: Half-width of the window over which a crease turns the normal, as a share of the working image width.
CREASE_REACH = 0.015


def _crease_map(points: np.ndarray) -> np.ndarray:
    """0 on flat surface … 1 where the normal turns by ≥ 30° across a short reach (``CREASE_REACH``).

    Normals are taken over that reach and averaged over a window of it, then compared at either side: a
    reconstructed mesh rounds a crease over a few pixels and carries bumps of a pixel or two, so normals from
    neighbouring pixels compared with their 2-px blur (as before) read the crease of the lab's reconstructed
    V edge as a turn of at most 2–6° (0.07–0.21 on this map), and no crease was ever named on reconstructed
    geometry; this way it reads 19–24° (0.62 on the lab's V edge, 0.81 on the demo's), 0 on the plane.
    """
    valid = np.isfinite(points[..., 2])
    h, w = valid.shape
    d = max(2, round(CREASE_REACH * w))
    # Off the surface, repeat the surface's median point; erosion below keeps the silhouette out.
    p = np.where(valid[..., None], points, np.nanmedian(points[valid], axis=0) if valid.any() else 0.0)
    p = p.astype(np.float32)
    dx = np.zeros_like(p)
    dy = np.zeros_like(p)
    dx[:, d:-d] = p[:, 2 * d:] - p[:, :-2 * d]
    dy[d:-d] = p[2 * d:] - p[:-2 * d]
    n = np.cross(dx, dy)
    n /= np.maximum(np.linalg.norm(n, axis=2, keepdims=True), 1e-12)
    n = cv2.blur(n, (2 * d + 1, 2 * d + 1))
    n /= np.maximum(np.linalg.norm(n, axis=2, keepdims=True), 1e-12)
    pad = cv2.copyMakeBorder(n, d, d, d, d, cv2.BORDER_REPLICATE)
    turn = np.zeros((h, w), np.float32)
    for oy, ox in ((0, d), (d, 0), (d, d), (d, -d)):
        a = pad[d + oy:d + oy + h, d + ox:d + ox + w]
        b = pad[d - oy:d - oy + h, d - ox:d - ox + w]
        turn = np.maximum(turn, np.degrees(np.arccos(np.clip((a * b).sum(axis=2), -1.0, 1.0))))
    turn[cv2.erode(valid.astype(np.uint8), np.ones((4 * d + 3, 4 * d + 3), np.uint8)) == 0] = 0.0
    return np.clip(turn / 30.0, 0.0, 1.0).astype(np.float32)


def _input_position(calibration: Any, points: np.ndarray) -> np.ndarray:
    """Real-input position (corner convention, input pixels) of the light reaching rig-frame points."""
    proj = calibration.rig.projector
    uv = np.full((len(points), 2), np.nan)
    ok = np.all(np.isfinite(points), axis=1)
    uv[ok] = proj.project(points[ok])
    uv -= np.asarray(proj.input_offset, float)  # frame → input pixels
    if calibration.warp is not None:
        # The model shows z = M(x): its input pixel u carries the real input at φ_M(u).
        good = np.all(np.isfinite(uv), axis=1)
        uv[good] = calibration.warp.map_m(uv[good], proj.input_size)
    return uv


def light_paths(calibration: Any, camera: Any
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per working-size camera pixel: real-input position (remap convention), its change per metre of
    depth along the ray, 3-D point, unit ray, and whether the pixel's light comes from the input."""

    w, h = camera.size
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    rays = camera.rays(np.stack([xs.ravel(), ys.ravel()], axis=1))
    t = first_hits(calibration.surface, np.zeros(3), rays)
    points = rays * t[:, None]
    unit = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    uv = _input_position(calibration, points)
    step = 0.005  # metres: small against the surface's size, large against float error
    per_metre = (_input_position(calibration, points + unit * step) - uv) / step
    iw, ih = calibration.rig.projector.input_size
    inside = np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= 0) & (uv[:, 0] <= iw) & (uv[:, 1] >= 0) & (uv[:, 1] <= ih)
    inside &= np.all(np.isfinite(per_metre), axis=1)
    corr = np.where(inside[:, None], uv - 0.5, -10.0).astype(np.float32).reshape(h, w, 2)
    per_metre = np.where(inside[:, None], per_metre, 0.0).astype(np.float32).reshape(h, w, 2)
    return (corr, per_metre, points.reshape(h, w, 3).astype(np.float32), unit.reshape(h, w, 3).astype(np.float32),
            inside.reshape(h, w))


def pattern_edges(sampled: np.ndarray, step: float = 0.15) -> np.ndarray:
    """Camera pixels within a pixel of an edge of the projected pattern (input step ≥ ``step`` per pixel)."""
    level = sampled.mean(axis=2).astype(np.float32)
    g = np.hypot(cv2.Sobel(level, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(level, cv2.CV_32F, 0, 1, ksize=3)) / 4
    return cv2.dilate((g >= step).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0


#: Input texels a working pixel may span and still measure a blur's change at its light path's centre: beyond,
#: it is measured on the input averaged over the pixel's footprint (:func:`footprint_sigma`), and the diagnosis
#: warns when no blur was found all the same. At 3.5 texels a pixel, measured at centres, the lab's blur alone
#: was named glossy on three surfaces of four (named defocus with the footprint); among the realistic preset's
#: ten other effects on the plane it is missed at 3.5 either way and found at 1.8.
MAX_TEXELS_PER_PIXEL = 2.0


def texels_per_pixel(corr: np.ndarray, mask: np.ndarray) -> float | None:
    """How many projector input texels one working pixel spans, across (the median over the lit pixels of the
    square root of ``corr``'s local Jacobian determinant); None with fewer than 16 lit pixels in a 2×2 block."""
    c = np.asarray(corr, np.float64)
    ok = mask & (c[..., 0] > -5)  # positions off the input are marked −10
    both = ok[:-1, :-1] & ok[:-1, 1:] & ok[1:, :-1]
    if int(both.sum()) < 16:
        return None
    dx = (c[:-1, 1:] - c[:-1, :-1])[both]
    dy = (c[1:, :-1] - c[:-1, :-1])[both]
    return float(np.median(np.sqrt(np.abs(dx[:, 0] * dy[:, 1] - dx[:, 1] * dy[:, 0]))))


def footprint_sigma(spans: float | None) -> float:
    """The Gaussian (input texels) that averages the input over a working pixel's footprint before a blur's
    change is read at the pixel's light path, when the pixel spans more than :data:`MAX_TEXELS_PER_PIXEL` texels
    (0 otherwise): a box of ``spans`` texels, less what the bilinear lookup averages itself."""
    if spans is None or spans <= MAX_TEXELS_PER_PIXEL:
        return 0.0
    return float(np.sqrt(spans * spans / 12.0 - 1.0 / 6.0))


def sample_pattern(obs: Observation, corr: np.ndarray, footprint: float = 0.0, blur: float = 0.0) -> np.ndarray:
    """:func:`sample_input` of a pattern's input blurred by ``blur`` texels (0: none); of a stack of patterns
    (:meth:`GapData.stacked`), each part's rows read its own input."""
    inputs = obs.inputs if obs.inputs is not None else (obs.x,)
    rows = corr.shape[0] // len(inputs)
    out = [sample_input(cv2.GaussianBlur(x, (0, 0), blur) if blur > 0 else x, corr[k * rows:(k + 1) * rows],
                        footprint) for k, x in enumerate(inputs)]
    return out[0] if len(out) == 1 else np.concatenate(out)


def sample_input(x: np.ndarray, corr: np.ndarray, footprint: float = 0.0) -> np.ndarray:
    """The input image's value at each camera pixel's light path (bilinear; black off the input), averaged over
    the pixel's ``footprint`` first (:func:`footprint_sigma`)."""
    x = np.asarray(x, np.float32)
    if footprint > 0:
        x = cv2.GaussianBlur(x, (0, 0), footprint, borderType=cv2.BORDER_CONSTANT)
    return cv2.remap(x, corr[..., 0], corr[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def load_gap_data(cal: Calibration, captures: CaptureSet, *, source: str = "", scale: float = 0.5, spp: int = 32,
                  seed: int = 0, progress: Progress | None = None, cancel: Cancel | None = None) -> GapData:
    """Render the model of every pattern of the calibration's capture set that the diagnosis uses.

    ``source`` names the calibration in the report (its folder)."""
    say = progress or quiet
    _check_levels(captures)
    proj = cal.rig.projector
    x0, y0 = proj.input_offset
    iw, ih = proj.input_size

    def input_of(e: Entry) -> np.ndarray:
        frame = captures.pattern(e.kind, name=e.name)
        if frame.shape[:2] != (proj.intrinsics.height, proj.intrinsics.width):
            raise DiagnosisError(f"pattern {e.name} is {frame.shape[1]}×{frame.shape[0]}, the calibrated projector "
                                 f"{proj.intrinsics.width}×{proj.intrinsics.height}: wrong calibration for this set?")
        return np.clip(frame[y0:y0 + ih, x0:x0 + iw], 0.0, 1.0).astype(np.float32)

    entries = choose_entries(captures, input_of)
    cw, ch = cal.rig.camera.intrinsics.size
    size = square_scaled_size(cw, ch, scale, minimum=(16, 12))
    camera = cal.rig.camera.intrinsics.scaled(*size)
    say("light paths", 0.0)
    corr, per_metre, points, rays, inside = light_paths(cal, camera)

    def model(**kw: Any) -> ForwardModel:
        return ForwardModel(cal.rig, cal.surface, camera_size=size, smoothing_eps=0.0, clamp=False, seed=seed,
                            **{"spp": spp, **kw})

    direct_model = model()
    warp_m = (lambda x: x) if cal.warp is None else (lambda x: np.clip(cal.warp.apply_m(x), 0, 1))
    gain = direct_model.render_input(np.ones((ih, iw, 3), np.float32), spp=4 * spp)
    mask = inside & (gain.mean(axis=2) > LIT_SHARE * float(np.percentile(gain.mean(axis=2), 99.5)))
    if mask.sum() < 100:
        raise DiagnosisError("the calibrated projector lights fewer than 100 camera pixels at the working "
                             "resolution: check the calibration (procam calibrate) or use a larger --scale")
    spans = texels_per_pixel(corr, mask)
    footprint = footprint_sigma(spans)
    # Indirect light as the difference of two path tracers that share their random numbers, so the direct
    # part (and its noise) cancels; it is smooth, so more samples and a light blur keep its noise small.
    indirect_model = model(bounces=INDIRECT_BOUNCES, integrator="prb", spp=2 * spp)
    # The direct-light integrator draws the same camera rays from the same seed, and a delta projector's light
    # along them is the path tracer's first bounce exactly (checked: the two renders are equal, bit for bit), in
    # less than half the time.
    direct_prb = model(spp=2 * spp)
    glossy_models = {r: model(glossy_roughness=r) for r in GLOSSY_ROUGHNESS}
    observations: list[Observation] = []
    for i, e in enumerate(entries):
        if cancel is not None and cancel():
            raise Cancelled("diagnosis cancelled")
        say(f"rendering pattern {i + 1}/{len(entries)}: {e.name}", 0.05 + 0.9 * i / len(entries))
        x = input_of(e)
        z = warp_m(x)
        s = 1000 + 10 * i
        if float(z.max()) > 0:
            direct = direct_model.render_input(z, seed=s)
            extra = indirect_model.render_input(z, seed=s + 1) - direct_prb.render_input(z, seed=s + 1)
            indirect = cv2.GaussianBlur(extra, (0, 0), 1.0)
            glossy = {r: m.render_input(z, seed=s + 2 + j) for j, (r, m) in enumerate(glossy_models.items())}
        else:  # a black input: the projector is the only light, so every render is black
            direct = indirect = np.zeros((size[1], size[0], 3), np.float32)
            glossy = dict.fromkeys(glossy_models, direct)
        capture = _downsize(captures.image(e.kind, name=e.name), size)
        sampled = sample_input(x, corr)
        observations.append(Observation(e.name, e.kind, x, capture, direct, indirect, glossy, sampled,
                                        pattern_edges(sampled),
                                        sample_input(x, corr, footprint) if footprint > 0 else None))
    fit, held = split_patterns(observations)
    return GapData(observations, size, mask, gain, corr, per_metre, points, rays, _crease_map(points), proj, camera,
                   cal.warp, fit, held, spans, report={"calibration": source,
                                      "capture_set": str(captures.path), "working_size": list(size), "spp": spp,
                                      "patterns": [o.name for o in observations],
                                      "validation": any(o.kind == "validation" for o in observations)})
