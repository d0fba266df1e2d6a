"""ProCam ▸ Cancel: stop the running background job of a step (the same as Esc)."""

import bpy
from bpy.props import StringProperty

from ..addon import jobs


class PROCAM_OT_cancel_job(bpy.types.Operator):
    """Stop the running ProCam job; nothing it was writing is kept and the scene stays as it was"""

    bl_idname = "procam.cancel_job"
    bl_label = "Cancel"
    # No UNDO: cancelling changes no data.
    bl_options = {"REGISTER"}

    step: StringProperty(name="Step", description="Step whose job to stop (empty: whichever runs)")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        if jobs.BOARD.running() is None:
            cls.poll_message_set("no ProCam job is running")
            return False
        return True

    def execute(self, context: bpy.types.Context) -> set[str]:
        job = jobs.BOARD.get(self.step) if self.step else jobs.BOARD.running()
        if job is None or job.finished:
            self.report({"WARNING"}, "nothing to cancel: the job has already finished")
            return {"CANCELLED"}
        job.cancel()
        self.report({"INFO"}, f"Cancelling {job.name}…")
        return {"FINISHED"}
