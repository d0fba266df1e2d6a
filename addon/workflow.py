"""The steps the Blender UI runs as background jobs, and the step summaries its panels show; no bpy.

Each ``run_*`` function takes folders, reports ``progress(message, fraction)``,
honours ``cancel()`` and returns plain data (numpy arrays, paths, figures) that
the operator then writes into the scene on the main thread. Each reads the
previous step's folder and writes its own, atomically, in the same layout as
the matching ``procam`` command, so the CLI and the UI read each other's
outputs. The ``*_summary`` functions read a step's folder for its panel; they
never raise (a panel must draw whatever is on disk) and are cached by the
manifest's modification time because panels redraw often.
"""

from __future__ import annotations

import json
import re
import shutil
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import CalibrationError, Cancelled, ImageError, NotImplementedStageError, ProCamError
from .outputs import AtomicFolder, fresh_output_folder, jsonable, output_names

Progress = Callable[[str, float], None]
Cancel = Callable[[], bool]

CALIBRATION_MANIFEST = "calibration.json"
COMPENSATION_MANIFEST = "compensation.json"
DIAGNOSIS_MANIFEST = "gap.json"
FRAMES_MANIFEST = "frames.json"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp", ".hdr", ".npy")


def _quiet(msg: str, frac: float) -> None:
    """Progress sink when the caller gives none."""


def _never() -> bool:
    return False


def prepare_worker_libraries() -> None:
    """Initialise, on the main thread, native libraries that a worker thread must not initialise first.

    pymeshlab loads its filter plugins when the first ``MeshSet`` is made; when
    that happens in a worker thread the process aborts at exit with a corrupted
    heap (measured: ``malloc_consolidate(): unaligned fastbin chunk``, exit 134,
    after a surface reconstruction in a thread; none when a ``MeshSet`` was made
    on the main thread first). Call this before starting a job that calibrates.
    """
    import pymeshlab

    pymeshlab.MeshSet()


# -- summaries (for panels) ----------------------------------------------------------------------

@dataclass(frozen=True)
class Summary:
    """A step's folder as a panel shows it: ``ok`` False means absent or unreadable, with the reason."""

    ok: bool
    headline: str
    lines: tuple[str, ...] = ()
    data: dict[str, Any] = field(default_factory=dict)


_CACHE: dict[tuple[str, str], tuple[object, Summary]] = {}


def _cached(kind: str, folder: str | Path, manifest: str, read: Callable[[Path, dict[str, Any]], Summary],
            missing: str) -> Summary:
    if not folder:
        return Summary(False, missing)
    root = Path(folder)
    path = root / manifest
    try:
        stamp: object = path.stat().st_mtime_ns
    except OSError:
        return Summary(False, f"{root.name or root}: no {manifest} — {missing}")
    key = (kind, str(root))
    hit = _CACHE.get(key)
    if hit is not None and hit[0] == stamp:
        return hit[1]
    try:
        doc = json.loads(path.read_text())
        if not isinstance(doc, dict):
            raise ValueError("not a JSON object")
        summary = read(root, doc)
    except (OSError, ValueError, KeyError, TypeError, ProCamError) as exc:
        summary = Summary(False, f"cannot read {path}: {exc}")
    _CACHE[key] = (stamp, summary)
    return summary


def _fmt(value: Any, spec: str, unit: str = "") -> str:
    try:
        return f"{float(value):{spec}}{unit}"
    except (TypeError, ValueError):
        return "–"


def _calibration_summary(root: Path, doc: dict[str, Any]) -> Summary:
    if doc.get("format") != "procam-calibration":
        raise ValueError("not a ProCam calibration")
    sec = doc.get("seconds", {})
    losses = doc.get("losses", {})
    surf = doc.get("surface_report", {}) or {}
    warp = doc.get("warp_report", {}) or {}
    before, after = warp.get("corners_before_px") or {}, warp.get("corners_after_px") or {}
    pose = doc.get("pose", {}) or {}
    position = np.asarray(doc["camera_from_projector"], dtype=float)[:3, 3]
    lines = (
        f"Surface: {surf.get('vertices', doc.get('surface', {}).get('vertices', '?'))} vertices, "
        f"{surf.get('faces', doc.get('surface', {}).get('faces', '?'))} faces ({_fmt(sec.get('surface'), '.1f', ' s')})",
        f"Pose: init {doc.get('init', pose.get('init', '?'))}, loss {_fmt(losses.get('pose'), '.4g')} "
        f"({_fmt(sec.get('pose'), '.1f', ' s')})",
        f"Projector at ({position[0]:+.3f}, {position[1]:+.3f}, {position[2]:+.3f}) m",
        f"Warp: corners {_fmt(before.get('median'), '.2f')} → {_fmt(after.get('median'), '.2f')} px median, "
        f"loss {_fmt(losses.get('warp'), '.4g')} ({_fmt(sec.get('warp'), '.1f', ' s')})",
    )
    head = f"Calibrated: warp corners {_fmt(after.get('median'), '.2f')} px"
    diag = root / "diagnostics"
    maps = sorted(p.name for p in diag.glob("*.png")) if diag.is_dir() else []
    return Summary(True, head, lines, {"diagnostics": maps, "capture_set": doc.get("capture_set", "")})


