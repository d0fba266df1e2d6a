"""The rig inside a Blender scene: camera, projector light, surface; built from and read back into the rig model.

Objects are found by a ``procam`` custom property (an ID property group with a
``role``: ``camera``, ``projector``, ``frustum`` or ``surface``), not by name,
so users may rename them. The exact model (K in float64, the pose, input
placement, intensity) is stored beside the Blender settings, because Blender
keeps lens, shift and ``matrix_world`` in float32: :func:`read_rig` returns the
stored values while the Blender settings still reproduce them, and derives new
values from Blender when the user has moved or edited an object.

The projector is a spot light whose Cycles node tree maps the emission
direction through K to an image (docs/developer.md, "Facts about the dependencies"):
Texture Coordinate ▸ Normal is the direction in the light's frame (−Z forward, +Y up), the image is
sampled with CLIP extension so nothing leaves the frame, and the strength is
``(−n_z)^−3`` so every pixel delivers the same power, as a pinhole projector.
Energy ``4π² · intensity`` matches Mitsuba's ``projector`` with ``scale = 1``.

Datablocks are built unlinked and linked into the scene last; a failure on
the way removes whatever was built, so the scene is never left half-changed.
All conversions between the rig frame and Blender go through :mod:`.frames`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import bpy
import numpy as np
from mathutils import Matrix

from ..colour import srgb_decode
from ..errors import ImageError, RigError, SurfaceError
from ..surface.mesh import SurfaceMesh
from ..rig import frames
from ..rig.model import Camera, Intrinsics, Projector, Rig

PROP = "procam"
CAMERA_NAME = "ProCam Camera"
PROJECTOR_NAME = "ProCam Projector"
FRUSTUM_NAME = "ProCam Projector Frustum"
SURFACE_NAME = "ProCam Surface"
PROJECTOR_IMAGE_NAME = "ProCam Projector Frame"

#: Light energy (W) per unit projector intensity: matches Mitsuba's ``projector`` with ``scale = 1``
#: (docs/developer.md, "Facts about the dependencies").
ENERGY_PER_INTENSITY = 4.0 * math.pi ** 2
#: Depth (m) of the viewport pyramid that shows the projector frustum.
FRUSTUM_DEPTH = 0.5
#: The spot cone is widened by this angle (rad) so that float32 rounding never clips the frame's corners.
_CONE_MARGIN = 1e-4
#: A stored pose/K is trusted while Blender's float32 copy agrees to this (m, px).
_POSE_TOL = 1e-5
_K_TOL = 1e-3
_GREY_ALBEDO = 0.8


@dataclass(frozen=True)
class RigObjects:
    """The ProCam objects of a scene (None where absent).

    ``projectors`` are all the scene's ProCam projectors in rig order (their stored ``index``, the first being
    projector 1 of the rig); ``projector`` is the one the panels and operators work on: the active object where it
    is one of several projectors (or a projector's frustum), else the first.
    """

    camera: bpy.types.Object | None
    projector: bpy.types.Object | None
    surface: bpy.types.Object | None
    projectors: tuple[bpy.types.Object, ...] = ()


# --------------------------------------------------------------------------- tags


def role(obj: bpy.types.Object) -> str | None:
    """The ProCam role of an object, or None."""
    data = obj.get(PROP)
    if data is None or not hasattr(data, "get"):
        return None
    value = data.get("role")
    return str(value) if value is not None else None


def _props(obj: bpy.types.Object) -> dict[str, Any]:
    data = obj.get(PROP)
    return data.to_dict() if data is not None and hasattr(data, "to_dict") else {}


def _objects_with_role(scene: bpy.types.Scene, name: str) -> list[bpy.types.Object]:
    return [o for o in scene.objects if role(o) == name]


def projector_index(obj: bpy.types.Object) -> int:
    """The stored place of a projector in the rig (0 = the first; a projector made before several existed: 0)."""
    try:
        return max(0, int(_props(obj).get("index", 0)))
    except (TypeError, ValueError):
        return 0


def _active_object(scene: bpy.types.Scene) -> bpy.types.Object | None:
    try:
        if bpy.context.scene != scene:
            return None
        return bpy.context.view_layer.objects.active
    except AttributeError:  # no view layer in this context
        return None


def find_rig_objects(scene: bpy.types.Scene) -> RigObjects:
    """The scene's ProCam camera, projectors and surface (the scene camera wins if several are tagged)."""
    cams = _objects_with_role(scene, "camera")
    cam = scene.camera if scene.camera in cams else (cams[0] if cams else None)
    # rig order: the stored index, then the name, so that a duplicated projector (same index) still reads stably
    projs = sorted((o for o in _objects_with_role(scene, "projector") if o.type == "LIGHT"),
                   key=lambda o: (projector_index(o), o.name))
    surfs = [o for o in _objects_with_role(scene, "surface") if o.type == "MESH"]
    current = projs[0] if projs else None
    if len(projs) > 1:
        active = _active_object(scene)
        if active is not None and role(active) == "frustum":
            active = active.parent
        if active in projs:
            current = active
    return RigObjects(cam, current, surfs[0] if surfs else None, tuple(projs))


# --------------------------------------------------------------------------- building blocks


class _Built:
    """Datablocks created so far, removed again if the build fails."""

    def __init__(self) -> None:
        self.items: list[tuple[Any, Any]] = []

    def add(self, collection: Any, block: Any) -> Any:
        self.items.append((collection, block))
        return block

    def remove_all(self) -> None:
        for collection, block in reversed(self.items):
            try:
                collection.remove(block)
            except (ReferenceError, RuntimeError):
                pass  # already gone with its owner
        self.items.clear()


def _matrix(m: np.ndarray) -> Matrix:
    return Matrix([list(map(float, row)) for row in np.asarray(m, dtype=np.float64)])


def _np_matrix(m: Matrix) -> np.ndarray:
    return np.array([list(row) for row in m], dtype=np.float64)


def _rig_to_world(scene: bpy.types.Scene) -> np.ndarray:
    """Pose of the rig frame in the 'Blender world as rig frame' (identity unless the camera was moved)."""
    cam = find_rig_objects(scene).camera
    return _camera_world_pose(cam) if cam is not None else np.eye(4)


def _stored_or_blender_pose(obj: bpy.types.Object) -> np.ndarray:
    """The stored exact pose while matrix_world still matches it, else the pose Blender shows."""
    world = _np_matrix(obj.matrix_world)
    stored = _props(obj).get("pose")
    if stored is not None:
        pose = np.asarray(stored, dtype=np.float64).reshape(4, 4)
        if np.max(np.abs(frames.blender_matrix_world(pose) - world)) <= _POSE_TOL:
            return pose
    return frames.pose_from_blender_matrix(world)


def _camera_world_pose(cam: bpy.types.Object) -> np.ndarray:
    return _stored_or_blender_pose(cam)


def spot_size_for(intr: Intrinsics) -> float:
    """Full cone angle (rad) of a spot light that just encloses the (possibly asymmetric) frustum."""
    w, h = intr.size
    corners = intr.rays(np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]]))
    half = float(np.max(np.arctan(np.hypot(corners[:, 0], corners[:, 1]))))
    size = 2.0 * half + _CONE_MARGIN
    if size >= math.pi:
        raise RigError(
            f"the projector frustum spans {math.degrees(2 * half):.1f}° from its lens axis, but a Blender spot "
            "light covers at most 180°; use a longer throw ratio or a smaller lens shift")
    return size


