"""Stage C as the compensate and show steps run it: options, the capture device, and one session for many targets.

Both steps loop over targets with the same per-target work: fit the target to
its display area, run stage C (closed loop through a device, or open loop
with θ from the validation captures), and turn the answer into the input and
the native frame to send. :class:`StageC` holds what the targets share (the
loaded scene, the device, θ of the open loop, the display area per aspect
ratio, the diagnosed effect models around stage C) so that each step only
decides how its folder grows.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..capture.devices import Device, FolderDevice, LensRemovedDevice
from ..capture.format import CaptureSet
from ..rig.lens import RigLens
from ..capture.photos import removed_lens
from ..errors import CalibrationError, CaptureError, ProCamError
from ..imageio import write_image
from ..gap.compensation import (RADIOMETRIC, AdaptedCaptures, AdaptedDevice, EffectAdapter, adapter_from_options,
                                effects_wanted)
from ..lab.truth import LabTruth
from ..live.shoot import open_camera_device, parse_camera_device
from ..options import Choice, option, validate
from ..progress import Cancel, Progress, part, quiet
from ..rig.model import Projector
from ..stages.calibrate import Calibration
from ..stages.compensate import (DEFAULT_SCHEDULE, ITERATIONS_JOINT, ITERATIONS_Z, SCHEDULES, BiasModel,
                                 CompensationResult, Compensator, Schedule, get_schedule, split_iterations)
from ..stages.display_area import (TARGET_ENCODINGS, DisplayArea, TargetAspectWarning, choose_area, fit_target,
                                   load_target, parse_area, parse_surround)
from ..stages.radiometry import PixelRadiometry, choose_radiometry
from ..stages.range import RangeError, RangeMap, fit_rule, parse_range
from ..stages.transport import TransportMemoryError, check_memory
from . import calibrate as calibrate_step
from . import diagnose as diagnose_step
from . import layout
from . import transport as transport_step

DEVICE_KINDS = ("lab", "folder", "live", "command")


def _schedule_counts(name: str) -> str:
    s = SCHEDULES[name]
    start = f"{s.fixed_point} fixed-point steps + " if s.fixed_point else ""
    return f"{name}: {start}{s.iterations_z}+{s.iterations_joint} iterations, lr {s.lr}, a capture every " \
           f"{s.capture_interval}"


SCHEDULE_CHOICES = (
    Choice("transport", "Transport", "Solve on the calibration's precomputed light-transport operator: no renders, "
                                     "under a second a target, 3 captures in closed loop"),
    Choice("fast", "Fast", "Fixed-point start, 150 joint iterations, 15 captures: renders every step; no operator "
                           "needed"),
    Choice("paper", "Paper", "The paper's 200 iterations on z, then 300 on z and θ"))

RADIOMETRY_CHOICES = (
    Choice("auto", "Auto", "Each camera pixel's own response and colour mixing where it predicts held-out captures "
                           "better than the global models"),
    Choice("pixel", "Per Pixel", "Each camera pixel's own response and colour mixing, measured from the calibration's "
                                 "flat and ramp captures"),
    Choice("global", "Global", "The global effect models and θ only"))

LOOP_CHOICES = (
    Choice("measured", "Measured", "Learn each pixel's slope from the captures, average against the camera's noise, "
                                   "stop at its noise floor"),
    Choice("damped", "Damped", "The paper's θ: a third of the way towards each capture's residual"))


@dataclass(frozen=True)
class StageCOptions:
    """How stage C runs for every target: the schedule (by name, with the values given over it) and choices.

    A schedule value left None is the named schedule's (``stages.compensate.SCHEDULES``); ``iterations`` is the
    total, split in the schedule's own ratio. Each field is the one declaration of its option (addon/options.py):
    ``procam compensate`` and ``procam show`` take it from the command line, the Compensate panel from the scene.
    """

    schedule: str = option(
        DEFAULT_SCHEDULE, label="Schedule", choices=SCHEDULE_CHOICES,
        help=f"stage-C schedule (default {DEFAULT_SCHEDULE}; 'paper' = the paper's 200+300 iterations); the "
             "iterations, learning rate and capture interval given override its values: "
             + "; ".join(_schedule_counts(n) for n in SCHEDULES))
    iterations: int | None = option(
        None, label="Iterations", min=0, soft_max=1000, blank=0,
        help="total iterations, split between z alone and z + θ in the schedule's own ratio "
             f"(paper: {ITERATIONS_Z}:{ITERATIONS_JOINT} Adam steps; fast: all joint Adam steps, after its fixed-point "
             "steps; transport: solver steps, half of them before the first capture; default: the schedule's counts; "
             "0 in the sidebar)")
    lr: float | None = option(None, min=1e-9, help="Adam learning rate on z (default: the schedule's)")
    alpha: float | None = option(None, flag="", min=0.0, max=0.5,
                                 help="θ's rate in Eq. 10 (default: the schedule's, matched to its captures)")
    capture_every: int | None = option(
        None, min=1, help="closed loop: capture W(z) every K joint iterations (default: the schedule's; 1 = the "
                          "paper, for fast real hardware)")
    loop: str = option(
        "measured", label="Loop Rule", choices=LOOP_CHOICES,
        help="closed loop on the transport schedule: 'measured' learns each pixel's slope from the captures, "
             "averages them against the camera's noise and stops at its noise floor (default); 'damped' is the "
             "paper's θ, a third of the way towards each capture's residual")
    spp: int = option(4, min=1, help="samples per pixel inside the loop")
    bounces: int = option(1, min=0, help="indirect bounces simulated")
    seed: int = option(0, min=0, label="Seed", help="seed of every random stream; the same seed repeats the result")
    area: tuple[int, int, int, int] | None = option(
        None, label="Display Area", parse=parse_area, blank="",
        help="display area x,y,width,height in camera pixels (default: the capture set's, else the largest "
             "rectangle of the target's aspect ratio that the projector covers; with several projectors, that they "
             "light together)")
    surround: tuple[float, float, float] | None = option(
        None, label="Surround", parse=parse_surround, blank="", metavar="R,G,B",
        help="the light outside the display area, as a share of the projector's white per channel, 0–1 (default "
             "black): the input there is held at it, not solved for, whatever effect models are inverted")
    target_encoding: str = option("auto", choices=TARGET_ENCODINGS,
                                  help="auto: 8-bit files are sRGB and are linearised, 16-bit/float are linear")
    use_bias: bool = option(True, negate="--no-bias", label="Bias θ",
                            help="estimate the per-pixel bias θ; off: no θ at all (the ablation), neither captures "
                                 "nor validation")
    device: str | None = option(
        None, check=lambda spec: device_kind(spec), label="Device", blank="",
        help="closed loop through lab:TRUTH_FILE (virtual lab), folder:CAPTURE_DIR, "
             "live:camera=SOURCE,display=N (a streaming camera), live:display=N,shoot='COMMAND … {out}' (the "
             "window shown, a command takes the photograph) or command:run='COMMAND … {frame} … {out}' (a command "
             "shows and photographs each frame); without a device θ is estimated from the validation captures (open "
             "loop)")
    effects: str = option(
        "none", label="Effect Models", blank="",
        help="effect models around stage C, fitted by procam diagnose: 'auto' (the ones it selected), NAME,... or "
             "'none' (default); needs --diagnosis")
    diagnosis: Path | None = option(None, subtype="DIR_PATH", help="the procam diagnose folder for --effects")
    radiometry: str = option(
        "auto", label="Radiometry", choices=RADIOMETRY_CHOICES,
        help="how a camera pixel's colour follows the simulated light: 'pixel' measures each camera pixel's own "
             "response and colour mixing from the calibration's black, white, grey and ramp captures and stage C "
             "works through it (the global response, colour mixing, vignetting, black level and camera curve of "
             "--effects are then left out; a closed loop starts from its answer and corrects it in the camera's "
             "units); 'global' keeps the global models and θ; 'auto' (default) uses the per-pixel model in the open "
             "loop where it predicts the held-out random-texture captures better, and says which it used (a "
             "closed loop learns each pixel's response itself and keeps the global models); with several "
             "projectors each projector's own model, in the open loop without --effects")
    range: str = option(
        "none", label="Range", check=parse_range, blank="",
        help="what the targets become before compensation: 'auto' fits one gain and offset to all the targets so "
             "that at most 1 % of their values lie outside what the projector shows on this surface (its white and "
             "black captures), never dimming targets that fit; 'bright' fits one offset and a gain that varies "
             "over the surface, dimmer only where the paint or the distance demands it and changing by at most 5 % "
             "per degree of the camera's view ('bright:PCT' sets that limit), and prints the brightness it keeps; "
             "'GAIN,OFFSET' gives them; 'none' (default) keeps the targets as they are")

    def run_arguments(self) -> dict[str, Any]:
        """The schedule keywords of :meth:`Compensator.run`: the schedule's name and only the values given."""
        iterations_z, iterations_joint = split_iterations(self.iterations, self.schedule)
        given = {"iterations_z": iterations_z, "iterations_joint": iterations_joint, "lr": self.lr,
                 "alpha": self.alpha, "capture_every": self.capture_every, "loop": self.loop}
        return {"schedule": self.schedule, **{k: v for k, v in given.items() if v is not None}}

    def resolved(self) -> Schedule:
        """The schedule every target runs (a bad value fails here, before any work)."""
        args = self.run_arguments()
        return replace(get_schedule(args.pop("schedule")), **args).check()

    def check(self) -> Schedule:
        """Refuse values stage C cannot use, before anything is loaded; returns the resolved schedule."""
        validate(self)
        return self.resolved()

    @property
    def mode(self) -> str:
        """closed-loop (a device and θ), open-loop (θ from the validation captures) or none (no θ)."""
        return "closed-loop" if self.device and self.use_bias else "open-loop" if self.use_bias else "none"

    @property
    def device_spec(self) -> str | None:
        """The device as the manifest names it: its kind and absolute path (None in the open loop)."""
        if not self.device or not self.use_bias:
            return None
        kind, _, where = self.device.partition(":")
        return self.device if kind in ("live", "command") else f"{kind}:{Path(where).absolute()}"


