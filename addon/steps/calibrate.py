"""The calibrate step: a capture set → a calibration folder (surface, projector pose, warp), and its readers.

The folder, written atomically (nothing is left behind when a stage fails or is cancelled):

``calibration.json``
    camera and projector models (pose as a 4×4 ``camera_from_projector`` in
    the rig frame, metres), warp parameters, losses and seconds per stage.
``surface.npz`` / ``surface.obj`` + ``albedo.png``
    the reconstructed mesh (rig frame) and its camera-aligned diffuse texture.
``diagnostics/``
    mask vs rendered mask, checkerboard capture vs render before/after the warp,
    the deformed grid of the warp.
``scene.blend`` (``with_blend``)
    the rig, the textured surface and those images, to open in Blender. The
    Blender UI leaves it out: the open scene is the .blend there, and bpy must
    not be driven from the worker thread the UI runs steps in.
"""

from __future__ import annotations

import io
import json
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..capture.format import CaptureSet
from ..errors import MALFORMED, CalibrationError, Cancelled, ProCamError
from ..imageio import kept_decoded, read_arrays, read_image, write_atomic_bytes, write_image
from ..options import Choice, option, validate
from ..outputs import AtomicFolder, check_replaceable, file_sha256, write_manifest
from ..progress import Cancel, Progress, part, quiet
from ..rig.model import Rig
from ..safepaths import inside, within
from ..stages.calibrate import STAGES, Calibration, calibrate_captures, stage_plan
from ..stages.intrinsics import pose_summary
from ..stages.transport import TransportError, build_transport
from ..stages.warp_model import Warp, grid_image
from ..surface.mesh import SurfaceMesh
from . import layout
from .summary import Summary, cached, fmt

KIND = layout.CALIBRATION


@dataclass(frozen=True)
class CalibrateOptions:
    """What ``procam calibrate`` and the Calibrate button ask for; each field declares its option once
    (addon/options.py)."""

    capture_dir: Path
    out: Path
    init: str = option(
        "graycode", label="Start Pose", prop="procam_calibration_init", choices=(
            Choice("graycode", "Gray Code", "Start stage A from Gray-code correspondences + PnP"),
            Choice("nominal", "Nominal", "Start stage A from the capture set's nominal projector pose (kept as it is "
                                         "when it came from a metric rig calibration)"),
            Choice("blender", "Scene Projector", "Start stage A from where the ProCam Projector stands in the scene "
                                                 "(on the command line: the one in --blend)"),
            Choice("given", offered=False)),
        help="starting pose for stage A: Gray-code correspondences + PnP (default), the capture set's nominal "
             "projector (kept as it is when it came from a metric rig calibration), or the ProCam Projector placed "
             "in a .blend (--blend); from Python, 'given' starts from initial_pose. With several projectors "
             "graycode and nominal start each projector from its own; blender and given are refused there (not "
             "implemented yet)")
    initial_pose: np.ndarray | None = None
    projector_intrinsics: str = option(
        "spec", label="Projector Lens", choices=(
            Choice("spec", "Spec Sheet", "The projector's focal length and principal point as the capture set gives "
                                         "them (throw ratio and lens shift, or a rig calibration)"),
            Choice("fit", "Fit to Gray Code", "Fit the projector's focal length and principal point to the Gray code "
                                              "on a curved or edged surface before finding its pose (kept at the "
                                              "spec where the surface cannot tell, e.g. a flat wall)")),
        help="the projector's focal length and principal point (default spec); fit fits each projector's own to "
             "its own Gray code (with several projectors the camera's focal length is held as given: it is every "
             "projector's); refused against a surface triangulated from the Gray code (it needs a depth image or a "
             "mesh)")
    stage_a: str = option(
        "ours", choices=("ours", "paper"),
        help="stage A's mask refinement: ours (debiased soft mask, annealed border smoothing) or the paper's "
             "(binary mask, Γ with ε = 0.01, 200 Adam steps), from the start --init gives (--init nominal --stage-a "
             "paper reproduces the paper's pipeline)")
    stages: str = option(
        "all", metavar="STAGES", check=lambda text: stage_plan(text),
        help="run these stages only, comma-separated from surface,pose,warp (a contiguous run): earlier ones come "
             "from the calibration already in --out, later ones are left to run (default: all); with several "
             "projectors each stage runs for every projector")
    depth_offset: float | None = option(
        None, min=-0.5, max=0.5, metavar="METRES", label="Depth Offset", own_field=True,
        help="the depth sensor's constant bias in metres (+ = it reads too far), subtracted from the depth; "
             "default: read from the capture set's wall depth image (a flat wall at a tape-measured distance), "
             "else 0")
    surface_from: str = option(
        "auto", choices=("auto", "depth", "graycode", "mesh"),
        help="where the surface comes from: the capture set's depth image, the Gray code triangulated with a "
             "calibrated rig (import-captures --rig with a metric rig file), or the mesh of --surface-mesh "
             "registered to either (default auto: the mesh if given, else depth if present, else the Gray code when "
             "the projector's pose is known)")
    surface_mesh: Path | SurfaceMesh | None = option(
        None, metavar="FILE", label="Surface Mesh", own_field=True, parse=Path,
        help="the object's mesh (.obj/.ply, a scan or CAD model in its own frame, metres or millimetres), "
             "registered by ICP to the depth or triangulated points and used as the surface")
    #: also write scene.blend, through the ``blend_writer`` given to :func:`run` (the procam command turns it on)
    with_blend: bool = False
    seed: int = option(0, min=0, help="seed of every random stream")
    precompute: bool = option(
        True, negate="--no-precompute",
        help="also precompute the light-transport operator into the folder (procam precompute; ~25 s at 640×480), "
             "which stage C's default schedule solves on (default on)")
    force: bool = False


