"""Building the Mitsuba scene of the simulated projection f̂: camera, textured surface, projector.

Everything here is built once per forward model; what changes between renders
(the projector frame, its pose, the albedo) is a scene parameter that
:mod:`.forward` updates in place.

Camera
    A ``perspective`` sensor at the rig origin (``frames.mitsuba_to_world`` of
    the identity pose). Its horizontal field of view comes from ``fx``; the
    principal point from ``principal_point_offset_x/y``, which Mitsuba adds to
    the film position of each sample in units of the film width/height. We
    measured the sign: an offset ``o_x`` moves an image point by ``−o_x · W``
    pixels, so ``cx = W/2 − o_x·W``, i.e. ``o_x = (W/2 − cx)/W`` and
    ``o_y = (H/2 − cy)/H``. The sensor's vertical scale is tied to its
    horizontal one (square pixels), so ``fy`` must equal ``fx``. The film is an
    RGB ``hdrfilm`` with a ``box`` filter of radius ½, so a pixel integrates
    exactly its own square, as the Cycles lab does with its 1-px box filter.

Surface
    A ``mi.Mesh`` filled from the :class:`SurfaceMesh` arrays, with face normals
    (flat shading, the triangle mesh as it is) and a two-sided ``diffuse`` BSDF
    (reconstructed meshes do not always wind consistently; a two-sided BSDF
    still gives zero where light and viewer are on different sides). Its
    reflectance is a ``bitmap`` (raw, linear, bilinear, clamped at the edges so
    the left and right borders do not bleed into each other). Mitsuba looks up
    texture row ``v · H`` from the *top* of the image, while our UVs have
    ``v = 0`` at the bottom, so the mesh gets ``v' = 1 − v``
    (``tests/test_render_forward.py`` checks it with an asymmetric marker).

Projector
    Mitsuba's ``projector`` emitter is a pinhole with a *symmetric* frustum:
    for a point ``p`` in its local frame (``+z`` forward, ``+x`` left, ``+y``
    up) it looks up the irradiance texture at

        u_e = ½ − x / (2 t z),    v_e = ½ − a · y / (2 t z),

    with ``t = tan(fov_x / 2)`` and ``a`` = the texture's width/height
    (``perspective_projection(size, size, 0, fov_x)`` in
    ``src/emitters/projector.cpp``), and it is dark outside ``[0, 1]²``. It has
    no principal point. With OpenCV axes (``x_cv = −x``, ``y_cv = −y``) that is
    ``u_e = ½ + X / (2t)``, ``v_e = ½ + a·Y / (2t)``, where ``X = x_cv/z`` and
    ``Y = y_cv/z``.

    Our projector is a pinhole with any ``K``: the native W×H frame pixel
    (corner convention) of a ray ``(X, Y, 1)`` is ``col = fx·X + cx``,
    ``row = fy·Y + cy``. We pad the frame with a one-texel black border
    (texture (W+2)×(H+2), so ``a = (W+2)/(H+2)``), whose bitmap coordinates are
    ``u_p = (col + 1)/(W+2)``, ``v_p = (row + 1)/(H+2)``. Eliminating ``X, Y``:

        u_p = [2t·fx · u_e + (cx + 1 − t·fx)] / (W+2)
        v_p = [2t·fy/a · v_e + (cy + 1 − t·fy/a)] / (H+2)

    an affine map, which is exactly what the bitmap's ``to_uv`` transform
    applies to every lookup. Any ``fx ≠ fy`` and any ``cx, cy`` are exact.
    The symmetric frustum must enclose the shifted one plus the border
    (half-width ``t`` covers ``max(cx, W−cx) + 1`` columns and half-height
    ``t/a`` covers ``max(cy, H−cy) + 1`` rows); outside the frame, the
    ``clamp`` wrap mode returns the black border texel, so the light stops
    where the real frame ends. Bilinear filtering makes the frame edge a
    one-texel ramp centred on the edge (half intensity at ``col = 0``), and
    keeps the lookup differentiable in the pose.

    The emitter's radiance towards a point at depth ``z`` (local) and angle
    ``θ`` off its axis is ``π · scale · T(u, v) / (z² cos θ)``, so the
    irradiance on a plane facing it at distance 1 is ``π · scale · T`` (the
    model's ``intensity``) and a Lambertian surface of albedo ρ seen by the
    camera has radiance ``ρ · scale · T · cos θ_s / (z² cos θ)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np

from ..errors import ImageError, RigError
from ..rig.frames import mitsuba_to_world
from ..rig.model import Intrinsics, Rig
from ..surface.mesh import SurfaceMesh

EMITTER_ID = "projector"
SURFACE_ID = "surface"
SENSOR_ID = "camera"

#: Integrator used for direct light (see :func:`integrator_dict` and the timings in :mod:`.forward`).
DIRECT_INTEGRATOR = "direct"

#: Largest image error (pixels, at the farthest image edge) we accept from drawing a camera with fx ≠ fy.
SQUARE_PIXEL_TOLERANCE_PX = 0.05


@dataclass(frozen=True)
class ProjectorFrustum:
    """How a W×H projector with any K is drawn by Mitsuba's symmetric ``projector`` emitter."""

    fov_x_deg: float
    padded_size: tuple[int, int]  # (W + 2, H + 2)
    to_uv: np.ndarray  # 3×3 affine map: emitter uv → padded-texture uv


