"""Shared pytest fixtures: an empty Blender scene, the extension registered, fresh-process Python runs, and a
virtual X server for the live loop's projector window."""

from __future__ import annotations

import fcntl
import hashlib
import os
import select
import shutil
import subprocess
import sys
import textwrap
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


def _shared(tmp_path_factory, name: str, key: tuple, build: Callable[[Path], None]) -> Path:
    """The folder ``build(folder)`` fills, made once per test run and ``key``, also when the run is split over
    worker processes (``pytest -n``): the first to take the folder's lock builds it, the others wait and read it.
    A build that failed leaves no mark, so the next one to ask builds it again from an empty folder."""
    base = tmp_path_factory.getbasetemp()
    # Each worker's base folder lies in the run's own; without workers the base is the run's.
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "shared"
    folder = root / f"{name}-{hashlib.sha1(repr(key).encode()).hexdigest()[:12]}"
    done = folder / ".built"
    if done.exists():
        return folder
    root.mkdir(parents=True, exist_ok=True)
    with open(root / f"{folder.name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            build(folder)
            done.touch()
    return folder


@pytest.fixture(scope="session")
def _two_projector_lab(tmp_path_factory) -> Path:
    def build(root: Path) -> None:
        from procam.addon.cli.app import main

        assert main(["lab", "--surface", "curve", "--projectors", "2", "--overlap", "0.2", "--projector-effects",
                     "2:response=0.9", "--scale", "0.2", "--samples", "4", "--out", str(root / "lab"), "--truth",
                     str(root / "lab.truth.json")]) == 0
        assert main(["calibrate", str(root / "lab"), "--out", str(root / "cal"), "--no-blend-output"]) == 0

    return _shared(tmp_path_factory, "two-projectors", (), build)


@pytest.fixture(scope="module")
def two_projector_lab(_two_projector_lab, tmp_path_factory) -> Path:
    """A folder of its own per test module holding ``lab/`` (two projectors side by side on the curve, 20 %
    overlap, camera 128×96, projectors 160×120, 4 spp; projector 2 alone with a tone curve), ``lab.truth.json`` and
    ``cal/`` (calibrated, both transport operators): rendered and calibrated once a test run, copied per module so
    that no module sees another's outputs."""
    root = tmp_path_factory.mktemp("two")
    shutil.copytree(_two_projector_lab, root, dirs_exist_ok=True, ignore=shutil.ignore_patterns(".built"))
    return root


@pytest.fixture(scope="session")
def lab_set(tmp_path_factory) -> Callable[..., tuple[Path, Path]]:
    """Render (once per test run and set of arguments) a small lab capture set; returns (capture dir, truth file).

    Small by default (camera 192×144, projector 240×180, 8 spp) so stage tests stay fast on 2 cores.
    """

    def make(surface: str = "vedge", effects: str = "", *, scale: float = 0.3, samples: int = 8,
             graycode: bool = True, seed: int = 0) -> tuple[Path, Path]:
        def build(root: Path) -> None:
            from procam.addon.lab.truth import make_truth
            from procam.addon.lab.lab import run_lab

            cam = (round(640 * scale), round(480 * scale))
            proj = (round(800 * scale), round(600 * scale))
            truth = make_truth(surface, effects=effects, seed=seed, samples=samples, camera_size=cam,
                               projector_size=proj)
            run_lab(truth, root / "captures", truth_path=root / "truth.json", graycode=graycode)

        root = _shared(tmp_path_factory, f"lab-{surface}", (surface, effects, scale, samples, graycode, seed), build)
        return root / "captures", root / "truth.json"

    return make


@pytest.fixture(scope="session")
def lab_calibration(lab_set, tmp_path_factory) -> Callable[..., tuple[Path, Path, Path]]:
    """A calibration folder made from a lab set's truth (true rig and surface, identity warp), once per test run.

    Returns (calibration dir, capture dir, truth file); the arguments are those of ``lab_set``. Compensation
    tests use it so that they do not depend on (or wait for) stages A and B.
    """

    def make(*args, **kwargs) -> tuple[Path, Path, Path]:
        captures_dir, truth_path = lab_set(*args, **kwargs)

        def build(folder: Path) -> None:
            from procam.addon.lab.truth import LabTruth
            from procam.addon.stages.calibrate import Calibration
            from procam.addon.stages.warp_model import Warp
            from procam.addon.steps import calibrate as calibrate_step

            truth = LabTruth.load(truth_path)  # tests are evaluation code: they may read the truth
            cal = Calibration(truth.rig, truth.surface, Warp.identity(truth.rig.projector.input_size),
                              str(captures_dir))
            (folder / "cal").mkdir()
            calibrate_step.write(folder / "cal", cal, {})

        return _shared(tmp_path_factory, "calibration", (str(captures_dir),), build) / "cal", captures_dir, truth_path

    return make


@pytest.fixture(scope="session")
def stored_calibration(lab_calibration, tmp_path_factory) -> Callable[..., tuple[Path, Path, Path]]:
    """A ``lab_calibration`` folder with its transport operator stored (``procam precompute``), made once per
    test run and set of arguments (those of ``lab_set``); returns what ``lab_calibration`` does. For tests of what
    runs on a calibration (shows, resumes, devices) rather than of the operator: without it every run of compensate
    or show renders the operator again in memory (in the show tests 36 of 46 seconds). Read it only: copy it before
    writing into it."""

    def make(*args, **kwargs) -> tuple[Path, Path, Path]:
        cal_dir, captures_dir, truth_path = lab_calibration(*args, **kwargs)

        def build(folder: Path) -> None:
            from procam.addon.cli.app import main

            shutil.copytree(cal_dir, folder / "cal")
            assert main(["precompute", str(folder / "cal")]) == 0

        return _shared(tmp_path_factory, "stored-calibration", (str(cal_dir),), build) / "cal", captures_dir, truth_path

    return make


@pytest.fixture(scope="session")
def live_calibration(stored_calibration, tmp_path_factory) -> Callable[..., Path]:
    """A ``lab_calibration`` folder with its transport operator and approximate inverse stored (``procam precompute
    --live``), made once per test run and set of arguments; the arguments are those of ``lab_set``. Shared by the
    real-time and live-show modules: copy it before writing into it."""

    def make(*args, **kwargs) -> Path:
        cal_dir, _, _ = stored_calibration(*args, **kwargs)

        def build(folder: Path) -> None:
            from procam.addon.cli.app import main

            shutil.copytree(cal_dir, folder / "cal")  # the operator is kept: only the inverse is added
            assert main(["precompute", str(folder / "cal"), "--live"]) == 0

        return _shared(tmp_path_factory, "live-calibration", (str(cal_dir),), build) / "cal"

    return make


@pytest.fixture(scope="module")
def xvfb():
    """A virtual X server (:data:`XVFB_SCREEN`) for the module, as DISPLAY with SDL on X11; the tests skip, saying
    why, where it cannot start."""
    if shutil.which("Xvfb") is None:
        pytest.skip("Xvfb is not installed (Debian: apt-get install xvfb; scripts/setup.sh does it as root)")
    screen = f"{XVFB_SCREEN[0]}x{XVFB_SCREEN[1]}x24"
    # The server picks a free display number itself and writes it to the pipe once it accepts clients: two test
    # processes starting one at the same moment cannot pick the same number.
    read_end, write_end = os.pipe()
    proc = subprocess.Popen(["Xvfb", "-displayfd", str(write_end), "-screen", "0", screen, "-nolisten", "tcp"],
                            pass_fds=(write_end,), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    os.close(write_end)
    with os.fdopen(read_end) as pipe:
        ready, _, _ = select.select([pipe], [], [], 10)
        number = pipe.readline().strip() if ready else ""
    if not number.isdigit():
        proc.kill()
        pytest.skip(f"the virtual X server did not start: {proc.communicate()[1].decode()[-300:]}")
    n = int(number)
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
