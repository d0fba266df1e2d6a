"""The virtual lab: a projector and camera simulated with Cycles plus injected real-world effects.

It stands in for real hardware. Cycles is not the model the pipeline uses
(Mitsuba), and the effects of :mod:`.effects` are applied where they arise in
a real rig: projector effects on the frame before it is emitted, scene effects
(interreflection, glossy surface) in the Cycles scene, camera effects on the
rendered image. The truth — the real projector pose, the surface, the effects
and their parameters — is written to a *sealed* JSON file outside the capture
set; pipeline and diagnosis code never read it, only evaluation does, and the
lab device can be re-opened from it to capture more images later.

Randomness: every shot ``k`` of a device draws its Cycles seed and its sensor
noise from ``(seed, k)`` alone, and the depth image from ``(seed, "depth")``.
So two devices opened on the same truth (or on its saved copy) with the same
seed return identical captures for the same sequence of frames, and taking
the depth image or not does not change any RGB capture.

The device builds its objects in a scene of its own (``bpy.data.scenes.new``)
and removes that scene and everything it created on :meth:`LabDevice.close`,
so it can run inside a user's Blender session without touching their scene.
"""

from __future__ import annotations

import io
import json
import math
import os
import shutil
import tempfile
import zipfile
import zlib
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..capture.devices import Device
from ..capture.format import CaptureSet, CaptureSetWriter, DepthInfo, WALL_PARAM, is_capture_set, validate_depth
from ..capture.patterns import PatternSpec, calibration_sequence
from ..errors import CaptureError, LabError
from ..imageio import write_atomic_bytes
from ..outputs import check_file_replaceable, check_replaceable, hidden_sibling, remove_stale_siblings
from ..progress import Cancel, Progress, check, quiet
from ..render.raycast import depth_map
from ..rig.demo import demo_projector, demo_rig
from ..rig.model import Camera, Intrinsics, Projector, Rig
from ..safepaths import inside
from ..surface.mesh import SurfaceMesh, read_mesh_file
from ..surface.shapes import SHAPES, builtin_surface
from .depth import depth_capture, sensor_resolution
from .effects import EffectSet, apply_camera, apply_projector, camera_render_intrinsics, parse_effects, render_settings

TRUTH_FORMAT = "procam-lab-truth"
#: Name of the scratch scene a :class:`LabDevice` renders in.
LAB_SCENE_NAME = "ProCam Lab"
#: Pattern kinds that calibration only binarises: rendered with fewer samples (see :func:`binary_samples`).
BINARY_KINDS = ("checker", "graycode")
#: Cycles takes a signed 32-bit seed.
_SEED_RANGE = 2 ** 31
#: Radiance of the even room light for the projector-off photo (white world; a white Lambertian texel facing it
#: reads about this much). The photo of the surface is taken with the room lights on, like the colour image of a
#: depth scan: it shows the surface's own colours, which is how calibration fills the albedo outside the projector's
#: reach and how the diagnosis tells projector vignetting from paint. Every other capture is taken in the dark.
ROOM_LIGHT = 0.25