#: What writes a calibration's ``scene.blend``: (path, rig, surface, diagnostic images) → the path. Blender's side
#: supplies it (``addon/blender/blend_file.save_calibration_blend``, passed by the command line); the steps never
#: import bpy, so a step runs, and is tested, where Blender is not.
BlendWriter = Callable[[Path, Rig, SurfaceMesh, dict[str, np.ndarray]], Path]


def run(options: CalibrateOptions, progress: Progress | None = None, cancel: Cancel | None = None, *,
        blend_writer: BlendWriter | None = None) -> Calibration:
    """Calibrate the capture set into ``options.out``; returns the calibration written. ``blend_writer`` writes
    its ``scene.blend`` (needed unless ``options.with_blend`` is off)."""
    say = progress or quiet
    validate(options, CalibrationError)
    if options.with_blend and blend_writer is None:
        raise CalibrationError("a calibration's scene.blend needs Blender's writer: pass blend_writer (the procam "
                               "command does), or turn with_blend off")
    plan = stage_plan(options.stages)
    if options.init == "given" and options.initial_pose is None:
        raise CalibrationError("a given start pose (init 'given') needs the pose itself")
    reused = STAGES[:STAGES.index(plan[0])]
    mesh = options.surface_mesh if isinstance(options.surface_mesh, (str, Path)) else None
    # A partial run (reused stages) replaces the calibration it continues; anything else needs force.
    check_replaceable(options.out, force=options.force or bool(reused), what=KIND.what, replaceable=KIND.holds,
                      inputs=(options.capture_dir, mesh), error=CalibrationError)
    # the captures' photographs decoded once for the check, the Gray code's decodings and the albedo (a real
    # session's calibration decoded each three times: 6 of its 16 s)
    with kept_decoded():
        captures = CaptureSet.load(options.capture_dir)
        previous, images = _previous(Path(options.out), options.capture_dir, reused) if reused else (None, {})
        folder = AtomicFolder(options.out, force=options.force or previous is not None, what=KIND.what,
                              replaceable=KIND.holds, error=CalibrationError, inputs=(options.capture_dir, mesh))
        precompute = options.precompute and plan[-1] == STAGES[-1]
        share = 0.8 if precompute else 0.95
        try:
            result = calibrate_captures(captures, plan=plan, previous=previous, previous_images=images,
                                        init=options.init, initial_pose=options.initial_pose, seed=options.seed,
                                        depth_offset=options.depth_offset, stage_a=options.stage_a,
                                        projector_intrinsics=options.projector_intrinsics,
                                        surface_from=options.surface_from, surface_mesh=options.surface_mesh,
                                        progress=part(say, 0.0, share), cancel=cancel)
            say("writing the calibration folder", share)
            write(folder.tmp, result.calibration, result.images,
                  blend_writer=blend_writer if options.with_blend else None)
        except BaseException:
            folder.abort()
            raise
    stopped: BaseException | None = None
    if precompute:
        try:
            _precompute(folder.tmp, result.calibration, options.seed, part(say, share, 1.0, "transport operator: "),
                        cancel)
        except (Cancelled, KeyboardInterrupt) as exc:
            # The calibration is finished and worth minutes: keep it, without the operator (compensation renders
            # its own when none is stored, and `procam precompute` adds it later).
            stopped = exc
            for k in range(result.calibration.projector_count):
                for name in layout.transport_files(k):
                    (folder.tmp / name).unlink(missing_ok=True)
        except BaseException:
            folder.abort()
            raise
    folder.commit()
    if stopped is not None:
        raise Cancelled(f"the transport operator's precompute was cancelled; the calibration is kept in "
                        f"{options.out} without it: run `procam precompute {options.out}` to add it (compensation "
                        "renders one itself meanwhile)", kept=True)
    say("done", 1.0)
    return result.calibration


