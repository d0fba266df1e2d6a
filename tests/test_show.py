"""``procam show``: a numbered target sequence → numbered 16-bit projector frames, resumable, at tiny size.

The calibration comes from the lab's truth (``stored_calibration`` fixture), the
schedule is a few iterations at 1 spp: these tests check the bookkeeping
(numbering, manifest, resume, failures, refusals), not compensation quality.
"""

from __future__ import annotations

import hashlib
import json
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from procam.addon.cli.app import EXIT_CANCELLED, EXIT_INTERNAL, EXIT_OK, EXIT_USER, main
from procam.addon.imageio import write_image
from procam.addon.outputs import OutputBusyError
from procam.addon.steps.layout import frame_name
from procam.addon.steps.show import MANIFEST, SequenceError, ShowFolder, frame_digits, list_frames

FAST = ["--iterations", "4", "--spp", "1"]


def _target(seed: int, w: int = 160, h: int = 120) -> np.ndarray:
    from procam.addon.capture.patterns import smooth_random

    return (0.05 + 0.4 * smooth_random((w, h), seed, 20.0)).astype(np.float32)


def _frames(folder: Path, numbers, prefix: str = "shot_") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for n in numbers:
        write_image(folder / f"{prefix}{n:04d}.png", _target(n))
    return folder


def _manifest(out: Path) -> dict:
    return json.loads((out / MANIFEST).read_text())


def _mtimes(out: Path) -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in sorted(out.glob("frame_*.png"))}


def _leftovers(out: Path) -> list[str]:
    """Temporary files of atomic writes: none may stay behind, whatever happened."""
    return [p.name for p in out.iterdir() if p.name.startswith(".")]


# -- listing a sequence (no rendering) -----------------------------------------------------------

def test_list_frames(tmp_path):
    seq = tmp_path / "seq"
    seq.mkdir()
    for n in (7, 8, 10):
        (seq / f"shot_{n:04d}.png").write_bytes(b"x")
    (seq / "notes.txt").write_text("not an image")
    (seq / ".hidden.png").write_bytes(b"x")
    by_folder = list_frames([seq])
    assert [(f.number, f.path.name) for f in by_folder] == [(7, "shot_0007.png"), (8, "shot_0008.png"),
                                                            (10, "shot_0010.png")]
    assert [f.number for f in list_frames([seq / "shot_####.png"])] == [7, 8, 10]
    assert [f.number for f in list_frames([seq / "shot_%04d.png"])] == [7, 8, 10]
    assert [f.number for f in list_frames([seq / "shot_0010.png", seq / "shot_0007.png"])] == [7, 10]
    # Names without distinct numbers: 1, 2, … in natural order.
    plain = tmp_path / "plain"
    plain.mkdir()
    for name in ("b.png", "a10.png", "a9.png"):
        (plain / name).write_bytes(b"x")
    assert [(f.number, f.path.name) for f in list_frames([plain])] == [(1, "a9.png"), (2, "a10.png"), (3, "b.png")]
    assert frame_name(7, frame_digits(by_folder)) == "frame_0007.png"
    assert frame_digits([type(by_folder[0])(123456, seq)]) == 6
    (seq / "shot_08.png").write_bytes(b"x")  # frame 8 twice under the pattern shot_#.png
    with pytest.raises(SequenceError, match="both match"):
        list_frames([seq / "shot_#.png"])
    for bad, msg in (([tmp_path / "none_####.png"], "no file"), ([tmp_path / "missing.png"], "not found"),
                     ([tmp_path / "nofolder" / "x_####.png"], "does not exist"), ([tmp_path / "empty"], "not found"),
                     ([seq, seq / "shot_0007.png"], "folder"), ([seq / "a_#_#.png"], "more than one")):
        with pytest.raises(SequenceError, match=msg):
            list_frames(bad)
    (tmp_path / "empty").mkdir()
    with pytest.raises(SequenceError, match="no images"):
        list_frames([tmp_path / "empty"])


def test_show_folder_refuses_foreign_folders_and_second_writers(tmp_path):
    user = tmp_path / "user"
    user.mkdir()
    (user / "important.txt").write_text("keep me")
    with pytest.raises(SequenceError, match="not a show folder"):
        ShowFolder(user).open()
    first = ShowFolder(tmp_path / "show")
    assert first.open() is None
    try:  # another run: another process, or another thread (a second job in Blender)
        refused: list[BaseException] = []

        def second() -> None:
            try:
                ShowFolder(tmp_path / "show").open()
            except OutputBusyError as exc:
                refused.append(exc)

        thread = threading.Thread(target=second)
        thread.start()
        thread.join()
        assert len(refused) == 1 and "another procam run" in str(refused[0])
    finally:
        first.unlock()
    second = ShowFolder(tmp_path / "show")
    assert second.open() is None  # free again once the first one let go
    second.unlock()


