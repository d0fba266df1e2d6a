"""The shared body of operators that run a long engine step as an :class:`~procam.addon.jobs.Job`.

With a window (the normal UI), ``invoke`` starts the job in a worker thread and
polls it from a window-manager timer: progress shows in the panel (the step's
job on ``jobs.BOARD``) and in the status bar, Esc or the panel's Cancel button
stops it. In background mode (``blender --background``, tests) there is no
event loop, so ``invoke`` and ``execute`` run the job synchronously. Either way
the scene is changed only in :meth:`JobOperator.apply`, once the job is done,
on the main thread; the operator's UNDO flag makes that one undo step, and a
cancelled or failed job changes nothing.
"""

import functools

import bpy

from ..addon import jobs
from ..addon.errors import ProCamError
from .messages import sidebar_text

#: Seconds between polls of a running job.
POLL_S = 0.2


def redraw_sidebars(context: bpy.types.Context) -> None:
    screen = context.screen
    for area in (screen.areas if screen is not None else ()):
        if area.type == "VIEW_3D":
            area.tag_redraw()


class JobOperator:
    """Mixin for ``bpy.types.Operator`` subclasses: set ``step`` and implement ``why_not``, ``make_job`` and
    ``apply``."""

    step = ""
    #: How this operator's own fields name the command's options in its messages (:func:`.messages.sidebar_text`).
    option_names: dict[str, str] = {}
    #: What a cancelled run leaves behind, for the report.
    cancel_note = "the scene and the output folder are unchanged"
    _timer = None
    _job = None
    _relay = None
    _device = None

    # -- to implement

    @classmethod
    def why_not(cls, scene: bpy.types.Scene) -> str | None:
        """Why the step cannot start with the scene's settings (the disabled button's tooltip), else None."""
        raise NotImplementedError

    def make_job(self, context: bpy.types.Context, relay: "jobs.MainThreadRelay | None") -> jobs.Job:
        """Validate the inputs (raise ProCamError) and build the job; ``relay`` is None when it runs here."""
        raise NotImplementedError

    def apply(self, context: bpy.types.Context, result: object) -> str:
        """Write a finished job's result into the scene (main thread); returns the report."""
        raise NotImplementedError

    def in_foreground(self, context: bpy.types.Context) -> bool:
        """Whether the job must run on the main thread even with a window (a live projector window on macOS)."""
        return False

    # -- the operator protocol

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        why = job_running_message() or cls.why_not(context.scene)
        if why is not None:
            cls.poll_message_set(why)
        return why is None

    def execute(self, context: bpy.types.Context) -> set[str]:
        return self._launch(context, threaded=False)

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        threaded = not bpy.app.background and context.window is not None and not self.in_foreground(context)
        return self._launch(context, threaded=threaded)

    def modal(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        job = self._job
        if event.type == "ESC" and event.value == "PRESS":
            job.cancel()
            return {"RUNNING_MODAL"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        if self._relay is not None:
            self._relay.pump()
        snap = job.snapshot()
        context.window_manager.progress_update(int(100 * snap.fraction))
        if context.workspace is not None:
            context.workspace.status_text_set(
                f"ProCam {job.name}: {100 * snap.fraction:.0f}% {snap.message} — Esc to cancel")
        redraw_sidebars(context)
        if not job.finished:
            return {"PASS_THROUGH"}
        self._stop_ui(context)
        return self._finish(context, job)

    def cancel(self, context: bpy.types.Context) -> None:
        """Blender ends the modal (window closed, file loaded): stop the worker and tidy up."""
        if self._job is not None:
            self._job.cancel()
            self._job.wait(5.0)
        self._stop_ui(context)

    # -- internals

    def _launch(self, context: bpy.types.Context, *, threaded: bool) -> set[str]:
        relay = None
        try:
            if jobs.BOARD.running() is not None:
                raise jobs.JobError(f"{jobs.BOARD.running().name} is still running: wait for it or cancel it")
            if threaded:
                holder: list[jobs.Job] = []
                relay = jobs.MainThreadRelay(cancel=lambda: bool(holder) and holder[0].cancelled())
                job = self.make_job(context, relay)
                holder.append(job)
            else:
                job = self.make_job(context, None)
            job.wording = functools.partial(sidebar_text, names=self.option_names)
            jobs.BOARD.add(self.step, job)
        except ProCamError as exc:
            self._close_device()
            self.report({"ERROR"}, sidebar_text(str(exc), self.option_names))
            return {"CANCELLED"}
        self._job, self._relay = job, relay
        if not threaded:
            job.run()
            return self._finish(context, job)
        wm = context.window_manager
        job.start()
        self._timer = wm.event_timer_add(POLL_S, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        redraw_sidebars(context)
        return {"RUNNING_MODAL"}

    def _stop_ui(self, context: bpy.types.Context) -> None:
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
            wm.progress_end()
            if context.workspace is not None:
                context.workspace.status_text_set(None)
        redraw_sidebars(context)

    def _close_device(self) -> None:
        if self._device is not None:
            try:
                self._device.close()
            finally:
                self._device = None

    def _finish(self, context: bpy.types.Context, job: jobs.Job) -> set[str]:
        self._close_device()
        snap = job.snapshot()
        if snap.status == jobs.DONE:
            try:
                message = self.apply(context, job.result)
            except ProCamError as exc:
                job.mark_failed(exc)
                self.report({"ERROR"}, sidebar_text(str(exc), self.option_names))
                return {"CANCELLED"}
            self.report({"INFO"}, f"{message} ({snap.seconds:.1f} s)")
            return {"FINISHED"}
        if snap.status == jobs.CANCELLED:
            # A step that kept finished work says what and where; otherwise this operator's own note holds.
            note = snap.error if snap.kept and snap.error else f"{job.name} cancelled: {self.cancel_note}"
            self.report({"WARNING"}, note)
            return {"CANCELLED"}
        self.report({"ERROR"}, snap.error or f"{job.name} failed")  # worded for the sidebar (Job.wording)
        return {"CANCELLED"}


def job_running_message() -> str | None:
    """Why a job operator is disabled while another job runs (for ``poll_message_set``), else None."""
    job = jobs.BOARD.running()
    return None if job is None else f"{job.name} is running: wait for it or cancel it"
