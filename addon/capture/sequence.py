"""The pattern-sequence folder: numbered projector frames to show with one's own tools, and ``sequence.json``.

For users with their own projection and capture tools: :func:`export_sequence`
writes the numbered pattern frames, the user shows and photographs them, and
:mod:`.photos` turns the photographs into a capture set; :func:`load_sequence`
reads a sequence back (every frame file resolved inside its folder).

Several projectors: each projector gets its own sequence, exported for its own size and lens, and
photographed while the others show black. Projector 2…N's sequences say which projector they are for
(``"projector_index": 1`` …, numbered from 0; absent for the first, so a one-projector sequence is written as
before) and leave out the surface photo, which is taken once, with the first projector's sequence.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any


from ..errors import CaptureError, RigError
from ..imageio import write_atomic_bytes, write_image
from ..rig.model import Camera, Projector
from ..outputs import AtomicFolder, holds_manifest
from ..safepaths import inside
from .patterns import calibration_sequence


SEQUENCE_FORMAT = "procam-sequence"
SEQUENCE_VERSION = 1
SEQUENCE_MANIFEST = "sequence.json"



def _is_sequence(path: Path) -> bool:
    return holds_manifest(path, SEQUENCE_MANIFEST, SEQUENCE_FORMAT)


def export_sequence(projector: Projector, out_dir: str | Path, *, checker_size: int | None = None,
                    area: str = "input", seed: int = 0, camera: Camera | None = None, graycode: bool = True,
                    validation: bool = True, layout: str = "procam", projector_index: int = 0,
                    force: bool = False) -> Path:
    """Write the numbered pattern frames (``0000_surface.png`` …) and ``sequence.json`` into a new folder.

    Frames are native projector resolution, 16-bit PNG, raw projector input
    levels (no sRGB transfer: show them without colour management). An
    existing non-empty folder is replaced only with ``force`` and only if it is
    itself an exported sequence. ``projector_index`` above 0: the sequence of that projector of several
    (numbered from 0), recorded in ``sequence.json``, without the surface photo (taken once, with the first's).
    """
    if isinstance(projector_index, bool) or not isinstance(projector_index, int) or projector_index < 0:
        raise CaptureError(f"the projector's index must be a whole number ≥ 0, got {projector_index!r}")
    seq = [spec for spec in calibration_sequence(projector, checker_size, area=area, graycode=graycode,
                                                 validation=validation, seed=seed, layout=layout)
           if projector_index == 0 or not spec.projector_off]
    folder = AtomicFolder(out_dir, force=force, what="pattern sequence", replaceable=_is_sequence, inputs=(),
                          error=CaptureError)
    try:
        frames = []
        for i, spec in enumerate(seq):
            file = f"{i:04d}_{spec.name}.png"
            write_image(folder.tmp / file, spec.image)
            frames.append({"index": i, "file": file, "name": spec.name, "kind": spec.kind, "params": spec.params})
        instructions = [
            "Show each frame full-screen on the projector, at its native resolution, without scaling "
            "or colour management, in the numbered order.",
            "For 'surface' switch the projector off (or cover the lens) and turn the room lights on, evenly: "
            "this photo shows the surface's own colours. Take every other frame in the dark.",
            "Keep camera exposure, white balance and focus fixed for the whole sequence.",
            "Save one photo per frame; name them so that sorting by the number in the name gives the "
            "sequence order (e.g. 0000.png, 0001.png …), then run: "
            "procam import-captures SEQUENCE CAPTURES --out SET"]
        if projector_index:
            number = projector_index + 1
            instructions = [
                f"This is projector {number}'s sequence. Show each frame full-screen on projector {number}, at its "
                "native resolution, without scaling or colour management, in the numbered order, while every other "
                "projector shows black. Take every frame in the dark.",
                "Use the camera of the other projectors' sequences, unmoved, with the same exposure, white balance "
                "and focus.",
                "Save one photo per frame, numbered in the sequence order, then add them to the capture set of "
                f"projectors 1 to {number - 1}: procam import-captures SEQUENCE CAPTURES --add-to SET --out NEW_SET"]
        doc = {"format": SEQUENCE_FORMAT, "version": SEQUENCE_VERSION,
               "projector": projector.to_dict(), "camera": camera.to_dict() if camera else None,
               **({"projector_index": projector_index} if projector_index else {}),
               "area": area, "seed": int(seed), "count": len(frames),
               "encoding": "raw projector input levels in [0, 1], 16-bit PNG, no sRGB transfer",
               "instructions": instructions, "frames": frames}
        write_atomic_bytes(folder.tmp / SEQUENCE_MANIFEST, (json.dumps(doc, indent=1) + "\n").encode())
    except BaseException:
        folder.abort()
        raise
    return folder.commit()


@dataclass(frozen=True)
class SequenceInfo:
    """An exported pattern sequence as read back from ``sequence.json``."""

    path: Path
    projector: Projector
    camera: Camera | None
    frames: list[dict[str, Any]]
    #: which projector of several the sequence is for (0 = the first, or a one-projector sequence)
    projector_index: int = 0


def load_sequence(sequence_dir: str | Path) -> SequenceInfo:
    root = Path(sequence_dir)
    manifest = root / SEQUENCE_MANIFEST
    if not manifest.is_file():
        raise CaptureError(f"{root} is not an exported pattern sequence: {SEQUENCE_MANIFEST} is missing "
                           "(create one with `procam patterns`)")
    try:
        doc = json.loads(manifest.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CaptureError(f"cannot read {manifest}: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != SEQUENCE_FORMAT:
        raise CaptureError(f"{manifest} is not a ProCam pattern sequence")
    if doc.get("version") != SEQUENCE_VERSION:
        raise CaptureError(f"{manifest}: sequence version {doc.get('version')!r} is not supported")
    try:
        projector = Projector.from_dict(doc["projector"])
        camera = Camera.from_dict(doc["camera"]) if doc.get("camera") else None
    except (KeyError, TypeError, ValueError, RigError) as exc:
        raise CaptureError(f"{manifest}: invalid projector or camera model: {exc}") from None
    index = doc.get("projector_index", 0)
    if isinstance(index, bool) or not isinstance(index, int) or index < 0:
        raise CaptureError(f"{manifest}: projector_index must be a whole number ≥ 0 (0 = the first projector), got "
                           f"{index!r}; export the sequence again with `procam patterns`")
    frames = doc.get("frames")
    if not isinstance(frames, list) or not frames:
        raise CaptureError(f"{manifest}: no frames listed")
    for i, f in enumerate(frames):
        if not isinstance(f, dict) or not all(isinstance(f.get(k), str) for k in ("file", "name", "kind")):
            raise CaptureError(f"{manifest}: frame {i} needs file, name and kind, as text; export the sequence "
                               "again with `procam patterns`")
        # A frame is a file of the sequence: a name leading out of it would be copied into the capture set.
        inside(root, f["file"], what=f"{manifest.name}: frame {i}", error=CaptureError)
        if not isinstance(f.get("params") or {}, dict):
            raise CaptureError(f"{manifest}: frame {i}'s params must be an object, not {f['params']!r}; export the "
                               "sequence again with `procam patterns`")
    return SequenceInfo(root, projector, camera, frames, index)


def sequence_frame(seq: SequenceInfo, frame: dict[str, Any]) -> Path:
    """The file of one of ``seq``'s frames, inside the sequence folder."""
    return inside(seq.path, frame["file"], what="pattern frame", error=CaptureError)
