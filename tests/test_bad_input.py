"""Bad input, at random: every manifest format and every image, depth and video input damaged, then read.

Hypothesis draws, for each format, which file of a small valid folder to damage
and how (:mod:`tests.bad_input`); the command that reads that format runs in
this process through the CLI. Promised (issue 37): exit 0 or 2, never 1 or a
hang; nothing opened outside the folders the command was given; nothing
deleted or changed that ProCam did not make. Each test runs all its cases and
then fails listing every case that broke a promise, so one run shows all that
is wrong with a format.

The default suite runs about 200 cases in well under two minutes on 2 cores;
``PROCAM_BAD_INPUT_SCALE=10`` (``scripts/bench_bad_input.py``) runs ten times as
many, with fresh random draws, and prints the table of figures.
"""

from __future__ import annotations

import contextlib
import json
import os
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis", reason="hypothesis is in requirements-dev.txt: pip install -r it")
from hypothesis import HealthCheck, Phase, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from tests.bad_input import (FAST, FAST_C, Case, Figures, link_folder_outside, make_world, mutate_file,  # noqa: E402
                             mutate_json, reset_example, run_case, snapshot)

SCALE = float(os.environ.get("PROCAM_BAD_INPUT_SCALE", "1"))
#: Fresh random draws (the benchmark), or the same cases every run (the default suite: a failure repeats).
RANDOM = SCALE != 1 or bool(os.environ.get("PROCAM_BAD_INPUT_RANDOM"))
FIGURES = Figures()


def _settings(examples: int):
    # No shrinking: a case never raises (its result is recorded), and the suite must keep to its time.
    return settings(max_examples=max(1, round(examples * SCALE)), deadline=None, database=None,
                    derandomize=not RANDOM, phases=[Phase.explicit, Phase.generate],
                    suppress_health_check=list(HealthCheck))


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("bad_input")
    make_world(root)
    return root


@pytest.fixture(scope="module", autouse=True)
def figures(request):
    """Print the figures after the module (and write them to ``PROCAM_BAD_INPUT_FIGURES`` when set)."""
    yield FIGURES
    capture = request.config.pluginmanager.getplugin("capturemanager")
    if FIGURES.cases:
        with capture.global_and_fixture_disabled() if capture else contextlib.nullcontext():
            print("\nbad-input property suite:\n" + FIGURES.table(), flush=True)
    if os.environ.get("PROCAM_BAD_INPUT_FIGURES"):
        Path(os.environ["PROCAM_BAD_INPUT_FIGURES"]).write_text(json.dumps(FIGURES.to_dict(), indent=1))


Scenario = Callable[[Case, Callable], tuple[list[str], list[Path], Path | None]]


def _check(world: Path, fmt: str, names: list[str], scenario: Scenario, examples: int) -> None:
    """Run ``examples`` generated cases of ``scenario`` (copy ``names``, damage, read) and fail listing every case
    that broke a promise."""
    before = len(FIGURES.failures.get(fmt, []))

    @_settings(examples)
    @given(data=st.data())
    def one(data):
        case = Case(world)
        reset_example(case, names)
        argv, inputs, resumed = scenario(case, data.draw)
        FIGURES.record(fmt, case, argv, run_case(case, argv, inputs, resumed=resumed))

    one()
    failures = FIGURES.failures.get(fmt, [])[before:]
    assert not failures, f"{len(failures)} bad-input case(s) of {fmt} broke a promise:\n" + "\n".join(failures)


def _pick_file(draw, folder: Path, suffixes=(".png", ".npy", ".npz", ".exr", ".obj", ".mtl")) -> Path:
    files = sorted(p for p in folder.rglob("*") if p.is_file() and not p.is_symlink() and p.suffix in suffixes)
    return draw(st.sampled_from(files))


