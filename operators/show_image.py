"""ProCam ▸ Show Image / Show Text: open a result image (diagnostic, residual map, compensated input) as a Blender
image, or a result text (the diagnosis summary) as a Blender text, and show it in the open editors."""

from pathlib import Path

import bpy
from bpy.props import StringProperty

from ..addon.errors import ProCamError
from ..addon.blender import rig as blender_rig
from .messages import sidebar_text


def _show_in_editors(context: bpy.types.Context, editor: str, attribute: str, datablock: bpy.types.ID) -> int:
    """Make ``datablock`` the one shown by every open editor of type ``editor``; returns how many."""
    shown = 0
    screen = context.screen
    for area in (screen.areas if screen is not None else ()):
        if area.type == editor:
            setattr(area.spaces.active, attribute, datablock)
            shown += 1
    return shown


class _ShowFile:
    """The file and Blender name both operators take, and their poll."""

    filepath: StringProperty(name="File", subtype="FILE_PATH")
    name: StringProperty(name="Name", description="Name of the Blender datablock (default: ProCam + file name)")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.scene is not None


class PROCAM_OT_show_image(_ShowFile, bpy.types.Operator):
    """Load the image file as a Blender image and show it in the open Image Editors"""

    bl_idname = "procam.show_image"
    bl_label = "Show Image"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        path = Path(bpy.path.abspath(self.filepath))
        try:
            image = blender_rig.load_image_file(path, self.name or f"ProCam {path.stem}")
        except ProCamError as exc:
            self.report({"ERROR"}, sidebar_text(str(exc)))
            return {"CANCELLED"}
        shown = _show_in_editors(context, "IMAGE_EDITOR", "image", image)
        where = f"shown in {shown} Image Editor(s)" if shown else "open an Image Editor to view it"
        self.report({"INFO"}, f"Image {image.name!r} ({image.size[0]}×{image.size[1]}): {where}")
        return {"FINISHED"}


class PROCAM_OT_show_text(_ShowFile, bpy.types.Operator):
    """Load the text file (e.g. the diagnosis summary) as a Blender text and show it in the open Text Editors"""

    bl_idname = "procam.show_text"
    bl_label = "Show Text"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        path = Path(bpy.path.abspath(self.filepath))
        try:
            body = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            self.report({"ERROR"}, f"cannot read {path}: {getattr(exc, 'strerror', None) or exc}")
            return {"CANCELLED"}
        name = self.name or f"ProCam {path.name}"
        text = bpy.data.texts.get(name) or bpy.data.texts.new(name)
        text.clear()
        text.write(body)
        shown = _show_in_editors(context, "TEXT_EDITOR", "text", text)
        where = f"shown in {shown} Text Editor(s)" if shown else "open a Text Editor to read it"
        self.report({"INFO"}, f"Text {name!r} ({len(body.splitlines())} lines): {where}")
        return {"FINISHED"}
