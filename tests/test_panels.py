"""Every ProCam panel's draw() against the real context, in each step state.

Blender in background mode cannot make a real UILayout (no window to draw in;
``window_manager.popup_menu`` crashes there), so draw() gets a recording
layout that enforces the real API from ``bpy.types.UILayout.bl_rna``: each
call must be a UILayout function with known keywords and its required
arguments, icons and enum values must exist, operators must be registered,
properties must exist on their data, and attributes set on an operator
button must be that operator's properties.
"""

import json
import threading

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from procam.addon import jobs  # noqa: E402
from procam.addon.errors import ImageError  # noqa: E402
from procam.addon.imageio import write_image  # noqa: E402

RNA = bpy.types.UILayout.bl_rna


class ButtonProps:
    """The properties of an operator button: only the operator's own may be set."""

    def __init__(self, idname):
        module, name = idname.split(".")
        rna = getattr(getattr(bpy.ops, module), name).get_rna_type()
        object.__setattr__(self, "_names", {p.identifier for p in rna.properties} - {"rna_type"})
        object.__setattr__(self, "_idname", idname)

    def __setattr__(self, key, value):
        assert key in self._names, f"{self._idname} has no property {key!r}"


class RecordingLayout:
    def __init__(self, calls):
        object.__setattr__(self, "calls", calls)

    def __setattr__(self, key, value):
        assert key in RNA.properties, f"UILayout has no attribute {key!r}"

    def __getattr__(self, name):
        fn = RNA.functions.get(name)
        assert fn is not None, f"UILayout has no function {name!r}"
        params = [p for p in fn.parameters if not p.is_output]
        output = next((p for p in fn.parameters if p.is_output), None)

        def call(*args, **kwargs):
            assert len(args) <= len(params), f"{name}: too many positional arguments"
            given = dict(zip((p.identifier for p in params), args))
            for key in kwargs:
                assert key in {p.identifier for p in params}, f"{name}() has no keyword {key!r}"
                assert key not in given, f"{name}(): {key!r} given twice"
            given.update(kwargs)
            for p in params:
                if p.is_required:
                    assert p.identifier in given, f"{name}() needs {p.identifier!r}"
                value = given.get(p.identifier)
                if value is not None and p.type == "ENUM" and not p.is_enum_flag:
                    assert value in {i.identifier for i in p.enum_items}, f"{name}(): {p.identifier}={value!r}"
            if name in ("operator",):
                idname = given["operator"]
                module, op = idname.split(".")
                assert hasattr(getattr(bpy.ops, module), op) and getattr(getattr(bpy.ops, module), op).idname(), idname
            if name in ("prop",):
                assert given["property"] in given["data"].bl_rna.properties, f"no property {given['property']!r}"
            if name == "template_list":
                assert hasattr(bpy.types, given["listtype_name"]), given["listtype_name"]
                assert given["propname"] in given["dataptr"].bl_rna.properties
                assert given["active_propname"] in given["active_dataptr"].bl_rna.properties
            self.calls.append((name, given))
            if output is not None and output.type == "POINTER":
                kind = output.fixed_type.identifier
                if kind == "UILayout":
                    return RecordingLayout(self.calls)
                if kind == "OperatorProperties":
                    return ButtonProps(given["operator"])
            return None

        return call


PANELS = ("PROCAM_PT_rig", "PROCAM_PT_captures", "PROCAM_PT_live", "PROCAM_PT_calibrate", "PROCAM_PT_compensate",
          "PROCAM_PT_diagnose", "PROCAM_PT_export")


def draw_all(context):
    out = {}
    for name in PANELS:
        panel = getattr(bpy.types, name)
        calls = []
        fake = type("Drawn", (), {"layout": RecordingLayout(calls)})()
        panel.draw(fake, context)
        out[name] = calls
    return out


def texts(calls):
    return " | ".join(str(c[1].get("text", "")) for c in calls)


def test_panels_are_in_workflow_order(registered):
    orders = [getattr(bpy.types, n).bl_order for n in PANELS]
    assert orders == sorted(orders) and len(set(orders)) == len(PANELS)
    assert {getattr(bpy.types, n).bl_category for n in PANELS} == {"ProCam"}


def test_recording_layout_catches_api_mistakes(registered):
    layout = RecordingLayout([])
    with pytest.raises(AssertionError, match="no function"):
        layout.lable(text="x")
    with pytest.raises(AssertionError, match="icon"):
        layout.label(text="x", icon="NOT_AN_ICON")
    with pytest.raises(AssertionError, match="no keyword"):
        layout.operator("procam.calibrate", txt="x")
    with pytest.raises(AssertionError, match="no property"):
        layout.prop(bpy.context.scene, "procam_nothing")
    with pytest.raises(AssertionError, match="has no property"):
        layout.operator("procam.cancel_job").stp = "x"