def _image_from_array(name: str, rgb: np.ndarray, built: _Built | None = None,
                      image: bpy.types.Image | None = None) -> bpy.types.Image:
    """A float, Non-Color Blender image holding ``rgb`` (row 0 = top), reusing ``image`` if it has the size."""
    h, w = rgb.shape[:2]
    if image is None or tuple(image.size) != (w, h) or not image.is_float:
        image = bpy.data.images.new(name, width=w, height=h, alpha=True, float_buffer=True)
        if built is not None:
            built.add(bpy.data.images, image)
    # Non-Color: Cycles uses the values as they are, no sRGB or colour-space transfer.
    image.colorspace_settings.name = "Non-Color"
    rgba = np.ones((h, w, 4), dtype=np.float32)
    rgba[..., :3] = rgb
    image.pixels.foreach_set(np.ascontiguousarray(rgba[::-1]).ravel())  # Blender's row 0 is the bottom
    image.update()
    # Pack (lossless float EXR, ~30 ms at 800×600): generated pixels are otherwise lost when the .blend is saved.
    image.pack()
    return image


def add_image(name: str, rgb: np.ndarray) -> bpy.types.Image:
    """A packed float Non-Color Blender image holding an H×W×3 array (row 0 = top), to view in Blender."""
    img = np.asarray(rgb, dtype=np.float32)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return _image_from_array(name, img[..., :3])


def _image_to_array(image: bpy.types.Image) -> np.ndarray:
    """H×W×3 float32 linear values of a Blender image (row 0 = top)."""
    w, h = image.size
    if w == 0 or h == 0:
        raise ImageError(f"image {image.name!r} has no pixels (missing file?)")
    ch = image.channels
    buf = np.empty(w * h * ch, dtype=np.float32)
    image.pixels.foreach_get(buf)
    img = buf.reshape(h, w, ch)[::-1]
    rgb = np.repeat(img[..., :1], 3, axis=2) if ch < 3 else img[..., :3]
    if not image.is_float and image.colorspace_settings.name == "sRGB":
        # Byte images report their stored (sRGB-encoded) values: decode to linear.
        rgb = srgb_decode(rgb)
    return np.ascontiguousarray(rgb, dtype=np.float32)


def _camera_props(intr: Intrinsics, pose: np.ndarray) -> dict[str, Any]:
    return {"role": "camera", "width": int(intr.width), "height": int(intr.height),
            "fx": float(intr.fx), "fy": float(intr.fy), "cx": float(intr.cx), "cy": float(intr.cy),
            "pose": [float(v) for v in np.asarray(pose).ravel()]}


def _build_camera(intr: Intrinsics, built: _Built) -> bpy.types.Object:
    params = frames.blender_camera_params(intr)
    data = built.add(bpy.data.cameras, bpy.data.cameras.new(CAMERA_NAME))
    for key, value in params.items():
        setattr(data, key, value)
    data.clip_start = 0.01
    data.clip_end = 1000.0
    obj = built.add(bpy.data.objects, bpy.data.objects.new(CAMERA_NAME, data))
    obj.matrix_world = _matrix(frames.blender_matrix_world(np.eye(4)))
    obj[PROP] = _camera_props(intr, np.eye(4))
    return obj


def _add_node(tree: Any, kind: str, location: tuple[float, float], **settings: Any) -> Any:
    node = tree.nodes.new(kind)
    node.location = location
    for key, value in settings.items():
        setattr(node, key, value)
    return node


