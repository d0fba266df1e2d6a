"""``procam show`` of a calibration of two projectors: one sequence per projector, resumable, refused when the rig
changed, in this process or on a local Dask cluster; evaluate reads it (images or a video); export-frames writes
one sequence per projector.

A small two-projector lab (camera 128×96, open loop, a few iterations): these tests check the bookkeeping and
the warm start, not compensation quality.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from procam.addon.cli.app import EXIT_OK, EXIT_USER, main

FAST = ["--iterations", "6"]


@pytest.fixture(scope="module")
def rig(two_projector_lab):
    """A calibrated two-projector lab (curve, 20 % overlap) and a sequence of three target frames."""
    from procam.addon.capture.patterns import smooth_random
    from procam.addon.imageio import write_image

    root = two_projector_lab
    seq = root / "frames"
    seq.mkdir()
    for n in (1, 2, 3):
        write_image(seq / f"shot_{n:04d}.png", (0.05 + 0.4 * smooth_random((120, 90), n, 20.0)).astype(np.float32))
    return root


def _manifest(out: Path) -> dict:
    return json.loads((out / "show.json").read_text())


def _frames(out: Path) -> dict[str, bytes]:
    """Every frame and θ file of a show, by its path in the folder."""
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*"))
            if p.is_file() and p.name != "show.json"}


def _projector_1_alone(cal: Path, dest: Path) -> Path:
    """The same calibration folder with projector 1 alone (a calibration of one projector, other contents)."""
    shutil.copytree(cal, dest)
    doc = json.loads((dest / "calibration.json").read_text())
    del doc["projectors"], doc["rig"]["projectors"]
    (dest / "calibration.json").write_text(json.dumps(doc))
    return dest


def _projector_2_moved(cal: Path, dest: Path) -> Path:
    """The same calibration folder with projector 2's pose moved 2 mm (as a new calibration of it would), its
    stored light-transport operators re-stamped to it so that loading it renders nothing."""
    from procam.addon.steps.calibrate import identity

    shutil.copytree(cal, dest)
    doc = json.loads((dest / "calibration.json").read_text())
    doc["rig"]["projectors"][1]["camera_from_projector"][0][3] += 0.002
    (dest / "calibration.json").write_text(json.dumps(doc))
    sha = identity(dest)["sha256"]
    for report in dest.glob("transport*.json"):
        (report).write_text(json.dumps({**json.loads(report.read_text()), "calibration_sha256": sha}))
    return dest


def test_a_show_of_two_projectors_is_one_sequence_per_projector_and_resumes_exactly(rig, tmp_path, capsys):
    from procam.addon.errors import Cancelled
    from procam.addon.imageio import read_image
    from procam.addon.steps import show as show_step
    from procam.addon.steps.stage_c import StageCOptions

    cal, seq = rig / "cal", rig / "frames"
    out = tmp_path / "show"
    args = ["show", str(cal), str(seq), "--out", str(out), *FAST]
    assert main(args) == EXIT_OK
    doc = _manifest(out)
    assert doc["projector_count"] == 2 and doc["complete"] and doc["frame_pattern"] == "projector_K/frame_####.png"
    files = _frames(out)
    assert sorted(files) == ["open_loop_bias_p1.npz", "open_loop_bias_p2.npz",
                             *(f"projector_{k}/frame_000{n}.png" for k in (1, 2) for n in (1, 2, 3))]
    for n in ("1", "2", "3"):
        entry = doc["frames"][n]
        assert [p["file"] for p in entry["projectors"]] == [f"projector_{k}/frame_000{n}.png" for k in (1, 2)]
        for k, p in enumerate(entry["projectors"]):
            data = files[p["file"]]
            assert (p["bytes"], p["sha256"]) == (len(data), hashlib.sha256(data).hexdigest())
            frame = read_image(out / p["file"])
            assert frame.shape[1::-1] == tuple(doc["projectors"][k]["frame_size"])
        assert sum(p["share"] for p in entry["projectors"]) == pytest.approx(1.0, abs=0.01)
    # Each projector warm-starts from its own previous frame: frames 2 and 3 start far closer than cold ones.
    assert [doc["frames"][n]["warm_start"] for n in ("1", "2", "3")] == [None, 1, 2]
    cold = tmp_path / "cold"
    assert main(["show", str(cal), str(seq), "--out", str(cold), *FAST, "--cold-start"]) == EXIT_OK
    for n in ("2", "3"):
        assert doc["frames"][n]["psnr_model_start"] > _manifest(cold)["frames"][n]["psnr_model_start"] + 2.0

    # A rerun does nothing and changes no byte.
    assert main(args) == EXIT_OK
    assert (_manifest(out)["runs"][-1]["done"], _manifest(out)["runs"][-1]["skipped"]) == (0, 3)
    assert _frames(out) == files
    # One projector's file of a frame missing: that frame alone is redone, to the same bytes.
    (out / "projector_2" / "frame_0002.png").unlink()
    assert main(args) == EXIT_OK
    assert (_manifest(out)["runs"][-1]["done"], _manifest(out)["runs"][-1]["skipped"]) == (1, 2)
    assert _frames(out) == files

    # Cancelled once frame 1 is finished: frame 1 kept whole, then a rerun resumes to a fresh run's bytes.
    cut = tmp_path / "cut"
    options = show_step.ShowOptions(cal, (seq,), cut, StageCOptions(iterations=6))
    with pytest.raises(Cancelled):
        show_step.run(options, cancel=lambda: "1" in _manifest(cut)["frames"])
    assert list(_manifest(cut)["frames"]) == ["1"] and _manifest(cut)["runs"][-1]["status"] == "cancelled"
    assert not (cut / "projector_1" / "frame_0002.png").exists()
    assert not [p.name for p in cut.rglob(".*")]  # no temporary file left behind
    result = show_step.run(options)
    assert (result.done, result.skipped) == ([2, 3], [1])
    assert _frames(cut) == files

    # The folder resumed with another rig: refused, naming the projectors; nothing changed.
    one = _projector_1_alone(cal, tmp_path / "cal1")
    capsys.readouterr()
    assert main(["show", str(one), str(seq), "--out", str(out), *FAST]) == EXIT_USER
    err = capsys.readouterr().err
    assert "projector 2 removed: the show was made for 2 projectors, the calibration has 1" in err
    assert "--force" in err and _frames(out) == files
    # Projector 2 calibrated again (its pose moved 2 mm): refused, naming it; nothing changed.
    again = _projector_2_moved(cal, tmp_path / "cal2")
    assert main(["show", str(again), str(seq), "--out", str(out), *FAST]) == EXIT_USER
    err = capsys.readouterr().err
    assert "projector 2 calibrated again" in err and "projector 1 calibrated" not in err
    assert "--force" in err and _frames(out) == files

    # evaluate measures the show's frames of both projectors at once.
    device = f"lab:{rig / 'lab.truth.json'}"
    assert main(["evaluate", str(cal), "--inputs", str(out), "--targets", *map(str, sorted(seq.glob("*.png"))),
                 "--device", device, "--out", str(tmp_path / "eval"), "--no-repeat"]) == EXIT_OK
    metrics = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert metrics["projector_count"] == 2 and len(metrics["targets"]) == 3
    assert metrics["mean"]["psnr"] > metrics["mean_uncompensated"]["psnr"] + 3
    # a one-projector calibration cannot evaluate it
    assert main(["evaluate", str(one), "--inputs", str(out), "--targets", str(seq / "shot_0001.png"),
                 "--device", device, "--out", str(tmp_path / "eval1")]) == EXIT_USER
    err = capsys.readouterr().err
    assert "shows 2 projectors, but the calibration" in err and "is of 1" in err, err


def test_a_show_of_two_projectors_on_a_local_cluster_is_one_process_s_and_resumes(rig, tmp_path, capsys):
    """Frames of two projectors as tasks on a local two-worker Dask cluster: the same bytes as one process (both
    with one Dr.Jit thread), each projector warm-started from its own frame; a run cancelled once a frame is
    finished keeps it whole and a rerun does only the rest."""
    from procam.addon.errors import Cancelled
    from procam.addon.steps import show as show_step
    from procam.addon.steps.stage_c import StageCOptions

    cal, seq = rig / "cal", rig / "frames"
    base = ["show", str(cal), str(seq), *FAST, "--chunk", "2", "--threads", "1"]
    single = tmp_path / "single"
    assert main([*base, "--out", str(single)]) == EXIT_OK
    out = tmp_path / "cluster"
    written: list[str] = []
    options = show_step.ShowOptions(cal, (seq,), out, StageCOptions(iterations=6), chunk=2, workers=2, threads=1)
    with pytest.raises(Cancelled):
        show_step.run(options, progress=lambda msg, frac: written.append(msg) if "dB (model)" in msg else None,
                      cancel=lambda: bool(written))
    doc = _manifest(out)
    kept = {n for n, e in doc["frames"].items() if e["status"] == "done"}
    assert doc["runs"][-1]["status"] == "cancelled" and 1 <= len(kept) < 3
    assert not [p.name for p in out.rglob(".*")]  # no temporary file left behind
    for n in kept:  # a kept frame is whole: every projector's file, as recorded
        assert all(hashlib.sha256((out / p["file"]).read_bytes()).hexdigest() == p["sha256"]
                   for p in doc["frames"][n]["projectors"])
    before = {p: (out / p).stat().st_mtime_ns for p in _frames(out) if p.startswith("projector_")}
    capsys.readouterr()
    assert main([*base, "--out", str(out), "--workers", "2"]) == EXIT_OK
    doc = _manifest(out)
    assert (doc["runs"][-1]["skipped"], doc["runs"][-1]["done"]) == (len(kept), 3 - len(kept))
    assert doc["runs"][-1]["where"] == "local cluster, 2 worker(s)" and doc["complete"]
    assert all((out / p).stat().st_mtime_ns == t for p, t in before.items())
    assert _frames(out) == _frames(single)
    assert [doc["frames"][n]["warm_start"] for n in ("1", "2", "3")] == [None, 1, None]
    assert [len(doc["frames"][n]["projectors"]) for n in ("1", "2", "3")] == [2, 2, 2]


def test_a_one_projector_show_resumed_with_two_is_refused_naming_the_added_projector(rig, tmp_path, capsys):
    cal, seq = rig / "cal", rig / "frames"
    one = _projector_1_alone(cal, tmp_path / "cal1")
    out = tmp_path / "show"
    # Projector 1 alone cannot read the two projectors' capture set: no θ, and an area given.
    args = [str(seq / "shot_0001.png"), "--out", str(out), *FAST, "--no-bias", "--area", "24,24,63,47"]
    assert main(["show", str(one), *args]) == EXIT_OK
    before = _frames(out)
    assert list(before) == ["frame_0001.png"]
    capsys.readouterr()
    assert main(["show", str(cal), *args]) == EXIT_USER
    assert "projector 2 added: the show was made for 1 projector, the calibration has 2" in capsys.readouterr().err
    assert _frames(out) == before
    # --force redoes it for the two projectors, and the one-projector frame is gone.
    assert main(["show", str(cal), *args, "--force"]) == EXIT_OK
    assert sorted(_frames(out)) == ["projector_1/frame_0001.png", "projector_2/frame_0001.png"]


def test_export_frames_of_two_projectors_is_one_sequence_per_projector(rig, tmp_path, capsys):
    """Every projector's frames copied bit for bit into its own numbered sequence, recorded per projector; a
    compensation whose record lacks a projector's frame is refused and nothing is written."""
    cal, seq = rig / "cal", rig / "frames"
    comp = tmp_path / "comp"
    targets = [str(seq / f"shot_000{n}.png") for n in (1, 2)]
    assert main(["compensate", str(cal), *targets, *FAST, "--out", str(comp)]) == EXIT_OK
    out = tmp_path / "frames"
    assert main(["export-frames", str(comp), "--out", str(out), "--first", "9"]) == EXIT_OK
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()) == [
        "frames.json", "projector_1/frame_0009.png", "projector_1/frame_0010.png", "projector_2/frame_0009.png",
        "projector_2/frame_0010.png"]
    doc = json.loads((out / "frames.json").read_text())
    assert doc["projector_count"] == 2 and doc["frame_pattern"] == "projector_K/frame_####.png"
    assert [p["frame_size"] for p in doc["projectors"]] == [[160, 120], [160, 120]]
    for frame, name in zip(doc["frames"], ("shot_0001", "shot_0002")):
        assert frame["target"] == name and frame["file"] == frame["projectors"][0]["file"]
        for k, p in enumerate(frame["projectors"]):
            data = (out / p["file"]).read_bytes()
            assert data == (comp / f"{name}_frame_p{k + 1}.png").read_bytes()
            assert (p["projector"], p["bytes"], p["sha256"]) == (k + 1, len(data), hashlib.sha256(data).hexdigest())
    # A record naming projector 1's frame alone: refused, nothing written.
    manifest = json.loads((comp / "compensation.json").read_text())
    manifest["targets"][1]["projectors"] = manifest["targets"][1]["projectors"][:1]
    (comp / "compensation.json").write_text(json.dumps(manifest))
    capsys.readouterr()
    assert main(["export-frames", str(comp), "--out", str(tmp_path / "bad")]) == EXIT_USER
    assert "names the frames of 1 projector(s), but the compensation is for 2" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_a_video_show_of_two_projectors_is_evaluated_against_the_video(rig, tmp_path):
    from tests.test_show import _video

    clip = _video(tmp_path / "clip.avi", 2)
    out = tmp_path / "show"
    assert main(["show", str(rig / "cal"), str(clip), "--out", str(out), *FAST]) == EXIT_OK
    assert sorted(_frames(out)) == ["open_loop_bias_p1.npz", "open_loop_bias_p2.npz", "projector_1/frame_0001.png",
                                    "projector_1/frame_0002.png", "projector_2/frame_0001.png",
                                    "projector_2/frame_0002.png"]
    assert _manifest(out)["frames"]["2"]["warm_start"] == 1
    assert main(["evaluate", str(rig / "cal"), "--inputs", str(out), "--targets", str(clip), "--device",
                 f"lab:{rig / 'lab.truth.json'}", "--out", str(tmp_path / "eval"), "--no-repeat"]) == EXIT_OK
    metrics = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert [t["name"] for t in metrics["targets"]] == ["frame_0001", "frame_0002"]
    assert metrics["mean"]["psnr"] > metrics["mean_uncompensated"]["psnr"] + 3