#: ``progress(done, total, message)``: called before each step of :func:`run_lab`.


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
    #: the projector's spec-sheet intrinsics the pipeline is given; None: the true ones
    nominal_intrinsics: Intrinsics | None = None
    #: the camera's intrinsics the pipeline is given (a field of view read off a spec); None: the true ones
    nominal_camera_intrinsics: Intrinsics | None = None

    @property
    def nominal_camera(self) -> Camera:
        """The camera as the pipeline is told it is."""
        return Camera(self.nominal_camera_intrinsics or self.rig.camera.intrinsics)

    @property
    def nominal_projector(self) -> Projector:
        """The projector as the pipeline is told it is: nominal pose (placed by eye) and nominal intrinsics."""
        proj = self.rig.projector
        return replace(proj, intrinsics=self.nominal_intrinsics or proj.intrinsics,
                       camera_from_projector=np.asarray(self.nominal_pose, dtype=float))

    @staticmethod
    def mesh_path(path: str | Path) -> Path:
        """Where the surface of the truth file ``path`` is stored (``<stem>.surface.npz`` beside it)."""
        path = Path(path)
        return path.with_name(path.stem + ".surface.npz")

    def save(self, path: str | Path) -> Path:
        """Write ``path`` (JSON) and the surface beside it (``<stem>.surface.npz``), each atomically."""
        path = Path(path)
        mesh_path = self.mesh_path(path)
        buf = io.BytesIO()
        np.savez_compressed(buf, vertices=self.surface.vertices, faces=self.surface.faces, uvs=self.surface.uvs,
                            albedo=self.surface.albedo)
        write_atomic_bytes(mesh_path, buf.getvalue())
        doc = {"format": TRUTH_FORMAT, "version": 1,
               "warning": "sealed lab truth: only evaluation code may read this file",
               "rig": self.rig.to_dict(),
               "camera_from_projector": self.rig.projector.camera_from_projector.tolist(),
               "nominal_camera_from_projector": np.asarray(self.nominal_pose).tolist(),
               **({"nominal_projector_intrinsics": self.nominal_intrinsics.to_dict()}
                  if self.nominal_intrinsics is not None else {}),
               **({"nominal_camera_intrinsics": self.nominal_camera_intrinsics.to_dict()}
                  if self.nominal_camera_intrinsics is not None else {}),
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
            if not isinstance(doc, dict) or doc.get("format") != TRUTH_FORMAT:
                raise LabError(f"{path} is not a ProCam lab truth file")
            data = np.load(inside(path.parent, doc["surface"]["mesh"], what="the lab truth's surface mesh",
                                  error=LabError))
            surface = SurfaceMesh(data["vertices"], data["faces"], data["uvs"], data["albedo"],
                                  name=doc["surface"].get("name", "surface"))
            return LabTruth(Rig.from_dict(doc["rig"]), surface, doc["surface"]["source"],
                            EffectSet.from_dict(doc["effects"]), int(doc["seed"]), int(doc["samples"]),
                            np.asarray(doc["nominal_camera_from_projector"], dtype=float),
                            Intrinsics.from_dict(doc["nominal_projector_intrinsics"])
                            if "nominal_projector_intrinsics" in doc else None,
                            Intrinsics.from_dict(doc["nominal_camera_intrinsics"])
                            if "nominal_camera_intrinsics" in doc else None)
        except FileNotFoundError as exc:
            raise LabError(f"lab truth not found: {exc.filename}") from None
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise LabError(f"cannot read lab truth {path}: {exc}") from None


def _whole(value: Any, what: str, lo: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < lo:
        raise LabError(f"{what} must be a whole number ≥ {lo}, got {value!r}")
    return int(value)


def check_supersample(value: Any) -> int:
    """The camera's supersampling (``apply_camera``) as a whole number from 1 to 4, else a :class:`LabError`."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 1 <= value <= 4:
        raise LabError(f"the supersampling must be a whole number from 1 to 4, got {value!r}")
    return int(value)


def scaled_rig(rig: Rig, scale: float) -> Rig:
    """The same rig at ``scale`` times its resolutions (same lenses and pose; at least 8×6 pixels)."""
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not 0.05 <= scale <= 2:
        raise LabError(f"the resolution scale must lie between 0.05 and 2, got {scale!r}")
    if scale == 1:
        return rig

    def size(intr: Any) -> tuple[int, int]:
        return max(8, round(intr.width * scale)), max(6, round(intr.height * scale))

    return Rig(Camera(rig.camera.intrinsics.scaled(*size(rig.camera.intrinsics))),
               rig.projector.scaled(*size(rig.projector.intrinsics)))


def make_truth(surface: str | Path | SurfaceMesh = "curve", *, effects: str | EffectSet | None = None,
               seed: int = 0, samples: int = 16, camera_size: tuple[int, int] = (640, 480),
               projector_size: tuple[int, int] = (800, 600), rig: Rig | None = None, scale: float = 1.0,
               surface_source: str | None = None, projector_shift: tuple[float, float] | None = None,
               nominal_error: tuple[float, float] = (0.0, 0.0), camera_fov_error: float = 0.0) -> LabTruth:
    """A lab session on a built-in surface (``plane``, ``curve``, ``vedge``, ``hedge``), a mesh file or a mesh.

    ``rig`` replaces the demo rig (then ``camera_size``/``projector_size``/``projector_shift``
    are not used); ``projector_shift`` (right, up; fractions of the image) gives the demo
    projector another lens shift, aimed so that its image still lands on the surface;
    ``scale`` scales either rig's resolutions (:func:`scaled_rig`). ``nominal_error``
    (focal length as a fraction, vertical lens shift in image heights) makes the
    projector's spec-sheet intrinsics the pipeline is given wrong by that much, as
    a throw ratio and shift read off a data sheet are. ``camera_fov_error``
    (degrees) does the same to the camera's horizontal field of view: the
    capture set, its depth image included, then carries that camera.
    The nominal projector pose the pipeline gets is the true one disturbed as
    by a person placing it by eye (:func:`rough_pose`). Cheap checks come
    first so that a bad request fails before any mesh is read.
    """
    seed = _whole(seed, "the seed", 0)
    samples = _whole(samples, "Cycles samples", 1)
    effect_set = parse_effects(effects)
    if rig is None:
        for what, size in (("camera", camera_size), ("projector", projector_size)):
            if len(size) != 2 or any(isinstance(v, bool) or int(v) != v or v < 2 for v in size):
                raise LabError(f"{what} size must be (width, height) in whole pixels ≥ 2, got {size!r}")
        cam, proj = tuple(int(v) for v in camera_size), tuple(int(v) for v in projector_size)
        rig = demo_rig(cam, proj)
        if projector_shift is not None:
            rig = Rig(rig.camera, demo_projector(*proj, shift=tuple(float(v) for v in projector_shift)))
    rig = scaled_rig(rig, scale)
    camera_render_intrinsics(effect_set, rig.camera.intrinsics)  # refuses a lens distortion that folds the image
    if isinstance(surface, SurfaceMesh):
        mesh, source = surface, surface_source or f"mesh {surface.name!r}"
    elif isinstance(surface, str) and surface in SHAPES:
        mesh, source = builtin_surface(surface, seed=seed), surface
    else:
        mesh = load_mesh_file(Path(surface))
        source = surface_source or str(Path(surface).resolve())
    rng = np.random.default_rng(seed + 7919)
    nominal_k = None
    if any(nominal_error):
        k, (df, dshift) = rig.projector.intrinsics, (float(v) for v in nominal_error)
        nominal_k = Intrinsics(k.width, k.height, k.fx * (1 + df), k.fy * (1 + df), k.cx, k.cy + dshift * k.height)
    nominal_cam = None
    if camera_fov_error:
        k = rig.camera.intrinsics
        fov = 2 * math.degrees(math.atan(k.width / (2 * k.fx))) + float(camera_fov_error)
        if not 1.0 <= fov <= 170.0:
            raise LabError(f"a camera field of view {camera_fov_error:+g}° off gives {fov:.1f}°; keep it in 1–170°")
        f = k.width / (2 * math.tan(math.radians(fov) / 2))
        nominal_cam = Intrinsics(k.width, k.height, f, f * k.fy / k.fx, k.cx, k.cy)
    return LabTruth(rig, mesh, source, effect_set, seed, samples, rough_pose(rig.projector.camera_from_projector, rng),
                    nominal_k, nominal_cam)


def load_mesh_file(path: Path) -> SurfaceMesh:
    """A user's ``.obj``/``.ply`` surface (rig frame, metres), with its texture if the file names one."""
    if not path.is_file():
        raise LabError(f"unknown surface {str(path)!r}: not one of {', '.join(SHAPES)} and no such mesh file")
    return read_mesh_file(path, error=LabError)


def _stream(seed: int, *keys: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), *map(int, keys)]))