def _math(tree: Any, op: str, location: tuple[float, float], a: Any = None, b: Any = None, c: Any = None) -> Any:
    """A Math node; each of a, b, c is a socket to link or a number to set."""
    node = _add_node(tree, "ShaderNodeMath", location, operation=op)
    for i, v in enumerate((a, b, c)):
        if v is None:
            continue
        if isinstance(v, (int, float)):
            node.inputs[i].default_value = float(v)
        else:
            tree.links.new(v, node.inputs[i])
    return node.outputs[0]


def _build_projector_nodes(light: bpy.types.Light, intr: Intrinsics, image: bpy.types.Image) -> None:
    """Cycles nodes: direction → pixel through K → image colour, strength (−n_z)^−3, zero behind the light."""
    if light.node_tree is None:
        light.use_nodes = True
    tree = light.node_tree
    tree.nodes.clear()
    w, h = intr.size
    coord = _add_node(tree, "ShaderNodeTexCoord", (-1200, 0))
    sep = _add_node(tree, "ShaderNodeSeparateXYZ", (-1000, 0))
    tree.links.new(coord.outputs["Normal"], sep.inputs[0])
    x, y, z = sep.outputs[0], sep.outputs[1], sep.outputs[2]
    depth = _math(tree, "MULTIPLY", (-800, -200), z, -1.0)  # distance along the lens axis per unit ray
    # OpenCV pixel (u, v) = (fx·x/d + cx, −fy·y/d + cy) with Blender's +Y up; texture (U, V) = (u/W, 1 − v/H).
    xd = _math(tree, "DIVIDE", (-600, 100), x, depth)
    yd = _math(tree, "DIVIDE", (-600, -50), y, depth)
    u = _math(tree, "MULTIPLY_ADD", (-400, 100), xd, intr.fx / w, intr.cx / w)
    v = _math(tree, "MULTIPLY_ADD", (-400, -50), yd, intr.fy / h, 1.0 - intr.cy / h)
    uv = _add_node(tree, "ShaderNodeCombineXYZ", (-200, 50))
    tree.links.new(u, uv.inputs[0])
    tree.links.new(v, uv.inputs[1])
    tex = _add_node(tree, "ShaderNodeTexImage", (0, 100), interpolation="Linear", extension="CLIP",
                    image=image, label="Projector frame")
    tex.name = "ProCam Frame"
    tree.links.new(uv.outputs[0], tex.inputs["Vector"])
    # Pinhole projector: radiant intensity grows as 1/cos³ off axis so that each pixel carries equal power.
    safe = _math(tree, "MAXIMUM", (-400, -250), depth, 1e-6)
    falloff = _math(tree, "POWER", (-200, -250), safe, -3.0)
    front = _math(tree, "GREATER_THAN", (-200, -400), depth, 0.0)
    strength = _math(tree, "MULTIPLY", (0, -300), falloff, front)
    emit = _add_node(tree, "ShaderNodeEmission", (300, 0))
    tree.links.new(tex.outputs["Color"], emit.inputs["Color"])
    tree.links.new(strength, emit.inputs["Strength"])
    out = _add_node(tree, "ShaderNodeOutputLight", (500, 0))
    tree.links.new(emit.outputs[0], out.inputs["Surface"])


def _frustum_vertices(intr: Intrinsics, depth: float = FRUSTUM_DEPTH) -> np.ndarray:
    """Apex and the four frame corners at ``depth`` in the light's local frame (Blender: −Z forward, +Y up)."""
    w, h = intr.size
    rays = intr.rays(np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])) * depth
    local = rays * np.array([1.0, -1.0, -1.0])  # OpenCV device axes → Blender object axes
    return np.vstack([np.zeros(3), local])


def _projector_props(projector: Projector, index: int | None = None) -> dict[str, Any]:
    """The stored model; ``index`` (the projector's place in a rig of several) only where several exist, so a
    one-projector scene stores what it always did."""
    intr = projector.intrinsics
    return {"role": "projector", "width": int(intr.width), "height": int(intr.height),
            "fx": float(intr.fx), "fy": float(intr.fy), "cx": float(intr.cx), "cy": float(intr.cy),
            "intensity": float(projector.intensity),
            "input_size": [int(v) for v in projector.input_size],
            "input_offset": [int(v) for v in projector.input_offset],
            "pose": [float(v) for v in projector.camera_from_projector.ravel()],
            **({"index": int(index)} if index is not None else {})}


def projector_name(index: int) -> str:
    """The name a new projector object gets: "ProCam Projector" for the first, "ProCam Projector 2" … after."""
    return PROJECTOR_NAME if index == 0 else f"{PROJECTOR_NAME} {index + 1}"


