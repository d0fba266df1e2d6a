"""Shared pytest fixtures: an empty Blender scene, the extension registered, and fresh-process Python runs."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def bpy_scene():
    """An empty factory-settings scene (no cube, no camera, no light); skips where bpy is missing."""
    bpy = pytest.importorskip("bpy")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    yield bpy.context.scene
    bpy.ops.wm.read_factory_settings(use_empty=True)


@pytest.fixture
def registered(bpy_scene) -> Iterator[None]:
    """The extension's operators and panels registered for one test (as Blender would on enabling it)."""
    import procam

    procam.register()
    try:
        yield
    finally:
        procam.unregister()


@pytest.fixture
def run_python() -> Callable[..., subprocess.CompletedProcess]:
    """Run a script in a fresh interpreter of this environment (a clean bpy state, its own env vars)."""

    def run(code: str, *args: str, env: dict[str, str] | None = None,
            timeout: float = 300) -> subprocess.CompletedProcess:
        full_env = {**os.environ, **(env or {})}
        return subprocess.run([sys.executable, "-c", textwrap.dedent(code), *args], cwd=REPO, env=full_env,
                              capture_output=True, text=True, timeout=timeout)

    return run
