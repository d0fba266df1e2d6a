"""The one video reader: the frames of a video file (.mp4, .mov, .avi, .mkv, …) through OpenCV's FFmpeg backend.

A show reads its targets one frame at a time, in order, so :class:`VideoReader`
decodes forwards and keeps its place; asking for an earlier frame reopens the
file. Frames are found by decoding (``grab``), never by seeking: seeking to a
frame number is exact only for some codecs, and a frame that depends on the
codec's seek would make a resumed show differ from a fresh one. Frame counts
are counted the same way (the container's own count can be an estimate), and a
file that decodes to fewer frames than its container lists is refused as damaged.
Video frames are 8-bit and, like 8-bit images, sRGB-encoded.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .capture.format import srgb_to_linear
from .errors import ImageError
from .imageio import check_pixels

#: File endings read as video (what FFmpeg inside OpenCV's wheels decodes).
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg", ".wmv", ".mts", ".m2ts")

#: Containers whose index lists exactly the frames decoded. Others' counts are estimates (duration × rate) or
#: count samples an edit list may hide (MP4, MOV), so they are allowed one frame over.
EXACT_COUNT_SUFFIXES = (".avi",)

_COUNTS: dict[tuple[str, int, int], int] = {}


def is_video(path: str | Path) -> bool:
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


def _open(path: Path):  # -> cv2.VideoCapture
    import cv2

    if not path.is_file():
        raise ImageError(f"video not found: {path}")
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    if not cap.isOpened():
        cap.release()
        raise ImageError(f"cannot open the video {path} (a format or codec FFmpeg in OpenCV does not read, or a "
                         "damaged file); convert it to .mp4 (H.264) or to numbered images")
    # The frame size its stream declares, before the first frame is decoded.
    width, height = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    try:
        check_pixels(width, height, f"the video {path}")
    except ImageError:
        cap.release()
        raise
    return cap


def frame_count(path: str | Path) -> int:
    """The number of frames of a video, counted by decoding (cached per path, size and modification time)."""
    path = Path(path)
    st = path.stat() if path.is_file() else None
    key = (str(path.absolute()), st.st_size if st else -1, st.st_mtime_ns if st else -1)
    if key not in _COUNTS:
        cap = _open(path)
        try:
            import cv2

            declared = cap.get(cv2.CAP_PROP_FRAME_COUNT)
            n = 0
            while cap.grab():
                n += 1
        finally:
            cap.release()
        if n == 0:
            raise ImageError(f"the video {path} holds no frame that can be decoded")
        # A damaged file (a few bytes changed) decodes to fewer frames than its container lists: the frames after
        # the lost one would carry the wrong numbers, and the neighbours of the damage are often corrupt too.
        slack = 0 if path.suffix.lower() in EXACT_COUNT_SUFFIXES else 1
        if declared > 0 and n + slack < round(declared):
            raise ImageError(f"the video {path} decodes to {n} frames but its container lists {round(declared)}: "
                             "the file is damaged or cut short (its frames would be misnumbered); copy or export "
                             "it again, or convert it to numbered images and check them")
        _COUNTS[key] = n
    return _COUNTS[key]


class VideoReader:
    """Frames of one video by index (0-based), decoded forwards (module doc). Close it, or use it as a context."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._cap: Any = None  # a cv2.VideoCapture once opened
        self._next = 0  # the index the next grab returns

    def read(self, index: int) -> np.ndarray:
        """Frame ``index`` as 8-bit RGB (H×W×3 uint8)."""
        import cv2

        if self._cap is None or index < self._next:
            self.close()
            self._cap, self._next = _open(self.path), 0
        while self._next < index:
            if not self._cap.grab():
                raise ImageError(f"the video {self.path} ends before frame {index + 1}")
            self._next += 1
        ok, bgr = self._cap.read()
        if not ok or bgr is None:
            raise ImageError(f"cannot decode frame {index + 1} of the video {self.path}")
        self._next += 1
        if bgr.ndim == 2:
            bgr = cv2.cvtColor(bgr, cv2.COLOR_GRAY2BGR)
        return np.ascontiguousarray(bgr[..., 2::-1])

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def __enter__(self) -> VideoReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def load_video_frame(reader: VideoReader, index: int, *, encoding: str = "auto") -> tuple[np.ndarray, str]:
    """A video frame as stage C reads a target: linear float H×W×3 in [0, 1], and a note on the decoding.

    8-bit frames are sRGB-encoded (``auto``/``srgb``) and are linearised, as 8-bit images are; ``linear`` takes
    the codes as linear light."""
    rgb = reader.read(index)
    img = rgb.astype(np.float32) / 255.0
    if encoding in ("auto", "srgb"):
        return srgb_to_linear(img).astype(np.float32), "sRGB-encoded 8-bit video frame, linearised"
    return img, "linear 8-bit video frame"
