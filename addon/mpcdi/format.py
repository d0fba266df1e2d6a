"""The VESA MPCDI file format: an ``.mpcdi`` zip archive of ``mpcdi.xml`` and, per region, a geometry warp (PFM) and
alpha and beta blend maps (PNG); written and read here, with no ProCam calibration in sight.

What the format says, and where it says it (read before changing anything here):

* VESA MPCDI Standard v2.0 (19 May 2015), §3.1–3.4: one ZIP archive, extension ``.mpcdi``, every file at its
  root (no sub-folders), one ``mpcdi.xml``; §3.5.2–3.5.3: the root ``MPCDI`` with ``profile`` (``2d``, ``3d``,
  ``a3``, ``sl``), ``geometry`` (1–2), ``color`` (1–5), ``date`` (``yyyy-MM-dd HH:mm:ss``), ``version="2.0"``;
  ``display`` › ``buffer id xResolution yResolution`` › ``region id x y xSize ySize xResolution yResolution``
  (x, y, sizes normalised in the buffer; resolutions in pixels); in ``sl`` each region has a ``frustum`` (yaw,
  pitch, roll, rightAngle, leftAngle, upAngle, downAngle, degrees) and a ``coordinateFrame`` (posx … rollz), and a
  buffer holds one region; a ``color`` tag per region (``decode``, ``encode``); ``files`` › ``fileset region=…`` ›
  ``geometryWarpFile`` (path, interpolation; geometricUnit and originOf3DData for ``a3``/``sl``), ``alphaMap``
  (path, componentDepth, bitDepth, gammaEmbedded), ``betaMap`` (path, componentDepth, bitDepth), ``distortionMap``
  (path; ``sl``). Optional ``extensionSet`` › ``extension name hasExternalFiles`` (§3.10). §2.4: a media server
  shows ``Pf = Pi·α·(1 − β) + β``. §3.6: the warp is a uniform grid in "fill layout" (the first sample's top left is
  the raster's top left, the last sample's bottom right its bottom right), 32-bit floats, at least 2×2, stored as a
  three-component PFM whose endianness is the PFM's own (its scale's sign); §3.6.2: 2D data are normalised
  coordinates (R = x, G = y) "the same as OpenGL UV mapping", B an error estimate (NaN when not computed; 1 with
  NaN coordinates where the data are unknown). §3.7: blend maps are PNG, 1 or 3 components, 8 or 16 bits, at
  least 2×2, any size. The text: the PDF kept in github.com/drwrose/PyMPCDI (``doc/MPCDI v2.0.pdf``, commit
  f3253ed), and v1.0a beside it.
* The reference reader, Scalable Display Technologies' MPCDI Library (BSD; the copy read: github.com/scaredyfish/MPCDI,
  ``src/IO/mpcdiReaderIntern.cpp``, ``mpcdiXMLStrings.h``, ``mpcdiPfmIO.cpp``), which Unreal's nDisplay embeds, is
  v1.0 and spells names its own way: ``level`` (v1.0's single level, 1–4) where v2.0 has ``geometry``/``color``,
  ``Xresolution``/``Yresolution``, ``xsize``/``ysize``, ``originof3DData``; it matches names exactly (tinyxml2) and
  *requires* ``geometricUnit``, ``interpolation`` and ``originof3DData`` in every geometryWarpFile, even in 2d.
  (drwrose/PyMPCDI's ``MpcdiFile.py`` asks for ``XResolution``/``YResolution``; it is not a reader this module
  aims at.) The standard says tag and attribute names are case-insensitive (§3.5.2), so this writer writes each
  name in the v2.0 spelling **and**, where the reference library's differs, in its spelling too, with the same
  value; this reader matches names without regard to case.
* What else the reference library reads, found by reading ProCam's files with it (``scripts/check_mpcdi_reference.sh``
  builds it and compares every value it reads with what was written; results, "Media servers: MPCDI"): its
  ``Reader::Read`` refuses a file whose ``version`` has a major number above 1 ("MPACS Version: 2.0 is not
  supported", error 16) unless the caller turns CheckVersionSupported off, which nDisplay does not; so the file
  says ``version="1.0"`` — it holds every v1.0 name, and v2.0's additions (``geometry``, ``color``, the ``color``
  tag, ``extensionSet``) are tags and attributes a v1.0 reader passes over. Its ``DataMap`` holds one byte per
  component, and ``PNGReadWrite::Read`` copies libpng's row bytes into it one byte a sample: a 16-bit PNG's high
  and low bytes become two samples and the map comes out scrambled; so the blend maps are 8-bit
  (:attr:`Mpcdi.map_bits`; 16 on request, for readers known to take it). Its PFM reader takes ``PF``, width, height,
  scale and one byte, then the rows last-first in the host's byte order whatever the scale's sign: little-endian,
  as written here.
* Rows of a PFM: netpbm's PFM stores the bottom row first, and the reference library writes and reads it so
  (``PfmIO::Write`` runs ``y`` from the last row to the first); §3.6.1's "the first pixel is the top left" describes
  the image, not the byte order. Here a warp array's row 0 is the top of the projector's raster.
* Which way v points: both open readers flip it — nDisplay's texture matrix for the 2d profile is (u, 1 − v)
  (``MPCDIData.cpp``), PyMPCDI's ``flipMat`` likewise, after placing the region by (x + xsize·u, y + ysize·v) — so
  a stored v is OpenGL's, 0 at the bottom, and a region's ``y`` is measured from the buffer's bottom edge. This
  module keeps that convention in the file and says so in :class:`Region`.

Bad input is a :class:`~..errors.MpcdiError` that says what is wrong.
"""

