"""safepaths: a name read from a manifest resolves inside its folder or is refused, whatever the manifest says."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from procam.addon.errors import CaptureError, ProCamError
from procam.addon.safepaths import inside, within


@pytest.fixture()
def tree(tmp_path: Path) -> tuple[Path, Path]:
    """A folder with a file and a subfolder, next to an outside folder holding a secret."""
    root = tmp_path / "set"
    (root / "images").mkdir(parents=True)
    (root / "images" / "a.png").write_bytes(b"inside")
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "secret.png").write_bytes(b"secret")
    return root, outside


def test_a_relative_name_inside_resolves_under_the_folder(tree: tuple[Path, Path]) -> None:
    root, _ = tree
    assert inside(root, "images/a.png", what="image") == root / "images" / "a.png"
    assert inside(root, "./images/a.png", what="image") == root / "images" / "a.png"
    # A name not there yet is still a name inside: the reader says it is missing.
    assert inside(root, "images/later.png", what="image") == root / "images" / "later.png"


@pytest.mark.parametrize("name", ["/etc/passwd", "//etc/passwd"])
def test_an_absolute_name_is_refused(tree: tuple[Path, Path], name: str) -> None:
    root, _ = tree
    with pytest.raises(ProCamError, match="relative path inside the folder"):
        inside(root, name, what="image")


def test_an_absolute_name_to_a_file_inside_is_refused_too(tree: tuple[Path, Path]) -> None:
    root, _ = tree
    with pytest.raises(ProCamError):
        inside(root, str((root / "images" / "a.png").absolute()), what="image")


@pytest.mark.parametrize("name", ["..", "../elsewhere/secret.png", "images/../../elsewhere/secret.png",
                                  "images/..", ".", "./"])
def test_climbing_out_or_naming_the_folder_itself_is_refused(tree: tuple[Path, Path], name: str) -> None:
    root, _ = tree
    with pytest.raises(ProCamError):
        inside(root, name, what="image")


def test_a_symlinked_file_leaving_the_folder_is_refused(tree: tuple[Path, Path]) -> None:
    root, outside = tree
    os.symlink(outside / "secret.png", root / "images" / "b.png")
    with pytest.raises(ProCamError, match="outside"):
        inside(root, "images/b.png", what="image")


def test_a_relative_symlink_climbing_out_is_refused(tree: tuple[Path, Path]) -> None:
    root, _ = tree
    os.symlink("../../elsewhere/secret.png", root / "images" / "b.png")
    with pytest.raises(ProCamError, match="outside"):
        inside(root, "images/b.png", what="image")


def test_a_symlinked_folder_leaving_the_folder_is_refused(tree: tuple[Path, Path]) -> None:
    root, outside = tree
    os.symlink(outside, root / "patterns")
    with pytest.raises(ProCamError, match="outside"):
        inside(root, "patterns/secret.png", what="pattern")
    with pytest.raises(ProCamError, match="outside"):
        inside(root, "patterns", what="pattern folder")


def test_a_dangling_symlink_pointing_out_is_refused(tree: tuple[Path, Path]) -> None:
    root, outside = tree
    os.symlink(outside / "not-yet.png", root / "images" / "b.png")
    with pytest.raises(ProCamError):
        inside(root, "images/b.png", what="image")


def test_symlinks_that_stay_inside_are_fine(tree: tuple[Path, Path]) -> None:
    root, _ = tree
    os.symlink("a.png", root / "images" / "b.png")
    os.symlink("images", root / "alias")
    assert inside(root, "images/b.png", what="image").read_bytes() == b"inside"
    assert inside(root, "alias/a.png", what="image").read_bytes() == b"inside"


def test_a_folder_given_through_a_symlink_is_its_own_inside(tree: tuple[Path, Path], tmp_path: Path) -> None:
    root, _ = tree
    os.symlink(root, tmp_path / "link-to-set")
    assert inside(tmp_path / "link-to-set", "images/a.png", what="image").read_bytes() == b"inside"


@pytest.mark.parametrize("name", ["images/a\x00.png", "\x00"])
def test_a_nul_byte_is_refused(tree: tuple[Path, Path], name: str) -> None:
    root, _ = tree
    with pytest.raises(ProCamError, match="not a file name"):
        inside(root, name, what="image")


@pytest.mark.parametrize("name", [None, 3, 1.5, True, ["images/a.png"], {"file": "a"}, b"images/a.png", ""])
def test_a_name_that_is_not_a_string_is_refused(tree: tuple[Path, Path], name: object) -> None:
    root, _ = tree
    with pytest.raises(ProCamError, match="not a file name"):
        inside(root, name, what="image")


def test_the_error_class_is_the_callers(tree: tuple[Path, Path]) -> None:
    root, outside = tree
    os.symlink(outside, root / "patterns")
    for name in ("/etc/passwd", "../x", None, "patterns/secret.png"):
        with pytest.raises(CaptureError):
            inside(root, name, what="image", error=CaptureError)


def test_within_takes_a_path_from_another_folder_only_when_it_stays_there(tree: tuple[Path, Path]) -> None:
    root, outside = tree
    assert within(root, root / "images" / "a.png", what="image") == root / "images" / "a.png"
    assert within(root, root, what="folder") == root
    with pytest.raises(ProCamError, match="outside"):
        within(root, outside / "secret.png", what="image")
    with pytest.raises(ProCamError, match="outside"):
        within(root, root / ".." / "elsewhere" / "secret.png", what="image")
    with pytest.raises(ProCamError):
        within(root, str(root / "a\x00b"), what="image")
    # A sibling whose name starts like the folder's is not inside it.
    (root.parent / "set2").mkdir()
    with pytest.raises(ProCamError):
        within(root, root.parent / "set2" / "x.png", what="image")
