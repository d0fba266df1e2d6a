"""The capture step: a capture set from the virtual lab, or from photographs of an exported pattern sequence.

Three front doors, each writing one new folder atomically:

* :func:`run_lab` — the lab renders every calibration pattern of a rig on a
  surface with Cycles and injected effects; the truth is sealed outside the set;
* :func:`run_patterns` — the numbered pattern frames of a projector, for users
  who project and photograph with their own tools;
* :func:`run_import` — those photographs, matched to their frames, as a capture set.

The capture-set format itself (reading, validating, writing) is
:mod:`..capture.format`'s, which the lab and the import share.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..rig.lens import RigLens
from ..capture.sequence import export_sequence, load_sequence
from ..capture.photos import add_projector_captures, import_captures, undistort_captures
from ..capture.format import CaptureSet
from ..errors import CaptureError, LabError, RigError
from ..lab.board import BoardTruth, default_supersample, render_board_sessions
from ..lab.effects import effect_help, parse_effects
from ..lab.truth import check_supersample, make_truth, parse_projector_effects, scaled_rig
from ..lab.lab import check_lab_outputs, run_lab as render_lab
from ..lab.layouts import LAYOUTS as PROJECTOR_LAYOUTS, MAX_PROJECTORS
from ..rig.demo import demo_rig
from ..options import option, same_option, validate
from ..progress import Cancel, Progress, quiet
from ..outputs import check_replaceable, file_sha256, writer_lock
from ..capture.patterns import LAYOUTS
from ..rig.model import Camera, Intrinsics, Projector, Rig, intrinsics_from_fov, projector_intrinsics_from_throw
from ..surface.mesh import SurfaceMesh
from . import layout
from . import rig as rig_step


def percent_pair(text: str) -> tuple[float, float]:
    """``A,B`` in percent → two fractions."""
    try:
        a, b = (float(v) / 100.0 for v in text.split(","))
    except ValueError:
        raise ValueError(f"expected two percentages A,B (e.g. 0,127), got {text!r}") from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise ValueError(f"expected two finite percentages A,B (e.g. 0,127), got {text!r}")
    return a, b


def board_size(text: str) -> tuple[int, int]:
    """``COLSxROWS`` inner corners."""
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"board must be COLSxROWS inner corners, e.g. 9x7; got {text!r}") from None
    return cols, rows


def pixel_size(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` in whole pixels."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"expected WIDTHxHEIGHT in pixels, e.g. 1920x1080; got {text!r}") from None
    if w < 8 or h < 6 or w > 8192 or h > 8192:
        raise ValueError(f"expected a size from 8x6 to 8192x8192 pixels, got {text!r}")
    return w, h


#: side-by-side footprints overlap by a fifth unless --overlap says otherwise
LAB_OVERLAP = 0.2


@dataclass(frozen=True)
class LabOptions:
    """What ``procam lab`` and Run Virtual Lab ask for."""

    out: Path
    #: a mesh too: Blender's ProCam Surface. The lab's sidebar is Run Virtual Lab's dialog, whose fields are the
    #: operator's own (own_field): their labels come from here
    surface: str | Path | SurfaceMesh = option(
        "curve", label="Surface", own_field=True,
        help="plane, curve, vedge, hedge, or an .obj/.ply file (rig frame, metres)")
    effects: str = option("", label="Effects", own_field=True, check=parse_effects,
                          help="NAME=STRENGTH[,NAME.PARAM=VALUE…], or a preset ('realistic'); the effects, their "
                               "parameters and the presets:\n" + effect_help())
    seed: int = option(0, min=0, label="Seed", own_field=True,
                       help="seed of every random stream; the same seed repeats the result")
    samples: int = option(16, min=1, label="Samples", own_field=True,
                          help="Cycles samples per pixel (default 16); checker and Gray-code frames, which are only "
                               "binarised, get a quarter (at least 4) unless --full-binary")
    scale: float = option(1.0, min=0.05, max=2.0, label="Resolution Scale", own_field=True,
                          help="resolution scale: 1 = camera 640×480, projector 800×600 (default); 0.5 halves both")
    graycode: bool = option(True, negate="--no-graycode", label="Gray Code", own_field=True,
                            help="render the Gray-code patterns (off: faster)")
    full_binary: bool = option(False, help="render checker and Gray-code frames with the full --samples too")
    truth: Path | None = option(None, label="Truth File", own_field=True,
                                help="sealed truth JSON, outside the capture set (default: OUT.truth.json beside OUT)")
    #: the rig to use instead of the demo rig (Blender's scene rig)
    rig: Rig | None = None
    surface_source: str | None = None
    camera_size: tuple[int, int] = option(
        (640, 480), parse=pixel_size, metavar="WxH",
        help="the demo camera's resolution before --scale (default 640x480; at another aspect than 4:3 its pixels "
             "stay square, 58° across)")
    projector_size: tuple[int, int] = option(
        (800, 600), parse=pixel_size, metavar="WxH",
        help="the demo projector's native resolution before --scale (default 800x600; e.g. 1920x1080: at another "
             "aspect than 4:3 its pixels stay square, same throw and lens shift, input ¾ of its width)")
    #: (right, up; fractions of the image)
    projector_shift: tuple[float, float] | None = option(
        None, parse=percent_pair, metavar="RIGHT,UP",
        help="the demo projector's lens shift in % of its image (default 0,15; a real projector may sit far below "
             "its image, e.g. 0,127)")
    #: (focal length fraction, vertical shift in image heights)
    nominal_error: tuple[float, float] = option(
        (0.0, 0.0), parse=percent_pair, metavar="FOCAL,SHIFT",
        help="give the pipeline a projector spec that is wrong by FOCAL % in focal length (throw ratio) and SHIFT % "
             "of the height in vertical lens shift, as a data sheet may be (default 0,0)")
    camera_fov_error: float = option(
        0.0, metavar="DEGREES",
        help="give the pipeline a camera whose horizontal field of view is DEGREES off, as a guessed or spec-sheet "
             "FoV may be (default 0)")
    supersample: int = option(
        1, check=check_supersample, metavar="N",
        help="render the camera at N times its resolution and average down, so that lens distortion resamples "
             "finer pixels than the camera's, as a real lens does (default 1; 2 costs 4×)")
    projectors: int = option(
        1, min=1, max=MAX_PROJECTORS, metavar="N",
        help="how many projectors light the surface (default 1): copies of the demo projector placed by --layout, "
             "each one's sequence captured while the others show black; depth and the surface photo are taken once")
    projector_layout: str = option(
        "side-by-side", flag="--layout", choices=PROJECTOR_LAYOUTS,
        help="with --projectors above 1: side-by-side (footprints in a row, overlapping by --overlap), stacked "
             "(all on the same area from slightly different positions) or grid (footprints in rows and columns, 2×2 "
             "for 4, overlapping by --overlap both ways) (default side-by-side)")
    overlap: float = option(
        LAB_OVERLAP, min=0.0, max=0.9, metavar="FRACTION",
        help="side-by-side and grid: how much neighbouring footprints overlap, as a fraction of a footprint's width "
             "(and, in a grid, of its height down) (default 0.2)")
    projector_effects: str = option(
        "", metavar="K:EFFECTS[;K:EFFECTS…]", check=parse_projector_effects,
        help="projectors with effects of their own, numbered from 1, in place of the projector effects of "
             "--effects: e.g. '2:response=0.6,crosstalk=0.3' for a second projector of another make; a "
             "black_level there is that projector's panel leak only (the room's ambient light stays --effects') "
             "(default none)")
    other_forms: float = option(
        0.0, min=0.0, max=1.0, metavar="STRENGTH",
        help="add a rig whose effects have forms ProCam does not model (a response and colour mixing that vary "
             "over the frame, an off-centre vignette, a disk blur growing across the frame, a camera knee curve "
             "and JPEG photos), at STRENGTH 0 (off, default) to 1, on top of --effects: what a real rig does to "
             "the models")
    force: bool = False

    def paths(self) -> tuple[Path, Path]:
        """The capture set and the truth file, absolute (so that "." or "../x" get proper names)."""
        out = Path(os.path.abspath(self.out))
        truth = Path(os.path.abspath(self.truth)) if self.truth else out.with_name(out.name + ".truth.json")
        return out, truth


def run_lab(options: LabOptions, progress: Progress | None = None, cancel: Cancel | None = None) -> CaptureSet:
    """Render a calibration capture set in the virtual lab; every argument is checked before the first render."""
    validate(options, LabError)
    if options.projector_layout == "stacked" and options.overlap != LAB_OVERLAP:
        raise LabError("--overlap sets how far side-by-side or grid footprints overlap; stacked projectors all light "
                       "the same area, so it has no meaning there: leave --overlap out, or use --layout side-by-side "
                       "or grid")
    out, truth_path = options.paths()
    # What the truth must not be written into: the mesh read, and any step folder (another set's capture.json…).
    named = isinstance(options.surface, (str, Path)) and Path(options.surface).is_file()
    mesh = Path(options.surface) if named else None
    inputs = (mesh, *layout.step_folders_around(truth_path))
    check_lab_outputs(out, truth_path, force=options.force, inputs=inputs)  # before reading any mesh
    check_supersample(options.supersample)
    # another run of this capture set or truth file is refused before any work
    with writer_lock(out), writer_lock(truth_path):
        return _run_lab(options, out, truth_path, inputs, progress, cancel)


def _run_lab(options: LabOptions, out: Path, truth_path: Path, inputs: tuple[Path | None, ...],
             progress: Progress | None, cancel: Cancel | None) -> CaptureSet:
    truth = make_truth(options.surface, effects=options.effects, seed=options.seed, samples=options.samples,
                       scale=options.scale, rig=options.rig, surface_source=options.surface_source,
                       camera_size=options.camera_size, projector_size=options.projector_size,
                       projector_shift=options.projector_shift, nominal_error=options.nominal_error,
                       camera_fov_error=options.camera_fov_error, projectors=options.projectors,
                       layout=options.projector_layout, overlap=options.overlap,
                       projector_effects=options.projector_effects, other_forms=options.other_forms)
    (progress or quiet)(f"surface {truth.surface_source}, effects {truth.effects.spec}"
                        + (f", other forms at {truth.other_forms:g}" if truth.other_forms else ""), 0.0)
    return render_lab(truth, out, truth_path=truth_path, force=options.force, inputs=inputs, graycode=options.graycode,
                      fast_binary=not options.full_binary, supersample=options.supersample, progress=progress,
                      cancel=cancel)


@dataclass(frozen=True)
class BoardOptions:
    """What ``procam lab-board`` asks for: board sessions of the demo rig for ``procam calibrate-rig``."""

    out: Path
    board: tuple[int, int] = option((9, 7), parse=board_size, metavar="COLSxROWS",
                                    help="inner corners (default 9x7)")
    square: float = option(0.06, min=1e-6, metavar="METRES", help="square size (default 0.06)")
    poses: int = option(6, min=3, help="board poses (default 6; at least 3)")
    effects: str = option("", check=parse_effects,
                          help="lab effects, e.g. distortion=0.5,noise=0.3 (default none)")
    samples: int = option(4, min=1, help="Cycles samples per pixel (default 4)")
    scale: float = same_option(LabOptions, "scale", label="",
                               help="resolution scale: 1 = camera 640×480, projector 800×600")
    seed: int = same_option(LabOptions, "seed", label="")
    truth: Path | None = same_option(LabOptions, "truth", label="", own_field=False,
                                     help="sealed truth file (default: OUT.truth.json beside OUT)")
    force: bool = False
    supersample: int | None = option(
        None, check=check_supersample, metavar="N",
        help="render the camera at N times its resolution and average down, so that lens distortion resamples "
             "finer pixels than the camera's, as a real lens does (default 2 when --effects distort the camera's "
             "lens, which costs 4× the rendering; else 1)")


def run_board(options: BoardOptions, progress: Progress | None = None, cancel: Cancel | None = None) -> BoardTruth:
    """Render the board sessions (``lab/board.py``) and seal their truth beside them."""
    validate(options, LabError)  # a bad effect fails before the first render
    supersample = check_supersample(options.supersample if options.supersample is not None
                                    else default_supersample(options.effects))
    return render_board_sessions(scaled_rig(demo_rig(), options.scale), Path(options.out), board=options.board,
                                 square=options.square, poses=options.poses, effects=options.effects,
                                 samples=options.samples, seed=options.seed, truth_path=options.truth,
                                 force=options.force, supersample=supersample, progress=progress,
                                 inputs=layout.step_folders_around(options.truth or Path(options.out)),
                                 cancel=cancel)


@dataclass(frozen=True)
class PatternsOptions:
    """What ``procam patterns`` and Export Patterns ask for."""

    projector: Projector
    out: Path
    camera: Camera | None = None
    checker: int | None = option(None, min=1, help="checkerboard square size in pixels (default: ~1/12 of the input)")
    area: str = option("input", choices=("input", "frame"),
                       help="draw patterns inside the projector input (default) or over the whole frame")
    graycode: bool = option(True, negate="--no-graycode", help="the Gray-code frames (off: left out)")
    validation: bool = option(True, negate="--no-validation", help="the validation frames (off: left out)")
    seed: int = option(0, min=0, help="seed of the random validation patterns")
    layout: str = option(
        "procam", choices=LAYOUTS, label="Order", own_field=True,
        help="procam (default): surface photo, black, white, checkerboards, Gray code, validation; opencv: OpenCV's "
             "structured-light order (Gray code, each bit then its inverse, x then y; then white and black; no "
             "surface photo or checkerboard), as procam calibrate-rig's board sessions use: import such photographs "
             "with it")
    projector_number: int = option(
        1, min=1, max=MAX_PROJECTORS, metavar="K", label="Projector Number", own_field=True,
        help="several projectors: the sequence of projector K (default 1), for its own size and lens; 2 and above "
             "leave out the surface photo (taken once, with projector 1's) and are recorded, so that import-captures "
             "--add-to tells the projectors' sequences apart")
    force: bool = False


@dataclass(frozen=True)
class ProjectorSheet:
    """The projector as a spec sheet gives it (native size, input area, throw ratio, lens shift): the command
    line's form of :class:`Projector` for ``patterns`` and ``capture``."""

    projector_width: int = option(required=True, min=1, help="native projector width (px)")
    projector_height: int = option(required=True, min=1, help="native projector height (px)")
    input_width: int | None = option(None, min=1, help="projector input width inside the frame (default: frame)")
    input_height: int | None = option(None, min=1, help="projector input height (default: frame)")
    throw_ratio: float = option(1.0, check=lambda t: projector_intrinsics_from_throw(1, 1, t),
                                help="nominal throw ratio, distance / width (default 1.0)")
    shift_x: float = option(0.0, help="nominal lens shift right, fraction of the width")
    shift_y: float = option(0.0, help="nominal lens shift up, fraction of the height")

    def projector(self) -> Projector:
        validate(self, RigError)
        intr = projector_intrinsics_from_throw(self.projector_width, self.projector_height, self.throw_ratio,
                                               self.shift_x, self.shift_y)
        if (self.input_width is None) != (self.input_height is None):
            raise RigError("give both --input-width and --input-height, or neither")
        return Projector(intr, input_size=(self.input_width, self.input_height) if self.input_width else None)


