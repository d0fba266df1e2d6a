"""`procam demo` end to end at a fifth of the paper's resolution, and its folders read back by the other commands:
`procam evaluate` and `procam diagnose` take the demo's calibration and compensation like any others."""

from __future__ import annotations

import json

import pytest

from procam.addon.cli.app import main

pytestmark = pytest.mark.blender


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "demo"
    code = main(["demo", "--out", str(out), "--scale", "0.2", "--iterations", "30", "--samples", "4",
                 "--targets", "city"])
    assert code == 0
    return out


def test_demo_writes_every_folder_and_compensation_helps(demo, capsys):
    for folder in ("captures", "calibration", "compensation", "evaluation", "diagnosis", "cross-check", "targets"):
        assert (demo / folder).is_dir(), folder
    assert not list(demo.parent.glob(".*tmp*")), "no temporary folder left beside the demo"
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
