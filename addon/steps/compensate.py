"""The compensate step: stage C for each target image into one compensation folder, and its readers.

The folder is written atomically (an existing one is only replaced with
``force``); for each target ``NAME``:

``NAME_input.png``      the projector input x* = W(z) at the input size (16-bit)
``NAME_frame.png``      x* placed in the native projector frame (16-bit)
``NAME_simulated.png``  clip(f̂(z) − θ): what the model expects the camera to see (camera size)
``NAME_target.png``     the target as fitted to the display area (area size, linear)

and ``compensation.json``: the calibration used (path and content hash), how
stage C ran (mode, device, schedule, effects), the rig the inputs are for,
and per target its file and that file's SHA-256 (evaluate checks it), area,
losses and seconds. All targets are read before any
work starts, so a missing or unreadable one fails at once; if a later target
fails during its optimisation, or the run is cancelled (Ctrl-C, Cancel), the
finished ones are kept, the manifest records the failure or the cancel and
``"complete": false``, and the error (or :class:`Cancelled`) is then raised.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..capture.devices import Device
from ..errors import Cancelled, CaptureError, ImageError, ProCamError
from ..imageio import READ_IMAGE_SUFFIXES, write_image
from ..outputs import (AtomicFolder, check_replaceable, file_sha256, natural_key, output_names, write_manifest,
                       writer_lock)
from ..progress import Cancel, Progress, check, part, quiet
from ..safepaths import inside
from ..stages.closed_loop import OtherRigError
from ..stages.range import range_line
from . import calibrate as calibrate_step
from . import layout, projectors
from .stage_c import StageC, StageCOptions, check_device_fits, loop_record, measure_radiometry, stage_c_inputs
from .summary import Summary, cached, fmt

KIND = layout.COMPENSATION


@dataclass(frozen=True)
class CompensateOptions:
    """What ``procam compensate`` and the Compensate button ask for."""

    calibration: Path
    targets: tuple[Path, ...]
    out: Path
    stage_c: StageCOptions = field(default_factory=StageCOptions)
    force: bool = False


def target_paths(files: Sequence[str | Path], sequence_dir: str | Path | None = None) -> tuple[Path, ...]:
    """The target images: the listed files, then the images of ``sequence_dir`` in natural order."""
    out = [Path(f) for f in files if str(f)]
    if sequence_dir:
        folder = Path(sequence_dir)
        if not folder.is_dir():
            raise ImageError(f"the target sequence folder {folder} does not exist; choose a folder of images")
        found = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in READ_IMAGE_SUFFIXES
                        and not p.name.startswith(".")), key=natural_key)
        if not found:
            raise ImageError(f"the target sequence folder {folder} holds no images ({', '.join(READ_IMAGE_SUFFIXES)})")
        out += found
    if not out:
        raise ImageError("no target images: add target files or choose an image sequence folder")
    return tuple(out)


def run(options: CompensateOptions, progress: Progress | None = None, cancel: Cancel | None = None, *,
        device: Device | None = None) -> CompensationView:
    """Compensate every target into ``options.out`` (module doc); ``device`` overrides opening
    ``options.stage_c.device`` (the manifest still names the latter)."""
    say = progress or quiet
    paths = list(options.targets)
    if not paths:
        raise ImageError("no target images: add target files or choose an image sequence folder")
    # The output is checked before any work, against every input: the calibration's capture set too (read from
    # its manifest: open-loop θ, the per-pixel radiometry and the display area read it), which the full read of
    # the calibration would only name after the scene is loaded and an operator perhaps rendered.
    check_replaceable(options.out, force=options.force, what=KIND.what, replaceable=KIND.holds,
                      inputs=(options.calibration, calibrate_step.capture_set_of(options.calibration), *paths,
                              *stage_c_inputs(options.stage_c)),
                      incomplete=KIND.incomplete)
    with writer_lock(options.out):  # another run of this output is refused before any work
        return _run(options, say, cancel, device, paths)


def _run(options: CompensateOptions, say: Progress, cancel: Cancel | None, device: Device | None,
         paths: list[Path]) -> CompensationView:
    options.stage_c.check()
    cal = calibrate_step.read(options.calibration)
    check_device_fits(options.stage_c.device, cal, device=device)  # a device of another rig: refused first
    say("reading the calibration and the targets", 0.0)
    ident = calibrate_step.identity(options.calibration)
    several = cal.projector_count > 1  # one joint solve on every projector, a frame per projector
    opening = (projectors.JointStage if several else StageC)(cal, options.stage_c, device=device,
                                                             progress=part(say, 0.0, 0.02))
    one_target = projectors.one_target if several else _one_target
    with opening as stage:
        # Read every target and choose its area first: a bad file or area fails before minutes of work.
        targets = [stage.load(p) for p in paths]
        # What each target held, so that evaluate can tell a different image under the same name.
        hashes = [file_sha256(p) for p in paths]
        for image, _ in targets:
            stage.area_for(image)
        if stage.fix_range([image for image, _ in targets]) is not None:
            r = stage.range_map
            assert r is not None
            say(f"range: targets mapped to {r.describe()}", 0.03)
        names = output_names(paths)
        folder = AtomicFolder(options.out, force=options.force, what=KIND.what, replaceable=KIND.holds,
                              inputs=(options.calibration, cal.capture_dir, *paths,
                                      *stage_c_inputs(options.stage_c)), incomplete=KIND.incomplete)
        records: list[dict[str, Any]] = []
        failure: ProCamError | None = None
        stopped: BaseException | None = None  # Ctrl-C or Cancel: the targets finished so far are kept
        try:
            measure_radiometry(stage, say, 0.02)
            if stage.options.mode == "open-loop":
                say("estimating θ from the validation captures (open loop)", 0.02)
                stage.estimate_bias()
            n = len(paths)
            for i, ((image, note), name, path, sha) in enumerate(zip(targets, names, paths, hashes)):
                try:
                    record = one_target(stage, folder.tmp, image, note, name, path, i, n, say, cancel)
                except (Cancelled, KeyboardInterrupt) as exc:
                    stopped = exc
                    for file in stage.target_files(name):  # a target cut short leaves no file behind
                        (folder.tmp / file).unlink(missing_ok=True)
                    break
                except ProCamError as exc:
                    if isinstance(exc, OtherRigError) and not any(r["status"] == "done" for r in records):
                        raise  # the device is another rig's and nothing is finished: no folder is left behind
                    failure = exc
                    records.append({"name": name, "file": str(path.absolute()), "file_sha256": sha,
                                    "status": "failed", "error": str(exc)})
                    break
                records.append({**record, "file_sha256": sha})
                problem = (record.get("loop") or {}).get("problem")
                if problem:  # the rig changed under the loop: its best answer is kept, the rest waits for the user
                    failure = CaptureError(f"the closed loop of {name!r} stopped: {problem} (its best answer so far "
                                           f"is kept in {options.out})")
                    break
            finished = sum(r["status"] == "done" for r in records)
            if stopped is not None and not finished:
                raise stopped
            if stopped is not None:
                records.append({"name": names[len(records)], "file": str(paths[len(records)].absolute()),
                                "status": "cancelled", "error": "cancelled before it finished"})
            areas = [r["area"] for r in records if r.get("area")]
            write_manifest(folder.tmp / KIND.manifest, {
                "format": KIND.format, "version": KIND.version,
                "calibration": ident["path"], "calibration_sha256": ident["sha256"], "capture_set": cal.capture_dir,
                **stage.settings(),
                "open_loop_bias": stage.bias_record(),
                **stage.rig_record(),
                "area": areas[0] if areas and all(a == areas[0] for a in areas) else None,
                "complete": failure is None and stopped is None, "targets": records})
        except BaseException:
            folder.abort()
            raise
        folder.commit()
    if stopped is not None:
        raise Cancelled(f"compensation was cancelled after {finished} of {len(paths)} target(s); the finished ones "
                        f"are kept in {options.out} (marked incomplete): run the same command again to redo it "
                        "whole; no --force is needed", kept=True)
    say("done", 1.0)
    if failure is not None:
        raise failure
    return read(options.out)


def _one_target(stage: StageC, tmp: Path, image: Any, note: Any, name: str, path: Path, i: int, n: int,
                say: Progress, cancel: Cancel | None) -> dict[str, Any]:
    """Compensate one target and write its files into ``tmp``; returns its record."""
    check(cancel, "compensation was cancelled; nothing was written")
    area = stage.area_for(image)
    say(f"target {i + 1}/{n}: {name} ({area.width}×{area.height} at {area.x},{area.y})", 0.05 + 0.95 * i / n)
    # The first target's answer is rendered by Mitsuba too: on the transport schedule that checks the operator
    # against the scene once per run, at the cost of one render.
    done = stage.compensate(image, name=name, what=f"target {path.name}", cancel=cancel,
                            verify=True if i == 0 else None,
                            progress=part(say, 0.05 + 0.95 * i / n, 0.05 + 0.95 * (i + 1) / n,
                                          f"target {i + 1}/{n} {name}: "))
    for w in done.warnings:
        say(f"warning: {w}", 0.05 + 0.95 * (i + 1) / n)
    files = layout.target_files(name)
    res = done.result
    write_image(tmp / files["input"], done.input)
    write_image(tmp / files["frame"], done.frame)
    write_image(tmp / files["simulated"], res.simulated)
    write_image(tmp / files["target"], done.fitted)
    loop = loop_record(tmp, name, res)
    return {"name": name, "file": str(path.absolute()), "status": "done", "encoding": note,
            "warnings": done.warnings, "mode": res.mode, "area": done.area.to_dict(), **files,
            "seconds": round(res.seconds, 2), "captures": res.captures,
            "seconds_compute": res.report.get("seconds_compute"),
            "seconds_verify": res.report.get("seconds_verify"),
            "simulated_by": res.report.get("simulated_by", "mitsuba"),
            "operator_vs_mitsuba_psnr": res.report.get("operator_vs_mitsuba_psnr"),
            "input_blur": res.report.get("input_blur"),  # the lens's blur held in the solve
            "loss_first": res.losses[0] if res.losses else None,
            "loss_last": res.losses[-1] if res.losses else None,
            "losses": [round(v, 7) for v in res.losses],
            "psnr_simulated_start": round(float(res.report["psnr_simulated_start"]), 3),
            "psnr_simulated": round(float(res.report["psnr_simulated"]), 3),
            **({"loop": loop} if loop else {})}


# -- reading ---------------------------------------------------------------------------------------

@dataclass
class CompensatedTarget:
    """One finished target of a compensation folder."""

    name: str
    input_path: Path
    frame_path: Path
    simulated_path: Path
    psnr_simulated: float
    seconds: float
    mode: str
    #: every projector's native frame and input, in rig order (one projector: ``frame_path`` and ``input_path``)
    frame_paths: tuple[Path, ...] = ()
    input_paths: tuple[Path, ...] = ()

    def __post_init__(self) -> None:
        if not self.frame_paths:
            self.frame_paths = (self.frame_path,)
        if not self.input_paths:
            self.input_paths = (self.input_path,)


@dataclass
class CompensationView:
    """A compensation folder: its manifest and finished targets."""

    folder: Path
    doc: dict[str, Any]
    targets: list[CompensatedTarget]

    @property
    def mode(self) -> str | None:
        mode = self.doc.get("mode")
        return mode if isinstance(mode, str) else None

    @property
    def projector_count(self) -> int:
        """How many projectors the frames are for (1 for a folder of one projector)."""
        several = self.doc.get("projectors")
        return len(several) if isinstance(several, list) and several else 1


def read(folder: str | Path) -> CompensationView:
    """A compensation folder and its finished targets; a clear error when it is not one."""
    folder = Path(folder)
    doc = KIND.read(folder)
    path = folder / KIND.manifest
    out = []
    targets = doc.get("targets") or []
    if not isinstance(targets, list):
        raise ProCamError(f"{path}: 'targets' must be a list of target records, not {targets!r}; give the folder "
                          f"{KIND.made_by} wrote")
    for t in targets:
        if not isinstance(t, dict) or t.get("status") != "done":
            continue
        try:
            name = str(t["name"])
            # The files a record names are this folder's own: never a path that leads out of it.
            image, frame, simulated = (inside(folder, t[key], what=f"the {key} image of target {name!r}")
                                       for key in ("input", "frame", "simulated"))
            several = t.get("projectors") if isinstance(t.get("projectors"), list) else []
            frames, inputs = (tuple(inside(folder, p[key], what=f"the {key} image of projector {k + 1} of target "
                                                                 f"{name!r}") for k, p in enumerate(several))
                              for key in ("frame", "input"))
            psnr = t.get("psnr_simulated")  # null where it was no number
            out.append(CompensatedTarget(name, image, frame, simulated, float("nan") if psnr is None else float(psnr),
                                         float(t.get("seconds", 0.0)), str(t.get("mode", "")), frames, inputs))
        except (KeyError, TypeError, ValueError) as exc:
            raise ProCamError(f"{path}: a target record is malformed ({exc})") from None
    return CompensationView(folder, doc, out)


def radiometry_text(record: Any) -> str | None:
    """What the run's ``radiometry`` record says stage C worked through (None for a folder without the record)."""
    if not isinstance(record, dict) or "used" not in record:
        return None
    rmse = record.get("held_out_rmse") or {}
    judged = (f" (held-out RMS {fmt(rmse.get('pixel'), '.4f')} per pixel, {fmt(rmse.get('global'), '.4f')} global)"
              if rmse else "")
    each = [p.get("held_out_rmse") or {} for p in record.get("projectors") or [] if isinstance(p, dict)]
    if each:  # several projectors: each one's own model, judged on its own held-out captures
        rmse = {"projectors": each}
        judged = " (held-out RMS per pixel / global: " + ", ".join(
            f"projector {k + 1} {fmt(r.get('pixel'), '.4f')} / {fmt(r.get('global'), '.4f')}"
            for k, r in enumerate(each)) + ")"
    if record["used"] == "pixel":
        replaced = record.get("replaces_effects") or []
        return (f"each camera pixel's own response and colour mixing{judged}"
                + (f"; it replaces the effect models {', '.join(replaced)}" if replaced else ""))
    why = record.get("reason")
    return f"global{judged}" + (f" — {why}" if why and not rmse else "")


