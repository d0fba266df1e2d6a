"""Writing a calibration as a .blend file (rig, textured surface, diagnostic images) without touching
the open Blender file: the datablocks are built in a scratch scene, written with
``bpy.data.libraries.write`` and removed again."""

from __future__ import annotations

import os
from pathlib import Path

import bpy
import numpy as np

from ..surface.mesh import SurfaceMesh
from ..errors import CalibrationError
from ..imageio import atomic_path
from ..outputs import OutputError
from ..rig.model import Rig
from . import rig as blender_rig

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


def save_calibration_blend_atomic(path: str | Path, rig: Rig, surface: SurfaceMesh, images: dict[str, np.ndarray],
                                  *, force: bool = False) -> Path:
    """:func:`save_calibration_blend` to a temporary name renamed into place; never overwrites unless ``force``."""
    path = Path(path)
    if path.suffix.lower() != ".blend":
        raise OutputError(f"{path.name} is not a .blend file name; give a path ending in .blend")
    if path.exists() and not force:
        raise OutputError(f"{path} exists; it is only replaced with Replace (force) on")
    if not path.parent.is_dir():
        raise OutputError(f"cannot write {path}: folder {path.parent} does not exist")
    tmp, _ = atomic_path(path)
    try:
        save_calibration_blend(tmp, rig, surface, images)
        os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)
    return path


def projector_pose_from_blend(path: str | Path) -> np.ndarray:
    """The ``camera_from_projector`` pose of the ProCam Projector in a .blend file (opened in this session)."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"--blend file not found: {path}")
    try:
        bpy.ops.wm.open_mainfile(filepath=str(path), load_ui=False)
    except RuntimeError as exc:
        raise CalibrationError(f"cannot open {path}: {exc}") from None
    return blender_rig.read_projector(bpy.context.scene).camera_from_projector
