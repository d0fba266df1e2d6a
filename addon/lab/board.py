"""A printed chessboard in the virtual lab: the board sessions ``procam calibrate-rig`` reads, with known truth.

A rig calibration photographs a flat chessboard in several poses, each under
the projector's Gray code (over the whole native frame), then white, then
black: OpenCV's structured-light layout, the one of
``realdata/kamino410-procam-calibration``. The lab renders the same with
Cycles and its effects (camera lens distortion included), one folder per
pose, so that the calibration can be measured against the rig it came from
(the truth is sealed in a file beside the sessions, never inside them).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..capture.patterns import gray_code_patterns, white
from ..errors import LabError
from ..imageio import write_atomic_bytes, write_image
from ..outputs import AtomicFolder, check_file_replaceable, holds_manifest
from ..progress import Cancel, Progress, check, quiet
from ..rig.model import Rig
from ..surface.mesh import SurfaceMesh
from .effects import lens_of, parse_effects
from .truth import make_truth

BOARD_TRUTH_FORMAT = "procam-lab-board-truth"
#: The board's albedo: white paper and printed black (not 0: ink reflects a little).
PAPER, INK = 0.85, 0.04


def board_mesh(board: tuple[int, int], square: float, camera_from_board: np.ndarray, *,
               texels_per_square: int = 24) -> SurfaceMesh:
    """A flat chessboard with ``board`` inner corners (per row, rows), squares of ``square`` metres and a white
    margin of one square, placed by ``camera_from_board`` (board frame: x along a row, y down the columns, z into
    the board; inner corner (i, j) at (i·square, j·square, 0), as OpenCV's object points)."""
    cols, rows = board
    if cols < 2 or rows < 2 or not square > 0:
        raise LabError(f"a chessboard needs at least 2×2 inner corners and a positive square, got {board}, {square}")
    # Squares span [-1, cols] × [-1, rows] (in squares); the white margin one more on each side.
    x0, x1, y0, y1 = -2, cols + 1, -2, rows + 1
    corners = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], np.float64) * square
    pose = np.asarray(camera_from_board, np.float64)
    verts = corners @ pose[:3, :3].T + pose[:3, 3]
    uvs = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float64)  # v up: the texture's first row is the top
    faces = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    n = texels_per_square
    ys, xs = np.mgrid[0:(y1 - y0) * n, 0:(x1 - x0) * n]
    sx, sy = np.floor(xs / n).astype(int) + x0, np.floor(ys / n).astype(int) + y0
    inside = (sx >= -1) & (sx < cols) & (sy >= -1) & (sy < rows)
    dark = inside & ((sx + sy) % 2 == 0)
    albedo = np.repeat(np.where(dark, INK, PAPER).astype(np.float32)[..., None], 3, axis=2)
    mesh = SurfaceMesh(verts, faces, uvs, albedo, name="board")
    if np.mean(mesh.face_normals() @ -pose[:3, 3]) < 0:  # face the camera
        mesh = SurfaceMesh(verts, faces[:, ::-1].copy(), uvs, albedo, name="board")
    return mesh


def _rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = (math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz))
    return (np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]]) @ np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
            @ np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]]))