def lab_depth(truth: LabTruth, seed: int | None = None) -> tuple[np.ndarray, DepthInfo]:
    """A phone-LiDAR-like depth image at camera resolution (metres, NaN = none), and how it was taken.

    Needs no Blender scene (a ray cast); the noise comes from ``(seed, "depth")``.
    """

    k = truth.rig.camera.intrinsics
    rng = _stream(truth.seed if seed is None else seed, zlib.crc32(b"depth"))
    d = depth_capture(depth_map(truth.surface, k), k, truth.effects, rng)
    return d, DepthInfo(k, tuple(sensor_resolution(truth.effects, k)))


#: Distance (metres) of the flat wall whose depth image calibrates the sensor's bias (see lab_wall_depth).
WALL_DISTANCE = 1.5


def lab_wall_depth(truth: LabTruth, distance: float = WALL_DISTANCE, seed: int | None = None) -> np.ndarray:
    """The same sensor's depth image of a flat wall square to the camera at a tape-measured ``distance``.

    What a user does once per depth device to learn its constant bias
    (:func:`procam.addon.surface.reconstruct.wall_depth_offset`): the lab
    applies the ``depth_noise`` effect exactly as to the scene (noise, bias,
    sensor resolution, lost returns), with its own noise stream.
    """

    k = truth.rig.camera.intrinsics
    half = 2.0 * distance  # far wider than any camera's field of view
    wall = SurfaceMesh(np.array([[-half, -half, distance], [half, -half, distance], [half, half, distance],
                                 [-half, half, distance]]), np.array([[0, 2, 1], [0, 3, 2]]),
                       np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]]),
                       np.full((2, 2, 3), 0.8, np.float32), name="wall")
    rng = _stream(truth.seed if seed is None else seed, zlib.crc32(b"depth-wall"))
    return depth_capture(depth_map(wall, k), k, truth.effects, rng)


