"""Evaluation: project projector inputs through a capture device and measure the camera's view against the target.

The paper's Table 2 measure (DESIGN.md §8): the capture is cropped to the
target display area, the target is fitted to that crop with
:func:`.display_area.fit_target` (the same pixels stage C saw), and PSNR and
SSIM come from :mod:`.metrics`. Always next to the baselines of the same run:

* **uncompensated** — the target projected as is, through the warp: the
  target placed in its area, carried into the projector input by the
  calibrated geometry (``Compensator.initial_input(how='geometric')``), then
  ``x = W(·)``;
* **classical** — :mod:`.classical` (per-pixel colour mixing, Gray-code geometry);
* the **ablations** of the paper's Fig. 9 — no θ (stage C with
  ``use_bias=False``) and no W (stage C on the calibration with its warp
  replaced by the identity, :func:`without_warp`).

:func:`evaluate_folder` is the engine of ``procam evaluate``: it reads what
``procam compensate`` wrote (``compensation.json`` names each target's
``NAME_frame.png`` / ``NAME_input.png`` and its display area), refuses inputs
made from another capture set, and writes per target a side-by-side image
(target | uncompensated | compensated | error map) and the captures.
"""

from __future__ import annotations

import json
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..capture.devices import Device
from ..errors import CaptureError, ImageError, ProCamError
from .display_area import DisplayArea, TargetAspectWarning, fit_target
from .metrics import error_map, psnr, ssim

Progress = Callable[[str], None]
COMPENSATION_MANIFEST = "compensation.json"
METRICS = "metrics.json"
FORMAT = "procam-evaluation"
VERSION = 1


class EvaluationError(ProCamError):
    """Evaluation cannot proceed."""


class InputsError(EvaluationError):
    """A compensation folder (``--inputs``) that is missing, incomplete or unreadable."""


class MismatchError(EvaluationError):
    """Inputs and calibration (or device) that do not belong together."""


# -- measuring one projection --------------------------------------------------------------------

@dataclass
class Measurement:
    """One projection through the device: the capture and its quality inside the display area."""

    capture: np.ndarray  # camera size
    psnr: float
    ssim: float
    seconds: float

    def scores(self) -> dict[str, float]:
        return {"psnr": round(self.psnr, 4), "ssim": round(self.ssim, 5)}


def check_capture(image: np.ndarray, camera_size: tuple[int, int]) -> np.ndarray:
    """A device capture as float32, if it has the camera's size and finite values; else a :class:`CaptureError`."""
    img = np.asarray(image, dtype=np.float32)
    cw, ch = camera_size
    if img.shape != (ch, cw, 3):
        got = f"{img.shape[1]}×{img.shape[0]}" if img.ndim >= 2 else str(img.shape)
        raise CaptureError(f"the capture device returned a {got} image (shape {img.shape}), but the calibrated camera "
                           f"is {cw}×{ch}×3; is the device the rig that was calibrated?")
    if not np.all(np.isfinite(img)):
        raise CaptureError("the capture device returned an image with NaN or infinite values")
    return img


def measure(device: Device, frame: np.ndarray, fitted: np.ndarray, area: DisplayArea,
            camera_size: tuple[int, int]) -> Measurement:
    """Project ``frame`` (native projector frame), capture, and score the area against ``fitted`` (area size)."""
    t0 = time.perf_counter()
    shot = check_capture(device.project(frame), camera_size)
    crop = area.crop(shot)
    return Measurement(shot, psnr(crop, fitted), ssim(crop, fitted), time.perf_counter() - t0)


def uncompensated_input(compensator: Any, placed: np.ndarray) -> np.ndarray:
    """The uncompensated baseline's projector input: the camera-size ``placed`` target carried into the
    projector by the calibrated geometry, as is (no photometric change), then through the warp W."""
    return compensator.warp_w(compensator.initial_input(placed, how="geometric"))


def without_warp(calibration: Any) -> Any:
    """The calibration with its warp replaced by the identity: the no-W ablation (paper's Fig. 9)."""
    from .warp import Warp

    return replace(calibration, warp=Warp.identity(calibration.rig.projector.input_size))


def side_by_side(target: np.ndarray, uncompensated: np.ndarray, compensated: np.ndarray,
                 *extra: np.ndarray, gap: int = 4) -> np.ndarray:
    """Area crops side by side: target | uncompensated | compensated | (extra…) | error map of compensated."""
    panels = [target, uncompensated, compensated, *extra, error_map(compensated, target)]
    h = target.shape[0]
    sep = np.ones((h, gap, 3), np.float32)
    row: list[np.ndarray] = []
    for p in panels:
        if row:
            row.append(sep)
        row.append(np.clip(np.asarray(p, np.float32), 0, 1))
    return np.concatenate(row, axis=1)


