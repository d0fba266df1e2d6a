"""The virtual lab: a projector and camera simulated with Cycles plus injected real-world effects.

It stands in for real hardware. Cycles is not the model the pipeline uses
(Mitsuba), and the effects of :mod:`.effects` are applied where they arise in
a real rig: projector effects on the frame before it is emitted, scene effects
(interreflection, glossy surface) in the Cycles scene, camera effects on the
rendered image. The truth — the real projector pose, the surface, the effects
and their parameters — is written to a *sealed* JSON file outside the capture
set; pipeline and diagnosis code never read it, only evaluation does, and the
lab device can be re-opened from it to capture more images later.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..capture.devices import Device, capture_sequence
from ..capture.format import CaptureSet, DepthInfo
from ..capture.patterns import calibration_sequence
from ..errors import LabError
from ..imageio import write_atomic_bytes
from ..rig.demo import demo_rig
from ..rig.model import Camera, Projector, Rig
from ..surface.mesh import SurfaceMesh
from ..surface.shapes import SHAPES, builtin_surface
from .effects import EffectSet, apply_camera, apply_projector, camera_render_intrinsics, parse_effects, render_settings

TRUTH_FORMAT = "procam-lab-truth"


def rough_pose(pose: np.ndarray, rng: np.random.Generator, offset_m: float = 0.16,
               angle_deg: float = 5.5) -> np.ndarray:
    """The pose an artist would place by eye: ``offset_m`` away and ``angle_deg`` turned, random directions."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    a = math.radians(angle_deg)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k
    shift = rng.normal(size=3)
    out = pose.copy()
    out[:3, :3] = rot @ pose[:3, :3]
    out[:3, 3] = pose[:3, 3] + offset_m * shift / np.linalg.norm(shift)
    return out


@dataclass(frozen=True)
class LabTruth:
    """Everything the lab knows and the pipeline must not: the sealed truth of one lab session."""

    rig: Rig
    surface: SurfaceMesh
    surface_source: str
    effects: EffectSet
    seed: int
    samples: int
    nominal_pose: np.ndarray

    def save(self, path: str | Path) -> Path:
        """Write ``path`` (JSON) and the surface beside it (``<stem>.surface.npz``), each atomically."""
        path = Path(path)
        mesh_path = path.with_name(path.stem + ".surface.npz")
        import io
        buf = io.BytesIO()
        np.savez_compressed(buf, vertices=self.surface.vertices, faces=self.surface.faces, uvs=self.surface.uvs,
                            albedo=self.surface.albedo)
        write_atomic_bytes(mesh_path, buf.getvalue())
        doc = {"format": TRUTH_FORMAT, "version": 1,
               "warning": "sealed lab truth: only evaluation code may read this file",
               "rig": self.rig.to_dict(),
               "camera_from_projector": self.rig.projector.camera_from_projector.tolist(),
               "nominal_camera_from_projector": np.asarray(self.nominal_pose).tolist(),
               "surface": {"source": self.surface_source, "mesh": mesh_path.name, "name": self.surface.name},
               "effects": self.effects.to_dict(), "effects_spec": self.effects.spec,
               "seed": int(self.seed), "samples": int(self.samples)}
        write_atomic_bytes(path, (json.dumps(doc, indent=1) + "\n").encode())
        return path

    @staticmethod
    def load(path: str | Path) -> "LabTruth":
        path = Path(path)
        try:
            doc = json.loads(path.read_text())
            if doc.get("format") != TRUTH_FORMAT:
                raise LabError(f"{path} is not a ProCam lab truth file")
            data = np.load(path.with_name(doc["surface"]["mesh"]))
            surface = SurfaceMesh(data["vertices"], data["faces"], data["uvs"], data["albedo"],
                                  name=doc["surface"].get("name", "surface"))
            return LabTruth(Rig.from_dict(doc["rig"]), surface, doc["surface"]["source"],
                            EffectSet.from_dict(doc["effects"]), int(doc["seed"]), int(doc["samples"]),
                            np.asarray(doc["nominal_camera_from_projector"], dtype=float))
        except FileNotFoundError as exc:
            raise LabError(f"lab truth not found: {exc.filename}") from None
        except (OSError, ValueError, KeyError) as exc:
            raise LabError(f"cannot read lab truth {path}: {exc}") from None


