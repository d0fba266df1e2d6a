"""The evaluate step: project compensated inputs through a device and measure PSNR/SSIM in the display area.

Reads a compensation folder (``compensation.json`` names each target's
``NAME_frame.png`` / ``NAME_input.png`` and its display area), refuses inputs
made from another capture set or rig, projects each target's input and, as a
baseline, the uncompensated target through the device, and writes a new
folder (atomically; replaced only with ``force``):

``metrics.json``                   per target PSNR/SSIM compensated, uncompensated [and classical]; the means
``NAME_comparison.png``            target | uncompensated | compensated [| classical] | error map (area crops)
``NAME_capture.png``               the camera's view of the compensated input
``NAME_uncompensated_capture.png`` the camera's view of the uncompensated target

Targets are matched to the compensation by file stem, as the compensate step
named them, and checked by content: a target whose SHA-256 differs from the one
recorded for the file compensated is refused (a folder from before the hash was
recorded is matched by name only, with a warning). If a target fails during the projections, the finished ones are
kept and ``metrics.json`` records the failure (``"complete": false``), which
is then raised.

A show folder (``procam show``) is read like a compensation folder, its frames
matched by the stems of the images they were made from; a show made from a
video is evaluated on that video (``--targets clip.mp4``, checked by its
hash): each finished frame against the video frame it was made from.
Given two or more targets in order (a sequence), ``metrics.json`` also holds
their **flicker** (:class:`Flicker`): the mean absolute difference between
consecutive captures inside the display area, minus that of the targets
themselves — what compensation adds to the sequence's own change.

Each compensated input is captured twice (unless ``repeat`` is off): the two
captures differ by the camera's noise alone, which gives the **noise
ceiling**, the range ceiling as a capture can score it (see
:func:`..stages.range.noise_ceiling`). A result is held to that one.
"""

from __future__ import annotations

import json
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any
from collections.abc import Iterator

import cv2
import numpy as np

from ..capture.devices import Device
from ..errors import ImageError, ProCamError
from ..imageio import read_image, write_image
from ..options import option, same_option, validate
from ..outputs import AtomicFolder, check_replaceable, file_sha256, output_names, write_manifest, writer_lock
from ..progress import Cancel, Progress, check, quiet
from ..safepaths import inside
from ..stages.calibrate import Calibration
from ..stages.classical import fit_classical
from ..stages.compensate import Compensator
from ..stages.display_area import DisplayArea, TargetAspectWarning, fit_target, load_target
from ..stages.metrics import check_capture, mean_scores, measure, psnr, side_by_side, uncompensated_input
from ..stages.range import RangeMap, capture_noise_mse, ceiling_gap_at_limit, noise_ceiling, range_ceiling
from ..stages import spill as spill_module
from ..stages.spill import one_projector_reach
from ..stages.transport import camera_to_input
from ..video import VideoReader, is_video, load_video_frame
from . import calibrate as calibrate_step
from . import layout, projectors
from .show import list_frames
from .show_work import source_record
from .stage_c import StageCOptions, check_device_fits, device_inputs, device_pipeline
from .summary import Summary, cached, fmt

KIND = layout.EVALUATION


class EvaluationError(ProCamError):
    """Evaluation cannot proceed."""


class InputsError(EvaluationError):
    """A compensation folder that is missing, incomplete or unreadable."""


class MismatchError(EvaluationError):
    """Inputs and calibration (or device) that do not belong together."""


@dataclass(frozen=True)
class EvaluateOptions:
    """What ``procam evaluate`` and the Evaluate button ask for."""

    calibration: Path
    inputs: Path  # the compensation folder
    targets: tuple[Path, ...]
    device: str = same_option(StageCOptions, "device", required=True,
                              help="lab:TRUTH_FILE (virtual lab), folder:CAPTURE_DIR or live:camera=SOURCE,display=N")
    out: Path
    classical: bool = option(
        False, help="also measure the classical per-pixel colour-mixing baseline (captures 3 flat primaries)")
    target_encoding: str = same_option(StageCOptions, "target_encoding")
    force: bool = False
    repeat: bool = option(
        True, negate="--no-repeat",
        help="capture each compensated input twice, for the camera's noise and the noise ceiling, the range ceiling "
             "as a capture through that noise can score it (off: once)")


@dataclass
class InputRecord:
    """One finished target of a compensation folder."""

    name: str
    frame: Path | None
    input: Path | None
    area: DisplayArea
    mode: str | None = None
    #: the file the input was computed from and its SHA-256 (None where an older ProCam recorded none)
    source: str | None = None
    sha256: str | None = None
    #: with several projectors: each projector's native frame, in projector order
    frames: tuple[Path, ...] = ()


