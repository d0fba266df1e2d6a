"""The one image I/O module: 16-bit PNG for captures and projector inputs, EXR/.npy for float data.

Images in memory are float32, linear, H×W×3 (or H×W), values in [0, 1].
Nothing here applies an sRGB transfer or a tone map. Writes go to a temporary
name in the target folder and are renamed into place, so a crash never leaves
a half-written file under the real name.
"""

from __future__ import annotations

import contextlib
import errno
import os
import struct
import tempfile
import threading
import tokenize
import zipfile
import zlib
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")

#: The most pixels (width × height) an image, depth map or video frame may declare: 2**27 = 134 million, a 16K×8K
#: equirectangular panorama or a 100-megapixel medium-format photograph, 16 times a 4K projector's frame. Read
#: into float32 RGB that is 1.6 GB; a file that declares more (a few hundred bytes can declare 20000×20000) is
#: refused before it is decoded. The environment variable PROCAM_MAX_PIXELS sets another limit.
MAX_PIXELS = 1 << 27
MAX_PIXELS_VARIABLE = "PROCAM_MAX_PIXELS"

_given = os.environ.get(MAX_PIXELS_VARIABLE, "").strip()
# OpenCV's own limit (read once, when cv2 loads) backs ours up for a format whose header is not read here.
os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", _given if _given.isdigit() and int(_given) > 0 else str(MAX_PIXELS))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from .errors import ImageError, ProCamError, WriteError  # noqa: E402


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


def write_failed(path: str | Path, exc: OSError) -> WriteError:
    """The error to raise when writing ``path`` failed with ``exc``: says what is wrong and what to do."""
    why = {errno.ENOSPC: "the disk is full; free some space and run it again",
           errno.EDQUOT: "the disk quota is exceeded; free some space and run it again",
           errno.EACCES: "no permission to write there; choose another folder or change its permissions",
           errno.EPERM: "no permission to write there; choose another folder or change its permissions",
           errno.EROFS: "the file system is read-only; choose another folder"}.get(exc.errno)
    return WriteError(f"cannot write {path}: {why or (exc.strerror or exc)}")


def atomic_path(path: Path) -> tuple[Path, Path]:
    """A temporary sibling for ``path`` (same suffix, same folder, so rename is atomic), with the usual mode."""
    path = Path(path)
    if not path.parent.is_dir():
        raise ImageError(f"cannot write {path}: folder {path.parent} does not exist")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    except OSError as exc:
        raise write_failed(path, exc) from None
    os.close(fd)
    usual_mode(tmp)
    return Path(tmp), path