def test_every_panel_draws_not_run_state(registered):
    drawn = draw_all(bpy.context)
    assert "Not run" in texts(drawn["PROCAM_PT_calibrate"])
    assert "Not run" in texts(drawn["PROCAM_PT_compensate"])
    ops = [c[1]["operator"] for calls in drawn.values() for c in calls if c[0] == "operator"]
    assert {"procam.create_rig", "procam.run_lab", "procam.calibrate", "procam.load_calibration", "procam.add_targets",
            "procam.compensate", "procam.diagnose", "procam.export_frames",
            "procam.export_calibration_blend", "procam.live_check", "procam.live_preview",
            "procam.live_capture"} <= set(ops)


def test_panels_draw_running_failed_and_done_states(registered, tmp_path):
    scene = bpy.context.scene
    # Running: a job blocked in a worker shows a progress bar and a Cancel button.
    gate = threading.Event()

    def engine(*, progress, cancel):
        progress("stage A: solving PnP", 0.4)
        gate.wait(5)

    job = jobs.BOARD.add("calibrate", jobs.Job("calibration", engine)).start()
    try:
        for _ in range(100):
            if job.snapshot().fraction > 0:
                break
            threading.Event().wait(0.01)
        calls = draw_all(bpy.context)["PROCAM_PT_calibrate"]
        assert any(c[0] == "progress" and c[1]["factor"] == pytest.approx(0.4) for c in calls)
        assert "stage A: solving PnP" in texts(calls) and "Cancel" in texts(calls)
    finally:
        gate.set()
        job.wait(5)

    # Failed: the message is shown.
    def fails(*, progress, cancel):
        raise ImageError("target t.png is unreadable: choose another file")

    jobs.BOARD.add("compensate", jobs.Job("compensation", fails)).run()
    assert "unreadable" in texts(draw_all(bpy.context)["PROCAM_PT_compensate"])

    # Done: a compensation folder and a diagnosis folder are summarised with their figures and buttons.
    comp = tmp_path / "comp"
    comp.mkdir()
    for suffix in ("input", "frame", "simulated"):
        write_image(comp / f"a_{suffix}.png", np.zeros((4, 4, 3), np.float32))
    (comp / "compensation.json").write_text(json.dumps({
        "format": "procam-compensation", "mode": "open-loop", "complete": True,
        "targets": [{"name": "a", "status": "done", "input": "a_input.png", "frame": "a_frame.png",
                     "simulated": "a_simulated.png", "seconds": 3.0, "psnr_simulated_start": 20.0,
                     "psnr_simulated": 27.5}]}))
    gap = tmp_path / "gap"
    gap.mkdir()
    write_image(gap / "residual.png", np.zeros((4, 4, 3), np.float32))
    (gap / "summary.md").write_text("# Sim-to-real gap\n\nresponse removes 33 %\n")
    (gap / "gap.json").write_text(json.dumps({
        "format": "procam-gap", "version": 1, "residual": {"rmse": 0.031, "psnr": 30.2},
        "regions": [{"bbox": [0, 0, 10, 10], "share": 0.55, "description": "projector border"}],
        "effects": [{"name": "vignetting", "params": {}, "heldout_rmse_before": 0.03, "heldout_rmse_after": 0.025,
                     "confidence": 0.7},
                    {"name": "response", "params": {}, "heldout_rmse_before": 0.03, "heldout_rmse_after": 0.02,
                     "confidence": 0.9}],
        "selected": ["response"], "headline": "The projector is out of focus: compensate with --effects auto.",
        "warnings": ["the selection stopped at its limit of 5 effects: --max-effects 6 would try it",
                     "a blur of about a texel can go unseen; --scale 0.9 looks at 2.0 texels a pixel"]}))
    jobs.BOARD.clear()
    scene.procam_compensation_dir = str(comp)
    scene.procam_diagnosis_dir = str(gap)
    drawn = draw_all(bpy.context)
    comp_text = texts(drawn["PROCAM_PT_compensate"])
    assert "1/1 targets compensated (open-loop)" in comp_text and "20.0 → 27.5 dB" in comp_text
    assert any(c[0] == "operator" and c[1]["operator"] == "procam.preview_compensated"
               for c in drawn["PROCAM_PT_compensate"])
    diag = texts(drawn["PROCAM_PT_diagnose"])
    assert diag.index("response") < diag.index("vignetting")  # selected first
    assert "55% projector border" in diag and "residual" in diag
    # the diagnosis's advice names the sidebar's fields, and the limit it names is a field of this panel
    assert "‘Effect Models’" in diag and "‘Max Effects’" in diag and "‘Working Scale’" in diag
    assert "--" not in diag
    fields = [c[1]["property"] for c in drawn["PROCAM_PT_diagnose"] if c[0] == "prop"]
    assert "procam_max_effects" in fields and "procam_diagnosis_scale" in fields
    opens = [c[1] for c in drawn["PROCAM_PT_diagnose"] if c[0] == "operator" and c[1]["operator"] == "procam.show_text"]
    assert len(opens) == 1
    assert bpy.ops.procam.show_text(filepath=str(gap / "summary.md"), name="ProCam diagnosis summary") == {"FINISHED"}
    assert bpy.data.texts["ProCam diagnosis summary"].as_string().startswith("# Sim-to-real gap")
    with pytest.raises(RuntimeError, match="cannot read .*missing.md"):
        bpy.ops.procam.show_text(filepath=str(gap / "missing.md"))


