"""One show frame's work, the same in the process running ``procam show`` and on a cluster's workers.

:func:`compute_frame` reads the target (an image file or a video frame),
runs stage C (warm-started from the previous frame's 16-bit PNG when given),
and returns the frame as the bytes of its 16-bit PNG with its manifest entry.
It writes nothing: the show step is the only writer of the show folder, so a
frame computed on another machine lands there exactly as one computed here.

What carries over is the previous frame's *correction*: frame n starts from
its own usual start (the target over the simulated white, mapped into the
projector) plus frame n−1's answer minus frame n−1's usual start. The
surface's corrections stay where they are in the projector while the content
moves; starting from frame n−1's answer as it is starts from the previous
picture, which on a moving shot is further off than the usual start
(``scripts/bench_video.py``).

Why the warm start reads the previous frame's PNG bytes and not its float z:
those bytes are what the show folder keeps (and verifies by SHA-256), so frame
n starts from exactly the same z whether frame n−1 was computed a moment ago,
on another worker, or in an earlier run and read back from disk — a float z
would have to be stored beside every frame to be resumable, and the 16-bit
quantisation (1/65535) is far below what stage C resolves.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import ImageError, ProCamError
from ..imageio import check_image_bytes
from ..outputs import file_sha256
from ..progress import Cancel, Progress, quiet
from ..stages.display_area import load_target
from ..video import VideoReader, load_video_frame
from .layout import projector_frame_name
from .projectors import JointStage
from .stage_c import StageC


@dataclass(frozen=True)
class FrameJob:
    """One frame to compute: its number, its target (an image, or frame ``index`` of a video), its output name,
    and the frame it is warm-started from (None: a cold start)."""

    number: int
    path: Path
    name: str
    index: int | None = None
    prev: int | None = None
    prev_path: Path | None = None
    prev_index: int | None = None


@dataclass
class FrameOutcome:
    """What :func:`compute_frame` returns: the PNG bytes and manifest entry of a finished frame, or its error."""

    number: int
    png: bytes | None
    entry: dict[str, Any]
    error: str | None = None
    warnings: list[str] = field(default_factory=list)
    areas: dict[str, Any] = field(default_factory=dict)
    #: with several projectors: each projector's PNG bytes, in projector order (``png`` is projector 1's)
    pngs: list[bytes] = field(default_factory=list)


def encode_png16(frame: np.ndarray) -> bytes:
    """The 16-bit RGB PNG of a float frame in [0, 1] (as ``imageio.write_image`` writes it)."""
    img = np.asarray(frame, dtype=np.float32)
    if not np.all(np.isfinite(img)):
        raise ImageError("refusing to write a frame that holds NaN or infinite values")
    data = np.round(np.clip(img, 0.0, 1.0) * 65535.0).astype(np.uint16)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(data[..., ::-1]))
    if not ok:
        raise ImageError("OpenCV could not encode a frame as PNG")
    return buf.tobytes()


def decode_png16(data: bytes) -> np.ndarray:
    """A 16-bit RGB PNG's bytes as float [0, 1] (H×W×3)."""
    check_image_bytes(data, "a frame to warm-start from")
    raw = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.dtype != np.uint16 or raw.ndim != 3:
        raise ImageError("a frame to warm-start from is not a 16-bit RGB PNG")
    return raw[..., 2::-1].astype(np.float32) / 65535.0


_HASHES: dict[tuple[str, int, int], str] = {}


def source_record(path: Path) -> dict[str, Any]:
    """Where a target came from: path, size, modification time and SHA-256 (a video's hashed once per process)."""
    st = path.stat()
    key = (str(path.absolute()), st.st_size, st.st_mtime_ns)
    if key not in _HASHES:
        _HASHES[key] = file_sha256(path)
    return {"source": str(path.absolute()), "source_bytes": st.st_size, "source_mtime_ns": st.st_mtime_ns,
            "source_sha256": _HASHES[key]}


def _load(stage: StageC | JointStage, path: Path, index: int | None, readers: dict[Path, VideoReader]
          ) -> tuple[np.ndarray, str]:
    if index is None:
        return stage.load(path) if isinstance(stage, StageC) else load_target(path,
                                                                              encoding=stage.options.target_encoding)
    reader = readers.get(path) or readers.setdefault(path, VideoReader(path))
    return load_video_frame(reader, index, encoding=stage.options.target_encoding)


