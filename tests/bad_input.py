"""The machinery of the bad-input property suite (``tests/test_bad_input.py``, ``scripts/bench_bad_input.py``).

A *world* of small, valid folders of every kind ProCam reads is made once
(pattern sequence and photographs, a depth map, a rig file, a capture set, a
lab capture set with its calibration, a compensation, a show, a diagnosis,
target images and a video). Each generated case copies the folders one command
needs into the same example folder (the same absolute path every time, so the
absolute paths and hashes the manifests record stay true), damages one thing at
random, runs the command that reads it through the CLI's :func:`main` in this
process, and checks the promises of issue 37:

- the exit code is 0 or 2 (1 is a bug; 130 or a run past :data:`CASE_SECONDS` is a hang);
- no file is opened (Python's ``open`` audit event; OpenCV's ``imread`` and ``VideoCapture``, which open files in
  C, are wrapped to raise the same event) whose real path lies outside :func:`allowed_roots`;
- no file of the inputs is deleted or changed (hashes before and after; in a show folder that is resumed only the
  files ProCam writes there may change), and the files of a user folder next to the example, which no command is
  given, are all still there.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import shutil
import signal
import site
import sys
import sysconfig
import tempfile
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
#: One case longer than this is a hang. The slowest valid case (a show of a two-frame video) takes about 3 s.
CASE_SECONDS = 30

# -- the audit hook ------------------------------------------------------------------------------------------

_OPENED: list[str] | None = None  # the paths opened while a case runs; None: not recording


def _audit(event: str, args: tuple) -> None:
    if _OPENED is None:
        return
    if event in ("open", "os.listdir", "os.scandir") and args and isinstance(args[0], (str, bytes, os.PathLike)):
        _OPENED.append(os.fsdecode(args[0]))


_HOOKED = False


def install_audit() -> None:
    """Install the audit hook (once per process: hooks cannot be removed) and make OpenCV's file readers, which
    open files in C where no audit event is raised, raise the ``open`` event first."""
    global _HOOKED
    if _HOOKED:
        return
    sys.addaudithook(_audit)
    import cv2

    imread, capture = cv2.imread, cv2.VideoCapture

    def audited_imread(path, *args, **kwargs):
        sys.audit("open", path, "r", 0)
        return imread(path, *args, **kwargs)

    def audited_capture(source=None, *args, **kwargs):
        if isinstance(source, (str, os.PathLike)):
            sys.audit("open", source, "r", 0)
        return capture() if source is None else capture(source, *args, **kwargs)

    cv2.imread, cv2.VideoCapture = audited_imread, audited_capture
    try:  # meshes (a calibration's --surface-mesh) are read by MeshLab, in C++
        import pymeshlab

        load = pymeshlab.MeshSet.load_new_mesh

        def audited_load(self, path, *args, **kwargs):
            sys.audit("open", path, "r", 0)
            return load(self, path, *args, **kwargs)

        pymeshlab.MeshSet.load_new_mesh = audited_load
    except (ImportError, TypeError, AttributeError):
        pass
    _HOOKED = True


def allowed_roots(example: Path, logs: Path) -> list[Path]:
    """Where a command may open files: the example folder (its inputs, its outputs, the folder given as ``--out``),
    the crash-log folder the CLI is pointed at, ProCam's own code, the Python installation and its packages, and
    the kernel's pseudo-file systems (CPU count, memory, ``/dev/null``, ``/dev/urandom``)."""
    roots = {example, logs, REPO, Path(sys.prefix), Path(sys.base_prefix), Path(sys.exec_prefix),
             Path("/proc"), Path("/sys"), Path("/dev")}
    for key in ("stdlib", "platstdlib", "purelib", "platlib"):
        roots.add(Path(sysconfig.get_paths()[key]))
    roots.update(Path(p) for p in site.getsitepackages())
    roots.update(Path(p) for p in sys.path if p and Path(p).is_dir() and Path(p) != Path("/"))
    return sorted({Path(os.path.realpath(r)) for r in roots})


#: Scratch folders ProCam makes for itself (``tempfile.mkdtemp``) in the temporary folder: the lab's Cycles renders.
SCRATCH_PREFIXES = ("procam-cycles-",)


def _scratch(real: Path) -> bool:
    tmp = Path(os.path.realpath(tempfile.gettempdir()))
    return tmp in real.parents and real.relative_to(tmp).parts[0].startswith(SCRATCH_PREFIXES)