def run_patterns(options: PatternsOptions, progress: Progress | None = None,
                 cancel: Cancel | None = None) -> Path:
    """Write the numbered calibration pattern frames and ``sequence.json``; returns the folder."""
    validate(options, CaptureError)
    (progress or quiet)("writing the pattern frames", 0.0)
    out = export_sequence(options.projector, options.out, checker_size=options.checker, area=options.area,
                          seed=options.seed, camera=options.camera, graycode=options.graycode,
                          validation=options.validation, layout=options.layout,
                          projector_index=options.projector_number - 1, force=options.force)
    (progress or quiet)(f"{len(load_sequence(out).frames)} frames", 1.0)
    return out


@dataclass(frozen=True, kw_only=True)
class PhotoSettings:
    """How photographs become a capture set: what importing a folder of them and capturing them live share."""

    camera_fov: float = option(
        60.0, min=1.0, max=179.0, label="Camera Field of View", own_field=True,
        help="nominal horizontal field of view of the camera in degrees (default 60), when nothing else gives the "
             "camera's K")
    depth_path: Path | None = option(
        None, flag="--depth", metavar="FILE", label="Depth", own_field=True,
        help="depth of the scene seen from the camera: .npy/.exr in metres, 16-bit .png/.tif in millimetres (0 = no "
             "depth; iPhone, RealSense, Azure Kinect), or a .ply point cloud in the camera's OpenCV frame (x right, "
             "y down, z forward). A shift of a few pixels against the photographs is found and corrected (with a "
             "warning)")
    depth_units: str = option(
        "auto", choices=("auto", "m", "mm"), label="Depth Units", own_field=True,
        help="units of the depth values; auto (default) detects millimetres given as metres and says so")
    #: the depth sensor's native resolution (a point cloud is projected at this size; default the camera's);
    #: the command line gives it as :class:`DepthSensorSize`
    depth_native_size: tuple[int, int] | None = None
    rig: Path | None = option(
        None, metavar="RIG_JSON", label="Rig Calibration", own_field=True,
        help="a rig calibration from `procam calibrate-rig`: calibrated camera and projector K, the camera's lens "
             "distortion removed from every photograph (and the depth map), the projector's pose when the rig was "
             "calibrated with --square in metres")
    check_exposure: bool = option(
        True, negate="--no-exposure-check", label="Check Exposure", own_field=True,
        help="refuse a session whose exposure or white balance seems to change between photographs (complementary "
             "patterns that do not add up to white + black); off: import anyway")

    def photo_settings(self) -> dict[str, Any]:
        """These settings as keywords, to hand them on to an import."""
        return {f.name: getattr(self, f.name) for f in fields(PhotoSettings)}