def _build_projector(projector: Projector, built: _Built, rig_to_world: np.ndarray,
                     index: int | None = None) -> bpy.types.Object:
    intr = projector.intrinsics
    spot = spot_size_for(intr)  # may raise before anything is built
    name = projector_name(index or 0)
    light = built.add(bpy.data.lights, bpy.data.lights.new(name, "SPOT"))
    light.spot_size = spot
    light.spot_blend = 0.0
    light.show_cone = True
    light.shadow_soft_size = 0.0  # a pinhole: radius 0
    if hasattr(light, "use_soft_falloff"):
        light.use_soft_falloff = False  # Blender ≥ 4.0 softens point-light falloff near the source otherwise
    light.energy = ENERGY_PER_INTENSITY * projector.intensity
    light.color = (1.0, 1.0, 1.0)
    # Start with the input area white: the lit footprint shows where the projector reaches.
    frame = projector.frame_from_input(np.ones((projector.input_size[1], projector.input_size[0], 3), np.float32))
    image = _image_from_array(PROJECTOR_IMAGE_NAME if not index else f"{name} Frame", frame, built)
    _build_projector_nodes(light, intr, image)
    obj = built.add(bpy.data.objects, bpy.data.objects.new(name, light))
    obj.matrix_world = _matrix(frames.blender_matrix_world(rig_to_world @ projector.camera_from_projector))
    obj[PROP] = _projector_props(projector, index)

    # Viewport-only pyramid showing the asymmetric frustum (the spot cone is symmetric about the lens axis).
    frustum = FRUSTUM_NAME if not index else f"{name} Frustum"
    mesh = built.add(bpy.data.meshes, bpy.data.meshes.new(frustum))
    verts = _frustum_vertices(intr)
    edges = np.array([[0, 1], [0, 2], [0, 3], [0, 4], [1, 2], [2, 3], [3, 4], [4, 1]], dtype=np.int32)
    mesh.vertices.add(len(verts))
    mesh.vertices.foreach_set("co", verts.astype(np.float32).ravel())
    mesh.edges.add(len(edges))
    mesh.edges.foreach_set("vertices", edges.ravel())
    mesh.update()
    pyramid = built.add(bpy.data.objects, bpy.data.objects.new(frustum, mesh))
    pyramid.parent = obj
    pyramid.matrix_parent_inverse = Matrix.Identity(4)
    pyramid.hide_render = True
    pyramid.hide_select = True
    pyramid.display_type = "WIRE"
    pyramid[PROP] = {"role": "frustum"}
    return obj


def _build_surface(mesh: SurfaceMesh, built: _Built, rig_to_world: np.ndarray) -> bpy.types.Object:
    pts = mesh.vertices @ rig_to_world[:3, :3].T + rig_to_world[:3, 3]
    verts = frames.blender_points(pts)
    faces = mesh.faces.astype(np.int32)
    data = built.add(bpy.data.meshes, bpy.data.meshes.new(mesh.name or SURFACE_NAME))
    data.vertices.add(len(verts))
    data.vertices.foreach_set("co", verts.astype(np.float32).ravel())
    data.loops.add(faces.size)
    data.loops.foreach_set("vertex_index", faces.ravel())
    data.polygons.add(len(faces))
    data.polygons.foreach_set("loop_start", np.arange(0, faces.size, 3, dtype=np.int32))
    uv_layer = data.uv_layers.new(name="UVMap")
    uv_layer.data.foreach_set("uv", mesh.uvs[faces.ravel()].astype(np.float32).ravel())
    data.update()
    if data.validate():
        raise SurfaceError(f"surface {mesh.name!r} has invalid geometry (degenerate or duplicate faces); "
                           "clean the mesh")

    mat = built.add(bpy.data.materials, bpy.data.materials.new(f"{SURFACE_NAME} Material"))
    if mat.node_tree is None:  # Blender < 5.0 creates materials without nodes
        mat.use_nodes = True
    tree = mat.node_tree
    tree.nodes.clear()
    image = _image_from_array(f"{SURFACE_NAME} Albedo", mesh.albedo, built)
    tex = _add_node(tree, "ShaderNodeTexImage", (-400, 0), interpolation="Linear", extension="EXTEND", image=image)
    uvmap = _add_node(tree, "ShaderNodeUVMap", (-600, 0), uv_map="UVMap")
    tree.links.new(uvmap.outputs[0], tex.inputs["Vector"])
    bsdf = _add_node(tree, "ShaderNodeBsdfDiffuse", (-100, 0))
    bsdf.inputs["Roughness"].default_value = 0.0  # Lambertian
    tree.links.new(tex.outputs["Color"], bsdf.inputs["Color"])
    out = _add_node(tree, "ShaderNodeOutputMaterial", (150, 0))
    tree.links.new(bsdf.outputs[0], out.inputs["Surface"])
    data.materials.append(mat)

    obj = built.add(bpy.data.objects, bpy.data.objects.new(SURFACE_NAME, data))
    obj[PROP] = {"role": "surface"}
    return obj


def _remove_object_tree(obj: bpy.types.Object) -> None:
    """Remove an object, its children and their data when nothing else uses it."""
    for child in list(obj.children):
        _remove_object_tree(child)
    data = obj.data
    bpy.data.objects.remove(obj, do_unlink=True)
    if data is None or data.users:
        return
    if isinstance(data, bpy.types.Light):
        tree = data.node_tree
        images = [n.image for n in tree.nodes if n.type == "TEX_IMAGE" and n.image] if tree else []
        bpy.data.lights.remove(data)
        for img in images:
            if img.users == 0:
                bpy.data.images.remove(img)
    elif isinstance(data, bpy.types.Camera):
        bpy.data.cameras.remove(data)
    elif isinstance(data, bpy.types.Mesh):
        bpy.data.meshes.remove(data)


def _link(scene: bpy.types.Scene, obj: bpy.types.Object) -> None:
    scene.collection.objects.link(obj)
    for child in obj.children:
        _link(scene, child)


def _untag_others(scene: bpy.types.Scene, name: str, keep: bpy.types.Object) -> None:
    for other in _objects_with_role(scene, name):
        if other != keep:
            del other[PROP]


# --------------------------------------------------------------------------- public API


def create_camera(scene: bpy.types.Scene, intrinsics: Intrinsics) -> bpy.types.Object:
    """Add "ProCam Camera" reproducing K at the rig origin; replaces a previous ProCam camera."""
    return create_rig_objects(scene, camera=intrinsics).camera


def create_projector(scene: bpy.types.Scene, projector: Projector) -> bpy.types.Object:
    """Add "ProCam Projector" (spot light + frustum pyramid) at its rig pose; replaces a previous one."""
    return create_rig_objects(scene, projector=projector).projector


