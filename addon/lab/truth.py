"""The virtual lab's truth: the real projector pose, the surface, the injected effects and their parameters.

Pure data and maths, no Blender: :class:`LabTruth` (sealed in a JSON file
beside a lab capture set, read only by evaluation and to re-open the lab),
:func:`make_truth`, and the lab's depth sensor. The Cycles side that renders
from a truth is :mod:`.cycles_device`; a whole capture session is :mod:`.lab`.
"""

from __future__ import annotations

import io
import json
import math
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..capture.format import DepthInfo
from ..errors import MALFORMED, LabError
from ..imageio import DAMAGED_ARRAYS, read_arrays, write_atomic_bytes
from ..outputs import holds_manifest
from ..render.raycast import depth_map
from ..rig.demo import demo_projector, demo_rig
from ..rig.model import Camera, Intrinsics, Projector, Rig
from ..safepaths import inside
from ..surface.mesh import SurfaceMesh, read_mesh_file
from ..surface.shapes import SHAPES, builtin_surface
from .depth import depth_capture, sensor_resolution
from .layouts import LAYOUTS, MAX_PROJECTORS, lay_out
from .effects import EffectSet, camera_render_intrinsics, parse_effects
from .other_forms import check_strength


TRUTH_FORMAT = "procam-lab-truth"
#: Pattern kinds that calibration only binarises: rendered with fewer samples (see :func:`binary_samples`).
BINARY_KINDS = ("checker", "graycode")

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
    #: projectors 2…N as the pipeline is told they are (nominal pose and intrinsics), one per ``rig.others``
    nominal_others: tuple[Projector, ...] = ()
    #: projector index (from 0) → its own projector effects, in place of those of ``effects`` (mixed projectors)
    projector_effects: dict[int, EffectSet] = field(default_factory=dict)
    #: strength of the other-forms rig on top of ``effects`` (:mod:`.other_forms`; 0 off)
    other_forms: float = 0.0
    #: the number (from 0) of this truth's first projector in the rig it was taken from (:meth:`for_projector`)
    first_projector: int = 0

    def __post_init__(self) -> None:
        if len(self.nominal_others) != len(self.rig.others):
            raise LabError(f"the lab truth has {len(self.rig.projectors)} projectors but nominal descriptions of "
                           f"{1 + len(self.nominal_others)}; make the lab captures and their truth again")
        odd = [k + 1 for k in self.projector_effects if not 0 <= k < len(self.rig.projectors)]
        if odd:
            raise LabError(f"the lab truth gives effects of projector(s) {', '.join(map(str, odd))}, but has "
                           f"{len(self.rig.projectors)} projector(s), numbered from 1")

    def effects_of(self, index: int) -> EffectSet:
        """The effects projector ``index`` is rendered with: the shared ones, its projector effects its own if given."""
        own = self.projector_effects.get(index)
        return self.effects if own is None else with_projector_effects(self.effects, own)

    def without(self, *names: str) -> LabTruth:
        """The same truth with the effects ``names`` switched off, shared and every projector's own (what a
        benchmark compares against: the lab without its sensor noise, without a lens's blur)."""
        shared, own = self.effects, dict(self.projector_effects)
        for name in names:
            shared = shared.with_effect(name, 0.0)
            own = {k: e.with_effect(name, 0.0) for k, e in own.items()}
        return replace(self, effects=shared, projector_effects=own)

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

    @property
    def nominal_projectors(self) -> tuple[Projector, ...]:
        """Every projector as the pipeline is told it is, the first first."""
        return (self.nominal_projector, *self.nominal_others)

    def for_projector(self, index: int) -> LabTruth:
        """The one-projector truth of projector ``index`` (0 = the first): what its own :class:`LabDevice` renders
        while the other projectors show black. Its seed is the projector's own (:func:`projector_seed`), so two
        projectors' captures do not share their noise."""
        proj = self.rig.projector_at(index)
        alone = {"rig": Rig(self.rig.camera, proj), "nominal_others": (), "effects": self.effects_of(index),
                 "projector_effects": {}, "first_projector": self.first_projector + index}
        if index == 0:
            return replace(self, **alone)
        nominal = self.nominal_others[index - 1]
        return replace(self, seed=projector_seed(self.seed, index), nominal_pose=nominal.camera_from_projector.copy(),
                       nominal_intrinsics=None if nominal.intrinsics == proj.intrinsics else nominal.intrinsics,
                       **alone)

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
               **({"camera_from_projectors": [p.camera_from_projector.tolist() for p in self.rig.projectors],
                   "nominal_projectors": [p.to_dict() for p in self.nominal_projectors]} if self.rig.others else {}),
               **({"projector_effects": {str(k): e.to_dict() for k, e in sorted(self.projector_effects.items())}}
                  if self.projector_effects else {}),
               "surface": {"source": self.surface_source, "mesh": mesh_path.name, "name": self.surface.name},
               "effects": self.effects.to_dict(), "effects_spec": self.effects.spec,
               **({"other_forms": float(self.other_forms)} if self.other_forms else {}),
               "seed": int(self.seed), "samples": int(self.samples)}
        write_atomic_bytes(path, (json.dumps(doc, indent=1) + "\n").encode())
        return path

    @staticmethod
    def load(path: str | Path) -> LabTruth:
        path = Path(path)
        try:
            doc = json.loads(path.read_text())
            if not isinstance(doc, dict) or doc.get("format") != TRUTH_FORMAT:
                raise LabError(f"{path} is not a ProCam lab truth file")
            data = read_arrays(inside(path.parent, doc["surface"]["mesh"], what="the lab truth's surface mesh",
                                      error=LabError), ("vertices", "faces", "uvs", "albedo"), error=LabError,
                               remedy=f"make the lab captures and their truth again (procam lab … --truth {path} "
                               "--force)")
            surface = SurfaceMesh(data["vertices"], data["faces"], data["uvs"], data["albedo"],
                                  name=doc["surface"].get("name", "surface"))
            return LabTruth(Rig.from_dict(doc["rig"]), surface, doc["surface"]["source"],
                            EffectSet.from_dict(doc["effects"]), int(doc["seed"]), int(doc["samples"]),
                            np.asarray(doc["nominal_camera_from_projector"], dtype=float),
                            Intrinsics.from_dict(doc["nominal_projector_intrinsics"])
                            if "nominal_projector_intrinsics" in doc else None,
                            Intrinsics.from_dict(doc["nominal_camera_intrinsics"])
                            if "nominal_camera_intrinsics" in doc else None,
                            tuple(Projector.from_dict(p) for p in doc.get("nominal_projectors", [])[1:]),
                            {int(k): EffectSet.from_dict(e) for k, e in doc.get("projector_effects", {}).items()},
                            check_strength(doc.get("other_forms", 0.0)))
        except FileNotFoundError as exc:
            raise LabError(f"lab truth not found: {exc.filename}") from None
        except (OSError, *MALFORMED) as exc:
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
               rig.projector.scaled(*size(rig.projector.intrinsics)),
               tuple(p.scaled(*size(p.intrinsics)) for p in rig.others))