def make_truth(surface: str | Path = "curve", *, effects: str | EffectSet | None = None, seed: int = 0,
               samples: int = 16, camera_size: tuple[int, int] = (640, 480),
               projector_size: tuple[int, int] = (800, 600)) -> LabTruth:
    """A lab session on a built-in surface (``plane``, ``curve``, ``vedge``, ``hedge``) or a mesh file."""
    if isinstance(surface, str) and surface in SHAPES:
        mesh = builtin_surface(surface, seed=seed)
        source = surface
    else:
        mesh = load_mesh_file(Path(surface))
        source = str(Path(surface).resolve())
    if not isinstance(samples, int) or samples < 1:
        raise LabError(f"Cycles samples must be a whole number ≥ 1, got {samples!r}")
    rig = demo_rig(camera_size, projector_size)
    rng = np.random.default_rng(seed + 7919)
    return LabTruth(rig, mesh, source, parse_effects(effects), seed, samples,
                    rough_pose(rig.projector.camera_from_projector, rng))


def load_mesh_file(path: Path) -> SurfaceMesh:
    """A user's ``.obj``/``.ply`` surface (rig frame, metres), with its texture if the file names one."""
    if not path.is_file():
        raise LabError(f"unknown surface {str(path)!r}: not one of {', '.join(SHAPES)} and no such mesh file")
    import pymeshlab

    ms = pymeshlab.MeshSet()
    try:
        ms.load_new_mesh(str(path))
    except pymeshlab.PyMeshLabException as exc:
        raise LabError(f"cannot read mesh {path}: {exc}") from None
    m = ms.current_mesh()
    verts, faces = np.asarray(m.vertex_matrix()), np.asarray(m.face_matrix())
    if len(faces) == 0:
        raise LabError(f"mesh {path} has no faces")
    albedo = np.full((4, 4, 3), 0.8, np.float32)
    uvs = np.zeros((len(verts), 2))
    if m.has_wedge_tex_coord() and m.texture_number() > 0:
        from ..imageio import read_image
        wedge = np.asarray(m.wedge_tex_coord_matrix()).reshape(-1, 3, 2)
        uvs[faces.ravel()] = wedge.reshape(-1, 2)  # one UV per vertex: seams take the last wedge's UV
        tex = path.parent / m.texture(0).name if hasattr(m.texture(0), "name") else None
        if tex is not None and tex.is_file():
            albedo = read_image(tex)
    elif m.has_vertex_tex_coord():
        uvs = np.asarray(m.vertex_tex_coord_matrix())
    return SurfaceMesh(verts, faces, uvs, albedo, name=path.stem)


