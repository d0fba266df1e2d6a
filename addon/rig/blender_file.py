"""Writing a calibration as a .blend file (rig, textured surface, diagnostic images) without touching
the open Blender file: the datablocks are built in a scratch scene, written with
``bpy.data.libraries.write`` and removed again."""

from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np

from ..surface.mesh import SurfaceMesh
from . import blender_rig
from .model import Rig

_COLLECTIONS = ("objects", "meshes", "lights", "cameras", "materials", "images", "node_groups", "scenes", "worlds")


def save_calibration_blend(path: str | Path, rig: Rig, surface: SurfaceMesh, images: dict[str, np.ndarray]) -> Path:
    """Write ``path`` holding a scene "ProCam Calibration" with the rig, the surface and the images."""
    before = {c: set(getattr(bpy.data, c)) for c in _COLLECTIONS}
    scene = bpy.data.scenes.new("ProCam Calibration")
    try:
        blender_rig.create_rig(scene, rig, surface)
        blocks: set = {scene}
        for name, img in images.items():
            image = blender_rig.add_image(f"ProCam {name}", img)
            image.use_fake_user = True  # keep diagnostics in the file although no material uses them
            blocks.add(image)
        bpy.data.libraries.write(str(path), blocks, fake_user=True)
    finally:
        for c in _COLLECTIONS:
            coll = getattr(bpy.data, c)
            for block in set(coll) - before[c]:
                try:
                    coll.remove(block)
                except (ReferenceError, RuntimeError):
                    pass
    return Path(path)
