"""``procam evaluate`` end to end on the small lab set, its metrics.json, bad inputs, and the no-W ablation.

The calibration is the lab truth with an identity warp (stages A and B are
tested elsewhere); compensation runs a few iterations without θ so the test
stays fast. Tests are evaluation code: they may read the lab truth.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import types

import numpy as np
import pytest

from procam.addon.cli.app import main
from procam.addon.errors import CaptureError, ProCamError


def _target(w: int = 160, h: int = 120, seed: int = 3) -> np.ndarray:
    from procam.addon.capture.patterns import smooth_random

    return (0.05 + 0.4 * smooth_random((w, h), seed, 20.0)).astype(np.float32)


@pytest.fixture(scope="module")
def env(stored_calibration, tmp_path_factory):
    from procam.addon.imageio import write_image
    from procam.addon.steps import calibrate as calibrate_step

    stored, captures_dir, truth_path = stored_calibration()
    root = tmp_path_factory.mktemp("evaluate")
    cal_dir = root / "cal"
    shutil.copytree(stored, cal_dir)  # the truth's calibration with its operator stored: compensate reads it
    cal = calibrate_step.read(cal_dir)
    targets = root / "targets"
    targets.mkdir()
    write_image(targets / "a.png", _target())
    write_image(targets / "b.png", _target(seed=5))
    comp = root / "comp"
    assert main(["compensate", str(cal_dir), str(targets / "a.png"), str(targets / "b.png"), "--out", str(comp),
                 "--iterations", "4", "--spp", "1", "--no-bias"]) == 0
    return types.SimpleNamespace(cal=cal, cal_dir=cal_dir, truth_path=truth_path, root=root, targets=targets,
                                 comp=comp, captures_dir=captures_dir)


def _evaluate(env, out, *targets, inputs=None, extra=()):
    return main(["evaluate", str(env.cal_dir), "--inputs", str(inputs or env.comp), "--targets",
                 *[str(t) for t in targets], "--device", f"lab:{env.truth_path}", "--out", str(out), *extra])


def test_evaluate_end_to_end(env, capsys):
    from procam.addon.imageio import read_image

    out = env.root / "eval"
    assert _evaluate(env, out, env.targets / "a.png", extra=["--classical"]) == 0
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["complete"] and [t["name"] for t in doc["targets"]] == ["a"]
    row = doc["targets"][0]
    assert {"name", "psnr", "ssim"} <= set(row) and set(doc["mean"]) == {"psnr", "ssim"}
    assert doc["mean"]["psnr"] == pytest.approx(row["psnr"], abs=1e-3)
    assert 5 < row["psnr"] < 60 and 0 < row["ssim"] <= 1 and row["warnings"] == []
    # Even 4 iterations of stage C start from the photometric inverse: better than the target projected as is.
    assert row["psnr"] > row["uncompensated"]["psnr"]
    # The classical baseline, in the same run: fitted with 3 flat primaries captured through the device.
    assert doc["classical"]["flat_colours_captured"] == 3 and row["classical"]["psnr"] > row["uncompensated"]["psnr"]
    area = row["area"]
    side = read_image(out / row["image"])  # target | uncompensated | compensated | classical | error
    assert side.shape[0] == area["height"] and side.shape[1] > 5 * area["width"]
    cam = env.cal.rig.camera.intrinsics
    assert read_image(out / "a_capture.png").shape == (cam.height, cam.width, 3)
    assert "uncompensated → compensated" in capsys.readouterr().out
    # Never overwritten without --force.
    assert _evaluate(env, out, env.targets / "a.png") == 2


def test_bad_inputs_are_clear_errors(env, capsys):
    from procam.addon.imageio import write_image

    root = env.root
    # No compensation folder / no compensation for this target name.
    assert _evaluate(env, root / "e1", env.targets / "a.png", inputs=root / "nowhere") == 2
    assert "procam compensate" in capsys.readouterr().err
    write_image(root / "c.png", _target())
    assert _evaluate(env, root / "e2", root / "c.png") == 2
    assert "no finished compensation for a target named 'c'" in capsys.readouterr().err
    # Missing input files.
    broken = root / "comp_missing"
    shutil.copytree(env.comp, broken)
    (broken / "a_frame.png").unlink()
    (broken / "a_input.png").unlink()
    assert _evaluate(env, root / "e3", env.targets / "a.png", inputs=broken) == 2
    assert "missing" in capsys.readouterr().err
    # Inputs computed from another capture set.
    other = root / "comp_other"
    shutil.copytree(env.comp, other)
    doc = json.loads((other / "compensation.json").read_text())
    doc["capture_set"] = str(root / "some-other-capture-set")
    (other / "compensation.json").write_text(json.dumps(doc))
    assert _evaluate(env, root / "e4", env.targets / "a.png", inputs=other) == 2
    assert "were computed from the capture set" in capsys.readouterr().err
    # An unreadable target and an empty one.
    bad = root / "bad"
    bad.mkdir()
    (bad / "a.png").write_bytes(b"not an image")
    assert _evaluate(env, root / "e5", bad / "a.png") == 2
    assert "a.png" in capsys.readouterr().err
    (bad / "b.png").write_bytes(b"")
    assert _evaluate(env, root / "e6", bad / "b.png") == 2
    assert "empty" in capsys.readouterr().err
    for name in ("e1", "e2", "e3", "e4", "e5", "e6"):
        assert not (root / name).exists()


def test_a_different_image_under_the_same_name_is_refused(env, capsys):
    from procam.addon.imageio import write_image
    from procam.addon.outputs import file_sha256

    root = env.root
    doc = json.loads((env.comp / "compensation.json").read_text())
    assert doc["targets"][0]["file_sha256"] == file_sha256(env.targets / "a.png")
    other = root / "elsewhere"
    other.mkdir()
    write_image(other / "a.png", _target(seed=11))  # same name, same size, another picture
    assert _evaluate(env, root / "e_same_name", other / "a.png") == 2
    err = capsys.readouterr().err
    assert "is not the image the input 'a'" in err and "contents differ" in err
    assert not (root / "e_same_name").exists()
    # A folder from before the hash was recorded: matched by name, with a warning that says so.
    old = root / "comp_no_hash"
    shutil.copytree(env.comp, old)
    for t in doc["targets"]:
        t.pop("file_sha256")
    (old / "compensation.json").write_text(json.dumps(doc))
    assert _evaluate(env, root / "e_no_hash", other / "a.png", inputs=old, extra=["--no-repeat"]) == 0
    assert "records no content hash for the target(s) a" in capsys.readouterr().err
    notes = json.loads((root / "e_no_hash" / "metrics.json").read_text())["notes"]
    assert any("matched by file name only" in n for n in notes)


def test_compensate_refuses_a_png_declaring_20000x20000(env, capsys):
    import time

    from tests.test_input_limits import png_bomb

    bomb = env.root / "bomb.png"
    bomb.write_bytes(png_bomb(20000, 20000))
    t0 = time.perf_counter()
    assert main(["compensate", str(env.cal_dir), str(bomb), "--out", str(env.root / "c_bomb"), "--iterations", "1",
                 "--spp", "1", "--no-bias"]) == 2
    assert time.perf_counter() - t0 < 30  # refused from the header, not after decoding 2.4 GB
    assert "declares 20000×20000 pixels" in capsys.readouterr().err
    assert not (env.root / "c_bomb").exists()


def test_other_capture_set_is_named(env):
    from procam.addon.steps.evaluate import CompensationInputs, MismatchError

    inputs = CompensationInputs.load(env.comp)
    inputs.doc["capture_set"] = "/elsewhere/captures"
    with pytest.raises(MismatchError, match="capture set /elsewhere/captures"):
        inputs.check_against(env.cal)
    inputs = CompensationInputs.load(env.comp)
    inputs.doc["camera_size"] = [10, 10]
    with pytest.raises(MismatchError, match="camera size"):
        inputs.check_against(env.cal)


def test_other_aspect_warns_and_is_recorded(env, capsys):
    from procam.addon.imageio import write_image

    # A target is evaluated against the compensation of that same image (its content is checked), so the wide
    # image is compensated into the display area of the others, whose aspect it does not have.
    wide = env.root / "wide"
    wide.mkdir()
    write_image(wide / "a.png", _target(240, 100))
    a = json.loads((env.comp / "compensation.json").read_text())["targets"][0]["area"]
    comp = env.root / "comp_wide"
    assert main(["compensate", str(env.cal_dir), str(wide / "a.png"), "--out", str(comp), "--iterations", "4",
                 "--spp", "1", "--no-bias", "--area", f"{a['x']},{a['y']},{a['width']},{a['height']}"]) == 0
    capsys.readouterr()
    out = env.root / "eval_wide"
    assert _evaluate(env, out, wide / "a.png", inputs=comp) == 0
    row = json.loads((out / "metrics.json").read_text())["targets"][0]
    assert row["warnings"] and "stretched" in row["warnings"][0]
    assert "stretched" in capsys.readouterr().err


def test_later_failure_keeps_finished_targets(env, monkeypatch, capsys):
    """A device that returns a capture of the wrong size on the second target: the first one's results stay."""
    from procam.addon.lab.truth import LabTruth
    from procam.addon.lab.cycles_device import LabDevice
    from procam.addon.steps import stage_c

    class Flaky:
        def __init__(self, truth):
            self.inner, self.calls = LabDevice(truth), 0
            self.projector = self.inner.projector

        def project(self, frame):
            self.calls += 1
            img = self.inner.project(frame)
            # three projections per target: compensated, uncompensated, compensated again (the camera's noise)
            return img if self.calls <= 3 else img[:-1]

        def close(self):
            self.inner.close()

    monkeypatch.setattr(stage_c, "open_device", lambda spec, *_, **__: Flaky(LabTruth.load(env.truth_path)))
    out = env.root / "eval_flaky"
    assert _evaluate(env, out, env.targets / "a.png", env.targets / "b.png") == 2
    assert "camera is" in capsys.readouterr().err
    doc = json.loads((out / "metrics.json").read_text())
    assert not doc["complete"] and [t["status"] for t in doc["targets"]] == ["done", "failed"]
    assert (out / "a_comparison.png").is_file() and not (out / "b_comparison.png").exists()
    assert doc["mean"]["psnr"] == doc["targets"][0]["psnr"]