def _read_manifest(manifest: Path, fmt: str, what: str) -> dict[str, Any]:
    """A step manifest of format ``fmt``, or an :class:`InputsError` saying what is wrong with it."""
    try:
        doc = json.loads(manifest.read_text())
    except (OSError, ValueError) as exc:
        raise InputsError(f"cannot read {manifest}: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != fmt:
        raise InputsError(f"{manifest} is not a ProCam {what} manifest")
    return doc


@dataclass
class CompensationInputs:
    """What ``procam compensate`` wrote, as evaluation needs it."""

    path: Path
    doc: dict[str, Any]
    records: dict[str, InputRecord] = field(default_factory=dict)

    @staticmethod
    def load(path: str | Path) -> CompensationInputs:
        root = Path(path)
        if (root / layout.SHOW.manifest).is_file():
            return CompensationInputs._load_show(root)
        manifest = root / layout.COMPENSATION.manifest
        if not root.is_dir():
            raise InputsError(f"the compensation folder {root} does not exist; give the folder procam compensate "
                              "wrote")
        if not manifest.is_file():
            raise InputsError(f"{root} has no {manifest.name}; give the folder procam compensate wrote")
        doc = _read_manifest(manifest, layout.COMPENSATION.format, "compensation")
        records: dict[str, InputRecord] = {}
        for r in doc.get("targets") or []:
            if not isinstance(r, dict) or r.get("status") != "done":
                continue
            try:
                area = DisplayArea.from_dict(r["area"])
                name = str(r["name"])
            except (KeyError, TypeError, ProCamError) as exc:
                raise InputsError(f"{manifest}: a target record is malformed ({exc})") from None
            frame = inside(root, r["frame"], what=f"the frame of target {name!r}", error=InputsError) \
                if r.get("frame") else None
            inp = inside(root, r["input"], what=f"the input of target {name!r}", error=InputsError) \
                if r.get("input") else None
            sha = r.get("file_sha256")
            several = r.get("projectors") if isinstance(r.get("projectors"), list) else []
            frames = tuple(inside(root, (p if isinstance(p, dict) else {}).get("frame"),
                                  what=f"the frame of projector {k + 1} of target {name!r}", error=InputsError)
                           for k, p in enumerate(several))
            records[name] = InputRecord(name, frame, inp, area, r.get("mode"), str(r.get("file") or ""),
                                        sha if isinstance(sha, str) else None, frames)
        return CompensationInputs(root, doc, records)

    @staticmethod
    def _load_show(root: Path) -> CompensationInputs:
        """A show folder's finished frames, named by the stems of their target images; a show of several
        projectors gives each frame's files of every projector (``frames``), in projector order."""
        manifest = root / layout.SHOW.manifest
        show = _read_manifest(manifest, layout.SHOW.format, "show")
        video = show.get("video") or None
        cal = show.get("calibration") or {}
        doc = {"format": layout.COMPENSATION.format, "capture_set": cal.get("capture_set"),
               "calibration": cal.get("path"), "camera_size": show.get("camera_size"),
               "projector": show.get("projector"), "range": (show.get("settings") or {}).get("range"),
               "video": video}
        if isinstance(show.get("projectors"), list):
            doc["projectors"] = show["projectors"]
        records: dict[str, InputRecord] = {}
        frames = [e for e in (show.get("frames") or {}).values() if isinstance(e, dict) and e.get("status") == "done"]
        for e in sorted(frames, key=lambda e: int(e.get("number", 0))):
            try:
                # a video's frames share one source: they are named by their output files (frame_NNNN)
                name = Path(str(e["file"])).stem if video else output_names([str(e["source"])])[0]
                file = inside(root, e["file"], what=f"the file of frame {name!r}", error=InputsError)
                sha = None if video else e.get("source_sha256")  # a video is checked whole (video_targets)
                several = e.get("projectors") if isinstance(e.get("projectors"), list) else []
                files = tuple(inside(root, p["file"], what=f"the file of projector {k + 1} of frame {name!r}",
                                     error=InputsError) for k, p in enumerate(several))
                records[name] = InputRecord(name, file, None, DisplayArea.from_dict(e["area"]),
                                            e.get("mode"), str(e.get("source") or ""),
                                            sha if isinstance(sha, str) else None, files)
            except (KeyError, TypeError, ValueError, ProCamError) as exc:
                raise InputsError(f"{manifest}: a frame record is malformed ({exc})") from None
        return CompensationInputs(root, doc, records)

    def _resolved(self, path: Any) -> Path:
        """A folder a manifest names, resolved to compare it; a name no file system takes (a NUL byte, not text)
        is the manifest's fault."""
        try:
            return Path(str(path)).resolve()
        except (ValueError, OSError) as exc:
            raise InputsError(f"{self.path} names a folder {path!r} that is no path ({exc}); run procam compensate "
                              "again") from None

    def check_against(self, calibration: Any, calibration_dir: str | Path | None = None) -> list[str]:
        """Refuse inputs made from another capture set or rig; return notes (e.g. another calibration folder)."""
        notes: list[str] = []
        doc = self.doc
        mine, theirs = str(calibration.capture_dir or ""), str(doc.get("capture_set") or "")
        if mine and theirs and self._resolved(mine) != self._resolved(theirs):
            raise MismatchError(f"the inputs in {self.path} were computed from the capture set {theirs}, but the "
                                f"calibration comes from {mine}; evaluate with the calibration the inputs were "
                                "made with")
        cam = list(calibration.rig.camera.intrinsics.size)
        want = {"camera_size": cam, **layout.projector_record(calibration.rig.projector)}
        have = {"camera_size": doc.get("camera_size"), **(doc.get("projector") or {})}
        for key, value in want.items():
            if have.get(key) is None:
                raise InputsError(f"{self.path} does not record the {key.replace('_', ' ')} its inputs are for "
                                  "(an older ProCam wrote it); run procam compensate again")
            if list(have[key]) != value:
                raise MismatchError(f"the inputs in {self.path} are for {key.replace('_', ' ')} {have[key]}, but the "
                                    f"calibration has {value}: they come from another rig or capture set")
        self.check_projectors(calibration)
        if calibration_dir is not None and doc.get("calibration") and \
                self._resolved(doc["calibration"]) != self._resolved(calibration_dir):
                notes.append(f"the inputs were computed with the calibration {doc['calibration']}, evaluated here "
                             f"with {calibration_dir} (same capture set)")
        return notes

    def check_projectors(self, calibration: Any) -> None:
        """Refuse inputs made for another number of projectors, or another size of any of them."""
        want = [layout.projector_record(p) for p in calibration.rig.projectors]
        have = self.doc.get("projectors")
        have = have if isinstance(have, list) else [self.doc.get("projector")]
        if len(have) != len(want):
            raise MismatchError(f"the inputs in {self.path} are for {len(have)} projector(s), but the calibration "
                                f"has {len(want)}: evaluate with the calibration the inputs were made with")
        for k, (a, b) in enumerate(zip(have, want)):
            if k and a != b:  # the first projector's record is checked field by field by check_against
                raise MismatchError(f"the inputs in {self.path} are for projector {k + 1} of {a}, but the "
                                    f"calibration's is {b}: they come from another rig")

    def frames(self, name: str, projectors: Any) -> list[np.ndarray]:
        """Every projector's native frame of a target of a compensation of several projectors, checked against
        each projector's size."""
        rec = self.record(name)
        if len(rec.frames) != len(projectors):
            raise MismatchError(f"{self.path}: target {name!r} has frames of {len(rec.frames)} projector(s), but the "
                                f"calibration has {len(projectors)}: evaluate with the calibration the inputs were "
                                "made with")
        out = []
        for k, (path, proj) in enumerate(zip(rec.frames, projectors)):
            if not path.is_file():
                raise InputsError(f"the frame of projector {k + 1} of {name!r} is missing ({path}); run procam "
                                  "compensate again")
            try:
                img = read_image(path, channels=3)
            except ImageError as exc:
                raise InputsError(f"the frame {path} is unreadable ({exc}); run procam compensate again") from None
            fw, fh = proj.intrinsics.size
            if img.shape[:2] != (fh, fw):
                raise MismatchError(f"{path} is {img.shape[1]}×{img.shape[0]}, but projector {k + 1}'s frame is "
                                    f"{fw}×{fh}: the inputs come from another rig")
            out.append(img)
        return out

    def check_targets(self, names: list[str], paths: tuple[Path, ...] | list[Path]) -> list[str]:
        """Refuse a target whose contents differ from the file its input was computed from (same name, another
        image); notes naming the targets whose record holds no hash (an older ProCam wrote it) and so are matched
        by name only."""
        unchecked = []
        for name, path in zip(names, paths):
            rec = self.record(name)
            if rec.sha256 is None:
                unchecked.append(name)
            elif file_sha256(path) != rec.sha256:
                raise MismatchError(f"{path} is not the image the input {name!r} in {self.path} was computed from "
                                    f"({rec.source or 'a file of that name'}): its contents differ. Give the target "
                                    "files as they were given to compensate (or compensate this one)")
        if not unchecked:
            return []
        return [f"{self.path} records no content hash for the target(s) {', '.join(unchecked)} (an older ProCam "
                "wrote it): they are matched by file name only, not checked to be the images compensated; run "
                "procam compensate again to have them checked"]

    def record(self, name: str) -> InputRecord:
        if name not in self.records:
            have = ", ".join(sorted(self.records)) or "none"
            raise InputsError(f"{self.path} holds no finished compensation for a target named {name!r} "
                              f"(targets there: {have}); name the target files as they were given to compensate")
        return self.records[name]

    def frame(self, name: str, projector: Any) -> np.ndarray:
        """The native projector frame of a target (from ``NAME_frame.png``, else ``NAME_input.png`` placed)."""
        rec = self.record(name)
        fw, fh = projector.intrinsics.size
        iw, ih = projector.input_size
        for path, size, is_frame in ((rec.frame, (fw, fh), True), (rec.input, (iw, ih), False)):
            if path is None or not path.is_file():
                continue
            try:
                img = read_image(path)
            except ImageError as exc:
                raise InputsError(f"the projector input {path} is unreadable ({exc}); run procam compensate "
                                  "again") from None
            if (img.shape[1], img.shape[0]) != size:
                raise MismatchError(f"{path} is {img.shape[1]}×{img.shape[0]}, but the calibrated projector "
                                    f"{'frame' if is_frame else 'input'} is {size[0]}×{size[1]}: the inputs come "
                                    "from another rig")
            return img if is_frame else projector.frame_from_input(img)
        missing = [str(p) for p in (rec.frame, rec.input) if p is not None] or [f"{name}_frame.png"]
        raise InputsError(f"the projector input of {name!r} is missing ({' and '.join(missing)} not found); run "
                          "procam compensate again")


#: What metrics.json says the flicker is.
FLICKER_MEASURE = ("flicker: for each pair of consecutive targets (in the order given) with the same display "
                   "area, the mean absolute difference (linear, 0–1, all channels) between their captures inside "
                   "the area, averaged over the pairs; 'targets' is the same for the targets fitted to the area "
                   "(and range-mapped), 'uncompensated' for the captures of the uncompensated targets; 'excess' = "
                   "captured − targets, which compensation should keep at or below 0")


class Flicker:
    """The flicker of a sequence (:data:`FLICKER_MEASURE`), taken as the targets come: only the previous target's
    area crops are kept (a minute of video would not fit in memory)."""

    def __init__(self) -> None:
        self.last: tuple[dict[str, Any], tuple[np.ndarray, ...]] | None = None
        self.pairs: list[tuple[float, float, float]] = []

    def add(self, row: dict[str, Any], crops: tuple[np.ndarray, np.ndarray, np.ndarray] | None) -> None:
        """The next row in order, with its crops (capture, fitted target, uncompensated capture); None: failed."""
        if crops is not None and self.last is not None and self.last[0]["area"] == row["area"]:
            self.pairs.append(tuple(float(np.mean(np.abs(b - a))) for a, b in zip(self.last[1], crops)))
        self.last = (row, crops) if crops is not None else None

    def report(self) -> dict[str, Any] | None:
        if not self.pairs:
            return None
        terms = {what: round(float(np.mean([p[k] for p in self.pairs])), 5)
                 for k, what in enumerate(("captured", "targets", "uncompensated"))}
        return {**terms, "excess": round(terms["captured"] - terms["targets"], 5), "pairs": len(self.pairs),
                "measure": FLICKER_MEASURE}


@dataclass
class EvaluationRun:
    """What :func:`evaluate_folder` measured; ``failure`` is the error that stopped it (finished targets kept)."""

    doc: dict[str, Any]
    failure: ProCamError | None = None


def input_seen(frame: np.ndarray, projector: Any, looks_at: np.ndarray) -> np.ndarray:
    """Per camera pixel and channel, the real projector input where the pixel looks (``looks_at``: texel
    coordinates of the input, NaN where it sees none; bilinear)."""
    x0, y0 = projector.input_offset
    w, h = projector.input_size
    x = np.ascontiguousarray(np.asarray(frame, np.float32)[y0:y0 + h, x0:x0 + w])
    u = np.nan_to_num(looks_at, nan=-10.0).astype(np.float32) - 0.5  # texel centres on integers for remap
    v = cv2.remap(x, u[..., 0], u[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    return np.where(np.isfinite(looks_at[..., :1]), v.reshape(*looks_at.shape[:2], -1), np.nan)


def evaluate_folder(calibration: Calibration, inputs: CompensationInputs,
                    targets: list[tuple[str, np.ndarray, str]] | VideoTargets, device: Device, out: Path, *,
                    calibration_dir: str | Path | None = None, notes: list[str] | None = None,
                    classical: bool = False, repeat: bool = True, progress: Progress | None = None,
                    cancel: Cancel | None = None) -> EvaluationRun:
    """Measure each ``(name, target image, note)`` of ``targets`` against its compensated input in ``inputs``.

    Writes into the existing folder ``out``: ``NAME_comparison.png`` (target |
    uncompensated | compensated [| classical] | error map, area crops),
    ``NAME_capture.png`` (the compensated capture) and
    ``NAME_uncompensated_capture.png``; returns the ``metrics.json`` document.
    ``inputs`` must have passed :meth:`CompensationInputs.check_against` (whose
    ``notes`` it records); every frame is read before the first projection, and
    a failure during the projections stops the run but keeps what was measured.
    ``repeat``: capture each compensated input a second time, for the camera's noise.
    """
    say = progress or quiet
    proj = calibration.rig.projector
    cam_size = calibration.rig.camera.intrinsics.size
    if not targets:
        raise EvaluationError("no target to evaluate; give at least one with --targets")
    # Read and check every input first: a bad file fails before any projection (read again when projected, so
    # a long show's frames are not all held at once).
    names = targets.names if isinstance(targets, VideoTargets) else [name for name, _, _ in targets]
    for name in names:
        inputs.frame(name, proj)
    comp = Compensator(calibration, bounces=0, spp=4)
    range_map = RangeMap.from_dict(inputs.doc.get("range"))
    captures = calibrate_step.captures_of(calibration)
    white, black = captures.image("white"), captures.image("black")
    reach = one_projector_reach(calibration, white, black)  # where the spill is measured (stages/spill.py)
    looks_at, _ = camera_to_input(calibration, cam_size)
    if calibration.warp is not None:  # the model's texel q shows what the real projector puts at φ_M(q)
        seen = np.isfinite(looks_at[..., 0])
        looks_at[seen] = calibration.warp.map_m(looks_at[seen], calibration.rig.projector.input_size)
    comp.check_device(device)
    model = None
    if classical:
        say("classical baseline: fitting the per-pixel colour mixing (flat primaries captured through the device)",
            0.0)
        model = fit_classical(captures, device=device)
    rows: list[dict[str, Any]] = []
    seen = Flicker()
    failure: ProCamError | None = None
    for i, (name, image, note) in enumerate(targets):
        rec = inputs.record(name)
        files = {k: v.format(name=name) for k, v in layout.EVALUATION_FILES.items()}
        area = rec.area.check(cam_size)
        check(cancel, "evaluation was cancelled; nothing was written")
        say(f"target {i + 1}/{len(targets)}: {name}", 0.05 + 0.95 * i / len(targets))
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", TargetAspectWarning)
                fitted = fit_target(image, area, what=f"target {name!r}")
            given = fitted
            if range_map is not None:  # the compensation aimed at the mapped target: measure against that
                fitted = range_map.apply(fitted, area)
            placed = area.place(fitted, cam_size)
            frame = inputs.frame(name, proj)
            got = measure(device, frame, fitted, area, cam_size)
            plain = measure(device, proj.frame_from_input(uncompensated_input(comp, placed)), fitted, area, cam_size)
            seen_black, seen_white, captured = area.crop(black), area.crop(white), area.crop(got.capture)
            at_limit = ceiling_gap_at_limit(fitted, captured, seen_black, seen_white,
                                            area.crop(input_seen(frame, proj, looks_at)))
            row: dict[str, Any] = {"name": name, **got.scores(), "uncompensated": plain.scores(),
                                   **relative_scores(range_map, area, captured, area.crop(plain.capture), given),
                                   "range_ceiling": round(range_ceiling(fitted, seen_black, seen_white), 2),
                                   "ceiling_gap_at_limit": None if at_limit is None else round(at_limit, 3)}
            replayed, again = False, None
            if repeat:
                again = check_capture(device.project(frame), cam_size)
                # The same image twice is a replay (a capture folder, a noiseless simulator), not a second shot: a
                # noise of 0 read from it would make the noise ceiling the range ceiling and claim a perfect camera.
                replayed = np.array_equal(again, got.capture)
                if not replayed:
                    noise = capture_noise_mse(captured, area.crop(again))
                    row["capture_noise_rmse"] = round(noise ** 0.5, 5)
                    row["noise_ceiling"] = round(noise_ceiling(fitted, seen_black, seen_white, noise), 2)
            spill_module.record(row, got.capture, plain.capture, black, area, reach,
                                again=None if replayed else again)
            extra = []
            if model is not None:
                t0 = time.perf_counter()
                x = model.compensate(placed, area.mask(cam_size))
                seconds = time.perf_counter() - t0
                cl = measure(device, proj.frame_from_input(x), fitted, area, cam_size)
                row["classical"] = {**cl.scores(), "seconds": round(seconds, 3)}
                extra.append(area.crop(cl.capture))
                write_image(out / files["classical"], x)
        except ProCamError as exc:
            failure = exc
            rows.append({"name": name, "status": "failed", "error": str(exc)})
            seen.add(rows[-1], None)
            say(f"{name}: failed: {exc}", 1.0)
            break
        row["warnings"] = [str(w.message) for w in caught] + (
            ["the device returned the same image for both captures of the input (a replayed capture): the camera's "
             "noise cannot be measured, so no noise ceiling is given"] if replayed else [])
        for w in row["warnings"]:
            say(f"warning: {w}", 0.05 + 0.95 * (i + 1) / len(targets))
        row["target_encoding"] = note
        row["area"] = area.to_dict()
        row["mode"] = rec.mode
        row["image"] = files["image"]
        row["status"] = "done"
        write_image(out / row["image"], side_by_side(fitted, area.crop(plain.capture), area.crop(got.capture), *extra))
        write_image(out / files["capture"], got.capture)
        write_image(out / files["uncompensated"], plain.capture)
        seen.add(row, (area.crop(got.capture), fitted, area.crop(plain.capture)))
        rows.append(row)
    done = [r for r in rows if r.get("status") == "done"]
    doc = {"format": KIND.format, "version": KIND.version, "inputs": str(inputs.path.absolute()),
           "calibration": str(Path(calibration_dir).absolute()) if calibration_dir else None,
           "capture_set": calibration.capture_dir, "notes": notes or [],
           "measure": "PSNR (dB, peak 1) and SSIM (Wang et al. 2004) of the capture inside the display area "
                      "against the target fitted to the area (and mapped by the compensation's range, if any); "
                      "range_ceiling: PSNR of that target clipped per pixel to the captured [black, white], the "
                      "best any input could do; ceiling_gap_at_limit: of the capture's squared error beyond the "
                      "clipped target's, the share where the input the pixel sees is already at full (capture too "
                      "dark) or at zero (too bright), which no solver can push further; capture_noise_rmse: the "
                      "camera's noise, from a second capture of the compensated input; noise_ceiling: the range "
                      "ceiling as a capture scores it, through that noise (a camera that compresses its photos, JPEG, "
                      "also quantises the picture's texture the same way in both captures: the difference misses "
                      "that, so on such a camera the ceiling is optimistic and reads higher for a blurred answer "
                      "than for a sharp one); " + RELATIVE_MEASURE + "; " + spill_module.MEASURE,
           "range": None if range_map is None else range_map.to_dict(),
           "classical": None if model is None else model.report,
           "targets": rows, "mean": mean_scores(done),
           "mean_uncompensated": mean_scores(done, "uncompensated"),
           **mean_relative(done),
           "mean_range_ceiling": round(float(np.mean([r["range_ceiling"] for r in done])), 2) if done else None,
           "mean_noise_ceiling": (round(float(np.mean([r["noise_ceiling"] for r in done])), 2)
                                  if done and all("noise_ceiling" in r for r in done) else None),
           "mean_classical": mean_scores(done, "classical") if model is not None else None,
           "flicker": seen.report(), "spill": spill_module.summarise(done, cam_size[0]),
           "complete": failure is None}
    return EvaluationRun(doc, failure)


class VideoTargets:
    """The finished frames of a show made from a video, as ``(name, target, note)``, decoded when asked for: a
    minute of full-resolution frames would not fit in memory at once."""

    def __init__(self, path: Path, names: list[str], encoding: str) -> None:
        self.path, self.names, self.encoding = path, names, encoding

    def __len__(self) -> int:
        return len(self.names)

    def __iter__(self) -> Iterator[tuple[str, np.ndarray, str]]:
        with VideoReader(self.path) as reader:
            for name in self.names:
                image, note = load_video_frame(reader, int(name.rsplit("_", 1)[1]) - 1, encoding=self.encoding)
                yield name, image, note


def video_targets(inputs: CompensationInputs, given: tuple[Path, ...], encoding: str) -> VideoTargets:
    """The targets of a show made from a video: every finished frame, read from the video it was made from."""
    video = inputs.doc["video"]
    if len(given) != 1 or not is_video(given[0]):
        raise InputsError(f"{inputs.path} was made from the video {video.get('source')}; give that video as the "
                          "only target (its finished frames are measured in order)")
    path = Path(given[0])
    if not path.is_file():
        raise InputsError(f"the video {path} does not exist")
    if source_record(path)["source_sha256"] != video.get("source_sha256"):
        raise MismatchError(f"{path} is not the video {inputs.path} was made from ({video.get('source')}): its "
                            "contents differ")
    names = sorted(inputs.records, key=lambda n: int(n.rsplit("_", 1)[1]))
    if not names:
        raise InputsError(f"{inputs.path} has no finished frame to evaluate")
    return VideoTargets(path, names, encoding)


def target_files(given: Sequence[str | Path]) -> tuple[Path, ...]:
    """The targets as ``procam show`` takes them (:func:`.show.list_frames`): one folder (its images in frame
    order) or one numbered pattern (``frames/shot_####.png``) becomes its image files; image files, and one video
    (whose frames a show made from it measures), stay as given."""
    items = tuple(Path(p) for p in given)
    if len(items) == 1 and not is_video(items[0]) and (items[0].is_dir() or not items[0].exists()):
        return tuple(f.path for f in list_frames(items))
    return items


def run(options: EvaluateOptions, progress: Progress | None = None, cancel: Cancel | None = None, *,
        device: Device | None = None) -> dict[str, Any]:
    """Measure every target of ``options`` into a new evaluation folder; returns ``metrics.json``'s document.
    ``device``: an open device to use instead of opening ``options.device`` (the manifest names the latter).
    The targets may be a folder or a numbered pattern, as ``procam show`` takes them (:func:`target_files`)."""
    say = progress or quiet
    validate(options)
    given = tuple(Path(p) for p in options.targets)
    options = replace(options, targets=target_files(given))
    # a folder or pattern given is an input too: the output must not lie inside it
    folders = tuple(p if p.is_dir() else p.parent for p in given if p.is_dir() or not p.exists())
    check_replaceable(options.out, force=options.force, what=KIND.what, replaceable=KIND.holds,
                      inputs=(options.calibration, calibrate_step.capture_set_of(options.calibration),
                              options.inputs, *options.targets, *folders, *device_inputs(options.device)),
                      incomplete=KIND.incomplete)
    with writer_lock(options.out):  # another run of this output is refused before any work
        return _run(options, say, cancel, device)


def _run(options: EvaluateOptions, say: Progress, cancel: Cancel | None, device: Device | None) -> dict[str, Any]:
    cal = calibrate_step.read(options.calibration)
    check_device_fits(options.device, cal, device=device)  # a device of another rig: refused before any projection
    inputs = CompensationInputs.load(options.inputs)
    notes = inputs.check_against(cal, options.calibration)  # inputs of another rig fail before any projection
    if inputs.doc.get("video"):
        targets: Any = video_targets(inputs, options.targets, options.target_encoding)
    else:
        names = output_names(options.targets)
        for name in names:
            inputs.record(name)  # a target with no compensation fails before anything is read or projected
        targets = [(name, *load_target(p, encoding=options.target_encoding))
                   for name, p in zip(names, options.targets)]
        for note in inputs.check_targets(names, options.targets):
            say(f"warning: {note}", 0.0)
            notes.append(note)
    folder = AtomicFolder(options.out, force=options.force, what=KIND.what, replaceable=KIND.holds,
                          inputs=(options.calibration, options.inputs, cal.capture_dir, *options.targets,
                                  *device_inputs(options.device)), incomplete=KIND.incomplete)
    owned = device is None
    try:
        if not options.device:
            raise EvaluationError("evaluation projects through a device: give lab:TRUTH_FILE, "
                                  "folder:CAPTURE_DIR or live:camera=…")
        device = device_pipeline(options.device, cal, device=device, progress=say)
        if cal.projector_count > 1:  # every projector's frame shown at once; overlap figures
            if options.classical:
                raise EvaluationError("the classical baseline is not evaluated for several projectors yet: "
                                      "evaluate without --classical")
            result = EvaluationRun(*projectors.evaluate(cal, inputs, targets, device, folder.tmp, notes=notes,
                                                        repeat=options.repeat, progress=say, cancel=cancel))
        else:
            result = evaluate_folder(cal, inputs, targets, device, folder.tmp, calibration_dir=options.calibration,
                                     notes=notes, classical=options.classical, repeat=options.repeat,
                                     progress=say, cancel=cancel)
        result.doc["device"] = options.device
        write_manifest(folder.tmp / KIND.manifest, result.doc)
    except BaseException:
        folder.abort()
        raise
    finally:
        if owned and device is not None:
            device.close()
    folder.commit()
    say("done", 1.0)
    if result.failure is not None:
        raise result.failure
    return result.doc


@dataclass
class EvaluationView:
    """An evaluation folder: its ``metrics.json`` and the figures its readers use."""

    folder: Path
    doc: dict[str, Any]

    @property
    def complete(self) -> bool:
        """Whether every target was measured (a failure keeps the finished ones and says so)."""
        return bool(self.doc.get("complete", True))

    @property
    def targets(self) -> list[dict[str, Any]]:
        """One row per target, finished (``status`` done) or failed, in the order given."""
        return [t for t in self.doc.get("targets") or [] if isinstance(t, dict)]

    @property
    def mean(self) -> dict[str, Any]:
        """Mean PSNR and SSIM of the finished targets, compensated."""
        return dict(self.doc.get("mean") or {})

    @property
    def mean_uncompensated(self) -> dict[str, Any]:
        return dict(self.doc.get("mean_uncompensated") or {})

    def comparisons(self) -> list[tuple[str, Path]]:
        """Each finished target's name and comparison image, a file of this folder."""
        return [(str(t["name"]), inside(self.folder, t["image"], what="the comparison image", error=EvaluationError))
                for t in self.targets if t.get("status") == "done"]


def read(folder: str | Path) -> EvaluationView:
    """An evaluation folder and its ``metrics.json``; a clear error when the folder holds none."""
    return EvaluationView(Path(folder), KIND.read(folder, EvaluationError))


#: What ``psnr_relative`` and ``brightness_kept`` are, said in metrics.json.
RELATIVE_MEASURE = ("psnr_relative: PSNR of the capture read back through the range map ((capture − offset) / gain "
                    "at each pixel, clipped to [0, 1]) against the target as given, so that maps compare: a target "
                    "dimmed to a fifth gains about 13 dB in plain PSNR from the dimming alone, none in this one, "
                    "and what the map clips counts; equal to psnr without a map; brightness_kept: the mean mapped "
                    "white (gain + offset) over the display area as a share of the target's white, 1 without a map")


def relative_scores(range_map: RangeMap | None, area: Any, captured: np.ndarray, uncompensated: np.ndarray,
                    target: np.ndarray) -> dict[str, Any]:
    """``psnr_relative`` of a compensated and an uncompensated capture (area crops) against the target as given
    (fitted to the area, not mapped), and the brightness the map keeps there (:data:`RELATIVE_MEASURE`)."""
    def back(capture: np.ndarray) -> np.ndarray:
        return capture if range_map is None else range_map.unmap(capture, area)
    return {"psnr_relative": round(psnr(back(captured), target), 4),
            "uncompensated_psnr_relative": round(psnr(back(uncompensated), target), 4),
            "brightness_kept": 1.0 if range_map is None else round(range_map.brightness_kept(area), 4)}


def mean_relative(rows: list[dict[str, Any]]) -> dict[str, float | None]:
    """The mean ``psnr_relative`` (compensated and uncompensated) and ``brightness_kept`` of done rows."""
    def mean(key: str) -> float | None:
        vals = [float(r[key]) for r in rows if r.get(key) is not None]
        return round(float(np.mean(vals)), 4) if vals else None
    return {"mean_psnr_relative": mean("psnr_relative"),
            "mean_uncompensated_psnr_relative": mean("uncompensated_psnr_relative"),
            "brightness_kept": mean("brightness_kept")}


def _target_line(t: dict[str, Any]) -> str:
    if t.get("status") != "done":
        return f"{t.get('name')}: failed — {t.get('error', '')}"
    u = t.get("uncompensated") or {}
    classical = (f", classical {fmt(t['classical'].get('psnr'), '.2f')} dB"
                 if isinstance(t.get("classical"), dict) else "")
    return (f"{t['name']}: PSNR {fmt(u.get('psnr'), '.2f')} → {fmt(t.get('psnr'), '.2f')} dB, SSIM "
            f"{fmt(u.get('ssim'), '.3f')} → {fmt(t.get('ssim'), '.3f')} (uncompensated → compensated{classical})"
            + (f"; relative to the mapped white {fmt(t.get('uncompensated_psnr_relative'), '.2f')} → "
               f"{fmt(t['psnr_relative'], '.2f')} dB, brightness kept {fmt(t.get('brightness_kept'), '.0%')}; "
               if t.get("psnr_relative") is not None and t.get("brightness_kept") != 1.0 else "; ")
            + f"range ceiling {fmt(t.get('range_ceiling'), '.2f')} dB"
            + (f" ({fmt(t['noise_ceiling'], '.2f')} dB through the camera's noise, RMS "
               f"{fmt(t.get('capture_noise_rmse'), '.4f')})" if "noise_ceiling" in t else "")
            + (f", {fmt(t['ceiling_gap_at_limit'], '.0%')} of the gap to it where the input is already at its limit"
               if t.get("ceiling_gap_at_limit") is not None else "")
            + ("; " + spill_module.spill_text(t["spill_mean"], t.get("spill_p995"), u.get("spill_mean"),
                                              u.get("spill_p995")) if "spill_mean" in t else ""))


def _overlap_line(doc: dict[str, Any]) -> str:
    """The figures of several projectors: inside the overlaps, outside them, along their edges."""
    m, u = doc.get("mean") or {}, doc.get("mean_uncompensated") or {}
    return (f"{doc.get('projector_count')} projectors: PSNR inside the overlap {fmt(u.get('psnr_overlap'), '.2f')} → "
            f"{fmt(m.get('psnr_overlap'), '.2f')} dB, outside it {fmt(u.get('psnr_outside'), '.2f')} → "
            f"{fmt(m.get('psnr_outside'), '.2f')} dB, along its edge {fmt(u.get('psnr_border'), '.2f')} → "
            f"{fmt(m.get('psnr_border'), '.2f')} dB; seam step {fmt(u.get('seam_step'), '.4f')} → "
            f"{fmt(m.get('seam_step'), '.4f')} (uncompensated → compensated)")


def _summary(root: Path, doc: dict[str, Any]) -> Summary:
    view = EvaluationView(root, doc)
    mean, plain = view.mean, view.mean_uncompensated
    head = (f"PSNR {fmt(plain.get('psnr'), '.2f')} → {fmt(mean.get('psnr'), '.2f')} dB, SSIM "
            f"{fmt(plain.get('ssim'), '.3f')} → {fmt(mean.get('ssim'), '.3f')} (uncompensated → compensated)")
    lines = [_target_line(t) for t in view.targets]
    if doc.get("projector_count", 1) > 1:
        lines.append(_overlap_line(doc))
    mapped = doc.get("range")
    if isinstance(mapped, dict):
        lines.append(f"targets mapped by the compensation's range: {fmt(mapped.get('gain'), '.3f')}·t "
                     f"{fmt(mapped.get('offset'), '+.3f')}" + (" (mean of a gain field)" if mapped.get("field") else "")
                     + (f"; brightness kept {fmt(doc['brightness_kept'], '.0%')}, PSNR relative to the mapped white "
                        f"{fmt(doc.get('mean_uncompensated_psnr_relative'), '.2f')} → "
                        f"{fmt(doc.get('mean_psnr_relative'), '.2f')} dB (uncompensated → compensated; comparable "
                        "across maps)" if doc.get("brightness_kept") is not None else ""))
    sp = doc.get("spill")
    if isinstance(sp, dict):
        lines.append(spill_module.spill_text(sp.get("mean"), sp.get("p995"), sp.get("uncompensated_mean"),
                                             sp.get("uncompensated_p995"))
                     + f", mean over targets (worst 99.5th pixel {fmt(sp.get('worst_p995'), '.1%')}; pixels the "
                     f"projectors reach farther than {sp.get('guard_px')} px from the area)")
    f = doc.get("flicker")
    if isinstance(f, dict):
        lines.append(f"flicker over {f.get('pairs')} consecutive pair(s): captured {fmt(f.get('captured'), '.4f')}, "
                     f"targets {fmt(f.get('targets'), '.4f')} (excess {fmt(f.get('excess'), '+.4f')}; uncompensated "
                     f"{fmt(f.get('uncompensated'), '.4f')})")
    return Summary(True, head, tuple(lines), {"targets": view.targets, "complete": view.complete})


def summary(folder: str | Path) -> Summary:
    """Mean and per-target PSNR/SSIM of an evaluation folder, compensated next to uncompensated."""
    return cached(KIND, folder, _summary, "run Evaluate or choose an evaluation folder")
