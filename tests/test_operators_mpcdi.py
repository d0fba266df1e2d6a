"""Export ▸ MPCDI in Blender: the same file as ``procam export-mpcdi``, its poll, and its refusal to replace a file."""

from __future__ import annotations

import pytest

bpy = pytest.importorskip("bpy")  # before pymeshlab (shared Embree), and the operators need it

from procam.addon.mpcdi.format import read_mpcdi  # noqa: E402
from tests.test_mpcdi import _calibration  # noqa: E402


def test_export_mpcdi_operator(registered, tmp_path):
    scene = bpy.context.scene
    scene.procam_calibration_dir = str(tmp_path / "nothing")
    assert not bpy.ops.procam.export_mpcdi.poll()
    scene.procam_calibration_dir = str(_calibration(tmp_path / "cal"))
    assert bpy.ops.procam.export_mpcdi.poll()
    out = tmp_path / "show.mpcdi"
    assert bpy.ops.procam.export_mpcdi(filepath=str(out), profile="2d") == {"FINISHED"}
    assert [r.id for r in read_mpcdi(out).regions] == ["projector_1", "projector_2"]
    with pytest.raises(RuntimeError, match="without ‘Replace’"):
        bpy.ops.procam.export_mpcdi(filepath=str(out))
    assert bpy.ops.procam.export_mpcdi(filepath=str(out), profile="sl", force=True) == {"FINISHED"}
    assert read_mpcdi(out).profile == "sl"