def effect_adapter(options: StageCOptions, calibration: Calibration) -> EffectAdapter | None:
    """The diagnosed effect models ``options.effects`` names, with the parameters its diagnosis folder fitted."""
    wanted = effects_wanted(options.effects) and options.diagnosis is not None
    view = diagnose_step.read(options.diagnosis) if wanted else None
    return adapter_from_options(options.effects, None if view is None else view.doc, calibration.rig.projector,
                                where=f"the diagnosis in {options.diagnosis}")


def device_kind(spec: str) -> str:
    kind, _, where = spec.partition(":")
    if not where or kind not in DEVICE_KINDS:
        raise CaptureError(f"the device must be lab:TRUTH_FILE (virtual lab), folder:CAPTURE_DIR (replayed "
                           f"captures), live:camera=SOURCE,display=N (a real projector and camera), "
                           f"live:display=N,shoot='COMMAND … {{out}}' (a command takes each photograph) or "
                           f"command:run='COMMAND … {{frame}} … {{out}}' (a command shows and photographs), got "
                           f"{spec!r}")
    if kind in ("live", "command"):
        parse_camera_device(spec)
    return kind


def device_inputs(spec: str | None) -> tuple[Path, ...]:
    """The files and folders the device ``spec`` reads (a lab truth and its surface, a replayed capture set):
    inputs of the run, which no output may replace."""
    kind, _, where = (spec or "").partition(":")
    if kind == "lab" and where:
        return Path(where), LabTruth.mesh_path(where)
    if kind == "folder" and where:
        return (Path(where),)
    return ()