def create_surface(scene: bpy.types.Scene, mesh: SurfaceMesh) -> bpy.types.Object:
    """Add a textured mesh (UVs, Diffuse BSDF on a Non-Color float albedo) and make it the ProCam Surface."""
    return create_rig_objects(scene, surface=mesh).surface


def create_rig(scene: bpy.types.Scene, rig: Rig, surface: SurfaceMesh | None = None) -> RigObjects:
    """Camera, every projector of the rig and optionally a surface in one step: all built, or nothing changed."""
    return create_rig_objects(scene, camera=rig.camera.intrinsics, projector=rig.projector, others=rig.others,
                              surface=surface)


def add_projector(scene: bpy.types.Scene, projector: Projector) -> bpy.types.Object:
    """Add one more ProCam projector (light, frustum, image) at its rig pose, after the scene's projectors.

    The scene must hold a ProCam camera (the rig frame) and a projector already; the new one is projector N + 1.
    """
    objs = find_rig_objects(scene)
    if objs.camera is None or not objs.projectors:
        raise RigError("add a projector to a rig: create the rig first (ProCam ▸ Create Rig)")
    index = max(projector_index(o) for o in objs.projectors) + 1
    rig = read_rig(scene)
    rig.with_projectors((*rig.projectors, projector))  # refuses a projector at another's pose
    built = _Built()
    try:
        obj = _build_projector(projector, built, _rig_to_world(scene), index)
    except BaseException:
        built.remove_all()
        raise
    first = objs.projectors[0]
    if "index" not in _props(first):  # the first projector of a one-projector scene says it is the first
        data = _props(first)
        data["index"] = 0
        first[PROP] = data
    _link(scene, obj)
    return obj


def _split(projectors: Sequence[Projector]) -> tuple[Projector, tuple[Projector, ...]]:
    return projectors[0], tuple(projectors[1:])


def create_rig_objects(scene: bpy.types.Scene, *, camera: Intrinsics | None = None,
                       projector: Projector | None = None, surface: SurfaceMesh | None = None,
                       others: Sequence[Projector] = ()) -> RigObjects:
    """Build the given parts unlinked, then swap them into the scene; on any error remove what was built.

    A ``projector`` (with ``others``, projectors 2…N) replaces every projector of the scene."""
    built = _Built()
    # A new camera defines the rig frame at the world origin; otherwise keep the present camera's frame.
    rig_to_world = np.eye(4) if camera is not None else _rig_to_world(scene)
    others = tuple(others)
    if others and projector is None:
        raise RigError("other projectors need the first projector too")
    try:
        cam = _build_camera(camera, built) if camera is not None else None
        projs = ([_build_projector(p, built, rig_to_world, k if others else None)
                  for k, p in enumerate((projector, *others))] if projector is not None else [])
        surf = _build_surface(surface, built, rig_to_world) if surface is not None else None
    except BaseException:
        built.remove_all()
        raise
    proj = projs[0] if projs else None
    # Nothing below can fail on valid input: replace, link, and set the scene's render size.
    if cam is not None:
        for o in _objects_with_role(scene, "camera"):
            _remove_object_tree(o)
        _link(scene, cam)
        scene.camera = cam
        scene.render.resolution_x, scene.render.resolution_y = camera.size
        scene.render.resolution_percentage = 100
        scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    if projs:
        for o in _objects_with_role(scene, "projector"):
            _remove_object_tree(o)
        for o in projs:
            _link(scene, o)
    if surf is not None:
        _link(scene, surf)
        _untag_others(scene, "surface", surf)
    now = find_rig_objects(scene)
    return RigObjects(cam or now.camera, proj or now.projector, surf or now.surface, tuple(projs) or now.projectors)


def set_surface(scene: bpy.types.Scene, obj: bpy.types.Object | None) -> bpy.types.Object:
    """Mark a mesh object of the scene as the ProCam Surface (the previous one is unmarked)."""
    if obj is None:
        raise SurfaceError("no object selected: select the mesh to project onto")
    if obj.type != "MESH":
        raise SurfaceError(f"{obj.name!r} is a {obj.type.lower()}, not a mesh: select the mesh to project onto")
    if len(obj.data.polygons) == 0:
        raise SurfaceError(f"mesh {obj.name!r} has no faces (only points or edges): give the surface faces")
    if obj.name not in scene.objects:
        raise SurfaceError(f"{obj.name!r} is not in scene {scene.name!r}: link it to the scene first")
    if role(obj) in ("camera", "projector", "frustum"):
        raise SurfaceError(f"{obj.name!r} is part of the ProCam rig, not a surface")
    _untag_others(scene, "surface", obj)
    obj[PROP] = {"role": "surface"}
    return obj


def _render_size(scene: bpy.types.Scene) -> tuple[int, int]:
    r = scene.render
    pct = r.resolution_percentage / 100.0
    return max(1, round(r.resolution_x * pct)), max(1, round(r.resolution_y * pct))


def read_camera(scene: bpy.types.Scene) -> Camera:
    """The ProCam camera's intrinsics at the scene's render size."""
    cam = find_rig_objects(scene).camera
    if cam is None:
        raise RigError("the scene has no ProCam camera: create the rig first (ProCam ▸ Create Rig)")
    d = cam.data
    w, h = _render_size(scene)
    derived = frames.intrinsics_from_blender_camera(
        d.lens, d.sensor_width, d.sensor_height, d.sensor_fit, d.shift_x, d.shift_y, w, h,
        scene.render.pixel_aspect_x / scene.render.pixel_aspect_y)
    p = _props(cam)
    try:
        stored = Intrinsics(int(p["width"]), int(p["height"]), p["fx"], p["fy"], p["cx"], p["cy"])
    except (KeyError, TypeError, RigError):
        return Camera(derived)
    if stored.size == derived.size and np.max(np.abs(stored.matrix - derived.matrix)) <= _K_TOL:
        return Camera(stored)
    return Camera(derived)