@dataclass(frozen=True)
class DepthSensorSize:
    """The depth sensor's native size as the command line and the import dialog give it: two numbers, both or
    neither."""

    depth_native_width: int | None = option(
        None, min=1, label="Depth Sensor Width", own_field=True,
        help="native depth-sensor width (e.g. 256); a .ply point cloud is projected at this size")
    depth_native_height: int | None = option(None, min=1, label="Depth Sensor Height", own_field=True,
                                             help="native depth-sensor height (e.g. 192)")

    def size(self) -> tuple[int, int] | None:
        validate(self, CaptureError)
        w, h = self.depth_native_width, self.depth_native_height
        if w is None and h is None:
            return None
        if w is None or h is None:
            raise CaptureError("give both the depth sensor's width and height (--depth-native-width, "
                               "--depth-native-height), or neither")
        return w, h


@dataclass(frozen=True)
class CameraSize:
    """The photographs' expected size (checked against them), as ``import-captures`` takes it."""

    camera_width: int | None = option(None, min=1, help="expected capture width (checked)")
    camera_height: int | None = option(None, min=1, help="expected capture height (checked)")

    def camera(self, fov: float) -> Camera | None:
        validate(self, CaptureError)
        if (self.camera_width is None) != (self.camera_height is None):
            raise CaptureError("give both --camera-width and --camera-height, or neither")
        return Camera(intrinsics_from_fov(self.camera_width, self.camera_height, fov)) if self.camera_width else None


