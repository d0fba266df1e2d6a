"""Output folders that appear whole or not at all, and the naming conventions every step's files share.

A command writes into a hidden temporary sibling of its output folder and
renames it into place only when everything is written, so a crash or a
cancel never leaves a half-written result under the real name, and an
existing result is only replaced with ``force`` — after the new one is complete.

:func:`check_replaceable` is the one place that decides whether an existing
output may be replaced: only a folder of the kind the step writes (its
manifest and format tag, so made by ProCam), never a file, never a folder of
other files, and never an input of the run or a folder holding one. The
hidden siblings are named after their owner (host and process id), so a later
run of the same output removes the ones a killed run left behind, and never
one a live run is still writing.

One run writes an output at a time: every writer holds :func:`writer_lock` on
its output (a hidden ``.NAME.lock`` file beside it, locked by the operating
system and holding the writer's host and process id) from before its work
starts until its result is in place, and a second run of the same output is
refused at once ("another procam run is writing to …"). A run that is killed
lets go with its process: the lock file it leaves never blocks the next run.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import shutil
import socket
import sys
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ProCamError
from .imageio import usual_mode, write_atomic_bytes


class OutputError(ProCamError):
    """An output folder that cannot be written or already holds results."""


class OutputBusyError(OutputError):
    """Another run is writing the same output right now: wait for it, or choose another output."""


def holds_manifest(folder: str | Path, manifest: str, format: str) -> bool:
    """Whether ``folder`` holds the JSON ``manifest`` with the format tag ``format``: a folder ProCam made."""
    try:
        doc = json.loads((Path(folder) / manifest).read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return False
    return isinstance(doc, dict) and doc.get("format") == format


def _real(path: str | Path) -> Path:
    return Path(os.path.realpath(os.path.abspath(path)))


def _input_at(path: str | Path, inputs: Iterable[str | Path | None], *, inside_path: bool) -> Path | None:
    """The first of ``inputs`` that is ``path`` or, with ``inside_path``, lies inside it (a folder to replace
    would take it along), else holds it (a file to write would land in it); real paths compared; else None."""
    real = _real(path)
    for given in inputs:
        if given is None:
            continue
        p = _real(given)
        if p == real or (real in p.parents if inside_path else p in real.parents):
            return Path(given)
    return None


def check_apart_from_inputs(target: str | Path, inputs: Iterable[str | Path | None], *,
                            error: type[ProCamError] = OutputError) -> None:
    """Refuse an output folder ``target`` that is one of ``inputs``, holds one (replacing it would take the input
    along) or lies inside one (a step never writes into what it reads, not even a new folder there); real paths
    compared, so a link to an input folder is that folder."""
    inputs = tuple(inputs)
    given = _input_at(target, inputs, inside_path=True)
    if given is not None:
        which = "is" if _real(given) == _real(target) else "holds"
        raise error(f"{target} {which} an input of this run ({given}); a step never replaces what it reads — "
                    "choose another output folder")
    real = _real(target)
    for given in inputs:
        if given is not None and _real(given) in real.parents:
            raise error(f"{target} lies inside {given}, an input of this run; a step never writes into what it "
                        "reads — choose an output outside it")


def check_replaceable(target: str | Path, *, force: bool, what: str, replaceable: Callable[[Path], bool],
                      inputs: Iterable[str | Path | None], error: type[ProCamError] = OutputError,
                      incomplete: Callable[[Path], bool] | None = None) -> bool:
    """Refuse an output ``target`` that must not be replaced; True when it holds something ``force`` replaces.

    ``replaceable(path)`` says whether an existing folder is of the kind this
    step writes (its manifest, with ProCam's format tag). Never replaced: a
    file, a non-empty folder that is not ``replaceable`` (user data), and an
    input of this run or a folder holding one (``inputs``: the files and
    folders the run reads), even with ``force``. A non-empty ``replaceable``
    folder is replaced only with ``force``, or when ``incomplete(path)`` says a failed or cancelled run left it
    (marked incomplete: a failed run never blocks its own retry). Never written at all: a folder inside an input
    (:func:`check_apart_from_inputs`).
    """
    target = Path(target)
    check_apart_from_inputs(target, inputs, error=error)
    if not target.exists():
        return False
    if not target.is_dir():
        raise error(f"{target} exists and is not a folder; choose another output path")
    try:
        empty = not any(target.iterdir())
    except OSError as exc:  # a folder we may not look into (permissions) is not ours to replace
        raise error(f"cannot look into {target} ({exc.strerror or exc}); choose another output folder") from None
    if empty:
        return False
    if not replaceable(target):
        raise error(f"{target} exists, is not empty and is not a {what}; refusing to replace it — choose another "
                    "output folder")
    if not force and not (incomplete is not None and incomplete(target)):
        raise error(f"{target} already holds a {what}; it is never overwritten without --force")
    return True


def check_file_replaceable(path: str | Path, *, force: bool, what: str, replaceable: Callable[[Path], bool],
                           inputs: Iterable[str | Path | None], error: type[ProCamError] = OutputError) -> bool:
    """:func:`check_replaceable` for an output that is one file: True when ``path`` exists and may be replaced.

    Never written: an input of this run or a file inside one (``inputs``:
    what the run reads, and the folders it must leave alone), a folder. An
    existing file is replaced only with ``force`` and only when
    ``replaceable(path)`` (its content shows ProCam wrote it, of this kind).
    """
    path = Path(path)
    given = _input_at(path, inputs, inside_path=False)
    if given is not None:
        raise error(f"the {what} {path} would be written into {given}, which this run must leave as it is (an "
                    "input, or a folder another ProCam step made); choose another file name")
    if not path.exists() and not path.is_symlink():
        return False
    if path.is_dir():
        raise error(f"the {what} {path} is a folder; give a file name")
    if path.is_symlink() or not replaceable(path):
        raise error(f"{path} exists and is not a {what}; refusing to replace it — choose another file name")
    if not force:
        raise error(f"the {what} {path} already exists; it is never overwritten without --force")
    return True


# -- hidden siblings: their owner in their name, so the ones a killed run left can be told apart ---------------

def _owner() -> str:
    host = re.sub(r"[^A-Za-z0-9]", "", socket.gethostname())[:24] or "host"
    return f"{host}-{os.getpid()}"


def hidden_sibling(target: Path, role: str) -> Path:
    """A new, empty, hidden folder beside ``target`` (``.NAME.ROLE-HOST-PID-XXXXXXXX``; ``role`` tmp or old)."""
    return Path(tempfile.mkdtemp(prefix=f".{target.name}.{role}-{_owner()}-", dir=target.parent))


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this machine; True when that cannot be told (never remove on a doubt)."""
    if pid == os.getpid():
        return True
    if sys.platform == "win32":
        try:
            import ctypes
            kernel32 = ctypes.windll.kernel32  # type: ignore[attr-defined]
            handle = kernel32.OpenProcess(0x1000, False, pid)  # PROCESS_QUERY_LIMITED_INFORMATION
            if not handle:
                return kernel32.GetLastError() != 87  # ERROR_INVALID_PARAMETER: no such process
            code = ctypes.c_ulong()
            ok = kernel32.GetExitCodeProcess(handle, ctypes.byref(code))
            kernel32.CloseHandle(handle)
            return not ok or code.value == 259  # STILL_ACTIVE
        except Exception:  # noqa: BLE001 — no answer: treat it as alive
            return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # EPERM: alive, another user's
        return True
    return True


def stale_siblings(target: str | Path) -> list[Path]:
    """The hidden ``tmp``/``old`` siblings of ``target`` whose owner, a process of this host, has ended."""
    target = Path(target)
    pattern = re.compile(rf"\.{re.escape(target.name)}\.(?:tmp|old)-([A-Za-z0-9]+)-(\d+)-[a-z0-9_]{{8}}")
    host = _owner().rsplit("-", 1)[0]
    try:
        names = os.listdir(target.parent)
    except OSError:
        return []
    out = []
    for name in sorted(names):
        m = pattern.fullmatch(name)
        if m and m.group(1) == host and not _pid_alive(int(m.group(2))):
            out.append(target.parent / name)
    return out


def remove_stale_siblings(target: str | Path, replaceable: Callable[[Path], bool]) -> list[Path]:
    """Remove what a killed run of ``target`` left beside it; returns what was removed.

    A half-written ``tmp`` sibling always goes; a set-aside ``old`` one only
    when ``target`` holds a complete result of its kind (else the old one may
    be the only copy left: a kill between setting it aside and moving the new
    one in).
    """
    target = Path(target)
    done = []
    for p in stale_siblings(target):
        if p.name[len(target.name) + 1:].startswith(".old-") and not (target.is_dir() and replaceable(target)):
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                p.unlink()
        done.append(p)
    return done


# -- one writer at a time: a lock beside each output -----------------------------------------------------------

try:
    import fcntl as _fcntl
except ImportError:  # Windows: an exclusively created lock file, with the owner's process id to tell a stale one
    _fcntl = None  # type: ignore[assignment]


def lock_path(target: str | Path) -> Path:
    """The lock file of the output ``target``: ``.NAME.lock`` beside it (a folder that is renamed into place, or
    a file written under a temporary name, cannot hold its own lock)."""
    target = Path(os.path.abspath(target))
    return target.parent / f".{target.name}.lock"


class _Held:
    """A lock this process holds: its open lock file, how deep the nested holders go, the thread that holds it,
    and the folders made to hold the lock file (removed again when they stay empty)."""

    def __init__(self, path: Path, fd: int, made: list[Path]) -> None:
        self.path, self.fd, self.made = path, fd, made
        self.depth = 1
        self.thread = threading.get_ident()


_HELD: dict[Path, _Held] = {}
_HELD_GUARD = threading.Lock()


def _owner_of(path: Path) -> str:
    """Who holds the lock file ``path``, as its holder wrote it ("process 1234 on host"), or ""."""
    try:
        host, pid = path.read_text(errors="replace").split()[:2]
        return f" (process {int(pid)} on {host})"
    except (OSError, ValueError):
        return ""


def _busy(target: Path, lock: Path) -> OutputBusyError:
    return OutputBusyError(f"another procam run{_owner_of(lock)} is writing to {target}; wait for it to finish or "
                           "choose another output")


def _make_parents(folder: Path) -> list[Path]:
    """Make ``folder`` and the folders above it that are missing; returns those made, deepest first."""
    missing = []
    p = folder
    while not p.exists() and p.parent != p:
        missing.append(p)
        p = p.parent
    folder.mkdir(parents=True, exist_ok=True)
    return missing


def _stamp(fd: int) -> None:
    os.ftruncate(fd, 0)
    os.write(fd, f"{_owner().rsplit('-', 1)[0]} {os.getpid()}\n".encode())


def _lock_flock(target: Path, lock: Path) -> int | None:
    """Lock ``lock`` with the operating system's advisory lock (freed when the process ends, however it ends);
    None where the file system has no such locks."""
    assert _fcntl is not None
    for _ in range(8):
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            _fcntl.flock(fd, _fcntl.LOCK_EX | _fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise _busy(target, lock) from None
        except OSError:  # a file system without advisory locks (some network shares)
            os.close(fd)
            return None
        # The holder before us removes the file as it lets go: a lock on a file no longer at ``lock`` is no lock.
        try:
            here, mine = os.stat(lock), os.fstat(fd)
            same = (here.st_dev, here.st_ino) == (mine.st_dev, mine.st_ino)
        except FileNotFoundError:
            same = False
        if same:
            _stamp(fd)
            return fd
        os.close(fd)
    raise _busy(target, lock)


def _lock_exclusive(target: Path, lock: Path) -> int:
    """Create ``lock`` exclusively, with this process's id in it; a lock file whose process (on this host) has
    ended is stale and taken over."""
    for _ in range(8):
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            try:
                host, pid = lock.read_text().split()[:2]
                stale = host == _owner().rsplit("-", 1)[0] and not _pid_alive(int(pid))
            except (OSError, ValueError):  # being written, or unreadable: its owner may well be alive
                stale = False
            if not stale:
                raise _busy(target, lock) from None
            with contextlib.suppress(FileNotFoundError):
                os.unlink(lock)
            continue
        _stamp(fd)
        return fd
    raise _busy(target, lock)


def hold_writer(target: str | Path) -> Path:
    """Take the writer lock of the output ``target`` (:func:`writer_lock`); returns the key to
    :func:`release_writer`. Nested holds in one thread share the lock; another thread or process is refused with
    :class:`OutputBusyError`."""
    key = _real(target)
    with _HELD_GUARD:
        held = _HELD.get(key)
        if held is not None:
            if held.thread != threading.get_ident():
                raise _busy(Path(target), held.path)
            held.depth += 1
            return key
        lock = lock_path(key)
        try:
            made = _make_parents(lock.parent)
        except OSError as exc:
            raise OutputError(f"cannot write {target}: {exc.strerror or exc}; choose another output or change its "
                              "folder's permissions") from None
        try:
            fd = _lock_flock(Path(target), lock) if _fcntl is not None else None
            if fd is None:
                fd = _lock_exclusive(Path(target), lock)
        except OSError as exc:
            _remove_empty(made)
            raise OutputError(f"cannot write {target}: {exc.strerror or exc}; choose another output or change its "
                              "folder's permissions") from None
        except BaseException:
            _remove_empty(made)
            raise
        _HELD[key] = _Held(lock, fd, made)
        return key


def release_writer(key: Path, *, whole: bool = False) -> None:
    """Let go of one hold of the writer lock ``key`` (all of them with ``whole``); the last one removes the lock
    file. A key no longer held is nothing to do."""
    with _HELD_GUARD:
        held = _HELD.get(key)
        if held is None or held.thread != threading.get_ident():
            return
        held.depth -= 1
        if held.depth > 0 and not whole:
            return
        del _HELD[key]
        with contextlib.suppress(OSError):
            os.unlink(held.path)  # while still locked: a waiting run then finds no file, or a new one
        os.close(held.fd)
        _remove_empty(held.made)


def _remove_empty(made: list[Path]) -> None:
    for folder in made:  # deepest first
        try:
            folder.rmdir()
        except OSError:
            break


@contextlib.contextmanager
def writer_lock(target: str | Path) -> Iterator[None]:
    """Hold the writer lock of the output ``target`` (a folder or a file) for the ``with`` block: the one rule
    that keeps two runs from writing one output. Every writer takes it before its work starts (after checking that
    the output may be written, so a refused output leaves nothing behind) and keeps it until its result is in
    place; the outermost ``with`` of a thread lets go of it whole (a hold inside it that was never let go, say a
    folder abandoned on an error, included)."""
    key = hold_writer(target)
    outermost = _HELD[key].depth == 1
    try:
        yield
    finally:
        release_writer(key, whole=outermost)


def holds_writer(target: str | Path) -> bool:
    """Whether this thread holds the writer lock of ``target``."""
    held = _HELD.get(_real(target))
    return held is not None and held.thread == threading.get_ident()


class AtomicFolder:
    """Build a folder in a hidden sibling and rename it into place when complete.

    An existing ``target`` is refused unless ``force``; even then it is only
    renamed to a backup and removed after the new folder is in place, so a
    failure at any point leaves either the old folder or the new one, never
    a mixture. :func:`check_replaceable` decides what may be replaced
    (``replaceable``: the kind this step writes; ``inputs``: what the run reads).
    """

    def __init__(self, target: str | Path, *, force: bool = False, what: str = "folder",
                 replaceable: Callable[[Path], bool], inputs: Iterable[str | Path | None],
                 error: type[ProCamError] = OutputError, incomplete: Callable[[Path], bool] | None = None) -> None:
        self.target = Path(target)
        self.error = error
        self.force = force
        self.what = what
        inputs = tuple(inputs)
        check_replaceable(self.target, force=force, what=what, replaceable=replaceable, inputs=inputs, error=error,
                          incomplete=incomplete)
        self._lock = hold_writer(self.target)  # no other run writes it until this one is done
        try:
            # again, now that no other run can: one that finished meanwhile may have left a result here
            check_replaceable(self.target, force=force, what=what, replaceable=replaceable, inputs=inputs,
                              error=error, incomplete=incomplete)
            self.target.parent.mkdir(parents=True, exist_ok=True)
            remove_stale_siblings(self.target, replaceable)
            self.tmp = hidden_sibling(self.target, "tmp")
            usual_mode(self.tmp)
        except OSError as exc:
            release_writer(self._lock)
            raise self.error(f"cannot write {self.what} at {self.target}: {exc.strerror or exc}") from None
        except BaseException:
            release_writer(self._lock)
            raise
        self.done = False

    def commit(self) -> Path:
        if self.done:
            raise self.error(f"{self.what} at {self.target} was already completed")
        backup: Path | None = None
        try:
            if self.target.exists():
                backup = _set_aside(self.target)
            os.replace(self.tmp, self.target)
        except OSError as exc:
            if backup is not None and backup.exists() and not self.target.exists():
                os.replace(backup, self.target)  # put the old one back
            self.abort()
            raise self.error(f"cannot move the new {self.what} into {self.target}: {exc.strerror or exc}") from None
        self.done = True
        if backup is not None:
            shutil.rmtree(backup, ignore_errors=True)
        release_writer(self._lock)
        return self.target

    def abort(self) -> None:
        if not self.done:
            shutil.rmtree(self.tmp, ignore_errors=True)
            self.done = True
            release_writer(self._lock)


def _set_aside(target: Path) -> Path:
    """Rename ``target`` to a hidden unique sibling; returns the sibling."""
    backup = hidden_sibling(target, "old")
    backup.rmdir()  # mkdtemp reserves a unique name; rename needs it free
    os.replace(target, backup)
    return backup


@contextlib.contextmanager
def fresh_output_folder(path: str | Path, *, force: bool = False, what: str = "results folder",
                        replaceable: Callable[[Path], bool], inputs: Iterable[str | Path | None]) -> Iterator[Path]:
    """Yield a temporary folder; on success it becomes ``path`` (replacing, only with ``force``, a folder
    :func:`check_replaceable` allows)."""
    folder = AtomicFolder(path, force=force, what=what, replaceable=replaceable, inputs=inputs)
    try:
        yield folder.tmp
    except BaseException:
        folder.abort()
        raise
    folder.commit()


def output_names(paths: Iterable[str | Path]) -> list[str]:
    """Output names from file stems, made unique (a/x.png and b/x.png become x and x_2)."""
    out: list[str] = []
    for p in paths:
        base = re.sub(r"[^A-Za-z0-9_.-]+", "-", Path(p).stem).strip("-") or "target"
        name, n = base, 1
        while name in out:
            n += 1
            name = f"{base}_{n}"
        out.append(name)
    return out


def jsonable(value: Any) -> Any:
    """Plain JSON types (numpy scalars/arrays become numbers/lists) so manifests are portable: a value that is not
    a number (NaN, ±inf: a PSNR over no pixels) becomes null, which every JSON reader takes (Python's json writes
    NaN, which JSON has not, and a browser's or jq's parser refuses the whole file)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist()) if value.dtype.kind == "f" else value.tolist()
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def natural_key(path: str | Path) -> list[Any]:
    """Sort key for file names in natural order: frame2 before frame10."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", Path(path).name)]