_ID_COLLECTIONS = ("objects", "meshes", "cameras", "lights", "materials", "images", "textures", "node_groups",
                   "worlds", "collections")


def _id_snapshot() -> dict[str, set[int]]:
    import bpy

    return {name: {b.as_pointer() for b in getattr(bpy.data, name)} for name in _ID_COLLECTIONS}


def _new_ids(before: dict[str, set[int]]) -> list[Any]:
    import bpy

    return [b for name in _ID_COLLECTIONS for b in getattr(bpy.data, name) if b.as_pointer() not in before[name]]


class LabDevice(Device):
    """A capture device that renders with Cycles: ``project(frame)`` returns the simulated camera image.

    ``seed`` (default: the truth's) sets the random streams of the shots; a
    re-opened device with the same seed repeats the same captures for the same
    frames. ``samples`` (default: the truth's) is the Cycles samples per pixel
    and may be changed between shots. Close the device (or use it as a context
    manager) to remove its scratch scene.
    """

    def __init__(self, truth: LabTruth, *, samples: int | None = None, seed: int | None = None,
                 supersample: int = 1) -> None:
        import bpy

        from ..blender import rig as blender_rig

        self.truth = truth
        self.projector = truth.rig.projector
        self.camera = truth.rig.camera
        self.effects = truth.effects
        self.samples = _whole(truth.samples if samples is None else samples, "Cycles samples", 1)
        self.seed = _whole(truth.seed if seed is None else seed, "the seed", 0)
        self._settings = render_settings(truth.effects, self.camera.intrinsics)
        self._shots = 0
        # Lens distortion resamples the image, so render a margin around it (same focal length).
        render_k = camera_render_intrinsics(truth.effects, self.camera.intrinsics)
        # Supersampling renders finer pixels for the lens to resample (apply_camera's doc).
        self.supersample = check_supersample(supersample)
        if self.supersample > 1:
            render_k = render_k.scaled(render_k.width * self.supersample, render_k.height * self.supersample)
        before = _id_snapshot()
        self._images_before = before["images"]
        self._scene = bpy.data.scenes.new(LAB_SCENE_NAME)
        self._owned: list[Any] = []
        try:
            objs = blender_rig.create_rig(self._scene, Rig(Camera(render_k), truth.rig.projector), truth.surface)
            if self._settings.get("glossy_weight", 0.0) > 0:
                _add_glossy_lobe(objs.surface, self._settings["glossy_weight"], self._settings["glossy_roughness"])
        except BaseException:
            self._owned = _new_ids(before)
            self.close()
            raise
        self._light = objs.projector
        self._surface = objs.surface
        self._surface_home = objs.surface.matrix_world.copy()
        #: Where the session is: ``calibration`` and ``validation`` while :func:`run_lab` captures (it sets them),
        #: ``show`` for any later use; ``session_shots`` makes a shot's number its time for ``warmup``.
        self.phase = "show"
        self.session_shots: int | None = None
        self._projector_depth: np.ndarray | None = None
        try:
            if self._settings.get("subsurface_weight", 0.0) > 0:
                _add_subsurface(objs.surface, self._settings["subsurface_weight"],
                                self._settings["subsurface_radius"])
            if truth.effects["defocus_depth"].active:
                self._projector_depth = projector_depth(truth.surface, truth.rig.projector)
            if self._settings.get("lamp_power", 0.0) > 0:
                self._add_lamp(*self._settings["lamp_position"], self._settings["lamp_power"])
        except BaseException:
            self._owned = _new_ids(before)
            self.close()
            raise
        self._owned = _new_ids(before)
        # (Cycles' persistent data was measured: no gain here, since a frame's render time is nearly all sampling.)

    @property
    def bounces(self) -> int:
        return int(self._settings.get("diffuse_bounces", 0))

    @property
    def shots(self) -> int:
        """How many captures this device has taken (each one's randomness depends on its number)."""
        return self._shots

    def _check_open(self) -> None:
        if self._scene is None:
            raise LabError("this lab device is closed; open a new LabDevice")

    def _add_lamp(self, side: float, height: float, power: float) -> None:
        """A point lamp beside and above the camera, its energy set so the lit surface peaks at ``power``."""
        import bpy
        from mathutils import Vector

        from .cycles import render_cycles

        cam = self._scene.camera
        data = bpy.data.lights.new("ProCam Lab Lamp", type="POINT")
        data.shadow_soft_size = 0.05
        lamp = bpy.data.objects.new("ProCam Lab Lamp", data)
        self._scene.collection.objects.link(lamp)
        # camera-frame offsets to world: Blender cameras look down their -Z with +Y up and +X right
        rot = cam.matrix_world.to_3x3()
        lamp.location = cam.matrix_world.translation + rot @ Vector((side, height, 0.0))
        data.energy = 100.0
        energy = self._light.data.energy
        self._light.data.energy = 0.0
        try:
            probe = render_cycles(self._scene, samples=4, bounces=0, seed=1)
        finally:
            self._light.data.energy = energy
        top = float(np.percentile(probe.mean(axis=2), 99.5))
        if top <= 0:
            raise LabError("the lab lamp does not light the surface the camera sees; move it (lamp.side/height)")
        data.energy = 100.0 * power / top

    def _place_surface(self) -> None:
        """The surface where this shot's phase has it (``surface_moved`` knocks it after calibration)."""
        shift = self._settings.get("surface_shift")
        if shift is None:
            return
        from mathutils import Matrix, Vector

        moved = self.phase != "calibration"
        home = self._surface_home
        if moved:
            centre = home.translation
            turn = Matrix.Rotation(math.radians(self._settings["surface_turn_deg"]), 4, "Z")
            move = Matrix.Translation(Vector((shift, shift * 0.5, 0.0)))
            self._surface.matrix_world = (move @ Matrix.Translation(centre) @ turn @ Matrix.Translation(-centre)
                                          @ home)
        else:
            self._surface.matrix_world = home

    def _render(self, room_light: float = 0.0) -> np.ndarray:
        from .cycles import render_cycles

        self._check_open()
        self._place_surface()
        k = self._shots
        self._shots += 1
        seed = int(np.random.SeedSequence([self.seed, k]).generate_state(1)[0]) % _SEED_RANGE
        bounces = self.bounces
        img = render_cycles(self._scene, samples=self.samples, bounces=bounces, seed=seed, room_light=room_light)
        gain = float(self._settings.get("indirect_gain", 0.0))
        if bounces > 0 and gain < 1.0:
            # direct + gain·indirect: the direct-only render with the same seed shares its sampling pattern,
            # so the difference (the indirect light) is not much noisier than either render
            direct = render_cycles(self._scene, samples=self.samples, bounces=0, seed=seed, room_light=room_light)
            img = direct + np.float32(gain) * (img - direct)
        return apply_camera(img, self.effects, self.camera.intrinsics, _stream(self.seed, k),
                            supersample=self.supersample)

    def project(self, frame: np.ndarray) -> np.ndarray:
        from ..blender import rig as blender_rig

        self._check_open()
        f = self.check_frame(frame)
        t = 1.0 if (self.session_shots is None or self.phase == "show") else self._shots / self.session_shots
        blender_rig.set_projector_image(self._light, apply_projector(f, self.effects, self.projector,
                                                                     depth=self._projector_depth, t=t))
        return self._render()

    def capture_off(self) -> np.ndarray:
        """Projector switched off, room lights on (:data:`ROOM_LIGHT`): the photo of the surface."""
        self._check_open()
        light = self._light.data
        energy = light.energy
        light.energy = 0.0
        try:
            return self._render(room_light=ROOM_LIGHT)
        finally:
            light.energy = energy

    def depth(self) -> tuple[np.ndarray, DepthInfo]:
        """A phone-LiDAR-like depth image at camera resolution, and how it was taken (see :func:`lab_depth`)."""
        return lab_depth(self.truth, self.seed)

    def close(self) -> None:
        """Remove the scratch scene and every datablock the device created."""
        import bpy

        scene, self._scene = getattr(self, "_scene", None), None
        owned, self._owned = getattr(self, "_owned", []), []
        light = getattr(self, "_light", None)
        try:
            if light is not None and light.data is not None and light.data.node_tree is not None:
                for node in light.data.node_tree.nodes:  # the frame image may have been replaced since
                    if node.type == "TEX_IMAGE" and node.image is not None and node.image not in owned:
                        owned.append(node.image)
            # the first render of a session makes Blender's "Render Result" image: remove it if we made it
            owned += [im for im in bpy.data.images if im.type == "RENDER_RESULT"
                      and im.as_pointer() not in getattr(self, "_images_before", ())]
        except ReferenceError:
            pass
        if scene is not None:
            try:
                bpy.data.scenes.remove(scene)
            except ReferenceError:
                pass
        alive = []
        for block in owned:
            try:
                block.name  # noqa: B018 — raises ReferenceError once removed
                alive.append(block)
            except ReferenceError:
                pass
        if alive:
            bpy.data.batch_remove(alive)

    def __del__(self) -> None:  # a forgotten close() must not leave a scene behind in a user's session
        try:
            if getattr(self, "_scene", None) is not None:
                self.close()
        except Exception:  # noqa: BLE001 — interpreter shutdown: Blender may already be gone
            pass


