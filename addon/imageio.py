"""The one image I/O module: 16-bit PNG for captures and projector inputs, EXR/.npy for float data.

Images in memory are float32, linear, H×W×3 (or H×W), values in [0, 1].
Nothing here applies an sRGB transfer or a tone map. Writes go to a temporary
name in the target folder and are renamed into place, so a crash never leaves
a half-written file under the real name.
"""

from __future__ import annotations

import os
import struct
import tempfile
from pathlib import Path

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from .errors import ImageError  # noqa: E402


# Read once, in the importing (main) thread: os.umask can only be read by setting it, which would race
# with files other threads create.
_UMASK = os.umask(0o022)
os.umask(_UMASK)


def usual_mode(path: str | Path) -> None:
    """Give a file or folder the mode an ordinary ``open``/``mkdir`` would (0666/0777 less the umask).

    ``mkstemp``/``mkdtemp`` create private (0600/0700) names, which the rename
    into place would keep: a media server or a show crew's other account could
    not read the calibration or the frames.
    """
    path = Path(path)
    try:
        os.chmod(path, (0o777 if path.is_dir() else 0o666) & ~_UMASK)
    except OSError:
        pass  # a file system without POSIX modes: nothing to fix


def atomic_path(path: Path) -> tuple[Path, Path]:
    """A temporary sibling for ``path`` (same suffix, same folder, so rename is atomic), with the usual mode."""
    path = Path(path)
    if not path.parent.is_dir():
        raise ImageError(f"cannot write {path}: folder {path.parent} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    usual_mode(tmp)
    return Path(tmp), path


def write_atomic_bytes(path: Path, data: bytes) -> None:
    tmp, final = atomic_path(path)
    try:
        tmp.write_bytes(data)
        os.replace(tmp, final)
    finally:
        tmp.unlink(missing_ok=True)


def _to_bgr(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3 and img.shape[2] == 3:
        return img[..., ::-1]
    if img.ndim == 3 and img.shape[2] == 4:
        return img[..., [2, 1, 0, 3]]
    return img


def write_image(path: str | Path, image: np.ndarray) -> Path:
    """Write float [0,1] data as 16-bit PNG (``.png``), float EXR (``.exr``) or ``.npy``."""
    path = Path(path)
    img = np.asarray(image, dtype=np.float32)
    if not np.all(np.isfinite(img)):
        raise ImageError(f"refusing to write {path.name}: the image holds NaN or infinite values")
    suffix = path.suffix.lower()
    tmp, final = atomic_path(path)
    try:
        if suffix == ".png":
            data = np.round(np.clip(img, 0.0, 1.0) * 65535.0).astype(np.uint16)
            ok = cv2.imwrite(str(tmp), _to_bgr(data))
        elif suffix == ".exr":
            ok = cv2.imwrite(str(tmp), _to_bgr(img), [cv2.IMWRITE_EXR_TYPE, cv2.IMWRITE_EXR_TYPE_FLOAT])
        elif suffix == ".npy":
            with open(tmp, "wb") as fh:
                np.save(fh, img)
            ok = True
        else:
            raise ImageError(f"unsupported image type {suffix!r} for {path}; use .png, .exr or .npy")
        if not ok:
            raise ImageError(f"OpenCV could not write {path}")
        os.replace(tmp, final)
    finally:
        tmp.unlink(missing_ok=True)
    return final


#: EXIF orientation (tag 0x0112) → what turns the stored pixels upright, as OpenCV's IMREAD_COLOR does it.
ORIENTATIONS = {1: "upright", 2: "mirrored left-right", 3: "rotated 180°", 4: "mirrored top-bottom",
                5: "mirrored along the diagonal", 6: "rotated 90° (camera turned clockwise)",
                7: "mirrored along the anti-diagonal", 8: "rotated 90° (camera turned anticlockwise)"}


def _tiff_orientation(tiff: bytes) -> int:
    """Orientation (tag 0x0112) in IFD0 of a TIFF structure (an EXIF block); 1 when absent or unreadable."""
    if len(tiff) < 8 or tiff[:2] not in (b"II", b"MM"):
        return 1
    e = "<" if tiff[:2] == b"II" else ">"
    (ifd,) = struct.unpack(e + "I", tiff[4:8])
    if ifd + 2 > len(tiff):
        return 1
    (n,) = struct.unpack(e + "H", tiff[ifd:ifd + 2])
    for i in range(n):
        at = ifd + 2 + 12 * i
        if at + 12 > len(tiff):
            break
        tag, typ, count = struct.unpack(e + "HHI", tiff[at:at + 8])
        if tag == 0x0112 and typ == 3 and count >= 1:
            (value,) = struct.unpack(e + "H", tiff[at + 8:at + 10])
            return value if value in ORIENTATIONS else 1
    return 1


def exif_orientation(path: str | Path) -> int:
    """The EXIF orientation of a JPEG (1–8, 1 = stored upright; 1 too for other files and JPEGs without EXIF)."""
    path = Path(path)
    if path.suffix.lower() not in (".jpg", ".jpeg"):
        return 1
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 17)  # EXIF (APP1) sits at the start and is at most 64 KiB
    except OSError:
        return 1
    if head[:2] != b"\xff\xd8":
        return 1
    at = 2
    while at + 4 <= len(head) and head[at] == 0xFF:
        marker = head[at + 1]
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no more metadata
            break
        (length,) = struct.unpack(">H", head[at + 2:at + 4])
        data = head[at + 4:at + 2 + length]
        if marker == 0xE1 and data[:6] == b"Exif\x00\x00":
            return _tiff_orientation(data[6:])
        at += 2 + length
    return 1


def apply_orientation(img: np.ndarray, orientation: int) -> np.ndarray:
    """Turn stored pixels upright for an EXIF orientation, exactly as OpenCV's ``IMREAD_COLOR`` does."""
    if orientation in (5, 6, 7, 8):
        img = np.swapaxes(img, 0, 1)
    flips = {2: (1,), 3: (0, 1), 4: (0,), 6: (1,), 7: (0, 1), 8: (0,)}.get(orientation, ())
    for axis in flips:
        img = np.flip(img, axis=axis)
    return np.ascontiguousarray(img)


def unit_float(pixels: np.ndarray) -> np.ndarray:
    """float32 in [0, 1] from 8- or 16-bit integer pixels (their full range); float pixels as they are."""
    a = np.asarray(pixels)
    if a.dtype == np.uint8:
        return a.astype(np.float32) / 255.0
    if a.dtype == np.uint16:
        return a.astype(np.float32) / 65535.0
    return a.astype(np.float32)


#: The files :func:`read_image` reads, and so what a folder of images (targets, a show's frames, board photographs,
#: imported captures) is taken to hold: the one list every such folder is listed with.
READ_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp", ".hdr", ".npy")


def read_image(path: str | Path, *, channels: int | None = 3) -> np.ndarray:
    """Read an image as float32 linear values; 8/16-bit files are scaled to [0, 1].

    ``channels=3`` returns H×W×3 (grey is repeated), ``1`` returns H×W,
    ``None`` returns what the file holds. A JPEG's EXIF orientation is applied
    (:func:`exif_orientation`), as OpenCV's ``IMREAD_COLOR`` would.
    """
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"image not found: {path}")
    if path.suffix.lower() == ".npy":
        try:
            img = np.load(path, allow_pickle=False).astype(np.float32)
        except (ValueError, OSError) as exc:
            raise ImageError(f"cannot read {path}: {exc}") from None
    else:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise ImageError(f"cannot read {path}: not an image or the file is damaged")
        # IMREAD_UNCHANGED ignores a JPEG's EXIF orientation (IMREAD_COLOR applies it): apply it here, so that a
        # photograph reads as every viewer shows it, whichever flags read it.
        raw = apply_orientation(raw, exif_orientation(path))
        img = _to_bgr(unit_float(raw))
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    if channels == 3:
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        elif img.shape[2] == 1:
            img = np.repeat(img, 3, axis=2)
    elif channels == 1 and img.ndim == 3:
        img = img[..., :3].mean(axis=2) if img.shape[2] >= 3 else img[..., 0]
    if not np.all(np.isfinite(img)):
        raise ImageError(f"{path} holds NaN or infinite values")
    return np.ascontiguousarray(img, dtype=np.float32)
