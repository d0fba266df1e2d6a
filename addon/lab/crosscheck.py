"""Cross-renderer agreement: the Cycles render of the Blender rig against the Mitsuba model f̂.

Both renderers see the same rig and surface and are fed the same projector
frames (white, then a checkerboard). Geometry is compared at the projected
checkerboard's corners, located to sub-pixel precision in each render after
dividing by that renderer's own white render (which cancels the surface
texture); intensity is compared on the white renders over well-lit pixels,
with no fitted scale: the light's energy follows from the projector model.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..capture.patterns import refine_corners
from ..render.forward import ForwardModel
from ..rig.model import Rig
from ..surface.mesh import SurfaceMesh, frame_points_to_camera


@dataclass
class CrossCheck:
    """Measured agreement between Cycles and Mitsuba (pixels of the camera image)."""

    corner_offsets: np.ndarray  # N, |Cycles corner − Mitsuba corner|
    intensity_rel_diff: float  # mean |Cycles − Mitsuba| / mean Mitsuba over lit pixels (white frame)
    intensity_rel_bias: float  # (mean Cycles − mean Mitsuba) / mean Mitsuba, same pixels
    lit_pixels: int
    bounces: int
    images: dict[str, np.ndarray] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)

    def summary(self) -> dict[str, float | int]:
        off = self.corner_offsets
        return {"bounces": self.bounces, "corners": int(len(off)),
                "corner_offset_median_px": float(np.median(off)) if len(off) else float("nan"),
                "corner_offset_max_px": float(np.max(off)) if len(off) else float("nan"),
                "intensity_mean_abs_diff_pct": 100.0 * self.intensity_rel_diff,
                "intensity_bias_pct": 100.0 * self.intensity_rel_bias,
                "lit_pixels": self.lit_pixels,
                **{f"seconds_{k}": round(v, 2) for k, v in self.seconds.items()}}


def checkerboard_frame(width: int, height: int, square: int) -> np.ndarray:
    """Native projector frame with a checkerboard whose corners fall on whole pixels."""
    y, x = np.mgrid[0:height, 0:width]
    board = ((x // square + y // square) % 2).astype(np.float32)
    return np.repeat(board[..., None], 3, axis=2)


def predicted_corners(rig: Rig, surface: SurfaceMesh, square: int, margin: int = 1) -> np.ndarray:
    """Camera pixels where the checkerboard's inner corners land, by ray casting (NaN where hidden)."""
    w, h = rig.projector.intrinsics.size
    xs = np.arange(square * margin, w - square * margin + 1, square)
    ys = np.arange(square * margin, h - square * margin + 1, square)
    px = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2).astype(np.float64)
    return frame_points_to_camera(rig, surface, px)


def _normalised(checker: np.ndarray, white: np.ndarray) -> np.ndarray:
    w = white.mean(axis=2)
    return np.where(w > 1e-4, checker.mean(axis=2) / np.maximum(w, 1e-4), 0.0).clip(0, 1)


def measure(cycles: dict[str, np.ndarray], mitsuba: dict[str, np.ndarray], guesses: np.ndarray,
            square_px_in_camera: float, bounces: int) -> CrossCheck:
    """Compare renders keyed 'white' and 'checker' from both renderers."""
    pat_c = _normalised(cycles["checker"], cycles["white"])
    pat_m = _normalised(mitsuba["checker"], mitsuba["white"])
    window = int(max(2, min(7, square_px_in_camera // 3)))
    h, w = pat_c.shape
    lit = (mitsuba["white"].mean(axis=2) > 0.05 * mitsuba["white"].mean(axis=2).max())
    lit &= cycles["white"].mean(axis=2) > 0.05 * cycles["white"].mean(axis=2).max()
    inner = cv2.erode(lit.astype(np.uint8), np.ones((2 * window + 3, 2 * window + 3), np.uint8)).astype(bool)
    ok = np.all(np.isfinite(guesses), axis=1)
    g = guesses[ok]
    ij = np.clip(np.round(g - 0.5).astype(int), 0, [w - 1, h - 1])
    g = g[inner[ij[:, 1], ij[:, 0]]]
    offsets = (np.linalg.norm(refine_corners(pat_c, g, window) - refine_corners(pat_m, g, window), axis=1)
               if len(g) else np.zeros(0))
    solid = cv2.erode(lit.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    c, m = cycles["white"][solid], mitsuba["white"][solid]
    mean_m = float(m.mean()) if m.size else float("nan")
    return CrossCheck(offsets, float(np.abs(c - m).mean() / mean_m), float((c.mean() - mean_m) / mean_m),
                      int(solid.sum()), bounces)


def run_cross_check(rig: Rig, surface: SurfaceMesh, *, bounces: int = 0, samples: int = 64, spp: int = 64,
                    square: int | None = None, seed: int = 0) -> CrossCheck:
    """Render white and checkerboard frames with Cycles (Blender scene) and Mitsuba, and measure agreement.

    Builds a fresh Blender scene for the rig, so call it headless or on a
    throw-away scene.
    """
    import bpy

    from ..blender import rig as blender_rig
    from .cycles import render_cycles

    pw, ph = rig.projector.intrinsics.size
    square = square or max(4, pw // 10)
    frames = {"white": np.ones((ph, pw, 3), np.float32), "checker": checkerboard_frame(pw, ph, square)}
    seconds: dict[str, float] = {}

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    blender_rig.create_camera(scene, rig.camera.intrinsics)
    light = blender_rig.create_projector(scene, rig.projector)
    blender_rig.create_surface(scene, surface)
    cycles: dict[str, np.ndarray] = {}
    for name, frame in frames.items():
        blender_rig.set_projector_image(light, frame)
        t0 = time.perf_counter()
        cycles[name] = render_cycles(scene, samples=samples, bounces=bounces, seed=seed)
        seconds[f"cycles_{name}"] = time.perf_counter() - t0

    model = ForwardModel(rig, surface, bounces=bounces, spp=spp, smoothing_eps=0.0, clamp=False, seed=seed)
    mitsuba: dict[str, np.ndarray] = {}
    for name, frame in frames.items():
        t0 = time.perf_counter()
        mitsuba[name] = model.render(frame)
        seconds[f"mitsuba_{name}"] = time.perf_counter() - t0

    guesses = predicted_corners(rig, surface, square)
    good = guesses[np.all(np.isfinite(guesses), axis=1)]
    # Square size in camera pixels: the median spacing of neighbouring predicted corners.
    square_cam = float(np.median(np.linalg.norm(np.diff(good, axis=0), axis=1))) if len(good) > 1 else 8.0
    result = measure(cycles, mitsuba, guesses, square_cam, bounces)
    result.images = {f"cycles_{k}": v for k, v in cycles.items()} | {f"mitsuba_{k}": v for k, v in mitsuba.items()}
    result.seconds = seconds
    return result
