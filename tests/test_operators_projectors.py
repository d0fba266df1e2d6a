"""Blender's sidebar with several projectors: Load Calibration places every projector, Compensate and Preview put
each projector's own frame on it, and the Calibrate, Compensate and Diagnose panels show every projector."""

import json

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")  # before pymeshlab (shared Embree), and the operators need it

from procam.addon.blender import rig as blender_rig  # noqa: E402
from procam.addon.imageio import read_image, write_image  # noqa: E402
from procam.addon.steps import compensate as compensate_step  # noqa: E402
from procam.addon.steps.calibrate import read as read_calibration  # noqa: E402
from tests.test_panels import draw_all  # noqa: E402


@pytest.fixture(scope="module")
def two(two_projector_lab):
    """A two-projector lab (curve, 20 % overlap, camera 128×96, projectors 160×120), calibrated, two targets."""
    from procam.addon.capture.targets import natural_target

    root = two_projector_lab
    targets = [write_image(root / f"{n}.png", natural_target(n, (120, 90))) for n in ("city", "forest")]
    return root, targets


def joined(calls):
    """The panel's text as one string: the sidebar wraps long lines at spaces, joined here again."""
    return " ".join(str(c[1].get("text", "")) for c in calls)


def _shown(scene):
    return [blender_rig.projector_image(o) for o in blender_rig.find_rig_objects(scene).projectors]


def test_each_projector_is_placed_and_shows_its_own_compensated_frame(registered, two, tmp_path):
    root, targets = two
    scene = bpy.context.scene
    bpy.ops.procam.create_rig(camera_width=128, camera_height=96, projector_width=160, projector_height=120,
                              surface="plane")  # the artist's one-projector scene
    scene.procam_calibration_dir = str(root / "cal")
    assert bpy.ops.procam.load_calibration() == {"FINISHED"}
    cal = read_calibration(root / "cal")
    objs = blender_rig.find_rig_objects(scene)
    assert len(objs.projectors) == 2
    for k, model in enumerate(blender_rig.read_rig(scene).projectors):
        np.testing.assert_allclose(model.camera_from_projector, cal.rig.projectors[k].camera_from_projector,
                                   atol=1e-6)
    nodes = [o.data.node_tree.nodes["ProCam Frame"].image for o in objs.projectors]
    assert nodes[0] != nodes[1]  # each projector has its own frame image
    assert {"ProCam Calibration warp_grid", "ProCam Calibration p2_warp_grid"} <= set(bpy.data.images.keys())

    for p in targets:
        scene.procam_targets.add().filepath = str(p)
    scene.procam_compensation_mode = "OPEN"
    scene.procam_iterations = 6
    scene.procam_compensation_dir = str(tmp_path / "comp")
    assert bpy.ops.procam.compensate() == {"FINISHED"}
    view = compensate_step.read(tmp_path / "comp")
    assert view.projector_count == 2 and [t.name for t in view.targets] == ["city", "forest"]
    assert [p.name for p in view.targets[1].frame_paths] == ["forest_frame_p1.png", "forest_frame_p2.png"]
    assert {"ProCam city input p1", "ProCam city input p2", "ProCam city simulated"} <= set(bpy.data.images.keys())
    # after Compensate, each projector shows its own frame of the first target
    for shown, path in zip(_shown(scene), view.targets[0].frame_paths):
        np.testing.assert_allclose(shown, read_image(path), atol=1e-4)
    assert not np.allclose(*_shown(scene), atol=1e-2)
    assert bpy.ops.procam.preview_compensated(target="forest") == {"FINISHED"}
    for shown, path in zip(_shown(scene), view.targets[1].frame_paths):
        np.testing.assert_allclose(shown, read_image(path), atol=1e-4)

    # the panels: every projector's inputs, the number of projectors in the headline, each one's diagnostics
    drawn = draw_all(bpy.context)
    comp = drawn["PROCAM_PT_compensate"]
    assert "2/2 targets compensated (open-loop) on 2 projectors" in joined(comp)
    assert "share of the light projector 1" in joined(comp)
    names = [c[1] for c in comp if c[0] == "operator" and c[1]["operator"] == "procam.show_image"]
    assert [c.get("text") for c in names[:3]] == ["1", "2", ""]  # city's input of each projector, its simulation
    cal_text = joined(drawn["PROCAM_PT_calibrate"])
    assert "Calibrated 2 projectors" in cal_text and "Projector 1:" in cal_text and "Projector 2:" in cal_text
    assert cal_text.index("Projector 2:") < cal_text.index("p2_warp_grid")
    assert "2 of 2" in joined(drawn["PROCAM_PT_rig"]) or "1 of 2" in joined(drawn["PROCAM_PT_rig"])

    # Export Projector Frames: one sequence per projector
    assert bpy.ops.procam.export_frames(directory=str(tmp_path / "frames")) == {"FINISHED"}
    assert sorted(str(p.relative_to(tmp_path / "frames")) for p in (tmp_path / "frames").rglob("*.png")) == [
        f"projector_{k}/frame_000{n}.png" for k in (1, 2) for n in (1, 2)]

    # a scene of another number of projectors is refused, and no projector changes
    bpy.ops.procam.create_rig(camera_width=128, camera_height=96, projector_width=160, projector_height=120)
    before = _shown(scene)
    with pytest.raises(RuntimeError, match="the scene has 1 ProCam projector.*frames for 2"):
        bpy.ops.procam.preview_compensated(target="city")
    np.testing.assert_array_equal(_shown(scene)[0], before[0])


def test_diagnose_panel_shows_the_verdict_and_a_line_per_projector(registered, tmp_path):
    """A diagnosis of two projectors (written here as procam diagnose writes it): the headline names the projector
    that differs, a line per projector, each projector's maps under its number; no one-projector boxes."""
    gap = tmp_path / "gap"
    for k in (1, 2):
        (gap / f"projector_{k}").mkdir(parents=True)
        write_image(gap / f"projector_{k}" / "residual_abs.png", np.zeros((4, 4, 3), np.float32))
    (gap / "summary.md").write_text("# ProCam sim-to-real diagnosis of 2 projectors\n")
    (gap / "gap.json").write_text(json.dumps({
        "format": "procam-gap", "version": 1, "projector_count": 2,
        "headline": "Projector 2 differs from the others by its response: 45% of its residual",
        "differs": {"projector": 2, "effect": "response"}, "selected": ["response", "vignetting"],
        "ranking": [{"projector": 2, "effect": "response", "reduction": 0.45, "others": 0.02, "margin": 0.43}],
        "projectors": [{"folder": "projector_1", "headline": "vignetting", "selected": ["vignetting"],
                        "residual": {"rmse": 0.03}, "residual_after": {"rmse": 0.02}},
                       {"folder": "projector_2", "headline": "response", "selected": ["response"],
                        "residual": {"rmse": 0.05}, "residual_after": {"rmse": 0.02}}]}))
    bpy.context.scene.procam_diagnosis_dir = str(gap)
    calls = draw_all(bpy.context)["PROCAM_PT_diagnose"]
    text = joined(calls)
    assert "Projector 2 differs from the others by its response" in text
    assert "projector 1: residual RMSE 0.0300 → 0.0200, selected vignetting" in text
    assert "projector 2: residual RMSE 0.0500" in text
    assert "Effects (selected first" not in text and "Regions (by share" not in text
    assert text.index("Projector 1:") < text.index("Projector 2:")
    maps = [c[1] for c in calls if c[0] == "operator" and c[1]["operator"] == "procam.show_image"]
    assert [m["text"] for m in maps] == ["residual_abs", "residual_abs"]