def stage_c_inputs(options: StageCOptions) -> tuple[Path, ...]:
    """What stage C reads besides the calibration and the targets: its device's files and the diagnosis."""
    return (*device_inputs(options.device), *((options.diagnosis,) if options.diagnosis else ()))


def _projector_count(spec: str) -> int | None:
    """How many projectors the device ``spec`` shows, told from its files without opening it (a lab truth, a
    replayed capture set); None where only opening it tells (a live camera's windows follow the calibration) or
    its files cannot be read (opening it then says what is wrong)."""
    kind, where = device_kind(spec), spec.partition(":")[2]
    try:
        if kind == "lab" and where:
            return len(LabTruth.load(Path(where)).rig.projectors)
        if kind == "folder" and where:
            return len(CaptureSet.load(Path(where), verify_images=False).projectors)
    except ProCamError:
        return None
    return None


def check_device_fits(spec: str | None, calibration: Calibration, *, device: Device | None = None) -> None:
    """Refuse, before any work, a device (``spec``, or ``device`` already open) that shows another number of
    projectors than ``calibration`` holds: the device of another rig, whose first capture would fail after every
    target was computed."""
    if not spec:
        return
    shown = getattr(device, "projectors", None)  # a device relayed from Blender's main thread may not say
    count = len(shown) if shown is not None else _projector_count(spec)
    if count is None:
        return
    want = 1 + len(calibration.rig.others)  # the calibration's projector_count, from its rig
    if count == want:
        return
    where = f" {calibration.folder}" if calibration.folder else ""
    raise CaptureError(f"the device {spec} shows {count} projector{'s' if count > 1 else ''}, but the calibration"
                       f"{where} is of {want}: give the device of the rig that was calibrated (a lab truth or "
                       f"capture set of {want} projector{'s' if want > 1 else ''}), or calibrate this device's rig "
                       "first")