def projector_seed(seed: int, index: int) -> int:
    """The seed of projector ``index``'s captures: the session's for the first (as with one projector), one of
    its own drawn from ``(seed, index)`` for each other."""
    if index == 0:
        return int(seed)
    return int(np.random.SeedSequence([int(seed), zlib.crc32(b"projector"), int(index)]).generate_state(1)[0])


def with_projector_effects(shared: EffectSet, own: EffectSet) -> EffectSet:
    """``shared`` with its projector effects (stage ``projector``) replaced by those of ``own``.

    ``black_level`` is half the projector's (its black panel's leak) and half the room's (the ambient light the
    camera sees, the same in every capture): ``own`` sets the leak when it names a black level, and otherwise the
    projector keeps the shared one, so naming a projector's response does not turn its panel's leak off.
    """
    out = EffectSet(tuple(own[e.name] if e.kind.stage == "projector" else e for e in shared.effects))
    room, leak = shared["black_level"], own["black_level"]["projector"]
    return out.with_effect("black_level", room.strength, **{**room.params, "projector": leak}) if leak > 0 else out


def parse_projector_effects(spec: str | Mapping[int, Any] | None, count: int | None = None) -> dict[int, EffectSet]:
    """``"2:response=0.6,vignetting=0.5;3:crosstalk=0.3"`` → projector index (from 0) → its own projector effects.

    The text (and a mapping's keys) number projectors from 1, as every other place a user reads or names a
    projector does (``projector_2/``, ``transport_p2.npz``, "projector 2: …"); the result is keyed by index from 0,
    as :class:`LabTruth` and the rig are. Until 2026-11-29 the option numbered them from 0, so a ``0`` is refused
    with a message that says so rather than read as something else: ``1`` then meant the second projector, and
    reading it silently as the first would give an old command another rig.

    Each projector named gets exactly these projector effects instead of those of the shared effects (a mixed
    rig: another response, colour or lens). Effects that act in the scene, the camera or the depth sensor are
    shared by every projector and refused here, as is a projector the rig does not have (``count``).
    """
    items: list[tuple[Any, Any]]
    if not spec:
        return {}
    if isinstance(spec, Mapping):
        items = list(spec.items())
    elif isinstance(spec, str):
        items = []
        for part in (p.strip() for p in spec.split(";")):
            head, colon, text = part.partition(":")
            if part and (not colon or not head.strip().isdigit()):
                raise LabError(f"projector effects are K:EFFECTS items separated by ';', K a projector numbered "
                               f"from 1 (e.g. 2:response=0.6,vignetting=0.5), got {part!r}")
            if part:
                items.append((int(head), text))
    else:
        raise LabError(f"projector effects must be text like '2:response=0.6', got {type(spec).__name__}")
    out: dict[int, EffectSet] = {}
    for number, text in items:
        if number == 0 and not isinstance(number, bool):
            raise LabError("projector effects name projector 0, but projectors are numbered from 1 (the first is 1, "
                           "as in projector_1/ and every message); before 2026-11-29 this option numbered them from "
                           "0: add 1 to each number")
        k = _whole(number, "a projector's number", 1)
        if count is not None and k > count:
            raise LabError(f"projector effects name projector {k}, but the lab has {count} projector(s), numbered "
                           "from 1")
        if k - 1 in out:
            raise LabError(f"projector effects name projector {k} twice; give all its effects in one item")
        effects = parse_effects(text)
        shared = [n for n in effects.active if effects[n].kind.stage != "projector" and n != "black_level"]
        if shared:
            raise LabError(f"projector {k}'s own effects may only act in the projector; {', '.join(shared)} "
                           "act(s) in the scene, the camera or the depth sensor, shared by every projector: give "
                           "them in the effects")
        room = sorted(set(effects["black_level"].overrides) - {"projector"})
        if room:
            raise LabError(f"projector {k}'s own black level is its panel's leak only (black_level.projector); "
                           f"black_level.{', black_level.'.join(room)} is the room's light, shared by every "
                           "projector: give it in the effects")
        out[k - 1] = effects
    return out