def file_sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def write_manifest(path: str | Path, doc: dict[str, Any]) -> Path:
    """A step's JSON manifest, in plain JSON types, written under a temporary name and renamed into place."""
    write_atomic_bytes(Path(path), (json.dumps(jsonable(doc), indent=1) + "\n").encode())
    return Path(path)


@contextlib.contextmanager
def folder_in_place(path: str | Path, *, force: bool = False, what: str = "results folder",
                    replaceable: Callable[[Path], bool], inputs: Iterable[str | Path | None]) -> Iterator[Path]:
    """Yield ``path`` itself, new and empty, for work whose files must name their final place (step folders
    that point at each other). An existing folder is set aside first (only with ``force`` and when
    :func:`check_replaceable` allows it) and removed once the work succeeds; on failure the partial folder goes
    and the old one comes back."""
    target = Path(path).absolute()
    inputs = tuple(inputs)
    check_replaceable(target, force=force, what=what, replaceable=replaceable, inputs=inputs)
    # the lock first: no other run writes it until this one is done
    with writer_lock(target), _in_place(target, force=force, what=what, replaceable=replaceable,
                                        inputs=inputs) as out:
        yield out


@contextlib.contextmanager
def _in_place(target: Path, *, force: bool, what: str, replaceable: Callable[[Path], bool],
              inputs: tuple[str | Path | None, ...]) -> Iterator[Path]:
    replacing = check_replaceable(target, force=force, what=what, replaceable=replaceable, inputs=inputs)
    remove_stale_siblings(target, replaceable)
    try:
        backup = _set_aside(target) if replacing else None
    except OSError as exc:
        raise OutputError(f"cannot replace {what} at {target}: {exc.strerror or exc}") from None
    try:
        try:
            target.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"cannot write {what} at {target}: {exc.strerror or exc}") from None
        usual_mode(target)
        yield target
    except BaseException:
        shutil.rmtree(target, ignore_errors=True)
        if backup is not None:
            os.replace(backup, target)
        raise
    if backup is not None:
        shutil.rmtree(backup, ignore_errors=True)