def compute_frame(stage: StageC | JointStage, job: FrameJob, start: list[bytes] | None, *, digits: int = 4,
                  readers: dict[Path, VideoReader], progress: Progress | None = None,
                  cancel: Cancel | None = None) -> FrameOutcome:
    """Stage C for one frame (module doc), of one projector (:class:`StageC`) or of every projector of a
    calibration of several at once (:class:`JointStage`, the joint solve). ``start``: the 16-bit PNG bytes of
    frame ``job.prev``, one per projector (None: cold); frame n starts, per projector, from its own usual start
    plus frame n−1's answer minus frame n−1's usual start. ``readers``: open video readers to reuse, by path.
    With several projectors the outcome's ``pngs`` hold each projector's frame (named with ``digits``) and its
    entry lists them under ``projectors`` (projector 1's also under the one-projector keys, as the compensation
    folder of several projectors does). A target that cannot be read or compensated comes back as an outcome
    with its error; cancellation and bugs are raised."""
    say = progress or quiet
    t0 = time.perf_counter()
    joint = isinstance(stage, JointStage)
    try:
        try:
            source = source_record(job.path)
        except OSError as exc:  # vanished or unreadable since the sequence was listed
            raise ImageError(f"cannot read the target {job.path}: {exc.strerror or exc}") from None
        img, note = _load(stage, job.path, job.index, readers)
        if job.index is not None:
            source["video_frame"] = job.index + 1
        z0: Any = None
        if start is not None and job.prev_path is not None:
            before, _ = _load(stage, job.prev_path, job.prev_index, readers)
            if isinstance(stage, JointStage):
                answers = stage.start_from_frames([decode_png16(b) for b in start])
                z0 = [np.clip(now + answer - then, 0.0, 1.0) for now, answer, then in
                      zip(stage.initial_inputs(img), answers, stage.initial_inputs(before))]
            else:
                z0 = np.clip(stage.initial_input(img) + stage.start_from_frame(decode_png16(start[0]))
                             - stage.initial_input(before), 0.0, 1.0)
        done = stage.compensate(img, name=f"frame {job.number}", what=f"target {job.path.name}", cancel=cancel,
                                progress=say, start=z0)
        pngs = [encode_png16(frame) for frame in (done.result.x_frames if joint else [done.frame])]
    except ProCamError as exc:
        return FrameOutcome(job.number, None, {"number": job.number, "source": str(job.path.absolute()),
                                               "status": "failed", "error": str(exc)}, str(exc))
    res = done.result
    warnings = list(done.warnings)
    if job.prev is not None and z0 is None:
        # Its predecessor has no answer (it failed): recorded, so that a rerun which finishes the predecessor
        # redoes this frame from it too, and the folder ends up as a fresh run's.
        warnings.append(f"computed cold: frame {job.prev} has no answer to start from; it is redone when frame "
                        f"{job.prev} is")
    shares = res.report.get("share_of_light") or [None] * len(pngs)
    files = [{"projector": k + 1, "file": projector_frame_name(job.number, digits, k) if joint else job.name,
              "bytes": len(png), "sha256": hashlib.sha256(png).hexdigest(), "share": shares[k]}
             for k, png in enumerate(pngs)]
    entry = {"number": job.number, "file": files[0]["file"], **source, "status": "done",
             "bytes": files[0]["bytes"], "sha256": files[0]["sha256"], **({"projectors": files} if joint else {}),
             "mode": res.mode, "area": done.area.to_dict(), "encoding": note, "warnings": warnings,
             "warm_start": job.prev if z0 is not None else None,
             "warm_start_missing": job.prev if job.prev is not None and z0 is None else None,
             "psnr_model_start": round(res.report["psnr_simulated_start"], 3),
             "psnr_model": round(res.report["psnr_simulated"], 3),
             **({"psnr_model_overlap": res.report.get("psnr_overlap"),
                 "psnr_model_outside": res.report.get("psnr_outside_overlap")} if joint else {}),
             "loss_first": res.losses[0] if res.losses else None,
             "loss_last": res.losses[-1] if res.losses else None, "captures": res.captures,
             "seconds": round(res.seconds, 2), "seconds_total": round(time.perf_counter() - t0, 2)}
    return FrameOutcome(job.number, pngs[0], entry, None, warnings,
                        {k: a.to_dict() for k, a in stage.areas.items()}, pngs if joint else [])