def _names(value: Any) -> list[str]:
    """The effect names of a record's ``used`` (a list) or ``not_inverted`` (names to reasons)."""
    return [str(n) for n in value] if isinstance(value, (list, dict)) else []


def effects_text(record: Any) -> str | None:
    """The effect models a run used, as its ``effects`` record says (None for a run without --effects): one
    projector's list, or each projector's of several and the camera's curve, every projector's; then those not
    inverted."""
    if not isinstance(record, dict):
        return None
    several = record.get("projectors")
    if not isinstance(several, list):
        used = ", ".join(_names(record.get("used"))) or "none"
        left = _names(record.get("not_inverted"))
        return used + (f"; not inverted: {', '.join(left)}" if left else "")
    mine = [p if isinstance(p, dict) else {} for p in several]
    camera = _names((record.get("camera") or {}).get("used")) if isinstance(record.get("camera"), dict) else []
    parts = [f"projector {k + 1}: {', '.join(_names(p.get('used'))) or 'none'}" for k, p in enumerate(mine)]
    parts += [f"the camera's, for every projector: {', '.join(camera)}"] if camera else []
    used = "; ".join(parts) if camera or any(_names(p.get("used")) for p in mine) else "none"
    left = [f"projector {k + 1}: {', '.join(_names(p.get('not_inverted')))}" for k, p in enumerate(mine)
            if _names(p.get("not_inverted"))]
    return used + (f"; not inverted: {'; '.join(left)}" if left else "")