def mean_scores(rows: list[dict[str, Any]], key: str | None = None) -> dict[str, float] | None:
    """Mean PSNR/SSIM of ``rows`` (or of ``row[key]``); None when there is none."""
    vals = [r if key is None else r.get(key) for r in rows]
    vals = [v for v in vals if v]
    if not vals:
        return None
    return {k: round(float(np.mean([v[k] for v in vals])), 4) for k in ("psnr", "ssim")}


# -- the compensation folder ---------------------------------------------------------------------

@dataclass
class InputRecord:
    """One finished target of a compensation folder."""

    name: str
    frame: Path | None
    input: Path | None
    area: DisplayArea
    mode: str | None = None


@dataclass
class CompensationInputs:
    """What ``procam compensate`` wrote, as evaluation needs it."""

    path: Path
    doc: dict[str, Any]
    records: dict[str, InputRecord] = field(default_factory=dict)

    @staticmethod
    def load(path: str | Path) -> "CompensationInputs":
        root = Path(path)
        manifest = root / COMPENSATION_MANIFEST
        if not root.is_dir():
            raise InputsError(f"--inputs {root} does not exist; give the folder procam compensate wrote")
        if not manifest.is_file():
            raise InputsError(f"{root} has no {COMPENSATION_MANIFEST}; give the folder procam compensate wrote")
        try:
            doc = json.loads(manifest.read_text())
        except (OSError, ValueError) as exc:
            raise InputsError(f"cannot read {manifest}: {exc}") from None
        if not isinstance(doc, dict) or doc.get("format") != "procam-compensation":
            raise InputsError(f"{manifest} is not a ProCam compensation manifest")
        records: dict[str, InputRecord] = {}
        for r in doc.get("targets") or []:
            if not isinstance(r, dict) or r.get("status") != "done":
                continue
            try:
                area = DisplayArea.from_dict(r["area"])
                name = str(r["name"])
            except (KeyError, TypeError, ProCamError) as exc:
                raise InputsError(f"{manifest}: a target record is malformed ({exc})") from None
            frame = root / r["frame"] if r.get("frame") else None
            inp = root / r["input"] if r.get("input") else None
            records[name] = InputRecord(name, frame, inp, area, r.get("mode"))
        return CompensationInputs(root, doc, records)

    def check_against(self, calibration: Any, calibration_dir: str | Path | None = None) -> list[str]:
        """Refuse inputs made from another capture set or rig; return notes (e.g. another calibration folder)."""
        notes: list[str] = []
        doc = self.doc
        mine, theirs = str(calibration.capture_dir or ""), str(doc.get("capture_set") or "")
        if mine and theirs and Path(mine).resolve() != Path(theirs).resolve():
            raise MismatchError(f"the inputs in {self.path} were computed from the capture set {theirs}, but the "
                                f"calibration comes from {mine}; evaluate with the calibration the inputs were "
                                "made with")
        cam = list(calibration.rig.camera.intrinsics.size)
        proj = calibration.rig.projector
        want = {"camera_size": cam, "frame_size": list(proj.intrinsics.size),
                "input_size": list(proj.input_size), "input_offset": list(proj.input_offset)}
        have = {"camera_size": doc.get("camera_size"), **(doc.get("projector") or {})}
        for key, value in want.items():
            if have.get(key) is not None and list(have[key]) != value:
                raise MismatchError(f"the inputs in {self.path} are for {key.replace('_', ' ')} {have[key]}, but the "
                                    f"calibration has {value}: they come from another rig or capture set")
        if calibration_dir is not None and doc.get("calibration"):
            if Path(doc["calibration"]).resolve() != Path(calibration_dir).resolve():
                notes.append(f"the inputs were computed with the calibration {doc['calibration']}, evaluated here "
                             f"with {calibration_dir} (same capture set)")
        return notes

    def record(self, name: str) -> InputRecord:
        if name not in self.records:
            have = ", ".join(sorted(self.records)) or "none"
            raise InputsError(f"{self.path} holds no finished compensation for a target named {name!r} "
                              f"(targets there: {have}); name the target files as they were given to compensate")
        return self.records[name]

    def frame(self, name: str, projector: Any) -> np.ndarray:
        """The native projector frame of a target (from ``NAME_frame.png``, else ``NAME_input.png`` placed)."""
        from ..imageio import read_image

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


# -- the engine of procam evaluate ---------------------------------------------------------------

@dataclass
class EvaluationRun:
    """What :func:`evaluate_folder` measured; ``failure`` is the error that stopped it (finished targets kept)."""

    doc: dict[str, Any]
    failure: ProCamError | None = None