# -- the command end to end ----------------------------------------------------------------------

def test_show_end_to_end_resume_and_refusals(stored_calibration, tmp_path, capsys):
    cal_dir, _, _ = stored_calibration()
    seq = _frames(tmp_path / "frames", (7, 8, 9))
    out = tmp_path / "show"
    args = ["show", str(cal_dir), str(seq / "shot_####.png"), "--out", str(out), *FAST]
    assert main(args) == EXIT_OK
    doc = _manifest(out)
    cal = json.loads((cal_dir / "calibration.json").read_text())
    fw, fh = cal["rig"]["projector"]["intrinsics"]["width"], cal["rig"]["projector"]["intrinsics"]["height"]
    assert sorted(p.name for p in out.glob("frame_*.png")) == ["frame_0007.png", "frame_0008.png", "frame_0009.png"]
    for p in out.glob("frame_*.png"):
        raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16 and raw.shape == (fh, fw, 3)
        assert p.stat().st_mode & 0o044  # readable by a media server running as another user
    assert doc["complete"] and doc["mode"] == "open-loop"
    assert doc["calibration"]["sha256"] == hashlib.sha256((cal_dir / "calibration.json").read_bytes()).hexdigest()
    assert doc["schedule"]["iterations"] == 4 and doc["schedule"]["spp"] == 1
    assert doc["effects"]["interreflection_bounces"] == 1 and doc["open_loop_bias"]["file"]
    for n in ("7", "8", "9"):
        e = doc["frames"][n]
        assert e["status"] == "done" and e["seconds"] > 0 and np.isfinite(e["psnr_model"])
        assert e["sha256"] == hashlib.sha256((out / e["file"]).read_bytes()).hexdigest()
    assert (doc["runs"][-1]["done"], doc["runs"][-1]["skipped"]) == (3, 0)
    assert "3 frame(s) compensated" in capsys.readouterr().out
    assert not _leftovers(out)

    # Rerun: nothing recomputed, no file touched.
    before = _mtimes(out)
    assert main(args) == EXIT_OK
    doc = _manifest(out)
    assert (doc["runs"][-1]["done"], doc["runs"][-1]["skipped"], doc["runs"][-1]["status"]) == (0, 3, "complete")
    assert _mtimes(out) == before

    # A damaged frame (same size, other bytes) is redone; the others stay as they are.
    damaged = out / "frame_0008.png"
    data = bytearray(damaged.read_bytes())
    data[-20] ^= 0xFF
    damaged.write_bytes(bytes(data))
    assert main(args) == EXIT_OK
    doc = _manifest(out)
    assert (doc["runs"][-1]["done"], doc["runs"][-1]["skipped"]) == (1, 2)
    after = _mtimes(out)
    assert after["frame_0007.png"] == before["frame_0007.png"] and after["frame_0009.png"] == before["frame_0009.png"]
    assert doc["frames"]["8"]["sha256"] == hashlib.sha256(damaged.read_bytes()).hexdigest()
    capsys.readouterr()

    # Other settings, or a changed target: refused, nothing touched, until --force.
    runs = len(doc["runs"])
    assert main(args[:-4] + ["--iterations", "3", "--spp", "1"]) == EXIT_USER
    err = capsys.readouterr().err
    assert "other settings" in err and "iterations" in err and "--force" in err and "Traceback" not in err
    # frames through each camera pixel's own model are other frames (this lab's auto choice kept the global ones)
    assert main(args + ["--radiometry", "pixel"]) == EXIT_USER
    err = capsys.readouterr().err
    assert "other settings" in err and "radiometry" in err
    write_image(seq / "shot_0009.png", _target(99))
    assert main(args) == EXIT_USER
    assert "frame(s) 9 changed" in capsys.readouterr().err
    assert _mtimes(out) == after and len(_manifest(out)["runs"]) == runs
    assert main(args[:-4] + ["--iterations", "3", "--spp", "1", "--no-bias", "--force"]) == EXIT_OK
    doc = _manifest(out)
    assert (doc["runs"][-1]["done"], doc["runs"][-1]["skipped"]) == (3, 0) and doc["schedule"]["iterations"] == 3
    assert doc["mode"] == "none" and not (out / "open_loop_bias.npz").exists()
    assert doc["complete"] and not _leftovers(out)

    # A manifest entry naming a file outside the folder, or a frame file that is a link leaving it, is not a
    # finished frame: it is redone into its own name, and the file outside is neither counted nor touched.
    first = _bytes(out)
    elsewhere, linked = tmp_path / "elsewhere.png", tmp_path / "linked.png"
    elsewhere.write_bytes(first["frame_0007.png"])
    linked.write_bytes(first["frame_0009.png"])
    doc["frames"]["7"]["file"] = str(elsewhere)
    (out / MANIFEST).write_text(json.dumps(doc))
    (out / "frame_0007.png").unlink()
    (out / "frame_0009.png").unlink()
    (out / "frame_0009.png").symlink_to(linked)
    capsys.readouterr()
    assert main(args[:-4] + ["--iterations", "3", "--spp", "1", "--no-bias"]) == EXIT_OK
    doc = _manifest(out)
    assert (doc["runs"][-1]["done"], doc["runs"][-1]["skipped"]) == (2, 1) and doc["frames"]["7"]["file"] == \
        "frame_0007.png"
    assert [doc["frames"][n]["run"] == doc["runs"][-1]["run"] for n in ("7", "8", "9")] == [True, False, True]
    assert not (out / "frame_0009.png").is_symlink() and _bytes(out) == first
    assert elsewhere.read_bytes() == first["frame_0007.png"] and linked.read_bytes() == first["frame_0009.png"]


