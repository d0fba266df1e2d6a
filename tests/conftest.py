"""Shared pytest fixtures: an empty Blender scene, the extension registered, fresh-process Python runs, and a
virtual X server for the live loop's projector window."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: The virtual screen of the ``xvfb`` fixture (width, height).
XVFB_SCREEN = (800, 600)


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


_LAB_SETS: dict[tuple, tuple[Path, Path]] = {}


@pytest.fixture(scope="session")
def _two_projector_lab(tmp_path_factory) -> Path:
    from procam.addon.cli.app import main

    root = tmp_path_factory.mktemp("two-projectors")
    assert main(["lab", "--surface", "curve", "--projectors", "2", "--overlap", "0.2", "--projector-effects",
                 "2:response=0.9", "--scale", "0.2", "--samples", "4", "--out", str(root / "lab"), "--truth",
                 str(root / "lab.truth.json")]) == 0
    assert main(["calibrate", str(root / "lab"), "--out", str(root / "cal"), "--no-blend-output"]) == 0
    return root


@pytest.fixture(scope="module")
def two_projector_lab(_two_projector_lab, tmp_path_factory) -> Path:
    """A folder of its own per test module holding ``lab/`` (two projectors side by side on the curve, 20 %
    overlap, camera 128×96, projectors 160×120, 4 spp; projector 2 alone with a tone curve), ``lab.truth.json`` and
    ``cal/`` (calibrated, both transport operators): rendered and calibrated once a session, copied per module so
    that no module sees another's outputs."""
    root = tmp_path_factory.mktemp("two")
    shutil.copytree(_two_projector_lab, root, dirs_exist_ok=True)
    return root


@pytest.fixture(scope="session")
def lab_set(tmp_path_factory) -> Callable[..., tuple[Path, Path]]:
    """Render (once per session and set of arguments) a small lab capture set; returns (capture dir, truth file).

    Small by default (camera 192×144, projector 240×180, 8 spp) so stage tests stay fast on 2 cores.
    """

    def make(surface: str = "vedge", effects: str = "", *, scale: float = 0.3, samples: int = 8,
             graycode: bool = True, seed: int = 0) -> tuple[Path, Path]:
        key = (surface, effects, scale, samples, graycode, seed)
        if key not in _LAB_SETS:
            from procam.addon.lab.truth import make_truth
            from procam.addon.lab.lab import run_lab

            root = tmp_path_factory.mktemp(f"lab-{surface}")
            cam = (round(640 * scale), round(480 * scale))
            proj = (round(800 * scale), round(600 * scale))
            truth = make_truth(surface, effects=effects, seed=seed, samples=samples, camera_size=cam,
                               projector_size=proj)
            run_lab(truth, root / "captures", truth_path=root / "truth.json", graycode=graycode)
            _LAB_SETS[key] = (root / "captures", root / "truth.json")
        return _LAB_SETS[key]

    return make


_LAB_CALIBRATIONS: dict[tuple, Path] = {}


@pytest.fixture(scope="session")
def lab_calibration(lab_set, tmp_path_factory) -> Callable[..., tuple[Path, Path, Path]]:
    """A calibration folder made from a lab set's truth (true rig and surface, identity warp), once per session.

    Returns (calibration dir, capture dir, truth file); the arguments are those of ``lab_set``. Compensation
    tests use it so that they do not depend on (or wait for) stages A and B.
    """

    def make(*args, **kwargs) -> tuple[Path, Path, Path]:
        captures_dir, truth_path = lab_set(*args, **kwargs)
        key = (str(captures_dir),)
        if key not in _LAB_CALIBRATIONS:
            from procam.addon.lab.truth import LabTruth
            from procam.addon.stages.calibrate import Calibration
            from procam.addon.stages.warp_model import Warp
            from procam.addon.steps import calibrate as calibrate_step

            truth = LabTruth.load(truth_path)  # tests are evaluation code: they may read the truth
            cal = Calibration(truth.rig, truth.surface, Warp.identity(truth.rig.projector.input_size),
                              str(captures_dir))
            folder = tmp_path_factory.mktemp("calibration") / "cal"
            folder.mkdir()
            calibrate_step.write(folder, cal, {})
            _LAB_CALIBRATIONS[key] = folder
        return _LAB_CALIBRATIONS[key], captures_dir, truth_path

    return make