def make_truth(surface: str | Path | SurfaceMesh = "curve", *, effects: str | EffectSet | None = None,
               seed: int = 0, samples: int = 16, camera_size: tuple[int, int] = (640, 480),
               projector_size: tuple[int, int] = (800, 600), rig: Rig | None = None, scale: float = 1.0,
               surface_source: str | None = None, projector_shift: tuple[float, float] | None = None,
               nominal_error: tuple[float, float] = (0.0, 0.0), camera_fov_error: float = 0.0,
               projectors: int = 1, layout: str = "side-by-side", overlap: float = 0.2,
               projector_effects: str | Mapping[int, Any] | None = None, other_forms: float = 0.0) -> LabTruth:
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
    ``projectors`` > 1 lays out that many copies of the demo projector (:func:`.layouts.lay_out`: ``layout``
    ``side-by-side`` with footprints overlapping by ``overlap`` of a width, or ``stacked``); a ``rig`` brings its
    own projectors instead. Each projector gets its own nominal pose and intrinsics, drawn in order, the first
    exactly as with one projector. ``projector_effects`` (:func:`parse_projector_effects`) gives projectors
    effects of their own.
    """
    seed = _whole(seed, "the seed", 0)
    samples = _whole(samples, "Cycles samples", 1)
    effect_set = parse_effects(effects)
    other_forms = check_strength(other_forms)
    count = _whole(projectors, "the number of projectors", 1)
    if count > MAX_PROJECTORS:
        raise LabError(f"the lab lays out 1 to {MAX_PROJECTORS} projectors, got {count}")
    if layout not in LAYOUTS:
        raise LabError(f"the projector layout must be one of {', '.join(LAYOUTS)}, got {layout!r}")
    own_effects = parse_projector_effects(projector_effects, max(count, len(rig.projectors) if rig else 1))
    if rig is not None and count > 1 and count != len(rig.projectors):
        raise LabError(f"the rig has {len(rig.projectors)} projector(s) of its own, and the lab lays out only copies "
                       f"of the demo projector: leave the rig out for {count} demo projectors, or give the rig all "
                       "its projectors")
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
    if len(rig.projectors) < count:
        rig = rig.with_projectors(lay_out(rig.projector, rig.camera, mesh, count, layout, overlap))
    rng = np.random.default_rng(seed + 7919)

    def spec_sheet(k: Intrinsics) -> Intrinsics | None:
        if not any(nominal_error):
            return None
        df, dshift = (float(v) for v in nominal_error)
        return Intrinsics(k.width, k.height, k.fx * (1 + df), k.fy * (1 + df), k.cx, k.cy + dshift * k.height)

    nominal_k = spec_sheet(rig.projector.intrinsics)
    nominal_cam = None
    if camera_fov_error:
        k = rig.camera.intrinsics
        fov = 2 * math.degrees(math.atan(k.width / (2 * k.fx))) + float(camera_fov_error)
        if not 1.0 <= fov <= 170.0:
            raise LabError(f"a camera field of view {camera_fov_error:+g}° off gives {fov:.1f}°; keep it in 1–170°")
        f = k.width / (2 * math.tan(math.radians(fov) / 2))
        nominal_cam = Intrinsics(k.width, k.height, f, f * k.fy / k.fx, k.cx, k.cy)
    first_pose = rough_pose(rig.projector.camera_from_projector, rng)
    others = tuple(replace(p, intrinsics=spec_sheet(p.intrinsics) or p.intrinsics,
                           camera_from_projector=rough_pose(p.camera_from_projector, rng)) for p in rig.others)
    return LabTruth(rig, mesh, source, effect_set, seed, samples, first_pose, nominal_k, nominal_cam, others,
                    own_effects, other_forms)


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


def projector_depth(surface: SurfaceMesh, projector: Projector) -> np.ndarray:
    """Depth of the surface along the projector's axis at each native frame pixel (metres, NaN off it)."""
    pose = np.asarray(projector.camera_from_projector, float)
    r, t = pose[:3, :3], pose[:3, 3]
    local = replace(surface, vertices=(surface.vertices - t) @ r)  # rig frame → projector frame
    return depth_map(local, projector.intrinsics)


# --------------------------------------------------------------------------- a whole capture session


def binary_samples(samples: int) -> int:
    """Samples for patterns that calibration only binarises (checker, Gray code): a quarter, at least 4.

    Their camera images are thresholded at half-way levels, where Monte Carlo
    noise of a few percent changes nothing, so they need not pay for the
    samples the photometric captures (white, black, validation) need.
    """
    return min(samples, max(4, samples // 4))


def is_truth_file(path: Path) -> bool:
    """Whether ``path`` is a lab truth file ProCam wrote (its format tag), which ``force`` may replace."""
    return holds_manifest(Path(path).parent, Path(path).name, TRUTH_FORMAT)


def is_truth_surface(path: Path) -> bool:
    """Whether ``path`` is the surface :meth:`LabTruth.save` stores beside a truth file: exactly its arrays."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return set(data.files) == {"vertices", "faces", "uvs", "albedo"}
    except DAMAGED_ARRAYS:
        return False
