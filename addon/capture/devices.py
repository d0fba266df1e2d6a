"""Capture devices: things that show a projector frame and return what the camera saw.

The pipeline talks to a :class:`Device` and never knows which one it has:
the virtual lab (``addon/lab/``) renders the frame with Cycles; the live
device (``addon/live/``) shows the frame in a window on the projector's
display and captures it with a camera client; :class:`FolderDevice` replays
a capture set, answering ``project`` for every frame that was captured; and
:class:`LensRemovedDevice` puts any of them through the camera lens that was
taken out of a calibration's photographs. :func:`capture_sequence` runs a
pattern sequence through any device into a new capture set.
"""

from __future__ import annotations

import hashlib
from abc import ABC, abstractmethod
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import CaptureError
from ..imageio import read_image
from ..rig.model import Camera, Projector
from .format import CaptureSet, CaptureSetWriter, DepthInfo, Entry
from .patterns import PatternSpec
from ..rig.lens import RigLens

class Device(ABC):
    """Shows a native projector frame and returns the camera's image (float32 H×W×3, linear).

    A device of several projectors lists them in :attr:`projectors` (the first is ``projector``) and shows one
    frame on each at once with :meth:`project_all`; ``project`` and ``capture_off`` are the first projector's.
    """

    projector: Projector

    @property
    def projectors(self) -> tuple[Projector, ...]:
        """Every projector this device shows frames on, the first (``projector``) first."""
        return (self.projector,)

    @abstractmethod
    def project(self, frame: np.ndarray) -> np.ndarray:
        """Show ``frame`` (native projector resolution, float32 H×W×3 in [0, 1]) and capture."""

    def project_all(self, frames: Sequence[np.ndarray]) -> np.ndarray:
        """Show ``frames[k]`` on projector ``k``, all at once, and capture once.

        One frame per projector, each at its projector's native size. A device of one projector shows
        ``frames[0]`` with :meth:`project`; a device of several that cannot show them together refuses.
        """
        checked = self.check_frames(frames)
        if len(checked) > 1:
            raise CaptureError(f"this {type(self).__name__} cannot show {len(checked)} projectors' frames at once; "
                               "capture each projector's frames while the others show black")
        return self.project(checked[0])

    def capture_off(self) -> np.ndarray:
        """Capture with the projector off; devices that cannot switch it off show a black frame."""
        w, h = self.projector.intrinsics.size
        return self.project(np.zeros((h, w, 3), dtype=np.float32))

    def close(self) -> None:  # noqa: B027 — a device that holds nothing needs no override
        """Release windows, cameras, renderers."""

    def check_frame(self, frame: np.ndarray, index: int = 0) -> np.ndarray:
        """``frame`` as float32 H×W×3, checked against projector ``index``'s native size and [0, 1]."""
        f = np.asarray(frame, dtype=np.float32)
        if f.ndim == 2:
            f = np.repeat(f[..., None], 3, axis=2)
        projectors = self.projectors
        w, h = projectors[index].intrinsics.size
        if f.shape != (h, w, 3):
            which = f"projector {index + 1}'s frame" if len(projectors) > 1 else "a projector frame"
            raise CaptureError(f"{which} must be {w}×{h}×3 (the native resolution), got {f.shape}; "
                               "place an input image with Projector.frame_from_input")
        if not np.all(np.isfinite(f)) or f.min() < 0 or f.max() > 1:
            raise CaptureError("a projector frame must hold values in [0, 1]")
        return f

    def check_frames(self, frames: Sequence[np.ndarray]) -> list[np.ndarray]:
        """One checked frame per projector (:meth:`check_frame`), or a :class:`CaptureError` on a wrong count."""
        if isinstance(frames, np.ndarray) and frames.ndim != 4:
            raise CaptureError("project_all takes a sequence of frames, one per projector, not one frame")
        count = len(self.projectors)
        if len(frames) != count:
            raise CaptureError(f"this device shows {count} projector(s) and takes one frame for each, got "
                               f"{len(frames)} frame(s)")
        return [self.check_frame(f, k) for k, f in enumerate(frames)]

    def __enter__(self) -> Device:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class ShownTogether(Device):
    """A device that shows every projector's frame at once and takes one photograph of them together (windows and
    a camera, windows and a shooting command, or a command that does both): a subclass takes that photograph in
    :meth:`_capture`, one frame per projector, and raises :attr:`error` for what goes wrong."""

    others: tuple[Projector, ...] = ()
    #: the subclass's error type (the user fixes a live rig otherwise than a command)
    error: type[CaptureError] = CaptureError
    #: how messages name the device ("this live device")
    what = "this device"
    _photo_size: tuple[int, int] | None = None

    @property
    def projectors(self) -> tuple[Projector, ...]:
        return (self.projector, *self.others)

    @property
    def camera_size(self) -> tuple[int, int] | None:
        """The photographs' size (width, height), known from the first one; checked against a calibration."""
        return self._photo_size

    @abstractmethod
    def _capture(self, frames: Sequence[np.ndarray]) -> np.ndarray:
        """Show ``frames`` (one per projector, checked) together and photograph them."""

    def _flat(self, value: float, lit: int | None = None) -> list[np.ndarray]:
        """A flat frame of ``value`` on every projector, or only on projector ``lit`` (the others black)."""
        return [np.full((p.intrinsics.height, p.intrinsics.width, 3), value if lit is None or k == lit else 0.0,
                        np.float32) for k, p in enumerate(self.projectors)]

    def _same_size(self, image: np.ndarray, number: int) -> np.ndarray:
        """``image`` (photograph ``number``), refused when its size is not the first photograph's."""
        size, first = (image.shape[1], image.shape[0]), self._photo_size
        if first is None:
            self._photo_size = size
        elif size != first:
            raise self.error(f"photograph {number} is {size[0]}×{size[1]}, the first was {first[0]}×{first[1]}: "
                             "keep the camera's image size fixed")
        return image

    def project(self, frame: np.ndarray) -> np.ndarray:
        if self.others:
            raise self.error(f"{self.what} shows {len(self.projectors)} projectors: give each its frame with "
                             "project_all (black for those that are off), or show one projector with the others "
                             "black through capture.devices.OneProjector")
        return self._capture([self.check_frame(frame)])

    def project_all(self, frames: Sequence[np.ndarray]) -> np.ndarray:
        """Every projector's frame at once (each checked at its projector's size), photographed together."""
        return self._capture(self.check_frames(frames))

    def capture_off(self) -> np.ndarray:
        """Every projector black (a window or a command cannot switch its projector off)."""
        return self._capture(self._flat(0.0))


