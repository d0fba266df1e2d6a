"""What a step may replace (addon/outputs.py ``check_replaceable``): only a folder or file of the kind it writes,
made by ProCam, never a folder of the user's files nor an input of the run; what a killed run leaves behind is
removed by the next run of the same output; Ctrl-C keeps the targets and the calibration already finished.

Every check runs before any rendering, so these tests use tiny or fabricated folders and take seconds.
"""

from __future__ import annotations

import ast
import contextlib
import json
import os
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from procam.addon.cli.app import main
from procam.addon.errors import Cancelled, LabError
from procam.addon.imageio import write_image
from procam.addon.outputs import (AtomicFolder, OutputBusyError, OutputError, check_file_replaceable,
                                  check_replaceable, folder_in_place, hidden_sibling, holds_writer, lock_path,
                                  stale_siblings, write_manifest, writer_lock)
from procam.addon.steps import layout
from procam.addon.steps.stage_c import StageC

from .test_capture import write_small_set

ADDON = Path(__file__).resolve().parents[1] / "addon"


def _user_folder(path: Path) -> Path:
    path.mkdir(parents=True)
    (path / "notes.txt").write_text("my own notes")
    (path / "photo.png").write_bytes(b"not really a png")
    return path


def _snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _manifest(folder: Path, kind: layout.FolderKind, **doc) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / kind.manifest).write_text(json.dumps({"format": kind.format, "version": kind.version, **doc}))
    return folder


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


# -- the rule itself -------------------------------------------------------------------------------------------

def test_check_replaceable_allows_only_a_procam_folder_of_the_kind_and_never_an_input(tmp_path):
    kind = layout.FRAMES
    check = lambda target, force=True, inputs=(): check_replaceable(  # noqa: E731
        target, force=force, what=kind.what, replaceable=kind.holds, inputs=inputs)
    assert check(tmp_path / "new") is False
    (tmp_path / "empty").mkdir()
    assert check(tmp_path / "empty") is False
    ours = _manifest(tmp_path / "ours", kind, frames=[])
    assert check(ours) is True
    with pytest.raises(OutputError, match="never overwritten without --force"):
        check(ours, force=False)
    user = _user_folder(tmp_path / "user")
    with pytest.raises(OutputError, match="is not a projector frame sequence; refusing"):
        check(user)
    # a manifest of that name but not ProCam's format tag is the user's file, not ours
    _manifest(tmp_path / "fake", layout.FolderKind("x", kind.manifest, "someone-elses-format"))
    with pytest.raises(OutputError, match="refusing to replace"):
        check(tmp_path / "fake")
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="not a folder"):
        check(tmp_path / "file")
    # an input, a folder holding one, the same through a symlink: never, even when of the kind and with force
    with pytest.raises(OutputError, match="is an input of this run"):
        check(ours, inputs=[ours])
    with pytest.raises(OutputError, match="holds an input of this run"):
        check(ours, inputs=[None, ours / "frame_0001.png"])
    os.symlink(ours, tmp_path / "link")
    with pytest.raises(OutputError, match="input of this run"):
        check(ours, inputs=[tmp_path / "link"])
    assert check(ours, inputs=[tmp_path / "user"]) is True


def test_every_writer_routes_through_the_rule_with_its_inputs():
    """Every call of a folder writer in addon/ names the kind it may replace and the run's inputs."""
    writers = {"AtomicFolder", "folder_in_place", "fresh_output_folder", "check_replaceable", "CaptureSetWriter",
               "check_file_replaceable"}
    seen = []
    for path in ADDON.rglob("*.py"):
        if path.name == "outputs.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call):
                name = node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", None)
                if name in writers:
                    keys = {k.arg for k in node.keywords}
                    where = f"{path.relative_to(ADDON)}:{node.lineno}"
                    seen.append(where)
                    assert "inputs" in keys or None in keys, f"{where}: {name} without inputs="  # None: **kwargs
                    assert name == "CaptureSetWriter" or "replaceable" in keys, f"{where}: {name} without replaceable="
    assert len(seen) >= 20


