"""``procam compensate``: stage C for each target image, closed loop through a device or open loop.

Writes into a new folder (atomically; an existing compensation folder is only
replaced with ``--force``), for each target ``NAME``:

``NAME_input.png``      the projector input x* = W(z) at the input size (16-bit)
``NAME_frame.png``      x* placed in the native projector frame (16-bit)
``NAME_simulated.png``  clip(f̂(z) − θ): what the model expects the camera to see (camera size)
``NAME_target.png``     the target as fitted to the display area (area size, linear)

and ``compensation.json``: the calibration used, the mode (closed-loop /
open-loop / none), the display area, iterations, losses and seconds per
target. All targets are read before any work starts, so a missing or
unreadable one fails at once; if a later target fails during its
optimisation, the finished ones are kept and the manifest records the failure.
"""

from __future__ import annotations

import argparse
import contextlib
import json
from dataclasses import asdict
import warnings
from pathlib import Path
from typing import Any

from ..cli import command
from ..errors import Cancelled, CaptureError, ProCamError

FORMAT = "procam-compensation"
VERSION = 1
MANIFEST = "compensation.json"


def open_device(spec: str | None) -> Any:
    """A capture device from ``lab:TRUTH_FILE`` (the virtual lab) or ``folder:CAPTURE_DIR`` (replayed captures)."""
    if not spec:
        return None
    kind, _, where = spec.partition(":")
    if not where:
        raise CaptureError(f"--device must be lab:TRUTH_FILE or folder:CAPTURE_DIR, got {spec!r}")
    if kind == "lab":
        from ..lab.lab import LabDevice, LabTruth

        return LabDevice(LabTruth.load(Path(where)))
    if kind == "folder":
        from ..capture.devices import FolderDevice

        return FolderDevice(Path(where))
    raise CaptureError(f"unknown device kind {kind!r} in --device {spec!r}; use lab:TRUTH_FILE or folder:CAPTURE_DIR")


def add_schedule_options(p: argparse.ArgumentParser) -> None:
    """The stage-C options shared by ``procam compensate`` and ``procam show`` (device, schedule, area, θ)."""
    from ..stages.compensate import DEFAULT_SCHEDULE, ITERATIONS_JOINT, ITERATIONS_Z, SCHEDULES
    from ..stages.display_area import TARGET_ENCODINGS

    def counts(name: str) -> str:
        s = SCHEDULES[name]
        start = f"{s.fixed_point} fixed-point steps + " if s.fixed_point else ""
        return (f"{name}: {start}{s.iterations_z}+{s.iterations_joint} iterations, lr {s.lr}, a capture every "
                f"{s.capture_interval}")

    p.add_argument("--device", default=None,
                   help="closed loop through lab:TRUTH_FILE (virtual lab) or folder:CAPTURE_DIR; "
                        "without a device θ is estimated from the validation captures (open loop)")
    p.add_argument("--schedule", choices=tuple(SCHEDULES), default=DEFAULT_SCHEDULE,
                   help=f"stage-C schedule (default {DEFAULT_SCHEDULE}; 'paper' = the paper's 200+300 iterations). "
                        "--iterations, --lr and --capture-every override its values: " +
                        "; ".join(counts(n) for n in SCHEDULES))
    p.add_argument("--iterations", type=int, default=None,
                   help="total Adam iterations, split between z alone and z + θ in the schedule's own ratio "
                        f"(paper: {ITERATIONS_Z}:{ITERATIONS_JOINT}; fast: all joint, after its fixed-point steps; "
                        "default: the schedule's counts)")
    p.add_argument("--area", default=None,
                   help="display area x,y,width,height in camera pixels (default: the capture set's, else the "
                        "largest rectangle of the target's aspect ratio that the projector covers)")
    p.add_argument("--spp", type=int, default=4, help="samples per pixel inside the loop (default 4)")
    p.add_argument("--bounces", type=int, default=1, help="indirect bounces simulated (default 1)")
    p.add_argument("--capture-every", type=int, default=None,
                   help="closed loop: capture W(z) every K joint iterations (default: the schedule's; "
                        "1 = the paper, for fast real hardware)")
    p.add_argument("--lr", type=float, default=None, help="Adam learning rate on z (default: the schedule's)")
    p.add_argument("--target-encoding", choices=TARGET_ENCODINGS, default="auto",
                   help="auto: 8-bit files are sRGB and are linearised, 16-bit/float are linear")
    p.add_argument("--no-bias", action="store_true", help="no θ at all (ablation): neither captures nor validation")
    p.add_argument("--seed", type=int, default=0)


def check_schedule(args: argparse.Namespace) -> None:
    """Refuse schedule values stage C cannot use, before anything is loaded."""
    if args.spp < 1 or args.bounces < 0:
        raise ProCamError(f"--spp must be ≥ 1 and --bounces ≥ 0, got {args.spp} and {args.bounces}")
    if args.capture_every is not None and args.capture_every < 1:
        raise ProCamError(f"--capture-every must be ≥ 1, got {args.capture_every}")
    if args.iterations is not None and args.iterations < 0:
        raise ProCamError(f"--iterations must be ≥ 0, got {args.iterations}")
    if args.lr is not None and not (0 < args.lr < float("inf")):
        raise ProCamError(f"--lr must be a positive number, got {args.lr}")