def test_show_failure_crash_and_cancel_resume(stored_calibration, tmp_path, capsys, monkeypatch):
    from procam.addon.stages.compensate import Compensator

    cal_dir, _, _ = stored_calibration()
    seq = _frames(tmp_path / "frames", (1, 2, 3))
    (seq / "shot_0002.png").write_bytes(b"this is not a PNG")  # a damaged frame in the middle
    out = tmp_path / "show"
    args = ["show", str(cal_dir), str(seq), "--out", str(out), *FAST, "--no-bias"]
    assert main(args) == EXIT_USER
    err = capsys.readouterr().err
    assert "1 frame(s) failed" in err and "frame 2" in err and "rerun" in err
    doc = _manifest(out)
    assert sorted(p.name for p in out.glob("frame_*.png")) == ["frame_0001.png", "frame_0003.png"]
    assert doc["frames"]["2"]["status"] == "failed" and "cannot read" in doc["frames"]["2"]["error"]
    assert [f["frame"] for f in doc["failures"]] == [2] and not doc["complete"]
    assert doc["runs"][-1]["status"] == "incomplete" and not _leftovers(out)
    # Frame 3 had no frame 2 to warm-start from: computed cold, and recorded (and said) so.
    assert doc["frames"]["3"]["warm_start"] is None and doc["frames"]["3"]["warm_start_missing"] == 2
    assert "frame 3: warning: computed cold" in err
    # Fixed: the rerun does frame 2, and frame 3 again from frame 2's answer (as a fresh run would); frame 1 stays.
    write_image(seq / "shot_0002.png", _target(2))
    before = _mtimes(out)
    assert main(args) == EXIT_OK
    doc = _manifest(out)
    assert doc["complete"] and (doc["runs"][-1]["done"], doc["runs"][-1]["skipped"]) == (2, 1)
    assert _mtimes(out)["frame_0001.png"] == before["frame_0001.png"]
    assert [doc["frames"][n]["warm_start"] for n in ("1", "2", "3")] == [None, 1, 2]
    resumed = _bytes(out)

    # A bug (crash) in the middle of a fresh show: exit 1, short message, traceback in a log, frame 1 kept.
    real, calls = Compensator.run, []

    def flaky(self, *a, **kw):
        calls.append(1)
        if len(calls) == 2:
            raise ZeroDivisionError("simulated crash")
        return real(self, *a, **kw)

    monkeypatch.setattr(Compensator, "run", flaky)
    monkeypatch.setenv("PROCAM_LOG_DIR", str(tmp_path / "logs"))
    out2 = tmp_path / "show2"
    args2 = ["show", str(cal_dir), str(seq), "--out", str(out2), *FAST, "--no-bias"]
    assert main(args2) == EXIT_INTERNAL
    err = capsys.readouterr().err
    assert "internal error: ZeroDivisionError: simulated crash" in err and "Traceback" not in err
    logs = list((tmp_path / "logs").glob("procam-show-*.log"))
    assert len(logs) == 1 and "Traceback" in logs[0].read_text() and str(logs[0]) in err
    doc = _manifest(out2)
    assert doc["runs"][-1]["status"].startswith("crashed") and list(doc["frames"]) == ["1"]
    assert [p.name for p in out2.glob("frame_*.png")] == ["frame_0001.png"] and not _leftovers(out2)

    # Ctrl-C during frame 2 of the rerun: exit 130, frame 2 not written, then a rerun completes.
    def interrupted(self, *a, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(Compensator, "run", interrupted)
    assert main(args2) == EXIT_CANCELLED
    assert "cancelled" in capsys.readouterr().err
    assert _manifest(out2)["runs"][-1]["status"] == "cancelled" and not (out2 / "frame_0002.png").exists()
    monkeypatch.setattr(Compensator, "run", real)
    assert main(args2) == EXIT_OK
    doc = _manifest(out2)
    assert doc["complete"] and (doc["runs"][-1]["done"], doc["runs"][-1]["skipped"]) == (2, 1)
    assert [r["status"] for r in doc["runs"]] == ["crashed: ZeroDivisionError: simulated crash", "cancelled",
                                                  "complete"]
    assert not _leftovers(out2)
    # The show resumed after its failed frame is the show made without one (out2: frames 2 and 3 computed in one
    # run from the fixed target): byte-identical.
    assert _bytes(out2) == resumed

    # A disk that refuses the frame stops the show at once (every frame would fail alike): exit 2, said so.
    import procam.addon.steps.show as show_step

    def full_disk(path, image):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(show_step, "write_atomic_bytes", full_disk)
    out3 = tmp_path / "show3"
    assert main(["show", str(cal_dir), str(seq / "shot_0001.png"), str(seq / "shot_0003.png"), "--out", str(out3),
                 *FAST, "--no-bias"]) == EXIT_USER
    assert "cannot write frame 1" in capsys.readouterr().err
    doc = _manifest(out3)
    assert doc["runs"][-1]["status"].startswith("stopped") and doc["frames"] == {} and not doc["failures"]


def test_show_refuses_a_foreign_folder_before_any_work(stored_calibration, tmp_path, capsys):
    cal_dir, _, _ = stored_calibration()
    seq = _frames(tmp_path / "frames", (1,))
    user = tmp_path / "user"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    assert main(["show", str(cal_dir), str(seq), "--out", str(user), *FAST]) == EXIT_USER
    assert "not a show folder" in capsys.readouterr().err
    assert [p.name for p in user.iterdir()] == ["notes.txt"]
    assert main(["show", str(cal_dir), str(tmp_path / "nothing_####.png"), "--out", str(tmp_path / "o")]) == EXIT_USER
    assert "no file" in capsys.readouterr().err and not (tmp_path / "o").exists()
    (tmp_path / "not_a_calibration").mkdir()  # (tmp_path itself would be an input holding the output)
    assert main(["show", str(tmp_path / "not_a_calibration"), str(seq), "--out", str(tmp_path / "o")]) == EXIT_USER
    assert "calibration" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_show_closed_loop_through_the_lab(stored_calibration, tmp_path, capsys):
    cal_dir, _, truth = stored_calibration()
    seq = _frames(tmp_path / "frames", (5,))
    out = tmp_path / "show"
    args = ["show", str(cal_dir), str(seq), "--out", str(out), "--iterations", "4", "--spp", "1",
            "--capture-every", "1"]
    assert main(args + ["--device", f"lab:{truth}"]) == EXIT_OK
    doc = _manifest(out)
    assert doc["mode"] == "closed-loop" and doc["device"] == f"lab:{Path(truth).absolute()}"
    assert doc["frames"]["5"]["captures"] >= 1 and doc["schedule"]["capture_every"] == 1
    capsys.readouterr()
    # The same folder without the device (open loop) is another setting: refused.
    assert main(args) == EXIT_USER
    err = capsys.readouterr().err
    assert "mode: 'closed-loop' → 'open-loop'" in err and "--force" in err


def test_show_range_auto_is_one_map_for_the_show(stored_calibration, tmp_path, capsys):
    """``--range auto`` fits one gain and offset to the show's frames (never per frame), records it in the settings,
    and a rerun with the same frames resumes under the same map."""
    from procam.addon.capture.patterns import smooth_random

    cal_dir, _, _ = stored_calibration()
    seq = tmp_path / "frames"
    seq.mkdir()
    for n in (1, 2):
        write_image(seq / f"shot_{n:04d}.png", (0.35 + 0.65 * smooth_random((160, 120), n, 20.0)).astype(np.float32))
    out = tmp_path / "show"
    args = ["show", str(cal_dir), str(seq / "shot_####.png"), "--out", str(out), *FAST, "--range", "auto"]
    assert main(args) == EXIT_OK
    rng = _manifest(out)["settings"]["range"]
    assert 0 < rng["gain"] < 1 and rng["clipped_share"] <= 0.0101
    assert main(args) == EXIT_OK and _manifest(out)["runs"][-1]["skipped"] == 2
    # Another map is another show: refused without --force, like any other setting.
    assert main([*args[:-1], f"{rng['gain'] * 0.9},{rng['offset']}"]) == EXIT_USER
    assert "range.gain" in capsys.readouterr().err


# -- video, warm start, frames on a cluster --------------------------------------------------------

def _video(path: Path, n: int, seed: int = 0) -> Path:
    """A small MJPG .avi (OpenCV's writer, no codec outside its wheels) of a slowly moving pattern."""
    from procam.addon.capture.patterns import smooth_random

    base = smooth_random((200, 120), seed, 20.0)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 24, (160, 120))
    assert writer.isOpened()
    for i in range(n):
        img = (0.1 + 0.6 * base[:, 4 * i:4 * i + 160]) * 255
        writer.write(np.round(img[..., ::-1]).astype(np.uint8))
    writer.release()
    return path