def test_a_file_output_is_replaced_only_when_procam_wrote_it(tmp_path):
    ours = tmp_path / "rig.json"
    ours.write_text(json.dumps({"format": "procam-rig"}))
    is_ours = lambda p: json.loads(p.read_text()).get("format") == "procam-rig"  # noqa: E731
    args = dict(what="rig calibration", replaceable=is_ours)
    assert check_file_replaceable(ours, force=True, inputs=(), **args) is True
    with pytest.raises(OutputError, match="without --force"):
        check_file_replaceable(ours, force=False, inputs=(), **args)
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"format": "procam-capture"}))
    with pytest.raises(OutputError, match="is not a rig calibration; refusing"):
        check_file_replaceable(other, force=True, inputs=(), **args)
    with pytest.raises(OutputError, match="would be written into"):
        check_file_replaceable(ours, force=True, inputs=(tmp_path,), **args)


# -- item 13: what a killed run leaves behind ------------------------------------------------------------------

def test_a_later_run_removes_the_hidden_folders_of_a_killed_run_of_its_own_output_only(tmp_path):
    kind = layout.FRAMES
    out = _manifest(tmp_path / "frames", kind, frames=[])
    mine = hidden_sibling(out, "tmp")  # this process: alive
    host_pid = mine.name.split(".tmp-")[1].rsplit("-", 1)[0]
    host, pid = host_pid.rsplit("-", 1)
    dead = _dead_pid()
    stale_tmp = tmp_path / f".frames.tmp-{host}-{dead}-abcd1234"
    stale_old = tmp_path / f".frames.old-{host}-{dead}-abcd1235"
    other_name = tmp_path / f".other.tmp-{host}-{dead}-abcd1236"
    other_host = tmp_path / f".frames.tmp-elsewhere-{dead}-abcd1237"
    unnamed = tmp_path / ".frames.tmp-k2j3h4g5"  # no owner in its name: cannot be told stale
    for p in (stale_tmp, stale_old, other_name, other_host, unnamed):
        p.mkdir()
        (p / "x.png").write_bytes(b"x")
    assert set(stale_siblings(out)) == {stale_tmp, stale_old}
    folder = AtomicFolder(out, force=True, what=kind.what, replaceable=kind.holds, inputs=())
    _manifest(folder.tmp, kind, frames=[])
    folder.commit()
    left = {p.name for p in tmp_path.iterdir()}
    assert stale_tmp.name not in left and stale_old.name not in left
    assert {mine.name, other_name.name, other_host.name, unnamed.name, "frames"} <= left
    # a live run's folder is never touched, whatever its name says
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        running = tmp_path / f".frames.tmp-{host}-{live.pid}-abcd1238"
        running.mkdir()
        assert stale_siblings(out) == []
    finally:
        live.kill()
        live.wait()


def test_a_set_aside_old_folder_stays_while_the_output_holds_no_complete_result(tmp_path):
    kind = layout.DEMO
    out = tmp_path / "demo"
    host = hidden_sibling(tmp_path / "probe", "tmp").name.split(".tmp-")[1].rsplit("-", 2)[0]
    old = tmp_path / f".demo.old-{host}-{_dead_pid()}-abcd1234"
    _manifest(old, kind)  # a kill between setting the old demo aside and moving the new one in: the only copy
    with folder_in_place(out, force=True, what=kind.what, replaceable=kind.holds, inputs=()) as where:
        (where / "partial.txt").write_text("x")
        assert old.is_dir()
        _manifest(where, kind)
    with folder_in_place(out, force=True, what=kind.what, replaceable=kind.holds, inputs=()) as where:
        assert not old.exists()  # now a complete demo is in place, the old one goes
        _manifest(where, kind)