def calibration_summary(folder: str | Path) -> Summary:
    """Key figures of a calibration folder: surface size, pose loss and position, warp corners before → after."""
    return _cached("calibration", folder, CALIBRATION_MANIFEST, _calibration_summary,
                   "run Calibrate or choose a calibration folder")


def _compensation_summary(root: Path, doc: dict[str, Any]) -> Summary:
    if doc.get("format") != "procam-compensation":
        raise ValueError("not a ProCam compensation folder")
    targets = [t for t in doc.get("targets", []) if isinstance(t, dict)]
    done = [t for t in targets if t.get("status") == "done"]
    lines = []
    for t in targets:
        if t.get("status") == "done":
            lines.append(f"{t['name']}: simulated PSNR {_fmt(t.get('psnr_simulated_start'), '.1f')} → "
                         f"{_fmt(t.get('psnr_simulated'), '.1f')} dB, {_fmt(t.get('seconds'), '.0f', ' s')}")
        else:
            lines.append(f"{t.get('name', '?')}: {t.get('status', '?')} — {t.get('error', '')}")
    mode = doc.get("mode")
    head = f"{len(done)}/{len(targets)} targets compensated ({mode if isinstance(mode, str) else 'mixed modes'})"
    return Summary(True, head, tuple(lines), {"targets": done, "complete": doc.get("complete", True)})


def compensation_summary(folder: str | Path) -> Summary:
    """The compensated targets of a folder: names, simulated PSNR before → after, seconds, mode."""
    return _cached("compensation", folder, COMPENSATION_MANIFEST, _compensation_summary,
                   "run Compensate or choose a compensation folder")


def _diagnosis_summary(root: Path, doc: dict[str, Any]) -> Summary:
    residual = doc.get("residual") or {}
    effects = [e for e in doc.get("effects", []) if isinstance(e, dict) and "name" in e]
    selected = [str(s) for s in doc.get("selected", [])]

    def gain(e: dict[str, Any]) -> float:
        try:
            return float(e.get("heldout_rmse_before")) - float(e.get("heldout_rmse_after"))
        except (TypeError, ValueError):
            return float("-inf")

    # Selected in the diagnosis's order (found on the residual, then absorbed by calibration), then by gain.
    effects.sort(key=lambda e: (0, selected.index(e["name"])) if e["name"] in selected else (1, -gain(e)))
    regions = [r for r in doc.get("regions", []) if isinstance(r, dict)]
    regions.sort(key=lambda r: -float(r.get("share", 0) or 0))
    head = (f"Residual RMSE {_fmt(residual.get('rmse'), '.4f')}, PSNR {_fmt(residual.get('psnr'), '.1f', ' dB')}; "
            f"{len(selected)} effect{'s' if len(selected) != 1 else ''} selected"
            + (f" ({len(doc['absorbed'])} absorbed by calibration)" if doc.get("absorbed") else ""))
    maps = [str(p.relative_to(root)) for p in sorted(root.rglob("*.png"))]
    text = next((n for n in ("summary.md", "summary.html") if (root / n).is_file()), None)
    return Summary(True, head, (), {"effects": effects, "selected": selected, "regions": regions, "maps": maps,
                                    "summary": text})


def diagnosis_summary(folder: str | Path) -> Summary:
    """A diagnosis folder (``gap.json``): residual, effects ranked (selected first, then held-out gain), regions, maps."""
    return _cached("diagnosis", folder, DIAGNOSIS_MANIFEST, _diagnosis_summary,
                   "run Diagnose or choose a diagnosis folder")


