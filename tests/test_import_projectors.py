"""Several projectors from one's own photographs: `procam patterns --projector-number K` for each projector and
`procam import-captures … --add-to SET --out NEW` (issue 38, item 2), at small sizes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from procam.addon.capture.format import CaptureSet
from procam.addon.capture.sequence import load_sequence
from procam.addon.cli.app import main
from procam.addon.imageio import read_image, write_image

from .test_capture import CAM, WarpDevice, _rig_file, shoot_folder, siblings

FIRST, SECOND = (80, 60), (64, 48)  # the two projectors' native sizes; the camera is 64×48


def patterns(out: Path, size: tuple[int, int], *extra: str) -> Path:
    args = ["patterns", "--projector-width", str(size[0]), "--projector-height", str(size[1]), "--checker", "8",
            "--no-graycode", "--out", str(out), *extra]
    assert main(args) == 0
    return out


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """Two projectors' sequences, photographed one at a time (the other black), and projector 1's set."""
    root = tmp_path_factory.mktemp("two")
    seq1, seq2 = patterns(root / "seq1", FIRST), patterns(root / "seq2", SECOND, "--projector-number", "2")
    photos1, photos2 = shoot_folder(seq1, root / "photos1"), shoot_folder(seq2, root / "photos2")
    assert main(["import-captures", str(seq1), str(photos1), "--out", str(root / "set1")]) == 0
    return root, seq1, seq2, photos1, photos2


def test_patterns_of_further_projectors_are_numbered_and_leave_out_the_surface_photo(session):
    _, seq1, seq2, _, _ = session
    doc1, doc2 = (json.loads((s / "sequence.json").read_text()) for s in (seq1, seq2))
    assert "projector_index" not in doc1 and doc1["frames"][0]["kind"] == "surface"  # one projector: as before
    assert doc2["projector_index"] == 1 and "surface" not in [f["kind"] for f in doc2["frames"]]
    assert len(doc2["frames"]) == len(doc1["frames"]) - 1 and "projector 2's sequence" in doc2["instructions"][0]
    info = load_sequence(seq2)
    assert info.projector_index == 1 and info.projector.intrinsics.size == SECOND


def test_two_projectors_imported_one_at_a_time_make_one_new_set(session, capsys):
    root, seq1, seq2, photos1, photos2 = session
    set1, set2 = root / "set1", root / "set2"
    before = (set1 / "capture.json").read_bytes()
    capsys.readouterr()
    assert main(["import-captures", str(seq2), str(photos2), "--add-to", str(set1), "--out", str(set2)]) == 0
    out = capsys.readouterr().out
    assert "2 projectors (1: 80×60, 2: 64×48)" in out and "left as it was" in out
    assert (set1 / "capture.json").read_bytes() == before  # the set added to is an input: never changed
    one, two = CaptureSet.load(set1), CaptureSet.load(set2)
    assert [p.intrinsics.size for p in two.projectors] == [FIRST, SECOND] and two.camera == one.camera
    assert len(two.entries_of("surface")) == 1  # taken once, with projector 1's sequence
    first, second = two.for_projector(0), two.for_projector(1)
    assert [(e.kind, e.name, e.params) for e in first] == [(e.kind, e.name, e.params) for e in one]
    assert np.array_equal(first.image("white"), one.image("white"))  # projector 1's captures copied exactly
    assert [e.kind for e in second] == [e.kind for e in first]  # its own sequence + the shared surface photo
    assert second.pattern("white").shape[:2] == SECOND[::-1] and first.pattern("white").shape[:2] == FIRST[::-1]
    white2 = second.entry("white")
    assert white2.params["source"] == "IMG_0101.png" and white2.name == "white_p1"
    assert np.allclose(second.image("white"), read_image(photos2 / "IMG_0101.png"), atol=1e-4)
    added = two.notes["added_projectors"]
    assert [a["projector"] for a in added] == [1] and added[0]["captures"] == str(photos2.resolve())
    assert "exposure" in added[0] and two.notes["captures"] == one.notes["captures"]

    # what must not be mixed is refused, and nothing is written
    def refused(args: list[str], message: str) -> None:
        assert main(["import-captures", *args]) == 2
        assert message in capsys.readouterr().err
    refused([str(seq2), str(photos2), "--add-to", str(set1), "--out", str(set1), "--force"], "is an input of this run")
    refused([str(seq2), str(photos2), "--add-to", str(set2), "--out", str(root / "x")],
            "holds projector 2's captures already")
    refused([str(seq1), str(photos1), "--add-to", str(set1), "--out", str(root / "x")],
            "it may be that projector's sequence again")
    seq3 = patterns(root / "seq3", (72, 54), "--projector-number", "3")
    refused([str(seq3), str(photos2), "--add-to", str(set1), "--out", str(root / "x")], "add projector 2 first")
    refused([str(seq2), str(photos1), "--add-to", str(set1), "--out", str(root / "x")],
            "are in " + str(set1) + " already (projector 1's)")
    refused([str(seq2), str(photos2), "--out", str(root / "x")], "--add-to SET --out NEW_SET")
    depth = root / "depth.npy"
    np.save(depth, np.full(CAM[::-1], 1.5, np.float32))
    refused([str(seq2), str(photos2), "--add-to", str(set1), "--out", str(root / "x"), "--depth", str(depth)],
            "the depth is taken once")
    assert not (root / "x").exists() and siblings(root / "x") == []
    assert (set1 / "capture.json").read_bytes() == before


def test_another_camera_size_is_refused(session, tmp_path, capsys):
    root, _, seq2, _, _ = session
    info = load_sequence(seq2)
    device = WarpDevice(info.projector, cam_size=(80, 60))
    photos = tmp_path / "wide"
    photos.mkdir()
    for i, f in enumerate(info.frames):
        write_image(photos / f"{i:04d}.png", device.project(read_image(seq2 / f["file"])))
    out = tmp_path / "set"
    assert main(["import-captures", str(seq2), str(photos), "--add-to", str(root / "set1"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "are 80×60 pixels" in err and "camera took 64×48" in err and "same camera" in err
    assert not out.exists() and siblings(out) == []


def test_a_projector_left_on_while_another_was_photographed_is_refused(session, tmp_path, capsys):
    """Projector 1 still showed white while projector 2's sequence was photographed: the finished set fails the
    black check before it is moved into place."""
    root, _, seq2, photos1, photos2 = session
    lit = tmp_path / "lit"
    lit.mkdir()
    white1 = read_image(photos1 / "IMG_0102.png")
    for p in sorted(photos2.iterdir()):
        write_image(lit / p.name, np.clip(read_image(p) + 0.1 * white1, 0, 1))
    out = tmp_path / "set"
    assert main(["import-captures", str(seq2), str(lit), "--add-to", str(root / "set1"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"capture set {out}: projector 2's black capture" in err and "projector 1 was not black" in err
    assert not out.exists() and siblings(out) == []


def test_every_projector_goes_through_one_camera_calibration(tmp_path, capsys):
    """With rig files: projector 2's needs the camera lens of the set's photographs; its own K and pose come in."""
    seq1, seq2 = patterns(tmp_path / "seq1", FIRST), patterns(tmp_path / "seq2", SECOND, "--projector-number", "2")
    photos1, photos2 = shoot_folder(seq1, tmp_path / "p1"), shoot_folder(seq2, tmp_path / "p2")
    lens = [-0.2, 0.0, 0.0, 0.0, 0.0]
    rig1 = _rig_file(tmp_path / "rig1.json", CAM, FIRST, lens)
    rig2 = _rig_file(tmp_path / "rig2.json", CAM, SECOND, lens)
    other = _rig_file(tmp_path / "other.json", CAM, SECOND, [-0.1, 0.0, 0.0, 0.0, 0.0])
    assert main(["import-captures", str(seq1), str(photos1), "--out", str(tmp_path / "set1"), "--rig", str(rig1)]) == 0
    assert main(["import-captures", str(seq1), str(photos1), "--out", str(tmp_path / "plain")]) == 0
    add = ["import-captures", str(seq2), str(photos2), "--add-to"]
    capsys.readouterr()
    assert main([*add, str(tmp_path / "set1"), "--out", str(tmp_path / "x"), "--rig", str(other)]) == 2
    assert "has another camera lens" in capsys.readouterr().err
    assert main([*add, str(tmp_path / "set1"), "--out", str(tmp_path / "x")]) == 2
    assert "take the same lens out of this projector's" in capsys.readouterr().err
    assert main([*add, str(tmp_path / "plain"), "--out", str(tmp_path / "x"), "--rig", str(rig2)]) == 2
    assert "kept the camera's lens distortion" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    assert main([*add, str(tmp_path / "set1"), "--out", str(tmp_path / "set2"), "--rig", str(rig2)]) == 0
    two = CaptureSet.load(tmp_path / "set2")
    assert (two.camera_status, two.projector_status, two.projector_pose_known) == ("calibrated", "calibrated", True)
    assert two.projectors[1].intrinsics.size == SECOND and two.projectors[1].intrinsics.cy == 80.5  # rig 2's K
    assert two.camera_lens == CaptureSet.load(tmp_path / "set1").camera_lens
    # Added without lenses, the lens comes out of the whole set of two afterwards, each projector's photographs alike
    assert main([*add, str(tmp_path / "plain"), "--out", str(tmp_path / "plain2")]) == 0
    assert main(["undistort-captures", str(tmp_path / "plain2"), "--rig", str(rig1), "--out", str(tmp_path / "u")]) == 0
    undistorted = CaptureSet.load(tmp_path / "u")
    assert len(undistorted.projectors) == 2 and undistorted.camera_lens["distortion"] == two.camera_lens["distortion"]
    assert np.allclose(undistorted.for_projector(1).image("white"), two.for_projector(1).image("white"), atol=1e-4)


def test_a_projector_whose_photographs_are_copies_of_another_ones_is_refused(session, tmp_path, capsys):
    """Projector 2's photographs copied from projector 1's (issue 53, item 5): said at import, not left to the
    calibration's "same pose" (which no stage can mend)."""
    root, _, seq2, photos1, photos2 = session
    copied = tmp_path / "copied"
    copied.mkdir()
    ones = sorted(photos1.iterdir())[1:]  # projector 1's, without the surface photo projector 2's sequence lacks
    for one, two in zip(ones, sorted(photos2.iterdir()), strict=True):
        write_image(copied / two.name, read_image(one))
    out = tmp_path / "set"
    assert main(["import-captures", str(seq2), str(copied), "--add-to", str(root / "set1"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"capture set {out}: projector 2's photographs are the same as projector 1's" in err, err
    assert "copied" in err and "numbered from 0" not in err
    assert not out.exists() and siblings(out) == []
    # nearly the same (a copy saved again with a little noise) is the same too
    rng = np.random.default_rng(0)
    for p in copied.iterdir():
        write_image(p, np.clip(read_image(p) + rng.normal(0, 0.002, read_image(p).shape), 0, 1).astype(np.float32))
    assert main(["import-captures", str(seq2), str(copied), "--add-to", str(root / "set1"), "--out", str(out)]) == 2
    assert "are the same as projector 1's" in capsys.readouterr().err