def _bytes(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out.glob("frame_*.png"))}


def test_show_from_a_video_warm_starts_and_resumes_exactly(stored_calibration, tmp_path, capsys):
    cal_dir, _, _ = stored_calibration()
    video = _video(tmp_path / "clip.avi", 3)
    assert [(f.number, f.index) for f in list_frames([video])] == [(1, 0), (2, 1), (3, 2)]
    out = tmp_path / "show"
    args = ["show", str(cal_dir), str(video), "--out", str(out), *FAST, "--no-bias", "--chunk", "2"]
    assert main(args) == EXIT_OK
    doc = _manifest(out)
    assert doc["video"]["frames"] == 3
    assert doc["video"]["source_sha256"] == hashlib.sha256(video.read_bytes()).hexdigest()
    assert doc["settings"]["warm_start"]["chunk"] == 2
    # Chunks by frame number {1, 2}, {3}: frame 2 starts from frame 1, frames 1 and 3 start cold.
    assert [doc["frames"][n]["warm_start"] for n in ("1", "2", "3")] == [None, 1, None]
    assert doc["frames"]["2"]["video_frame"] == 2 and "8-bit video" in doc["frames"]["2"]["encoding"]
    first = _bytes(out)
    # Frame 2 redone on resume starts from frame 1 read back from disk: the same bytes as when computed in a run.
    (out / "frame_0002.png").unlink()
    assert main(args) == EXIT_OK
    assert _manifest(out)["runs"][-1]["done"] == 1 and _bytes(out) == first
    # Cold start is another setting; a changed video is noticed like a changed image.
    capsys.readouterr()
    assert main(args + ["--cold-start"]) == EXIT_USER
    assert "warm_start" in capsys.readouterr().err
    _video(video, 3, seed=5)
    assert main(args) == EXIT_USER
    assert "the video" in capsys.readouterr().err and _bytes(out) == first
    cold = tmp_path / "cold"
    assert main(["show", str(cal_dir), str(video), "--out", str(cold), *FAST, "--no-bias", "--cold-start"]) == EXIT_OK
    doc = _manifest(cold)
    assert doc["settings"]["warm_start"] is None and all(e["warm_start"] is None for e in doc["frames"].values())
    assert not _leftovers(out) and not _leftovers(cold)