def _damage_step_folder(case: Case, draw, folder: Path, manifest: str, *, link_dirs: tuple[str, ...] = ()) -> None:
    """Damage a step folder: its manifest (most often), one of its files, or one of its sub-folders made a link."""
    choices = ["manifest", "manifest", "manifest", "file"] + (["link"] if link_dirs else [])
    what = draw(st.sampled_from(choices))
    if what == "manifest":
        mutate_json(case, draw, folder / manifest)
    elif what == "file":
        mutate_file(case, draw, _pick_file(draw, folder))
    else:
        link_folder_outside(case, folder / draw(st.sampled_from(link_dirs)))


# -- the formats ---------------------------------------------------------------------------------------------

def _import(case: Case, extra: list[str]) -> list[str]:
    w = case.w
    return ["import-captures", str(w / "seq"), str(w / "photos"), "--out", str(case.example / "out" / "set"), *extra]


def test_sequence(world):
    """``sequence.json`` and its pattern images, read by ``import-captures``."""
    def scenario(case, draw):
        _damage_step_folder(case, draw, case.w / "seq", "sequence.json")
        return _import(case, []), [case.w / "seq", case.w / "photos"], None

    _check(world, "sequence", ["seq", "photos"], scenario, 24)


def test_photographs_and_depth(world):
    """Photographs (a folder the user gives) and a depth map (``--depth``), read by ``import-captures``."""
    def scenario(case, draw):
        if draw(st.booleans()):
            mutate_file(case, draw, _pick_file(draw, case.w / "photos"), links=False)
        else:
            mutate_file(case, draw, case.w / "depth.npy", links=False)
        argv = _import(case, ["--depth", str(case.w / "depth.npy")])
        return argv, [case.w / "seq", case.w / "photos", case.w / "depth.npy"], None

    _check(world, "photos+depth", ["seq", "photos", "depth.npy"], scenario, 24)


def test_rig(world):
    """A rig file (``rig.json``), read by ``import-captures --rig`` and ``undistort-captures --rig``."""
    def scenario(case, draw):
        mutate_json(case, draw, case.w / "rig.json")
        if draw(st.booleans()):
            argv = _import(case, ["--rig", str(case.w / "rig.json")])
        else:
            argv = ["undistort-captures", str(case.w / "set"), "--rig", str(case.w / "rig.json"), "--out",
                    str(case.example / "out" / "u")]
        return argv, [case.w / "seq", case.w / "photos", case.w / "set", case.w / "rig.json"], None

    _check(world, "rig", ["seq", "photos", "set", "rig.json"], scenario, 16)


def test_capture_set(world):
    """A capture set (``capture.json``, images, patterns, depth), read by ``undistort-captures``."""
    def scenario(case, draw):
        _damage_step_folder(case, draw, case.w / "set", "capture.json", link_dirs=("images", "patterns", "depth"))
        argv = ["undistort-captures", str(case.w / "set"), "--rig", str(case.w / "rig.json"), "--out",
                str(case.example / "out" / "u")]
        return argv, [case.w / "set", case.w / "rig.json"], None

    _check(world, "capture", ["set", "rig.json"], scenario, 24)


def test_capture_set_calibrated(world):
    """A lab capture set read by ``calibrate`` (surface, pose, warp): slow (about 6 s a case), so few cases."""
    def scenario(case, draw):
        _damage_step_folder(case, draw, case.w / "captures", "capture.json", link_dirs=("images", "depth"))
        argv = ["calibrate", str(case.w / "captures"), "--out", str(case.example / "out" / "cal"),
                "--no-precompute", "--no-blend-output"]
        return argv, [case.w / "captures"], None

    _check(world, "capture/cal", ["captures"], scenario, 3)


def _compensate(case: Case, extra: list[str] = ()) -> list[str]:
    return ["compensate", str(case.w / "cal"), str(case.w / "frames" / "shot_0001.png"), "--out",
            str(case.example / "out" / "c"), *FAST_C, *extra]