def read_projector(scene: bpy.types.Scene, index: int | None = None) -> Projector:
    """A ProCam projector in the rig frame (pose relative to the ProCam camera): projector ``index`` of the rig
    (0 = the first), or by default the one the panels work on (the active one of several, else the only one)."""
    objs = find_rig_objects(scene)
    if objs.projector is None:
        raise RigError("the scene has no ProCam projector: create the rig first (ProCam ▸ Create Rig)")
    if index is None:
        return _read_projector_object(objs, objs.projector)
    if isinstance(index, bool) or not 0 <= index < len(objs.projectors):
        raise RigError(f"the scene has {len(objs.projectors)} ProCam projector(s), numbered 0 to "
                       f"{len(objs.projectors) - 1}; there is no projector {index!r}")
    return _read_projector_object(objs, objs.projectors[index])


def _read_projector_object(objs: RigObjects, obj: bpy.types.Object) -> Projector:
    p = _props(obj)
    try:
        intr = Intrinsics(int(p["width"]), int(p["height"]), p["fx"], p["fy"], p["cx"], p["cy"])
    except KeyError as exc:
        raise RigError(f"the ProCam projector {obj.name!r} lacks its stored {exc}; recreate the rig") from None
    pose_world = _stored_or_blender_pose(obj)
    rig_to_world = _camera_world_pose(objs.camera) if objs.camera is not None else np.eye(4)
    pose = pose_world if np.array_equal(rig_to_world, np.eye(4)) else np.linalg.inv(rig_to_world) @ pose_world
    intensity = float(p.get("intensity", 1.0))
    energy = obj.data.energy
    if abs(energy - ENERGY_PER_INTENSITY * intensity) > 1e-6 * max(1.0, energy):
        intensity = energy / ENERGY_PER_INTENSITY  # the user changed the light's power
    return Projector(intr, pose, intensity,
                     tuple(p["input_size"]) if "input_size" in p else None,
                     tuple(p["input_offset"]) if "input_offset" in p else None)


def read_rig(scene: bpy.types.Scene) -> Rig:
    """Camera and projectors of the scene as a :class:`Rig`, the projectors in their stored order (exact round trip
    while objects are untouched)."""
    camera = read_camera(scene)
    objs = find_rig_objects(scene)
    if not objs.projectors:
        raise RigError("the scene has no ProCam projector: create the rig first (ProCam ▸ Create Rig)")
    return Rig(camera, *_split([_read_projector_object(objs, o) for o in objs.projectors]))


def read_surface(scene: bpy.types.Scene) -> SurfaceMesh:
    """The ProCam Surface as a triangulated mesh in the rig frame (modifiers applied), with its albedo."""
    obj = find_rig_objects(scene).surface
    if obj is None:
        raise SurfaceError("the scene has no ProCam Surface: select a mesh and use ProCam ▸ Set Surface")
    return read_mesh_object(scene, obj)


def read_mesh_object(scene: bpy.types.Scene, obj: bpy.types.Object) -> SurfaceMesh:
    """Any mesh object as a triangulated mesh in the rig frame (modifiers applied), with its albedo."""
    if obj.type != "MESH":
        raise SurfaceError(f"{obj.name!r} is a {obj.type.lower()}, not a mesh: choose a mesh object")
    objs = find_rig_objects(scene)
    if bpy.context.scene == scene:
        depsgraph = bpy.context.evaluated_depsgraph_get()
    else:
        depsgraph = scene.view_layers[0].depsgraph
        depsgraph.update()
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        mesh.calc_loop_triangles()
        n_tri = len(mesh.loop_triangles)
        if n_tri == 0:
            raise SurfaceError(f"mesh {obj.name!r} has no faces: give the surface faces")
        co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
        mesh.vertices.foreach_get("co", co)
        tri_verts = np.empty(n_tri * 3, dtype=np.int32)
        mesh.loop_triangles.foreach_get("vertices", tri_verts)
        tri_loops = np.empty(n_tri * 3, dtype=np.int32)
        mesh.loop_triangles.foreach_get("loops", tri_loops)
        uv_layer = mesh.uv_layers.active
        if uv_layer is not None:
            loop_uv = np.empty(len(mesh.loops) * 2, dtype=np.float32)
            uv_layer.data.foreach_get("uv", loop_uv)
            tri_uv = loop_uv.reshape(-1, 2)[tri_loops].astype(np.float64)
        else:
            tri_uv = np.zeros((len(tri_loops), 2))
    finally:
        evaluated.to_mesh_clear()
    # A vertex with different UVs on different faces (a seam) becomes one vertex per UV.
    keys = np.column_stack([tri_verts.astype(np.float64), tri_uv])
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    vidx = uniq[:, 0].astype(np.int64)
    world = _np_matrix(obj.matrix_world)
    local = co.reshape(-1, 3).astype(np.float64)[vidx]
    pts_world = local @ world[:3, :3].T + world[:3, 3]
    rig_to_world = _camera_world_pose(objs.camera) if objs.camera is not None else np.eye(4)
    pts = frames.rig_points(pts_world)
    if not np.array_equal(rig_to_world, np.eye(4)):
        inv = np.linalg.inv(rig_to_world)
        pts = pts @ inv[:3, :3].T + inv[:3, 3]
    faces = inverse.reshape(-1, 3).astype(np.int32)
    if np.linalg.det(world[:3, :3]) < 0:
        faces = faces[:, ::-1].copy()  # a mirrored object flips the winding
    albedo = _surface_albedo(obj)
    return SurfaceMesh(pts, faces, np.clip(uniq[:, 1:], 0.0, 1.0), albedo, name=obj.name)