def test_show_on_a_local_two_worker_cluster(stored_calibration, tmp_path, capsys):
    """Frames as tasks on a local Dask cluster: byte-identical to one process; a cancelled run resumes without
    redoing finished frames; the closed loop is refused."""
    import procam.addon.steps.show as show_step
    from procam.addon.steps.stage_c import StageCOptions

    cal_dir, _, truth = stored_calibration()
    seq = _frames(tmp_path / "frames", (1, 2, 3))
    single = tmp_path / "single"
    # 2 spp: several samples per pixel, whose sums are ordered by Dr.Jit's thread count, the same on both sides.
    base = ["show", str(cal_dir), str(seq), "--iterations", "4", "--spp", "2", "--chunk", "2", "--threads", "1"]
    assert main([*base, "--out", str(single)]) == EXIT_OK
    capsys.readouterr()
    assert main([*base, "--out", str(tmp_path / "x"), "--workers", "2", "--device", f"lab:{truth}"]) == EXIT_USER
    assert "closed loop" in capsys.readouterr().err and not (tmp_path / "x").exists()

    # Cancelled as soon as the first frame is written: that frame is kept, the rest is not computed twice.
    out = tmp_path / "cluster"
    written: list[str] = []
    options = show_step.ShowOptions(cal_dir, (seq,), out, StageCOptions(iterations=4, spp=2), chunk=2, workers=2,
                                    threads=1)
    with pytest.raises(show_step.Cancelled):
        show_step.run(options, progress=lambda msg, frac: written.append(msg) if "dB (model)" in msg else None,
                      cancel=lambda: bool(written))
    doc = _manifest(out)
    kept = {n for n, e in doc["frames"].items() if e["status"] == "done"}
    assert doc["runs"][-1]["status"] == "cancelled" and len(kept) >= 1 and not _leftovers(out)
    before = _mtimes(out)
    assert main([*base, "--out", str(out), "--workers", "2"]) == EXIT_OK
    doc = _manifest(out)
    assert doc["runs"][-1]["skipped"] == len(kept) and doc["runs"][-1]["done"] == 3 - len(kept)
    assert all(_mtimes(out)[k] == v for k, v in before.items())
    assert _bytes(out) == _bytes(single) and doc["runs"][-1]["where"] == "local cluster, 2 worker(s)"
    assert [doc["frames"][n]["warm_start"] for n in ("1", "2", "3")] == [None, 1, None]