def test_calibration(world):
    """A calibration folder (``calibration.json``, surface, albedo) and the capture set it names, read by
    ``compensate`` (open loop: the validation captures are read too)."""
    def scenario(case, draw):
        if draw(st.integers(0, 3)) == 0:
            _damage_step_folder(case, draw, case.w / "captures", "capture.json", link_dirs=("images",))
        else:
            _damage_step_folder(case, draw, case.w / "cal", "calibration.json", link_dirs=("diagnostics",))
        return _compensate(case), [case.w / "cal", case.w / "captures", case.w / "frames"], None

    _check(world, "calibration", ["cal", "captures", "frames"], scenario, 12)


def test_target_images(world):
    """A target image, read by ``compensate``."""
    def scenario(case, draw):
        mutate_file(case, draw, case.w / "frames" / "shot_0001.png", links=False)
        return _compensate(case), [case.w / "cal", case.w / "captures", case.w / "frames"], None

    _check(world, "target", ["cal", "captures", "frames"], scenario, 10)


def test_compensation(world):
    """A compensation folder (``compensation.json`` and its images), read by ``export-frames`` and ``evaluate``."""
    def scenario(case, draw):
        _damage_step_folder(case, draw, case.w / "comp", "compensation.json")
        if draw(st.booleans()):
            argv = ["export-frames", str(case.w / "comp"), "--out", str(case.example / "out" / "e")]
        else:
            argv = ["evaluate", str(case.w / "cal"), "--inputs", str(case.w / "comp"), "--targets",
                    str(case.w / "frames" / "shot_0001.png"), "--device", f"lab:{case.w / 'truth.json'}", "--out",
                    str(case.example / "out" / "ev"), "--no-repeat"]
        return argv, [case.w / "comp", case.w / "cal", case.w / "frames", case.w / "truth.json"], None

    _check(world, "compensation", ["comp", "cal", "captures", "frames", "truth.json", "truth.surface.npz"],
           scenario, 20)


def test_show(world):
    """A show folder (``show.json`` and its frames), read when ``show`` resumes it."""
    def scenario(case, draw):
        _damage_step_folder(case, draw, case.w / "show", "show.json")
        (case.w / "show" / "notes.txt").write_text("the user's note in the show folder\n")
        argv = ["show", str(case.w / "cal"), str(case.w / "frames"), "--out", str(case.w / "show"), *FAST]
        return argv, [case.w / "show", case.w / "cal", case.w / "frames"], case.w / "show"

    _check(world, "show", ["show", "cal", "captures", "frames"], scenario, 8)


def test_diagnosis(world):
    """A diagnosis folder (``gap.json``), read by ``compensate --effects auto --diagnosis``."""
    def scenario(case, draw):
        if draw(st.integers(0, 3)) == 0:
            mutate_file(case, draw, _pick_file(draw, case.w / "gap"))
        else:
            mutate_json(case, draw, case.w / "gap" / "gap.json")
        argv = _compensate(case, ["--effects", "auto", "--diagnosis", str(case.w / "gap")])
        return argv, [case.w / "gap", case.w / "cal", case.w / "frames"], None

    _check(world, "gap", ["gap", "cal", "captures", "frames"], scenario, 8)


def test_video(world):
    """A target video, read by ``show``."""
    def scenario(case, draw):
        mutate_file(case, draw, case.w / "clip.avi", links=False)
        argv = ["show", str(case.w / "cal"), str(case.w / "clip.avi"), "--out", str(case.example / "out" / "v"),
                *FAST]
        return argv, [case.w / "cal", case.w / "clip.avi"], None

    _check(world, "video", ["cal", "captures", "clip.avi"], scenario, 8)


def _writers(case: Case) -> dict[str, tuple[Callable[[str], list[str]], list[Path], list[Path]]]:
    """The commands that write a folder from the world's folders: (argv for an output, the folders it reads that
    an output could be put at or in, every input it reads)."""
    w = case.w
    return {
        "import-captures": (lambda out: _import(case, ["--out", out, "--force"]), [w / "seq", w / "photos"],
                            [w / "seq", w / "photos"]),
        "undistort-captures": (lambda out: ["undistort-captures", str(w / "set"), "--rig", str(w / "rig.json"),
                                            "--out", out, "--force"], [w / "set"], [w / "set"]),
        "compensate": (lambda out: _compensate(case, ["--out", out, "--force"]), [w / "cal", w / "frames"],
                       [w / "cal", w / "captures", w / "frames"]),
        "export-frames": (lambda out: ["export-frames", str(w / "comp"), "--out", out, "--force"],
                          [w / "comp"], [w / "comp"]),
        "evaluate": (lambda out: ["evaluate", str(w / "cal"), "--inputs", str(w / "comp"), "--targets",
                                  str(w / "frames" / "shot_0001.png"), "--device", f"lab:{w / 'truth.json'}",
                                  "--out", out, "--no-repeat", "--force"], [w / "comp", w / "cal"],
                     [w / "cal", w / "comp", w / "frames"]),
    }