def _surface_albedo(obj: bpy.types.Object) -> np.ndarray:
    """The image of the first Image Texture in the object's materials, else uniform grey."""
    for slot in obj.material_slots:
        mat = slot.material
        if mat is None or mat.node_tree is None:
            continue
        for node in mat.node_tree.nodes:
            if node.type == "TEX_IMAGE" and node.image is not None and node.image.size[0] > 0:
                return np.clip(_image_to_array(node.image), 0.0, 1.0)
    return np.full((1, 1, 3), _GREY_ALBEDO, dtype=np.float32)


def _projector_frame_node(obj: bpy.types.Object) -> Any:
    if obj is None or obj.type != "LIGHT" or role(obj) != "projector":
        raise RigError("not a ProCam projector: create the rig first (ProCam ▸ Create Rig)")
    tree = obj.data.node_tree
    node = tree.nodes.get("ProCam Frame") if tree is not None else None
    if node is None:
        raise RigError(f"the projector {obj.name!r} has lost its image node; recreate the rig")
    return node


def set_projector_image(obj: bpy.types.Object, frame: np.ndarray | str | Path) -> bpy.types.Image:
    """Load a projector frame (array or image file) into the light, as float Non-Color data.

    The image must have the projector's native size, or its input size, in
    which case it is placed at the input offset in a black frame.
    """
    node = _projector_frame_node(obj)
    return _show_frame(obj, node, _native_frame(obj, frame))


def set_projector_frames(scene: bpy.types.Scene, frames: Sequence[np.ndarray | str | Path]) -> list[bpy.types.Image]:
    """Every ProCam projector of the scene shows its own frame: ``frames[k]`` on projector k (rig order).

    All frames are read and checked against their projector first: a wrong count or size changes no projector.
    """
    objs = find_rig_objects(scene)
    if len(objs.projectors) != len(frames):
        raise RigError(f"the scene has {len(objs.projectors)} ProCam projector(s), but there are frames for "
                       f"{len(frames)}: load the calibration they were made with (ProCam ▸ Load Calibration)")
    nodes = [_projector_frame_node(o) for o in objs.projectors]
    full = []
    for k, (obj, frame) in enumerate(zip(objs.projectors, frames)):
        try:
            full.append(_native_frame(obj, frame))
        except ImageError as exc:
            raise ImageError(f"projector {k + 1} ({obj.name!r}): {exc}") from None
    return [_show_frame(o, n, f) for o, n, f in zip(objs.projectors, nodes, full)]


def _native_frame(obj: bpy.types.Object, frame: np.ndarray | str | Path) -> np.ndarray:
    """A frame for the projector ``obj`` at its native size, checked (a frame of its input size is placed)."""
    p = _props(obj)
    w, h = int(p["width"]), int(p["height"])
    if isinstance(frame, (str, Path)):
        from ..imageio import read_image  # cv2 is heavy; only needed for files

        frame = read_image(frame, channels=3)
    img = np.asarray(frame, dtype=np.float32)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise ImageError(f"a projector frame must be H×W×3, got shape {img.shape}")
    img = img[..., :3]
    if not np.all(np.isfinite(img)):
        raise ImageError("the projector frame holds NaN or infinite values")
    iw, ih = (int(v) for v in p.get("input_size", (w, h)))
    if img.shape[:2] == (h, w):
        return img
    if img.shape[:2] == (ih, iw):
        return read_projector_from_object(obj).frame_from_input(img)
    size = f"{w}×{h}" + (f" (native) or {iw}×{ih} (input)" if (iw, ih) != (w, h) else "")
    raise ImageError(f"the projector frame must be {size} pixels, got {img.shape[1]}×{img.shape[0]}; "
                     "resize it or use the projector's resolution")


def _show_frame(obj: bpy.types.Object, node: Any, full: np.ndarray) -> bpy.types.Image:
    # a new image (another size) keeps the projector's own image name: several projectors never share one
    name = node.image.name if node.image is not None else PROJECTOR_IMAGE_NAME
    image = _image_from_array(name, np.clip(full, 0.0, None), image=node.image)
    if node.image is not image:
        old = node.image
        node.image = image
        if old is not None and old.users == 0:
            bpy.data.images.remove(old)
    return image


def read_projector_from_object(obj: bpy.types.Object) -> Projector:
    """The projector model stored on one light object (pose in Blender-world rig coordinates)."""
    p = _props(obj)
    intr = Intrinsics(int(p["width"]), int(p["height"]), p["fx"], p["fy"], p["cx"], p["cy"])
    return Projector(intr, _stored_or_blender_pose(obj), float(p.get("intensity", 1.0)),
                     tuple(p["input_size"]) if "input_size" in p else None,
                     tuple(p["input_offset"]) if "input_offset" in p else None)


def projector_image(obj: bpy.types.Object) -> np.ndarray:
    """The frame the projector currently shows (H×W×3 float32)."""
    node = _projector_frame_node(obj)
    if node.image is None:
        raise ImageError("the projector has no image loaded")
    return _image_to_array(node.image)