_STORED_CALIBRATIONS: dict[str, Path] = {}


@pytest.fixture(scope="session")
def stored_calibration(lab_calibration, tmp_path_factory) -> Callable[..., tuple[Path, Path, Path]]:
    """A ``lab_calibration`` folder with its transport operator stored (``procam precompute``), made once per
    session and set of arguments (those of ``lab_set``); returns what ``lab_calibration`` does. For tests of what
    runs on a calibration (shows, resumes, devices) rather than of the operator: without it every run of compensate
    or show renders the operator again in memory (in the show tests 36 of 46 seconds). Read it only: copy it before
    writing into it."""

    def make(*args, **kwargs) -> tuple[Path, Path, Path]:
        cal_dir, captures_dir, truth_path = lab_calibration(*args, **kwargs)
        key = str(cal_dir)
        if key not in _STORED_CALIBRATIONS:
            from procam.addon.cli.app import main

            folder = tmp_path_factory.mktemp("stored-calibration") / "cal"
            shutil.copytree(cal_dir, folder)
            assert main(["precompute", str(folder)]) == 0
            _STORED_CALIBRATIONS[key] = folder
        return _STORED_CALIBRATIONS[key], captures_dir, truth_path

    return make


_LIVE_CALIBRATIONS: dict[str, Path] = {}


@pytest.fixture(scope="session")
def live_calibration(stored_calibration, tmp_path_factory) -> Callable[..., Path]:
    """A ``lab_calibration`` folder with its transport operator and approximate inverse stored (``procam precompute
    --live``), made once per session and set of arguments; the arguments are those of ``lab_set``. Shared by the
    real-time and live-show modules: copy it before writing into it."""

    def make(*args, **kwargs) -> Path:
        cal_dir, _, _ = stored_calibration(*args, **kwargs)
        key = str(cal_dir)
        if key not in _LIVE_CALIBRATIONS:
            from procam.addon.cli.app import main

            folder = tmp_path_factory.mktemp("live-calibration") / "cal"
            shutil.copytree(cal_dir, folder)  # the operator is kept: only the inverse is added
            assert main(["precompute", str(folder), "--live"]) == 0
            _LIVE_CALIBRATIONS[key] = folder
        return _LIVE_CALIBRATIONS[key]

    return make


def _free_display() -> int:
    for n in range(90, 200):
        if not Path(f"/tmp/.X11-unix/X{n}").exists() and not Path(f"/tmp/.X{n}-lock").exists():
            return n
    raise RuntimeError("no free X display number")


@pytest.fixture(scope="module")
def xvfb():
    """A virtual X server (:data:`XVFB_SCREEN`) for the module, as DISPLAY with SDL on X11; the tests skip, saying
    why, where it cannot start."""
    if shutil.which("Xvfb") is None:
        pytest.skip("Xvfb is not installed (Debian: apt-get install xvfb; scripts/setup.sh does it as root)")
    n = _free_display()
    screen = f"{XVFB_SCREEN[0]}x{XVFB_SCREEN[1]}x24"
    proc = subprocess.Popen(["Xvfb", f":{n}", "-screen", "0", screen, "-nolisten", "tcp"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 10
    while not Path(f"/tmp/.X11-unix/X{n}").exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            pytest.skip(f"the virtual X server did not start: {proc.stderr.read().decode()[-300:]}")
        time.sleep(0.05)
    saved = {k: os.environ.get(k) for k in ("DISPLAY", "SDL_VIDEODRIVER")}
    os.environ["DISPLAY"], os.environ["SDL_VIDEODRIVER"] = f":{n}", "x11"
    yield f":{n}"
    import pygame
    pygame.display.quit()
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
    proc.terminate()
    proc.wait(timeout=10)