_WRITER_WORLD = ["seq", "photos", "set", "rig.json", "cal", "captures", "frames", "comp", "truth.json",
                 "truth.surface.npz"]


def test_replacing_folders(world):
    """``--out --force`` naming a user's folder or the command's own input: refused, nothing lost."""
    def scenario(case, draw):
        mine = case.example / "mine"
        commands = _writers(case)
        name = draw(st.sampled_from(sorted(commands)))
        make, targets, inputs = commands[name]
        out = draw(st.sampled_from([mine, *targets]))
        case.did.append(f"{name} --out {out.relative_to(case.example)} --force")
        return make(str(out)), [*inputs, mine], None

    _check(world, "--out --force", _WRITER_WORLD, scenario, 16)


def test_an_output_inside_an_input_or_written_by_another_run_is_refused(world):
    """Issue 53: ``--out`` inside a folder the command reads, or an output another run is writing (a thread of this
    process holds its writer lock, as a second job in Blender would): exit 2 with the reason, and every input
    exactly as it was, not even a file or a folder added."""
    from procam.addon.outputs import writer_lock

    @_settings(12)
    @given(data=st.data())
    def one(data):
        case = Case(world)
        reset_example(case, _WRITER_WORLD)
        name = data.draw(st.sampled_from(sorted(_writers(case))))
        make, targets, inputs = _writers(case)[name]
        busy = data.draw(st.booleans())
        # the folders it is given (compensate is given target files, not the folder that holds them)
        folders = [t for t in targets if not (name == "compensate" and t.name == "frames")]
        out = case.example / "new" if busy else data.draw(st.sampled_from(folders)) / data.draw(
            st.sampled_from(["nested", "a/b"]))
        before = {p: snapshot(p) for p in inputs}
        held, done = threading.Event(), threading.Event()

        def hold() -> None:
            with writer_lock(out):
                held.set()
                done.wait(60)

        holder = threading.Thread(target=hold)
        if busy:
            holder.start()
            assert held.wait(30)
        try:
            result = run_case(case, make(str(out)), inputs)
        finally:
            done.set()
            if busy:
                holder.join()
        what = f"{name} --out {out.relative_to(case.example)}" + (" while another run writes it" if busy else "")
        assert result.code == 2, f"{what}: exit {result.code}\n{result.stderr}"
        assert ("another procam run" if busy else "lies inside") in result.stderr, f"{what}: {result.stderr}"
        assert {p: snapshot(p) for p in inputs} == before, f"{what}: an input changed"
        assert not result.escapes, f"{what}: {result.escapes}"

    one()


# -- defects the suite found, each pinned by a case of its own -----------------------------------------------

@pytest.mark.parametrize("params", [-1e308, "x", [1, 2]])
def test_sequence_frame_params_of_another_type_is_refused(world, params):
    """A frame's ``params`` that is not an object (found by the suite: exit 1, "'float' object is not iterable")."""
    case = Case(world)
    reset_example(case, ["seq", "photos"])
    doc = json.loads((case.w / "seq" / "sequence.json").read_text())
    doc["frames"][0]["params"] = params
    (case.w / "seq" / "sequence.json").write_text(json.dumps(doc))
    result = run_case(case, _import(case, []), [case.w / "seq", case.w / "photos"])
    assert result.code == 2 and "frame 0" in result.stderr, result.stderr[-500:]


