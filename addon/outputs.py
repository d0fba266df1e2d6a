"""Output folders that appear whole or not at all, and the naming conventions every step's files share.

A command writes into a hidden temporary sibling of its output folder and
renames it into place only when everything is written, so a crash or a
cancel never leaves a half-written result under the real name, and an
existing result is only replaced with ``force`` — after the new one is complete.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ProCamError
from .imageio import usual_mode, write_atomic_bytes


class OutputError(ProCamError):
    """An output folder that cannot be written or already holds results."""


class AtomicFolder:
    """Build a folder in a hidden sibling and rename it into place when complete.

    An existing ``target`` is refused unless ``force``; even then it is only
    renamed to a backup and removed after the new folder is in place, so a
    failure at any point leaves either the old folder or the new one, never
    a mixture. ``replaceable(path)`` says which existing folders ``force``
    may replace (others are refused even with ``force``, to protect user data).
    """

    def __init__(self, target: str | Path, *, force: bool = False, what: str = "folder",
                 replaceable: Callable[[Path], bool] | None = None,
                 error: type[ProCamError] = OutputError) -> None:
        self.target = Path(target)
        self.error = error
        self.force = force
        self.what = what
        check_replaceable(self.target, force=force, what=what, replaceable=replaceable, error=error)
        try:
            self.target.parent.mkdir(parents=True, exist_ok=True)
            self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.target.name}.tmp-", dir=self.target.parent))
            usual_mode(self.tmp)
        except OSError as exc:
            raise self.error(f"cannot write {self.what} at {self.target}: {exc.strerror or exc}") from None
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
        return self.target

    def abort(self) -> None:
        if not self.done:
            shutil.rmtree(self.tmp, ignore_errors=True)
            self.done = True


def check_replaceable(target: Path, *, force: bool, what: str, replaceable: Callable[[Path], bool] | None = None,
                      error: type[ProCamError] = OutputError) -> bool:
    """Refuse an output ``target`` that must not be replaced; True when it holds something ``force`` replaces.

    A file is never replaced, nor a non-empty folder that is not ``replaceable``
    (user data); a non-empty one that is only with ``force``.
    """
    if not target.exists():
        return False
    if not target.is_dir():
        raise error(f"{target} exists and is not a folder; choose another output path")
    if not any(target.iterdir()):
        return False
    if replaceable is not None and not replaceable(target):
        raise error(f"{target} exists, is not empty and is not a {what}; refusing to replace it — choose another "
                    "output folder")
    if not force:
        raise error(f"{target} already holds a {what}; it is never overwritten without --force (force=True)")
    return True


def _set_aside(target: Path) -> Path:
    """Rename ``target`` to a hidden unique sibling; returns the sibling."""
    backup = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
    backup.rmdir()  # mkdtemp reserves a unique name; rename needs it free
    os.replace(target, backup)
    return backup


@contextlib.contextmanager
def fresh_output_folder(path: str | Path, *, force: bool = False, what: str = "results folder") -> Iterator[Path]:
    """Yield a temporary folder; on success it becomes ``path`` (replacing it only with ``force``)."""
    folder = AtomicFolder(path, force=force, what=what)
    try:
        yield folder.tmp
    except BaseException:
        folder.abort()
        raise
    folder.commit()


def output_names(paths: "Iterable[str | Path]") -> list[str]:
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
    """Plain JSON types (numpy scalars/arrays become numbers/lists) so manifests are portable."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
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
                    replaceable: Callable[[Path], bool] | None = None) -> Iterator[Path]:
    """Yield ``path`` itself, new and empty, for work whose files must name their final place (step folders
    that point at each other). An existing folder is set aside first (only with ``force`` and when
    ``replaceable``) and removed once the work succeeds; on failure the partial folder goes and the old one
    comes back."""
    target = Path(path).absolute()
    replacing = check_replaceable(target, force=force, what=what, replaceable=replaceable)
    backup = _set_aside(target) if replacing else None
    try:
        target.mkdir(parents=True, exist_ok=True)
        usual_mode(target)
        yield target
    except BaseException:
        shutil.rmtree(target, ignore_errors=True)
        if backup is not None:
            os.replace(backup, target)
        raise
    if backup is not None:
        shutil.rmtree(backup, ignore_errors=True)
