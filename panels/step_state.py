"""How every step panel shows its state: not run, running with progress (and Cancel), done with its key figure,
failed with its message. Draw helpers only."""

import textwrap

import bpy

from ..addon import jobs
from ..addon.steps.summary import Summary

WRAP = 44


def wrapped(layout: bpy.types.UILayout, text: str, icon: str = "NONE") -> None:
    """A label broken into sidebar-width lines (the first one carries the icon)."""
    col = layout.column(align=True)
    lines = textwrap.wrap(text, WRAP) or [""]
    col.label(text=lines[0], icon=icon)
    for line in lines[1:]:
        col.label(text=line)


def draw_state(layout: bpy.types.UILayout, step: str, summary: Summary) -> bool:
    """Draw the step's state; returns True when its results are there to show (done)."""
    job = jobs.BOARD.get(step)
    snap = job.snapshot() if job is not None else None
    box = layout.box()
    if snap is not None and not snap.finished:
        box.progress(factor=snap.fraction, type="BAR", text=f"{100 * snap.fraction:.0f}% — {snap.seconds:.0f} s")
        wrapped(box, snap.message, icon="TIME")
        box.operator("procam.cancel_job", text="Cancel", icon="CANCEL").step = step
        return False
    if snap is not None and snap.status == jobs.FAILED:
        wrapped(box, f"Failed: {snap.error}", icon="ERROR")
    elif snap is not None and snap.status == jobs.CANCELLED and snap.kept and snap.error:
        wrapped(box, f"Cancelled: {snap.error}", icon="CANCEL")
    elif snap is not None and snap.status == jobs.CANCELLED:
        box.label(text="Cancelled: nothing was changed", icon="CANCEL")
    if summary.ok:
        wrapped(box, summary.headline, icon="CHECKMARK")
        for line in summary.lines:
            wrapped(box, line)
        return True
    if snap is None:
        wrapped(box, f"Not run. {summary.headline}", icon="INFO")
    return False