def escapes(opened: list[str], roots: list[Path], cwd: Path) -> list[str]:
    """The opened paths whose real path (every symlink followed) lies outside every root and is not one of ProCam's
    own scratch folders."""
    out = []
    for name in dict.fromkeys(opened):
        real = Path(os.path.realpath(cwd / name))
        if not any(real == r or r in real.parents for r in roots) and not _scratch(real):
            out.append(f"{name} -> {real}" if str(real) != name else name)
    return out


# -- files ---------------------------------------------------------------------------------------------------

def snapshot(root: Path) -> dict[str, str]:
    """Every file and link under ``root`` (links not followed): relative name → content hash or link target."""
    out: dict[str, str] = {}
    if not root.exists() and not root.is_symlink():
        return out
    if root.is_symlink():
        return {".": "link:" + os.readlink(root)}
    for folder, dirs, files in os.walk(root, followlinks=False):
        for name in dirs + files:
            p = Path(folder) / name
            rel = str(p.relative_to(root))
            if p.is_symlink():
                out[rel] = "link:" + os.readlink(p)
            elif p.is_file():
                out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def lost(before: dict[str, str], after: dict[str, str],
         may_change: Callable[[str], bool] = lambda n: False) -> list[str]:
    """Files of ``before`` that are gone or changed in ``after``, except those ``may_change`` allows."""
    return [f"{n} ({'deleted' if n not in after else 'changed'})" for n, h in before.items()
            if after.get(n) != h and not may_change(n)]


# -- the world: small valid folders, made once ---------------------------------------------------------------

def _png(path: Path, w: int, h: int, seed: int = 0) -> Path:
    from procam.addon.imageio import write_image

    rng = np.random.default_rng(seed)
    write_image(path, rng.uniform(0.05, 0.6, (h, w, 3)).astype(np.float32))
    return path


def _video(path: Path, n: int) -> Path:
    """A small MJPG .avi (OpenCV's own writer) of a moving pattern."""
    import cv2

    from procam.addon.capture.patterns import smooth_random

    base = smooth_random((80, 48), 0, 20.0)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 24, (64, 48))
    for i in range(n):
        img = (0.1 + 0.6 * base[:, 4 * i:4 * i + 64]) * 255
        writer.write(np.round(np.repeat(img[..., None], 3, 2)).astype(np.uint8))
    writer.release()
    return path