class LabDevice(Device):
    """A capture device that renders with Cycles: ``project(frame)`` returns the simulated camera image."""

    def __init__(self, truth: LabTruth, *, samples: int | None = None) -> None:
        import bpy

        from ..rig import blender_rig

        self.truth = truth
        self.projector = truth.rig.projector
        self.camera = truth.rig.camera
        self.effects = truth.effects
        self.samples = int(samples or truth.samples)
        self._settings = render_settings(truth.effects, self.camera.intrinsics)
        self._rng = np.random.default_rng(truth.seed)
        self._shots = 0
        bpy.ops.wm.read_factory_settings(use_empty=True)
        self._scene = bpy.context.scene
        # Lens distortion resamples the image, so render a margin around it (same focal length).
        render_k = camera_render_intrinsics(truth.effects, self.camera.intrinsics)
        objs = blender_rig.create_rig(self._scene, Rig(Camera(render_k), truth.rig.projector), truth.surface)
        self._light = objs.projector
        if self._settings.get("glossy_weight", 0.0) > 0:
            _add_glossy_lobe(objs.surface, self._settings["glossy_weight"], self._settings["glossy_roughness"])

    @property
    def bounces(self) -> int:
        return int(self._settings.get("diffuse_bounces", 0))

    def _render(self) -> np.ndarray:
        from .cycles import render_cycles

        self._shots += 1
        img = render_cycles(self._scene, samples=self.samples, bounces=self.bounces,
                            seed=self.truth.seed * 100003 + self._shots)
        return apply_camera(img, self.effects, self.camera.intrinsics, self._rng)

    def project(self, frame: np.ndarray) -> np.ndarray:
        from ..rig import blender_rig

        f = self.check_frame(frame)
        blender_rig.set_projector_image(self._light, apply_projector(f, self.effects, self.projector))
        return self._render()

    def capture_off(self) -> np.ndarray:
        """Projector switched off: only ambient light (and camera effects) remain."""
        light = self._light.data
        energy = light.energy
        light.energy = 0.0
        try:
            return self._render()
        finally:
            light.energy = energy

    def depth(self) -> tuple[np.ndarray, DepthInfo]:
        """A phone-LiDAR-like depth image at camera resolution, and how it was taken."""
        from ..render.raycast import depth_map
        from .depth import depth_capture, sensor_resolution

        k = self.camera.intrinsics
        d = depth_capture(depth_map(self.truth.surface, k), k, self.effects, self._rng)
        return d, DepthInfo(k, tuple(sensor_resolution(self.effects, k)))


def _add_glossy_lobe(obj: Any, weight: float, roughness: float) -> None:
    """Mix a GGX glossy lobe into the surface's diffuse material (non-Lambertian reflectance)."""
    tree = obj.active_material.node_tree
    out = next(n for n in tree.nodes if n.type == "OUTPUT_MATERIAL")
    diffuse = next(n for n in tree.nodes if n.type == "BSDF_DIFFUSE")
    glossy = tree.nodes.new("ShaderNodeBsdfGlossy")
    glossy.distribution = "GGX"
    glossy.inputs["Roughness"].default_value = float(roughness)
    mix = tree.nodes.new("ShaderNodeMixShader")
    mix.inputs["Fac"].default_value = float(weight)
    tree.links.new(diffuse.outputs[0], mix.inputs[1])
    tree.links.new(glossy.outputs[0], mix.inputs[2])
    tree.links.new(mix.outputs[0], out.inputs["Surface"])


def run_lab(truth: LabTruth, out_dir: str | Path, *, truth_path: str | Path, force: bool = False,
            graycode: bool = True, validation: bool = True, progress: Any = None) -> CaptureSet:
    """Render a complete calibration capture set into ``out_dir`` and seal the truth at ``truth_path``."""
    out_dir, truth_path = Path(out_dir).absolute(), Path(truth_path).absolute()
    if out_dir == truth_path.parent or out_dir in truth_path.parents:
        raise LabError(f"the truth file {truth_path} must lie outside the capture set {out_dir}")
    if not truth_path.parent.is_dir():
        raise LabError(f"cannot write the truth file: folder {truth_path.parent} does not exist")
    device = LabDevice(truth)
    nominal = replace(truth.rig.projector, camera_from_projector=truth.nominal_pose)
    seq = calibration_sequence(truth.rig.projector, graycode=graycode, validation=validation, seed=truth.seed)
    if progress is not None:
        seq = progress(seq)
    depth, depth_info = device.depth()

    class _Nominal(Device):
        """The lab device as the pipeline sees it: it reports the nominal projector, not the true one."""

        projector = nominal

        def project(self, frame: np.ndarray) -> np.ndarray:
            return device.project(frame)

        def capture_off(self) -> np.ndarray:
            return device.capture_off()

    result = capture_sequence(_Nominal(), seq, out_dir, truth.rig.camera, force=force, depth=depth,
                              depth_info=depth_info,
                              notes={"device": "virtual lab (Cycles)", "samples": device.samples,
                                     "truth": "sealed, outside this folder"})
    truth.save(truth_path)
    return result