class SomeProjectors(Device):
    """Projectors ``keep`` (numbered from 0, in that order) of a device of several, the others showing black: how one
    projector of a rig is captured on its own (its sequence, its own closed loop), or a solve that leaves out a
    projector lighting nothing where it works. Closing it leaves the device open (its owner closes it)."""

    def __init__(self, device: Device, keep: Sequence[int]) -> None:
        count = len(device.projectors)
        bad = [k for k in keep if not 0 <= k < count]
        if bad or not keep:
            raise CaptureError(f"the device shows {count} projector(s); there is no projector "
                               f"{', '.join(str(k + 1) for k in bad) or '(none chosen)'}")
        self.device, self.keep = device, [int(k) for k in keep]
        self.projector = device.projectors[self.keep[0]]

    def __getattr__(self, name: str) -> Any:  # the live device's report, camera_size, …
        if name in ("device", "keep"):  # not set yet: no recursion through the lookup below
            raise AttributeError(name)
        return getattr(self.device, name)

    @property
    def projectors(self) -> tuple[Projector, ...]:
        return tuple(self.device.projectors[k] for k in self.keep)

    def project_all(self, frames: Sequence[np.ndarray]) -> np.ndarray:
        shown = [np.zeros((p.intrinsics.height, p.intrinsics.width, 3), np.float32) for p in self.device.projectors]
        for k, frame in zip(self.keep, self.check_frames(frames)):
            shown[k] = frame
        return self.device.project_all(shown)

    def project(self, frame: np.ndarray) -> np.ndarray:
        if len(self.keep) != 1:
            raise CaptureError(f"this device shows {len(self.keep)} projectors: give each its frame with project_all")
        return self.project_all([frame])

    def capture_off(self) -> np.ndarray:
        return self.device.capture_off()


