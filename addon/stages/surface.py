"""The calibration's surface stage: where the surface comes from and how it is made.

The capture set's depth image (minus the depth sensor's bias, read from its
image of a flat wall), the Gray code triangulated with a calibrated rig when
there is no depth sensor, or the user's mesh of the object (scan or CAD)
registered to either. Each ends as a :class:`SurfaceMesh` in the rig frame and
a report saying which source it came from.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..capture.format import CaptureSet
from ..errors import CalibrationError, ProCamError, SurfaceError
from ..progress import Progress, quiet
from ..surface.mesh import SurfaceMesh
from ..surface.reconstruct import reconstruct_surface, wall_depth_offset
from ..surface.register import depth_points, load_mesh, place_mesh, register_mesh
from ..surface.triangulate import triangulate_depth


def scene_depth(captures: CaptureSet, depth_offset: float | None = None) -> tuple[np.ndarray, float, str]:
    """The depth image of the scene, the sensor bias to subtract from it, and where that bias comes from.

    The scene's depth is the one ``depth`` entry without ``wall_distance_m``;
    entries with it are the sensor's images of a flat wall at that distance,
    each giving the bias (:func:`wall_depth_offset`, their median when
    several). A given ``depth_offset`` wins; with neither the bias is 0 and
    the surface keeps whatever the sensor's bias is (module doc of
    :mod:`procam.addon.surface.reconstruct`: no image can reveal it).
    """
    depth = captures.depth()
    if depth_offset is not None:
        return depth, float(depth_offset), "given"
    walls = captures.depth_walls()
    if not walls:
        return depth, 0.0, "none (no wall depth image in the capture set)"
    offsets = []
    for e, distance in walls:
        try:
            offsets.append(wall_depth_offset(captures.depth(name=e.name), distance))
        except SurfaceError as exc:
            raise CalibrationError(f"depth wall image {e.file}: {exc}") from None
    return depth, float(np.median(offsets)), f"wall depth image{'s' if len(walls) > 1 else ''} " + \
        ", ".join(f"{e.file} at {distance} m" for e, distance in walls)


#: Where the surface comes from: the depth image, the Gray code triangulated with a known rig, the user's mesh
#: registered to either; 'auto' = depth if the capture set has one, else Gray code if the projector's pose is known.
SURFACE_SOURCES = ("auto", "depth", "graycode", "mesh")


def _has_depth(captures: CaptureSet) -> bool:
    return any("wall_distance_m" not in e.params for e in captures.entries_of("depth"))


def surface_photo(captures: CaptureSet) -> np.ndarray | None:
    """The surface's first texture: its photo, when the session has one. Only a start: stage A's albedo step
    replaces it by white − black, so a session without the photo (OpenCV's sequence) starts from a grey one."""
    return captures.image("surface") if captures.entries_of("surface") else None


def surface_from_captures(captures: CaptureSet, source: str = "auto", *,
                          surface_mesh: SurfaceMesh | str | Path | None = None, depth_offset: float | None = None,
                          pose: np.ndarray | None = None, progress: Progress | None = None
                          ) -> tuple[SurfaceMesh, dict[str, Any], list[str]]:
    """The surface stage: (mesh in the rig frame, its report with ``source``, warnings).

    ``'depth'`` meshes the capture set's depth image; ``'graycode'`` the Gray
    code triangulated with the capture set's known projector pose
    (:mod:`procam.addon.surface.triangulate`; or ``pose``, the start pose the
    user gave, when asked for explicitly); both go through
    :func:`reconstruct_surface`. ``'mesh'`` registers ``surface_mesh`` (file or
    mesh, its own frame) to the depth's points, else the triangulated ones
    (:mod:`procam.addon.surface.register`). ``'auto'``: the mesh when one is
    given, else depth when the capture set has it, else Gray code when the
    pose is known, else a :class:`CalibrationError` saying what to do.
    """
    say = progress or quiet
    if source not in SURFACE_SOURCES:
        raise CalibrationError(f"unknown surface source {source!r}; choose one of {', '.join(SURFACE_SOURCES)}")
    if surface_mesh is not None and source not in ("auto", "mesh"):
        raise CalibrationError(f"a surface mesh was given but the surface source is {source!r}; drop the mesh, or "
                               "use the mesh (--surface-from mesh or auto)")
    has_depth, known = _has_depth(captures), captures.projector_pose_known
    if source == "auto":
        if surface_mesh is not None:
            source = "mesh"
        elif has_depth:
            source = "depth"
        elif known:
            source = "graycode"
        else:
            raise CalibrationError(
                f"surface: the capture set {captures.path} has no depth image and does not know the projector's "
                "pose, so there is nothing to make the surface from; import the captures with a metric rig file "
                "(procam import-captures --rig rig.json, from procam calibrate-rig --square METRES) to triangulate "
                "the Gray code, add a depth image (import-captures --depth), or give a mesh of the object "
                "(--surface-mesh FILE.obj)")
    if source == "mesh" and surface_mesh is None:
        raise CalibrationError("surface: --surface-from mesh needs the mesh (--surface-mesh FILE.obj or .ply)")
    cam = captures.camera.intrinsics
    warnings: list[str] = []
    extra: dict[str, Any] = {}
    try:
        # The measured surface: the depth image (with its sensor bias), or the triangulated Gray code.
        if source == "depth" or (source == "mesh" and has_depth):
            say("surface: reconstructing from depth" if source == "depth" else "surface: reading the depth", 0.0)
            depth, offset, offset_source = scene_depth(captures, depth_offset)
            extra = {"depth_offset_source": offset_source}
            min_valid = 0.5
            measured = "depth"
        else:  # graycode, or a mesh to register without a depth image
            given = pose if (source == "graycode" and not known) else None
            if not known and given is None:
                raise CalibrationError(
                    f"surface: the Gray code of {captures.path} can be triangulated only with the projector's pose "
                    "known; import the captures with a metric rig file (procam import-captures --rig rig.json), "
                    + ("give a depth image, or give a mesh (--surface-mesh)" if source == "graycode"
                       else "or add a depth image, to register the mesh to"))
            say("surface: triangulating the Gray code with the known rig", 0.0)
            depth, tri = triangulate_depth(captures, given)
            offset = 0.0
            extra = {"triangulation": tri.to_dict(), "depth_offset_source": "none (triangulated)",
                     "pose": "calibrated (capture set)" if given is None else "the given start pose"}
            if given is not None:
                warnings.append("the surface was triangulated with the given start pose, not a calibrated one: it is "
                                "only as right as that pose")
            # The Gray code covers only the projector's footprint: a small share of the image is normal.
            min_valid = 0.02
            measured = "graycode"
        if source != "mesh":
            mesh, rec = reconstruct_surface(depth, cam, surface_photo(captures), depth_offset=offset,
                                            min_valid=min_valid)
            return mesh, {**rec.to_dict(), "source": source, **extra}, warnings
        say(f"surface: registering the mesh to the {measured} points", 0.02)
        what = str(surface_mesh) if not isinstance(surface_mesh, SurfaceMesh) else f"the mesh {surface_mesh.name!r}"
        user = surface_mesh if isinstance(surface_mesh, SurfaceMesh) else load_mesh(surface_mesh)
        points = depth_points(np.asarray(depth, dtype=np.float64) - offset, cam)
        reg = register_mesh(user, points, source=what)
    except CalibrationError:
        raise
    except ProCamError as exc:
        raise CalibrationError(f"surface: {exc}") from None
    warnings += reg.warnings
    mesh = place_mesh(user, reg, cam, surface_photo(captures), name="registered")
    rep = {"source": "mesh", "mesh_file": what, "measured": measured, "registration": reg.report(),
           "vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)), "depth_offset": float(offset), **extra}
    return mesh, rep, warnings