def schedule_arguments(args: argparse.Namespace) -> dict[str, Any]:
    """Keyword arguments of :meth:`Compensator.run` for the schedule options: the schedule's name and only the
    values given on the command line (the others are the schedule's)."""
    from ..stages.compensate import DEFAULT_SCHEDULE, split_iterations

    schedule = getattr(args, "schedule", None) or DEFAULT_SCHEDULE
    iterations_z, iterations_joint = split_iterations(args.iterations, schedule)
    given = {"iterations_z": iterations_z, "iterations_joint": iterations_joint, "lr": args.lr,
             "capture_every": args.capture_every}
    return {"schedule": schedule, **{k: v for k, v in given.items() if v is not None}}


def resolved_schedule(arguments: dict[str, Any]) -> Any:
    """The :class:`Schedule` that :func:`schedule_arguments`' keywords make (checked: a bad value fails here)."""
    from dataclasses import replace

    from ..stages.compensate import get_schedule

    overrides = {k: v for k, v in arguments.items() if k != "schedule"}
    return replace(get_schedule(arguments["schedule"]), **overrides).check()


def add_effect_options(p: argparse.ArgumentParser) -> None:
    """``--effects`` / ``--diagnosis``: diagnosed effect models around stage C (addon/gap/compensation.py)."""
    p.add_argument("--effects", default="none",
                   help="effect models around stage C, fitted by procam diagnose: 'auto' (the ones it selected), "
                        "NAME,... or 'none' (default); needs --diagnosis")
    p.add_argument("--diagnosis", type=Path, default=None, help="the procam diagnose folder for --effects")


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("calibration", type=Path, help="calibration folder (from procam calibrate)")
    p.add_argument("targets", type=Path, nargs="+", metavar="TARGET", help="target images (PNG, JPEG, EXR, …)")
    p.add_argument("--out", type=Path, required=True, help="folder to create for the projector inputs")
    add_schedule_options(p)
    add_effect_options(p)
    p.add_argument("--force", action="store_true", help="replace an existing compensation folder at --out")


