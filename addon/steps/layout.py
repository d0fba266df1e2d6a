"""Every step folder's manifest name, format tag and version, and the files each step writes: one place to look.

A folder is recognised by its manifest; a reader checks the format tag and
version before trusting anything else in it. Capture sets (``capture.json``)
and exported pattern sequences (``sequence.json``) are defined with their
format in :mod:`..capture.format` and :mod:`..capture.sequence`, which the lab
and the import share; they are listed here too so that this page names every
folder ProCam writes.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..capture import sequence as sequence_format
from ..capture import format as capture_format
from ..errors import ProCamError
from ..outputs import holds_manifest


@dataclass(frozen=True)
class FolderKind:
    """One kind of step folder: the manifest that marks it and its format tag and version."""

    what: str  # in messages: "calibration folder"
    manifest: str
    format: str
    version: int = 1
    made_by: str = ""  # the command that writes it, for messages that say what to run

    def read(self, folder: str | Path, error: type[ProCamError] = ProCamError) -> dict[str, Any]:
        """The folder's manifest document, checked for this kind's format; ``error`` says what is wrong."""
        path = Path(folder) / self.manifest
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise error(f"{folder} is not a {self.what} ({exc}); give the folder {self.made_by} wrote") from None
        if not isinstance(doc, dict) or doc.get("format") != self.format:
            raise error(f"{path} is not a ProCam {self.what} manifest; give the folder {self.made_by} wrote")
        return doc

    def holds(self, path: str | Path) -> bool:
        """Whether ``path`` (a folder) holds this kind's manifest with its format tag: what ``force`` may replace."""
        return holds_manifest(path, self.manifest, self.format)

    def incomplete(self, path: str | Path) -> bool:
        """Whether ``path`` holds this kind's manifest marked ``"complete": false``: what a failed or cancelled run
        left, which the next run replaces without ``force`` (a failed run never blocks its own retry)."""
        try:
            doc = json.loads((Path(path) / self.manifest).read_text())
        except (OSError, ValueError, UnicodeDecodeError):
            return False
        return isinstance(doc, dict) and doc.get("format") == self.format and doc.get("complete") is False


CAPTURES = FolderKind("capture set", capture_format.MANIFEST, capture_format.FORMAT, capture_format.VERSION,
                      "procam lab / procam import-captures")
PATTERNS = FolderKind("pattern sequence", sequence_format.SEQUENCE_MANIFEST, sequence_format.SEQUENCE_FORMAT,
                      sequence_format.SEQUENCE_VERSION, "procam patterns")
CALIBRATION = FolderKind("calibration folder", "calibration.json", "procam-calibration", 1, "procam calibrate")
COMPENSATION = FolderKind("compensation folder", "compensation.json", "procam-compensation", 1, "procam compensate")
SHOW = FolderKind("show folder", "show.json", "procam-show", 1, "procam show")
EVALUATION = FolderKind("evaluation folder", "metrics.json", "procam-evaluation", 1, "procam evaluate")
DIAGNOSIS = FolderKind("diagnosis folder", "gap.json", "procam-gap", 1, "procam diagnose")
FRAMES = FolderKind("projector frame sequence", "frames.json", "procam-frames", 1, "procam export-frames")
DEMO = FolderKind("demo folder", "summary.json", "procam-demo", 1, "procam demo")
#: every kind of step folder
FOLDER_KINDS = (CAPTURES, PATTERNS, CALIBRATION, COMPENSATION, SHOW, EVALUATION, DIAGNOSIS, FRAMES, DEMO)


def step_folders_around(path: str | Path) -> tuple[Path, ...]:
    """The folders holding ``path`` that are step folders ProCam made: a file of another step must not land there."""
    p = Path(os.path.abspath(path))
    return tuple(d for d in p.parents if any(k.holds(d) for k in FOLDER_KINDS))


#: not a folder: one JSON file (its default name); camera and projector intrinsics and their relative pose.
RIG = FolderKind("rig calibration", "rig.json", "procam-rig", 1, "procam calibrate-rig")

# -- the files inside ------------------------------------------------------------------------------

#: calibration: the mesh (rig frame) and its texture, the same mesh for other tools, diagnostics, the scene.
SURFACE_NPZ, SURFACE_OBJ, SURFACE_MTL, ALBEDO_PNG = "surface.npz", "surface.obj", "surface.mtl", "albedo.png"
DIAGNOSTICS_DIR = "diagnostics"
#: the light-transport operator of a calibration (stages/transport.py) and its record, in the calibration folder
TRANSPORT_NPZ, TRANSPORT_JSON = "transport.npz", "transport.json"


def transport_files(k: int = 0) -> tuple[str, str]:
    """The light-transport operator of projector ``k`` (0 = the first) and its record: ``transport.npz`` and
    ``transport.json`` for the first (the one-projector names), ``transport_p2.npz`` … for the others."""
    if k == 0:
        return TRANSPORT_NPZ, TRANSPORT_JSON
    return f"transport_p{k + 1}.npz", f"transport_p{k + 1}.json"


def inverse_files(k: int = 0) -> tuple[str, str]:
    """The approximate inverse of projector ``k``'s operator (stages/realtime.py) and its record, beside the
    operator: ``inverse.npz`` and ``inverse.json`` for the first, ``inverse_p2.npz`` … for the others."""
    return tuple(name.replace("transport", "inverse", 1) for name in transport_files(k))  # type: ignore[return-value]


SCENE_BLEND = "scene.blend"

#: compensation, per target NAME.
TARGET_FILES = {"input": "{name}_input.png", "frame": "{name}_frame.png", "simulated": "{name}_simulated.png",
                "target": "{name}_target.png"}

#: show: numbered frames and θ estimated once for the open loop.
FRAME_PREFIX = "frame_"
OPEN_LOOP_BIAS = "open_loop_bias.npz"

#: evaluation, per target NAME.
EVALUATION_FILES = {"image": "{name}_comparison.png", "capture": "{name}_capture.png",
                    "uncompensated": "{name}_uncompensated_capture.png", "classical": "{name}_classical_input.png"}

#: diagnosis.
DIAGNOSIS_SUMMARY = "summary.md"


def projector_record(projector: Any) -> dict[str, list[int]]:
    """What a compensation or show records of a projector its inputs are for, and evaluation checks: its native
    frame size, and the size and offset of its input inside that frame."""
    return {"frame_size": list(projector.intrinsics.size), "input_size": list(projector.input_size),
            "input_offset": list(projector.input_offset)}


def frame_name(number: int, digits: int = 4) -> str:
    """The file of projector frame ``number`` (``frame_0001.png``): zero-padded as media servers expect."""
    return f"{FRAME_PREFIX}{number:0{digits}d}.png"


#: with several projectors, each projector's sequence lies in its own folder (K from 1)
PROJECTOR_FOLDER = "projector_{k}"


def projector_frame_name(number: int, digits: int, projector: int) -> str:
    """The file of frame ``number`` of projector index ``projector`` (from 0) in a sequence of several projectors:
    ``projector_1/frame_0001.png``, each folder numbered as one projector's sequence is."""
    return f"{PROJECTOR_FOLDER.format(k=projector + 1)}/{frame_name(number, digits)}"


def correction_file(name: str) -> str:
    """Where ``procam compensate`` puts the measured closed loop's correction of target ``name`` (|θ|, float EXR)."""
    return f"{name}_correction.exr"


def target_files(name: str) -> dict[str, str]:
    """The files ``procam compensate`` writes for the target ``name``."""
    return {k: v.format(name=name) for k, v in TARGET_FILES.items()}
