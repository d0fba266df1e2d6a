"""Exceptions for failures the user can fix; each message says what to do; and the user's cancel.

The CLI prints the message and exits non-zero; operators pass it to ``self.report``.
Anything that is not a ``ProCamError`` (or a :class:`Cancelled`) is a bug in ProCam.
"""


class ProCamError(Exception):
    """Base of all errors whose message is meant for the user."""

    exit_code = 2


class RigError(ProCamError):
    """Bad camera/projector specification or pose."""


class SurfaceError(ProCamError):
    """A surface object or mesh that cannot be used."""


class ImageError(ProCamError):
    """A missing, unreadable or ill-shaped image."""


class WriteError(ProCamError):
    """An output that cannot be written: a full disk, no permission, a read-only file system."""


class RenderError(ProCamError):
    """The renderer cannot run (backend, LLVM, GPU) or produced invalid values."""


class CaptureError(ProCamError):
    """A capture set that is missing, incomplete or inconsistent."""


class CalibrationError(ProCamError):
    """A calibration stage cannot proceed from the given captures."""


class LiveError(CaptureError):
    """The live projector window or camera cannot be opened, or behaves in a way captures cannot trust."""


class LabError(ProCamError):
    """A bad virtual-lab request: unknown surface or effect, a value out of range."""


class Cancelled(Exception):
    """The user cancelled a running stage (Esc in Blender, Ctrl-C between two steps); nothing was written, or a
    resumable step says what it kept.

    Not a :class:`ProCamError`: a stage that records a failed target and goes on, or turns one error into another,
    catches ``ProCamError``, and a cancel is neither a failure nor something to go on after. Whoever decides what a
    cancel means (the CLI's exit code 130, a job's cancelled state) catches it by name, before ``Exception``.
    """

    exit_code = 130

    def __init__(self, message: str = "", *, kept: bool = False) -> None:
        super().__init__(message)
        #: finished work was kept (a partial folder, photographs, frames), and the message says where
        self.kept = kept


#: What reading a parsed JSON manifest of the wrong shape raises in code that indexes and converts it: a missing
#: key or item, a value of another type (a list where an object was, ``int(None)``), a bad or infinite number.
#: A manifest reader catches these around its parsing and raises its own error, which says what to do.
MALFORMED = (LookupError, TypeError, ValueError, AttributeError, OverflowError)


class MpcdiError(ProCamError):
    """A VESA MPCDI file that cannot be written from a calibration, or read back: its structure, its files."""