@dataclass(frozen=True)
class ImportOptions(PhotoSettings):
    """What ``procam import-captures`` and Import Captures ask for."""

    sequence_dir: Path
    photos_dir: Path
    out: Path
    #: the camera model (size checked against the photographs); None: from the photographs and ``camera_fov``
    camera: Camera | None = None
    encoding: str = option("auto", choices=("auto", "srgb", "linear"), label="Encoding", own_field=True,
                           help="how the captures are encoded; auto: 8-bit files are sRGB, 16-bit/float are linear")
    #: a depth map already in memory (metres, aligned with the camera up to a few pixels)
    depth: np.ndarray | None = None
    add_to: Path | None = option(
        None, metavar="SET", label="Add to Capture Set", own_field=True,
        help="several projectors: a NEW capture set at --out holding SET's captures and this projector's (the "
             "next one, numbered after SET's), photographed by SET's camera while every other projector showed "
             "black; SET is read, never changed (--out must be another folder). The depth and the surface photo "
             "are SET's; with --rig, the same camera calibration as SET's")
    force: bool = False


def rig_models(rig_path: Path, projector: Projector, camera: Camera | None = None
               ) -> tuple[Camera, Projector, RigLens]:
    """The camera and projector of a rig calibration, for a sequence shown by ``projector`` (its size and input
    area are kept; its K, and its pose when the rig's lengths are metres, come from the rig)."""
    cal = rig_step.read(rig_path)
    if cal.projector_size != projector.intrinsics.size:
        raise CaptureError(f"{rig_path} calibrates a {cal.projector_size[0]}×{cal.projector_size[1]} projector, but "
                           f"the pattern sequence is for {projector.intrinsics.size[0]}×"
                           f"{projector.intrinsics.size[1]}; calibrate the rig at the projector's native size")
    if camera is not None and camera.intrinsics.size != cal.camera_size:
        raise CaptureError(f"{rig_path} calibrates a {cal.camera_size[0]}×{cal.camera_size[1]} camera, but the "
                           f"camera given is {camera.intrinsics.size[0]}×{camera.intrinsics.size[1]}")
    try:
        proj = replace(projector, intrinsics=Intrinsics.from_opencv_matrix(*cal.projector_size, cal.projector_matrix),
                       lens_distortion=tuple(float(v) for v in cal.projector_distortion))
        if cal.metric:
            proj = proj.with_pose(cal.camera_from_projector)
        lens = RigLens(Intrinsics.from_opencv_matrix(*cal.camera_size, cal.camera_matrix), cal.camera_distortion,
                       f"{Path(rig_path).resolve()} (sha256 {file_sha256(Path(rig_path))[:12]})", cal.metric)
        cam = Camera(lens.pinhole)  # what the photographs become once the lens is taken out
    except RigError as exc:
        raise CaptureError(f"{rig_path} does not describe a usable rig: {exc}") from None
    return cam, proj, lens


