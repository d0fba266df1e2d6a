"""Output folders that appear whole or not at all, and progress lines for long work.

A command writes into a hidden temporary sibling of its output folder and
renames it into place only when everything is written, so a crash or a
cancel never leaves a half-written result under the real name, and an
existing result is only replaced with ``force`` — after the new one is complete.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ProCamError


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
        if self.target.exists():
            if not self.target.is_dir():
                raise self.error(f"{self.target} exists and is not a folder; choose another output path")
            empty = not any(self.target.iterdir())
            if not empty:
                if replaceable is not None and not replaceable(self.target):
                    raise self.error(f"{self.target} exists, is not empty and is not a {what}; "
                                       "refusing to replace it — choose another output folder")
                if not force:
                    raise self.error(f"{self.target} already holds a {what}; it is never overwritten "
                                       "without --force (force=True)")
        try:
            self.target.parent.mkdir(parents=True, exist_ok=True)
            self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.target.name}.tmp-", dir=self.target.parent))
        except OSError as exc:
            raise self.error(f"cannot write {self.what} at {self.target}: {exc.strerror or exc}") from None
        self.done = False

    def commit(self) -> Path:
        if self.done:
            raise self.error(f"{self.what} at {self.target} was already completed")
        backup: Path | None = None
        try:
            if self.target.exists():
                backup = Path(tempfile.mkdtemp(prefix=f".{self.target.name}.old-", dir=self.target.parent))
                backup.rmdir()  # mkdtemp reserves a unique name; rename needs it free
                os.replace(self.target, backup)
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


def progress(message: str) -> None:
    """One progress line on stderr (stdout stays for results)."""
    print(f"[procam {time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)
