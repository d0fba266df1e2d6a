"""Images decoded once: what a step keeps while it reads a capture set in several passes, and what a check trusts."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest

from procam.addon import imageio
from procam.addon.capture.format import CaptureSet
from procam.addon.errors import CaptureError
from procam.addon.imageio import kept_decoded, known_size, read_image, write_image


@pytest.fixture
def decodes(monkeypatch) -> list[str]:
    """Every file OpenCV decodes, by name."""
    seen: list[str] = []
    real = cv2.imread

    def counting(path: str, *args):
        seen.append(path)
        return real(path, *args)
    monkeypatch.setattr(imageio.cv2, "imread", counting)
    return seen


def test_a_file_read_again_within_a_step_is_not_decoded_again_and_each_reader_gets_its_own(tmp_path, decodes):
    path = tmp_path / "a.png"
    cv2.imwrite(str(path), np.full((6, 8, 3), 30000, np.uint16))  # written elsewhere: not known to this process
    with kept_decoded():
        first = read_image(path)
        first[:] = 0.0  # a reader that writes into its image does not change the next reader's
        second = read_image(path)
        assert len(decodes) == 1 and second.mean() == pytest.approx(30000 / 65535, abs=1e-6)
        # replaced: another version (another size too, so that a clock coarser than the two writes cannot hide it)
        cv2.imwrite(str(path), np.full((6, 9, 3), 1000, np.uint16))
        assert read_image(path).mean() == pytest.approx(1000 / 65535, abs=1e-6) and len(decodes) == 2
        read_image(path, keep=False)  # read for its size alone: decoded, not kept
        read_image(path, channels=1)  # another shape of the same file is its own entry
        assert len(decodes) == 4
    read_image(path)  # outside a step nothing is kept
    read_image(path)
    assert len(decodes) == 6


def test_kept_images_stay_within_their_budget_the_least_recently_read_dropped_first(tmp_path, decodes):
    paths = [tmp_path / f"{i}.png" for i in range(3)]
    for p in paths:
        cv2.imwrite(str(p), np.zeros((10, 10, 3), np.uint16))
    with kept_decoded(max_bytes=2 * 10 * 10 * 3 * 4):  # room for two
        for p in (*paths[:2], paths[0], paths[2]):  # the third pushes out the second, read longest ago
            read_image(p)
        assert len(decodes) == 3
        read_image(paths[0])
        assert len(decodes) == 3
        read_image(paths[1])
        assert len(decodes) == 4


def test_a_set_this_process_wrote_is_checked_without_decoding_it_and_a_replaced_file_is_decoded(
        lab_set, tmp_path, decodes):
    source, _ = lab_set()
    captures = tmp_path / "captures"
    shutil.copytree(source, captures)  # copied: files this process did not write
    CaptureSet.load(captures)
    everything = len(decodes)
    assert everything > 10
    CaptureSet.load(captures)  # decoded whole once: known since
    assert len(decodes) == everything
    white = CaptureSet.load(captures, verify_images=False).entry("white").file
    write_image(captures / white, read_image(captures / white))  # written by this process: its size is known
    assert known_size(captures / white) is not None
    CaptureSet.load(captures)
    assert len(decodes) == everything + 1  # the read just above, not the check
    data = (captures / white).read_bytes()
    (captures / white).write_bytes(data[: len(data) // 2])  # truncated by someone else: decoded, and refused
    with pytest.raises(CaptureError, match="unreadable or truncated"):
        CaptureSet.load(captures)


@pytest.mark.parametrize("dtype, full", [(np.uint8, 255.0), (np.uint16, 65535.0)])
def test_integer_pixels_read_as_their_share_of_full_scale_in_rgb_order(tmp_path, dtype, full):
    raw = (np.random.default_rng(4).random((5, 7, 4)) * full).astype(dtype)
    path = tmp_path / "a.png"
    cv2.imwrite(str(path), raw)  # OpenCV's order: blue, green, red, alpha
    img = read_image(path)
    assert img.dtype == np.float32 and img.flags.c_contiguous and img.shape == (5, 7, 3)
    assert np.array_equal(img, raw[..., 2::-1].astype(np.float32) / full)
    assert np.array_equal(read_image(path, channels=1), img.mean(axis=2))