@pytest.mark.parametrize("where, value", [(("projector", "input_size"), [60]),
                                          (("projector", "input_size"), [60, 1e999]),
                                          (("projector", "input_offset"), [10])])
def test_sequence_projector_of_a_bad_input_size_is_refused(world, where, value):
    """An input size or offset of one number or an infinite one (found by the suite: IndexError, OverflowError)."""
    case = Case(world)
    reset_example(case, ["seq", "photos"])
    doc = json.loads((case.w / "seq" / "sequence.json").read_text())
    doc[where[0]][where[1]] = value
    (case.w / "seq" / "sequence.json").write_text(json.dumps(doc))
    result = run_case(case, _import(case, []), [case.w / "seq", case.w / "photos"])
    assert result.code == 2 and "projector" in result.stderr, result.stderr[-500:]


@pytest.mark.parametrize("key", ["depth", "notes"])
def test_capture_set_section_of_another_type_is_refused(world, key):
    """capture.json's depth or notes that is not an object (found by the suite: AttributeError, TypeError)."""
    case = Case(world)
    reset_example(case, ["set", "rig.json"])
    doc = json.loads((case.w / "set" / "capture.json").read_text())
    doc[key] = 1e308
    (case.w / "set" / "capture.json").write_text(json.dumps(doc))
    argv = ["undistort-captures", str(case.w / "set"), "--rig", str(case.w / "rig.json"), "--out",
            str(case.example / "out" / "u")]
    result = run_case(case, argv, [case.w / "set"])
    assert result.code == 2 and key in result.stderr, result.stderr[-500:]


@pytest.mark.parametrize("text", ["[]", "[1, 2]", "null", "1e308", '"calibration"'])
def test_calibration_manifest_that_is_not_an_object_is_refused(world, text):
    """A calibration.json that is a list, null, a number or a string (found by the suite: exit 1, "'list' object has
    no attribute 'get'")."""
    case = Case(world)
    reset_example(case, ["cal", "captures", "frames"])
    (case.w / "cal" / "calibration.json").write_text(text)
    result = run_case(case, _compensate(case), [case.w / "cal", case.w / "captures", case.w / "frames"])
    assert result.code == 2 and "calibration" in result.stderr, result.stderr[-500:]