def projector_depth(surface: SurfaceMesh, projector: Projector) -> np.ndarray:
    """Depth of the surface along the projector's axis at each native frame pixel (metres, NaN off it)."""
    pose = np.asarray(projector.camera_from_projector, float)
    r, t = pose[:3, :3], pose[:3, 3]
    local = replace(surface, vertices=(surface.vertices - t) @ r)  # rig frame → projector frame
    return depth_map(local, projector.intrinsics)


def _mix_into_surface(obj: Any, node: Any, weight: float) -> None:
    """Mix ``node``'s shader with ``weight`` into whatever the surface's material outputs now."""
    tree = obj.active_material.node_tree
    out = next(n for n in tree.nodes if n.type == "OUTPUT_MATERIAL")
    upstream = out.inputs["Surface"].links[0].from_socket
    mix = tree.nodes.new("ShaderNodeMixShader")
    mix.inputs["Fac"].default_value = float(weight)
    tree.links.new(upstream, mix.inputs[1])
    tree.links.new(node.outputs[0], mix.inputs[2])
    tree.links.new(mix.outputs[0], out.inputs["Surface"])


def _add_subsurface(obj: Any, weight: float, radius: float) -> None:
    """Mix random-walk subsurface scattering (same colour as the paint) into the surface's material."""
    tree = obj.active_material.node_tree
    diffuse = next(n for n in tree.nodes if n.type == "BSDF_DIFFUSE")
    sss = tree.nodes.new("ShaderNodeSubsurfaceScattering")
    sss.falloff = "RANDOM_WALK"
    sss.inputs["Scale"].default_value = float(radius)
    sss.inputs["Radius"].default_value = (1.0, 1.0, 1.0)
    colour = diffuse.inputs["Color"]
    if colour.is_linked:
        tree.links.new(colour.links[0].from_socket, sss.inputs["Color"])
    else:
        sss.inputs["Color"].default_value = colour.default_value
    _mix_into_surface(obj, sss, weight)


