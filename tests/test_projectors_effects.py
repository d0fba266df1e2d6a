"""Diagnosed effect models around the joint solve of several projectors: each projector's own effects from its own
diagnosis (its lens's blur held in the solve, its tone curve inverted on its frame), the camera's left out, and a
diagnosis of another rig refused."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from procam.addon.steps import layout

KIND = layout.DIAGNOSIS


def _write(folder: Path, doc: dict[str, Any]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / KIND.manifest).write_text(json.dumps({"format": KIND.format, "version": KIND.version, **doc}))


def _projector_doc(params: dict[str, dict[str, float]]) -> dict[str, Any]:
    """One projector's gap.json as compensation reads it: what ``--effects auto`` inverts, and the fitted ones."""
    return {"selected": list(params), "selected_params": params, "compensation": {"params": params},
            "effects": [{"name": n, "params": p} for n, p in params.items()]}


def diagnosis_of_two(folder: Path, cal: Path, params: list[dict[str, dict[str, float]]], *,
                     count: int = 2, sha: str | None = None) -> Path:
    """A diagnosis folder of ``count`` projectors of the calibration ``cal`` (``projector_K/gap.json`` each)."""
    from procam.addon.steps import calibrate as calibrate_step

    _write(folder, {"source": str(cal), "projector_count": count,
                    "calibration_sha256": sha or calibrate_step.identity(cal)["sha256"]})
    for k, p in enumerate(params):
        _write(folder / f"projector_{k + 1}", _projector_doc(p))
    return folder


@pytest.fixture(scope="module")
def rig(two_projector_lab) -> tuple[Path, Path]:
    from procam.addon.imageio import write_image
    from procam.addon.capture.targets import natural_target

    root = two_projector_lab
    return root, write_image(root / "city.png", natural_target("city", (120, 90)))


def test_each_projector_holds_its_own_lens_blur_in_the_joint_solve(rig, tmp_path):
    """Projector 1's diagnosis fitted a blur of 0.8 texel and a camera curve, projector 2's a blur of 1.2: each
    projector's compensator solves through its own blur (all its texels unknowns), the camera curve is left out and
    said so, and compensation.json records per projector what was used."""
    from procam.addon.cli.app import main as procam

    root, target = rig
    diag = diagnosis_of_two(tmp_path / "diag", root / "cal", [
        {"defocus": {"sigma": 0.8}, "camera_response": {"curve": 0.3}}, {"defocus": {"sigma": 1.2}}])
    out = tmp_path / "comp"
    assert procam(["compensate", str(root / "cal"), str(target), "--iterations", "3", "--effects", "auto",
                   "--diagnosis", str(diag), "--out", str(out)]) == 0
    doc = json.loads((out / "compensation.json").read_text())
    mine = doc["effects"]["projectors"]
    assert [p["input_blur"] for p in mine] == [0.8, 1.2]
    assert [p["used"] for p in mine] == [["defocus"], ["defocus"]]
    assert "camera_response" in mine[0]["not_inverted"] and "camera_response" not in mine[0]["params"]
    assert [p["input_blur"] for p in doc["targets"][0]["projectors"]] == [0.8, 1.2]
    # without effects the record is as before: no effects, no blur
    plain = tmp_path / "plain"
    assert procam(["compensate", str(root / "cal"), str(target), "--iterations", "3", "--out", str(plain)]) == 0
    doc = json.loads((plain / "compensation.json").read_text())
    assert doc["effects"] is None and "input_blur" not in doc["targets"][0]["projectors"][0]

    # show shares the joint stage: each projector's effects recorded, and part of its resumable settings
    (tmp_path / "frames").mkdir()
    shutil.copy(target, tmp_path / "frames" / "shot_0001.png")
    show = ["show", str(root / "cal"), str(tmp_path / "frames"), "--out", str(tmp_path / "show"), "--iterations", "2"]
    assert procam(show + ["--effects", "auto", "--diagnosis", str(diag)]) == 0
    manifest = json.loads((tmp_path / "show" / "show.json").read_text())
    assert [p["input_blur"] for p in manifest["effects"]["projectors"]] == [0.8, 1.2]
    assert procam(show) == 2  # other effects than the finished frames': refused without --force