def store_transport(folder: str | Path, calibration: Calibration, *, bounces: int = 1, seed: int = 0,
                    progress: Progress | None = None, cancel: Cancel | None = None) -> dict[str, Any]:
    """Render the light-transport operator of ``calibration`` (the one written in ``folder``, or its
    :meth:`~.Calibration.for_projector` view of one projector; a calibration of several: its first projector's) and
    store it there: ``layout.transport_files(k)`` of its projector ``k`` (``transport.npz`` and ``transport.json``
    for the first: what it holds, how long it took, and the content hashes of the calibration folder it belongs to),
    each atomically. Returns the record.

    Each projector's operator is that projector lit alone: its direct light where it reaches, and its indirect
    light everywhere in the camera, so also its light bouncing onto the other projectors' areas."""
    folder = Path(folder)
    view = calibration.for_projector(0) if calibration.projector_count > 1 else calibration
    operator_file, report_file = layout.transport_files(view.projector_index)
    op = build_transport(view, bounces=bounces, seed=seed, progress=progress, cancel=cancel)
    ident = identity(folder)
    doc = {**op.report, "calibration_sha256": ident["sha256"], "surface_sha256": ident["surface_sha256"],
           "file": operator_file}
    buf = io.BytesIO()
    np.savez(buf, **op.arrays())
    write_atomic_bytes(folder / operator_file, buf.getvalue())
    write_atomic_bytes(folder / report_file, (json.dumps(doc, indent=1) + "\n").encode())
    return doc


def _precompute(folder: Path, calibration: Calibration, seed: int, say: Progress, cancel: Cancel | None) -> None:
    """Every projector's transport operator into the calibration folder being written (so it appears with the
    calibration, or not at all). An operator that cannot be built leaves the calibration standing: compensation
    says so and renders one when it needs it."""
    count = calibration.projector_count
    for k in range(count):
        name = f"projector {k + 1}'s " if count > 1 else ""
        try:
            store_transport(folder, calibration.for_projector(k), seed=seed, cancel=cancel,
                            progress=part(say, k / count, (k + 1) / count, name))
        except TransportError as exc:
            if cancel is not None and cancel():
                raise Cancelled("precomputing the transport operator was cancelled") from None
            say(f"warning: no {name}transport operator precomputed ({exc})", 1.0)