def rig_summary(scene: bpy.types.Scene) -> dict[str, str]:
    """Short human-readable state of the rig for the panel (no exceptions)."""
    objs = find_rig_objects(scene)
    out = {"camera": "none", "projector": "none", "surface": "none"}
    try:
        if objs.camera is not None:
            k = read_camera(scene).intrinsics
            fov = math.degrees(2 * math.atan(k.width / (2 * k.fx)))
            out["camera"] = f"{objs.camera.name}: {k.width}×{k.height}, {fov:.1f}° wide"
        if objs.projector is not None:
            pr = read_projector(scene)
            k = pr.intrinsics
            sx, sy = k.shift
            # with several, which one the panels show and work on: select another projector to switch
            which = (f" ({objs.projectors.index(objs.projector) + 1} of {len(objs.projectors)})"
                     if len(objs.projectors) > 1 else "")
            out["projector"] = (f"{objs.projector.name}{which}: {k.width}×{k.height}, throw {k.throw_ratio:.2f}, "
                                f"shift {100 * sx:+.0f}%/{100 * sy:+.0f}%")
    except Exception as exc:  # noqa: BLE001 — the panel must draw whatever state the user made
        out["error"] = str(exc)
    if objs.surface is not None:
        out["surface"] = f"{objs.surface.name}: {len(objs.surface.data.polygons)} faces"
    return out


# --------------------------------------------------------------------------- calibration and result images

CALIBRATED_SURFACE_NAME = "ProCam Calibrated Surface"


def _same_model(obj: bpy.types.Object, props: dict[str, Any]) -> bool:
    """True when a ProCam object's stored intrinsics (and input placement) equal ``props``."""
    mine = _props(obj)
    keys = [k for k in props if k not in ("pose", "role", "intensity")]
    try:
        return all(np.allclose(np.asarray(mine[k], dtype=float), np.asarray(props[k], dtype=float), atol=1e-9)
                   for k in keys)
    except (KeyError, TypeError, ValueError):
        return False


def apply_calibration(scene: bpy.types.Scene, rig: Rig, surface: SurfaceMesh, *, source: str = "",
                      move_projector: bool = True) -> RigObjects:
    """Bring a calibration into the scene: the projector moves to the estimated pose, the surface appears textured.

    ``move_projector`` False (a calibration whose pose stage has not run)
    leaves an existing projector where the artist put it.

    A camera and projector whose stored models equal the calibration's are
    kept (the projector is only moved, its image stays); others are replaced.
    Projectors are kept only all together (the same number, each one's model
    equal, in rig order); otherwise the scene's projectors become the
    calibration's.
    The reconstructed surface becomes the ProCam Surface; a surface from an
    earlier calibration is removed, the user's own surface is unmarked and
    hidden (so a render shows only the calibrated one) but kept.
    """
    objs = find_rig_objects(scene)
    keep_cam = objs.camera is not None and _same_model(objs.camera, _camera_props(rig.camera.intrinsics, np.eye(4)))
    # the scene's projectors, in rig order, are kept where each one's model is the calibration's projector's
    keep_proj = len(objs.projectors) == len(rig.projectors) and all(
        _same_model(o, _projector_props(p)) for o, p in zip(objs.projectors, rig.projectors))
    previous = [o for o in scene.objects if role(o) == "surface" or "calibration" in _props(o)]
    mesh = SurfaceMesh(surface.vertices, surface.faces, surface.uvs, surface.albedo, name=CALIBRATED_SURFACE_NAME)
    new = create_rig_objects(scene, camera=None if keep_cam else rig.camera.intrinsics,
                             projector=None if keep_proj else rig.projector, others=() if keep_proj else rig.others,
                             surface=mesh)
    # Nothing below can fail on valid objects: move, rename, tag, tidy.
    if keep_proj and move_projector:
        for proj, model in zip(new.projectors, rig.projectors):
            proj.matrix_world = _matrix(
                frames.blender_matrix_world(_rig_to_world(scene) @ model.camera_from_projector))
            data = _props(proj)
            data["pose"] = [float(v) for v in model.camera_from_projector.ravel()]
            data["intensity"] = float(model.intensity)
            proj[PROP] = data
            proj.data.energy = ENERGY_PER_INTENSITY * model.intensity
    new.surface.name = CALIBRATED_SURFACE_NAME
    new.surface[PROP] = {"role": "surface", "calibration": str(source)}
    for old in previous:
        if old == new.surface:
            continue
        if "calibration" in _props(old):
            _remove_object_tree(old)
        else:
            old.hide_viewport = old.hide_render = True
    return find_rig_objects(scene)


def set_image(name: str, rgb: np.ndarray) -> bpy.types.Image:
    """A packed float Non-Color image called ``name`` holding ``rgb``, reusing an image of that name and size."""
    img = np.asarray(rgb, dtype=np.float32)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    existing = bpy.data.images.get(name)
    image = _image_from_array(name, img[..., :3], image=existing)
    if existing is not None and existing is not image and existing.users == 0:
        bpy.data.images.remove(existing)
        image.name = name
    return image


def load_image_file(path: str | Path, name: str | None = None) -> bpy.types.Image:
    """A Blender image of a file on disk (not packed), read as data (Non-Color); reloaded if already loaded."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"image file not found: {path}")
    try:
        image = bpy.data.images.load(str(path), check_existing=True)
    except RuntimeError as exc:
        raise ImageError(f"Blender cannot read {path}: {exc}") from None
    image.reload()
    image.colorspace_settings.name = "Non-Color"  # our PNGs hold linear data (see imageio)
    if name:
        image.name = name
    return image