def test_calibrate_panel_shows_key_figures_of_a_calibration_folder(registered, tmp_path):
    cal = tmp_path / "cal"
    (cal / "diagnostics").mkdir(parents=True)
    write_image(cal / "diagnostics" / "pose_mask.png", np.zeros((4, 4, 3), np.float32))
    pose = np.eye(4)
    pose[:3, 3] = [0.2, -0.1, 0.05]
    (cal / "calibration.json").write_text(json.dumps({
        "format": "procam-calibration", "camera_from_projector": pose.tolist(), "init": "graycode",
        "surface_report": {"vertices": 120, "faces": 200}, "losses": {"pose": 0.01, "warp": 0.04},
        "warp_report": {"corners_before_px": {"median": 2.5}, "corners_after_px": {"median": 0.1}},
        "seconds": {"surface": 1.0, "pose": 2.0, "warp": 3.0}}))
    bpy.context.scene.procam_calibration_dir = str(cal)
    calls = draw_all(bpy.context)["PROCAM_PT_calibrate"]
    text = texts(calls)
    assert "2.50 → 0.10 px" in text and "200 faces" in text and "(+0.200, -0.100, +0.050) m" in text
    assert any(c[0] == "operator" and c[1]["operator"] == "procam.show_image" for c in calls)


def test_board_calibration_subpanel_draws_its_states(registered, tmp_path):
    """The Captures panel's Board Calibration: not run (with what to choose), the poses it found, a running job
    with Cancel."""
    panel = bpy.types.PROCAM_PT_board
    assert panel.bl_parent_id == "PROCAM_PT_captures" and panel.bl_category == "ProCam"

    def draw():
        calls = []
        panel.draw(type("Drawn", (), {"layout": RecordingLayout(calls)})(), bpy.context)
        return calls

    calls = draw()
    assert "Choose the folder of board sessions" in texts(calls) and "Not run" in texts(calls)
    assert any(c[0] == "operator" and c[1]["operator"] == "procam.calibrate_rig" for c in calls)
    for name in ("pose_1", "pose_2", "pose_10", "empty"):
        (tmp_path / name).mkdir()
        if name != "empty":
            (tmp_path / name / "graycode_00.png").write_bytes(b"")
    bpy.context.scene.procam_board_sessions_dir = str(tmp_path)
    assert "3 board poses: pose_1, pose_2, pose_10" in texts(draw())  # natural order, folders without images left out
    gate = threading.Event()
    job = jobs.BOARD.add("calibrate_rig", jobs.Job("rig calibration", lambda *, progress, cancel: (
        progress("pose_2: decoding the Gray code", 0.3), gate.wait(5)))).start()
    try:
        for _ in range(100):
            if job.snapshot().fraction > 0:
                break
            threading.Event().wait(0.01)
        text = texts(draw())
        assert "pose_2: decoding the Gray code" in text and "Cancel" in text
    finally:
        gate.set()
        job.wait(5)