def write(folder: Path, cal: Calibration, images: dict[str, np.ndarray], *,
          blend_writer: BlendWriter | None = None) -> None:
    """The files of a calibration folder into the (new, empty) ``folder``; ``scene.blend`` too when a
    ``blend_writer`` is given."""
    mesh = cal.surface
    write_manifest(folder / KIND.manifest, manifest(cal))
    buf = io.BytesIO()
    np.savez_compressed(buf, vertices=mesh.vertices, faces=mesh.faces, uvs=mesh.uvs, albedo=mesh.albedo)
    write_atomic_bytes(folder / layout.SURFACE_NPZ, buf.getvalue())
    write_image(folder / layout.ALBEDO_PNG, mesh.albedo)
    write_atomic_bytes(folder / layout.SURFACE_MTL, f"newmtl albedo\nKd 1 1 1\nmap_Kd {layout.ALBEDO_PNG}\n".encode())
    write_atomic_bytes(folder / layout.SURFACE_OBJ, _obj_text(mesh).encode())
    diag = folder / layout.DIAGNOSTICS_DIR
    diag.mkdir()
    clipped = {name: np.clip(im, 0, 1) for name, im in images.items()}
    for name, im in clipped.items():
        write_image(diag / f"{name}.png", im)
    if blend_writer is not None:
        blend_writer(folder / layout.SCENE_BLEND, cal.rig, mesh, clipped)  # every projector of the rig


def manifest(cal: Calibration) -> dict[str, Any]:
    """``calibration.json`` of a calibration: with several projectors, the first projector's at the top level as
    for one, and a ``projectors`` list (each projector's pose, warp and own report, in order)."""
    doc = {"format": KIND.format, "version": KIND.version, "capture_set": cal.capture_dir,
           "rig": cal.rig.to_dict(),
           "camera_from_projector": cal.rig.projector.camera_from_projector.tolist(),
           "warp": cal.warp.to_dict() if cal.warp is not None else None,
           "surface": {"mesh": layout.SURFACE_NPZ, "obj": layout.SURFACE_OBJ, "albedo": layout.ALBEDO_PNG,
                       "vertices": int(len(cal.surface.vertices)), "faces": int(len(cal.surface.faces))},
           **cal.report}
    if cal.projector_count > 1:
        entries = list(cal.report.get("projectors") or [])
        entries += [{}] * (cal.projector_count - len(entries))
        doc["projectors"] = [{"camera_from_projector": p.camera_from_projector.tolist(),
                              "warp": w.to_dict() if w is not None else None, **own}
                             for p, w, own in zip(cal.rig.projectors, cal.warps, entries)]
    return doc


def _obj_text(mesh: SurfaceMesh) -> str:
    lines = ["# ProCam surface, rig frame (OpenCV camera frame, metres)", f"mtllib {layout.SURFACE_MTL}",
             "usemtl albedo"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in mesh.vertices]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in mesh.uvs]
    lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in mesh.faces]
    return "\n".join(lines) + "\n"


def _previous(out: Path, capture_dir: str | Path,
              needed: tuple[str, ...]) -> tuple[Calibration, dict[str, np.ndarray]]:
    """The calibration at ``out`` whose ``needed`` stages a partial run reuses (same capture set), with its images."""
    if not KIND.holds(out):
        raise CalibrationError(f"running from stage {STAGES[len(needed)]!r} reuses the {', '.join(needed)} of the "
                               f"calibration in {out}, but there is none; run the earlier stages first "
                               f"(--stages {','.join(STAGES[:len(needed) + 1])})")
    prev = read(out, complete=False)
    if Path(prev.capture_dir).resolve() != Path(capture_dir).resolve():
        raise CalibrationError(f"the calibration in {out} was made from {prev.capture_dir}, not {capture_dir}; "
                               "run every stage (--stages all) or choose another output folder")
    missing = [n for n in needed if prev.stages.get(n) not in ("run", "reused")]
    if missing:
        raise CalibrationError(f"the calibration in {out} has not run stage(s) {', '.join(missing)}; "
                               f"run --stages {','.join(STAGES[:len(needed) + 1])}")
    return prev, diagnostic_images(out)


# -- reading ---------------------------------------------------------------------------------------