def camera_lens_of(calibration: Calibration) -> RigLens | None:
    """The camera lens import took out of the photographs ``calibration`` was made from (None: none was): as the
    calibration records it, else as its capture set does (calibrations made before they recorded it)."""
    doc = calibration.report.get("camera_lens_removed")
    if doc is not None:
        return RigLens.from_dict(doc)
    captures = calibrate_step.captures_of(calibration, required=False)
    return None if captures is None else removed_lens(captures)


def open_device(spec: str | None, projector: Projector | None = None,
                progress: Progress | None = None, *, others: Sequence[Projector] = (),
                camera_size: tuple[int, int] | None = None) -> Device | None:
    """A capture device as it is, from ``lab:TRUTH_FILE`` (the virtual lab), ``folder:CAPTURE_DIR`` (replayed
    captures), ``live:…`` (the projector window and a camera or a shooting command; ``projector`` gives the window its
    size, ``others`` the windows of projectors 2…N of a rig of several, one display each; ``camera_size`` the
    calibration's camera, which a live camera is checked against as soon as it connects) or ``command:…`` (a
    command shows and photographs). Stage C and
    evaluation project through :func:`device_pipeline`, which opens it and puts the calibration's lens after it."""
    if not spec:
        return None
    kind, where = device_kind(spec), spec.partition(":")[2]
    if kind in ("live", "command"):
        if projector is None:
            raise CaptureError(f"a {kind} device needs the calibrated projector to size its frames")
        return open_camera_device(spec, projector, others=others, progress=progress, camera_size=camera_size)
    if kind == "folder":
        return FolderDevice(Path(where))
    from ..lab.cycles_device import LabDevice  # bpy: the lab renders with Cycles

    return LabDevice(LabTruth.load(Path(where)))


def device_pipeline(spec: str | None, calibration: Calibration, *, device: Device | None = None,
                    adapter: EffectAdapter | None = None, progress: Progress | None = None
                    ) -> Device | AdaptedDevice | None:
    """The device stage C and evaluation project through, from the command line and from Blender alike: ``device``
    (one opened elsewhere: Blender opens the lab on its main thread and relays to it) or the one ``spec`` names,
    opened here; then the lens that was taken out of ``calibration``'s photographs, if one was (a camera's frames,
    live or the lab's; a replayed capture set's are as it stored them); then ``adapter``'s effect models (send g⁻¹(x),
    see h⁻¹(capture)). None without ``spec``. Closing the answer closes the device (a relayed one's owner closes
    the real one)."""
    if not spec:
        if device is not None:
            raise ValueError("a device given without the spec that names it: which lens it needs is unknown")
        return None
    check_device_fits(spec, calibration, device=device)
    # Read before a window opens, so that a capture set that cannot say which lens it lost is refused first.
    lens = None if device_kind(spec) == "folder" else camera_lens_of(calibration)
    if device is None:
        # a live camera is checked against the calibration's as it connects, before seconds of measuring it
        size = tuple(calibration.rig.camera.intrinsics.size) if device_kind(spec) == "live" else None
        device = open_device(spec, calibration.rig.projector, progress, others=calibration.rig.others,
                             camera_size=size)
    if lens is not None:
        (progress or quiet)(f"the camera's frames go through the lens taken out of the calibration's photographs "
                            f"({lens.source})", 0.0)
        device = LensRemovedDevice(device, lens)
    return device if adapter is None else AdaptedDevice(device, adapter)


