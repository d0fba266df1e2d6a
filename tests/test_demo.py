"""`procam demo` end to end at a fifth of the paper's resolution, and its folders read back by the other commands:
`procam evaluate` and `procam diagnose` take the demo's calibration and compensation like any others."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from procam.addon.cli.app import main
from procam.addon.steps import diagnose as diagnose_step

pytestmark = pytest.mark.blender

#: The demo's diagnosis here weighs these candidates, not all ten: the selection among every model is test_gap's and
#: test_projectors' to check, the demo's wiring (the folders, the summary, the loop closed) is these tests'. All ten
#: took three quarters of the demo's time; the lab's tone curve, black level and crosstalk keep the loop closed.
DEMO_CANDIDATES = "black_level,response,crosstalk,defocus"
#: two projectors: the projector-2 tone curve the demo injects, the black level, and the camera's curve that the
#: rig's joint fit weighs once for every projector
DEMO2_CANDIDATES = "black_level,response,camera_response"


def narrowed_diagnosis(monkeypatch: pytest.MonkeyPatch, candidates: str) -> list:
    """The demo's own diagnosis options (scale, spp, limits) with fewer candidates; returns the options it ran."""
    real, ran = diagnose_step.run, []

    def run(options, *args, **kwargs):
        ran.append(replace(options, effects=candidates))
        return real(ran[-1], *args, **kwargs)

    monkeypatch.setattr(diagnose_step, "run", run)
    return ran


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "demo"
    with pytest.MonkeyPatch.context() as mp:
        ran = narrowed_diagnosis(mp, DEMO_CANDIDATES)
        code = main(["demo", "--out", str(out), "--scale", "0.2", "--iterations", "30", "--samples", "4",
                     "--targets", "city"])
    assert code == 0 and len(ran) == 1 and ran[0].scale == 1.0  # 0.3 / 0.2 of the camera, at most all of it
    return out


def test_demo_writes_every_folder_and_compensation_helps(demo, capsys):
    for folder in ("captures", "calibration", "compensation", "evaluation", "diagnosis", "cross-check", "targets"):
        assert (demo / folder).is_dir(), folder
    assert not list(demo.parent.glob(".*tmp*")), "no temporary folder left beside the demo"
    # the page a person opens first, its path printed
    assert (demo / "report.html").is_file() and "<h2>Diagnosis</h2>" in (demo / "report.html").read_text()
    summary = json.loads((demo / "summary.json").read_text())
    row, = summary["compensation"]["targets"]
    assert row["psnr"] > row["uncompensated_psnr"] + 3.0
    assert summary["calibration"]["position_error_cm"] < 2.0
    # The diagnosis names the calibration where it now lies, not where it was built.
    assert f"`{demo / 'calibration'}`" in (demo / "diagnosis" / "summary.md").read_text()
    # and the summary carries its warnings (a selection at its limit, a blur too fine for the working scale)
    gap = json.loads((demo / "diagnosis" / "gap.json").read_text())
    assert summary["diagnosis"]["warnings"] == gap["warnings"]
    # the loop closed: the same targets compensated again with the effects the diagnosis says compensation inverts
    fx = summary["with_effects"]
    assert fx["effects"] == summary["diagnosis"]["compensation"] and fx["effects"]
    again = json.loads((demo / "compensation-effects" / "compensation.json").read_text())
    assert sorted(again["effects"]["used"]) == sorted(fx["effects"])
    assert fx["mean"]["psnr"] > fx["mean"]["uncompensated_psnr"] + 3.0 and (demo / "evaluation-effects").is_dir()


def test_evaluate_accepts_the_demos_folders(demo, tmp_path):
    out = tmp_path / "evaluation"
    code = main(["evaluate", str(demo / "calibration"), "--inputs", str(demo / "compensation"),
                 "--targets", str(demo / "targets" / "city.png"), "--device", f"lab:{demo / 'lab-truth.json'}",
                 "--out", str(out)])
    assert code == 0
    ours = json.loads((out / "metrics.json").read_text())["targets"][0]
    theirs = json.loads((demo / "evaluation" / "metrics.json").read_text())["targets"][0]
    assert ours["psnr"] == pytest.approx(theirs["psnr"], abs=0.05)


def test_diagnose_accepts_the_demos_calibration(demo, tmp_path):
    out = tmp_path / "diagnosis"
    code = main(["diagnose", str(demo / "calibration"), "--out", str(out), "--effects", "black_level,response",
                 "--spp", "8"])
    assert code == 0
    gap = json.loads((out / "gap.json").read_text())
    assert gap["residual_after"]["rmse"] < gap["residual"]["rmse"]
    assert f"`{demo / 'calibration'}`" in (out / "summary.md").read_text()


def test_demo_of_two_projectors_reports_the_overlap_and_each_projector(tmp_path, capsys, monkeypatch):
    out = tmp_path / "demo2"
    narrowed_diagnosis(monkeypatch, DEMO2_CANDIDATES)
    code = main(["demo", "--out", str(out), "--projectors", "2", "--scale", "0.2", "--iterations", "20",
                 "--samples", "4", "--targets", "city"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "projector 2 position error" in printed and "overlap of the projectors" in printed
    summary = json.loads((out / "summary.json").read_text())
    poses = summary["calibration"]["projectors"]
    assert len(poses) == 2 and all(p["position_error_cm"] < 2.0 for p in poses)
    overlap = summary["compensation"]["overlap"]
    assert overlap["mean"]["psnr_overlap"] > overlap["mean_uncompensated"]["psnr_overlap"] + 3.0
    assert len(summary["diagnosis"]["projectors"]) == 2 and summary["diagnosis"]["headline"]
    # projector 2's own tone curve, the one the demo gives it, is the difference the diagnosis names
    differs = summary["diagnosis"]["differs"]
    assert (differs["projector"], differs["effect"]) == (2, "response"), summary["diagnosis"]["headline"]
    for k in (1, 2):
        assert (out / "diagnosis" / f"projector_{k}" / "gap.json").is_file()
        assert (out / "compensation" / f"city_frame_p{k}.png").is_file()
    assert "with_effects" not in summary  # effect models around stage C: one projector only
