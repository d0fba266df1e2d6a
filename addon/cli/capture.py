"""``procam patterns``, ``import-captures`` and ``undistort-captures``: the folder workflow for users with their own
tools.

``patterns`` writes the numbered calibration frames at the projector's native
resolution; the user shows and photographs them; ``import-captures`` turns the
photographs into a capture set that calibration reads; ``undistort-captures`` takes a
board-calibrated camera lens out of a capture set made before the camera was calibrated.

Several projectors, one projector at a time: ``patterns --projector-number K`` for each projector, then
``import-captures SEQ1 PHOTOS1 --out SET1`` and ``import-captures SEQ2 PHOTOS2 --add-to SET1 --out SET2`` …,
each run a new set of one more projector; a set is never changed in place, so a calibration made from SET1 still
reads the set it was made from.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..capture.sequence import load_sequence
from ..options import add_arguments, declared, from_arguments
from ..rig.model import Projector
from ..steps.capture import (CameraSize, DepthSensorSize, ImportOptions, PatternsOptions, PhotoSettings,
                             ProjectorSheet, UndistortOptions, run_import, run_patterns, run_undistort)
from .app import command
from .terminal import run_step


def add_projector_options(p: argparse.ArgumentParser) -> None:
    """The projector as a spec sheet gives it: native size, input area, throw ratio, lens shift."""
    add_arguments(p, ProjectorSheet)


def projector_from_args(args: argparse.Namespace) -> Projector:
    return from_arguments(ProjectorSheet, args).projector()


def _configure_patterns(p: argparse.ArgumentParser) -> None:
    add_projector_options(p)
    add_arguments(p, PatternsOptions)
    p.add_argument("--out", type=Path, required=True, help="new folder for the numbered frames")
    p.add_argument("--force", action="store_true", help="replace an existing sequence folder at --out")


@command("patterns", "Export the numbered calibration pattern sequence for your own projection/capture tools "
         "(one sequence per projector when there are several).", _configure_patterns)
def patterns(args: argparse.Namespace) -> int:
    projector = projector_from_args(args)
    w, h = projector.intrinsics.size
    out = run_step("patterns", run_patterns, from_arguments(PatternsOptions, args, projector=projector, out=args.out,
                                                            force=args.force))
    n = len(load_sequence(out).frames)
    print(f"wrote {n} frames ({w}×{h}) and sequence.json to {out}")
    return 0


def add_camera_options(p: argparse.ArgumentParser) -> None:
    """What import-captures and a live capture need beyond the photographs: camera lens, rig file, depth, checks."""
    add_arguments(p, PhotoSettings)
    add_arguments(p, DepthSensorSize)


def depth_native_size(args: argparse.Namespace) -> tuple[int, int] | None:
    return from_arguments(DepthSensorSize, args).size()


def _configure_import(p: argparse.ArgumentParser) -> None:
    p.add_argument("sequence_dir", type=Path, help="folder written by `procam patterns`")
    p.add_argument("captures_dir", type=Path, help="folder of numbered captures (png, jpg, tif, exr), one per frame")
    p.add_argument("--out", type=Path, required=True, help="new capture-set folder")
    add_arguments(p, CameraSize)
    add_arguments(p, ImportOptions, exclude=[d.name for d in declared(PhotoSettings)])
    add_camera_options(p)
    p.add_argument("--force", action="store_true", help="replace an existing capture set at --out")


@command("import-captures", "Import numbered captures of an exported pattern sequence as a capture set "
         "(several projectors: add each further projector's with --add-to SET into a new set).", _configure_import)
def import_photographs(args: argparse.Namespace) -> int:
    camera = from_arguments(CameraSize, args).camera(args.camera_fov)
    cs = run_step("import-captures", run_import, from_arguments(
        ImportOptions, args, sequence_dir=args.sequence_dir, photos_dir=args.captures_dir, out=args.out,
        camera=camera, depth_native_size=depth_native_size(args), force=args.force))
    w, h = cs.camera.intrinsics.size
    print(f"wrote capture set {cs.path}: {len(cs)} images, camera {w}×{h}")
    if args.add_to is not None:
        sizes = ", ".join(f"{k + 1}: {p.intrinsics.width}×{p.intrinsics.height}" for k, p in enumerate(cs.projectors))
        print(f"  {len(cs.projectors)} projectors ({sizes}): {args.add_to}'s captures and projector "
              f"{len(cs.projectors)}'s; {args.add_to} is left as it was")
    if args.rig is not None:
        pose = ("from the rig (use calibrate --init nominal to keep it)" if cs.projector_pose_known
                else "left to calibrate (the rig is in board squares)")
        print(f"  camera and projector from {args.rig}: lens distortion removed from the photographs; "
              f"projector pose {pose}")
    return 0


def _configure_undistort(p: argparse.ArgumentParser) -> None:
    p.add_argument("captures_dir", type=Path, help="a capture set (procam lab, import-captures or capture)")
    add_arguments(p, UndistortOptions)
    p.add_argument("--out", type=Path, required=True, help="new capture-set folder")
    p.add_argument("--force", action="store_true", help="replace an existing capture set at --out")


@command("undistort-captures", "Take the camera lens of a rig calibration out of an existing capture set.",
         _configure_undistort)
def undistort(args: argparse.Namespace) -> int:
    cs = run_step("undistort-captures", run_undistort, from_arguments(
        UndistortOptions, args, captures_dir=args.captures_dir, out=args.out, force=args.force))
    print(f"wrote capture set {cs.path}: {len(cs)} images with the camera's lens from {args.rig} taken out; "
          "calibrate it, and a live camera's frames will go through the same lens")
    return 0