@dataclass(frozen=True)
class UndistortOptions:
    """What ``procam undistort-captures`` asks for: a capture set, the rig calibration of its camera, a new folder."""

    captures_dir: Path
    rig: Path = option(required=True, metavar="RIG_JSON",
                       help="a rig calibration from `procam calibrate-rig` of the camera that took the set")
    out: Path
    force: bool = False


def run_undistort(options: UndistortOptions, progress: Progress | None = None,
                  cancel: Cancel | None = None) -> CaptureSet:
    """The capture set with the rig's camera lens taken out (:func:`..capture.photos.undistort_captures`)."""
    del cancel  # a few seconds of image remapping
    check_replaceable(options.out, force=options.force, what=layout.CAPTURES.what, replaceable=layout.CAPTURES.holds,
                      inputs=(options.captures_dir, options.rig), error=CaptureError)
    with writer_lock(options.out):  # another run of this output is refused before any work
        captures = CaptureSet.load(options.captures_dir)
        _, _, lens = rig_models(options.rig, captures.projector, captures.camera)
        return undistort_captures(captures, lens, options.out, force=options.force,
                                  inputs=(options.captures_dir, options.rig), progress=progress)


def run_import(options: ImportOptions, progress: Progress | None = None,
               cancel: Cancel | None = None) -> CaptureSet:
    """Turn photographs of an exported pattern sequence into a new capture set (with ``add_to``: a new capture
    set of that set's projectors and this one, :func:`_run_add`)."""
    validate(options, CaptureError)
    check_replaceable(options.out, force=options.force, what=layout.CAPTURES.what, replaceable=layout.CAPTURES.holds,
                      inputs=(options.sequence_dir, options.photos_dir, options.depth_path, options.rig,
                              options.add_to),
                      error=CaptureError)
    with writer_lock(options.out):  # another run of this output is refused before any work
        if options.add_to is not None:
            return _run_add(options, options.add_to, progress)
        return _import(options, progress)