from __future__ import annotations

import math
import re
import time
import xml.etree.ElementTree as ET
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import MpcdiError, ProCamError
from ..imageio import check_image_bytes

#: the profiles a reader may meet (§3.5), and those this module writes
PROFILES = ("2d", "3d", "a3", "sl")
WRITTEN_PROFILES = ("2d", "sl")
#: §2.7 and §3.5.2's values
INTERPOLATIONS = ("linear", "keystone", "smooth", "unknown")
UNITS = ("mm", "cm", "dm", "m", "in", "ft", "yd", "unknown")
ORIGINS = ("centerOfMass", "idealEyePoint", "floorCenter", "unknown")
#: Level 1 of the 2d profile caps the warp grid at 32×32 samples (Table 3-2); finer grids are level 2.
LEVEL1_GRID = 32
#: the descriptor's name inside the archive (§3.5.2)
XML_NAME = "mpcdi.xml"
#: ProCam's own extension (§3.10): read by ProCam, ignored by readers that do not know it
EXTENSION = "procam"
#: a member of the archive: a plain file name (§3.3: no sub-folders)
_MEMBER = re.compile(r"[A-Za-z0-9_.-]+")
#: the largest archive member read back (a zip bomb declares little and inflates to much)
MAX_MEMBER_BYTES = 1 << 30


@dataclass(frozen=True)
class Frustum:
    """A region's view frustum (§2.2.1, Table 2-1), degrees: the rotation (yaw right, pitch up, roll clockwise, in
    that order) and the field of view's edges (left and down negative)."""

    yaw: float
    pitch: float
    roll: float
    right_angle: float
    left_angle: float
    up_angle: float
    down_angle: float

    TAGS = ("yaw", "pitch", "roll", "rightAngle", "leftAngle", "upAngle", "downAngle")

    def values(self) -> tuple[float, ...]:
        return (self.yaw, self.pitch, self.roll, self.right_angle, self.left_angle, self.up_angle, self.down_angle)


@dataclass(frozen=True)
class CoordinateFrame:
    """A shader-lamp projector's place (§2.2.2): its position and the unit vectors of its yaw, pitch and roll axes, in
    the world frame of the file's 3D data."""

    position: tuple[float, float, float]
    yaw_axis: tuple[float, float, float]
    pitch_axis: tuple[float, float, float]
    roll_axis: tuple[float, float, float]

    TAGS = ("posx", "posy", "posz", "yawx", "yawy", "yawz", "pitchx", "pitchy", "pitchz", "rollx", "rolly", "rollz")

    def values(self) -> tuple[float, ...]:
        return (*self.position, *self.yaw_axis, *self.pitch_axis, *self.roll_axis)