def make_world(root: Path) -> None:
    """Write every input folder under ``root/world/w``, about 7 s on 2 cores.

    They are made in ``root/example/w``, where every case runs, and moved: the absolute paths their manifests
    record (a calibration's capture set, a compensation's calibration) then hold in every case's copy."""
    from procam.addon.capture.sequence import export_sequence
    from procam.addon.capture.photos import import_captures
    from procam.addon.cli.app import main
    from procam.addon.lab.truth import LabTruth, make_truth
    from procam.addon.lab.lab import run_lab
    from procam.addon.stages.calibrate import Calibration
    from procam.addon.stages.warp import Warp
    from procam.addon.steps import calibrate as calibrate_step
    from tests import test_capture as tc

    w = root / "example" / "w"
    w.mkdir(parents=True)
    # Imported photographs: sequence, photos, depth, rig file, and the capture set imported from them.
    seq = export_sequence(tc.small_projector(), w / "seq", checker_size=10, graycode=False)
    tc.shoot_folder(seq, w / "photos")
    np.save(w / "depth.npy", np.full((tc.CAM[1], tc.CAM[0]), 1.7, np.float32))
    tc._rig_file(w / "rig.json", tc.CAM, tc.FRAME, [-0.2, 0.05, 0.0, 0.0, 0.0])
    import_captures(seq, w / "photos", None, None, w / "set", depth_path=w / "depth.npy")
    # A lab capture set (64×48 camera, 80×60 projector), its calibration from the truth, and every later step.
    truth = make_truth("plane", effects="", seed=0, samples=2, camera_size=(64, 48), projector_size=(80, 60))
    run_lab(truth, w / "captures", truth_path=w / "truth.json", graycode=True)
    truth = LabTruth.load(w / "truth.json")
    cal = Calibration(truth.rig, truth.surface, Warp.identity(truth.rig.projector.input_size), str(w / "captures"))
    (w / "cal").mkdir()
    calibrate_step.write(w / "cal", cal, {})
    (w / "frames").mkdir()
    for n in (1, 2):
        _png(w / "frames" / f"shot_{n:04d}.png", 64, 48, seed=n)
    _video(w / "clip.avi", 2)
    quiet = contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO())
    with quiet[0], quiet[1]:
        runs = [["compensate", str(w / "cal"), str(w / "frames" / "shot_0001.png"), "--out", str(w / "comp"),
                 *FAST_C],
                ["show", str(w / "cal"), str(w / "frames"), "--out", str(w / "show"), *FAST],
                ["diagnose", str(w / "cal"), "--out", str(w / "gap"), "--effects", "black_level,response", "--scale",
                 "1", "--spp", "2", "--max-effects", "1"]]
        for argv in runs:
            if main(argv) != 0:
                raise RuntimeError(f"the world's folder could not be made: procam {' '.join(argv)}")
    # What a case may point outside with: valid files and folders, so that following a link or a path succeeds
    # (and is seen) rather than failing for another reason.
    outside = root / "outside"
    outside.mkdir()
    _png(outside / "secret.png", 64, 48, seed=7)
    np.save(outside / "secret.npy", np.full((48, 64), 1.5, np.float32))
    shutil.copytree(w / "set" / "images", outside / "images")
    shutil.copytree(w / "cal", outside / "cal")
    shutil.copy(w / "rig.json", outside / "rig.json")
    (outside / "secret.txt").write_text("not for ProCam\n")
    # A user's folder next to the example that no command is given: it must stay as it is.
    user = root / "user"
    user.mkdir()
    (user / "precious.txt").write_text("the user's own file\n")
    _png(user / "frame_0001.png", 8, 8)
    (user / "show.json").write_text('{"format": "procam-show", "version": 1}')
    (root / "example").rename(root / "world")


#: stage C at its smallest: what the world's compensation and show were made with (a resumed show must match).
FAST = ["--iterations", "2", "--spp", "1", "--no-bias"]
FAST_C = ["--schedule", "fast", "--iterations", "2", "--spp", "1"]


# -- mutations -----------------------------------------------------------------------------------------------

#: JSON values that a manifest's field may hold instead of the right one.
ODD_VALUES: list[Any] = [None, True, -1, 0, 128.9, 1e308, -1e308, math.nan, math.inf, 10 ** 30, "", "x", "NaN",
                         [], {}, [1, 2, 3], {"a": 1}, "\x00", "é" * 3]


FILE_SUFFIXES = (".png", ".npy", ".npz", ".exr", ".json", ".obj", ".avi", ".mp4", ".jpg", ".txt")


def json_paths(doc: Any, prefix: tuple = (), depth: int = 0) -> Iterator[tuple]:
    """Key paths into a JSON document (the first two items of a list stand for all of them)."""
    if depth > 6:
        return
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield prefix + (k,)
            yield from json_paths(v, prefix + (k,), depth + 1)
    elif isinstance(doc, list):
        for i, v in enumerate(doc[:2]):
            yield prefix + (i,)
            yield from json_paths(v, prefix + (i,), depth + 1)


def _get(doc: Any, path: tuple) -> Any:
    for k in path:
        doc = doc[k]
    return doc


def _set(doc: Any, path: tuple, value: Any) -> None:
    _get(doc, path[:-1])[path[-1]] = value


@dataclass
class Case:
    """One generated case: where it runs and what was done to it (its description reproduces it)."""

    root: Path  # the session's folder: world/, example/, outside/, user/, logs/
    did: list[str] = field(default_factory=list)

    @property
    def example(self) -> Path:
        return self.root / "example"

    @property
    def w(self) -> Path:
        return self.example / "w"

    @property
    def outside(self) -> Path:
        return self.root / "outside"


def escape_names(case: Case, folder: Path, what: str) -> list[str]:
    """File names that leave ``folder``: absolute, climbing out, and a link inside it that points outside."""
    target = case.outside / what
    link = folder / f"link_{what}"
    if not link.is_symlink():
        link.symlink_to(target)
    return [str(target), os.path.relpath(target, folder), f"link_{what}", "../" * 12 + "etc/passwd", "/etc/passwd"]