def test_a_replayed_capture_gives_no_noise_ceiling(env, monkeypatch, capsys):
    """A device that returns the same image for the same frame (a capture folder replayed, a noiseless simulator)
    shows no noise; the second capture then measures nothing, and no noise ceiling is claimed."""
    from procam.addon.lab.truth import LabTruth
    from procam.addon.lab.cycles_device import LabDevice
    from procam.addon.steps import stage_c

    class Replay:
        def __init__(self, truth):
            self.inner, self.seen = LabDevice(truth), {}
            self.projector = self.inner.projector

        def project(self, frame):
            key = np.ascontiguousarray(frame).tobytes()
            if key not in self.seen:
                self.seen[key] = self.inner.project(frame)
            return self.seen[key].copy()

        def close(self):
            self.inner.close()

    monkeypatch.setattr(stage_c, "open_device", lambda spec, *_, **__: Replay(LabTruth.load(env.truth_path)))
    out = env.root / "eval_replay"
    assert _evaluate(env, out, env.targets / "a.png") == 0
    doc = json.loads((out / "metrics.json").read_text())
    row = doc["targets"][0]
    assert "noise_ceiling" not in row and "capture_noise_rmse" not in row and doc["mean_noise_ceiling"] is None
    assert any("replayed capture" in w for w in row["warnings"]) and "replayed capture" in capsys.readouterr().err


