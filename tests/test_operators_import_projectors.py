"""Export Patterns and Import Captures for several projectors, one at a time: the dialogs' Projector Number and Add
to Capture Set, as ``procam patterns --projector-number K`` and ``procam import-captures … --add-to SET`` (the same
options, declared once on the steps), at small sizes."""

import json

import pytest

bpy = pytest.importorskip("bpy")  # before pymeshlab (shared Embree), and the operators need it

from procam.addon.blender import rig as blender_rig  # noqa: E402
from procam.addon.capture.format import CaptureSet  # noqa: E402
from procam.addon.capture.sequence import load_sequence  # noqa: E402
from procam.addon.rig.model import Projector, projector_intrinsics_from_throw  # noqa: E402
from tests.test_capture import shoot_folder  # noqa: E402

FIRST, SECOND = (80, 60), (64, 48)  # the two projectors' native sizes; the camera is 64×48, as shoot_folder's


def test_export_patterns_of_projector_2_and_import_it_added_to_projector_1s_set(registered, tmp_path):
    scene = bpy.context.scene
    assert bpy.ops.procam.create_rig(camera_width=64, camera_height=48, projector_width=FIRST[0],
                                     projector_height=FIRST[1]) == {"FINISHED"}
    blender_rig.add_projector(scene, Projector(projector_intrinsics_from_throw(*SECOND, 1.0)))
    assert len(blender_rig.find_rig_objects(scene).projectors) == 2

    # Projector Number: each projector's own sequence, at its own size; one the scene lacks is refused.
    assert bpy.ops.procam.export_patterns(directory=str(tmp_path / "seq1")) == {"FINISHED"}
    assert bpy.ops.procam.export_patterns(directory=str(tmp_path / "seq2"), projector_number=2) == {"FINISHED"}
    one, two = load_sequence(tmp_path / "seq1"), load_sequence(tmp_path / "seq2")
    assert (one.projector_index, one.projector.intrinsics.size) == (0, FIRST)
    assert (two.projector_index, two.projector.intrinsics.size) == (1, SECOND)
    assert "surface" not in [f["kind"] for f in two.frames]  # taken once, with projector 1's sequence
    with pytest.raises(RuntimeError, match="the scene has 2 ProCam projector.*‘Projector Number’ from 1 to 2"):
        bpy.ops.procam.export_patterns(directory=str(tmp_path / "seq3"), projector_number=3)
    assert not (tmp_path / "seq3").exists()

    photos1 = shoot_folder(tmp_path / "seq1", tmp_path / "photos1")
    photos2 = shoot_folder(tmp_path / "seq2", tmp_path / "photos2")
    assert bpy.ops.procam.import_captures(sequence_dir=str(tmp_path / "seq1"), photos_dir=str(photos1),
                                          out_dir=str(tmp_path / "set1")) == {"FINISHED"}
    before = (tmp_path / "set1" / "capture.json").read_bytes()
    # Add to Capture Set: the depth is set 1's; one given is refused, naming the dialog's field.
    depth = tmp_path / "depth.npy"
    depth.write_bytes(b"")
    with pytest.raises(RuntimeError, match="import without ‘Depth’"):
        bpy.ops.procam.import_captures(sequence_dir=str(tmp_path / "seq2"), photos_dir=str(photos2),
                                       out_dir=str(tmp_path / "bad"), add_to_dir=str(tmp_path / "set1"),
                                       depth_file=str(depth))
    assert not (tmp_path / "bad").exists()
    assert bpy.ops.procam.import_captures(sequence_dir=str(tmp_path / "seq2"), photos_dir=str(photos2),
                                          out_dir=str(tmp_path / "set2"),
                                          add_to_dir=str(tmp_path / "set1")) == {"FINISHED"}
    assert scene.procam_capture_dir == str(tmp_path / "set2")
    both = CaptureSet.load(tmp_path / "set2")
    assert [p.intrinsics.size for p in both.projectors] == [FIRST, SECOND]
    assert json.loads((tmp_path / "set2" / "capture.json").read_text())["notes"]["added_projectors"][0][
        "projector"] == 1
    assert (tmp_path / "set1" / "capture.json").read_bytes() == before  # the set added to is never changed
    # Without Add to Capture Set, projector 2's sequence alone is refused, saying to add it.
    with pytest.raises(RuntimeError, match="‘Add to Capture Set’"):
        bpy.ops.procam.import_captures(sequence_dir=str(tmp_path / "seq2"), photos_dir=str(photos2),
                                       out_dir=str(tmp_path / "alone"))
    assert not (tmp_path / "alone").exists()
