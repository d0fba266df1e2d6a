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
from collections.abc import Iterator
from pathlib import Path

from .errors import ProCamError


class OutputError(ProCamError):
    """An output folder that cannot be written or already holds results."""


@contextlib.contextmanager
def fresh_output_folder(path: str | Path, *, force: bool = False) -> Iterator[Path]:
    """Yield a temporary folder; on success it becomes ``path`` (replacing it only with ``force``)."""
    final = Path(path).absolute()
    if final.exists() and not force:
        if not final.is_dir() or any(final.iterdir()):
            raise OutputError(f"{path} already exists and is not empty; choose another --out or pass --force")
    parent = final.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-", dir=parent))
    except OSError as exc:
        raise OutputError(f"cannot create output folder {path}: {exc.strerror or exc}") from None
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if final.exists():
        old = parent / f".{final.name}.old-{os.getpid()}-{time.time_ns()}"
        os.replace(final, old)
    os.replace(tmp, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def progress(message: str) -> None:
    """One progress line on stderr (stdout stays for results)."""
    print(f"[procam {time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)