@dataclass
class Region:
    """One projector's region of a buffer and its files.

    ``x, y, xsize, ysize``: where the region lies in its buffer, normalised, ``y`` from the buffer's **bottom** edge
    (OpenGL's way, module doc). ``resolution``: the projector's (width, height) in pixels. ``warp``: (rows, cols, 3)
    float32, row 0 the top of the projector's raster, a uniform grid in fill layout; in 2D (R, G) the normalised
    (u, v) of the region the sample shows, v up, B the error estimate, NaN coordinates where unknown; in 3D the
    world point. ``alpha``/``beta``: (h, w) or (h, w, 3) in [0, 1], row 0 at the top (beta None: no beta map).
    ``alpha_gamma``: the gamma already applied to the alpha map (1: linear). ``distortion``: the ``sl`` lens
    distortion map (as a 2D warp). ``extra``: ProCam's extension files of this region, name → (h, w, 3) map.
    """

    id: str
    x: float
    y: float
    xsize: float
    ysize: float
    resolution: tuple[int, int]
    warp: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray | None = None
    alpha_gamma: float = 1.0
    interpolation: str = "linear"
    frustum: Frustum | None = None
    frame: CoordinateFrame | None = None
    distortion: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    #: the id of the buffer it belongs to
    buffer: str = "display"


@dataclass
class Mpcdi:
    """A whole MPCDI file: its profile, its buffers (id → (width, height) in pixels, 0 for unknown), its regions in
    order, the unit and origin of 3D data, and ProCam's extension (``extension``: plain JSON-able values written as
    XML attributes of its ``definitions``; None: no extension)."""

    profile: str
    buffers: dict[str, tuple[int, int]]
    regions: list[Region]
    geometric_unit: str = "unknown"
    origin: str = "unknown"
    date: str = ""
    version: str = "1.0"  # module doc: the reference library refuses 2.0; the v2.0 names are written beside v1.0's
    geometry_level: int = 0  # read back from a file; written from the regions (:func:`levels`)
    color_level: int = 0
    extension: dict[str, str] | None = None
    map_bits: int = 8  # the alpha and beta maps' bit depth, 8 or 16 (module doc: the reference library reads 8)

    def region(self, id: str) -> Region:
        for r in self.regions:
            if r.id == id:
                return r
        raise MpcdiError(f"the MPCDI file has no region {id!r}; its regions are {[r.id for r in self.regions]}")


# -- PFM ----------------------------------------------------------------------------------------------------------

def pfm_bytes(data: np.ndarray) -> bytes:
    """A three-component PFM of (rows, cols, 3) float data, row 0 at the top: little-endian (scale −1), the bottom
    row first (netpbm's PFM, as the reference library writes it)."""
    a = np.asarray(data, dtype="<f4")
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 2 or a.shape[1] < 2:
        raise MpcdiError(f"a geometry warp must be a grid of at least 2×2 samples of 3 values, got shape {a.shape}")
    header = f"PF\n{a.shape[1]} {a.shape[0]}\n-1.0\n".encode("ascii")
    return header + np.ascontiguousarray(a[::-1]).tobytes()


def read_pfm(data: bytes, what: str = "PFM") -> np.ndarray:
    """A PFM file (``PF`` three components or ``Pf`` one) as (rows, cols, 3|1) float32, row 0 at the top; either
    endianness (the scale's sign)."""
    tokens: list[bytes] = []
    pos = 0
    # The header: a magic word and three numbers, each followed by one whitespace byte (netpbm).
    while len(tokens) < 4:
        m = re.compile(rb"\s*(\S+)\s").match(data, pos)
        if m is None:
            raise MpcdiError(f"{what} is not a PFM file: its header is cut or malformed")
        tokens.append(m.group(1))
        pos = m.end()
    magic = tokens[0]
    if magic not in (b"PF", b"Pf"):
        raise MpcdiError(f"{what} is not a PFM file (it starts with {magic[:8]!r}, not PF or Pf)")
    try:
        width, height, scale = int(tokens[1]), int(tokens[2]), float(tokens[3])
    except ValueError:
        raise MpcdiError(f"{what}: the PFM header's size and scale are not numbers ({tokens[1:]!r})") from None
    channels = 3 if magic == b"PF" else 1
    if width < 1 or height < 1 or scale == 0 or not math.isfinite(scale):
        raise MpcdiError(f"{what}: a PFM of {width}×{height} with scale {scale} is not valid")
    need = width * height * channels * 4
    if len(data) - pos != need:
        raise MpcdiError(f"{what}: a {width}×{height} PFM of {channels} component(s) holds {need} bytes of samples, "
                         f"but {len(data) - pos} follow its header; the file is cut or damaged")
    dtype = "<f4" if scale < 0 else ">f4"
    a = np.frombuffer(data, dtype=dtype, count=width * height * channels, offset=pos)
    return a.reshape(height, width, channels)[::-1].astype(np.float32)