class OneProjector(SomeProjectors):
    """Projector ``index`` of a device of several, the others showing black."""

    def __init__(self, device: Device, index: int) -> None:
        super().__init__(device, [index])


def capture_sequence(device: Device, sequence: Sequence[PatternSpec], out_dir: str | Path, camera: Camera, *,
                     force: bool = False, depth: np.ndarray | None = None, depth_info: DepthInfo | None = None,
                     notes: dict[str, Any] | None = None, **writer_args: Any) -> CaptureSet:
    """Show each pattern through ``device`` and write the captures as a new capture set."""
    with CaptureSetWriter(out_dir, camera, device.projector, depth_info=depth_info, notes=notes,
                          force=force, inputs=writer_args.pop("inputs", ()), **writer_args) as writer:
        for spec in sequence:
            frame = spec.image
            shot = device.capture_off() if spec.projector_off else device.project(frame)
            writer.add(spec.kind, shot, name=spec.name, frame=None if spec.projector_off else frame, **spec.params)
        if depth is not None:
            writer.add_depth(depth)
    return CaptureSet.load(out_dir, verify_images=False)


def _frame_key(frame: np.ndarray) -> str:
    # The 16-bit quantisation the capture set stores, so a frame matches its stored pattern file exactly.
    q = np.round(np.clip(np.asarray(frame, dtype=np.float32), 0, 1) * 65535.0).astype(np.uint16)
    return hashlib.sha1(q.tobytes() + str(q.shape).encode()).hexdigest()


class FolderDevice(Device):
    """Replays a capture set: ``project(frame)`` returns the capture recorded for exactly that frame.

    It lets the pipeline run offline on captures made with the user's own
    tools. A frame that was never captured raises a :class:`CaptureError`
    (export it, capture it, import again).
    """

    def __init__(self, capture_dir: str | Path) -> None:
        self.captures = CaptureSet.load(capture_dir)
        self.projector = self.captures.projector
        self.camera = self.captures.camera
        self._by_frame: dict[str, Entry] = {}
        keys: dict[str, str] = {}  # pattern file → key: patterns shown twice are stored once
        for e in self.captures.entries:
            if e.pattern:
                if e.pattern not in keys:
                    keys[e.pattern] = _frame_key(read_image(self.captures.pattern_file(e)))
                self._by_frame.setdefault(keys[e.pattern], e)

    def project(self, frame: np.ndarray) -> np.ndarray:
        f = self.check_frame(frame)
        entry = self._by_frame.get(_frame_key(f))
        if entry is None:
            raise CaptureError(f"this frame was never captured in {self.captures.path}; export it with the "
                               "sequence, capture it with your tools and import the captures again")
        return read_image(self.captures.file(entry))

    def capture_off(self) -> np.ndarray:
        if self.captures.entries_of("surface"):
            return self.captures.image("surface")
        return super().capture_off()


class LensRemovedDevice(Device):
    """A device whose camera images go through the lens taken out of the calibration's photographs.

    A capture set imported with a rig file (``import-captures --rig``, ``capture --rig``) or undistorted after
    (``undistort-captures``) holds photographs with the camera's lens distortion taken out, and its calibration
    lives in that pinhole camera; a live camera (or the lab's) still delivers the lens's image, which would sit
    up to the lens's displacement off the calibration, silently."""

    def __init__(self, device: Device, lens: RigLens) -> None:
        self.device, self.lens = device, lens
        self.projector = device.projector

    def __getattr__(self, name: str) -> Any:  # the live device's report, camera_size, …
        return getattr(self.device, name)

    @property
    def projectors(self) -> tuple[Projector, ...]:
        return self.device.projectors

    def project(self, frame: np.ndarray) -> np.ndarray:
        return self.lens.image(self.device.project(frame))

    def project_all(self, frames: Sequence[np.ndarray]) -> np.ndarray:
        return self.lens.image(self.device.project_all(frames))

    def capture_off(self) -> np.ndarray:
        return self.lens.image(self.device.capture_off())

    def close(self) -> None:
        self.device.close()