def read(folder: str | Path, *, complete: bool = True) -> Calibration:
    """A calibration folder; with ``complete`` (for compensation, diagnosis, evaluation) one that has not run
    every stage is refused, saying which to run."""
    folder = Path(folder)
    path = folder / KIND.manifest
    if not path.is_file():
        raise CalibrationError(f"{folder} is not a calibration folder (no {KIND.manifest}); run {KIND.made_by}")
    doc = KIND.read(folder, CalibrationError)  # a JSON object of the calibration's format, or refused
    try:
        data = read_arrays(_mesh(folder, doc["surface"]["mesh"]), ("vertices", "faces", "uvs", "albedo"),
                           error=CalibrationError, remedy=f"calibrate again: procam calibrate "
                           f"{doc.get('capture_set') or 'CAPTURE_SET'} --out {folder} --force")
        surface = SurfaceMesh(data["vertices"], data["faces"], data["uvs"], data["albedo"], name="surface")
        warp = Warp.from_dict(doc["warp"]) if doc.get("warp") else None
        report = {k: v for k, v in doc.items() if k not in ("format", "version", "capture_set", "rig",
                                                             "camera_from_projector", "warp", "surface")}
        rig = Rig.from_dict(doc["rig"])
        warps: list[Warp | None] = [warp] + [None] * len(rig.others)
        entries = doc.get("projectors")
        if entries is not None:
            if not isinstance(entries, list) or len(entries) != len(rig.projectors) or \
                    not all(isinstance(e, dict) for e in entries):
                raise ValueError(f"'projectors' lists {len(entries) if isinstance(entries, list) else 'no'} "
                                 f"projector entries for the rig's {len(rig.projectors)} projectors")
            warps = [Warp.from_dict(e["warp"]) if e.get("warp") else None for e in entries]
            report["projectors"] = [{k: v for k, v in e.items() if k not in ("camera_from_projector", "warp")}
                                    for e in entries]
        cal = Calibration(rig, surface, warp, doc.get("capture_set", ""), report, str(folder.absolute()),
                          other_warps=tuple(warps[1:]))
    except (OSError, *MALFORMED) as exc:
        raise CalibrationError(f"cannot read calibration {folder}: {exc}") from None
    missing = cal.missing_stages
    if complete and missing:
        raise CalibrationError(f"the calibration in {folder} has not run {', '.join(missing)} yet; run "
                               f"procam calibrate {cal.capture_dir} --out {folder} --stages {','.join(missing)}")
    return cal


def captures_of(cal: Calibration, *, verify_images: bool = False, required: bool = True) -> CaptureSet | None:
    """The capture set a calibration was made from; None when it moved and ``required`` is false (then the
    display area must come from the user or the model alone)."""
    try:
        return CaptureSet.load(cal.capture_dir, verify_images=verify_images)
    except ProCamError as exc:
        if required:
            raise CalibrationError(f"the capture set {cal.capture_dir!r} this calibration was made from cannot be "
                                   f"read ({exc}); put it back where it was") from None
        return None


def capture_set_of(folder: str | Path) -> Path | None:
    """The capture set a calibration folder names, read from its manifest alone (no mesh, no checks), so that a
    step can refuse an output inside it before any work; None when the manifest cannot tell (:func:`read` then
    says what is wrong)."""
    try:
        doc = json.loads((Path(folder) / KIND.manifest).read_text())
    except (OSError, ValueError):
        return None
    given = doc.get("capture_set") if isinstance(doc, dict) else None
    return Path(given) if isinstance(given, str) and given else None


def _mesh(folder: Path, name: object) -> Path:
    """The surface mesh a calibration manifest names: a file of the calibration folder."""
    return inside(folder, name, what="the surface mesh", error=CalibrationError)


def identity(folder: str | Path) -> dict[str, str]:
    """Path and content hashes of a calibration folder (its manifest and surface mesh): what made a result."""
    folder = Path(folder)
    doc_path = folder / KIND.manifest
    try:
        mesh = json.loads(doc_path.read_text()).get("surface", {}).get("mesh", layout.SURFACE_NPZ)
        return {"path": str(folder.absolute()), "sha256": file_sha256(doc_path),
                "surface_sha256": file_sha256(_mesh(folder, mesh))}
    except (OSError, ValueError, AttributeError) as exc:
        raise CalibrationError(f"cannot read the calibration {folder}: {exc}") from None


def diagnostic_images(folder: str | Path) -> dict[str, np.ndarray]:
    """The diagnostic images of a calibration folder (``diagnostics/*.png``) by name."""
    diag = Path(folder) / layout.DIAGNOSTICS_DIR
    if not diag.is_dir():
        return {}
    return {p.stem: read_image(within(folder, p, what="diagnostic image", error=CalibrationError), channels=3)
            for p in sorted(diag.glob("*.png"))}