def test_check_capture_size():
    from procam.addon.stages.metrics import check_capture

    assert check_capture(np.zeros((4, 5, 3)), (5, 4)).dtype == np.float32
    with pytest.raises(CaptureError, match="5×4"):
        check_capture(np.zeros((4, 6, 3)), (5, 4))
    with pytest.raises(CaptureError, match="NaN"):
        check_capture(np.full((4, 5, 3), np.nan), (5, 4))


def test_no_w_ablation_uses_an_identity_warp(env):
    from procam.addon.stages.compensate import Compensator
    from procam.addon.stages.metrics import without_warp
    from procam.addon.stages.warp_model import Warp

    size = env.cal.rig.projector.input_size
    rng = np.random.default_rng(0)
    shifts = rng.normal(0, 1.5, (8, 8, 2))
    warped = type(env.cal)(env.cal.rig, env.cal.surface, Warp(8, size, shifts, -shifts), env.cal.capture_dir)
    ablation = without_warp(warped)
    assert ablation.warp.is_identity and not warped.warp.is_identity and ablation.rig is warped.rig
    z = rng.uniform(0, 1, (size[1], size[0], 3)).astype(np.float32)
    comp = Compensator(ablation, bounces=0, spp=1)
    assert np.array_equal(comp.warp_w(z), z) and np.array_equal(comp.warp_m(z), z)
    assert not np.allclose(Compensator(warped, bounces=0, spp=1).warp_w(z), z)