def test_live_panel_draws_placement_check_report_and_session(registered, tmp_path):
    """Display or position fields by placement, the last check's measurements, an interrupted session; Compensate's
    Live mode names the Live panel's rig instead of the Device field."""
    from procam.addon.live.device import LiveReport

    scene = bpy.context.scene

    def props(calls):
        return [c[1]["property"] for c in calls if c[0] == "prop"]

    calls = draw_all(bpy.context)["PROCAM_PT_live"]
    assert "procam_live_display" in props(calls) and "procam_live_position" not in props(calls)
    assert "Not run" in texts(calls)
    scene.procam_live_placement = "POSITION"
    report = LiveReport(0.12, (0.1, 0.12, 0.11), 1 / 30, 0.004, 2, {"exposure": True}, 0.01, 0.0)
    jobs.BOARD.add("live_check", jobs.Job("live check", lambda *, progress, cancel: ("displays: 0: 800×600",
                                                                                       report))).run()
    (tmp_path / "set.session").mkdir()
    (tmp_path / "set.session" / "session.json").write_text("{}")
    scene.procam_live_capture_dir = str(tmp_path / "set")
    drawn = draw_all(bpy.context)
    calls = drawn["PROCAM_PT_live"]
    assert "procam_live_position" in props(calls) and "procam_live_display" not in props(calls)
    text = texts(calls)
    assert "latency 120 ms" in text and "displays: 0: 800×600" in text and "interrupted session" in text
    job = jobs.BOARD.add("live_capture", jobs.Job("live capture", lambda *, progress, cancel: None))
    job.cancel()
    job.run()
    assert "interrupted session" in texts(draw_all(bpy.context)["PROCAM_PT_live"])  # said after Esc too
    assert "procam_device" in props(drawn["PROCAM_PT_compensate"])
    scene.procam_compensation_mode = "LIVE"
    compensate = draw_all(bpy.context)["PROCAM_PT_compensate"]
    assert "procam_device" not in props(compensate) and "Live panel" in texts(compensate)


def test_live_panel_shows_the_live_shows_frame_rate_while_it_runs_and_its_report_after(registered):
    """Running: the last second's figures and Stop Live Show in place of Start; after: the report's lines."""
    from procam.addon.steps.live_show import LiveShowReport, LiveStatus, ShownFrame
    from procam.operators.live_show import SHOW_STATUS

    def operators(calls):
        return [c[1]["operator"] for c in calls if c[0] == "operator"]

    calls = draw_all(bpy.context)["PROCAM_PT_live"]
    assert "procam.live_show_start" in operators(calls) and "procam_live_source" in [
        c[1]["property"] for c in calls if c[0] == "prop"]
    report = LiveShowReport(frames_in=4, dropped=1, seconds=0.2, stopped="the video ended",
                            frames=[ShownFrame(n, 0.04 * n, 0.04 * n + 0.012, 8.0) for n in (1, 2, 4)])
    gate = threading.Event()
    job = jobs.BOARD.add("live_show", jobs.Job("live show", lambda *, progress, cancel: gate.wait(5) and report))
    job.start()
    try:
        SHOW_STATUS.update(LiveStatus(3.0, 90, 85, 5, 9.6, 14.2, 29.7))
        calls = draw_all(bpy.context)["PROCAM_PT_live"]
        text = texts(calls)
        assert "29.7 fps: shown 85, dropped 5" in text and "latency 14 ms, solve 10 ms" in text
        assert "procam.live_show_stop" in operators(calls) and "procam.live_show_start" not in operators(calls)
    finally:
        gate.set()
        job.wait(5)
    calls = draw_all(bpy.context)["PROCAM_PT_live"]
    text = texts(calls)
    assert "Live show: 3 frames shown of 4 in, 1" in text and "16.7 fps (open loop)" in text  # wrapped lines
    assert "stopped: the video ended" in text and "procam.live_show_start" in operators(calls)


def test_step_messages_name_the_sidebar_fields_not_the_command_options():
    """The steps' messages are the command's ("rerun with --force"); the sidebar reports them by its fields, and
    every field a message may name is one the sidebar has."""
    from procam.operators.messages import DIAGNOSE_FIELDS, SIDEBAR_NAMES, sidebar_text
    from procam.panels.properties import scene_properties

    assert sidebar_text("x already holds a calibration; it is never overwritten without --force (force=True)") == \
        "x already holds a calibration; it is never overwritten without ‘Replace Results’"
    assert sidebar_text("choose another --out", {"--out": "‘Show’ folder"}) == "choose another ‘Show’ folder"
    assert sidebar_text("give --workers N") == "give --workers (an option of the procam command) N"
    assert sidebar_text("a--b and --force-ish stay") == "a--b and --force-ish (an option of the procam command) stay"
    labels = {getattr(p, "keywords", {}).get("name") for p in scene_properties().values()}
    for option, text in [*SIDEBAR_NAMES.items(), *DIAGNOSE_FIELDS.items()]:
        assert option == "--out" or text.strip("‘’") in labels, (option, text)