def write_atomic_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` under a temporary name renamed into place; a failed write is a :class:`WriteError`
    (a full disk is the user's to fix, not a bug) and leaves no temporary file."""
    tmp, final = atomic_path(path)
    try:
        tmp.write_bytes(data)
        os.replace(tmp, final)
    except OSError as exc:
        raise write_failed(final, exc) from None
    finally:
        tmp.unlink(missing_ok=True)


def _to_bgr(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3 and img.shape[2] == 3:
        return img[..., ::-1]
    if img.ndim == 3 and img.shape[2] == 4:
        return img[..., [2, 1, 0, 3]]
    return img


#: Images this process wrote, or decoded whole and found readable, by :func:`file_version`: their size (width,
#: height). A capture set's check that every file decodes (``CaptureSet.verify``) trusts these.
_KNOWN: dict[tuple[str, int, int, int, int], tuple[int, int]] = {}


def file_version(path: Path) -> tuple[str, int, int, int, int] | None:
    """What tells one version of a file from another without reading it (path, device, inode, size, modification
    time in nanoseconds), or None where it cannot be read: a rewritten or replaced file has another."""
    try:
        st = path.stat()
    except OSError:
        return None
    return (str(path.resolve()), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def known_size(path: Path) -> tuple[int, int] | None:
    """The size of the image at ``path`` if this process wrote this version of it or decoded it whole, else None."""
    version = file_version(path)
    return None if version is None else _KNOWN.get(version)


def remember_size(path: Path, size: tuple[int, int]) -> None:
    """Record that the image now at ``path`` decodes whole to ``size`` (width, height)."""
    version = file_version(path)
    if version is not None:
        _KNOWN[version] = (int(size[0]), int(size[1]))


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
    except OSError as exc:
        raise write_failed(final, exc) from None
    finally:
        tmp.unlink(missing_ok=True)
    remember_size(final, (img.shape[1], img.shape[0]))
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


def exif_block(path: str | Path) -> bytes | None:
    """The EXIF block (a TIFF structure) of a JPEG, or a TIFF file's own header and first IFDs; None for others."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".jpg", ".jpeg", ".tif", ".tiff"):
        return None
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 17)  # EXIF (APP1) sits at the start and is at most 64 KiB
    except OSError:
        return None
    if suffix in (".tif", ".tiff"):
        return head if head[:2] in (b"II", b"MM") else None
    if head[:2] != b"\xff\xd8":
        return None
    at = 2
    while at + 4 <= len(head) and head[at] == 0xFF:
        marker = head[at + 1]
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no more metadata
            break
        (length,) = struct.unpack(">H", head[at + 2:at + 4])
        data = head[at + 4:at + 2 + length]
        if marker == 0xE1 and data[:6] == b"Exif\x00\x00":
            return data[6:]
        at += 2 + length
    return None


def exif_orientation(path: str | Path) -> int:
    """The EXIF orientation of a JPEG (1–8, 1 = stored upright; 1 too for other files and JPEGs without EXIF)."""
    if Path(path).suffix.lower() not in (".jpg", ".jpeg"):
        return 1
    tiff = exif_block(path)
    return 1 if tiff is None else _tiff_orientation(tiff)



def apply_orientation(img: np.ndarray, orientation: int) -> np.ndarray:
    """Turn stored pixels upright for an EXIF orientation, exactly as OpenCV's ``IMREAD_COLOR`` does."""
    if orientation in (5, 6, 7, 8):
        img = np.swapaxes(img, 0, 1)
    flips = {2: (1,), 3: (0, 1), 4: (0,), 6: (1,), 7: (0, 1), 8: (0,)}.get(orientation, ())
    for axis in flips:
        img = np.flip(img, axis=axis)
    return np.ascontiguousarray(img)


def unit_float(pixels: np.ndarray) -> np.ndarray:
    """float32 in [0, 1] from 8- or 16-bit integer pixels (their full range); float pixels as they are. A new
    array, converted in one pass (converted, then divided, a 1280×1024 photograph took two; the same values), also
    from a strided view such as OpenCV's pixels put in RGB order."""
    a = np.asarray(pixels)
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(a.dtype)
    if scale is None:
        return a.astype(np.float32)
    return np.divide(a, np.float32(scale), out=np.empty(a.shape, np.float32))


#: The files :func:`read_image` reads, and so what a folder of images (targets, a show's frames, board photographs,
#: imported captures) is taken to hold: the one list every such folder is listed with.
READ_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp", ".hdr", ".npy")


def max_pixels() -> int:
    """The pixel limit: ``PROCAM_MAX_PIXELS`` when set (a positive whole number), else :data:`MAX_PIXELS`."""
    given = os.environ.get(MAX_PIXELS_VARIABLE, "").strip().replace("_", "")
    if not given:
        return MAX_PIXELS
    if not given.isdigit() or int(given) <= 0:
        raise ImageError(f"{MAX_PIXELS_VARIABLE} must be a positive whole number of pixels (e.g. {MAX_PIXELS}), "
                         f"got {os.environ[MAX_PIXELS_VARIABLE]!r}")
    return int(given)


def check_pixels(width: int, height: int, what: str) -> None:
    """Refuse ``what`` (a file, a video) whose frames are ``width`` × ``height``, beyond the pixel limit."""
    limit = max_pixels()
    if width < 0 or height < 0 or width * height > limit:
        raise ImageError(f"{what} declares {width}×{height} pixels ({width * height / 1e6:.1f} megapixels), more "
                         f"than the limit of {limit} ({limit / 1e6:.1f} megapixels); scale it down, or raise the "
                         f"limit with the environment variable {MAX_PIXELS_VARIABLE} if the memory allows it")


def npy_shape(path: Path) -> tuple[int, ...]:
    """The array shape a ``.npy`` file's header declares (read without loading the data)."""
    from numpy.lib import format as npy

    try:
        with open(path, "rb") as fh:
            version = npy.read_magic(fh)
            if version == (1, 0):
                shape, _, _ = npy.read_array_header_1_0(fh)
            else:
                shape, _, _ = npy.read_array_header_2_0(fh)
    except (*DAMAGED_ARRAYS, TypeError) as exc:
        raise ImageError(f"cannot read {path}: not a NumPy .npy file or a damaged one ({exc})") from None
    return tuple(int(v) for v in shape)


def _jpeg_size(fh) -> tuple[int, int] | None:
    fh.seek(2)
    while True:
        b = fh.read(1)
        while b == b"\xff":  # fill bytes before a marker
            b = fh.read(1)
        if not b:
            return None
        marker = b[0]
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # markers without a length
            continue
        head = fh.read(2)
        if len(head) < 2:
            return None
        (length,) = struct.unpack(">H", head)
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # a start of frame
            sof = fh.read(5)
            if len(sof) < 5:
                return None
            h, w = struct.unpack(">HH", sof[1:5])
            return (w, h) if h else None  # height 0: given later (DNL); OpenCV's own limit applies
        if marker in (0xD9, 0xDA):
            return None
        fh.seek(length - 2, 1)
        b = fh.read(1)
        if b != b"\xff":
            return None


def _tiff_size(fh) -> tuple[int, int] | None:
    head = fh.read(8)
    e = "<" if head[:2] == b"II" else ">"
    if struct.unpack(e + "H", head[2:4])[0] != 42:  # BigTIFF (43): OpenCV's own limit applies
        return None
    fh.seek(struct.unpack(e + "I", head[4:8])[0])
    raw = fh.read(2)
    if len(raw) < 2:
        return None
    found: dict[int, int] = {}
    for _ in range(struct.unpack(e + "H", raw)[0]):
        entry = fh.read(12)
        if len(entry) < 12:
            break
        tag, typ = struct.unpack(e + "HH", entry[:4])
        if tag in (256, 257) and typ in (3, 4):
            found[tag] = struct.unpack(e + ("H" if typ == 3 else "I"), entry[8:10] if typ == 3 else entry[8:12])[0]
    return (found[256], found[257]) if len(found) == 2 else None


def _exr_size(fh) -> tuple[int, int] | None:
    fh.seek(8)
    for _ in range(1000):  # attributes: name\0 type\0 size value, until an empty name
        name = b""
        while (c := fh.read(1)) not in (b"\0", b""):
            name += c
        if not name or len(name) > 255:
            return None
        typ = b""
        while (c := fh.read(1)) not in (b"\0", b""):
            typ += c
        raw = fh.read(4)
        if len(raw) < 4:
            return None
        (size,) = struct.unpack("<i", raw)
        if name == b"dataWindow" and typ == b"box2i" and size == 16:
            x0, y0, x1, y1 = struct.unpack("<4i", fh.read(16))
            return x1 - x0 + 1, y1 - y0 + 1
        fh.seek(size, 1)
    return None


def _radiance_size(fh) -> tuple[int, int] | None:
    fh.seek(0)
    for _ in range(200):
        line = fh.readline(4096)
        if not line:
            return None
        words = line.split()
        if len(words) == 4 and words[0] in (b"-Y", b"+Y", b"-X", b"+X") and words[2] in (b"-Y", b"+Y", b"-X", b"+X"):
            try:
                a, b = int(words[1]), int(words[3])
            except ValueError:
                return None
            return (b, a) if words[0].endswith(b"Y") else (a, b)
    return None


def declared_size(fh) -> tuple[int, int] | None:
    """(width, height) an image file's header declares (PNG, JPEG, TIFF, BMP, EXR, Radiance HDR), read from the
    binary file object ``fh`` without decoding; None for another format or a header not understood."""
    head = fh.read(32)
    try:
        if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
            return struct.unpack(">II", head[16:24])
        if head[:2] == b"\xff\xd8":
            return _jpeg_size(fh)
        if head[:4] in (b"II*\0", b"MM\0*"):
            fh.seek(0)
            return _tiff_size(fh)
        if head[:2] == b"BM" and len(head) >= 26:
            (info,) = struct.unpack("<I", head[14:18])
            w, h = struct.unpack("<HH", head[18:22]) if info == 12 else struct.unpack("<ii", head[18:26])
            return abs(w), abs(h)
        if head[:4] == b"\x76\x2f\x31\x01":
            return _exr_size(fh)
        if head[:2] == b"#?":
            return _radiance_size(fh)
    except (struct.error, OSError, ValueError):
        return None
    return None


def check_image_file(path: str | Path, what: str | None = None) -> tuple[int, ...] | None:
    """Refuse an image or ``.npy`` file that declares more pixels than the limit, before it is decoded.

    Returns the shape a ``.npy`` declares (None for an image file). A ``.npy``'s first two axes are its
    height and width; one that is not 2-D or 3-D is no image."""
    path = Path(path)
    what = what or str(path)
    if path.suffix.lower() == ".npy":
        shape = npy_shape(path)
        if len(shape) not in (2, 3):
            raise ImageError(f"{what} holds an array of shape {shape}, not an image (H×W or H×W×C)")
        check_pixels(shape[1], shape[0], what)
        if len(shape) == 3 and not 1 <= shape[2] <= 4:
            raise ImageError(f"{what} holds {shape[2]} channels per pixel; an image has 1, 3 or 4")
        return shape
    try:
        with open(path, "rb") as fh:
            size = declared_size(fh)
    except OSError as exc:
        raise ImageError(f"cannot read {what}: {exc.strerror or exc}") from None
    if size is not None:
        check_pixels(int(size[0]), int(size[1]), what)
    return None


def check_image_bytes(data: bytes, what: str) -> None:
    """:func:`check_image_file` for an image held in memory (a PNG about to be decoded)."""
    import io

    size = declared_size(io.BytesIO(data))
    if size is not None:
        check_pixels(int(size[0]), int(size[1]), what)


#: What NumPy raises on a cut, byte-flipped or foreign .npz/.npy file: its own header checks, and the zip and zlib
#: layers of an .npz (a member is inflated, and its CRC checked, only when it is read).
#: What NumPy raises on a damaged .npy/.npz: a cut file, a bad archive, or a header that no longer parses (its
#: dictionary is read as Python literals: a flipped byte gives a SyntaxError or a TokenError).
DAMAGED_ARRAYS = (OSError, ValueError, EOFError, KeyError, SyntaxError, tokenize.TokenError, zipfile.BadZipFile,
                  zlib.error)


def read_arrays(path: str | Path, names: Iterable[str] | None = None, *, error: type[ProCamError],
                remedy: str) -> dict[str, np.ndarray]:
    """The arrays ``names`` (every member when None) of an .npz file a step wrote, each read in full now. A missing
    file, or one that is cut, damaged, pickled or lacks one of ``names``, is ``error``, which says so and ends with
    ``remedy`` (the step that makes the file again)."""
    path = Path(path)
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise ValueError("a single array, not an .npz archive")
        with data:
            return {n: np.asarray(data[n]) for n in (data.files if names is None else names)}
    except FileNotFoundError:
        raise error(f"{path} is missing; {remedy}") from None
    except DAMAGED_ARRAYS as exc:
        why = f"{type(exc).__name__}: {exc}" if isinstance(exc, KeyError) else str(exc)
        raise error(f"{path} is damaged ({why}); {remedy}") from None


class _Kept:
    """The images :func:`kept_decoded` keeps: file version and channels → image, the least recently read first."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes, self.bytes = max_bytes, 0
        self.images: dict[tuple[Any, ...], np.ndarray] = {}
        self.lock = threading.Lock()

    def get(self, key: tuple[Any, ...]) -> np.ndarray | None:
        with self.lock:
            img = self.images.pop(key, None)
            if img is None:
                return None
            self.images[key] = img
            return img.copy()  # a reader may write into what it got

    def put(self, key: tuple[Any, ...], img: np.ndarray) -> None:
        if img.nbytes > self.max_bytes:
            return
        with self.lock:
            old = self.images.pop(key, None)
            self.bytes += img.nbytes - (0 if old is None else old.nbytes)
            self.images[key] = img.copy()
            while self.bytes > self.max_bytes:
                self.bytes -= self.images.pop(next(iter(self.images))).nbytes


_kept: _Kept | None = None


@contextlib.contextmanager
def kept_decoded(max_bytes: int = 1 << 30) -> Iterator[None]:
    """Within: each image :func:`read_image` decodes is kept (up to ``max_bytes``, the least recently read dropped
    first), and a read of the same version of the file (:func:`file_version`) is a copy of it. A step that reads a
    capture set in several passes (its check, the Gray code's decoding, the diagnosis's data and its session
    check) decoded each photograph three to five times: a real session's diagnosis spent 13 of its 19 s on it.
    Nested, the outer one holds."""
    global _kept
    if _kept is not None:
        yield
        return
    _kept = _Kept(max_bytes)
    try:
        yield
    finally:
        _kept = None


def read_image(path: str | Path, *, channels: int | None = 3, keep: bool = True) -> np.ndarray:
    """Read an image as float32 linear values; 8/16-bit files are scaled to [0, 1].

    ``channels=3`` returns H×W×3 (grey is repeated), ``1`` returns H×W,
    ``None`` returns what the file holds. A JPEG's EXIF orientation is applied
    (:func:`exif_orientation`), as OpenCV's ``IMREAD_COLOR`` would. Within :func:`kept_decoded` a file read before
    is not decoded again (``keep`` False: nor is this one kept, a file read once for its size).
    """
    path = Path(path)
    kept = _kept if keep else None
    version = file_version(path) if kept is not None else None
    if kept is not None and version is not None:
        img = kept.get((version, channels))
        if img is not None:
            return img
    img = _read_image(path, channels)
    if kept is not None and version is not None:
        kept.put((version, channels), img)
    return img


def _read_image(path: Path, channels: int | None) -> np.ndarray:
    if not path.is_file():
        raise ImageError(f"image not found: {path}")
    check_image_file(path)  # before decoding: a small file can declare billions of pixels
    whole_numbers = False  # 8- or 16-bit pixels, which cannot be NaN
    if path.suffix.lower() == ".npy":
        try:
            img = np.load(path, allow_pickle=False).astype(np.float32)
        except DAMAGED_ARRAYS as exc:
            raise ImageError(f"cannot read {path}: {exc}") from None
    else:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise ImageError(f"cannot read {path}: not an image or the file is damaged")
        # IMREAD_UNCHANGED ignores a JPEG's EXIF orientation (IMREAD_COLOR applies it): apply it here, so that a
        # photograph reads as every viewer shows it, whichever flags read it.
        raw = apply_orientation(raw, exif_orientation(path))
        img, whole_numbers = unit_float(_to_bgr(raw)), raw.dtype.kind in "ui"
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    if channels == 3:
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        elif img.shape[2] == 1:
            img = np.repeat(img, 3, axis=2)
    elif channels == 1 and img.ndim == 3:
        img = img[..., :3].mean(axis=2) if img.shape[2] >= 3 else img[..., 0]
    if not whole_numbers and not np.all(np.isfinite(img)):
        raise ImageError(f"{path} holds NaN or infinite values")
    return np.ascontiguousarray(img, dtype=np.float32)

