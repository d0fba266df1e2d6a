"""A manifest that names a file outside its folder (absolute, ``../``, or through a symlink) is refused by every
reader with exit 2, and nothing outside the folders the user gave is read or copied (issue 37, items 3–5)."""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from procam.addon.cli.app import main
from procam.addon.imageio import write_image
from procam.addon.steps import layout

SECRET = b"not yours to read"
_opened: list[str] | None = None


def _audit(event: str, args: tuple) -> None:
    if event == "open" and _opened is not None and isinstance(args[0], (str, bytes, os.PathLike)):
        _opened.append(os.fsdecode(args[0]))


sys.addaudithook(_audit)  # one hook for the session (hooks cannot be removed); it records only inside opened()


@contextmanager
def opened() -> Iterator[list[str]]:
    """The files opened in this process meanwhile (resolved), from Python's audit events."""
    global _opened
    _opened = []
    seen = _opened
    try:
        yield seen
    finally:
        _opened = None
        seen[:] = [os.path.realpath(p) for p in seen]


def _outside(tmp_path: Path, name: str = "secret.png", shape: tuple[int, int] = (60, 80)) -> Path:
    """An image outside every folder given to the command, that a manifest tries to reach."""
    folder = tmp_path / "elsewhere"
    folder.mkdir(exist_ok=True)
    path = folder / name
    write_image(path, np.full((*shape, 3), 0.5, np.float32))
    return path


def _read_outside(seen: list[str], outside: Path) -> list[str]:
    root = os.path.realpath(outside)
    return [p for p in seen if p == root or p.startswith(root + os.sep)]


# -- item 3: export-frames copies what compensation.json names ------------------------------------------------

def _compensation(folder: Path, frame: str) -> Path:
    """A compensation folder whose one finished target names ``frame`` as its projector frame."""
    folder.mkdir()
    for name in ("a_input.png", "a_frame.png", "a_simulated.png"):
        write_image(folder / name, np.zeros((60, 80, 3), np.float32))
    doc = {"format": layout.COMPENSATION.format, "version": 1,
           "targets": [{"name": "a", "status": "done", "input": "a_input.png", "frame": frame,
                        "simulated": "a_simulated.png", "psnr_simulated": 30.0, "seconds": 1.0, "mode": "forward"}]}
    (folder / layout.COMPENSATION.manifest).write_text(json.dumps(doc))
    return folder


def test_export_frames_of_an_honest_compensation_copies_its_frame(tmp_path: Path) -> None:
    comp = _compensation(tmp_path / "comp", "a_frame.png")
    assert main(["export-frames", str(comp), "--out", str(tmp_path / "frames")]) == 0
    assert (tmp_path / "frames" / "frame_0001.png").read_bytes() == (comp / "a_frame.png").read_bytes()


@pytest.mark.parametrize("how", ["absolute", "climbing", "symlink", "symlinked folder"])
def test_export_frames_refuses_a_frame_outside_the_compensation(tmp_path: Path, how: str, capsys) -> None:
    secret = _outside(tmp_path)
    secret.write_bytes(SECRET)
    comp = tmp_path / "comp"
    frame = {"absolute": str(secret), "climbing": "../elsewhere/secret.png", "symlink": "link.png",
             "symlinked folder": "frames/secret.png"}[how]
    _compensation(comp, frame)
    if how == "symlink":
        os.symlink(secret, comp / "link.png")
    if how == "symlinked folder":
        os.symlink(secret.parent, comp / "frames")
    out = tmp_path / "frames"
    with opened() as seen:
        assert main(["export-frames", str(comp), "--out", str(out)]) == 2
    assert not out.exists()
    assert _read_outside(seen, secret.parent) == []
    assert "names files inside itself" in capsys.readouterr().err
