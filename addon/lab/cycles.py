"""Cycles renders of the Blender rig as linear float images: the virtual lab's camera.

:func:`render_cycles` renders the scene camera on the CPU into a temporary
OpenEXR file (the Render Result's pixels cannot be read back in background
mode), reads it as float32 linear RGB, and removes the file. Every setting
that could bend the values is pinned for the render and restored afterwards:
no view transform, look, exposure or gamma, a 1-pixel box filter, no
denoising, no clamping, and a black world so that only the projector lights
the room (unless a render asks for the room lights on). Blender's per-frame
chatter on stdout ("Saved: '…exr'") is silenced for the render so that
commands keep stdout for their results.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import bpy
import numpy as np

from ..errors import RenderError

_DARK_WORLD = "ProCam Dark Room"


class _Settings:
    """Set attributes for one render and put the old values back afterwards."""

    def __init__(self) -> None:
        self._saved: list[tuple[Any, str, Any]] = []

    def set(self, owner: Any, attr: str, value: Any) -> None:
        if not hasattr(owner, attr):
            return  # settings differ across Blender versions; absent means not applicable
        self._saved.append((owner, attr, getattr(owner, attr)))
        setattr(owner, attr, value)

    def restore(self) -> None:
        for owner, attr, value in reversed(self._saved):
            try:
                setattr(owner, attr, value)
            except (AttributeError, TypeError, ValueError, ReferenceError):
                pass
        self._saved.clear()


def _world(room_light: float = 0.0) -> bpy.types.World:
    """The lab's room: dark, or lit evenly from every direction with radiance ``room_light`` (white)."""
    world = bpy.data.worlds.new(_DARK_WORLD)
    world.color = (0.0, 0.0, 0.0)
    if world.node_tree is None:  # Blender < 5.0 creates worlds without nodes
        world.use_nodes = True
    for node in world.node_tree.nodes:
        if node.type == "BACKGROUND":
            # A new world lights the scene grey until its strength is set (docs/developer.md, dependency facts).
            lit = room_light > 0
            node.inputs["Strength"].default_value = float(room_light) if lit else 0.0
            node.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0) if lit else (0.0, 0.0, 0.0, 1.0)
    return world


@contextlib.contextmanager
def _quiet_stdout() -> Iterator[None]:
    """Send the C-level stdout to /dev/null for one render (Blender prints "Saved: '…exr'" per frame).

    Only file descriptor 1 is redirected, and only for the duration of the
    render; stderr (warnings, errors) is untouched. C stdio buffers are flushed
    on both sides so that earlier output still reaches the real stdout and the
    render's chatter does not leak out later. Where the descriptor cannot be
    duplicated (an embedded or unusual console), the render runs unsilenced.
    """
    try:
        sys.stdout.flush()
        _c_flush()
        saved = os.dup(1)
    except (OSError, ValueError, AttributeError):
        yield
        return
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, 1)
        finally:
            os.close(devnull)
    except OSError:
        os.close(saved)
        yield
        return
    try:
        yield
    finally:
        _c_flush()
        os.dup2(saved, 1)
        os.close(saved)


def _c_flush() -> None:
    """fflush(NULL): push C stdio buffers out before the descriptor behind stdout changes."""
    global _LIBC
    if _LIBC is None:
        try:
            _LIBC = ctypes.CDLL(None)
            _LIBC.fflush.argtypes = [ctypes.c_void_p]
        except (OSError, AttributeError, TypeError):  # no C library handle (e.g. Windows)
            _LIBC = False
    if _LIBC:
        _LIBC.fflush(None)


_LIBC: Any = None


def _read_exr(path: Path) -> np.ndarray:
    image = bpy.data.images.load(str(path), check_existing=False)
    try:
        w, h = image.size
        ch = image.channels
        if w == 0 or h == 0:
            raise RenderError(f"Cycles wrote an unreadable image ({path.name})")
        buf = np.empty(w * h * ch, dtype=np.float32)
        image.pixels.foreach_get(buf)
    finally:
        bpy.data.images.remove(image)
    img = buf.reshape(h, w, ch)[::-1, :, :3]  # Blender's row 0 is the bottom
    return np.ascontiguousarray(img, dtype=np.float32)