def _summary(root: Path, doc: dict[str, Any]) -> Summary:
    targets = [t for t in doc.get("targets", []) if isinstance(t, dict)]
    done = [t for t in targets if t.get("status") == "done"]
    lines = []
    effects = effects_text(doc.get("effects"))
    lines += [f"effect models: {effects}"] if effects is not None else []
    radiometry = radiometry_text(doc.get("radiometry"))
    lines += [f"radiometry: {radiometry}"] if radiometry else []
    several = doc.get("projectors") if isinstance(doc.get("projectors"), list) else []
    count = len(several) or 1
    for t in targets:
        if t.get("status") == "done":
            lines.append(f"{t['name']}: simulated PSNR {fmt(t.get('psnr_simulated_start'), '.1f')} → "
                         f"{fmt(t.get('psnr_simulated'), '.1f')} dB in the display area, {t.get('mode', '?')}, "
                         f"{fmt(t.get('seconds'), '.1f', ' s')}" + _shares(t, count))
            lines += _loop_line(t)
        else:
            lines.append(f"{t.get('name', '?')}: {t.get('status', '?')} — {t.get('error', '')}")
        if count > 1:  # what several projectors warn of (one that lights nothing in the area) is said here
            lines += [f"{t.get('name', '?')}: warning: {w}" for w in (t.get("warnings") or [])]
    lines += range_line(doc.get("range"))
    notes = doc.get("transport_notes")
    lines += [f"note: {n}" for n in notes if isinstance(n, str)] if isinstance(notes, list) else []
    mode = doc.get("mode")
    head = f"{len(done)}/{len(targets)} targets compensated ({mode if isinstance(mode, str) else 'mixed modes'})"
    if count > 1:
        head += f" on {count} projectors"
    return Summary(True, head, tuple(lines), {"targets": done, "complete": doc.get("complete", True),
                                             "projector_count": count})