def test_evaluate_reports_the_flicker_of_a_show(stored_calibration, tmp_path):
    cal_dir, _, truth = stored_calibration()
    seq = _frames(tmp_path / "frames", (1, 2, 3))
    show = tmp_path / "show"
    assert main(["show", str(cal_dir), str(seq), "--out", str(show), *FAST, "--no-bias"]) == EXIT_OK
    out = tmp_path / "eval"
    targets = [str(p) for p in sorted(seq.glob("*.png"))]
    assert main(["evaluate", str(cal_dir), "--inputs", str(show), "--targets", *targets, "--device",
                 f"lab:{truth}", "--out", str(out)]) == EXIT_OK
    f = json.loads((out / "metrics.json").read_text())["flicker"]
    assert f["pairs"] == 2 and f["targets"] > 0 and f["captured"] > 0 and "consecutive" in f["measure"]
    assert f["excess"] == pytest.approx(f["captured"] - f["targets"], abs=2e-5)


def test_evaluate_measures_a_show_made_from_a_video_against_that_video(stored_calibration, tmp_path, capsys):
    """Each finished frame is measured against the video frame it was made from; the flicker is taken in frame
    order; another video (by contents) or image targets are refused with what to give instead."""
    from procam.addon.video import VideoReader, load_video_frame

    cal_dir, _, truth = stored_calibration()
    video = _video(tmp_path / "clip.avi", 3)
    show = tmp_path / "show"
    assert main(["show", str(cal_dir), str(video), "--out", str(show), *FAST, "--no-bias"]) == EXIT_OK
    out = tmp_path / "eval"
    evaluate = ["evaluate", str(cal_dir), "--inputs", str(show), "--device", f"lab:{truth}"]
    assert main(evaluate + ["--targets", str(video), "--out", str(out)]) == EXIT_OK
    doc = json.loads((out / "metrics.json").read_text())
    assert [r["name"] for r in doc["targets"]] == ["frame_0001", "frame_0002", "frame_0003"]
    assert all(r["status"] == "done" and r["psnr"] > r["uncompensated"]["psnr"] for r in doc["targets"])
    assert doc["flicker"]["pairs"] == 2 and "8-bit video" in doc["targets"][1]["target_encoding"]
    # frame 2's comparison starts with the video's frame 2 fitted to the area, not frame 1
    from procam.addon.imageio import read_image
    from procam.addon.stages.display_area import DisplayArea, fit_target

    area = DisplayArea.from_dict(doc["targets"][1]["area"])
    with VideoReader(video) as reader:
        f1, f2 = (fit_target(load_video_frame(reader, i)[0], area) for i in (0, 1))
    panel = read_image(out / "frame_0002_comparison.png")[:, :f2.shape[1]]
    assert np.abs(panel - f2).mean() < 0.1 * np.abs(panel - f1).mean()
    capsys.readouterr()
    other = _video(tmp_path / "other.avi", 3, seed=7)
    assert main(evaluate + ["--targets", str(other), "--out", str(tmp_path / "e2")]) == EXIT_USER
    assert "is not the video" in capsys.readouterr().err
    img = tmp_path / "f.png"
    write_image(img, _target(1))
    assert main(evaluate + ["--targets", str(img), "--out", str(tmp_path / "e3")]) == EXIT_USER
    assert "give that video" in capsys.readouterr().err
    assert not (tmp_path / "e2").exists() and not (tmp_path / "e3").exists()


