"""Blender side of the extension: registers operators, panels, scene properties and the ``procam`` CLI command.

Imported only from ``register()``/``unregister()`` in ``__init__.py``, so that
importing the package outside Blender never imports ``bpy``.
"""

from __future__ import annotations

from collections.abc import Sequence

import bpy

from .operators.add_projector import PROCAM_OT_add_projector
from .operators.calibrate import PROCAM_OT_calibrate, PROCAM_OT_load_calibration, PROCAM_OT_use_selected_surface_mesh
from .operators.calibrate_rig import PROCAM_OT_calibrate_rig
from .operators.cancel_job import PROCAM_OT_cancel_job
from .operators.capture_io import PROCAM_OT_export_patterns, PROCAM_OT_import_captures
from .operators.compensate import (PROCAM_OT_add_targets, PROCAM_OT_compensate, PROCAM_OT_evaluate,
                                   PROCAM_OT_prepare_show, PROCAM_OT_preview_compensated, PROCAM_OT_remove_target)
from .operators.create_rig import PROCAM_OT_create_rig
from .operators.diagnose import PROCAM_OT_diagnose
from .operators.export import PROCAM_OT_export_calibration_blend, PROCAM_OT_export_frames, PROCAM_OT_export_mpcdi
from .operators.live import PROCAM_OT_live_capture, PROCAM_OT_live_check, PROCAM_OT_live_preview
from .operators.live_show import PROCAM_OT_live_show_start, PROCAM_OT_live_show_stop
from .operators.open_report import PROCAM_OT_open_report
from .operators.run_lab import PROCAM_OT_run_lab
from .operators.set_projector_image import PROCAM_OT_set_projector_image
from .operators.set_surface import PROCAM_OT_set_surface
from .operators.show_image import PROCAM_OT_show_image, PROCAM_OT_show_text
from .panels import board, captures, live, properties
from .panels.board import PROCAM_PT_board
from .panels.calibrate import PROCAM_PT_calibrate
from .panels.captures import PROCAM_PT_captures
from .panels.compensate import PROCAM_PT_compensate, PROCAM_UL_targets
from .panels.diagnose import PROCAM_PT_diagnose
from .panels.export import PROCAM_PT_export
from .panels.live import PROCAM_PT_live
from .panels.rig import PROCAM_PT_rig

OPERATORS = (PROCAM_OT_create_rig, PROCAM_OT_add_projector, PROCAM_OT_set_surface, PROCAM_OT_set_projector_image,
             PROCAM_OT_run_lab,
             PROCAM_OT_export_patterns, PROCAM_OT_import_captures, PROCAM_OT_calibrate_rig,
             PROCAM_OT_calibrate, PROCAM_OT_load_calibration, PROCAM_OT_use_selected_surface_mesh,
             PROCAM_OT_add_targets, PROCAM_OT_remove_target,
             PROCAM_OT_compensate, PROCAM_OT_evaluate, PROCAM_OT_prepare_show, PROCAM_OT_preview_compensated,
             PROCAM_OT_diagnose, PROCAM_OT_show_image, PROCAM_OT_show_text, PROCAM_OT_open_report,
             PROCAM_OT_export_calibration_blend, PROCAM_OT_export_frames, PROCAM_OT_export_mpcdi,
             PROCAM_OT_cancel_job,
             PROCAM_OT_live_check, PROCAM_OT_live_preview, PROCAM_OT_live_capture, PROCAM_OT_live_show_start,
             PROCAM_OT_live_show_stop)
#: Sidebar panels in workflow order (a sub-panel right after its parent, which must be registered first).
PANELS = (PROCAM_PT_rig, PROCAM_PT_captures, PROCAM_PT_board, PROCAM_PT_live, PROCAM_PT_calibrate,
          PROCAM_PT_compensate, PROCAM_PT_diagnose, PROCAM_PT_export)
CLASSES = (properties.PROCAM_PG_target, PROCAM_UL_targets, *OPERATORS, *PANELS)
CLI_COMMAND = "procam"

_cli_handle = None


def scene_properties() -> dict[str, object]:
    return {**captures.scene_properties(), **board.scene_properties(), **live.scene_properties(),
            **properties.scene_properties()}


def run_cli(argv: Sequence[str]) -> int:
    """``blender --background --command procam ARGS``: the same code path as the venv's ``procam ARGS``."""
    from .addon.cli.app import main

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
    from .addon import jobs

    jobs.BOARD.clear()  # a worker must not outlive its operators
    if _cli_handle is not None:
        bpy.utils.unregister_cli_command(_cli_handle)
        _cli_handle = None
    for name in scene_properties():
        if hasattr(bpy.types.Scene, name):
            delattr(bpy.types.Scene, name)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