def _import(options: ImportOptions, progress: Progress | None) -> CaptureSet:
    camera, projector, lens = options.camera, None, None
    if options.rig is not None:
        camera, projector, lens = rig_models(options.rig, load_sequence(options.sequence_dir).projector, camera)
    (progress or quiet)("matching the photographs to their frames", 0.0)
    return import_captures(options.sequence_dir, options.photos_dir, camera, projector, options.out,
                           encoding=options.encoding, camera_fov=options.camera_fov, depth=options.depth,
                           depth_path=options.depth_path, depth_units=options.depth_units,
                           depth_native_size=options.depth_native_size, undistort=lens,
                           check_session=options.check_exposure, progress=progress, force=options.force,
                           inputs=(options.rig,))


def _run_add(options: ImportOptions, add_to: Path, progress: Progress | None) -> CaptureSet:
    """One more projector's photographs and the captures of the set ``add_to`` as a new capture set at
    ``options.out`` (:func:`..capture.photos.add_projector_captures`); ``add_to`` is never changed."""
    if options.depth is not None or options.depth_path is not None or options.depth_native_size is not None:
        raise CaptureError(f"the depth is taken once, with the first projector's photographs: a projector added to "
                           f"{add_to} keeps its depth; import without --depth")
    base = CaptureSet.load(add_to)
    if len(base.projectors) >= MAX_PROJECTORS:
        raise CaptureError(f"{add_to} holds {len(base.projectors)} projectors, the most a capture set takes "
                           f"({MAX_PROJECTORS})")
    cam = base.camera.intrinsics.size
    if options.camera is not None and options.camera.intrinsics.size != cam:
        size = options.camera.intrinsics.size
        raise CaptureError(f"the camera given is {size[0]}×{size[1]}, but {add_to}'s camera is {cam[0]}×{cam[1]}: "
                           "every projector's sequence must be photographed by the same camera")
    projector, lens = None, None
    if options.rig is not None:
        _, projector, lens = rig_models(options.rig, load_sequence(options.sequence_dir).projector, base.camera)
    (progress or quiet)("matching the photographs to their frames", 0.0)
    return add_projector_captures(base, options.sequence_dir, options.photos_dir, options.out, projector=projector,
                                  encoding=options.encoding, undistort=lens, check_session=options.check_exposure,
                                  progress=progress, force=options.force, inputs=(options.rig,))