def projector_frustum(intr: Intrinsics) -> ProjectorFrustum:
    """Symmetric frustum and texture transform that reproduce ``intr`` exactly (derivation in the module doc)."""
    w, h = intr.size
    pw, ph = w + 2, h + 2
    a = pw / ph
    # Half-extent (tangent units) needed in x and y, each including the one-texel border.
    need_x = (max(intr.cx, w - intr.cx) + 1.0) / intr.fx
    need_y = (max(intr.cy, h - intr.cy) + 1.0) / intr.fy
    t = max(need_x, a * need_y)
    fov = math.degrees(2.0 * math.atan(t))
    if not 0.0 < fov < 179.0:
        raise RigError(f"the projector's field of view ({fov:.1f}° with lens shift) is too wide to simulate; "
                       "check its focal length (throw ratio) and principal point")
    to_uv = np.array([[2 * t * intr.fx / pw, 0.0, (intr.cx + 1.0 - t * intr.fx) / pw],
                      [0.0, 2 * t * intr.fy / (a * ph), (intr.cy + 1.0 - t * intr.fy / a) / ph],
                      [0.0, 0.0, 1.0]])
    return ProjectorFrustum(fov, (pw, ph), to_uv)


def camera_sensor_settings(intr: Intrinsics) -> dict[str, float]:
    """Field of view and principal-point offsets of a Mitsuba ``perspective`` sensor for ``intr``."""
    w, h = intr.size
    edge = max(intr.cy, h - intr.cy) / intr.fy
    if abs(intr.fx - intr.fy) * edge > SQUARE_PIXEL_TOLERANCE_PX:
        raise RigError(
            f"the simulated camera needs square pixels, but fx={intr.fx:.3f} and fy={intr.fy:.3f} differ by "
            f"{abs(intr.fx - intr.fy) * edge:.2f} px at the image edge; resample the camera images so that "
            "fx = fy (e.g. scale the rows by fx/fy) and calibrate again")
    return {"fov": math.degrees(2.0 * math.atan(w / (2.0 * intr.fx))),
            "principal_point_offset_x": (w / 2 - intr.cx) / w,
            "principal_point_offset_y": (h / 2 - intr.cy) / h}