def diagnosis_available() -> tuple[bool, str]:
    """(True, '') when the diagnosis engine can be imported, else (False, why)."""
    try:
        from .gap import diagnose  # noqa: F401
    except Exception as exc:  # noqa: BLE001 — any import failure means the step is unavailable, say why
        return False, f"{type(exc).__name__}: {exc}"
    if not callable(getattr(diagnose, "diagnose", None)):
        return False, "procam.addon.gap.diagnose has no diagnose() function"
    return True, ""


# -- calibration ---------------------------------------------------------------------------------

@dataclass
class CalibrationView:
    """A calibration as the scene shows it: the rig, the textured surface, the warp grid and diagnostic images."""

    folder: Path
    calibration: Any  # stages.calibrate.Calibration
    images: dict[str, np.ndarray]


def load_calibration_view(folder: str | Path, *, progress: Progress | None = None,
                          cancel: Cancel | None = None) -> CalibrationView:
    """Read a calibration folder with its diagnostics (``diagnostics/*.png``) and the warp's deformed grid."""
    from .imageio import read_image
    from .stages.calibrate import Calibration
    from .stages.warp import grid_image

    say = progress or _quiet
    folder = Path(folder)
    say("reading the calibration", 0.0)
    cal = Calibration.load(folder, complete=False)  # a stage at a time: show what is there
    images: dict[str, np.ndarray] = {}
    diag = folder / "diagnostics"
    files = sorted(diag.glob("*.png")) if diag.is_dir() else []
    for i, path in enumerate(files):
        say(f"reading {path.name}", 0.2 + 0.7 * i / max(1, len(files)))
        images[path.stem] = read_image(path, channels=3)
    if cal.warp is not None:
        images["warp_grid"] = np.clip(grid_image(cal.warp, cal.warp.size), 0.0, 1.0).astype(np.float32)
    say("done", 1.0)
    return CalibrationView(folder, cal, images)


def run_calibration(capture_dir: str | Path, out_dir: str | Path, *, init: str = "graycode",
                    initial_pose: np.ndarray | None = None, force: bool = False, seed: int = 0,
                    stages: str | None = None, depth_offset: float | None = None,
                    progress: Progress | None = None, cancel: Cancel | None = None) -> CalibrationView:
    """``procam calibrate`` without the .blend (the UI's scene is the .blend; Export saves one)."""
    from .stages.calibrate import calibrate

    say = progress or _quiet
    calibrate(capture_dir, out_dir, init=init, initial_pose=initial_pose, force=force, with_blend=False,
              progress=lambda m, f: say(m, 0.95 * f), cancel=cancel, seed=seed, stages=stages,
              depth_offset=depth_offset)
    return load_calibration_view(out_dir, progress=lambda m, f: say(m, 0.95 + 0.05 * f))


# -- compensation --------------------------------------------------------------------------------

def _number_key(path: Path) -> tuple:
    """Natural order: frame2 before frame10."""
    return tuple(int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name))


def target_paths(files: Sequence[str | Path], sequence_dir: str | Path | None = None) -> list[Path]:
    """The target images: the listed files, then the images of ``sequence_dir`` in numbered order."""
    out = [Path(f) for f in files if str(f)]
    if sequence_dir:
        folder = Path(sequence_dir)
        if not folder.is_dir():
            raise ImageError(f"the target sequence folder {folder} does not exist; choose a folder of images")
        found = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
                        and not p.name.startswith(".")), key=_number_key)
        if not found:
            raise ImageError(f"the target sequence folder {folder} holds no images ({', '.join(IMAGE_SUFFIXES)})")
        out += found
    if not out:
        raise ImageError("no target images: add target files or choose an image sequence folder")
    return out


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


@dataclass
class CompensationView:
    """A compensation folder as the scene shows it."""

    folder: Path
    targets: list[CompensatedTarget]
    mode: str | None


def read_compensation(folder: str | Path) -> CompensationView:
    """The finished targets of a compensation folder (written by the UI or ``procam compensate``)."""
    folder = Path(folder)
    path = folder / COMPENSATION_MANIFEST
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise CalibrationError(f"{folder} is not a compensation folder ({exc}); run Compensate first") from None
    out = []
    for t in doc.get("targets", []):
        if t.get("status") != "done":
            continue
        out.append(CompensatedTarget(t["name"], folder / t["input"], folder / t["frame"], folder / t["simulated"],
                                     float(t.get("psnr_simulated", float("nan"))), float(t.get("seconds", 0.0)),
                                     str(t.get("mode", ""))))
    mode = doc.get("mode")
    return CompensationView(folder, out, mode if isinstance(mode, str) else None)