def board_poses(count: int, board: tuple[int, int], square: float, *, centre: tuple[float, float, float] =
                (0.0, 0.0, 1.5), seed: int = 0) -> list[np.ndarray]:
    """``count`` camera_from_board poses around ``centre`` with the tilts a person gives a board (±25° about x and
    y, ±10° about z, ±15 cm in depth): varied enough to separate focal length, principal point and distortion."""
    if count < 3:
        raise LabError(f"a rig calibration needs at least 3 board poses, got {count}")
    rng = np.random.default_rng(seed)
    half = np.array([(board[0] - 1) / 2, (board[1] - 1) / 2, 0.0]) * square  # board centre in its frame
    poses = []
    for k in range(count):
        # Alternate the sign of the main tilts so that the poses are spread, not random-walk clustered.
        rx = math.radians((1 if k % 2 else -1) * rng.uniform(10, 25))
        ry = math.radians((1 if (k // 2) % 2 else -1) * rng.uniform(10, 25))
        r = _rotation(rx, ry, math.radians(rng.uniform(-10, 10)))
        c = np.asarray(centre) + np.array([rng.uniform(-0.08, 0.08), rng.uniform(-0.06, 0.06),
                                           rng.uniform(-0.15, 0.15)])
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = r, c - r @ half
        poses.append(pose)
    return poses


@dataclass(frozen=True)
class BoardTruth:
    """What the board sessions were rendered from: the rig, the board and its poses."""

    rig: Rig
    board: tuple[int, int]
    square: float
    poses: tuple[np.ndarray, ...]
    effects: str

    def save(self, path: Path) -> None:
        doc = {"format": BOARD_TRUTH_FORMAT, "version": 1,
               "warning": "sealed lab truth: only evaluation code may read this file",
               "rig": self.rig.to_dict(), "board": list(self.board), "square": self.square,
               "camera_from_board": [p.tolist() for p in self.poses], "effects": self.effects}
        write_atomic_bytes(path, (json.dumps(doc, indent=1) + "\n").encode())

    @staticmethod
    def load(path: Path) -> BoardTruth:
        try:
            doc = json.loads(Path(path).read_text())
            return BoardTruth(Rig.from_dict(doc["rig"]), tuple(doc["board"]), float(doc["square"]),
                              tuple(np.asarray(p, float) for p in doc["camera_from_board"]), doc["effects"])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise LabError(f"cannot read the board sessions' truth {path}: {exc}") from None


def default_supersample(effects: str) -> int:
    """2 when ``effects`` distort the camera's lens (its resampling needs finer pixels, ``apply_camera``), else 1."""
    return 2 if lens_of(parse_effects(effects)) is not None else 1


def is_board_truth(path: Path) -> bool:
    """Whether ``path`` is a board truth file ProCam wrote (its format tag), which ``force`` may replace."""
    return holds_manifest(Path(path).parent, Path(path).name, BOARD_TRUTH_FORMAT)


def is_board_sessions(path: Path) -> bool:
    """Whether ``path`` holds board sessions as :func:`render_board_sessions` writes them, and nothing else: these
    folders have no manifest, so only ``pose_NN`` folders of ``graycode_NN.png`` files may be replaced."""
    sessions = list(Path(path).iterdir())
    return bool(sessions) and all(
        s.is_dir() and not s.is_symlink() and re.fullmatch(r"pose_\d{2,}", s.name)
        and all(f.is_file() and re.fullmatch(r"graycode_\d{2,}\.png", f.name) for f in s.iterdir())
        for s in sessions)


def render_board_sessions(rig: Rig, out: Path, *, board: tuple[int, int] = (9, 7), square: float = 0.06,
                          poses: int = 6, effects: str = "", samples: int = 16, seed: int = 0,
                          truth_path: Path | None = None, force: bool = False, supersample: int = 1,
                          inputs: Iterable[str | Path | None] = (), progress: Progress | None = None,
                          cancel: Cancel | None = None) -> BoardTruth:
    """Render one session folder per board pose into ``out`` (``pose_00/graycode_00.png`` …, Gray code for the
    projector's native frame in OpenCV's order, then white, then black) and seal the truth at ``truth_path``
    (default: beside ``out``). The folder is written atomically. ``supersample`` renders the camera finer and
    averages down (:func:`.effects.apply_camera`). Nothing is written into ``inputs`` (the folders the truth must
    not land in); an existing truth file is replaced only with ``force`` and only when it is one of ours."""
    say = progress or quiet
    truth_path = Path(truth_path) if truth_path else Path(out).with_name(Path(out).name + ".truth.json")
    size = rig.projector.intrinsics.size
    frames = [img for *_, img in gray_code_patterns(size)] + [white(size), np.zeros((size[1], size[0], 3), np.float32)]
    placed = board_poses(poses, board, square, centre=(0.0, 0.0, 1.5), seed=seed)
    truth = BoardTruth(rig, tuple(board), float(square), tuple(placed), effects)
    check_file_replaceable(truth_path, force=force, what="ProCam board truth file", replaceable=is_board_truth,
                           inputs=(out, *inputs), error=LabError)
    folder = AtomicFolder(out, force=force, what="board sessions", error=LabError, replaceable=is_board_sessions,
                          inputs=(truth_path,))
    try:
        for k, pose in enumerate(placed):
            lab = make_truth(board_mesh(board, square, pose), rig=rig, effects=effects, samples=samples,
                             seed=seed + k, surface_source=f"chessboard {board[0]}x{board[1]}, pose {k}")
            session = folder.tmp / f"pose_{k:02d}"
            session.mkdir()
            from .cycles_device import LabDevice  # bpy: the lab's renders

            with LabDevice(lab, supersample=supersample) as device:
                for i, frame in enumerate(frames):
                    check(cancel, "rendering the board sessions")
                    say(f"pose {k + 1}/{poses}: frame {i + 1}/{len(frames)}", (k * len(frames) + i) /
                        (poses * len(frames)))
                    write_image(session / f"graycode_{i:02d}.png", device.project(frame))
        truth.save(truth_path)
    except BaseException:
        folder.abort()
        raise
    folder.commit()
    say("done", 1.0)
    return truth
