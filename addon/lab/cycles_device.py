"""The virtual lab's camera: :class:`LabDevice` renders a projector frame on the truth's surface with Cycles.

The effects of :mod:`.effects` are applied where they arise in a real rig:
projector effects on the frame before it is emitted, scene effects
(interreflection, glossy surface, subsurface scattering) in the Cycles scene,
camera effects on the rendered image.

Randomness: every shot ``k`` of a device draws its Cycles seed and its sensor
noise from ``(seed, k)`` alone. So two devices opened on the same truth (or on
its saved copy) with the same seed return identical captures for the same
sequence of frames.

The device builds its objects in a scene of its own (``bpy.data.scenes.new``)
and removes that scene and everything it created on :meth:`LabDevice.close`,
so it can run inside a user's Blender session without touching their scene.
This is the lab's Blender side: it imports bpy, so the rest of the engine imports it only where it renders.

Several projectors: a device opened on a truth of N projectors holds N projector lights in one scene and
:meth:`LabDevice.project_all` shows one frame on each in one Cycles render. Each frame goes through its own
projector's effects (:meth:`~.truth.LabTruth.effects_of`), the camera effects act once on the image of all the
light together, as a camera's non-linear response and noise act on what it sees. ``project(frame)`` of such a
device is refused (which projector is meant?): give every projector its frame, black for those that are off.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from ..capture.devices import Device
from ..errors import CaptureError
from ..capture.format import DepthInfo
from ..errors import LabError
from ..rig.model import Camera, Projector, Rig
from .effects import apply_camera, apply_projector, camera_render_intrinsics, render_settings
from .other_forms import OtherForms
import bpy
from mathutils import Matrix, Vector

from ..blender import rig as blender_rig
from .cycles import render_cycles
from .truth import LabTruth, _stream, _whole, check_supersample, lab_depth, projector_depth


#: Name of the scratch scene a :class:`LabDevice` renders in.
LAB_SCENE_NAME = "ProCam Lab"
#: Cycles takes a signed 32-bit seed.
_SEED_RANGE = 2 ** 31
#: Radiance of the even room light for the projector-off photo (white world; a white Lambertian texel facing it
#: reads about this much). The photo of the surface is taken with the room lights on, like the colour image of a
#: depth scan: it shows the surface's own colours, which is how calibration fills the albedo outside the projector's
#: reach and how the diagnosis tells projector vignetting from paint. Every other capture is taken in the dark.
ROOM_LIGHT = 0.25


_ID_COLLECTIONS = ("objects", "meshes", "cameras", "lights", "materials", "images", "textures", "node_groups",
                   "worlds", "collections")


def _id_snapshot() -> dict[str, set[int]]:
    return {name: {b.as_pointer() for b in getattr(bpy.data, name)} for name in _ID_COLLECTIONS}


def _new_ids(before: dict[str, set[int]]) -> list[Any]:
    return [b for name in _ID_COLLECTIONS for b in getattr(bpy.data, name) if b.as_pointer() not in before[name]]


class LabDevice(Device):
    """A capture device that renders with Cycles: ``project(frame)`` returns the simulated camera image.

    ``seed`` (default: the truth's) sets the random streams of the shots; a
    re-opened device with the same seed repeats the same captures for the same
    frames. ``samples`` (default: the truth's) is the Cycles samples per pixel
    and may be changed between shots. Close the device (or use it as a context
    manager) to remove its scratch scene. ``first_shot``: the number of its first shot (a device opened for one
    shot of a longer series draws that shot's randomness). ``repeat_draws``: every shot draws the first shot's
    randomness (Cycles' sampling and the sensor's), so a frame shown twice is captured twice alike and two frames'
    captures differ by what the frames change, not by fresh noise (common random numbers: the flicker of a clip
    without the camera's own, scripts/bench_live_show.py; take ``noise`` out of the effects too, as Poisson draws
    follow the signal).
    """

    def __init__(self, truth: LabTruth, *, samples: int | None = None, seed: int | None = None,
                 supersample: int = 1, first_shot: int = 0, repeat_draws: bool = False) -> None:
        self.truth = truth
        self.projector = truth.rig.projector
        self._projectors = truth.rig.projectors
        self.camera = truth.rig.camera
        self.effects = truth.effects  # the camera's and the scene's effects (and the first projector's)
        self._projector_effects = [truth.effects_of(k) for k in range(len(self._projectors))]
        self._other_forms = [OtherForms(truth.other_forms, truth.first_projector + k)
                             for k in range(len(self._projectors))]
        self.samples = _whole(truth.samples if samples is None else samples, "Cycles samples", 1)
        self.seed = _whole(truth.seed if seed is None else seed, "the seed", 0)
        self._settings = render_settings(truth.effects, self.camera.intrinsics)
        self._shots = _whole(first_shot, "the first shot's number", 0)  # a device per shot (lab/shoot.py) numbers on
        self._first_shot, self.repeat_draws = self._shots, bool(repeat_draws)
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
            objs = blender_rig.create_rig(self._scene, Rig(Camera(render_k), truth.rig.projector, truth.rig.others),
                                          truth.surface)
            if self._settings.get("glossy_weight", 0.0) > 0:
                _add_glossy_lobe(objs.surface, self._settings["glossy_weight"], self._settings["glossy_roughness"])
        except BaseException:
            self._owned = _new_ids(before)
            self.close()
            raise
        self._lights = objs.projectors
        self._light = objs.projectors[0]
        self._surface = objs.surface
        self._surface_home = objs.surface.matrix_world.copy()
        #: Where the session is: ``calibration`` and ``validation`` while :func:`run_lab` captures (it sets them),
        #: ``show`` for any later use; ``session_shots`` makes a shot's number its time for ``warmup``.
        self.phase = "show"
        self.session_shots: int | None = None
        self._projector_depths: list[np.ndarray | None] = [None] * len(self._projectors)
        try:
            if self._settings.get("subsurface_weight", 0.0) > 0:
                _add_subsurface(objs.surface, self._settings["subsurface_weight"],
                                self._settings["subsurface_radius"])
            for k, (proj, effects) in enumerate(zip(self._projectors, self._projector_effects)):
                if effects["defocus_depth"].active:
                    self._projector_depths[k] = projector_depth(truth.surface, proj)
            if self._settings.get("lamp_power", 0.0) > 0:
                side, height = self._settings["lamp_position"]
                self._add_lamp(side, height, self._settings["lamp_power"])
        except BaseException:
            self._owned = _new_ids(before)
            self.close()
            raise
        self._owned = _new_ids(before)
        # (Cycles' persistent data was measured: no gain here, since a frame's render time is nearly all sampling.)

    @property
    def projectors(self) -> tuple[Projector, ...]:
        """The lab's projectors, the first first: :meth:`project_all` shows one frame on each."""
        return self._projectors

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
        cam = self._scene.camera
        data = bpy.data.lights.new("ProCam Lab Lamp", type="POINT")
        data.shadow_soft_size = 0.05
        lamp = bpy.data.objects.new("ProCam Lab Lamp", data)
        self._scene.collection.objects.link(lamp)
        # camera-frame offsets to world: Blender cameras look down their -Z with +Y up and +X right
        rot = cam.matrix_world.to_3x3()
        lamp.location = cam.matrix_world.translation + rot @ Vector((side, height, 0.0))
        data.energy = 100.0
        with self._lights_off():
            probe = render_cycles(self._scene, samples=4, bounces=0, seed=1)
        top = float(np.percentile(probe.mean(axis=2), 99.5))
        if top <= 0:
            raise LabError("the lab lamp does not light the surface the camera sees; move it (lamp.side/height)")
        data.energy = 100.0 * power / top

    def _place_surface(self) -> None:
        """The surface where this shot's phase has it (``surface_moved`` knocks it after calibration)."""
        shift = self._settings.get("surface_shift")
        if shift is None:
            return
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
        self._check_open()
        self._place_surface()
        k = self._first_shot if self.repeat_draws else self._shots
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
        recorded = apply_camera(img, self.effects, self.camera.intrinsics, _stream(self.seed, k),
                                supersample=self.supersample)
        return self._other_forms[0].camera_record(recorded)

    def project(self, frame: np.ndarray) -> np.ndarray:
        self._check_open()
        if len(self._projectors) > 1:
            raise CaptureError(f"this lab device shows {len(self._projectors)} projectors: give each its frame with "
                               "project_all (black for those that are off), or open a device on one projector's "
                               "truth (LabTruth.for_projector)")
        return self._show([self.check_frame(frame)])

    def project_all(self, frames: Sequence[np.ndarray]) -> np.ndarray:
        """Every projector's frame at once, in one render: the light of all of them, seen by the camera once."""
        self._check_open()
        return self._show(self.check_frames(frames))

    def _show(self, frames: list[np.ndarray]) -> np.ndarray:
        t = 1.0 if (self.session_shots is None or self.phase == "show") else self._shots / self.session_shots
        for light, f, proj, effects, depth, other in zip(self._lights, frames, self._projectors,
                                                         self._projector_effects, self._projector_depths,
                                                         self._other_forms):
            emitted = apply_projector(f, effects, proj, depth=depth, t=t)
            blender_rig.set_projector_image(light, other.projector_light(emitted, proj.intrinsics.width))
        return self._render()

    @contextlib.contextmanager
    def _lights_off(self) -> Iterator[None]:
        energies = [light.data.energy for light in self._lights]
        for light in self._lights:
            light.data.energy = 0.0
        try:
            yield
        finally:
            for light, energy in zip(self._lights, energies):
                light.data.energy = energy

    def capture_off(self) -> np.ndarray:
        """Projectors switched off, room lights on (:data:`ROOM_LIGHT`): the photo of the surface."""
        self._check_open()
        with self._lights_off():
            return self._render(room_light=ROOM_LIGHT)

    def depth(self) -> tuple[np.ndarray, DepthInfo]:
        """A phone-LiDAR-like depth image at camera resolution, and how it was taken (see :func:`lab_depth`)."""
        return lab_depth(self.truth, self.seed)

    def close(self) -> None:
        """Remove the scratch scene and every datablock the device created."""
        scene, self._scene = getattr(self, "_scene", None), None
        owned, self._owned = getattr(self, "_owned", []), []
        try:
            for light in getattr(self, "_lights", ()):
                if light.data is not None and light.data.node_tree is not None:
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