def run_compensation(calibration_dir: str | Path, targets: Sequence[str | Path], out_dir: str | Path, *,
                     device: Any = None, device_spec: str | None = None, use_bias: bool = True,
                     schedule: str | None = None, iterations: int | None = None, spp: int = 4, bounces: int = 1,
                     seed: int = 0, force: bool = False,
                     progress: Progress | None = None, cancel: Cancel | None = None) -> CompensationView:
    """Stage C for each target into a new compensation folder (the layout of ``procam compensate``).

    ``device`` given: closed loop through it; else open loop (θ from the
    calibration's validation captures). Every target is read before work
    starts. A target that fails stops the run; the finished ones are kept and
    the manifest records the failure, which is then raised. A cancel leaves nothing.
    """
    from .capture.format import CaptureSet
    from .imageio import write_atomic_bytes, write_image
    from .stages.calibrate import Calibration
    from .stages.compensate import DEFAULT_SCHEDULE, Compensator, get_schedule, split_iterations
    from .stages.display_area import TargetAspectWarning, choose_area, fit_target, load_target

    say, stop = progress or _quiet, cancel or _never
    paths = [Path(p) for p in targets]
    if not paths:
        raise ImageError("no target images: add target files or choose an image sequence folder")
    say("reading the calibration and the targets", 0.0)
    cal = Calibration.load(calibration_dir)
    loaded = [load_target(p) for p in paths]
    names = output_names(paths)
    schedule = schedule or DEFAULT_SCHEDULE
    iterations_z, iterations_joint = split_iterations(iterations, schedule)
    resolved = get_schedule(schedule)
    iterations_z = resolved.iterations_z if iterations_z is None else iterations_z
    iterations_joint = resolved.iterations_joint if iterations_joint is None else iterations_joint
    try:
        captures = CaptureSet.load(cal.capture_dir, verify_images=False) if cal.capture_dir else None
    except ProCamError:
        captures = None
    by_aspect: dict[float, Any] = {}
    areas = []
    for img, _ in loaded:
        aspect = round(img.shape[1] / img.shape[0], 4)
        if aspect not in by_aspect:
            by_aspect[aspect] = choose_area(cal, aspect=aspect, captures=captures)
        areas.append(by_aspect[aspect])
    folder = AtomicFolder(out_dir, force=force, what="compensation folder",
                          replaceable=lambda p: (p / COMPENSATION_MANIFEST).is_file())
    records: list[dict[str, Any]] = []
    failure: ProCamError | None = None
    try:
        comp = Compensator(cal, bounces=bounces, spp=spp, seed=seed)
        bias = None
        if device is None and use_bias:
            say("estimating θ from the validation captures (open loop)", 0.02)
            bias = comp.estimate_bias(captures)
        n = len(paths)
        for i, ((img, note), name, area, path) in enumerate(zip(loaded, names, areas, paths)):
            if stop():
                raise Cancelled("compensation was cancelled; nothing was written")
            lo, span = 0.05 + 0.95 * i / n, 0.95 / n

            def step(msg: str, frac: float, lo: float = lo, span: float = span, name: str = name,
                     i: int = i) -> None:
                say(f"target {i + 1}/{n} {name}: {msg}", lo + span * min(max(frac, 0.0), 1.0))

            try:
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always", TargetAspectWarning)
                    fitted = fit_target(img, area, what=f"target {path.name}")
                    res = comp.run(fitted, area, device=device, schedule=schedule, iterations_z=iterations_z,
                                   iterations_joint=iterations_joint, progress=step, cancel=stop,
                                   open_loop_theta=bias, use_bias=use_bias, name=name)
            except Cancelled:
                raise
            except ProCamError as exc:
                failure = exc
                records.append({"name": name, "file": str(path.absolute()), "status": "failed", "error": str(exc)})
                break
            files = {"input": f"{name}_input.png", "frame": f"{name}_frame.png",
                     "simulated": f"{name}_simulated.png", "target": f"{name}_target.png"}
            write_image(folder.tmp / files["input"], res.x_input)
            write_image(folder.tmp / files["frame"], res.x_frame)
            write_image(folder.tmp / files["simulated"], res.simulated)
            write_image(folder.tmp / files["target"], fitted)
            records.append({"name": name, "file": str(path.absolute()), "status": "done", "encoding": note,
                            "warnings": [str(w.message) for w in caught], "mode": res.mode,
                            "area": area.to_dict(), **files, "seconds": round(res.seconds, 2),
                            "captures": res.captures,
                            "loss_first": res.losses[0] if res.losses else None,
                            "loss_last": res.losses[-1] if res.losses else None,
                            "psnr_simulated_start": round(float(res.report["psnr_simulated_start"]), 3),
                            "psnr_simulated": round(float(res.report["psnr_simulated"]), 3)})
        modes = sorted({r["mode"] for r in records if r.get("status") == "done"})
        doc = {"format": "procam-compensation", "version": 1,
               "calibration": str(Path(calibration_dir).absolute()), "capture_set": cal.capture_dir,
               "mode": modes[0] if len(modes) == 1 else (modes or None), "device": device_spec,
               "open_loop_bias": None if bias is None else {"kind": bias.kind, **bias.report},
               "schedule": schedule,
               "iterations": {"total": iterations_z + iterations_joint, "z": iterations_z, "joint": iterations_joint},
               "bounces": bounces, "spp": spp, "seed": seed, "warp": cal.warp is not None,
               "complete": failure is None, "targets": records, "written_by": "blender-ui"}
        write_atomic_bytes(folder.tmp / COMPENSATION_MANIFEST, (json.dumps(jsonable(doc), indent=1) + "\n").encode())
    except BaseException:
        folder.abort()
        raise
    folder.commit()
    say("done", 1.0)
    if failure is not None:
        raise failure
    return read_compensation(out_dir)


