"""View3D ▸ Sidebar ▸ ProCam ▸ Captures: the scene's capture set, its state, and the virtual-lab button."""

import textwrap
from pathlib import Path

import bpy
from bpy.props import StringProperty

from ..addon.capture.format import MANIFEST, CaptureSet
from ..addon.errors import ProCamError


def scene_properties() -> dict[str, object]:
    """Scene properties this panel shows (registered on ``bpy.types.Scene`` by ``blender_registration``)."""
    return {"procam_capture_dir": StringProperty(
        name="Capture Set", subtype="DIR_PATH",
        description="Folder of the capture set that calibration reads (the virtual lab writes it here)")}


_STATUS: dict[str, tuple[object, str, str]] = {}


def capture_set_status(path: str) -> tuple[str, str]:
    """(icon, text) for a capture-set folder: its image count, or why it cannot be loaded.

    The panel redraws often, so the answer is kept until ``capture.json`` changes;
    images are not decoded here (loading the set for calibration checks them).
    """
    if not path:
        return "INFO", "No capture set: run the virtual lab or choose a folder"
    root = Path(bpy.path.abspath(path))
    try:
        stamp: object = (root / MANIFEST).stat().st_mtime_ns
    except OSError:
        stamp = None
    cached = _STATUS.get(str(root))
    if cached is not None and cached[0] == stamp:
        return cached[1], cached[2]
    try:
        cs = CaptureSet.load(root, verify_images=False)
    except ProCamError as exc:
        result = ("ERROR", str(exc))
    else:
        images = [e for e in cs.entries if e.kind != "depth"]
        w, h = cs.camera.intrinsics.size
        depth = (" + depth" if len(images) < len(cs.entries) else "") + (" + wall" if cs.depth_walls() else "")
        result = ("CHECKMARK", f"{len(images)} images{depth}, camera {w}×{h}")
    _STATUS[str(root)] = (stamp, *result)
    return result


class PROCAM_PT_captures(bpy.types.Panel):
    bl_idname = "PROCAM_PT_captures"
    bl_label = "Captures"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "ProCam"
    bl_order = 1

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        scene = context.scene
        layout.prop(scene, "procam_capture_dir", text="")
        icon, text = capture_set_status(scene.procam_capture_dir)
        col = layout.column(align=True)
        lines = textwrap.wrap(text, 44) or [""]
        col.label(text=lines[0], icon=icon)
        for line in lines[1:]:
            col.label(text=line)
        layout.operator("procam.run_lab", icon="RENDER_STILL")
        row = layout.row(align=True)  # a session with the user's own projector and camera
        row.operator("procam.export_patterns", icon="EXPORT")
        row.operator("procam.import_captures", icon="IMPORT")