# -- blend maps ---------------------------------------------------------------------------------------------------

def png_bytes(image: np.ndarray, bits: int = 8) -> bytes:
    """A blend map as a PNG of 1 or 3 components (grey or RGB), ``bits`` 8 or 16, values in [0, 1]."""
    a = np.asarray(image, np.float32)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)) or min(a.shape[:2]) < 2:
        raise MpcdiError(f"a blend map must be an image of at least 2×2 pixels, 1 or 3 components, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise MpcdiError("a blend map holds NaN or infinite values")
    top = 65535 if bits == 16 else 255
    q = np.round(np.clip(a, 0.0, 1.0) * top).astype(np.uint16 if bits == 16 else np.uint8)
    ok, buf = cv2.imencode(".png", q[..., ::-1] if q.ndim == 3 else q)
    if not ok:
        raise MpcdiError("OpenCV could not encode a blend map as PNG")
    return bytes(buf)


def read_png(data: bytes, what: str) -> tuple[np.ndarray, int]:
    """A blend map PNG as float32 in [0, 1] ((h, w) grey or (h, w, 3) RGB) and its bit depth."""
    if not data.startswith(b"\x89PNG\r\n\x1a\n"):
        raise MpcdiError(f"{what} is not a PNG file (§3.7: blend maps are PNG)")
    try:
        check_image_bytes(data, what)
    except ProCamError as exc:  # a PNG declaring more pixels than ProCam reads
        raise MpcdiError(f"{what}: {exc}") from None
    raw = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise MpcdiError(f"{what} is damaged: OpenCV cannot decode it")
    bits = 16 if raw.dtype == np.uint16 else 8
    img = raw.astype(np.float32) / (65535.0 if bits == 16 else 255.0)
    if img.ndim == 3:
        img = img[..., 2::-1] if img.shape[2] >= 3 else img[..., 0]
    if min(img.shape[:2]) < 2:
        raise MpcdiError(f"{what} is {img.shape[1]}×{img.shape[0]}; blend maps are at least 2×2 (§3.7)")
    return np.ascontiguousarray(img), bits


# -- levels -------------------------------------------------------------------------------------------------------

def levels(m: Mpcdi) -> tuple[int, int, int]:
    """(v2.0 geometry level, v2.0 colour level, v1.0 level) of what ``m`` holds (Tables 3-2, 3-3; v1.0a Fig. 3-2).
    Geometry: 1 when every 2d warp grid is at most 32×32, else 2 (up to per pixel); ``sl`` with a distortion map
    is 2. Colour: 2 (single-channel alpha and beta, a gamma to decode and encode) when every map has one component,
    4 when one has three (RGB alpha and beta) — level 4 asks for a decode LUT, which ProCam does not write, so it
    writes one component. v1.0: 1 (a grid ≤ 32², no beta), 2 (with beta), 4 (finer grids)."""
    fine = any(r.warp.shape[0] > LEVEL1_GRID or r.warp.shape[1] > LEVEL1_GRID for r in m.regions)
    geometry = 2 if fine or (m.profile == "sl" and any(r.distortion is not None for r in m.regions)) else 1
    rgb = any(a is not None and a.ndim == 3 for r in m.regions for a in (r.alpha, r.beta))
    color = 4 if rgb else 2
    beta = any(r.beta is not None for r in m.regions)
    return geometry, color, 4 if geometry == 2 else (2 if beta else 1)


# -- writing ------------------------------------------------------------------------------------------------------

def _num(v: float) -> str:
    return repr(float(v)) if math.isfinite(v) else "0.0"


def _sub(parent: ET.Element, tag: str, text: Any = None, **attrs: str) -> ET.Element:
    el = ET.SubElement(parent, tag, attrs)
    if text is not None:
        el.text = _num(text) if isinstance(text, float) else str(text)
    return el


def _check(m: Mpcdi) -> None:
    if m.profile not in WRITTEN_PROFILES:
        raise MpcdiError(f"ProCam writes the MPCDI profiles {', '.join(WRITTEN_PROFILES)}, not {m.profile!r}")
    if not m.regions:
        raise MpcdiError("an MPCDI file needs at least one region (one per projector)")
    if m.map_bits not in (8, 16):
        raise MpcdiError(f"blend maps are PNGs of 8 or 16 bits (§3.7), not {m.map_bits}")
    ids = [r.id for r in m.regions]
    if len(set(ids)) != len(ids) or not all(_MEMBER.fullmatch(i) for i in ids):
        raise MpcdiError(f"region ids must be unique plain names (letters, digits, _ . -), got {ids}")
    for r in m.regions:
        if r.buffer not in m.buffers:
            raise MpcdiError(f"region {r.id} is in buffer {r.buffer!r}, which the file does not declare")
        box = (r.x, r.y, r.xsize, r.ysize)
        if not all(math.isfinite(v) for v in box) or not (0 <= r.x <= 1 and 0 <= r.y <= 1 and 0 < r.xsize <= 1
                                                          and 0 < r.ysize <= 1):
            raise MpcdiError(f"region {r.id}: x, y must be in [0, 1] and its sizes in (0, 1], got {box}")
        if min(r.resolution) < 1:
            raise MpcdiError(f"region {r.id}: a resolution of {r.resolution} pixels")
        if r.interpolation not in INTERPOLATIONS:
            raise MpcdiError(f"region {r.id}: interpolation {r.interpolation!r} is not one of {INTERPOLATIONS}")
        if m.profile == "sl" and (r.frustum is None or r.frame is None or r.distortion is None):
            raise MpcdiError(f"region {r.id}: the sl profile needs a frustum, a coordinate frame and a distortion map "
                             "per region (§3.5.2)")
    if m.profile == "sl" and len({r.buffer for r in m.regions}) != len(m.regions):
        raise MpcdiError("in the sl profile each buffer holds one region (§3.5.2)")
    if m.geometric_unit not in UNITS or m.origin not in ORIGINS:
        raise MpcdiError(f"geometricUnit {m.geometric_unit!r} / originOf3DData {m.origin!r} are not the standard's")
    if m.profile == "sl" and m.origin == "idealEyePoint":
        raise MpcdiError("the sl profile's 3D data cannot have their origin at idealEyePoint (§3.5.2)")


def file_names(region: Region) -> dict[str, str]:
    """The archive's file of each of a region's parts (the reference library's names: GeometryWarpFile-ID.pfm …)."""
    names = {"warp": f"GeometryWarpFile-{region.id}.pfm", "alpha": f"AlphaMap-{region.id}.png",
             "beta": f"BetaMap-{region.id}.png", "distortion": f"DistortionMap-{region.id}.pfm"}
    names.update({k: f"{k}-{region.id}.png" for k in region.extra})
    return names


def to_xml(m: Mpcdi) -> bytes:
    """``mpcdi.xml`` of ``m`` (module doc: v2.0 names, and the reference library's where they differ)."""
    _check(m)
    geometry, color, level = levels(m)
    date = m.date or time.strftime("%Y-%m-%d %H:%M:%S")
    root = ET.Element("MPCDI", {"profile": m.profile, "geometry": str(geometry), "color": str(color),
                                "level": str(level), "date": date, "version": m.version})
    display = _sub(root, "display")
    for bid, (bw, bh) in m.buffers.items():
        battrs = {"id": bid}
        if bw > 0 and bh > 0:  # optional (§3.5.2)
            battrs.update(xResolution=str(bw), yResolution=str(bh), Xresolution=str(bw), Yresolution=str(bh))
        buffer = _sub(display, "buffer", **battrs)
        for r in (r for r in m.regions if r.buffer == bid):
            w, h = r.resolution
            region = _sub(buffer, "region", id=r.id, x=_num(r.x), y=_num(r.y), xSize=_num(r.xsize),
                          ySize=_num(r.ysize), xsize=_num(r.xsize), ysize=_num(r.ysize), xResolution=str(w),
                          yResolution=str(h), Xresolution=str(w), Yresolution=str(h))
            if r.frustum is not None:
                fr = _sub(region, "frustum")
                for tag, v in zip(Frustum.TAGS, r.frustum.values()):
                    _sub(fr, tag, float(v))
            if r.frame is not None:
                cf = _sub(region, "coordinateFrame")
                for tag, v in zip(CoordinateFrame.TAGS, r.frame.values()):
                    _sub(cf, tag, float(v))
            colour = _sub(region, "color")
            # ProCam's levels are projector input levels, linear in light: nothing to decode or encode (γ = 1).
            _sub(colour, "decode", type="gamma", gamma="1.0")
            _sub(colour, "encode", type="gamma", gamma="1.0")
    files = _sub(root, "files")
    for r in m.regions:
        names = file_names(r)
        fs = _sub(files, "fileset", region=r.id)
        gw = _sub(fs, "geometryWarpFile")
        _sub(gw, "path", names["warp"])
        _sub(gw, "geometricUnit", m.geometric_unit)
        _sub(gw, "originOf3DData", m.origin)
        _sub(gw, "originof3DData", m.origin)  # the reference library's spelling, which it requires
        _sub(gw, "interpolation", r.interpolation)
        am = _sub(fs, "alphaMap")
        _sub(am, "path", names["alpha"])
        _sub(am, "componentDepth", 3 if r.alpha.ndim == 3 else 1)
        _sub(am, "bitDepth", m.map_bits)
        _sub(am, "gammaEmbedded", float(r.alpha_gamma))
        if r.beta is not None:
            bm = _sub(fs, "betaMap")
            _sub(bm, "path", names["beta"])
            _sub(bm, "componentDepth", 3 if r.beta.ndim == 3 else 1)
            _sub(bm, "bitDepth", m.map_bits)
        if r.distortion is not None:
            _sub(_sub(fs, "distortionMap"), "path", names["distortion"])
    extras = [(r, k) for r in m.regions for k in r.extra]
    if m.extension is not None or extras:
        ext = _sub(_sub(root, "extensionSet"), "extension", name=EXTENSION,
                   hasExternalFiles="True" if extras else "False")
        _sub(ext, "definitions", **{k: str(v) for k, v in (m.extension or {}).items()})
        if extras:
            fset = _sub(ext, "fileSet")
            for r, k in extras:
                _sub(fset, "file", file_names(r)[k], id=f"{k}-{r.id}", region=r.id, kind=k)
    ET.indent(root, space=" ")
    return b'<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding="utf-8") + b"\n"


def archive_members(m: Mpcdi) -> dict[str, bytes]:
    """Every file of the archive, ``mpcdi.xml`` first."""
    out = {XML_NAME: to_xml(m)}
    for r in m.regions:
        names = file_names(r)
        out[names["warp"]] = pfm_bytes(r.warp)
        out[names["alpha"]] = png_bytes(r.alpha, m.map_bits)
        if r.beta is not None:
            out[names["beta"]] = png_bytes(r.beta, m.map_bits)
        if r.distortion is not None:
            out[names["distortion"]] = pfm_bytes(r.distortion)
        for k, v in r.extra.items():
            out[names[k]] = png_bytes(v, 16)  # ProCam's own files: no other reader takes them
    return out


def write_archive(m: Mpcdi, fh: Any) -> None:
    """The ``.mpcdi`` zip of ``m`` into the binary file ``fh`` (deflated: the warp floats shrink little, the maps'
    flat areas much)."""
    with zipfile.ZipFile(fh, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=6) as z:
        for name, data in archive_members(m).items():
            z.writestr(name, data)


# -- reading ------------------------------------------------------------------------------------------------------

def _lower(name: str) -> str:
    return name.split("}")[-1].lower()


def _attr(el: ET.Element, name: str, what: str, kind: type = str, required: bool = True) -> Any:
    """An attribute by name, without regard to case (§3.5.2), converted to ``kind``."""
    for k, v in el.attrib.items():
        if k.lower() == name.lower():
            try:
                return kind(v)
            except ValueError:
                raise MpcdiError(f"{what}: attribute {name}={v!r} is not a {kind.__name__}") from None
    if required:
        raise MpcdiError(f"{what} has no {name} attribute")
    return None


def _child(el: ET.Element, tag: str) -> ET.Element | None:
    return next((c for c in el if _lower(c.tag) == tag.lower()), None)


def _children(el: ET.Element, tag: str) -> list[ET.Element]:
    return [c for c in el if _lower(c.tag) == tag.lower()]


def _text(el: ET.Element, tag: str, what: str, kind: type = str, required: bool = True) -> Any:
    c = _child(el, tag)
    if c is None or c.text is None or not c.text.strip():
        if required:
            raise MpcdiError(f"{what} has no {tag}")
        return None
    try:
        return kind(c.text.strip())
    except ValueError:
        raise MpcdiError(f"{what}: {tag} {c.text.strip()!r} is not a {kind.__name__}") from None


class _Archive:
    """The members of an ``.mpcdi`` zip, each checked for size before it is inflated."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self.zip = zipfile.ZipFile(path)
            self.infos = {i.filename: i for i in self.zip.infolist()}
        except (OSError, zipfile.BadZipFile, ValueError) as exc:
            raise MpcdiError(f"{path} is not an MPCDI file: {exc} (an .mpcdi file is a ZIP archive)") from None

    def read(self, name: str, what: str) -> bytes:
        if not _MEMBER.fullmatch(name):
            raise MpcdiError(f"{self.path}: {what} is named {name!r}; files of an MPCDI archive lie at its root (§3.3)")
        info = self.infos.get(name)
        if info is None:
            raise MpcdiError(f"{self.path}: {what} {name!r} is named in mpcdi.xml but not in the archive")
        if info.file_size > MAX_MEMBER_BYTES:
            raise MpcdiError(f"{self.path}: {name} inflates to {info.file_size} bytes; refusing a member over "
                             f"{MAX_MEMBER_BYTES}")
        try:
            return self.zip.read(name)
        except (OSError, zipfile.BadZipFile, ValueError, EOFError) as exc:
            raise MpcdiError(f"{self.path}: {name} is damaged ({exc})") from None

    def close(self) -> None:
        self.zip.close()


def _frustum(el: ET.Element, what: str) -> Frustum:
    return Frustum(*(float(_text(el, t, f"{what}'s frustum", float)) for t in Frustum.TAGS))


def _frame(el: ET.Element, what: str) -> CoordinateFrame:
    v = [float(_text(el, t, f"{what}'s coordinateFrame", float)) for t in CoordinateFrame.TAGS]
    return CoordinateFrame((v[0], v[1], v[2]), (v[3], v[4], v[5]), (v[6], v[7], v[8]), (v[9], v[10], v[11]))


def read_mpcdi(path: str | Path) -> Mpcdi:
    """Read an ``.mpcdi`` file back: its descriptor and every region's files, checked against the structure the
    standard sets (module doc); names are matched without regard to case."""
    path = Path(path)
    if not path.is_file():
        raise MpcdiError(f"MPCDI file not found: {path}")
    archive = _Archive(path)
    try:
        return _read(archive, path)
    finally:
        archive.close()


def _read(archive: _Archive, path: Path) -> Mpcdi:
    if XML_NAME not in archive.infos:
        raise MpcdiError(f"{path} holds no {XML_NAME}; every MPCDI archive has one (§3.5.2)")
    try:
        root = ET.fromstring(archive.read(XML_NAME, "the descriptor"))
    except ET.ParseError as exc:
        raise MpcdiError(f"{path}: {XML_NAME} is not well-formed XML ({exc})") from None
    if _lower(root.tag) != "mpcdi":
        raise MpcdiError(f"{path}: the root of {XML_NAME} is <{root.tag}>, not <MPCDI>")
    profile = _attr(root, "profile", "MPCDI")
    if profile not in PROFILES:
        raise MpcdiError(f"{path}: profile {profile!r} is not one of {', '.join(PROFILES)}")
    version = _attr(root, "version", "MPCDI", required=False) or ""
    geometry = _attr(root, "geometry", "MPCDI", int, required=False) or _attr(root, "level", "MPCDI", int,
                                                                                required=False) or 0
    color = _attr(root, "color", "MPCDI", int, required=False) or 0
    display = _child(root, "display")
    files = _child(root, "files")
    if display is None or files is None:
        raise MpcdiError(f"{path}: {XML_NAME} needs one display and one files tag (§3.5.2)")
    buffers: dict[str, tuple[int, int]] = {}
    regions: list[Region] = []
    filesets = {_attr(f, "region", "a fileset"): f for f in _children(files, "fileset")}
    unit = origin = "unknown"
    map_bits = 8
    for b in _children(display, "buffer"):
        bid = _attr(b, "id", "a buffer")
        buffers[bid] = (_attr(b, "xResolution", f"buffer {bid}", int, required=False) or 0,
                        _attr(b, "yResolution", f"buffer {bid}", int, required=False) or 0)
        rs = _children(b, "region")
        if not rs:
            raise MpcdiError(f"{path}: buffer {bid} holds no region (§3.5.2: one or more)")
        for r in rs:
            rid = _attr(r, "id", f"a region of buffer {bid}")
            what = f"{path}: region {rid}"
            fs = filesets.get(rid)
            if fs is None:
                raise MpcdiError(f"{what} has no fileset in <files>")
            gw, am, bm, dm = (_child(fs, t) for t in ("geometryWarpFile", "alphaMap", "betaMap", "distortionMap"))
            if gw is None or am is None:
                raise MpcdiError(f"{what}: its fileset needs a geometryWarpFile and an alphaMap (§3.5.2)")
            warp = read_pfm(archive.read(_text(gw, "path", f"{what}'s geometryWarpFile"), "its geometry warp"),
                            f"{what}'s geometry warp")
            if warp.shape[2] != 3 or min(warp.shape[:2]) < 2:
                raise MpcdiError(f"{what}: its geometry warp must be a 3-component PFM of at least 2×2 (§3.6), got "
                                 f"{warp.shape[1]}×{warp.shape[0]}×{warp.shape[2]}")
            unit = _text(gw, "geometricUnit", what, required=False) or unit
            origin = _text(gw, "originOf3DData", what, required=False) or origin
            interpolation = _text(gw, "interpolation", what, required=False) or "unknown"
            alpha, bits = read_png(archive.read(_text(am, "path", f"{what}'s alphaMap"), "its alpha map"),
                                f"{what}'s alpha map")
            depth = _text(am, "componentDepth", f"{what}'s alphaMap", int)
            if depth != (3 if alpha.ndim == 3 else 1):
                raise MpcdiError(f"{what}: its alphaMap declares componentDepth {depth} but its PNG has "
                                 f"{3 if alpha.ndim == 3 else 1} component(s)")
            gamma = _text(am, "gammaEmbedded", f"{what}'s alphaMap", float, required=False) or 1.0
            map_bits = max(map_bits, bits)
            beta = None
            if bm is not None:
                beta, bits = read_png(archive.read(_text(bm, "path", f"{what}'s betaMap"), "its beta map"),
                                   f"{what}'s beta map")
                map_bits = max(map_bits, bits)
            distortion = None
            if dm is not None:
                distortion = read_pfm(archive.read(_text(dm, "path", f"{what}'s distortionMap"), "its distortion "
                                                   "map"), f"{what}'s distortion map")
            fr, cf = _child(r, "frustum"), _child(r, "coordinateFrame")
            regions.append(Region(
                rid, _attr(r, "x", what, float), _attr(r, "y", what, float), _attr(r, "xSize", what, float),
                _attr(r, "ySize", what, float), (_attr(r, "xResolution", what, int),
                                                 _attr(r, "yResolution", what, int)),
                warp, alpha, beta, float(gamma), interpolation, None if fr is None else _frustum(fr, what),
                None if cf is None else _frame(cf, what), distortion, buffer=bid))
    if not regions:
        raise MpcdiError(f"{path}: the display holds no buffer with a region")
    extension = None
    for ext in _children(_child(root, "extensionSet") or ET.Element("x"), "extension"):
        if _attr(ext, "name", "an extension", required=False) != EXTENSION:
            continue  # another tool's extension: not ours to read
        defs = _child(ext, "definitions")
        extension = dict(defs.attrib) if defs is not None else {}
        fset = _child(ext, "fileSet")
        for f in ([] if fset is None else _children(fset, "file")):
            r = next((x for x in regions if x.id == f.get("region")), None)
            kind = f.get("kind") or ""
            if r is not None and _MEMBER.fullmatch(kind) and f.text:
                r.extra[kind], _ = read_png(archive.read(f.text.strip(), f"extension file {kind}"),
                                            f"{path}: region {r.id}'s {kind}")
    m = Mpcdi(profile, buffers, regions, unit, origin, _attr(root, "date", "MPCDI", required=False) or "", version,
              int(geometry), int(color), extension, map_bits)
    for r in regions:
        if not all(math.isfinite(v) for v in (r.x, r.y, r.xsize, r.ysize)) or r.xsize <= 0 or r.ysize <= 0:
            raise MpcdiError(f"{path}: region {r.id} has a place in its buffer that is not a box: "
                             f"{(r.x, r.y, r.xsize, r.ysize)}")
        if min(r.resolution) < 1:
            raise MpcdiError(f"{path}: region {r.id} declares a resolution of {r.resolution}")
    return m