# -- diagnosis -----------------------------------------------------------------------------------

def run_diagnosis(calibration_dir: str | Path, out_dir: str | Path, *, force: bool = False,
                  progress: Progress | None = None, cancel: Cancel | None = None) -> Summary:
    """The sim-to-real diagnosis (``addon.gap.diagnose``) into ``out_dir``; returns its summary."""
    ok, why = diagnosis_available()
    if not ok:
        raise NotImplementedStageError(f"the diagnosis step ({why})", "issue 6")
    from .gap.diagnose import diagnose

    diagnose(calibration_dir, out_dir, force=force, progress=progress or _quiet, cancel=cancel or _never)
    summary = diagnosis_summary(out_dir)
    if not summary.ok:
        raise ProCamError(f"the diagnosis finished but its folder cannot be read: {summary.headline}")
    return summary


# -- export --------------------------------------------------------------------------------------

def export_frames(compensation_dir: str | Path, out_dir: str | Path, *, force: bool = False,
                  first: int = 1) -> Path:
    """The compensated projector frames as a numbered 16-bit PNG sequence (``frame_0001.png`` …) with ``frames.json``.

    Frames are the full native projector resolution, in the compensation's
    target order, copied bit for bit; the manifest names the calibration, the
    mode and each frame's target and simulated PSNR.
    """
    view = read_compensation(compensation_dir)
    if not view.targets:
        raise ImageError(f"{compensation_dir} holds no finished targets to export; run Compensate first")
    for t in view.targets:
        if not t.frame_path.is_file():
            raise ImageError(f"compensated frame {t.frame_path} is missing; run Compensate again")
    doc = json.loads((Path(compensation_dir) / COMPENSATION_MANIFEST).read_text())
    with fresh_output_folder(out_dir, force=force, what="projector frame sequence") as tmp:
        frames = []
        for i, t in enumerate(view.targets):
            file = f"frame_{first + i:04d}.png"
            shutil.copyfile(t.frame_path, tmp / file)
            frames.append({"index": first + i, "file": file, "target": t.name, "mode": t.mode,
                           "psnr_simulated": t.psnr_simulated})
        manifest = {"format": "procam-frames", "version": 1, "compensation": str(Path(compensation_dir).absolute()),
                    "calibration": doc.get("calibration"), "mode": view.mode,
                    "encoding": "raw projector input levels, 16-bit PNG, native projector resolution, no sRGB transfer",
                    "written": time.strftime("%Y-%m-%dT%H:%M:%S"), "frames": frames}
        (tmp / FRAMES_MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    return Path(out_dir)


__all__ = ["CalibrationView", "CompensatedTarget", "CompensationView", "Summary", "calibration_summary",
           "compensation_summary", "diagnosis_available", "diagnosis_summary", "export_frames",
           "load_calibration_view", "output_names", "prepare_worker_libraries", "read_compensation", "run_calibration", "run_compensation",
           "run_diagnosis", "target_paths"]