@dataclass
class CalibrationView:
    """A calibration as the scene shows it: the rig, the textured surface, the warp grid and diagnostic images."""

    folder: Path
    calibration: Calibration
    images: dict[str, np.ndarray]


def read_view(folder: str | Path, progress: Progress | None = None,
              cancel: Cancel | None = None) -> CalibrationView:
    """A calibration folder with its diagnostics and the warp's deformed grid, a stage at a time (what is there)."""
    say = progress or quiet
    say("reading the calibration", 0.0)
    cal = read(folder, complete=False)
    say("reading the diagnostic images", 0.3)
    images = diagnostic_images(folder)
    if cal.warp is not None:
        images["warp_grid"] = np.clip(grid_image(cal.warp, cal.warp.size), 0.0, 1.0).astype(np.float32)
    say("done", 1.0)
    return CalibrationView(Path(folder), cal, images)


def run_view(options: CalibrateOptions, progress: Progress | None = None,
             cancel: Cancel | None = None) -> CalibrationView:
    """:func:`run`, then :func:`read_view` of the folder written: what the Calibrate button shows."""
    run(options, part(progress, 0.0, 0.95), cancel)
    return read_view(options.out, part(progress, 0.95, 1.0))


def _surface_lines(surf: dict[str, Any], doc: dict[str, Any], seconds: Any) -> list[str]:
    offset = surf.get("depth_offset", 0.0)
    lines = [f"Surface: {surf.get('vertices', doc.get('surface', {}).get('vertices', '?'))} vertices, "
             f"{surf.get('faces', doc.get('surface', {}).get('faces', '?'))} faces, "
             f"from {surf.get('source', 'depth')}, "
             f"depth offset {fmt(100 * offset if isinstance(offset, (int, float)) else None, '+.2f', ' cm')} "
             f"({surf.get('depth_offset_source', 'none')}) ({fmt(seconds, '.1f', ' s')})"]
    t = surf.get("triangulation")
    if isinstance(t, dict):
        lines.append(f"triangulated Gray code: {t.get('points')} points ({t.get('rejected')} rejected), reprojection "
                     f"{fmt(t.get('reprojection_rms_px'), '.2f')} px rms, "
                     f"{fmt(t.get('triangulation_angle_deg'), '.1f')}° between the rays")
    g = surf.get("registration")
    if isinstance(g, dict):
        lines.append(f"mesh {surf.get('mesh_file')} registered to the {surf.get('measured')} points: residual "
                     f"{fmt(g.get('rms_mm'), '.2f')} mm rms, {fmt(g.get('median_mm'), '.2f')} mm median, overlap "
                     f"{fmt(g.get('overlap'), '.0%')}, {g.get('iterations')} iterations (start: {g.get('start')})")
    return lines


def _projector_lines(doc: dict[str, Any], sec: dict[str, Any], name: str = "") -> list[str]:
    """The pose and warp lines of one projector's report (``name``: "Projector 2 " with several, else none)."""
    losses = doc.get("losses", {}) or {}
    warp = doc.get("warp_report", {}) or {}
    before, after = warp.get("corners_before_px") or {}, warp.get("corners_after_px") or {}
    pose = doc.get("pose", {}) or {}
    cfp = np.asarray(doc["camera_from_projector"], dtype=float)
    position, axis = cfp[:3, 3], cfp[:3, 2]
    method = (pose.get("info") or {}).get("method", "ours") if isinstance(pose.get("info"), dict) else "ours"
    lines = [
        f"{name + 'pose' if name else 'Pose'}: init {doc.get('init', pose.get('init', '?'))}, stage A {method}, "
        f"loss {fmt(losses.get('pose'), '.4g')} ({fmt(sec.get('pose'), '.1f', ' s')})",
        f"{name or 'Projector '}at ({position[0]:+.3f}, {position[1]:+.3f}, {position[2]:+.3f}) m, pointing "
        f"({axis[0]:+.4f}, {axis[1]:+.4f}, {axis[2]:+.4f})",
    ]
    intrinsics = doc.get("projector_intrinsics")
    if isinstance(intrinsics, dict) and intrinsics.get("summary"):
        lines.append(f"projector intrinsics (fitted to the Gray code): {intrinsics['summary']}")
    elif isinstance(doc.get("pose_uncertainty"), dict):  # (a fit's summary states the pose's ± itself)
        lines.append(f"{name + 'pose' if name else 'Pose'} uncertainty, intrinsics as given: "
                     f"{pose_summary(doc['pose_uncertainty'])}")
    source = " (from the Gray code)" if warp.get("source") == "graycode" else ""
    lines.append(f"{name + 'warp' if name else 'Warp'}{source}: "
                 f"corners {fmt(before.get('median'), '.2f')} → {fmt(after.get('median'), '.2f')} px median, "
                 f"loss {fmt(losses.get('warp'), '.4g')} ({fmt(sec.get('warp'), '.1f', ' s')})")
    return lines


