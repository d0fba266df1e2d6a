"""The virtual lab's capture session: a whole capture set rendered from a truth, and the truth sealed beside it.

The lab stands in for real hardware. Cycles is not the model the pipeline
uses (Mitsuba), and the effects of :mod:`.effects` are applied where they
arise in a real rig (:mod:`.cycles_device`). The truth — the real projector
pose, the surface, the effects and their parameters (:mod:`.truth`) — is
written to a *sealed* JSON file outside the capture set; pipeline and
diagnosis code never read it, only evaluation does, and the lab device can
be re-opened from it to capture more images later. Taking the depth image
(from ``(seed, "depth")``) or not does not change any RGB capture.

Several projectors: each projector's sequence is captured while the others
show black, so each is rendered by a device of its own (the truth's
:meth:`~.truth.LabTruth.for_projector`, its own random streams) on the shared
surface and camera; the surface photo and the depth are taken once. With a
projector black level (``black_level.projector`` > 0, any projector's) the
others' black is light too — the leak of their black panels reaches every
capture of the session, as in a real room — so each projector's sequence is
rendered with every projector in the scene, the others showing black
(:class:`_AmongOthersBlack`, one render per shot, the projector's own random
streams). Without a black level the others' black is no light at all, and
each projector is rendered alone: the same captures, and Cycles' samples spent
on the one light that shines.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ..capture.devices import Device
from ..capture.format import CaptureSet, CaptureSetWriter, DepthInfo, WALL_PARAM, is_capture_set, validate_depth
from ..capture.patterns import PatternSpec, calibration_sequence
from ..errors import CaptureError, LabError
from ..outputs import check_file_replaceable, check_replaceable, hidden_sibling, remove_stale_siblings
from ..progress import Cancel, Progress, check, quiet
from .truth import (BINARY_KINDS, WALL_DISTANCE, LabTruth, binary_samples, is_truth_file, is_truth_surface,
                    lab_depth, lab_wall_depth)


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

    def __init__(self, device: Device, nominal: Any) -> None:
        self.device, self.projector = device, nominal

    def project(self, frame: np.ndarray) -> np.ndarray:
        return self.device.project(frame)

    def project_all(self, frames: Sequence[np.ndarray]) -> np.ndarray:
        return self.device.project_all(frames)

    def capture_off(self) -> np.ndarray:
        return self.device.capture_off()


class _AmongOthersBlack(Device):
    """Projector ``index`` of a device of the whole rig, the other projectors showing black in every shot."""

    def __init__(self, device: Device, index: int, projectors: Sequence[Any]) -> None:
        self.device, self.index = device, index
        self.projector = projectors[index]
        self._blacks = [np.zeros((p.intrinsics.height, p.intrinsics.width, 3), np.float32) for p in projectors]

    def project(self, frame: np.ndarray) -> np.ndarray:
        return self.device.project_all([frame if k == self.index else black for k, black in enumerate(self._blacks)])

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
    views = [truth.for_projector(k) for k in range(len(truth.rig.projectors))]
    seqs: list[list[PatternSpec]] = [
        [spec for spec in calibration_sequence(view.rig.projector, graycode=graycode, validation=validation,
                                               seed=truth.seed) if k == 0 or not spec.projector_off]
        for k, view in enumerate(views)]  # the surface photo (every projector off) is taken once
    total = sum(len(seq) for seq in seqs) + 2  # + depth + the scene
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
    nominal = truth.nominal_projectors
    writer = CaptureSetWriter(out_dir, truth.nominal_camera, nominal[0], others=nominal[1:], depth_info=depth_info,
                              notes=notes, force=force, inputs=inputs)
    tmp_truth: Path | None = None
    try:
        from .cycles_device import LabDevice  # bpy: the lab's renders

        done = 2
        # The others' black panels leak light (module doc): then every projector's shots see all of them.
        glow = len(views) > 1 and any(truth.effects_of(k)["black_level"]["projector"] > 0 for k in range(len(views)))
        for k, (view, seq) in enumerate(zip(views, seqs)):
            with LabDevice(replace(truth, seed=view.seed) if glow else view, supersample=supersample) as device:
                shown = _NominalDevice(_AmongOthersBlack(device, k, truth.rig.projectors) if glow else device,
                                       nominal[k])
                device.phase, device.session_shots = "calibration", len(seq)
                for spec in seq:
                    check(cancel, "the lab run was cancelled; nothing was written")
                    if spec.kind == "validation":
                        device.phase = "validation"
                    name = spec.name if k == 0 else f"{spec.name}_p{k}"
                    report(done, total, name)
                    done += 1
                    device.samples = binary if spec.kind in BINARY_KINDS else truth.samples
                    frame = None if spec.projector_off else spec.image
                    shot = shown.capture_off() if frame is None else shown.project(frame)
                    writer.add(spec.kind, shot, name=name, frame=frame, projector_index=k, **spec.params)
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
    many = f" of {len(cs.projectors)} projectors" if cs.others else ""
    return f"{n} captures{many} + depth{wall} at {w}×{h} in {seconds:.0f} s"


__all__ = ["check_lab_outputs", "describe_run", "run_lab"]