@dataclass
class TargetResult:
    """Stage C's answer for one target, as a step writes it."""

    result: CompensationResult
    fitted: np.ndarray  # the target fitted to the display area (area size)
    area: DisplayArea
    input: np.ndarray  # the projector input to send (input size)
    frame: np.ndarray  # that input in the native projector frame
    warnings: list[str]


def measure_radiometry(stage: Any, say: Progress, fraction: float = 0.0) -> dict[str, Any] | None:
    """A stage's (:class:`StageC` or ``projectors.JointStage``) choice of radiometry, said while it measures each
    camera pixel's own model: once, before the targets (``compensate``) or before a show's settings are made;
    None with ``--radiometry global``, which measures nothing."""
    if stage.options.radiometry == "global":
        return None
    say("measuring each camera pixel's response and colour mixing, judged on held-out captures", fraction)
    record: dict[str, Any] = stage.choose_radiometry()
    return record


def loop_record(tmp: Path, name: str, result: Any) -> dict[str, Any] | None:
    """The measured closed loop's record of target ``name`` from its stage-C ``result`` (None for other loops), with
    where it corrected the model written into ``tmp``: |θ| per camera pixel, linear (``layout.correction_file``)."""
    loop = result.report.get("loop")
    if not loop:
        return None
    loop = {**loop, "correction": layout.correction_file(name)}
    write_image(tmp / loop["correction"], np.abs(np.asarray(result.theta, np.float32)))
    return loop