def _corners(doc: dict[str, Any]) -> Any:
    return ((doc.get("warp_report") or {}).get("corners_after_px") or {}).get("median")


def _summary(root: Path, doc: dict[str, Any]) -> Summary:
    sec = doc.get("seconds", {}) or {}
    surf = doc.get("surface_report", {}) or {}
    entries = doc.get("projectors") if isinstance(doc.get("projectors"), list) else None
    lines = _surface_lines(surf, doc, sec.get("surface"))
    if entries:
        for k, entry in enumerate(entries):
            lines += _projector_lines(entry, entry.get("seconds") or {}, f"Projector {k + 1} ")
    else:
        lines += _projector_lines(doc, sec)
    stages = doc.get("stages") or dict.fromkeys(STAGES, "run")  # folders from before stages ran all three
    lines.append("stages: " + ", ".join(f"{k} {v}" for k, v in stages.items()))
    lines += [f"warning: {w}" for w in doc.get("warnings") or []]
    if sec:
        lines.append("seconds: " + ", ".join(f"{k} {fmt(v, '.1f')}" for k, v in sec.items()))
    head = f"Calibrated: warp corners {fmt(_corners(doc), '.2f')} px" if not entries else \
        f"Calibrated {len(entries)} projectors: warp corners {', '.join(fmt(_corners(e), '.2f') for e in entries)} px"
    diag = root / layout.DIAGNOSTICS_DIR
    maps = sorted(p.name for p in diag.glob("*.png")) if diag.is_dir() else []
    return Summary(True, head, tuple(lines), {"diagnostics": maps, "capture_set": doc.get("capture_set", ""),
                                             **({"projectors": len(entries)} if entries else {})})


#: the transport operator's report by path, with its modification time: a precompute adds it to a calibration
#: folder without touching calibration.json, so it is read beside the cached summary, not in it
_TRANSPORT: dict[Path, tuple[int, str | None]] = {}


def _transport_line(root: Path, k: int = 0, count: int = 1) -> str | None:
    """The transport operator line of projector ``k`` of ``count``."""
    path = root / layout.transport_files(k)[1]
    try:
        stamp = path.stat().st_mtime_ns
    except OSError:
        return None
    hit = _TRANSPORT.get(path)
    if hit is None or hit[0] != stamp:
        try:
            doc = json.loads(path.read_text())
            whose = f" of projector {k + 1}" if count > 1 else ""
            line = f"transport operator{whose}: {doc['megabytes']} MB in {fmt(doc.get('seconds'), '.0f', ' s')}"
        except (OSError, ValueError, KeyError, TypeError):
            line = None
        hit = _TRANSPORT[path] = (stamp, line)
    return hit[1]


def summary(folder: str | Path) -> Summary:
    """Key figures of a calibration folder: surface size, pose loss and position, warp corners before → after."""
    s = cached(KIND, folder, _summary, "run Calibrate or choose a calibration folder")
    if not s.ok:
        return s
    count = int(s.data.get("projectors", 1))
    lines = [_transport_line(Path(folder), k, count) for k in range(count)]
    return replace(s, lines=(*s.lines, *(line for line in lines if line)))