@command("compensate", "Find the projector input for each target image (stage C).", _configure)
def run(args: argparse.Namespace) -> int:
    from ..capture.format import AtomicFolder, CaptureSet
    from ..cli import cancel_on_interrupt
    from ..imageio import write_atomic_bytes, write_image
    from ..outputs import ProgressBar, output_names, progress
    from ..stages.calibrate import Calibration
    from ..stages.compensate import Compensator
    from ..stages.display_area import TargetAspectWarning, choose_area, fit_target, load_target, parse_area
    from ..stages.sequence import calibration_identity

    from ..gap.compensation import AdaptedCaptures, AdaptedDevice, adapter_from_options

    check_schedule(args)
    cal = Calibration.load(args.calibration)
    adapter = adapter_from_options(args.effects, args.diagnosis, cal.rig.projector)
    ident = calibration_identity(args.calibration)
    # Read every target first: a bad file fails before minutes of work.
    targets = [load_target(p, encoding=args.target_encoding) for p in args.targets]
    names = output_names(args.targets)
    user_area = parse_area(args.area) if args.area else None
    sched = schedule_arguments(args)
    resolved = resolved_schedule(sched)
    try:
        captures = CaptureSet.load(cal.capture_dir, verify_images=False) if cal.capture_dir else None
    except ProCamError:
        captures = None  # a moved capture set: the area must then come from --area or the model alone
    # Check every target's area before the work starts (an --area outside the image fails here).
    areas = []
    by_aspect: dict[float, Any] = {}  # an automatic area costs a render: one per distinct aspect ratio
    for img, _ in targets:
        aspect = round(img.shape[1] / img.shape[0], 4)
        if aspect not in by_aspect:
            by_aspect[aspect] = choose_area(cal, aspect=aspect, user=user_area, captures=captures)
        areas.append(by_aspect[aspect])
    folder = AtomicFolder(args.out, force=args.force, what="compensation folder",
                          replaceable=lambda p: (p / MANIFEST).is_file())
    device = None
    failure: ProCamError | None = None
    records: list[dict[str, Any]] = []
    stack = contextlib.ExitStack()  # Ctrl-C becomes a clean cancel between iterations; the bar ends its line
    cancel = stack.enter_context(cancel_on_interrupt())
    bar = stack.enter_context(ProgressBar(len(targets), "compensate", unit="targets"))
    try:
        device = open_device(args.device)
        model_device, model_captures = device, captures
        if adapter is None:
            comp = Compensator(cal, bounces=args.bounces, spp=args.spp, seed=args.seed)
        else:
            # The effects sit around stage C: it sees light emitted and light seen (addon/gap/compensation.py).
            comp = adapter.compensator(cal, bounces=args.bounces, spp=args.spp, seed=args.seed)
            model_device = AdaptedDevice(device, adapter) if device is not None else None
            model_captures = AdaptedCaptures(captures, adapter) if captures is not None else None
            progress(f"effect models: {', '.join(adapter.used) or 'none'}"
                     + (f"; not inverted: {', '.join(adapter.not_used)}" if adapter.not_used else ""))
        bounces = comp.bounces
        bias = None
        if device is None and not args.no_bias:
            progress("estimating θ from the validation captures (open loop)")
            bias = comp.estimate_bias(model_captures)

        for i, ((img, note), name, area, path) in enumerate(zip(targets, names, areas, args.targets)):
            progress(f"target {i + 1}/{len(targets)}: {name} ({area.width}×{area.height} at {area.x},{area.y})")
            try:
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always", TargetAspectWarning)
                    fitted = fit_target(img, area, what=f"target {path.name}")
                    model_target = fitted if adapter is None else adapter.model_target(fitted, area)
                    res = comp.run(model_target, area,
                                   device=model_device, **sched,
                                   progress=lambda msg, frac, i=i: bar.update(i + min(frac, 0.999), msg),
                                   cancel=cancel, open_loop_theta=bias, use_bias=not args.no_bias, name=name)
            except Cancelled:
                raise
            except ProCamError as exc:
                failure = exc
                records.append({"name": name, "file": str(path.absolute()), "status": "failed", "error": str(exc)})
                break
            notes = [str(w.message) for w in caught]
            for n in notes:
                progress(f"warning: {n}")
            files = {"input": f"{name}_input.png", "frame": f"{name}_frame.png",
                     "simulated": f"{name}_simulated.png", "target": f"{name}_target.png"}
            write_image(folder.tmp / files["input"], adapter.input_for(res.x_input) if adapter else res.x_input)
            write_image(folder.tmp / files["frame"], adapter.frame_to_send(res.x_input) if adapter else res.x_frame)
            write_image(folder.tmp / files["simulated"], res.simulated)
            write_image(folder.tmp / files["target"], fitted)
            records.append({"name": name, "file": str(path.absolute()), "status": "done", "encoding": note,
                            "warnings": notes, "mode": res.mode, "area": area.to_dict(), **files,
                            "seconds": round(res.seconds, 2), "captures": res.captures,
                            "loss_first": res.losses[0] if res.losses else None,
                            "loss_last": res.losses[-1] if res.losses else None,
                            "losses": [round(v, 7) for v in res.losses],
                            "psnr_simulated_start": round(res.report["psnr_simulated_start"], 3),
                            "psnr_simulated": round(res.report["psnr_simulated"], 3)})
            bar.update(i + 1, f"{name} done", force=True)
            print(f"{name}: {res.mode}, {res.seconds:.1f} s, simulated PSNR {res.report['psnr_simulated_start']:.2f} "
                  f"→ {res.report['psnr_simulated']:.2f} dB in the display area")
        proj = cal.rig.projector
        modes = sorted({r["mode"] for r in records if r.get("status") == "done"})
        doc = {"format": FORMAT, "version": VERSION,
               "calibration": str(Path(args.calibration).absolute()), "calibration_sha256": ident["sha256"],
               "capture_set": cal.capture_dir,
               "mode": modes[0] if len(modes) == 1 else (modes or None),
               "device": args.device, "open_loop_bias": None if bias is None else {"kind": bias.kind, **bias.report},
               "schedule": asdict(resolved),
               "iterations": {"total": resolved.iterations_z + resolved.iterations_joint,
                              "z": resolved.iterations_z, "joint": resolved.iterations_joint},
               "capture_every": resolved.capture_every if device is not None else None,
               "effects": None if adapter is None else {
                   "diagnosis": str(Path(args.diagnosis).absolute()), "used": adapter.used,
                   "not_inverted": adapter.not_used, "params": adapter.params},
               "lr": resolved.lr, "bounces": bounces, "spp": args.spp, "seed": args.seed,
               "warp": cal.warp is not None,
               "projector": {"frame_size": list(proj.intrinsics.size), "input_size": list(proj.input_size),
                             "input_offset": list(proj.input_offset)},
               "camera_size": list(cal.rig.camera.intrinsics.size),
               "area": records[0]["area"] if records and records[0].get("area") and all(
                   r.get("area") == records[0]["area"] for r in records) else None,
               "complete": failure is None, "targets": records}
        write_atomic_bytes(folder.tmp / MANIFEST, (json.dumps(doc, indent=1) + "\n").encode())
    except BaseException:
        folder.abort()
        raise
    finally:
        if device is not None:
            device.close()
        stack.close()
    folder.commit()
    print(f"compensation: {args.out} ({sum(r['status'] == 'done' for r in records)}/{len(targets)} targets)")
    if failure is not None:
        raise failure
    return 0
