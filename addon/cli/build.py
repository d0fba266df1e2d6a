"""``procam build-extension``: the Blender extension zips, one per platform with its wheels
(scripts/build_extension.py)."""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path
from types import ModuleType

from .app import command
from ..errors import ProCamError

_SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "build_extension.py"


def _build_script() -> ModuleType:
    # The build script is standard-library only and lives outside the package (it is not shipped in the zip),
    # so load it by path: this command works from a source checkout, which is what a build needs anyway.
    if not _SCRIPT.is_file():
        raise ProCamError("build-extension works from a ProCam source checkout (scripts/build_extension.py "
                          "is not part of an installed extension)")
    spec = importlib.util.spec_from_file_location("procam_build_extension", _SCRIPT)
    if spec is None or spec.loader is None:
        raise ProCamError(f"cannot load {_SCRIPT} as a Python module")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _configure(parser: argparse.ArgumentParser) -> None:
    if _SCRIPT.is_file():  # an installed extension has no build script; running the command then says why
        _build_script().add_arguments(parser)


@command("build-extension", "Build the Blender extension zips, one per platform "
         "(dist/procam-<version>-<platform>.zip) with that platform's wheels", _configure)
def build_extension(args: argparse.Namespace) -> int:
    script = _build_script()
    try:
        script.run(args)
    except script.BuildError as exc:
        raise ProCamError(str(exc)) from None
    return 0