def evaluate_folder(calibration: Any, inputs: CompensationInputs, targets: list[tuple[str, np.ndarray, str]],
                    device: Device, out: Path, *, calibration_dir: str | Path | None = None,
                    classical: bool = False, progress: Progress | None = None) -> EvaluationRun:
    """Measure each ``(name, target image, note)`` of ``targets`` against its compensated input in ``inputs``.

    Writes into the existing folder ``out``: ``NAME_comparison.png`` (target |
    uncompensated | compensated [| classical] | error map, area crops),
    ``NAME_capture.png`` (the compensated capture) and
    ``NAME_uncompensated_capture.png``; returns the ``metrics.json`` document.
    Every input is checked before the first projection; a failure during the
    projections stops the run but keeps what was measured.
    """
    from ..imageio import write_image
    from .compensate import Compensator

    say = progress or (lambda msg: None)
    notes = inputs.check_against(calibration, calibration_dir)
    proj = calibration.rig.projector
    cam_size = calibration.rig.camera.intrinsics.size
    if not targets:
        raise EvaluationError("no target to evaluate; give at least one with --targets")
    # Read and check everything first: a bad file fails before any projection.
    frames = {name: inputs.frame(name, proj) for name, _, _ in targets}
    comp = Compensator(calibration, bounces=0, spp=4)
    comp.check_device(device)
    model = None
    if classical:
        from ..capture.format import CaptureSet
        from .classical import fit_classical

        say("classical baseline: fitting the per-pixel colour mixing (flat primaries captured through the device)")
        model = fit_classical(CaptureSet.load(calibration.capture_dir, verify_images=False), device=device)
    rows: list[dict[str, Any]] = []
    failure: ProCamError | None = None
    for i, (name, image, note) in enumerate(targets):
        rec = inputs.record(name)
        area = rec.area.check(cam_size)
        say(f"target {i + 1}/{len(targets)}: {name}")
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", TargetAspectWarning)
                fitted = fit_target(image, area, what=f"target {name!r}")
            placed = area.place(fitted, cam_size)
            got = measure(device, frames[name], fitted, area, cam_size)
            plain = measure(device, proj.frame_from_input(uncompensated_input(comp, placed)), fitted, area, cam_size)
            row: dict[str, Any] = {"name": name, **got.scores(), "uncompensated": plain.scores()}
            extra = []
            if model is not None:
                t0 = time.perf_counter()
                x = model.compensate(placed, area.mask(cam_size))
                seconds = time.perf_counter() - t0
                cl = measure(device, proj.frame_from_input(x), fitted, area, cam_size)
                row["classical"] = {**cl.scores(), "seconds": round(seconds, 3)}
                extra.append(area.crop(cl.capture))
                write_image(out / f"{name}_classical_input.png", x)
        except ProCamError as exc:
            failure = exc
            rows.append({"name": name, "status": "failed", "error": str(exc)})
            say(f"{name}: failed: {exc}")
            break
        row["warnings"] = [str(w.message) for w in caught]
        for w in row["warnings"]:
            say(f"warning: {w}")
        row["target_encoding"] = note
        row["area"] = area.to_dict()
        row["mode"] = rec.mode
        row["image"] = f"{name}_comparison.png"
        row["status"] = "done"
        write_image(out / row["image"], side_by_side(fitted, area.crop(plain.capture), area.crop(got.capture), *extra))
        write_image(out / f"{name}_capture.png", got.capture)
        write_image(out / f"{name}_uncompensated_capture.png", plain.capture)
        rows.append(row)
    done = [r for r in rows if r.get("status") == "done"]
    doc = {"format": FORMAT, "version": VERSION, "inputs": str(inputs.path.absolute()),
           "calibration": str(Path(calibration_dir).absolute()) if calibration_dir else None,
           "capture_set": calibration.capture_dir, "notes": notes,
           "measure": "PSNR (dB, peak 1) and SSIM (Wang et al. 2004) of the capture inside the display area "
                      "against the target fitted to the area",
           "classical": None if model is None else model.report,
           "targets": rows, "mean": mean_scores(done),
           "mean_uncompensated": mean_scores(done, "uncompensated"),
           "mean_classical": mean_scores(done, "classical") if model is not None else None,
           "complete": failure is None}
    return EvaluationRun(doc, failure)


__all__ = ["CompensationInputs", "EvaluationError", "EvaluationRun", "InputRecord", "InputsError", "Measurement",
           "MismatchError", "check_capture", "evaluate_folder", "mean_scores", "measure", "side_by_side",
           "uncompensated_input", "without_warp"]
