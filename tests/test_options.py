"""Each option declared once (addon/options.py): the command line, the checks, the sidebar and the sidebar's
wording of messages all come from the ``Options`` field."""

from __future__ import annotations

import argparse
import ast
import math
from pathlib import Path

import pytest

from procam.addon.errors import ProCamError
from procam.addon.options import add_arguments, declared, from_arguments, from_values, sidebar_names, validate
from procam.addon.steps.stage_c import StageCOptions

REPO = Path(__file__).resolve().parents[1]


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(exit_on_error=False)
    add_arguments(p, StageCOptions)
    return p


def test_the_command_line_is_derived_from_the_declaration():
    args = _parser().parse_args(["--schedule", "fast", "--iterations", "40", "--lr", "0.02", "--area", "1,2,30,40",
                                 "--no-bias", "--device", "lab:x.json", "--range", "auto", "--spp", "2"])
    options = from_arguments(StageCOptions, args)
    assert options == StageCOptions(schedule="fast", iterations=40, lr=0.02, area=(1, 2, 30, 40), use_bias=False,
                                    device="lab:x.json", range="auto", spp=2)
    assert from_arguments(StageCOptions, _parser().parse_args([])) == StageCOptions()


@pytest.mark.parametrize("argv", [["--lr", "nan"], ["--lr", "inf"], ["--spp", "2.5"], ["--spp", "0"],
                                  ["--iterations", "-1"], ["--schedule", "slow"], ["--area", "1,2,3"],
                                  ["--range", "bright"], ["--device", "camera:0"], ["--capture-every", "0"]])
def test_a_bad_value_is_refused_where_it_is_parsed(argv):
    with pytest.raises((argparse.ArgumentError, SystemExit)):
        _parser().parse_args(argv)


@pytest.mark.parametrize("given", [{"lr": math.nan}, {"spp": 1.5}, {"spp": True}, {"bounces": -1},
                                   {"schedule": "slow"}, {"range": "x"}, {"alpha": 0.9}, {"seed": -3}])
def test_the_same_checks_hold_for_options_made_in_python(given):
    with pytest.raises(ProCamError):
        validate(StageCOptions(**given))
    with pytest.raises(ProCamError):
        StageCOptions(**given).check()


def test_the_sidebar_reads_the_same_declaration():
    scene = {"procam_schedule": "paper", "procam_iterations": 0, "procam_seed": 3, "procam_area": " ",
             "procam_use_bias": True, "procam_device": "", "procam_effects": "", "procam_range": "0.8,0.02"}
    options = from_values(StageCOptions, scene.__getitem__, device=None)
    assert options == StageCOptions(schedule="paper", iterations=None, seed=3, range="0.8,0.02")
    scene.update(procam_iterations=12, procam_area="0,0,64,48")
    assert from_values(StageCOptions, scene.__getitem__).area == (0, 0, 64, 48)
    names = sidebar_names([StageCOptions])
    assert names["--no-bias"] == "‘Bias θ’" and names["--schedule"] == "‘Schedule’" and "--spp" not in names


def test_the_diagnosis_options_come_from_their_declaration_too():
    from procam.addon.steps.diagnose import DiagnoseOptions

    p = argparse.ArgumentParser(exit_on_error=False)
    add_arguments(p, DiagnoseOptions)
    for bad in (["--min-share", "nan"], ["--scale", "2"], ["--max-effects", "0"], ["--spp", "1.5"]):
        with pytest.raises((argparse.ArgumentError, SystemExit)):
            p.parse_args(bad)
    options = from_arguments(DiagnoseOptions, p.parse_args(["--scale", "1", "--max-effects", "6"]),
                             calibration=Path("c"), out=Path("d"))
    assert (options.scale, options.max_effects, options.min_share) == (1.0, 6, DiagnoseOptions.min_share)
    with pytest.raises(ProCamError):
        DiagnoseOptions(Path("c"), Path("d"), min_share=math.nan).check()
    scene = {"procam_diagnosis_scale": 0.25, "procam_max_effects": 3}
    assert from_values(DiagnoseOptions, scene.__getitem__, calibration=Path("c"), out=Path("d")) == \
        DiagnoseOptions(Path("c"), Path("d"), scale=0.25, max_effects=3)


def _options_classes():
    from procam.addon.steps.calibrate import CalibrateOptions
    from procam.addon.steps.diagnose import DiagnoseOptions

    cli = REPO / "addon" / "cli"
    return [(StageCOptions, [cli / "compensate.py", cli / "show.py"]),
            (CalibrateOptions, [cli / "calibrate.py"]), (DiagnoseOptions, [cli / "diagnose.py"])]


@pytest.mark.parametrize("index", range(3))
def test_no_declared_option_is_declared_a_second_time(index):
    """A declared option's flag is added to no parser by hand, its scene property made by no hand, and its name in
    messages written in no table: the declaration on the Options class is the only one. (``--diagnosis`` is named
    by the Diagnosis folder field, which the Diagnose panel writes and Compensate reads.)"""
    cls, files = _options_classes()[index]
    flags = {d.spec.negate or d.spec.cli_flag(d.name) for d in declared(cls)} - {"", "--diagnosis"}
    props = {d.spec.prop or f"procam_{d.name}" for d in declared(cls) if d.spec.label and not d.spec.own_field}
    for path in files:  # the command's parsers
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                assert node.value not in flags, f"{path.name} declares {node.value} again"
    for path in (REPO / "panels" / "properties.py", REPO / "operators" / "messages.py"):  # the sidebar's tables
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Dict):
                for key in node.keys:
                    if isinstance(key, ast.Constant):
                        assert key.value not in flags | props, f"{path.name} declares {key.value} again"