# -- refusals and interruptions: a silent cluster, Ctrl-C, SIGKILL, a damaged video, a manifest naming elsewhere --

def _silent_server():
    """A TCP server on 127.0.0.1 that accepts connections and never answers (a wrong port, a stuck host)."""
    import socket
    import threading

    server = socket.create_server(("127.0.0.1", 0))
    accepted = []

    def serve():
        while True:
            try:
                accepted.append(server.accept()[0])
            except OSError:
                return

    threading.Thread(target=serve, daemon=True).start()
    return server, accepted


def test_show_cluster_that_never_answers_is_refused_in_time(stored_calibration, tmp_path, capsys):
    import time

    from procam.addon.errors import Cancelled
    from procam.addon.steps.show_cluster import Cluster, ClusterError

    server, accepted = _silent_server()
    address = f"tcp://127.0.0.1:{server.getsockname()[1]}"
    try:
        t0 = time.monotonic()
        with pytest.raises(ClusterError, match=f"{address} accepted the connection but did not answer within 1 s"):
            Cluster(address=address, connect_timeout=1.0)
        assert time.monotonic() - t0 < 5 and accepted
        # Ctrl-C (the cancel poll) stops the wait at once, not at the timeout.
        t0 = time.monotonic()

        def cancelled():
            raise Cancelled("show cancelled")

        with pytest.raises(Cancelled):
            Cluster(address=address, connect_timeout=60.0, poll=cancelled)
        assert time.monotonic() - t0 < 2
        # The command: exit 2, the address named, the frames not computed.
        cal_dir, _, _ = stored_calibration()
        seq = _frames(tmp_path / "frames", (1,))
        out = tmp_path / "show"
        assert main(["show", str(cal_dir), str(seq), "--out", str(out), *FAST, "--no-bias", "--cluster", address,
                     "--connect-timeout", "1"]) == EXIT_USER
        err = capsys.readouterr().err
        assert address in err and "--connect-timeout" in err and "Traceback" not in err
        assert not out.exists()  # a cluster that cannot be reached leaves no show folder behind
        assert main(["show", str(cal_dir), str(seq), "--out", str(out), "--cluster", address,
                     "--connect-timeout", "0"]) == EXIT_USER
        assert "--connect-timeout must be" in capsys.readouterr().err
    finally:
        server.close()


def _procam(*args: str):
    """``procam ARGS`` in a child process of its own process group (a terminal's Ctrl-C reaches the whole group)."""
    import os
    import subprocess
    import sys

    import procam

    env = {**os.environ, "PYTHONPATH": str(Path(procam.__file__).parent.parent)}  # this checkout, not another
    return subprocess.Popen([sys.executable, "-c", "import sys; from procam.addon.cli.app import main; "
                             "sys.exit(main())", *args], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)


def _wait_for_a_frame(child, out: Path, timeout: float = 240.0) -> None:
    import time

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        assert child.poll() is None, child.communicate()
        try:
            if any(e.get("status") == "done" for e in _manifest(out)["frames"].values()):
                return
        except (OSError, ValueError, KeyError):
            pass  # not written yet
        time.sleep(0.05)
    child.kill()
    raise AssertionError("no frame finished in time")


def _kept_frames_intact(out: Path) -> list[str]:
    doc = _manifest(out)
    done = [e for e in doc["frames"].values() if e["status"] == "done"]
    assert done and all(hashlib.sha256((out / e["file"]).read_bytes()).hexdigest() == e["sha256"] for e in done)
    return sorted(e["file"] for e in done)


