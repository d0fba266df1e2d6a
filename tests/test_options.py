"""Each option declared once (addon/options.py): the command line, the checks, the sidebar and the sidebar's
wording of messages all come from the ``Options`` field."""

from __future__ import annotations

import argparse
import dataclasses
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
                                 "--no-bias", "--device", "lab:x.json", "--range", "auto", "--spp", "2",
                                 "--surround", "0.1,0.2,0"])
    options = from_arguments(StageCOptions, args)
    assert options == StageCOptions(schedule="fast", iterations=40, lr=0.02, area=(1, 2, 30, 40), use_bias=False,
                                    device="lab:x.json", range="auto", spp=2, surround=(0.1, 0.2, 0.0))
    assert from_arguments(StageCOptions, _parser().parse_args([])) == StageCOptions()


@pytest.mark.parametrize("argv", [["--lr", "nan"], ["--lr", "inf"], ["--spp", "2.5"], ["--spp", "0"],
                                  ["--iterations", "-1"], ["--schedule", "slow"], ["--area", "1,2,3"],
                                  ["--range", "dim"], ["--device", "camera:0"], ["--capture-every", "0"],
                                  ["--surround", "1.5"], ["--surround", "0,0"]])
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
             "procam_use_bias": True, "procam_device": "", "procam_effects": "", "procam_range": "0.8,0.02",
             "procam_loop": "measured", "procam_radiometry": "auto", "procam_surround": ""}
    options = from_values(StageCOptions, scene.__getitem__, device=None)
    assert options == StageCOptions(schedule="paper", iterations=None, seed=3, range="0.8,0.02")
    scene.update(procam_iterations=12, procam_area="0,0,64,48")
    assert from_values(StageCOptions, scene.__getitem__).area == (0, 0, 64, 48)
    scene.update(procam_surround="0.05")
    assert from_values(StageCOptions, scene.__getitem__).surround == (0.05, 0.05, 0.05)
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
    """Each converted Options class and the command files that must not declare its options again."""
    from procam.addon.steps.calibrate import CalibrateOptions
    from procam.addon.steps.capture import (BoardOptions, CameraSize, DepthSensorSize, ImportOptions, LabOptions,
                                            PatternsOptions, PhotoSettings, ProjectorSheet, UndistortOptions)
    from procam.addon.steps.demo import DemoOptions
    from procam.addon.steps.diagnose import DiagnoseOptions
    from procam.addon.steps.evaluate import EvaluateOptions
    from procam.addon.steps.export import ExportFramesOptions
    from procam.addon.steps.live import LiveCaptureOptions, LiveCheckOptions, LiveRigSheet
    from procam.addon.steps.live_show import LiveShowOptions
    from procam.addon.steps.mpcdi import ApplyMpcdiOptions, ExportMpcdiOptions
    from procam.addon.steps.report import ReportOptions
    from procam.addon.steps.rig import RigOptions
    from procam.addon.steps.show import ShowOptions
    from procam.addon.steps.transport import PrecomputeOptions

    cli = REPO / "addon" / "cli"
    capture, live = cli / "capture.py", cli / "live.py"
    return [(StageCOptions, [cli / "compensate.py", cli / "show.py", cli / "demo.py", cli / "evaluate.py"]),
            (CalibrateOptions, [cli / "calibrate.py"]), (DiagnoseOptions, [cli / "diagnose.py"]),
            (ShowOptions, [cli / "show.py"]), (EvaluateOptions, [cli / "evaluate.py"]),
            (ExportFramesOptions, [cli / "export.py"]), (PrecomputeOptions, [cli / "precompute.py"]),
            (DemoOptions, [cli / "demo.py"]), (LabOptions, [cli / "lab.py"]), (BoardOptions, [cli / "lab.py"]),
            (PatternsOptions, [capture, live]), (ProjectorSheet, [capture, live]), (PhotoSettings, [capture, live]),
            (DepthSensorSize, [capture, live]), (CameraSize, [capture]), (ImportOptions, [capture]),
            (UndistortOptions, [capture]), (LiveCaptureOptions, [live]), (LiveCheckOptions, [live]),
            (LiveRigSheet, [live]), (LiveShowOptions, [live]), (RigOptions, [cli / "rig.py"]),
            (ExportMpcdiOptions, [cli / "mpcdi.py"]), (ApplyMpcdiOptions, [cli / "mpcdi.py"]),
            (ReportOptions, [cli / "report.py"])]