def render_cycles(scene: bpy.types.Scene, *, samples: int = 64, bounces: int = 0, seed: int = 0,
                  size: tuple[int, int] | None = None, room_light: float = 0.0) -> np.ndarray:
    """Render the scene camera with Cycles on the CPU: float32, linear, H×W×3.

    ``bounces`` = 0 gives direct light only; more adds interreflections.
    ``size`` = (width, height) overrides the render resolution for this
    render only (the camera keeps its lens: same aspect gives scaled K).
    ``room_light`` > 0 lights the room evenly from every direction (a white
    world of that radiance) instead of leaving it dark.
    """
    if scene.camera is None:
        raise RenderError("the scene has no camera to render from: create the rig first (ProCam ▸ Create Rig)")
    if not np.isfinite(room_light) or room_light < 0:
        raise RenderError(f"room light must be a radiance ≥ 0, got {room_light}")
    if samples < 1 or bounces < 0:
        raise RenderError(f"samples must be ≥ 1 and bounces ≥ 0, got samples={samples}, bounces={bounces}")
    if size is not None and (int(size[0]) < 1 or int(size[1]) < 1):
        raise RenderError(f"render size must be positive, got {size}")

    tmpdir = Path(tempfile.mkdtemp(prefix="procam-cycles-"))
    settings = _Settings()
    world = None
    try:
        r, c = scene.render, scene.cycles
        settings.set(r, "engine", "CYCLES")
        settings.set(c, "device", "CPU")
        settings.set(c, "samples", int(samples))
        settings.set(c, "use_adaptive_sampling", False)  # same noise for every pattern
        settings.set(c, "seed", int(seed))
        settings.set(c, "use_animated_seed", False)
        for attr in ("max_bounces", "diffuse_bounces", "glossy_bounces", "transmission_bounces", "volume_bounces"):
            settings.set(c, attr, int(bounces))
        settings.set(c, "sample_clamp_direct", 0.0)  # 0 = no clamping
        settings.set(c, "sample_clamp_indirect", 0.0)
        settings.set(c, "use_denoising", False)
        settings.set(c, "pixel_filter_type", "BOX")
        settings.set(c, "filter_width", 1.0)
        settings.set(c, "film_exposure", 1.0)
        settings.set(r, "film_transparent", False)
        settings.set(r, "use_motion_blur", False)
        settings.set(r, "use_border", False)
        settings.set(r, "use_compositing", False)
        settings.set(r, "use_sequencer", False)
        settings.set(r, "use_freestyle", False)
        settings.set(r, "threads_mode", "FIXED")
        settings.set(r, "threads", max(1, min(1024, os.cpu_count() or 1)))
        if size is not None:
            settings.set(r, "resolution_x", int(size[0]))
            settings.set(r, "resolution_y", int(size[1]))
        settings.set(r, "resolution_percentage", 100)
        vs = scene.view_settings
        settings.set(vs, "view_transform", "Standard")
        settings.set(vs, "look", "None")
        settings.set(vs, "exposure", 0.0)
        settings.set(vs, "gamma", 1.0)
        settings.set(vs, "use_curve_mapping", False)
        fmt = r.image_settings
        if hasattr(fmt, "media_type"):
            settings.set(fmt, "media_type", "IMAGE")  # Blender 5.0 groups formats by media type
        settings.set(fmt, "file_format", "OPEN_EXR")
        settings.set(fmt, "color_mode", "RGB")
        settings.set(fmt, "color_depth", "32")
        settings.set(fmt, "exr_codec", "ZIP")
        settings.set(r, "use_file_extension", True)
        settings.set(r, "filepath", str(tmpdir / "frame"))
        world = _world(room_light)
        settings.set(scene, "world", world)

        with _quiet_stdout():
            bpy.ops.render.render(write_still=True, scene=scene.name)
        written = sorted(tmpdir.glob("*.exr"))
        if not written:
            raise RenderError("Cycles wrote no image; check the console for Cycles errors")
        img = _read_exr(written[0])
    finally:
        settings.restore()
        if world is not None:
            bpy.data.worlds.remove(world)
        shutil.rmtree(tmpdir, ignore_errors=True)
    if not np.all(np.isfinite(img)):
        raise RenderError("Cycles produced NaN or infinite values")
    return img
