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
import json
import time
import warnings
from pathlib import Path
from typing import Any

from ..cli import command
from ..errors import CaptureError, ProCamError

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


def _configure(p: argparse.ArgumentParser) -> None:
    from ..stages.compensate import CAPTURE_EVERY, ITERATIONS_JOINT, ITERATIONS_Z, LEARNING_RATE
    from ..stages.display_area import TARGET_ENCODINGS

    p.add_argument("calibration", type=Path, help="calibration folder (from procam calibrate)")
    p.add_argument("targets", type=Path, nargs="+", metavar="TARGET", help="target images (PNG, JPEG, EXR, …)")
    p.add_argument("--out", type=Path, required=True, help="folder to create for the projector inputs")
    p.add_argument("--device", default=None,
                   help="closed loop through lab:TRUTH_FILE (virtual lab) or folder:CAPTURE_DIR; "
                        "without a device θ is estimated from the validation captures (open loop)")
    p.add_argument("--iterations", type=int, default=ITERATIONS_Z + ITERATIONS_JOINT,
                   help=f"total iterations, split {ITERATIONS_Z}:{ITERATIONS_JOINT} between z alone and z + θ "
                        f"(default {ITERATIONS_Z + ITERATIONS_JOINT}, the paper's)")
    p.add_argument("--area", default=None,
                   help="display area x,y,width,height in camera pixels (default: the capture set's, else the "
                        "largest rectangle of the target's aspect ratio that the projector covers)")
    p.add_argument("--spp", type=int, default=4, help="samples per pixel inside the loop (default 4)")
    p.add_argument("--bounces", type=int, default=1, help="indirect bounces simulated (default 1)")
    p.add_argument("--capture-every", type=int, default=CAPTURE_EVERY,
                   help=f"closed loop: capture W(z) every K joint iterations (default {CAPTURE_EVERY}; "
                        "1 = the paper, for fast real hardware)")
    p.add_argument("--lr", type=float, default=LEARNING_RATE, help=f"Adam learning rate on z (default {LEARNING_RATE})")
    p.add_argument("--target-encoding", choices=TARGET_ENCODINGS, default="auto",
                   help="auto: 8-bit files are sRGB and are linearised, 16-bit/float are linear")
    p.add_argument("--no-bias", action="store_true", help="no θ at all (ablation): neither captures nor validation")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--force", action="store_true", help="replace an existing compensation folder at --out")


def _names(paths: list[Path]) -> list[str]:
    """Output names from file stems, made unique (a/x.png and b/x.png become x and x_2)."""
    import re

    out: list[str] = []
    for p in paths:
        base = re.sub(r"[^A-Za-z0-9_.-]+", "-", p.stem).strip("-") or "target"
        name, n = base, 1
        while name in out:
            n += 1
            name = f"{base}_{n}"
        out.append(name)
    return out


@command("compensate", "Find the projector input for each target image (stage C).", _configure)
def run(args: argparse.Namespace) -> int:
    from ..capture.format import AtomicFolder, CaptureSet
    from ..imageio import write_atomic_bytes, write_image
    from ..outputs import progress
    from ..stages.calibrate import Calibration
    from ..stages.compensate import Compensator, _split_iterations
    from ..stages.display_area import TargetAspectWarning, choose_area, fit_target, load_target, parse_area

    cal = Calibration.load(args.calibration)
    # Read every target first: a bad file fails before minutes of work.
    targets = [load_target(p, encoding=args.target_encoding) for p in args.targets]
    names = _names(list(args.targets))
    user_area = parse_area(args.area) if args.area else None
    iterations_z, iterations_joint = _split_iterations(args.iterations)
    if args.spp < 1 or args.bounces < 0 or args.capture_every < 1:
        raise ProCamError("--spp and --capture-every must be ≥ 1 and --bounces ≥ 0")
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
    try:
        device = open_device(args.device)
        comp = Compensator(cal, bounces=args.bounces, spp=args.spp, seed=args.seed)
        bias = None
        if device is None and not args.no_bias:
            progress("estimating θ from the validation captures (open loop)")
            bias = comp.estimate_bias(captures)
        last = [0.0]

        def say(msg: str, frac: float) -> None:
            now = time.monotonic()
            if now - last[0] >= 2.0 or frac >= 1.0:
                progress(msg)
                last[0] = now

        for i, ((img, note), name, area, path) in enumerate(zip(targets, names, areas, args.targets)):
            progress(f"target {i + 1}/{len(targets)}: {name} ({area.width}×{area.height} at {area.x},{area.y})")
            try:
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always", TargetAspectWarning)
                    fitted = fit_target(img, area, what=f"target {path.name}")
                    res = comp.run(fitted, area, device=device, iterations_z=iterations_z,
                                   iterations_joint=iterations_joint, lr=args.lr, capture_every=args.capture_every,
                                   progress=say, open_loop_theta=bias, use_bias=not args.no_bias, name=name)
            except ProCamError as exc:
                failure = exc
                records.append({"name": name, "file": str(path.absolute()), "status": "failed", "error": str(exc)})
                break
            notes = [str(w.message) for w in caught]
            for n in notes:
                progress(f"warning: {n}")
            files = {"input": f"{name}_input.png", "frame": f"{name}_frame.png",
                     "simulated": f"{name}_simulated.png", "target": f"{name}_target.png"}
            write_image(folder.tmp / files["input"], res.x_input)
            write_image(folder.tmp / files["frame"], res.x_frame)
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
            print(f"{name}: {res.mode}, {res.seconds:.1f} s, simulated PSNR {res.report['psnr_simulated_start']:.2f} "
                  f"→ {res.report['psnr_simulated']:.2f} dB in the display area")
        proj = cal.rig.projector
        modes = sorted({r["mode"] for r in records if r.get("status") == "done"})
        doc = {"format": FORMAT, "version": VERSION,
               "calibration": str(Path(args.calibration).absolute()), "capture_set": cal.capture_dir,
               "mode": modes[0] if len(modes) == 1 else (modes or None),
               "device": args.device, "open_loop_bias": None if bias is None else {"kind": bias.kind, **bias.report},
               "iterations": {"total": args.iterations, "z": iterations_z, "joint": iterations_joint},
               "capture_every": args.capture_every if device is not None else None,
               "lr": args.lr, "bounces": args.bounces, "spp": args.spp, "seed": args.seed,
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
    folder.commit()
    print(f"compensation: {args.out} ({sum(r['status'] == 'done' for r in records)}/{len(targets)} targets)")
    if failure is not None:
        raise failure
    return 0