#: the sidebar's and the dialogs' tables of names and properties
SIDEBAR_TABLES = ("panels/properties.py", "panels/board.py", "operators/messages.py", "operators/run_lab.py",
                  "operators/capture_io.py", "operators/live.py", "operators/calibrate_rig.py")


#: how many classes :func:`_options_classes` lists (checked below, so that none is left out of the test after it)
OPTION_CLASSES = 25


def test_every_options_class_is_checked():
    assert len(_options_classes()) == OPTION_CLASSES


@pytest.mark.parametrize("index", range(OPTION_CLASSES))
def test_no_declared_option_is_declared_a_second_time(index):
    """A declared option's flag is added to no parser by hand, its scene property made by no hand, and its name in
    messages written in no table: the declaration on the Options class is the only one. (``--diagnosis`` is named
    by the Diagnosis folder field, which the Diagnose panel writes and Compensate reads; ``--targets`` in the
    sidebar's table is evaluate's list of images, not the demo's option of that name.)"""
    cls, files = _options_classes()[index]
    flags = {d.spec.negate or d.spec.cli_flag(d.name) for d in declared(cls)} - {"", "--diagnosis"}
    if cls.__name__ == "DemoOptions":
        flags.discard("--targets")
    props = {d.spec.prop or f"procam_{d.name}" for d in declared(cls) if d.spec.label and not d.spec.own_field}
    for path in files:  # the command's parsers
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                assert node.value not in flags, f"{path.name} declares {node.value} again"
    for path in (REPO / name for name in SIDEBAR_TABLES):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Dict):
                for key in node.keys:
                    # --force and --out: every command's, which messages.py names for all their messages
                    if isinstance(key, ast.Constant) and key.value not in ("--force", "--out"):
                        assert key.value not in flags | props, f"{path.name} declares {key.value} again"
            if isinstance(node, ast.keyword) and node.arg == "name" and isinstance(node.value, ast.Constant):
                # a dialog's or panel's own field of a declared option takes its label from the declaration
                labels = {d.spec.label for d in declared(cls) if d.spec.label}
                assert node.value.value not in labels or path.name == "properties.py", \
                    f"{path.name} labels a field {node.value.value!r} by hand"


def test_every_options_class_is_covered():
    """A step's Options class with declared options is in the list above (a new one is checked too)."""
    import importlib
    import pkgutil

    import procam.addon.steps as steps

    covered = {cls for cls, _ in _options_classes()}
    for info in pkgutil.iter_modules(steps.__path__):
        module = importlib.import_module(f"procam.addon.steps.{info.name}")
        for value in vars(module).values():
            if (isinstance(value, type) and dataclasses.is_dataclass(value) and value.__module__ == module.__name__
                    and any(True for _ in declared(value))):
                assert value in covered, f"{value.__name__} declares options but is not checked here"