def _loop_line(record: dict[str, Any]) -> list[str]:
    """How the measured closed loop went for a target: its captures, the residual against the noise floor, and why
    it stopped (nothing for other loops)."""
    loop = record.get("loop")
    if not isinstance(loop, dict) or not loop.get("per_capture"):
        return []
    rms = [h.get("residual_rms") for h in loop["per_capture"] if isinstance(h, dict)]
    return [f"  closed loop: {loop.get('captures')} captures, residual RMS {fmt(rms[0], '.4f')} → "
            f"{fmt(rms[-1], '.4f')} against the camera's noise {fmt(loop.get('noise_rms'), '.4f')}; "
            f"stopped: {loop.get('stopped')}"
            + (f": {loop['problem']}" if loop.get("problem") else "")]


def _shares(record: dict[str, Any], count: int) -> str:
    """Each projector's share of the light of a target of several projectors ("" for one)."""
    several = record.get("projectors") if isinstance(record.get("projectors"), list) else []
    if count < 2 or not several:
        return ""
    shares = [p.get("share") if isinstance(p, dict) else None for p in several]
    text = "; share of the light " + ", ".join(
        f"projector {k + 1} {fmt(100 * v if isinstance(v, (int, float)) else None, '.0f', '%')}"
        for k, v in enumerate(shares))
    lit = record.get("area_shares")
    return text + (f"; {projectors.shares_text(lit)}" if isinstance(lit, list) and lit else "")


def summary(folder: str | Path) -> Summary:
    """The compensated targets of a folder: names, simulated PSNR before → after, seconds, mode."""
    return cached(KIND, folder, _summary, "run Compensate or choose a compensation folder")