def test_the_joint_solve_runs_on_the_blurred_operators(rig, tmp_path):
    """The σ of each projector reaches its transport view (``T_k B_k``, every texel an unknown)."""
    from procam.addon.stages.transport import BlurredRows
    from procam.addon.steps import calibrate as calibrate_step
    from procam.addon.steps.projectors import JointStage
    from procam.addon.steps.stage_c import StageCOptions

    root, _ = rig
    diag = diagnosis_of_two(tmp_path / "diag", root / "cal", [{"defocus": {"sigma": 0.7}}, {}])
    cal = calibrate_step.read(root / "cal")
    with JointStage(cal, StageCOptions(effects="auto", diagnosis=diag)) as stage:
        area = stage.area_for(np.zeros((90, 120, 3), np.float32))
        first, second = (comp.transport_view(area) for comp in stage.compensators)
        assert isinstance(first, BlurredRows) and first.sigma == 0.7 and not isinstance(second, BlurredRows)
        assert stage.effects()["projectors"][1] == {"used": [], "not_inverted": {}, "params": {}, "input_blur": None}
        # The real-time solve holds the same blur for projector 1 alone, and shows both projectors' frames.
        from procam.addon.capture.targets import natural_target
        from procam.addon.steps.realtime import RealtimeSolver

        said: list[str] = []
        solver = RealtimeSolver.for_stage(stage, progress=lambda msg, frac: said.append(msg))
        out = solver.solve(natural_target("city", (120, 90)))
        assert not any("blur" in m for m in said) and len(out.frames) == 2
        views = solver._plan(out.area).views
        assert views[0].blur is not None and views[0].blur.sigma == 0.7 and views[1].blur is None
        assert len(views[0].texels) > len(views[0].view.texels) and all(f[..., :3].max() > 12 for f in out.frames)


def test_each_projectors_frame_goes_through_its_own_tone_curve_inverse():
    """In the closed loop projector k's frame is sent as g_k⁻¹ of it; a projector without effects as it is."""
    from procam.addon.gap.compensation import AdaptedProjectors, projector_adapter
    from procam.addon.rig.model import Intrinsics, Projector

    proj = Projector(Intrinsics(40, 30, 50.0, 50.0, 20.0, 15.0))
    curve = {"response": {"gamma_r": 2.0, "gamma_g": 2.0, "gamma_b": 2.0}}
    adapter = projector_adapter("auto", _projector_doc(curve), proj)
    assert adapter is not None and adapter.used == ["response"]

    class Rig:
        projectors = (proj, proj)

        def project_all(self, frames: list[np.ndarray]) -> list[np.ndarray]:
            return frames

    frame = np.full((30, 40, 3), 0.25, np.float32)
    sent = AdaptedProjectors(Rig(), [adapter, None]).project_all([frame, frame])
    assert np.allclose(sent[0], 0.5, atol=1e-3) and np.array_equal(sent[1], frame)  # (0.25)^(1/2) = 0.5


def test_a_diagnosis_of_another_rig_or_a_shared_effect_named_is_refused(rig, tmp_path, capsys):
    """A diagnosis of one projector for a calibration of two, one of another calibration, and a camera effect named
    for several projectors: refused with what to do, nothing written."""
    from procam.addon.cli.app import main as procam

    root, target = rig
    base = ["compensate", str(root / "cal"), str(target), "--iterations", "2", "--out", str(tmp_path / "c")]
    one = tmp_path / "one"
    _write(one, _projector_doc({"defocus": {"sigma": 0.8}}))  # a one-projector diagnosis: no projector_count
    assert procam(base + ["--effects", "auto", "--diagnosis", str(one)]) == 2
    assert "is of 1 projector(s), but the calibration has 2" in capsys.readouterr().err
    other = diagnosis_of_two(tmp_path / "other", root / "cal", [{}, {}], sha="0" * 64)
    assert procam(base + ["--effects", "auto", "--diagnosis", str(other)]) == 2
    assert "made on another calibration" in capsys.readouterr().err
    both = diagnosis_of_two(tmp_path / "both", root / "cal", [{"camera_response": {"curve": 0.3}}] * 2)
    # the camera's curve named needs its fit on every projector's patterns, which this (older) diagnosis lacks
    assert procam(base + ["--effects", "camera_response", "--diagnosis", str(both)]) == 2
    assert "no fit of the camera's effects on every projector's patterns" in capsys.readouterr().err
    # a surface effect is not inverted for several projectors
    assert procam(base + ["--effects", "glossy", "--diagnosis", str(both)]) == 2
    assert "the surface's effects and the camera's lens are not" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()


def test_the_compensation_summary_lists_the_effects_each_projector_used():
    """``--effects auto`` on two projectors recorded response and crosstalk on both (defocus on projector 2, the
    camera's curve once for both): the summary and the report list them per projector, not "none"."""
    from procam.addon.steps import compensate as compensate_step
    from procam.addon.steps.report_sections import Reader

    used = [["response", "crosstalk"], ["response", "crosstalk", "defocus"]]
    doc = {"mode": "open-loop", "targets": [], "projectors": [{}, {}], "effects": {
        "diagnosis": "/d", "camera": {"used": ["camera_response"], "params": {"camera_response": {"curve": 0.3}}},
        "projectors": [{"used": u, "not_inverted": {"glossy": "the camera's and the surface's effects are every "
                                                             "projector's"} if k == 0 else {},
                        "params": {}, "input_blur": None} for k, u in enumerate(used)]}}
    lines = compensate_step._summary(Path("/nowhere"), doc).lines
    line = next(x for x in lines if x.startswith("effect models:"))
    assert line == ("effect models: projector 1: response, crosstalk; projector 2: response, crosstalk, defocus; "
                    "the camera's, for every projector: camera_response; not inverted: projector 1: glossy")
    _, blocks = Reader([], lambda *_: None).compensation(Path("/nowhere"), doc)
    facts = dict(blocks[0]["items"])
    assert facts["effects inverted"] == line.removeprefix("effect models: ")
    # one projector: as before
    one = {"targets": [], "effects": {"used": ["response"], "not_inverted": {"distortion": "why"}}}
    assert "effect models: response; not inverted: distortion" in compensate_step._summary(Path("/x"), one).lines
    none = {"targets": [], "effects": {"diagnosis": "/d", "camera": None, "projectors": [
        {"used": [], "not_inverted": {}, "params": {}, "input_blur": None}] * 2}}
    assert "effect models: none" in compensate_step._summary(Path("/x"), none).lines