#: every command's flags as users know them (before the options were declared on the steps)
FLAGS = {
    "apply-mpcdi": "--first --force --out",
    "calibrate-rig": "--board --camera-distortion --force --out --projector --projector-distortion --square --window",
    "capture": "--area --camera-fov --checker --depth --depth-native-height --depth-native-width --depth-units "
               "--device --force --input-height --input-width --layout --no-exposure-check --no-graycode "
               "--no-validation --out --projector-height --projector-width --projectors --restart --rig --seed "
               "--shift-x --shift-y --throw-ratio",
    "demo": "--effects --force --full --iterations --out --projectors --samples --scale --schedule --seed --surface "
            "--targets",
    "evaluate": "--classical --device --force --inputs --no-repeat --out --target-encoding --targets",
    "export-frames": "--first --force --out",
    "export-mpcdi": "--area --content-size --force --out --profile --warp-step",
    "import-captures": "--add-to --camera-fov --camera-height --camera-width --depth --depth-native-height "
                       "--depth-native-width --depth-units --encoding --force --no-exposure-check --out --rig",
    "lab-board": "--board --effects --force --out --poses --samples --scale --seed --square --supersample --truth",
    "lab": "--camera-fov-error --camera-size --effects --force --full-binary --layout --no-graycode --nominal-error "
           "--other-forms --out --overlap --projector-effects --projector-shift --projector-size --projectors "
           "--samples --scale --seed --supersample --surface --truth",
    "live-show": "--area --correction --device --diagnosis --duration --effects --hold --range --refine-steps --source "
                 "--surround --target-encoding",
    "live-check": "--device --list-displays --no-exposure-check --projector-height --projector-width --projectors",
    "patterns": "--area --checker --force --input-height --input-width --layout --no-graycode --no-validation --out "
                "--projector-height --projector-number --projector-width --seed --shift-x --shift-y --throw-ratio",
    "precompute": "--bounces --force --live --seed",
    "report": "--force --out --thumbnails --title",
    "show": "--area --bounces --capture-every --chunk --cluster --cold-start --connect-timeout --device --diagnosis "
            "--effects --fail-fast --force --iterations --loop --lr --no-bias --out --radiometry --range --schedule "
            "--seed --spp --surround --target-encoding --threads --workers",
    "undistort-captures": "--force --out --rig",
}


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    from procam.addon.cli.app import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


@pytest.mark.parametrize("command", sorted(FLAGS))
def test_each_command_keeps_its_flags(command):
    parser = _subparsers()[command]
    flags = {s for a in parser._actions for s in a.option_strings} - {"-h", "--help"}
    assert flags == set(FLAGS[command].split())