@pytest.mark.parametrize("how", ["cut", "flip", "empty", "text"])
def test_damaged_surface_mesh_is_refused_as_damaged(world, how):
    """A cut or byte-flipped ``surface.npz`` (found by the suite: exit 1, zipfile.BadZipFile): the calibration's
    error, saying the file is damaged and to calibrate again."""
    case = Case(world)
    reset_example(case, ["cal", "captures", "frames"])
    path = case.w / "cal" / "surface.npz"
    data = path.read_bytes()
    if how == "cut":
        path.write_bytes(data[:len(data) // 2])
    elif how == "flip":  # inside the first member's compressed or stored data: a CRC or inflate failure
        buf = bytearray(data)
        for o in range(100, len(data) - 200, max(1, len(data) // 16)):
            buf[o] ^= 0xFF
        path.write_bytes(bytes(buf))
    elif how == "empty":
        path.write_bytes(b"")
    else:
        path.write_text("not an npz file\n")
    result = run_case(case, _compensate(case), [case.w / "cal", case.w / "captures", case.w / "frames"])
    assert result.code == 2, result.stderr[-800:]
    assert "damaged" in result.stderr and "procam calibrate" in result.stderr, result.stderr[-500:]


@pytest.mark.parametrize("value", [float("inf"), float("-inf"), float("nan")])
def test_capture_set_non_finite_note_is_refused(world, value):
    """capture.json whose ``notes.exposure.lit_fraction`` is infinite (found by the suite: exit 1 when the new
    capture set's manifest is written, "Out of range float values are not JSON compliant")."""
    case = Case(world)
    reset_example(case, ["set", "rig.json"])
    doc = json.loads((case.w / "set" / "capture.json").read_text())
    doc.setdefault("notes", {}).setdefault("exposure", {})["lit_fraction"] = value
    (case.w / "set" / "capture.json").write_text(json.dumps(doc))
    argv = ["undistort-captures", str(case.w / "set"), "--rig", str(case.w / "rig.json"), "--out",
            str(case.example / "out" / "u")]
    result = run_case(case, argv, [case.w / "set"])
    assert result.code == 2 and "lit_fraction" in result.stderr, result.stderr[-500:]


@pytest.mark.parametrize("how", ["cut", "flip", "lone array", "member missing", "missing"])
def test_read_arrays_refuses_a_damaged_archive_saying_what_to_do(tmp_path, how):
    """Every .npz a step wrote is read through one function: a damaged one is the folder's error, never exit 1."""
    import numpy as np

    from procam.addon.errors import CalibrationError
    from procam.addon.imageio import read_arrays

    path = tmp_path / "surface.npz"
    np.savez_compressed(path, vertices=np.arange(3000, dtype=np.float32), faces=np.arange(300))
    data = path.read_bytes()
    if how == "cut":
        path.write_bytes(data[:len(data) - 40])
    elif how == "flip":
        path.write_bytes(bytes(b ^ 0xFF if 60 <= i < 64 else b for i, b in enumerate(data)))
    elif how == "lone array":
        with open(path, "wb") as fh:
            np.save(fh, np.ones(3))
    elif how == "missing":
        path.unlink()
    names = ("vertices", "faces", "uvs") if how == "member missing" else ("vertices", "faces")
    with pytest.raises(CalibrationError, match=r"(damaged|missing).*; calibrate again$"):
        read_arrays(path, names, error=CalibrationError, remedy="calibrate again")


def test_damaged_lab_truth_surface_is_refused(world):
    """A cut ``truth.surface.npz`` beside a lab truth (read by ``evaluate --device lab:``): the lab's error."""
    from procam.addon.errors import LabError
    from procam.addon.lab.lab import LabTruth

    case = Case(world)
    reset_example(case, ["truth.json", "truth.surface.npz"])
    surface = case.w / "truth.surface.npz"
    surface.write_bytes(surface.read_bytes()[:200])
    with pytest.raises(LabError, match="damaged.*procam lab"):
        LabTruth.load(case.w / "truth.json")


def test_damaged_transport_operator_is_refused(world, tmp_path):
    """A cut ``transport.npz`` that its record says belongs to the calibration: precompute it again."""
    import numpy as np

    from procam.addon.stages.transport import TransportError
    from procam.addon.steps import calibrate as calibrate_step
    from procam.addon.steps import transport as transport_step

    case = Case(world)
    reset_example(case, ["cal", "captures"])
    folder = case.w / "cal"
    ident = calibrate_step.identity(folder)
    (folder / "transport.json").write_text(json.dumps({"calibration_sha256": ident["sha256"], "bounces": 1, "seed": 0,
                                                       "surface_sha256": ident["surface_sha256"]}))
    np.savez(folder / "transport.npz", index=np.arange(5000), weight=np.ones(5000, np.float32))
    (folder / "transport.npz").write_bytes((folder / "transport.npz").read_bytes()[:3000])
    with pytest.raises(TransportError, match="damaged.*procam precompute"):
        transport_step.load(calibrate_step.read(folder), bounces=1, seed=0)
    (folder / "transport.json").write_text("[]")  # a record that is not an object: no operator of this calibration
    assert transport_step.load(calibrate_step.read(folder), bounces=1, seed=0) is None


def _readers() -> dict:
    from procam.addon.capture.format import CaptureSet
    from procam.addon.lab.lab import LabTruth
    from procam.addon.steps import calibrate as calibrate_step
    from procam.addon.steps import compensate as compensate_step
    from procam.addon.steps import rig as rig_step

    return {"cal/calibration.json": lambda w: calibrate_step.read(w / "cal"),
            "rig.json": lambda w: rig_step.read(w / "rig.json"),
            "set/capture.json": lambda w: CaptureSet.load(w / "set"),
            "truth.json": lambda w: LabTruth.load(w / "truth.json"),
            "comp/compensation.json": lambda w: compensate_step.read(w / "comp")}


@pytest.mark.parametrize("manifest, where, value", [
    ("cal/calibration.json", ("warp", "grid"), float("inf")),
    ("rig.json", ("version",), float("inf")),
    ("rig.json", ("board", "inner_corners"), []),
    ("rig.json", ("board", "inner_corners"), [9]),
    ("rig.json", ("board", "inner_corners"), ""),
    ("rig.json", ("camera", "std"), None),
    ("rig.json", ("projector", "std"), [1, 2]),
    ("set/capture.json", ("images", 0, "name"), [1, 2, 3]),
    ("set/capture.json", ("images", 0, "name"), {"a": 1}),
    ("truth.json", ("seed",), float("inf")),
    ("comp/compensation.json", ("targets",), 128.9),
    ("comp/compensation.json", ("targets",), True),
])
def test_manifest_value_of_another_shape_is_refused(world, manifest, where, value):
    """A value of another shape where a reader indexes or converts it (found by setting every key of every
    manifest to every odd value: IndexError, AttributeError, OverflowError, "unhashable type", "not iterable").
    The reader alone is run: its error is the user's (a ProCamError), never an internal one."""
    from procam.addon.errors import ProCamError

    case = Case(world)
    reset_example(case, ["cal", "captures", "rig.json", "set", "truth.json", "truth.surface.npz", "comp"])
    path = case.w / manifest
    doc = json.loads(path.read_text())
    _get_set(doc, where, value)
    path.write_text(json.dumps(doc))
    with pytest.raises(ProCamError):
        _readers()[manifest](case.w)


def _get_set(doc, where, value) -> None:
    for key in where[:-1]:
        doc = doc[key]
    doc[where[-1]] = value


def test_rig_board_of_one_number_is_refused_by_undistort(world):
    """rig.json whose board has one inner-corner count (found by the suite: exit 1, IndexError)."""
    case = Case(world)
    reset_example(case, ["set", "rig.json"])
    doc = json.loads((case.w / "rig.json").read_text())
    del doc["board"]["inner_corners"][1]
    (case.w / "rig.json").write_text(json.dumps(doc))
    argv = ["undistort-captures", str(case.w / "set"), "--rig", str(case.w / "rig.json"), "--out",
            str(case.example / "out" / "u")]
    result = run_case(case, argv, [case.w / "set", case.w / "rig.json"])
    assert result.code == 2 and "rig" in result.stderr, result.stderr[-500:]


@pytest.mark.parametrize("damage", ["no number", "a number", "a list"])
def test_show_entry_damaged_is_redone_or_refused(world, damage):
    """A resumed show whose frame entry lost its ``number`` (found by the suite: exit 1, KeyError: 'number'), or is
    no record at all (found by the long run: exit 1, 'float' object has no attribute 'get')."""
    case = Case(world)
    reset_example(case, ["show", "cal", "captures", "frames"])
    doc = json.loads((case.w / "show" / "show.json").read_text())
    if damage == "no number":
        del doc["frames"]["1"]["number"]
    else:
        doc["frames"]["1"] = 1e308 if damage == "a number" else [1, 2]
    (case.w / "show" / "show.json").write_text(json.dumps(doc))
    from tests.bad_input import FAST
    argv = ["show", str(case.w / "cal"), str(case.w / "frames"), "--out", str(case.w / "show"), *FAST]
    result = run_case(case, argv, [case.w / "show", case.w / "cal", case.w / "frames"], resumed=case.w / "show")
    assert result.code in (0, 2) and not result.losses, result.stderr[-800:]


# -- found by the long run (scripts/bench_bad_input.py, 1583 cases): each once, here for good ----------------------

@pytest.mark.parametrize("name", [1e308, None, ["a"]])
def test_sequence_frame_name_that_is_not_text_is_refused(world, name):
    """A frame's ``name`` that is not text (found by the long run: exit 1, TypeError in a regular expression)."""
    case = Case(world)
    reset_example(case, ["seq", "photos"])
    doc = json.loads((case.w / "seq" / "sequence.json").read_text())
    doc["frames"][0]["name"] = name
    (case.w / "seq" / "sequence.json").write_text(json.dumps(doc))
    result = run_case(case, _import(case, []), [case.w / "seq", case.w / "photos"])
    assert result.code == 2 and "frame 0" in result.stderr, result.stderr[-500:]


def test_depth_npy_whose_header_no_longer_parses_is_refused(world):
    """A depth .npy whose header dictionary has a flipped byte (found by the long run: exit 1, tokenize's
    TokenError from NumPy's header parser)."""
    case = Case(world)
    reset_example(case, ["seq", "photos", "depth.npy"])
    path = case.w / "depth.npy"
    data = bytearray(path.read_bytes())
    data[data.index(b"}")] = ord("(")  # the header's closing brace: its literal never ends
    path.write_bytes(bytes(data))
    result = run_case(case, _import(case, ["--depth", str(path)]), [case.w / "seq", case.w / "photos", path])
    assert result.code == 2 and "depth.npy" in result.stderr, result.stderr[-500:]


def test_validation_capture_of_another_size_is_refused(world):
    """A calibration's capture set holding one capture of another size, read by the open-loop θ (found by the long
    run: exit 1, numpy's 'all input arrays must have the same shape')."""
    from procam.addon.imageio import write_image

    case = Case(world)
    reset_example(case, ["cal", "captures", "frames"])
    victim = sorted((case.w / "captures" / "images").glob("*val*.png"))[0]
    write_image(victim, np.zeros((7, 9, 3), np.float32))
    result = run_case(case, _compensate(case), [case.w / "cal", case.w / "captures", case.w / "frames"])
    assert result.code == 2 and victim.name in result.stderr, result.stderr[-500:]


def test_compensation_naming_a_calibration_that_is_no_path_is_refused(world):
    """compensation.json's calibration holding a NUL byte (found by the long run: exit 1, 'embedded null byte')."""
    case = Case(world)
    reset_example(case, ["comp", "cal", "captures", "frames", "truth.json", "truth.surface.npz"])
    doc = json.loads((case.w / "comp" / "compensation.json").read_text())
    doc["calibration"] = "\x00"
    (case.w / "comp" / "compensation.json").write_text(json.dumps(doc))
    argv = ["evaluate", str(case.w / "cal"), "--inputs", str(case.w / "comp"), "--targets",
            str(case.w / "frames" / "shot_0001.png"), "--device", f"lab:{case.w / 'truth.json'}", "--out",
            str(case.example / "out" / "ev"), "--no-repeat"]
    result = run_case(case, argv, [case.w / "comp", case.w / "cal", case.w / "frames", case.w / "truth.json"])
    assert result.code == 2 and "no path" in result.stderr, result.stderr[-500:]


@pytest.mark.parametrize("value", [10 ** 30, [1, 2], {"gain": "x", "offset": 0}, {"gain": -1.0, "offset": 0.0}])
def test_compensation_range_record_of_another_shape_is_refused(world, value):
    """compensation.json's range map that is not a gain and an offset (found by the long run: exit 1, "'int' object
    is not subscriptable")."""
    case = Case(world)
    reset_example(case, ["comp", "cal", "captures", "frames", "truth.json", "truth.surface.npz"])
    doc = json.loads((case.w / "comp" / "compensation.json").read_text())
    doc["range"] = value
    (case.w / "comp" / "compensation.json").write_text(json.dumps(doc))
    argv = ["evaluate", str(case.w / "cal"), "--inputs", str(case.w / "comp"), "--targets",
            str(case.w / "frames" / "shot_0001.png"), "--device", f"lab:{case.w / 'truth.json'}", "--out",
            str(case.example / "out" / "ev"), "--no-repeat"]
    result = run_case(case, argv, [case.w / "comp", case.w / "cal", case.w / "frames", case.w / "truth.json"])
    assert result.code == 2 and "range map" in result.stderr, result.stderr[-500:]