class StageC:
    """One calibration's stage C for a run of targets (module doc). Use as a context manager: closes the device.

    ``device``: an open device to use instead of opening ``options.device``
    (Blender opens the lab on its main thread and relays to it).
    ``compensator``: a loaded :class:`Compensator` to reuse (same spp,
    bounces and seed; not with effect models, whose scene moves with them).
    """

    def __init__(self, calibration: Calibration, options: StageCOptions, *, device: Device | None = None,
                 compensator: Compensator | None = None, progress: Progress | None = None) -> None:
        say = progress or quiet
        self.calibration, self.options = calibration, options
        self.schedule = options.check()
        self.adapter: EffectAdapter | None = effect_adapter(options, calibration)
        self.captures = calibrate_step.captures_of(calibration, required=False)
        self.user_area = choose_area(calibration, aspect=1.0, user=options.area) if options.area else None
        self.areas: dict[str, DisplayArea] = {}
        given = parse_range(options.range)
        #: the show's map t → gain·t + offset (None: targets as they are); ``auto`` is fitted by :meth:`fix_range`
        self.range_map: RangeMap | None = given if isinstance(given, RangeMap) else None
        if compensator is not None and self.adapter is not None:
            raise ProCamError("a run with effect models builds its own compensator (its scene moves with them)")
        if compensator is not None and (compensator.bounces, compensator.spp, compensator.seed) != \
                (options.bounces, options.spp, options.seed):
            raise ProCamError("the compensator given was made with other bounces/spp/seed than the options'")
        self._owned = device is None
        #: the per-pixel radiometric model when :meth:`choose_radiometry` chose it, and the record of that choice
        self.pixel: PixelRadiometry | None = None
        self.radiometry: dict[str, Any] | None = None
        #: the device as it is, with the calibration's lens (:func:`device_pipeline`); None: open loop
        self._lensed = device_pipeline(options.device, calibration, device=device,
                                       progress=part(say, 0.0, 0.0, "device: ")) \
            if options.mode == "closed-loop" else None
        #: the device stage C projects through: that, then the effect models
        self.device: Device | AdaptedDevice | None = \
            self._lensed if self._lensed is None or self.adapter is None else AdaptedDevice(self._lensed, self.adapter)
        #: what the run says of the calibration's stored operator (one rendered in memory, and why), for its record
        self.transport_notes: list[str] = []
        try:
            say("loading the calibrated scene", 0.0)
            if compensator is not None:
                self.compensator = compensator
            elif self.adapter is None:
                self.compensator = Compensator(calibration, bounces=options.bounces, spp=options.spp,
                                               seed=options.seed)
            else:
                self.compensator = self.adapter.compensator(calibration, bounces=options.bounces, spp=options.spp,
                                                            seed=options.seed)
            # outside the display area the input holds the surround (black unless asked): it is not solved for
            self.compensator.surround = options.surround or (0.0, 0.0, 0.0)
            if self.schedule.transport:
                # With effect models the operator is the moved scene's, rendered here; else the stored one.
                found = None if self.adapter is not None else \
                    transport_step.find(calibration, bounces=options.bounces, seed=options.seed)
                if found is not None and found.operator is not None:
                    self.compensator.transport = found.operator
                else:
                    try:
                        check_memory(calibration.rig.camera.intrinsics.size, bounces=options.bounces)
                        if found is not None:  # said unthrottled and recorded: every run pays for it until stored
                            note = transport_step.rebuild_note(calibration, found, bounces=options.bounces,
                                                               seed=options.seed)
                            self.transport_notes.append(note)
                            say(f"note: {note}", 0.0)
                    except TransportMemoryError as exc:
                        say(f"warning: {exc}; this run renders every step instead (schedule fast)", 0.0)
                        self.options = replace(options, schedule="fast")
                        self.schedule = self.options.check()
            if self.schedule.transport and self.adapter is not None:
                self.adapter.blur_in_solve(self.compensator)
            self.bias: BiasModel | None = None
        except BaseException:
            self.close()
            raise

    @property
    def bounces(self) -> int:
        return self.compensator.bounces

    def choose_radiometry(self) -> dict[str, Any]:
        """Whether stage C works through each camera pixel's own radiometric model (``--radiometry``,
        stages/radiometry.py), decided once for the run by held-out captures; returns the record of the choice.
        Chosen, it replaces the effect models' radiometric part (their lens's blur and scene stay) and the
        open-loop θ (zero: the model predicts the patterns it was measured from)."""
        if self.radiometry is not None:
            return self.radiometry
        rule = self.options.radiometry
        if rule == "global":
            self.radiometry = {"used": "global", "rule": rule}
            return self.radiometry
        if rule == "auto" and self.options.mode == "closed-loop":
            # The measured loop learns each pixel's slope from its own captures: started from the per-pixel model's
            # answer it gained 0.10 dB on the lab of other forms and lost 0.06 on the lab's own forms (one target
            # 0.13; docs/results.md), so a closed loop starts from it only when asked.
            self.radiometry = {"used": "global", "rule": rule, "reason": "a closed loop learns each pixel's response "
                               "from its own captures (--radiometry pixel starts it from the per-pixel model)"}
            return self.radiometry
        if self.captures is None:
            if rule == "pixel":
                raise CalibrationError(f"--radiometry pixel needs the calibration's capture set, which cannot be "
                                       f"read at {self.calibration.capture_dir!r}: put it back, or use --radiometry "
                                       "global")
            self.radiometry = {"used": "global", "rule": rule, "reason": "the calibration's capture set cannot be read"}
            return self.radiometry
        adapter = self.adapter
        view = None if adapter is None else AdaptedCaptures(self.captures, adapter)
        space = None if adapter is None or not adapter.camera_side else adapter.camera_to_light
        pixel, record = choose_radiometry(self.compensator, self.captures, rule, global_view=view, to_space=space)
        self.radiometry = record
        if pixel is None:
            return record
        self.pixel = pixel
        if adapter is not None:
            kept = {n: p for n, p in adapter.params.items() if n not in RADIOMETRIC}
            record["replaces_effects"] = [n for n in adapter.used if n in RADIOMETRIC]
            self.adapter = replace(adapter, params=kept) if kept else None
        if self._lensed is not None:
            # the closed loop measures each pixel's slope in the camera's own units (stages/closed_loop.py): it
            # starts from the per-pixel model's answer and corrects it there (:meth:`compensate`)
            self.device = self._lensed if self.adapter is None else AdaptedDevice(self._lensed, self.adapter)
            record["closed_loop"] = "starts from the per-pixel model's answer, corrects in the camera's units"
        cw, ch = self.compensator.camera_size
        self.bias = BiasModel(np.zeros((ch, cw, 3), np.float32), None, "pixel",
                              {"radiometry": "each camera pixel's own model; θ = 0"})
        return record

    def keep_global_radiometry(self, why: str) -> None:
        """Use the global models whatever ``--radiometry`` says (a path that cannot take the per-pixel model)."""
        if self.radiometry is None:
            self.radiometry = {"used": "global", "rule": self.options.radiometry, "reason": why}

    def model_target(self, fitted: np.ndarray, area: DisplayArea) -> np.ndarray:
        """A target fitted to the display area, in the units stage C compares with f̂ (through the per-pixel model
        or the effect models' camera side)."""
        if self.pixel is not None:
            return self.pixel.crop(area).to_light(fitted)
        return fitted if self.adapter is None else self.adapter.model_target(fitted, area)

    def estimate_bias(self) -> BiasModel:
        """θ of the open loop, from the calibration's validation captures (seen through the effect models)."""
        if self.pixel is not None:  # θ = 0 (choose_radiometry)
            assert self.bias is not None
            return self.bias
        captures = self.captures
        if captures is not None and self.adapter is not None:
            captures = AdaptedCaptures(captures, self.adapter)
        self.bias = self.compensator.estimate_bias(captures)
        return self.bias

    def area_for(self, image: np.ndarray) -> DisplayArea:
        """The display area of a target: the user's, else the largest the projector covers at its aspect ratio
        (one render per distinct aspect ratio, kept in :attr:`areas` by the ratio to 4 decimals)."""
        if self.user_area is not None:
            return self.user_area
        aspect = image.shape[1] / image.shape[0]
        key = f"{aspect:.4f}"
        if key not in self.areas:
            self.areas[key] = choose_area(self.calibration, aspect=aspect, captures=self.captures)
        return self.areas[key]

    def fix_range(self, images: list[np.ndarray]) -> RangeMap | None:
        """With ``--range auto`` or ``bright``, fit the show's map to ``images`` (all its targets, or an even
        sample of a long show's frames) against the calibration's white and black captures; else the given map."""
        rule = parse_range(self.options.range)
        if not isinstance(rule, str) or rule == "none":
            return self.range_map
        if self.captures is None:
            raise RangeError(f"--range {rule} needs the white and black captures of the calibration's capture set, "
                             f"which cannot be read at {self.calibration.capture_dir!r}: put it back, or give "
                             "--range GAIN,OFFSET")
        white, black = self.captures.image("white"), self.captures.image("black")
        fitted, blacks, whites, areas = [], [], [], []
        for image in images:
            area = self.area_for(image)
            areas.append(area)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", TargetAspectWarning)  # said again when the target is compensated
                fitted.append(fit_target(image, area))
            blacks.append(area.crop(black))
            whites.append(area.crop(white))
        self.range_map = fit_rule(rule, fitted, blacks, whites, areas, self.calibration.rig.camera.intrinsics)
        return self.range_map

    def load(self, path: str | Path) -> tuple[np.ndarray, str]:
        """A target image as stage C reads it (linear light; the note says how it was decoded)."""
        return load_target(path, encoding=self.options.target_encoding)

    def compensate(self, image: np.ndarray, *, name: str, what: str, progress: Progress | None = None,
                   cancel: Cancel | None = None, start: np.ndarray | None = None,
                   verify: bool | None = None) -> TargetResult:
        """Stage C for one target image; :class:`ProCamError` when this target cannot be compensated.
        ``start``: the virtual input z to start from (a warm start, :meth:`start_from_frame`). ``verify``: render
        the answer with Mitsuba after a solve on the transport operator (None: the schedule's choice)."""
        self.choose_radiometry()
        if self.options.mode == "open-loop" and self.bias is None:
            self.estimate_bias()
        area = self.area_for(image)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", TargetAspectWarning)
            fitted = fit_target(image, area, what=what)
            if self.range_map is not None:
                fitted = self.range_map.apply(fitted, area)
            model_target = self.model_target(fitted, area)
            arguments = self.options.run_arguments()
            if self.pixel is not None and self.device is not None:
                # the closed loop starts from the per-pixel model's open-loop answer, then corrects it in the
                # camera's units (without the effect models' radiometric part, which the per-pixel model replaced)
                first = self.compensator.run(
                    model_target, area, **{**arguments, "iterations_z": self.schedule.iterations_z,
                                           "iterations_joint": 0},
                    cancel=cancel, open_loop_theta=self.bias, name=name, start=start, verify=False)
                start, arguments["iterations_z"] = first.z, 0
                model_target = fitted if self.adapter is None else self.adapter.model_target(fitted, area)
            res = self.compensator.run(model_target, area, device=self.device, **arguments,
                                       progress=progress, cancel=cancel,
                                       open_loop_theta=self.bias if self.device is None else None,
                                       use_bias=self.options.use_bias, name=name, start=start, verify=verify)
        if self.adapter is None:
            x_input, frame = res.x_input, res.x_frame
        else:
            x_input, frame = self.adapter.input_for(res.x_input), self.adapter.frame_to_send(res.x_input)
        return TargetResult(res, fitted, area, x_input, frame, [str(w.message) for w in caught])

    def initial_input(self, image: np.ndarray) -> np.ndarray:
        """The z stage C starts a target from on its own (its ``inverse`` init, as :meth:`compensate` places the
        target): with :meth:`start_from_frame`, a warm start carries the previous frame's correction over."""
        self.choose_radiometry()
        if self.options.mode == "open-loop" and self.bias is None:
            self.estimate_bias()
        area = self.area_for(image)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TargetAspectWarning)  # said when the target is compensated
            fitted = fit_target(image, area)
            if self.range_map is not None:
                fitted = self.range_map.apply(fitted, area)
            model_target = self.model_target(fitted, area)
            placed = area.place(fit_target(model_target, area), self.compensator.camera_size)
        bias = self.bias if self.options.mode == "open-loop" else None
        return self.compensator.initial_input(placed, bias)

    def start_from_frame(self, frame: np.ndarray) -> np.ndarray:
        """The virtual input z whose native frame is ``frame`` (as :meth:`compensate` made it): the input area
        cut out, the effect models' g⁻¹ undone (light = g(input)), the warp undone (z = M(x))."""
        proj = self.calibration.rig.projector
        (x0, y0), (w, h) = proj.input_offset, proj.input_size
        if frame.shape[:2] != tuple(proj.intrinsics.size)[::-1]:
            raise ProCamError(f"a frame to start from must be {proj.intrinsics.size[0]}×{proj.intrinsics.size[1]}, "
                              f"got {frame.shape[1]}×{frame.shape[0]}")
        x = np.asarray(frame[y0:y0 + h, x0:x0 + w, :3], np.float32)
        if self.adapter is not None:
            x = np.clip(self.adapter.emitted(x, blur=not self.adapter.defocus_in_solver), 0.0, 1.0)
        return self.compensator.warp_m(x)

    @staticmethod
    def target_files(name: str) -> list[str]:
        """Every file ``procam compensate`` writes for a target ``name`` (a target cut short leaves none)."""
        return [*layout.target_files(name).values(), layout.correction_file(name)]

    def bias_record(self) -> dict[str, Any] | None:
        """The open-loop θ model as the manifest records it (None in the closed loop)."""
        if self.bias is None or self.options.mode != "open-loop":
            return None
        return {"kind": self.bias.kind, **self.bias.report}

    def settings(self) -> dict[str, Any]:
        """What decides the pixels of every target: the manifest's record of how stage C ran."""
        o, s = self.options, self.schedule
        mode = o.mode
        return {"mode": mode, "device": o.device_spec, "schedule": asdict(s),
                "iterations": {"total": s.iterations_z + s.iterations_joint, "z": s.iterations_z,
                               "joint": s.iterations_joint},
                "lr": s.lr, "capture_every": s.capture_every if mode == "closed-loop" else None,
                "bounces": self.bounces, "spp": o.spp, "seed": o.seed, "warp": self.calibration.warp is not None,
                "area_given": list(o.area) if o.area else None, "surround": list(o.surround or (0.0, 0.0, 0.0)),
                "target_encoding": o.target_encoding,
                "range": None if self.range_map is None else self.range_map.to_dict(),
                "radiometry": self.radiometry,
                "effects": None if self.adapter is None else {
                    "diagnosis": str(Path(o.diagnosis).absolute()), "used": self.adapter.used,
                    "not_inverted": self.adapter.not_used, "params": self.adapter.params},
                **({"transport_notes": list(self.transport_notes)} if self.transport_notes else {})}

    def rig_record(self) -> dict[str, Any]:
        """The rig the inputs are for, which evaluation checks before projecting them."""
        return {"projector": layout.projector_record(self.calibration.rig.projector),
                "camera_size": list(self.calibration.rig.camera.intrinsics.size)}

    def close(self) -> None:
        if self._owned and self.device is not None:
            self.device.close()
        self.device = None

    def __enter__(self) -> StageC:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
