"""One multi-projector capture set from one capture set per projector, taken with the same camera on one surface.

Each projector's sequence is captured (or imported) on its own while the
others show black; :func:`combine_projector_sets` writes them as one set whose
entries say which projector showed them (``capture/format.py``). What every
projector shares is taken from the first projector's set only: the surface
photo, the depth images and the targets (the surface and depth are taken
once). The sets must agree on the camera (its model and size) and on whether
its lens was taken out; each keeps its own projector.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from ..errors import CaptureError
from ..progress import Progress, quiet
from .format import SHARED_KINDS, CaptureSet, CaptureSetWriter
from .others_black import check_distinct_projectors


def combine_projector_sets(sets: Sequence[CaptureSet], out: str | Path, *, force: bool = False,
                           notes: dict[str, Any] | None = None, inputs: Iterable[str | Path | None] = (),
                           progress: Progress | None = None) -> CaptureSet:
    """A new capture set of ``len(sets)`` projectors: projector ``k``'s captures from ``sets[k]`` (a set of one
    projector each), the shared surface photo, depth and targets from ``sets[0]``. Nothing is written when they
    disagree on the camera, or when two projectors' photographs are the same (:func:`.check_distinct_projectors`)."""
    say = progress or quiet
    if len(sets) < 2:
        raise CaptureError("combining capture sets needs one set per projector, at least two")
    first = sets[0]
    for k, cs in enumerate(sets):
        if cs.others:
            raise CaptureError(f"{cs.path} already holds {len(cs.projectors)} projectors; give one set per projector")
        if k and cs.camera.to_dict() != first.camera.to_dict():
            raise CaptureError(f"projector {k + 1}'s captures ({cs.path}) were taken with another camera (model or "
                               f"size) than projector 1's ({first.path}); capture every projector with the same "
                               "camera and settings")
        if k and cs.camera_lens != first.camera_lens:
            raise CaptureError(f"projector {k + 1}'s captures ({cs.path}) and projector 1's ({first.path}) differ in "
                               "whether the camera's lens was taken out; import them the same way")
    total = sum(len(cs.entries) for cs in sets)
    done = 0
    with CaptureSetWriter(out, first.camera, first.projector, others=[cs.projector for cs in sets[1:]],
                          depth_info=first.depth_info, target_area=first.target_area,
                          camera_status=first.camera_status, projector_status=first.projector_status,
                          projector_pose_known=first.projector_pose_known,
                          notes={**first.notes, **(notes or {})}, camera_lens=first.camera_lens, force=force,
                          inputs=(*(cs.path for cs in sets), *inputs),
                          check=lambda written: check_distinct_projectors(written, where=str(out))) as writer:
        for k, cs in enumerate(sets):
            for e in cs.entries:
                done += 1
                if k and e.kind in SHARED_KINDS:
                    continue  # taken once, from the first projector's set
                say(f"projector {k + 1}: {e.name}", done / max(total, 1))
                # projector k's names carry _pK, as the lab names them, so every projector's files stay apart
                writer.copy(cs, e, name=e.name if k == 0 else f"{e.name}_p{k}",
                            projector_index=0 if e.kind in SHARED_KINDS else k)
    return CaptureSet.load(out, verify_images=False)


__all__ = ["combine_projector_sets"]