def test_range_auto_on_bright_content(env, capsys):
    """Bright content clips; ``--range auto`` maps the targets inside what the projector shows, evaluation measures
    against the mapped targets and reports the range ceiling next to each figure."""
    from procam.addon.capture.patterns import smooth_random
    from procam.addon.imageio import write_image

    bright = write_image(env.root / "bright.png", (0.35 + 0.65 * smooth_random((160, 120), 7, 20.0)).astype(np.float32))
    rows = {}
    for rng in ("none", "auto", "bright"):
        comp, out = env.root / f"comp-{rng}", env.root / f"eval-{rng}"
        assert main(["compensate", str(env.cal_dir), str(bright), "--out", str(comp), "--iterations", "4",
                     "--spp", "1", "--no-bias", "--range", rng]) == 0
        manifest = json.loads((comp / "compensation.json").read_text())
        assert main(["evaluate", str(env.cal_dir), "--inputs", str(comp), "--targets", str(bright), "--device",
                     f"lab:{env.truth_path}", "--out", str(out)] + (["--no-repeat"] if rng == "none" else [])) == 0
        doc = json.loads((out / "metrics.json").read_text())
        rows[rng] = (manifest["range"], doc["range"], doc["targets"][0])
    assert rows["none"][0] is None and rows["none"][1] is None
    fitted, recorded, row = rows["auto"]
    assert fitted == recorded and 0 < fitted["gain"] < 1 and fitted["clipped_share"] <= 0.0101
    plain = rows["none"][2]
    # The raw bright target lies far outside the range; the mapped one almost inside: the ceiling says so, and the
    # compensation gets much closer to what it aims at.
    assert plain["range_ceiling"] < 25 and row["range_ceiling"] > plain["range_ceiling"] + 10
    assert row["psnr"] > plain["psnr"] + 3 and row["psnr"] <= row["range_ceiling"]
    # Captured twice, the input gives the camera's noise (the lab's renders differ from shot to shot), and the
    # ceiling a capture can reach through it lies below the range's; captured once, neither is claimed.
    assert row["capture_noise_rmse"] > 0 and row["psnr"] <= row["noise_ceiling"] + 0.5
    assert row["noise_ceiling"] < row["range_ceiling"]
    assert "noise_ceiling" not in plain
    # Far outside the range, most of what separates the capture from the ceiling is where the input is at full.
    assert plain["ceiling_gap_at_limit"] > 0.5
    out = capsys.readouterr().out
    assert "range ceiling" in out
    # Relative to the mapped white (the capture read back through the map, against the target as given) the maps
    # compare: without one it is the plain PSNR; auto's plain PSNR holds what dimming alone gains, this one does not.
    assert plain["psnr_relative"] == pytest.approx(plain["psnr"], abs=1e-3) and plain["brightness_kept"] == 1.0
    assert row["psnr_relative"] < row["psnr"] - 1  # gain ≈ 0.6: errors read back 1/gain larger
    assert row["brightness_kept"] == pytest.approx(fitted["gain"] + fitted["offset"], abs=1e-3)
    # bright: a gain field under 1, recorded with the brightness it keeps, printed by compensate and evaluate
    field_map, recorded, lit = rows["bright"]
    assert field_map == recorded and field_map["rule"].startswith("bright") and field_map["field"]["per_degree"] == 0.05
    assert lit["brightness_kept"] == pytest.approx(field_map["brightness_kept"], abs=0.01)
    assert fitted["gain"] + fitted["offset"] <= lit["brightness_kept"] + 1e-3 and lit["psnr_relative"] > 0
    assert "brightness kept" in out and "relative to the mapped white" in out
    assert main(["compensate", str(env.cal_dir), str(bright), "--out", str(env.root / "x"), "--range", "2"]) == 2