def mutate_json(case: Case, draw: Callable, path: Path) -> None:
    """Damage one manifest: a key deleted, a value of another type or size, a file name leaving the folder, the
    format tag or version changed, or the text itself cut or replaced."""
    # File names are what lets a manifest reach outside its folder: twice as likely as the other damages.
    kind = draw(_st().sampled_from(["delete", "retype", "path", "path", "format", "text"]))
    text = path.read_text()
    if kind == "text":
        how = draw(_st().sampled_from(["cut", "empty", "list", "null", "bytes"]))
        if how == "cut":
            n = draw(_st().integers(0, max(0, len(text) - 1)))
            path.write_text(text[:n])
        else:
            path.write_bytes({"empty": b"", "list": b"[]", "null": b"null", "bytes": b"\xff\xfe{\x00"}[how])
        case.did.append(f"{path.name}: text {how}")
        return
    doc = json.loads(text)
    if kind == "format":
        key = draw(_st().sampled_from(["format", "version"]))
        value = draw(_st().sampled_from(["procam-other", 2, 999, None, "1", 1.5] if key == "version" else
                                        ["procam-other", "procam-capture", "procam-show", None, 1]))
        doc[key] = value
        case.did.append(f"{path.name}: {key} = {value!r}")
    else:
        paths = list(json_paths(doc))
        if kind == "path":
            strings = [p for p in paths if isinstance(_get(doc, p), str)]
            names = [p for p in strings if "/" in _get(doc, p) or Path(_get(doc, p)).suffix in FILE_SUFFIXES]
            paths = names or strings or paths
        where = draw(_st().sampled_from(paths))
        if kind == "delete":
            del _get(doc, where[:-1])[where[-1]]
            case.did.append(f"{path.name}: del {where}")
        elif kind == "retype":
            value = draw(_st().sampled_from(ODD_VALUES))
            _set(doc, where, value)
            case.did.append(f"{path.name}: {where} = {value!r}")
        else:
            old = _get(doc, where)
            what = "secret.png"
            if isinstance(old, str) and ("/" in old or os.sep in old) and not Path(old).suffix:
                what = draw(_st().sampled_from(["images", "cal"]))
            elif isinstance(old, str) and Path(old).suffix in (".json", ".npy", ".txt"):
                what = {".json": "rig.json", ".npy": "secret.npy", ".txt": "secret.txt"}[Path(old).suffix]
            value = draw(_st().sampled_from(escape_names(case, path.parent, what)))
            _set(doc, where, value)
            case.did.append(f"{path.name}: {where} = {value!r} (was {str(old)[:60]!r})")
    path.write_text(json.dumps(doc, indent=1))


def _crafted_png(width: int, height: int) -> bytes:
    """A PNG whose header declares ``width``×``height`` with almost no pixel data (a decompression bomb's shape)."""
    import struct
    import zlib

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\x00" * 64)) + \
        chunk(b"IEND", b"")


def _crafted_npy(shape: tuple[int, ...]) -> bytes:
    header = f"{{'descr': '<f4', 'fortran_order': False, 'shape': {shape!r}, }}"
    header += " " * (118 - len(header)) + "\n"
    return b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode() + b"\x00" * 64