def border_smoothing(width: int, height: int, eps: float) -> np.ndarray:
    """Γ(i)·Γ(j) of the paper's Eq. 11–12 at texel centres, as an H×W float32 array (all ones when eps = 0)."""
    if not 0.0 <= eps < 0.5:
        raise RigError(f"border smoothing ε must lie in [0, 0.5), got {eps}")
    if eps == 0.0:
        return np.ones((height, width), dtype=np.float32)

    def gamma(n: int) -> np.ndarray:
        t = (np.arange(n) + 0.5) / n
        return np.minimum(1.0, np.minimum(t, 1.0 - t) / eps)

    return (gamma(height)[:, None] * gamma(width)[None, :]).astype(np.float32)


def pad_index(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """For each element of the padded (H+2)×(W+2)×3 texture: its index in the H×W×3 frame, and whether it has one.

    Used with a masked gather so that padding stays differentiable in Dr.Jit.
    """
    rows, cols, ch = np.meshgrid(np.arange(height + 2), np.arange(width + 2), np.arange(3), indexing="ij")
    inside = (rows >= 1) & (rows <= height) & (cols >= 1) & (cols <= width)
    index = ((rows - 1) * width + (cols - 1)) * 3 + ch
    return np.where(inside, index, 0).astype(np.uint32).ravel(), inside.ravel()


def check_image(image: Any, size: tuple[int, int], what: str, hint: str) -> np.ndarray:
    """An H×W×3 float32 copy of an image of the given (width, height); grey H×W images are repeated."""
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    w, h = size
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[:2] != (h, w):
        raise ImageError(f"{what} must be {w}×{h} pixels with 3 channels (H×W×3), got shape {img.shape}; {hint}")
    if not np.all(np.isfinite(img)):
        raise ImageError(f"{what} holds NaN or infinite values; {hint}")
    return img


def integrator_dict(bounces: int, kind: str = "auto") -> dict[str, Any]:
    """Integrator for direct light only (bounces = 0) or with ``bounces`` indirect bounces.

    ``prb`` with ``max_depth = 2 + bounces``: depth 1 would be emitters seen
    directly (the projector is a delta light, never seen), depth 2 adds direct
    illumination, each further depth one indirect bounce. For direct light,
    ``direct`` with one emitter sample per camera ray (the projector is a delta
    light, so more emitter samples per ray would repeat the same value) and no
    BSDF samples (they can never hit a delta light) was measured against ``prb``
    with ``max_depth = 2``; see :mod:`.forward` for the numbers and the choice.
    """
    if not isinstance(bounces, (int, np.integer)) or bounces < 0:
        raise RigError(f"bounces must be a whole number ≥ 0 (0 = direct light only), got {bounces!r}")
    if kind == "auto":
        kind = DIRECT_INTEGRATOR if bounces == 0 else "prb"
    if kind == "direct":
        if bounces:
            raise RigError("the 'direct' integrator cannot simulate indirect bounces; use 'prb'")
        return {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0}
    return {"type": kind, "max_depth": 2 + int(bounces), "rr_depth": 2 + int(bounces) + 1}


def surface_mesh(mi: ModuleType, surface: SurfaceMesh) -> Any:
    """A Mitsuba mesh (no BSDF yet) holding the surface's triangles and UVs (v flipped for Mitsuba)."""
    v = np.asarray(surface.vertices, dtype=np.float32)
    f = np.asarray(surface.faces, dtype=np.uint32)
    uv = np.asarray(surface.uvs, dtype=np.float32).copy()
    uv[:, 1] = 1.0 - uv[:, 1]  # ours: v = 0 at the bottom row; Mitsuba's bitmap: v = 0 at the top row
    mesh = mi.Mesh(SURFACE_ID, len(v), len(f), has_vertex_normals=False, has_vertex_texcoords=True)
    mp = mi.traverse(mesh)
    mp["vertex_positions"] = mi.Float(v.ravel())
    mp["faces"] = mi.UInt32(f.ravel())
    mp["vertex_texcoords"] = mi.Float(uv.ravel())
    mp.update()
    return mesh


def _crop_settings(crop: tuple[int, int, int, int] | None, w: int, h: int) -> dict[str, int]:
    """The hdrfilm's crop window, checked against the film."""
    if crop is None:
        return {}
    x, y, cw, ch = (int(v) for v in crop)
    if cw < 1 or ch < 1 or x < 0 or y < 0 or x + cw > w or y + ch > h:
        raise RigError(f"the camera crop {crop} does not lie inside the {w}×{h} film")
    return {"crop_offset_x": x, "crop_offset_y": y, "crop_width": cw, "crop_height": ch}


def build_scene(mi: ModuleType, rig: Rig, surface: SurfaceMesh, camera: Intrinsics, *,
                bounces: int = 0, spp: int = 4, integrator: str = "auto", glossy_roughness: float | None = None,
                crop: tuple[int, int, int, int] | None = None) -> Any:
    """Load the Mitsuba scene of a rig and surface, rendered at the resolution of ``camera``.

    The projector starts dark; :class:`.forward.ForwardModel` sets its frame.
    ``glossy_roughness`` replaces the diffuse material by a white GGX lobe of that
    (Blender-style) roughness, α = roughness²: the diagnosis mixes such renders
    with the diffuse ones to model a non-Lambertian surface (``gap`` effect ``glossy``).
    ``crop`` = (x, y, width, height) in camera pixels renders only that window of the film (same lens).
    """
    if not isinstance(spp, (int, np.integer)) or spp < 1:
        raise RigError(f"samples per pixel must be a whole number ≥ 1, got {spp!r}")
    proj = rig.projector
    frustum = projector_frustum(proj.intrinsics)
    pw, ph = frustum.padded_size
    w, h = camera.size
    root = int(round(math.sqrt(spp)))
    # Stratified (jittered) samples integrate a pixel's square with less noise; it needs a square count.
    sampler = "stratified" if root * root == spp else "independent"

    reflectance = {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(surface.albedo, dtype=np.float32)),
                   "raw": True, "filter_type": "bilinear", "wrap_mode": "clamp"}
    if glossy_roughness is None:
        material = {"type": "diffuse", "reflectance": reflectance}
    else:
        material = {"type": "roughconductor", "material": "none", "distribution": "ggx",
                    "alpha": max(float(glossy_roughness) ** 2, 1e-3)}
    bsdf = mi.load_dict({"type": "twosided", "material": material})
    mesh = surface_mesh(mi, surface)
    mesh.set_bsdf(bsdf)

    return mi.load_dict({
        "type": "scene",
        "integrator": integrator_dict(bounces, integrator),
        SENSOR_ID: {
            "type": "perspective", "fov_axis": "x", **camera_sensor_settings(camera),
            "near_clip": 1e-3, "far_clip": 1e4,
            "to_world": mi.ScalarTransform4f(mitsuba_to_world(np.eye(4)).astype(np.float32)),
            "sampler": {"type": sampler, "sample_count": int(spp)},
            "film": {"type": "hdrfilm", "width": int(w), "height": int(h), "pixel_format": "rgb",
                     "component_format": "float32", "rfilter": {"type": "box"}, **_crop_settings(crop, w, h)},
        },
        EMITTER_ID: {
            "type": "projector", "fov": frustum.fov_x_deg, "fov_axis": "x", "scale": float(proj.intensity),
            "to_world": mi.ScalarTransform4f(mitsuba_to_world(proj.camera_from_projector).astype(np.float32)),
            "irradiance": {"type": "bitmap", "bitmap": mi.Bitmap(np.zeros((ph, pw, 3), dtype=np.float32)),
                           "raw": True, "filter_type": "bilinear", "wrap_mode": "clamp",
                           "to_uv": mi.ScalarTransform3f(frustum.to_uv.astype(np.float32))},
        },
        SURFACE_ID: mesh,
    })