def test_esc_during_an_evaluation_writes_nothing_and_counts_as_cancelled(env):
    """Esc in Blender while the evaluation waits for the lab on the main thread: the relay ends the wait with
    Cancelled. That is a cancel, not a failed target: no folder is committed, no failed row is recorded, and the
    job is cancelled (the operator then says the output folder is unchanged, which it is)."""
    from procam.addon import jobs
    from procam.addon.lab.truth import LabTruth
    from procam.addon.lab.cycles_device import LabDevice
    from procam.addon.steps import evaluate as evaluate_step

    out = env.root / "eval_cancelled"
    options = evaluate_step.EvaluateOptions(env.cal_dir, env.comp, (env.targets / "a.png",),
                                            f"lab:{env.truth_path}", out)
    lab = LabDevice(LabTruth.load(env.truth_path))
    try:
        relay = jobs.MainThreadRelay(cancel=lambda: True, poll_s=0.001)  # Esc is pressed while the lab is wanted
        job = jobs.Job("evaluation", evaluate_step.run, options, device=jobs.RelayedDevice(lab, relay)).run()
    finally:
        lab.close()
    snap = job.snapshot()
    assert snap.status == jobs.CANCELLED and "cancelled" in snap.error, snap
    assert not out.exists() and not [p for p in env.root.iterdir() if out.name in p.name]


# -- issue 53: evaluate takes the target forms show takes ---------------------------------------------------------

def test_evaluate_takes_a_folder_a_numbered_pattern_or_a_video_as_show_does(tmp_path, monkeypatch):
    from procam.addon.imageio import write_image
    from procam.addon.steps import evaluate as evaluate_step
    from procam.addon.steps.show import SequenceError, list_frames

    frames = tmp_path / "frames"
    frames.mkdir()
    for n in (10, 2, 1):
        write_image(frames / f"shot_{n:04d}.png", np.full((6, 8, 3), 0.5, np.float32))
    (frames / ".hidden.png").write_bytes(b"x")
    in_order = [frames / f"shot_{n:04d}.png" for n in (1, 2, 10)]
    assert [f.path for f in list_frames([frames])] == in_order
    assert evaluate_step.target_files([frames]) == tuple(in_order)
    assert evaluate_step.target_files([frames / "shot_####.png"]) == tuple(in_order)
    assert evaluate_step.target_files([frames / "shot_%04d.png"]) == tuple(in_order)
    files = (frames / "shot_0002.png", frames / "shot_0001.png")
    assert evaluate_step.target_files(files) == files  # files as given, in the order given
    video = tmp_path / "clip.mp4"
    assert evaluate_step.target_files([video]) == (video,)  # a video stays one target (its frames are measured)
    (tmp_path / "empty").mkdir()
    with pytest.raises(SequenceError, match="no images"):
        evaluate_step.target_files([tmp_path / "empty"])

    seen = []
    monkeypatch.setattr(evaluate_step, "_run", lambda options, *rest: seen.append(options) or {})
    options = evaluate_step.EvaluateOptions(tmp_path / "cal", tmp_path / "comp", (frames / "shot_####.png",),
                                            "folder:x", tmp_path / "ev")
    evaluate_step.run(options)
    assert seen[0].targets == tuple(in_order)
    with pytest.raises(ProCamError, match="lies inside"):  # the folder of the targets is an input
        evaluate_step.run(dataclasses.replace(options, out=frames / "ev"))


def test_evaluate_reports_the_spill_outside_the_area(env, capsys):
    """Issue 50: the light outside the display area where the projector reaches, as a share of the picture's level,
    per target (compensated and uncompensated) and over the run, in metrics.json and the summary."""
    out = env.root / "eval_spill"
    assert _evaluate(env, out, env.targets / "a.png", env.targets / "b.png") == 0
    doc = json.loads((out / "metrics.json").read_text())
    for row in doc["targets"]:
        assert row["outside_pixels"] > 0 and row["picture_level"] > 0
        assert -0.05 < row["spill_mean"] < 0.2 and row["spill_mean"] <= row["spill_p995"] < 2
        assert isinstance(row["uncompensated"]["spill_p995"], float)
    s = doc["spill"]
    assert s["mean"] == pytest.approx(np.mean([r["spill_mean"] for r in doc["targets"]]), abs=1e-4)
    assert s["guard_px"] >= 2 and "spill_mean" in doc["measure"]
    text = capsys.readouterr().out
    assert "spill outside the area: mean" in text and "99.5th pixel" in text