def test_each_projectors_diagnosis_says_what_the_joint_run_inverts_for_it():
    """Projector 1's own diagnosis would invert its defocus and the camera's curve; the fit on both projectors'
    patterns kept its tone curve alone and took the camera's curve once for both. Its summary and gap.json say what
    compensation of the rig with --effects auto does for it, not what its own diagnosis alone would."""
    from procam.addon.gap.diagnose import summary_markdown
    from procam.addon.steps import diagnose as diagnose_step

    curve = {"gamma_r": 1.3, "gamma_g": 1.3, "gamma_b": 1.3}
    own = {"compensation": {"effects": ["defocus", "camera_response"],
                            "params": {"defocus": {"sigma": 0.8}, "camera_response": {"curve": 0.3}},
                            "left_out": {"black_level": "stage C's θ already holds a constant offset"}}}
    joint = {"compensation": {"shared": {"camera_response": {"curve": 0.25}},
                              "projectors": [{"response": curve}, {}], "left_out": {}}}
    said = diagnose_step.rig_compensation(own, joint, 0)
    assert said["effects"] == ["response", "camera_response"] and said["params"] == {"response": curve}
    assert "defocus" in said["left_out"] and "every projector's patterns" in said["left_out"]["defocus"]
    assert said["left_out"]["black_level"].startswith("stage C")
    assert said["alone"] == own["compensation"]["effects"]
    # without the fit on every projector's patterns: its own projector effects, the camera's left out
    alone = diagnose_step.rig_compensation(own, None, 0)
    assert alone["effects"] == ["defocus"] and "camera_response" in alone["left_out"]

    doc = json.loads(json.dumps(_SUMMARY_DOC))
    doc["compensation"] = said
    text = summary_markdown(doc)
    line = next(x for x in text.splitlines() if x.startswith("**Compensation"))
    assert line.startswith("**Compensation of the rig with `--effects auto` inverts for this projector:** response, "
                           "camera_response"), line
    assert "not defocus: " in line


_SUMMARY_DOC = {"headline": "h", "calibration": "c", "patterns": {"fit": [], "held_out": []},
                "residual": {"rmse": 0.1, "psnr": 20.0, "rmse_structured": 0.1},
                "residual_after": {"rmse": 0.05, "psnr": 26.0, "rmse_structured": 0.05},
                "smooth_sigma_px": 2, "session": {"changed": False}, "unexplained": {"detected": False},
                "selected": ["defocus"], "absorbed": [], "modelled": ["defocus"], "effects": [], "steps": [],
                "min_share": 0.06, "regions": [], "selected_params": {"defocus": {"sigma": 0.8}}, "evidence": {},
                "error_split": {}}


def test_a_projectors_headline_does_not_advise_what_the_rigs_run_leaves_out():
    """Projector 1's own diagnosis names its defocus and advises --effects auto, which the rig's run does not invert
    for it: its headline says that and why, not the advice; an effect the rig's run inverts keeps the advice."""
    from procam.addon.gap.diagnose import ACTIONS
    from procam.addon.steps import diagnose as diagnose_step

    why = "not selected for this projector when fitted on every projector's patterns together"
    for name in ("defocus", "crosstalk", "response", "camera_response", "glossy"):
        said = ACTIONS[name].format(where=" towards the left of the camera image")
        said = said[0].upper() + said[1:] + "; 40% of the residual above the noise stays unexplained."
        doc = {"headline": said, "modelled": [name], "compensation": {"left_out": {name: why}}}
        got = diagnose_step.rig_headline(doc)
        assert "compensate with --effects auto" not in got and f"does not invert it ({why})" in got, got
        assert got.endswith("; 40% of the residual above the noise stays unexplained."), got
        assert got.startswith(re.split(r"(?:, or |; |: )compensate", said)[0]), got  # what the effect is stays
        kept = {**doc, "compensation": {"left_out": {}}}
        assert diagnose_step.rig_headline(kept) == said