@pytest.mark.parametrize("argv", [
    ["show", "c", "t", "--out", "o", "--workers", "0"], ["show", "c", "t", "--out", "o", "--chunk", "1.5"],
    ["show", "c", "t", "--out", "o", "--connect-timeout", "nan"], ["show", "c", "t", "--out", "o", "--threads", "-2"],
    ["evaluate", "c", "--inputs", "i", "--targets", "t", "--out", "o", "--device", "camera:0"],
    ["export-frames", "c", "--out", "o", "--first", "-1"], ["precompute", "c", "--bounces", "-1"],
    ["export-mpcdi", "c", "--out", "o.mpcdi", "--profile", "3d"], ["export-mpcdi", "c", "--out", "o.mpcdi",
                                                                     "--content-size", "1920"],
    ["export-mpcdi", "c", "--out", "o.mpcdi", "--warp-step", "0"], ["apply-mpcdi", "f", "c", "--out", "o", "--first",
                                                                      "-1"],
    ["precompute", "c", "--seed", "-1"], ["demo", "--samples", "0"], ["demo", "--scale", "nan"],
    ["demo", "--iterations", "2.5"], ["demo", "--schedule", "slow"], ["lab", "--out", "o", "--seed", "-1"],
    ["lab", "--out", "o", "--supersample", "9"], ["lab-board", "--out", "o", "--poses", "2"],
    ["lab-board", "--out", "o", "--square", "0"], ["lab-board", "--out", "o", "--scale", "inf"],
    ["patterns", "--projector-width", "0", "--projector-height", "6", "--out", "o"],
    ["patterns", "--projector-width", "8", "--projector-height", "6", "--checker", "0", "--out", "o"],
    ["patterns", "--projector-width", "8", "--projector-height", "6", "--throw-ratio", "0", "--out", "o"],
    ["import-captures", "s", "p", "--out", "o", "--camera-fov", "200"],
    ["import-captures", "s", "p", "--out", "o", "--depth-native-width", "0"],
    ["capture", "--device", "camera:0", "--projector-width", "8", "--projector-height", "6", "--out", "o"],
    ["live-check", "--projector-width", "-1"],
    ["live-show", "c", "--source", "0", "--device", "live:display=1", "--hold", "-1"],
    ["live-show", "c", "--source", "0", "--device", "live:display=1", "--duration", "0"],
    ["live-show", "c", "--source", "0", "--device", "live:bogus"],
    ["live-show", "c", "--source", "0", "--device", "live:display=1,shoot='gphoto2 --filename {out}'"],
    ["compensate", "c", "t", "--out", "o", "--device", "command:run='tool {frame}'"],
    ["evaluate", "c", "--inputs", "i", "--targets", "t", "--out", "o", "--device", "live:display=1,shoot='x'"],
    ["capture", "--device", "live:display=1,shoot='x {out}',size=8x6", "--projector-width", "8",
     "--projector-height", "6", "--out", "o"],
    ["calibrate-rig", "s", "--board", "9x7", "--projector", "8x6", "--out", "r.json", "--window", "3"],
    ["calibrate-rig", "s", "--board", "9x7", "--projector", "8x6", "--out", "r.json", "--square", "nan"],
])
def test_a_bad_value_is_refused_by_every_command_where_it_is_parsed(argv, capsys):
    """Refused by argparse (exit 2, its usage line), before any step runs or anything is read."""
    from procam.addon.cli.app import build_parser

    with pytest.raises(SystemExit) as exit_:
        build_parser().parse_args(argv)
    assert exit_.value.code == 2
    assert f"procam {argv[0]}: error: argument" in capsys.readouterr().err


def test_the_demo_takes_stage_c_declaration_of_its_schedule():
    from procam.addon.options import spec_of
    from procam.addon.steps.demo import DemoOptions

    for name in ("schedule", "iterations"):
        assert spec_of(DemoOptions, name) == spec_of(StageCOptions, name)


def test_the_board_panel_fields_come_from_the_declaration():
    from procam.addon.steps.rig import RigOptions

    names = sidebar_names([RigOptions])
    assert names["--window"] == "‘Corner Window’" and names["--projector"] == "‘Projector Size’"
    scene = {"procam_board_window": 31, "procam_board_camera_distortion": "k1k2",
             "procam_board_projector_distortion": "auto"}
    options = from_values(RigOptions, scene.__getitem__, sessions=(Path("a"),), out=Path("r.json"), board=(9, 7),
                          projector_size=(8, 6))
    assert (options.window, options.camera_model, options.projector_model) == (31, "k1k2", "auto")


@pytest.mark.parametrize("argv, says", [
    (["show", "cal", "frames", "--out", "o", "--chunk", "x"], "--chunk takes a whole number, got 'x'"),
    (["compensate", "cal", "t.png", "--out", "o", "--lr", "fast"], "--lr takes a number, got 'fast'"),
    (["live-check", "--device", "live:camera=0,display=x"], "display= takes whole numbers (display=1+2), got 'x'"),
    (["live-check", "--device", "live:camera=0,position=a:b"],
     "position= takes whole numbers (position=X:Y, several as X:Y+X:Y), got 'a:b'"),
    (["live-check", "--device", "live:camera=0,latency=soon"], "latency= takes a number of seconds or auto, got "
                                                               "'soon'"),
])
def test_a_value_that_is_no_number_is_named_without_python_words(argv, says, capsys):
    from procam.addon.cli.app import main

    with pytest.raises(SystemExit) as exit_:
        raise SystemExit(main(argv))
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert says in err and "invalid literal" not in err and "could not convert" not in err, err