def mutate_file(case: Case, draw: Callable, path: Path, *, links: bool = True) -> None:
    """Damage one image, depth map or video: cut, bytes flipped, deleted, another size or shape, a header that
    declares a huge size, or (``links``: a file a manifest names, not one the user gives) a link to a file outside
    the folder."""
    data = path.read_bytes()
    suffix = path.suffix.lower()
    kinds = ["truncate", "flip", "delete", "other"] + (["link"] if links else [])
    if suffix in (".png", ".npy"):
        kinds.append("huge")
    kind = draw(_st().sampled_from(kinds))
    if kind == "truncate":
        n = draw(_st().integers(0, max(0, len(data) - 1)))
        path.write_bytes(data[:n])
        detail = f"cut to {n} of {len(data)} bytes"
    elif kind == "flip":
        offsets = draw(_st().lists(_st().integers(0, len(data) - 1), min_size=1, max_size=8))
        buf = bytearray(data)
        for o in offsets:
            buf[o] ^= 0xFF
        path.write_bytes(bytes(buf))
        detail = f"bytes flipped at {offsets}"
    elif kind == "delete":
        path.unlink()
        detail = "deleted"
    elif kind == "link":
        target = case.outside / ("secret.npy" if suffix == ".npy" else "secret.png" if suffix == ".png" else
                                 "secret.txt")
        path.unlink()
        path.symlink_to(target)
        detail = f"a link to {target}"
    elif kind == "huge":
        if suffix == ".png":
            w, h = draw(_st().sampled_from([(40000, 40000), (100000, 3), (6000, 4500)]))
            path.write_bytes(_crafted_png(w, h))
            detail = f"a PNG header declaring {w}×{h}"
        else:
            shape = draw(_st().sampled_from([(10 ** 6, 10 ** 6), (48, 64, 10 ** 9)]))
            path.write_bytes(_crafted_npy(shape))
            detail = f"a .npy header declaring {shape}"
    else:
        if suffix == ".npy":
            value = draw(_st().sampled_from(["1-D", "2x2", "scalar", "int", "nan", "object"]))
            arr = {"1-D": np.ones(64, np.float32), "2x2": np.ones((2, 2), np.float32),
                   "scalar": np.float32(1.0), "int": np.ones((48, 64), np.int64),
                   "nan": np.full((48, 64), np.nan, np.float32),
                   "object": np.array([{"a": 1}], dtype=object)}[value]
            with open(path, "wb") as fh:
                np.save(fh, arr, allow_pickle=True)
            detail = f"a {value} array"
        elif suffix in (".png", ".jpg", ".tif", ".exr"):
            w, h = draw(_st().sampled_from([(1, 1), (37, 23), (128, 96), (3, 500)]))
            path.unlink()
            _png(path.with_suffix(".png"), w, h)
            if suffix != ".png":
                path.with_suffix(".png").rename(path)
            detail = f"an image of {w}×{h}"
        else:
            path.write_bytes(b"not a " + suffix.encode() + b" file\n")
            detail = "text"
    case.did.append(f"{path.relative_to(case.example)}: {detail}")


def link_folder_outside(case: Case, folder: Path) -> None:
    """Replace a folder inside an input by a link to a copy of it outside (``images`` → outside/images)."""
    shutil.rmtree(folder)
    target = case.outside / ("images" if folder.name == "images" else "cal")
    folder.symlink_to(target, target_is_directory=True)
    case.did.append(f"{folder.relative_to(case.example)}: a link to {target}")


def _st():
    from hypothesis import strategies

    return strategies


# -- running one case ----------------------------------------------------------------------------------------

class Hang(BaseException):
    """Raised by the alarm: not an ``Exception``, so that the CLI's handlers do not turn it into an exit code."""


@dataclass
class Result:
    code: int | None
    escapes: list[str]
    losses: list[str]
    stderr: str


def run_case(case: Case, argv: list[str], inputs: list[Path], *, resumed: Path | None = None,
             seconds: int = CASE_SECONDS) -> Result:
    """Run ``procam argv`` in this process and check it: exit code, files opened, files lost.

    ``inputs`` are the folders and files the command is given to read; ``resumed`` is a step folder that is also its
    output (a show resumed), in which only the files ProCam writes may change."""
    from procam.addon.cli.app import main

    install_audit()
    logs = case.root / "logs"
    roots = allowed_roots(case.example, logs)
    watched = {p: snapshot(p) for p in inputs}
    guarded = {p: snapshot(p) for p in (case.root / "user", case.outside)}
    global _OPENED
    err = io.StringIO()
    old_handler = signal.signal(signal.SIGALRM, _on_alarm)
    old_env = os.environ.get("PROCAM_LOG_DIR")
    os.environ["PROCAM_LOG_DIR"] = str(logs)
    cwd = Path.cwd()
    opened: list[str] = []
    code: int | None
    try:
        os.chdir(case.example)
        _OPENED = opened
        signal.alarm(seconds)
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            code = main(argv)
    except Hang:
        code = None
    finally:
        signal.alarm(0)
        _OPENED = None
        os.chdir(cwd)
        signal.signal(signal.SIGALRM, old_handler)
        if old_env is None:
            os.environ.pop("PROCAM_LOG_DIR", None)
        else:
            os.environ["PROCAM_LOG_DIR"] = old_env
    losses = []
    for p, before in watched.items():
        may = _procam_show_file if p == resumed else (lambda n: False)
        losses += [f"{p.relative_to(case.example)}/{x}" for x in lost(before, snapshot(p), may)]
    for p, before in guarded.items():
        losses += [f"{p}/{x}" for x in lost(before, snapshot(p))]
    return Result(code, escapes(opened, roots, case.example), losses, err.getvalue())


