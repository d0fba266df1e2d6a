"""Blender side of the extension: registers operators, panels and the ``procam`` command-line command.

Imported only from ``register()``/``unregister()`` in ``__init__.py``, so that
importing the package outside Blender never imports ``bpy``.
"""

from __future__ import annotations

from collections.abc import Sequence

import bpy

from .operators.create_rig import PROCAM_OT_create_rig
from .operators.run_lab import PROCAM_OT_run_lab
from .operators.set_projector_image import PROCAM_OT_set_projector_image
from .operators.set_surface import PROCAM_OT_set_surface
from .panels.captures import PROCAM_PT_captures, scene_properties
from .panels.rig import PROCAM_PT_rig

CLASSES = (PROCAM_OT_create_rig, PROCAM_OT_set_surface, PROCAM_OT_set_projector_image, PROCAM_OT_run_lab,
           PROCAM_PT_rig, PROCAM_PT_captures)
CLI_COMMAND = "procam"

_cli_handle = None


def run_cli(argv: Sequence[str]) -> int:
    """``blender --background --command procam ARGS``: the same code path as the venv's ``procam ARGS``."""
    from .addon.cli import main

    try:
        return main(list(argv))
    except SystemExit as exc:  # argparse exits on --help or bad arguments; Blender wants a return code
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)


def register() -> None:
    global _cli_handle
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    for name, prop in scene_properties().items():
        setattr(bpy.types.Scene, name, prop)
    if hasattr(bpy.utils, "register_cli_command") and _cli_handle is None:
        _cli_handle = bpy.utils.register_cli_command(CLI_COMMAND, run_cli)


def unregister() -> None:
    global _cli_handle
    if _cli_handle is not None:
        bpy.utils.unregister_cli_command(_cli_handle)
        _cli_handle = None
    for name in scene_properties():
        if hasattr(bpy.types.Scene, name):
            delattr(bpy.types.Scene, name)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