def test_a_killed_export_leaves_a_folder_the_next_export_removes(tmp_path):
    comp = _fake_compensation(tmp_path / "comp")
    code = (f"import os, sys, time\nsys.argv = ['procam', 'export-frames', {str(comp)!r}, '--out', "
            f"{str(tmp_path / 'frames')!r}]\nimport procam.addon.outputs as o\nreal = o.AtomicFolder.commit\n"
            "def hang(self):\n    print(self.tmp, flush=True); time.sleep(60)\no.AtomicFolder.commit = hang\n"
            "from procam.addon.cli.app import main\nmain(sys.argv[1:])\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    tmp = Path(proc.stdout.readline().strip())
    proc.kill()  # SIGKILL: no cleanup runs
    proc.wait()
    assert tmp.is_dir() and (tmp / "frames.json").is_file()
    assert main(["export-frames", str(comp), "--out", str(tmp_path / "frames")]) == 0
    assert not tmp.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


# -- item 1: export-frames -------------------------------------------------------------------------------------

def _fake_compensation(folder: Path) -> Path:
    folder.mkdir(parents=True)
    write_image(folder / "a_frame.png", np.full((6, 8, 3), 0.5, np.float32))
    return _manifest(folder, layout.COMPENSATION, mode="none", targets=[
        {"name": "a", "status": "done", "input": "a_input.png", "frame": "a_frame.png",
         "simulated": "a_simulated.png", "psnr_simulated": 30.0, "mode": "none"}])


def test_export_frames_replaces_only_a_frame_sequence_and_never_its_input(tmp_path, capsys):
    comp = _fake_compensation(tmp_path / "comp")
    user = _user_folder(tmp_path / "user")
    before = _snapshot(user)
    assert main(["export-frames", str(comp), "--out", str(user)]) == 2
    err = capsys.readouterr().err
    assert "already holds" not in err and "is not a projector frame sequence" in err
    assert main(["export-frames", str(comp), "--out", str(user), "--force"]) == 2
    assert _snapshot(user) == before
    comp_before = _snapshot(comp)
    assert main(["export-frames", str(comp), "--out", str(comp), "--force"]) == 2
    assert "input of this run" in capsys.readouterr().err
    assert _snapshot(comp) == comp_before
    frames = tmp_path / "frames"
    assert main(["export-frames", str(comp), "--out", str(frames)]) == 0
    assert main(["export-frames", str(comp), "--out", str(frames), "--force", "--first", "0"]) == 0
    assert (frames / "frame_0000.png").is_file()


# -- item 2: the lab's truth file ------------------------------------------------------------------------------

def test_lab_truth_replaces_only_a_truth_file_procam_wrote(tmp_path, capsys):
    from procam.addon.lab.truth import TRUTH_FORMAT
    from procam.addon.lab.lab import check_lab_outputs

    other = write_small_set(tmp_path / "other-set").path
    before = _snapshot(other)
    # another set's manifest, and any file inside another ProCam folder
    for truth in (other / "capture.json", other / "truth.json"):
        assert main(["lab", "--out", str(tmp_path / "new"), "--truth", str(truth), "--force", "--scale", "0.05"]) == 2
        assert f"would be written into {other}" in capsys.readouterr().err
    assert _snapshot(other) == before
    assert not (tmp_path / "new").exists()
    user = tmp_path / "my.json"
    user.write_text('{"mine": 1}')
    assert main(["lab", "--out", str(tmp_path / "new"), "--truth", str(user), "--force", "--scale", "0.05"]) == 2
    assert "is not a ProCam lab truth file" in capsys.readouterr().err
    assert user.read_text() == '{"mine": 1}'
    ours = tmp_path / "t.json"
    ours.write_text(json.dumps({"format": TRUTH_FORMAT}))
    check_lab_outputs(tmp_path / "new", ours, force=True)  # ours: replaced with force only
    with pytest.raises(LabError, match="without --force"):
        check_lab_outputs(tmp_path / "new", ours)
    (tmp_path / "t.surface.npz").write_bytes(b"user data")
    with pytest.raises(LabError, match="t.surface.npz exists and is not a ProCam lab truth file"):
        check_lab_outputs(tmp_path / "new", ours, force=True)


# -- every step: a folder of the user's files, and its own input, are refused with --force ------------------------

def _inputs(tmp_path: Path) -> SimpleNamespace:
    cset = write_small_set(tmp_path / "captures").path
    cal = _manifest(tmp_path / "cal", layout.CALIBRATION, capture_set=str(cset))
    comp = _fake_compensation(tmp_path / "comp")
    targets = tmp_path / "targets"
    targets.mkdir()
    write_image(targets / "t.png", np.full((6, 8, 3), 0.5, np.float32))
    session = tmp_path / "sessions" / "pose_00"
    session.mkdir(parents=True)
    write_image(session / "graycode_00.png", np.zeros((6, 8, 3), np.float32))
    rig = tmp_path / "rig.json"
    rig.write_text(json.dumps({"format": "procam-rig"}))
    mesh = tmp_path / "meshes" / "m.obj"
    mesh.parent.mkdir()
    mesh.write_text("v 0 0 1\n")
    seq = _manifest(tmp_path / "seq", layout.PATTERNS)
    photos = tmp_path / "photos"
    photos.mkdir()
    write_image(photos / "0000.png", np.zeros((6, 8, 3), np.float32))
    return SimpleNamespace(**locals())


#: (command line with OUT for the output, the input that --out names in case (b) or None)
STEPS = {
    "lab": (lambda i: ["lab", "--surface", str(i.mesh), "--truth", str(i.tmp_path / "t.json"), "--scale", "0.05",
                       "--out", "OUT"], lambda i: i.mesh.parent),
    "lab-board": (lambda i: ["lab-board", "--scale", "0.05", "--poses", "3", "--out", "OUT"], None),
    "patterns": (lambda i: ["patterns", "--projector-width", "32", "--projector-height", "24", "--out", "OUT"], None),
    "import-captures": (lambda i: ["import-captures", str(i.seq), str(i.photos), "--out", "OUT"], lambda i: i.photos),
    "undistort-captures": (lambda i: ["undistort-captures", str(i.cset), "--rig", str(i.rig), "--out", "OUT"],
                           lambda i: i.cset),
    "calibrate": (lambda i: ["calibrate", str(i.cset), "--out", "OUT"], lambda i: i.cset),
    "calibrate-rig": (lambda i: ["calibrate-rig", str(i.session), "--board", "9x7", "--projector", "8x6",
                                 "--out", "OUT"], lambda i: i.session / "rig.json"),
    "compensate": (lambda i: ["compensate", str(i.cal), str(i.targets / "t.png"), "--out", "OUT"], lambda i: i.cal),
    "compensate (folder of targets)": (lambda i: ["compensate", str(i.cal), str(i.targets / "t.png"), "--out", "OUT"],
                                       lambda i: i.targets),
    "evaluate": (lambda i: ["evaluate", str(i.cal), "--inputs", str(i.comp), "--targets", str(i.targets / "t.png"),
                            "--device", f"folder:{i.cset}", "--out", "OUT"], lambda i: i.comp),
    "evaluate (device)": (lambda i: ["evaluate", str(i.cal), "--inputs", str(i.comp), "--targets",
                                     str(i.targets / "t.png"), "--device", f"folder:{i.cset}", "--out", "OUT"],
                          lambda i: i.cset),
    "diagnose": (lambda i: ["diagnose", str(i.cal), "--out", "OUT"], lambda i: i.cal),
    "export-frames": (lambda i: ["export-frames", str(i.comp), "--out", "OUT"], lambda i: i.comp),
    "demo": (lambda i: ["demo", "--scale", "0.1", "--out", "OUT"], None),
}


@pytest.mark.parametrize("step", sorted(STEPS))
def test_every_step_refuses_user_files_and_its_own_input_with_force(step, tmp_path, capsys):
    args, own_input = STEPS[step]
    i = _inputs(tmp_path)
    before = _snapshot(tmp_path)
    user = tmp_path / "user"
    if step == "calibrate-rig":  # its output is one file
        user.mkdir()
        user = user / "rig.json"
        user.write_text('{"mine": 1}')
    else:
        _user_folder(user)
    everything = _snapshot(tmp_path)
    cmd = [str(user) if a == "OUT" else a for a in args(i)] + ["--force"]
    assert main(cmd) == 2, capsys.readouterr().err
    err = capsys.readouterr().err
    assert "refusing to replace" in err, err
    assert _snapshot(tmp_path) == everything
    if own_input is not None:
        target = own_input(i)
        cmd = [str(target) if a == "OUT" else a for a in args(i)] + ["--force"]
        assert main(cmd) == 2
        err = capsys.readouterr().err
        assert "input of this run" in err or "would be written into" in err, err
    assert {k: v for k, v in _snapshot(tmp_path).items() if not k.startswith("user")} == before
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


# -- item 13: Ctrl-C keeps what is finished ---------------------------------------------------------------------

def _calibration_folder(tmp_path: Path, capture_dir: Path) -> Path:
    from procam.addon.lab.truth import make_truth
    from procam.addon.stages.calibrate import Calibration
    from procam.addon.stages.warp import Warp
    from procam.addon.steps import calibrate as calibrate_step

    truth = make_truth("plane", camera_size=(32, 24), projector_size=(40, 30))
    folder = tmp_path / "cal"
    folder.mkdir()
    calibrate_step.write(folder, Calibration(truth.rig, truth.surface, Warp.identity(truth.rig.projector.input_size),
                                             str(capture_dir)), {})
    return folder


class _Stage:
    """Stage C stood in for: each target is "compensated" at once; the one named ``stop`` is interrupted."""

    stop, interrupt = "b", Cancelled

    def __init__(self, cal, options, *, device=None, progress=None) -> None:
        self.options, self.bias, self.range_map = options, None, None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        pass

    def load(self, path):
        from procam.addon.imageio import read_image
        return read_image(path), "linear"

    def area_for(self, image):
        return SimpleNamespace(width=8, height=6, x=0, y=0, to_dict=lambda: {"x": 0, "y": 0, "width": 8, "height": 6})

    def fix_range(self, images):
        return None

    def estimate_bias(self) -> None:
        pass

    def choose_radiometry(self) -> dict:
        return {"used": "global", "rule": "auto"}

    def compensate(self, image, *, name, what, cancel, verify, progress):
        if name == self.stop:
            raise self.interrupt("compensation was cancelled")
        result = SimpleNamespace(simulated=image, mode="none", seconds=1.0, captures=0, losses=[1.0, 0.5],
                                 report={"psnr_simulated_start": 10.0, "psnr_simulated": 20.0})
        return SimpleNamespace(warnings=[], input=image, frame=image, fitted=image, area=self.area_for(image),
                               result=result)

    def settings(self):
        return {"mode": "none"}

    def rig_record(self):
        return {}

    def bias_record(self):
        return None

    target_files = staticmethod(StageC.target_files)


@pytest.mark.parametrize("interrupt", [Cancelled, KeyboardInterrupt])
def test_ctrl_c_during_compensate_keeps_the_finished_targets(tmp_path, monkeypatch, interrupt):
    from procam.addon.steps import compensate as compensate_step

    cal = _calibration_folder(tmp_path, tmp_path / "captures")
    targets = []
    for name in "abc":
        targets.append(write_image(tmp_path / f"{name}.png", np.full((6, 8, 3), 0.5, np.float32)))
    monkeypatch.setattr(compensate_step, "StageC", type("S", (_Stage,), {"interrupt": interrupt}))
    out = tmp_path / "comp"
    with pytest.raises(Cancelled, match=r"after 1 of 3 target\(s\); the finished ones are kept"):
        compensate_step.run(compensate_step.CompensateOptions(cal, tuple(targets), out))
    view = compensate_step.read(out)
    assert [t.name for t in view.targets] == ["a"] and view.targets[0].frame_path.is_file()
    assert view.doc["complete"] is False
    assert [(t["name"], t["status"]) for t in view.doc["targets"]] == [("a", "done"), ("b", "cancelled")]
    assert sorted(p.name for p in out.iterdir()) == ["a_frame.png", "a_input.png", "a_simulated.png", "a_target.png",
                                                     "compensation.json"]
    # stopped at the first target: nothing finished, nothing written
    monkeypatch.setattr(compensate_step, "StageC", type("S", (_Stage,), {"stop": "a", "interrupt": interrupt}))
    with pytest.raises((Cancelled, KeyboardInterrupt)):
        compensate_step.run(compensate_step.CompensateOptions(cal, tuple(targets), tmp_path / "none"))
    assert not (tmp_path / "none").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


@pytest.mark.parametrize("interrupt", [Cancelled, KeyboardInterrupt])
def test_ctrl_c_during_the_precompute_keeps_the_calibration_without_its_operator(tmp_path, monkeypatch, interrupt):
    from procam.addon.steps import calibrate as calibrate_step
    from procam.addon.steps import transport as transport_step

    cset = write_small_set(tmp_path / "captures").path
    made = calibrate_step.read(_calibration_folder(tmp_path, cset))

    def store(folder, calibration, **kwargs):
        (Path(folder) / layout.TRANSPORT_NPZ).write_bytes(b"half an operator")
        raise interrupt("precomputing the transport operator was cancelled")

    monkeypatch.setattr(calibrate_step, "calibrate_captures",
                        lambda captures, **kwargs: SimpleNamespace(calibration=made, images={}))
    monkeypatch.setattr(calibrate_step, "store_transport", store)
    out = tmp_path / "calibration"
    with pytest.raises(Cancelled, match=f"kept in {out} without it: run `procam precompute {out}`"):
        calibrate_step.run(calibrate_step.CalibrateOptions(cset, out, with_blend=False))
    cal = calibrate_step.read(out)
    assert not (out / layout.TRANSPORT_NPZ).exists() and not (out / layout.TRANSPORT_JSON).exists()
    assert transport_step.load(cal, bounces=1, seed=0) is None  # what compensation reads: none stored
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_a_manifest_holds_only_json_a_value_that_is_no_number_is_null(tmp_path):
    def strict(text: str) -> object:
        def refuse(name: str) -> object:
            raise ValueError(f"{name} is not JSON")
        return json.loads(text, parse_constant=refuse)

    path = write_manifest(tmp_path / "m.json", {"psnr": float("nan"), "seam": np.float32(np.inf), "ok": 1.5,
                                                 "rows": np.array([1.0, np.nan]), "n": np.int64(3)})
    assert strict(path.read_text()) == {"psnr": None, "seam": None, "ok": 1.5, "rows": [1.0, None], "n": 3}


# -- issue 53: one writer at a time, whatever the command ---------------------------------------------------------

@contextlib.contextmanager
def _another_run_writing(target: Path) -> Iterator[int]:
    """Another process holds the writer lock of ``target`` for the ``with`` block; yields its process id."""
    code = ("import sys\nfrom procam.addon.outputs import writer_lock\nwith writer_lock(sys.argv[1]):\n"
            "    print('held', flush=True)\n    sys.stdin.read()\n")
    proc = subprocess.Popen([sys.executable, "-c", code, str(target)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True, env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    try:
        assert proc.stdout is not None and proc.stdout.readline() == "held\n"
        yield proc.pid
    finally:
        assert proc.stdin is not None
        proc.stdin.close()
        proc.wait(60)


def test_a_second_writer_of_an_output_is_refused_while_the_first_writes(tmp_path):
    kind = layout.FRAMES
    out = tmp_path / "frames"
    with _another_run_writing(out) as pid:
        assert lock_path(out).is_file()
        with pytest.raises(OutputBusyError, match=rf"another procam run \(process {pid} on .*\) is writing to "):
            AtomicFolder(out, what=kind.what, replaceable=kind.holds, inputs=())
        with pytest.raises(OutputBusyError, match="another procam run"), writer_lock(out):
            pass
    assert not lock_path(out).exists()  # the other run let go, and removed its lock file
    folder = AtomicFolder(out, what=kind.what, replaceable=kind.holds, inputs=())
    assert holds_writer(out) and lock_path(out).is_file()
    _manifest(folder.tmp, kind, frames=[])
    folder.commit()
    assert not holds_writer(out) and not lock_path(out).exists()
    # in one run, nested holders share the lock (a step holds it, and so does the folder it writes)
    with writer_lock(out):
        with writer_lock(out):
            pass
        assert holds_writer(out)
        folder = AtomicFolder(out, force=True, what=kind.what, replaceable=kind.holds, inputs=())
        folder.abort()
        assert holds_writer(out)
    assert not holds_writer(out)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_another_thread_is_another_writer(tmp_path):
    out = tmp_path / "out"
    held, done = threading.Event(), threading.Event()

    def hold() -> None:
        with writer_lock(out):
            held.set()
            done.wait(30)

    thread = threading.Thread(target=hold)
    thread.start()
    try:
        assert held.wait(30)
        with pytest.raises(OutputBusyError, match="another procam run"), writer_lock(out):
            pass
    finally:
        done.set()
        thread.join()
    with writer_lock(out):
        pass


@pytest.mark.parametrize("flock", [True, False])
def test_a_lock_left_by_a_killed_run_never_blocks_the_next(tmp_path, monkeypatch, flock):
    import procam.addon.outputs as outputs

    if not flock:  # where the OS has no advisory locks: an exclusive file, stale once its process has ended
        monkeypatch.setattr(outputs, "_fcntl", None)
    out = tmp_path / "out"
    host = hidden_sibling(tmp_path / "probe", "tmp").name.split(".tmp-")[1].rsplit("-", 2)[0]
    lock_path(out).write_text(f"{host} {_dead_pid()}\n")
    with writer_lock(out):
        assert lock_path(out).read_text() == f"{host} {os.getpid()}\n"
    assert not lock_path(out).exists()
    if not flock:  # a live process's lock file is honoured
        live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
        try:
            lock_path(out).write_text(f"{host} {live.pid}\n")
            with pytest.raises(OutputBusyError, match=f"process {live.pid}"), writer_lock(out):
                pass
        finally:
            live.kill()
            live.wait()


def test_a_refused_writer_leaves_no_folder_it_made_for_its_lock(tmp_path):
    out = tmp_path / "a" / "b" / "out"
    with _another_run_writing(out), pytest.raises(OutputBusyError), writer_lock(out):
        pass
    assert not (tmp_path / "a").exists()


#: the commands of STEPS, and those that write in place or one file: show, report, precompute
WRITERS = {**{name: args for name, (args, _) in STEPS.items()},
           "show": lambda i: ["show", str(i.cal), str(i.targets), "--out", "OUT"],
           "report": lambda i: ["report", str(i.comp), "--out", "OUT"]}


@pytest.mark.parametrize("step", sorted(WRITERS))
def test_every_writer_refuses_an_output_another_run_is_writing_before_any_work(step, tmp_path, capsys):
    i = _inputs(tmp_path)
    out = tmp_path / ("report.html" if step == "report" else "rig-out.json" if step == "calibrate-rig" else "out")
    before = _snapshot(tmp_path)
    cmd = [str(out) if a == "OUT" else a for a in WRITERS[step](i)]
    with _another_run_writing(out):
        assert main(cmd) == 2
        err = capsys.readouterr().err
        assert "another procam run" in err and f"is writing to {out}" in err, err
    assert _snapshot(tmp_path) == before
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


# -- issue 53: an output never lies inside an input ---------------------------------------------------------------

#: (command line with OUT, the input folder OUT is put inside)
INSIDE = {
    "import-captures": (STEPS["import-captures"][0], lambda i: i.photos),
    "import-captures --add-to": (lambda i: ["import-captures", str(i.seq), str(i.photos), "--add-to", str(i.cset),
                                            "--out", "OUT"], lambda i: i.cset),
    "undistort-captures": (STEPS["undistort-captures"][0], lambda i: i.cset),
    "calibrate": (STEPS["calibrate"][0], lambda i: i.cset),
    "calibrate-rig": (STEPS["calibrate-rig"][0], lambda i: i.session),
    "compensate": (STEPS["compensate"][0], lambda i: i.cal),
    # the calibration's capture set, named only in its manifest: refused before the calibration is read
    "compensate (capture set)": (STEPS["compensate"][0], lambda i: i.cset),
    "evaluate": (STEPS["evaluate"][0], lambda i: i.comp),
    "evaluate (device)": (STEPS["evaluate"][0], lambda i: i.cset),
    "diagnose": (STEPS["diagnose"][0], lambda i: i.cal),
    "diagnose (capture set)": (STEPS["diagnose"][0], lambda i: i.cset),
    "export-frames": (STEPS["export-frames"][0], lambda i: i.comp),
    "show": (WRITERS["show"], lambda i: i.cal),
    "show (capture set)": (WRITERS["show"], lambda i: i.cset),
    "show (folder of targets)": (WRITERS["show"], lambda i: i.targets),
    "report": (WRITERS["report"], lambda i: i.comp),
}


@pytest.mark.parametrize("step", sorted(INSIDE))
@pytest.mark.parametrize("force", [False, True])
def test_every_step_refuses_an_output_inside_one_of_its_inputs(step, force, tmp_path, capsys):
    args, folder = INSIDE[step]
    i = _inputs(tmp_path)
    name = {"report": "report.html", "calibrate-rig": "rig-out.json"}.get(step, "nested")
    out = folder(i) / "deeper" / name
    before = _snapshot(tmp_path)
    listing = sorted(str(p) for p in tmp_path.rglob("*"))
    cmd = [str(out) if a == "OUT" else a for a in args(i)] + (["--force"] if force else [])
    assert main(cmd) == 2
    err = capsys.readouterr().err
    assert f"{folder(i)}" in err and ("inside" in err or "would be written into" in err), err
    assert _snapshot(tmp_path) == before
    assert sorted(str(p) for p in tmp_path.rglob("*")) == listing  # not even an empty folder or a lock file


def test_check_replaceable_refuses_an_output_inside_an_input(tmp_path):
    kind = layout.FRAMES
    inp = _user_folder(tmp_path / "in")
    with pytest.raises(OutputError, match=rf"{tmp_path / 'in' / 'out'} lies inside {inp}, an input of this run"):
        check_replaceable(inp / "out", force=True, what=kind.what, replaceable=kind.holds, inputs=[inp])
    os.symlink(inp, tmp_path / "link")  # the same folder by another name
    with pytest.raises(OutputError, match="lies inside"):
        check_replaceable(tmp_path / "link" / "out", force=True, what=kind.what, replaceable=kind.holds, inputs=[inp])
    # a file input: its folder is no input
    assert check_replaceable(tmp_path / "out", force=True, what=kind.what, replaceable=kind.holds,
                             inputs=[inp / "notes.txt"]) is False


# -- issue 53: a refused compensate is refused before any work, and never blocks its own retry --------------------

@pytest.mark.parametrize("projectors", [2, 3])
def test_compensate_with_a_device_of_another_rig_is_refused_before_any_work(tmp_path, capsys, projectors):
    from procam.addon.lab.truth import make_truth

    cal = _calibration_folder(tmp_path, tmp_path / "captures")  # one projector
    truth = tmp_path / f"lab{projectors}.json"
    make_truth("plane", camera_size=(32, 24), projector_size=(40, 30), projectors=projectors).save(truth)
    target = write_image(tmp_path / "t.png", np.full((6, 8, 3), 0.5, np.float32))
    out = tmp_path / "comp"
    for step in (["compensate", str(cal), str(target)], ["show", str(cal), str(target)]):
        assert main([*step, "--device", f"lab:{truth}", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert f"lab:{truth} shows {projectors} projectors, but the calibration {cal} is of 1" in err, err
        assert "%" not in err  # no progress: refused before any work
        for internal in ("project_all", "LabTruth", "for_projector", "force=True"):
            assert internal not in err, err
        assert not out.exists()


def test_check_device_fits_names_each_side(tmp_path):
    from procam.addon.lab.truth import make_truth
    from procam.addon.steps import calibrate as calibrate_step
    from procam.addon.steps.stage_c import check_device_fits

    cal = calibrate_step.read(_calibration_folder(tmp_path, tmp_path / "captures"))
    one = tmp_path / "one.json"
    make_truth("plane", camera_size=(32, 24), projector_size=(40, 30)).save(one)
    check_device_fits(f"lab:{one}", cal)  # the same rig's number of projectors: nothing to say
    check_device_fits(None, cal)
    check_device_fits(f"folder:{tmp_path / 'missing'}", cal)  # what the device itself says, when it opens
    cset = write_small_set(tmp_path / "set").path
    check_device_fits(f"folder:{cset}", cal)


def test_an_incomplete_folder_of_a_failed_run_is_replaced_without_force(tmp_path, monkeypatch):
    from procam.addon.steps import compensate as compensate_step

    kind = layout.COMPENSATION
    half = _manifest(tmp_path / "half", kind, complete=False, targets=[])
    whole = _manifest(tmp_path / "whole", kind, complete=True, targets=[])
    check = lambda target, force=False: check_replaceable(  # noqa: E731
        target, force=force, what=kind.what, replaceable=kind.holds, inputs=(), incomplete=kind.incomplete)
    assert check(half) is True
    with pytest.raises(OutputError, match="never overwritten without --force") as refused:
        check(whole)
    assert "force=True" not in str(refused.value)
    with pytest.raises(OutputError, match="never overwritten without --force"):  # an incomplete one of a kind
        check_replaceable(half, force=False, what=kind.what, replaceable=kind.holds, inputs=())  # that cannot tell

    # the run: Ctrl-C after the first target leaves an incomplete folder, and the same command redoes it whole
    cal = _calibration_folder(tmp_path, tmp_path / "captures")
    targets = tuple(write_image(tmp_path / f"{n}.png", np.full((6, 8, 3), 0.5, np.float32)) for n in "abc")
    monkeypatch.setattr(compensate_step, "StageC", _Stage)
    out = tmp_path / "comp"
    with pytest.raises(Cancelled, match="run the same command again to redo it whole; no --force is needed"):
        compensate_step.run(compensate_step.CompensateOptions(cal, targets, out))
    assert compensate_step.read(out).doc["complete"] is False
    monkeypatch.setattr(compensate_step, "StageC", type("S", (_Stage,), {"stop": "none"}))
    view = compensate_step.run(compensate_step.CompensateOptions(cal, targets, out))
    assert view.doc["complete"] is True and [t.name for t in view.targets] == ["a", "b", "c"]


def test_export_of_a_compensation_without_finished_targets_names_the_command(tmp_path, capsys):
    comp = _manifest(tmp_path / "comp", layout.COMPENSATION, mode="none", targets=[], complete=False)
    assert main(["export-frames", str(comp), "--out", str(tmp_path / "frames")]) == 2
    err = capsys.readouterr().err
    assert "holds no finished targets to export; run procam compensate first" in err, err
    assert "run Compensate" not in err