def _on_alarm(signum, frame):
    raise Hang()


def _procam_show_file(name: str) -> bool:
    """The files a resumed show may rewrite: its frames, manifest, open-loop bias and temporary files."""
    base = os.path.basename(name)
    return base.startswith(("frame_", ".")) or base in ("show.json", "open_loop_bias.npz")


def reset_example(case: Case, names: list[str]) -> None:
    """A fresh example folder holding copies of the world's ``names`` (links are kept as links)."""
    if case.example.exists():
        shutil.rmtree(case.example)
    (case.example / "out").mkdir(parents=True)
    mine = case.example / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("a user's folder given as --out\n")
    for name in names:
        src = case.root / "world" / "w" / name
        dst = case.w / name
        dst.parent.mkdir(parents=True, exist_ok=True)
        if src.is_dir():
            shutil.copytree(src, dst, symlinks=True)
        else:
            shutil.copy2(src, dst)


# -- figures -------------------------------------------------------------------------------------------------

@dataclass
class Figures:
    """What the suite saw, per format: cases run, exit codes, and the cases that broke a promise."""

    cases: Counter = field(default_factory=Counter)
    codes: dict[str, Counter] = field(default_factory=dict)
    failures: dict[str, list[str]] = field(default_factory=dict)
    escapes: Counter = field(default_factory=Counter)
    losses: Counter = field(default_factory=Counter)
    internal: Counter = field(default_factory=Counter)
    hangs: Counter = field(default_factory=Counter)

    def record(self, fmt: str, case: Case, argv: list[str], result: Result) -> None:
        self.cases[fmt] += 1
        code = "hang" if result.code is None else result.code
        self.codes.setdefault(fmt, Counter())[code] += 1
        problems = []
        if result.code is None:
            self.hangs[fmt] += 1
            problems.append(f"no exit within {CASE_SECONDS} s")
        elif result.code not in (0, 2):
            if result.code == 1:
                self.internal[fmt] += 1
            problems.append(f"exit {result.code}: {_last_error(result.stderr)}")
        if result.escapes:
            self.escapes[fmt] += 1
            problems.append(f"opened outside: {result.escapes[:3]}")
        if result.losses:
            self.losses[fmt] += 1
            problems.append(f"lost: {result.losses[:3]}")
        if problems:
            self.failures.setdefault(fmt, []).append(
                f"[{'; '.join(case.did)}] procam {argv[0]}: {' | '.join(problems)}")

    def table(self) -> str:
        lines = [f"{'format':<13}{'cases':>6}{'internal':>9}{'hangs':>6}{'escapes':>8}{'losses':>7}  exit codes"]
        for fmt in sorted(self.cases):
            codes = ", ".join(f"{k}: {v}" for k, v in sorted(self.codes[fmt].items(), key=lambda kv: str(kv[0])))
            lines.append(f"{fmt:<13}{self.cases[fmt]:>6}{self.internal[fmt]:>9}{self.hangs[fmt]:>6}"
                         f"{self.escapes[fmt]:>8}{self.losses[fmt]:>7}  {codes}")
        total = Counter()
        for c in self.codes.values():
            total.update(c)
        lines.append(f"{'all':<13}{sum(self.cases.values()):>6}{sum(self.internal.values()):>9}"
                     f"{sum(self.hangs.values()):>6}{sum(self.escapes.values()):>8}{sum(self.losses.values()):>7}  "
                     + ", ".join(f"{k}: {v}" for k, v in sorted(total.items(), key=lambda kv: str(kv[0]))))
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        return {"cases": dict(self.cases),
                "codes": {f: {str(k): v for k, v in c.items()} for f, c in self.codes.items()},
                "internal": dict(self.internal), "hangs": dict(self.hangs), "escapes": dict(self.escapes),
                "losses": dict(self.losses), "failures": self.failures}


def _last_error(stderr: str) -> str:
    lines = [ln for ln in stderr.splitlines() if "error" in ln]
    return (lines[-1] if lines else stderr.strip().splitlines()[-1] if stderr.strip() else "")[:300]
