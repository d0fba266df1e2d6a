"""Projector patterns for a capture session, and Gray-code decoding.

Every pattern is a float32 H×W×3 image in [0, 1] at a given ``size =
(width, height)``: either the projector input size (the paper's 600×600) or
the native frame. :func:`calibration_sequence` places each one into the native
projector frame (``Projector.frame_from_input``), because that is what a
device shows, and lists them in a fixed order:

    surface (projector off) · black · white · checkerboard(s) ·
    Gray code (x bits, then y bits, each followed by its inverse) · validation ·
    white again (``val_white_end``)

The closing white repeats the opening one at the session's end: the diagnosis
compares the two to tell whether the light drifted (a projector warming up) or
the surface or camera moved during the session (``addon/gap/session.py``).

Gray code comes from OpenCV's ``structured_light.GrayCodePattern`` so the bit
order and code are OpenCV's: images ``2k``/``2k+1`` are column bit ``k`` and
its inverse (bit 0 = most significant), then the row bits. Decoding is a
vectorised numpy version of ``GrayCodePattern.getProjPixel`` (which works one
pixel at a time) and is checked against it in the tests.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from ..errors import CaptureError
from ..rig.model import Projector

if TYPE_CHECKING:
    from .format import CaptureSet

Size = tuple[int, int]

#: Defaults of the validation set: enough levels to see a response curve, one ramp per channel, a few textures.
GREY_LEVELS = (0.25, 0.5, 0.75)
RAMP_CHANNELS = ("r", "g", "b")
RANDOM_COUNT = 2
#: The session's last capture: white again (a validation pattern, and the end of the session-stability check).
CLOSING_WHITE = "val_white_end"
_CHANNEL = {"r": 0, "g": 1, "b": 2}


def _check_size(size: Size) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise CaptureError(f"pattern size must be (width, height), got {size!r}") from None
    if w <= 0 or h <= 0:
        raise CaptureError(f"pattern size must be positive, got {w}×{h}")
    return w, h


def _rgb(grey: np.ndarray) -> np.ndarray:
    return np.repeat(np.asarray(grey, dtype=np.float32)[..., None], 3, axis=2)


def flat(size: Size, value: float | Sequence[float]) -> np.ndarray:
    """A uniform image of one grey level or one RGB colour."""
    w, h = _check_size(size)
    v = np.broadcast_to(np.asarray(value, dtype=np.float32), (3,))
    if np.any(v < 0) or np.any(v > 1):
        raise CaptureError(f"pattern values must lie in [0, 1], got {value!r}")
    return np.ascontiguousarray(np.broadcast_to(v, (h, w, 3)), dtype=np.float32)


def white(size: Size) -> np.ndarray:
    return flat(size, 1.0)


def black(size: Size) -> np.ndarray:
    return flat(size, 0.0)


def checkerboard(size: Size, square: int, phase: int = 0) -> np.ndarray:
    """Squares of ``square`` pixels from the top-left corner; the top-left square is black for phase 0."""
    w, h = _check_size(size)
    if not isinstance(square, (int, np.integer)) or square <= 0:
        raise CaptureError(f"checkerboard square size must be a positive number of pixels, got {square!r}")
    if phase not in (0, 1):
        raise CaptureError(f"checkerboard phase must be 0 or 1, got {phase!r}")
    y, x = np.mgrid[0:h, 0:w]
    return _rgb(((x // square + y // square + phase) % 2).astype(np.float32))


def default_checker_size(size: Size) -> int:
    """About 12 squares across the shorter side (50 px for the paper's 600×600 input)."""
    return max(4, round(min(_check_size(size)) / 12))


# -- Gray code -----------------------------------------------------------------------------------

def gray_code_bits(size: Size) -> tuple[int, int]:
    """Bits per axis (columns, rows), as OpenCV counts them: ceil(log2(width)), ceil(log2(height))."""
    w, h = _check_size(size)
    return (math.ceil(math.log2(w)) if w > 1 else 0, math.ceil(math.log2(h)) if h > 1 else 0)


@functools.lru_cache(maxsize=4)
def _gray_code_stack(w: int, h: int) -> np.ndarray:
    # Cached as uint8 (N×H×W): 40 images at 600×600 are 14 MB; float copies are made per use.
    if w < 2 or h < 2:
        raise CaptureError(f"Gray code needs a pattern of at least 2×2 pixels, got {w}×{h}")
    gen = cv2.structured_light.GrayCodePattern_create(w, h)
    ok, images = gen.generate()
    if not ok:
        raise CaptureError(f"OpenCV could not generate Gray-code patterns for {w}×{h}")
    stack = np.stack(images)
    stack.setflags(write=False)
    return stack


def gray_code_layout(size: Size) -> list[tuple[str, int, bool]]:
    """(axis, bit, inverted) of each Gray-code image, in OpenCV's order."""
    nx, ny = gray_code_bits(size)
    return ([("x", b, inv) for b in range(nx) for inv in (False, True)]
            + [("y", b, inv) for b in range(ny) for inv in (False, True)])


def gray_code_pattern(size: Size, axis: str, bit: int, inverted: bool) -> np.ndarray:
    """One Gray-code image (float32 H×W×3, 0 or 1)."""
    layout = gray_code_layout(size)
    try:
        i = layout.index((axis, int(bit), bool(inverted)))
    except ValueError:
        nx, ny = gray_code_bits(size)
        raise CaptureError(f"no Gray-code image axis={axis!r} bit={bit} for {size[0]}×{size[1]} "
                           f"({nx} x bits, {ny} y bits)") from None
    return _rgb(_gray_code_stack(*_check_size(size))[i].astype(np.float32) / 255.0)


def gray_code_patterns(size: Size) -> list[tuple[str, int, bool, np.ndarray]]:
    """All Gray-code images in OpenCV's order as (axis, bit, inverted, image)."""
    stack = _gray_code_stack(*_check_size(size))
    return [(a, b, inv, _rgb(stack[i].astype(np.float32) / 255.0))
            for i, (a, b, inv) in enumerate(gray_code_layout(size))]


@dataclass(frozen=True)
class GrayCodeDecoding:
    """Per camera pixel: the projector pixel it sees.

    ``coords`` (H×W×2, float32) are projector positions (x, y) of the pixel
    *centres* in the corner convention of ``rig.model`` (integer index + 0.5),
    plus ``offset`` (where the coded grid sits in the native frame); NaN where
    ``valid`` is False. The Gray code resolves whole projector pixels, so the
    error against the true mapping is at most half a pixel per axis.
    """

    coords: np.ndarray
    valid: np.ndarray
    grid_size: tuple[int, int]
    offset: tuple[int, int] = (0, 0)


def _grey(img: np.ndarray) -> np.ndarray:
    a = np.asarray(img, dtype=np.float32)
    return a.mean(axis=2) if a.ndim == 3 else a


def decode_gray_code(captures: Sequence[np.ndarray], size: Size, *, white_capture: np.ndarray | None = None,
                     black_capture: np.ndarray | None = None, black_threshold: float = 0.02,
                     white_threshold: float = 0.004, offset: tuple[int, int] = (0, 0)) -> GrayCodeDecoding:
    """Decode captured Gray-code images (OpenCV order, each followed by its inverse) into projector coordinates.

    A pixel is valid when every bit pair differs by at least
    ``white_threshold`` (OpenCV's "white threshold", here in linear [0, 1]
    units), the decoded position lies inside the coded grid, and, when white
    and black captures are given, white − black exceeds ``black_threshold``
    (OpenCV's shadow mask).
    """
    w, h = _check_size(size)
    layout = gray_code_layout((w, h))
    if len(captures) != len(layout):
        raise CaptureError(f"Gray-code decoding for {w}×{h} needs {len(layout)} captures "
                           f"(each bit and its inverse), got {len(captures)}")
    grey = [_grey(c) for c in captures]
    shape = grey[0].shape
    if any(g.shape != shape for g in grey):
        raise CaptureError("Gray-code captures differ in size")
    nx, _ = gray_code_bits((w, h))
    error = np.zeros(shape, dtype=bool)

    def axis_value(first: int, nbits: int) -> np.ndarray:
        nonlocal error
        value = np.zeros(shape, dtype=np.int64)
        binary = np.zeros(shape, dtype=bool)
        for k in range(nbits):
            pos, neg = grey[first + 2 * k], grey[first + 2 * k + 1]
            error |= np.abs(pos - neg) < white_threshold
            # Gray → binary: b_k = b_{k-1} xor g_k, most significant bit first (OpenCV's grayToDec).
            binary = binary ^ (pos > neg)
            value = (value << 1) | binary
        return value

    xs = axis_value(0, nx)
    ys = axis_value(2 * nx, len(layout) // 2 - nx)
    valid = ~error & (xs < w) & (ys < h)
    if white_capture is not None and black_capture is not None:
        valid &= (_grey(white_capture) - _grey(black_capture)) > black_threshold
    coords = np.stack([xs + 0.5 + offset[0], ys + 0.5 + offset[1]], axis=-1).astype(np.float32)
    coords[~valid] = np.nan
    return GrayCodeDecoding(coords, valid, (w, h), (int(offset[0]), int(offset[1])))


def decode_gray_code_set(captures: CaptureSet, **thresholds: Any) -> GrayCodeDecoding:
    """Decode the Gray-code images of a capture set into native projector-frame coordinates.

    The latest decoding is kept (read-only arrays), keyed by the Gray-code, white and black files' paths, sizes
    and times, the coded area and the thresholds: one calibration decodes the same set for the surface, the
    Gray-code warp and the pose evidence, through capture-set objects that differ only in their camera or
    projector model, and reading and decoding a real 1280×1024 session's 44 images costs seconds each time.
    """
    entries = captures.entries_of("graycode")
    if not entries:
        raise CaptureError(f"capture set {captures.path} holds no Gray-code images")
    areas = {e.params.get("area", "input") for e in entries}
    if len(areas) != 1:
        raise CaptureError(f"capture set {captures.path}: Gray-code images mix areas {sorted(areas)}")
    area = areas.pop()
    whites, blacks = captures.entries_of("white"), captures.entries_of("black")
    levels = whites[:1] + blacks[:1] if whites and blacks else []
    proj = captures.projector
    size = proj.input_size if area == "input" else proj.intrinsics.size
    offset = proj.input_offset if area == "input" else (0, 0)
    key = (tuple(_file_stamp(captures.file(e)) for e in entries + levels), tuple(size), tuple(offset),
           tuple(sorted(thresholds.items())))
    kept = _LATEST_DECODING.get(key)
    if kept is not None:
        return kept
    images = [captures.image("graycode", axis=a, bit=b, inverted=inv) for a, b, inv in gray_code_layout(size)]
    extra: dict[str, np.ndarray] = {}
    if levels:
        extra = {"white_capture": captures.image("white"), "black_capture": captures.image("black")}
    dec = decode_gray_code(images, size, offset=offset, **extra, **thresholds)
    dec.coords.flags.writeable = False
    dec.valid.flags.writeable = False
    _LATEST_DECODING.clear()
    _LATEST_DECODING[key] = dec
    return dec


_LATEST_DECODING: dict[Any, GrayCodeDecoding] = {}


def _file_stamp(path: Path) -> tuple[str, int, int]:
    try:
        st = path.stat()
    except OSError:  # reading it will say what is wrong
        return str(path.absolute()), -1, -1
    return str(path.absolute()), st.st_size, st.st_mtime_ns


# -- validation patterns -------------------------------------------------------------------------

def refine_corners(pattern: np.ndarray, guesses: np.ndarray, window: int) -> np.ndarray:
    """Sub-pixel corners (N×2, corner convention) of a grey H×W ``pattern`` near ``guesses`` (N×2),
    with OpenCV's ``cornerSubPix`` and a (2·window+1)² search window."""
    pts = guesses.astype(np.float32).reshape(-1, 1, 2) - 0.5  # OpenCV: pixel centres on integers
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    out = cv2.cornerSubPix(np.ascontiguousarray(pattern, dtype=np.float32), pts, (window, window), (-1, -1), crit)
    return out.reshape(-1, 2).astype(np.float64) + 0.5


def colour_ramp(size: Size, channel: str = "r", axis: str = "x") -> np.ndarray:
    """A ramp from 0 to 1 along ``axis`` in one channel (``r``, ``g``, ``b``) or all (``grey``)."""
    w, h = _check_size(size)
    if axis not in ("x", "y"):
        raise CaptureError(f"ramp axis must be 'x' or 'y', got {axis!r}")
    n = w if axis == "x" else h
    ramp = (np.arange(n, dtype=np.float32) + 0.5) / n
    plane = np.broadcast_to(ramp[None, :] if axis == "x" else ramp[:, None], (h, w))
    if channel == "grey":
        return _rgb(plane)
    if channel not in _CHANNEL:
        raise CaptureError(f"ramp channel must be r, g, b or grey, got {channel!r}")
    img = np.zeros((h, w, 3), dtype=np.float32)
    img[..., _CHANNEL[channel]] = plane
    return img


def smooth_random(size: Size, seed: int, scale: float = 32.0) -> np.ndarray:
    """Smooth random colours (features about ``scale`` px), in [0.05, 0.95]; the same seed gives the same image."""
    w, h = _check_size(size)
    if not scale > 0:
        raise CaptureError(f"random-pattern scale must be positive, got {scale}")
    rng = np.random.default_rng(int(seed))
    gw, gh = math.ceil(w / scale) + 3, math.ceil(h / scale) + 3
    coarse = rng.random((gh, gw, 3), dtype=np.float32)
    # Bicubic upsampling of a coarse grid: smooth, deterministic, and no FFT wrap-around at the borders.
    fine = cv2.resize(coarse, (round(gw * scale), round(gh * scale)), interpolation=cv2.INTER_CUBIC)
    y0, x0 = round(scale), round(scale)
    fine = fine[y0:y0 + h, x0:x0 + w]
    return (0.05 + 0.9 * np.clip(fine, 0.0, 1.0)).astype(np.float32)


def _validation_specs(size: Size, seed: int, grey_levels: Sequence[float], ramp_channels: Sequence[str],
                      random_count: int, random_scale: float
                      ) -> list[tuple[str, dict[str, Any], Callable[[], np.ndarray]]]:
    out: list[tuple[str, dict[str, Any], Callable[[], np.ndarray]]] = []
    for level in grey_levels:
        out.append((f"val_grey_{level:.3f}".rstrip("0").rstrip("."), {"pattern": "grey", "level": float(level)},
                    functools.partial(flat, size, float(level))))
    for ch in ramp_channels:
        out.append((f"val_ramp_{ch}", {"pattern": "ramp", "channel": ch, "axis": "x"},
                    functools.partial(colour_ramp, size, ch, "x")))
    for i in range(random_count):
        s = int(seed) + i
        out.append((f"val_random_{s}", {"pattern": "random", "seed": s, "scale": float(random_scale)},
                    functools.partial(smooth_random, size, s, float(random_scale))))
    return out


def validation_patterns(size: Size, *, seed: int = 0, grey_levels: Sequence[float] = GREY_LEVELS,
                        ramp_channels: Sequence[str] = RAMP_CHANNELS, random_count: int = RANDOM_COUNT,
                        random_scale: float = 32.0) -> list[tuple[str, dict[str, Any], np.ndarray]]:
    """Held-out patterns for the sim-to-real diagnosis: (name, params, image)."""
    return [(name, params, make()) for name, params, make in
            _validation_specs(size, seed, grey_levels, ramp_channels, random_count, random_scale)]


# -- the calibration sequence --------------------------------------------------------------------

@dataclass(frozen=True)
class PatternSpec:
    """One step of a capture session: what to show (the native frame, built on demand) and how to label it."""

    name: str
    kind: str
    params: dict[str, Any]
    render: Callable[[], np.ndarray] = field(repr=False, compare=False)

    @property
    def image(self) -> np.ndarray:
        """The native projector frame (float32 H×W×3); built each time so a long list stays small."""
        return self.render()

    @property
    def projector_off(self) -> bool:
        return self.kind == "surface"


#: Pattern orders: ProCam's own, and OpenCV's structured-light session (Gray code, white, black).
LAYOUTS = ("procam", "opencv")


def calibration_sequence(projector: Projector, checker_size: int | None = None, *, area: str = "input",
                         checker_phases: Sequence[int] = (0, 1), graycode: bool = True,
                         validation: bool = True, seed: int = 0, grey_levels: Sequence[float] = GREY_LEVELS,
                         ramp_channels: Sequence[str] = RAMP_CHANNELS,
                         random_count: int = RANDOM_COUNT, layout: str = "procam") -> list[PatternSpec]:
    """The patterns of a calibration session, in a fixed order, as native projector frames.

    ``area="input"`` draws every pattern inside the projector input rectangle
    (the rest of the frame stays black, as during compensation); ``"frame"``
    uses the whole native frame. ``surface`` means the projector is off; a
    device that cannot switch it off shows the (black) frame instead.
    ``layout="opencv"``: OpenCV's structured-light session instead (its
    ``GrayCodePattern`` frames, which are ours, then white, then black; no
    surface photo, no checkerboard), the order of ``procam calibrate-rig``'s
    board sessions and of many existing captures, then the validation patterns
    if asked for.
    """
    if area not in ("input", "frame"):
        raise CaptureError(f"pattern area must be 'input' or 'frame', got {area!r}")
    if layout not in LAYOUTS:
        raise CaptureError(f"pattern layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    size = projector.input_size if area == "input" else projector.intrinsics.size
    frame_size = projector.intrinsics.size
    checker_size = default_checker_size(size) if checker_size is None else checker_size
    if not isinstance(checker_size, (int, np.integer)) or checker_size <= 0 or checker_size > min(size):
        raise CaptureError(f"checker size must be a whole number of pixels between 1 and {min(size)}, "
                           f"got {checker_size!r}")

    def place(make: Callable[[], np.ndarray]) -> Callable[[], np.ndarray]:
        if area == "frame":
            return make
        return lambda: projector.frame_from_input(make())

    base = {"area": area}
    dark = PatternSpec("black", "black", dict(base), place(lambda: black(size)))
    light = PatternSpec("white", "white", dict(base), place(lambda: white(size)))
    seq = [] if layout == "opencv" else [
        PatternSpec("surface", "surface", {"projector": "off"}, lambda: black(frame_size)), dark, light]
    for ph in checker_phases if layout == "procam" else ():
        seq.append(PatternSpec(f"checker_s{checker_size}_p{ph}", "checker",
                               {**base, "square": int(checker_size), "phase": int(ph)},
                               place(functools.partial(checkerboard, size, int(checker_size), int(ph)))))
    if graycode:
        nx, ny = gray_code_bits(size)
        for axis, bit, inv in gray_code_layout(size):
            seq.append(PatternSpec(f"graycode_{axis}{bit:02d}" + ("_inv" if inv else ""), "graycode",
                                   {**base, "axis": axis, "bit": bit, "inverted": inv,
                                    "bits": nx if axis == "x" else ny, "grid": [int(size[0]), int(size[1])]},
                                   place(functools.partial(gray_code_pattern, size, axis, bit, inv))))
    if layout == "opencv":
        seq += [light, dark]
    if validation:
        for name, params, make in _validation_specs(size, seed, grey_levels, ramp_channels, random_count, 32.0):
            seq.append(PatternSpec(name, "validation", {**base, **params}, place(make)))
        seq.append(PatternSpec(CLOSING_WHITE, "validation", {**base, "pattern": "grey", "level": 1.0,
                                                             "repeat": "white"}, place(lambda: white(size))))
    names = [s.name for s in seq]
    if len(set(names)) != len(names):
        raise CaptureError("pattern names in the sequence are not unique (repeated grey levels or checker phases?)")
    return seq


__all__ = ["CLOSING_WHITE", "GrayCodeDecoding", "LAYOUTS", "PatternSpec", "black", "calibration_sequence",
           "checkerboard", "colour_ramp", "decode_gray_code", "decode_gray_code_set", "default_checker_size", "flat",
           "gray_code_bits", "gray_code_layout", "gray_code_pattern", "gray_code_patterns", "smooth_random",
           "validation_patterns", "white"]