def _add_glossy_lobe(obj: Any, weight: float, roughness: float) -> None:
    """Mix a GGX glossy lobe into the surface's diffuse material (non-Lambertian reflectance)."""
    glossy = obj.active_material.node_tree.nodes.new("ShaderNodeBsdfGlossy")
    glossy.distribution = "GGX"
    glossy.inputs["Roughness"].default_value = float(roughness)
    _mix_into_surface(obj, glossy, weight)


# --------------------------------------------------------------------------- a whole capture session


def binary_samples(samples: int) -> int:
    """Samples for patterns that calibration only binarises (checker, Gray code): a quarter, at least 4.

    Their camera images are thresholded at half-way levels, where Monte Carlo
    noise of a few percent changes nothing, so they need not pay for the
    samples the photometric captures (white, black, validation) need.
    """
    return min(samples, max(4, samples // 4))


def _nearest_existing(path: Path) -> Path:
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _check_writable_folder(folder: Path, what: str) -> None:
    """``folder`` exists as a writable folder or can be created (nothing is left behind by the check)."""
    base = _nearest_existing(folder)
    if not base.is_dir():
        raise LabError(f"cannot write the {what} at {folder}: {base} is a file, not a folder")
    try:
        probe = tempfile.mkdtemp(prefix=".procam-probe-", dir=base)
        os.rmdir(probe)
    except OSError as exc:
        raise LabError(f"cannot write the {what} at {folder}: {exc.strerror or exc} ({base})") from None


def is_truth_file(path: Path) -> bool:
    """Whether ``path`` is a lab truth file ProCam wrote (its format tag), which ``force`` may replace."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return False
    return isinstance(doc, dict) and doc.get("format") == TRUTH_FORMAT


def is_truth_surface(path: Path) -> bool:
    """Whether ``path`` is the surface :meth:`LabTruth.save` stores beside a truth file: exactly its arrays."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return set(data.files) == {"vertices", "faces", "uvs", "albedo"}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):
        return False


def check_lab_outputs(out_dir: str | Path, truth_path: str | Path, *, force: bool = False,
                      inputs: Iterable[str | Path | None] = ()) -> tuple[Path, Path]:
    """Refuse, before any rendering, outputs that :func:`run_lab` could not write or must not replace.

    The truth file (and the surface stored beside it) must lie outside the
    capture set; an existing capture set or truth file is replaced only with
    ``force`` and only when ProCam wrote it (:func:`..outputs.check_replaceable`);
    nothing is written into ``inputs`` (what the run reads, and the step folders
    the truth must not land in). Returns both paths made absolute.
    """
    inputs = tuple(inputs)
    out_dir, truth_path = Path(out_dir).absolute(), Path(truth_path).absolute()
    out_real = Path(os.path.realpath(out_dir))
    for p in (truth_path, LabTruth.mesh_path(truth_path)):
        real = Path(os.path.realpath(p))
        if real == out_real or out_real in real.parents:
            raise LabError(f"the truth file {p} must lie outside the capture set {out_dir}: the pipeline reads "
                           "everything in the capture set, and the truth is sealed from it")
    if truth_path.suffix.lower() != ".json":
        raise LabError(f"the truth file must be a .json file, got {truth_path.name!r}")
    check_replaceable(out_dir, force=force, what="capture set", replaceable=is_capture_set, inputs=inputs,
                      error=LabError)
    for p, ours in ((truth_path, is_truth_file), (LabTruth.mesh_path(truth_path), is_truth_surface)):
        check_file_replaceable(p, force=force, what="ProCam lab truth file", replaceable=ours, inputs=inputs,
                               error=LabError)
    _check_writable_folder(out_dir.parent, "capture set")
    _check_writable_folder(truth_path.parent, "truth file")
    return out_dir, truth_path


def _check_depth(depth: np.ndarray, truth: LabTruth) -> None:
    try:
        validate_depth(depth, "lab depth")
    except CaptureError:
        seen = float(np.mean(np.isfinite(depth) & (depth > 0)))
        raise LabError(f"the surface {truth.surface_source!r} covers only {seen:.0%} of the camera view (at most "
                       "half may be empty): place it in front of the camera (rig frame: x right, y down, z forward, "
                       "metres; the camera is at the origin)") from None


class _NominalDevice(Device):
    """The lab device as the pipeline sees it: it reports the nominal projector, not the true one."""

    def __init__(self, device: LabDevice, nominal: Any) -> None:
        self.device, self.projector = device, nominal

    def project(self, frame: np.ndarray) -> np.ndarray:
        return self.device.project(frame)

    def capture_off(self) -> np.ndarray:
        return self.device.capture_off()


def run_lab(truth: LabTruth, out_dir: str | Path, *, truth_path: str | Path, force: bool = False,
            inputs: Iterable[str | Path | None] = (),
            graycode: bool = True, validation: bool = True, fast_binary: bool = True, depth_wall: bool = True,
            supersample: int = 1, progress: Progress | None = None, cancel: Cancel | None = None) -> CaptureSet:
    """Render a complete calibration capture set into ``out_dir`` and seal the truth at ``truth_path``.

    Everything that can be checked is checked before rendering (outputs, the
    surface in view); the capture set appears only once complete (an existing
    one is replaced only with ``force``, and only then), and the truth file
    with it. ``fast_binary`` renders checker and Gray-code frames with
    :func:`binary_samples`. ``depth_wall`` adds the depth sensor's image of a
    flat wall at a known distance (:func:`lab_wall_depth`), from which
    calibration reads the sensor's bias. ``progress`` reports each capture;
    ``cancel`` stops between captures and leaves nothing behind.
    """
    inputs = tuple(inputs)
    out_dir, truth_path = check_lab_outputs(out_dir, truth_path, force=force, inputs=inputs)
    nominal = truth.nominal_projector
    seq: list[PatternSpec] = calibration_sequence(truth.rig.projector, graycode=graycode, validation=validation,
                                                  seed=truth.seed)
    total = len(seq) + 2  # + depth + the scene
    say = progress or quiet

    def report(done: int, n: int, message: str) -> None:
        say(f"{done}/{n} {message}", done / n)
    report(0, total, "depth image")
    depth, depth_info = lab_depth(truth)
    _check_depth(depth, truth)
    binary = binary_samples(truth.samples) if fast_binary else truth.samples
    notes = {"device": "virtual lab (Cycles)", "samples": truth.samples,
             "samples_binary": {"kinds": list(BINARY_KINDS), "samples": binary},
             "truth": "sealed, outside this folder"}
    report(1, total, "building the lab scene")
    created_dirs = sorted({p for d in (out_dir.parent, truth_path.parent) for p in (d, *d.parents) if not p.exists()},
                          key=lambda p: len(p.parts), reverse=True)
    if truth.nominal_camera_intrinsics is not None:  # the depth image is unprojected with the camera as given
        depth_info = DepthInfo(truth.nominal_camera_intrinsics.scaled(*depth_info.intrinsics.size),
                               depth_info.native_size)
    writer = CaptureSetWriter(out_dir, truth.nominal_camera, nominal, depth_info=depth_info, notes=notes, force=force,
                              inputs=inputs)
    tmp_truth: Path | None = None
    try:
        with LabDevice(truth, supersample=supersample) as device:
            shown = _NominalDevice(device, nominal)
            device.phase, device.session_shots = "calibration", len(seq)
            for i, spec in enumerate(seq):
                check(cancel, "the lab run was cancelled; nothing was written")
                if spec.kind == "validation":
                    device.phase = "validation"
                report(i + 2, total, spec.name)
                device.samples = binary if spec.kind in BINARY_KINDS else truth.samples
                frame = None if spec.projector_off else spec.image
                shot = shown.capture_off() if frame is None else shown.project(frame)
                writer.add(spec.kind, shot, name=spec.name, frame=frame, **spec.params)
        writer.add_depth(depth)
        if depth_wall:
            writer.add_depth(lab_wall_depth(truth), name="wall", **{WALL_PARAM: WALL_DISTANCE})
        # Seal the truth under a temporary name first: the set and its truth appear together or not at all.
        truth_path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_siblings(truth_path, is_truth_file)
        tmp_truth = hidden_sibling(truth_path, "tmp")
        truth.save(tmp_truth / truth_path.name)
        writer.commit()
    except BaseException:
        writer.abort()
        if tmp_truth is not None:
            _remove_tree(tmp_truth)
        for p in created_dirs:  # folders made on the way to the outputs, deepest first
            try:
                p.rmdir()
            except OSError:
                pass
        raise
    try:
        for src, dst in ((tmp_truth / LabTruth.mesh_path(truth_path).name, LabTruth.mesh_path(truth_path)),
                         (tmp_truth / truth_path.name, truth_path)):
            os.replace(src, dst)
    except OSError as exc:
        raise LabError(f"the capture set is in {out_dir}, but its truth could not be moved to {truth_path}: "
                       f"{exc.strerror or exc}; it is still in {tmp_truth}") from None
    _remove_tree(tmp_truth)
    report(total, total, "done")
    return CaptureSet.load(out_dir, verify_images=False)


def _remove_tree(path: Path) -> None:
    shutil.rmtree(path, ignore_errors=True)


def describe_run(cs: CaptureSet, seconds: float) -> str:
    """One line about a finished lab run (for the CLI and the operator)."""
    n = len([e for e in cs.entries if e.kind != "depth"])
    w, h = cs.camera.intrinsics.size
    wall = " + wall depth" if cs.depth_walls() else ""
    return f"{n} captures + depth{wall} at {w}×{h} in {seconds:.0f} s"


__all__ = ["LAB_SCENE_NAME", "LabDevice", "LabTruth", "binary_samples", "check_lab_outputs", "describe_run",
           "lab_depth", "load_mesh_file", "make_truth", "rough_pose", "run_lab", "scaled_rig"]