def test_ctrl_c_in_a_terminal_cancels_a_two_worker_show_cleanly(stored_calibration, tmp_path):
    """The terminal sends SIGINT to the whole process group, workers included: they ignore it, and the show stops
    with exit 130, no traceback, the finished frames kept."""
    import os
    import signal

    cal_dir, _, _ = stored_calibration()
    seq = _frames(tmp_path / "frames", range(1, 9))
    out = tmp_path / "show"
    child = _procam("show", str(cal_dir), str(seq), "--out", str(out), "--iterations", "30", "--spp", "1",
                    "--no-bias", "--chunk", "2", "--workers", "2", "--threads", "1")
    try:
        _wait_for_a_frame(child, out)
        os.killpg(child.pid, signal.SIGINT)
        _, err = child.communicate(timeout=120)
    finally:
        if child.poll() is None:
            os.killpg(child.pid, signal.SIGKILL)
    assert child.returncode == EXIT_CANCELLED, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err and "bug in ProCam" not in err, err
    kept = _kept_frames_intact(out)
    assert f"{len(kept)} finished frame(s) kept" in err and "rerun the same command to resume" in err, err
    assert len(kept) < 8 and _manifest(out)["runs"][-1]["status"] == "cancelled"


def test_a_killed_show_reads_as_interrupted_and_resumes(stored_calibration, tmp_path, capsys):
    """SIGKILL leaves the manifest saying "running": the reader, the panel summary and the resume say
    "interrupted" once the recorded process is gone."""
    import os
    import signal
    import socket

    from procam.addon.steps import show as show_step

    cal_dir, _, _ = stored_calibration()
    seq = _frames(tmp_path / "frames", (1, 2, 3, 4))
    out = tmp_path / "show"
    args = ["show", str(cal_dir), str(seq), "--out", str(out), "--iterations", "30", "--spp", "1", "--no-bias"]
    child = _procam(*args)
    try:
        _wait_for_a_frame(child, out)
        # While it runs: its process and host are recorded, and it reads as running.
        run = _manifest(out)["runs"][-1]
        assert (run["status"], run["pid"], run["host"]) == ("running", child.pid, socket.gethostname())
        assert show_step.summary(out).data["status"] == "running"
        os.killpg(child.pid, signal.SIGKILL)
        child.communicate(timeout=60)
    finally:
        if child.poll() is None:
            os.killpg(child.pid, signal.SIGKILL)
    kept = _kept_frames_intact(out)
    assert _manifest(out)["runs"][-1]["status"] == "running"  # what SIGKILL leaves on disk
    s = show_step.summary(out)
    assert s.data["status"] == "interrupted" and "interrupted" in s.headline and "rerun" in s.lines[0]
    assert show_step.read(out).runs[-1]["status"] == "interrupted"
    assert main(args) == EXIT_OK
    doc = _manifest(out)
    assert [r["status"] for r in doc["runs"]] == ["interrupted", "complete"] and doc["complete"]
    assert doc["runs"][-1]["skipped"] == len(kept)


def test_a_damaged_video_is_refused(tmp_path, capsys):
    """A few bytes flipped in one frame's chunk header: FFmpeg drops that frame, so the frames after it would
    be misnumbered; the container lists 6."""
    video = _video(tmp_path / "clip.avi", 6)
    assert len(list_frames([video])) == 6
    data = bytearray(video.read_bytes())
    tag = [i for i in range(len(data)) if data[i:i + 4] == b"00dc"][3]  # frame 3's chunk in the movie list
    data[tag] ^= 0xFF
    damaged = tmp_path / "damaged.avi"
    damaged.write_bytes(bytes(data))
    with pytest.raises(SequenceError, match="decodes to 5 frames but its container lists 6"):
        list_frames([damaged])
    assert main(["show", str(tmp_path), str(damaged), "--out", str(tmp_path / "out")]) == EXIT_USER
    assert "damaged" in capsys.readouterr().err and not (tmp_path / "out").exists()


def test_a_local_cluster_writes_nothing_outside_the_folders_given(run_python, tmp_path):
    """Dask's workers keep their scratch space (and its global.lock, purge.lock) beside the show folder, and it goes
    when the cluster closes: nothing is left in $TMPDIR (issue 53)."""
    tmpdir, out = tmp_path / "tmpdir", tmp_path / "show"
    tmpdir.mkdir()
    proc = run_python("""
        import sys
        from pathlib import Path
        from procam.addon.steps.show_cluster import Cluster
        cluster = Cluster(workers=1, threads=1, beside=Path(sys.argv[1]))
        print(cluster.describe)
        print(sorted(p.name for p in Path(sys.argv[1]).parent.iterdir()))
        cluster.close()
    """, str(out), env={"TMPDIR": str(tmpdir)}, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "'.show.tmp-" in proc.stdout  # the scratch space, while the cluster runs
    assert sorted(p.name for p in tmpdir.rglob("*")) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tmpdir"]
