"""The live device with several projectors on a virtual X server: one window per projector, all shown at once, a
loopback network camera filming both, and ``procam capture`` of a two-projector rig into one capture set.

Xvfb gives SDL one display only (neither a second ``-screen`` nor ``+xinerama`` shows up as a second SDL display),
so the projectors' displays are emulated as desktop positions side by side on the one virtual screen
(``position=X:Y+X:Y``), as the one-projector live tests place their window with ``position=X:Y``."""

from __future__ import annotations

import time

import numpy as np
import pytest

from procam.addon.capture.combine import combine_projector_sets
from procam.addon.capture.devices import OneProjector
from procam.addon.capture.format import CaptureSet, CaptureSetWriter, DepthInfo
from procam.addon.cli.app import main
from procam.addon.errors import Cancelled, CaptureError, LiveError
from procam.addon.live.device import LiveDevice
from procam.addon.live.loopback import LoopbackCamera, LoopbackRig
from procam.addon.rig.model import Camera, Projector, intrinsics_from_fov, projector_intrinsics_from_throw
from procam.addon.steps.live import LiveCaptureOptions, run_live_capture

ORIGIN = (40, 30)


def _projector(size: tuple[int, int]) -> Projector:
    return Projector(projector_intrinsics_from_throw(size[0], size[1], 1.25))


def _grab(region: tuple[int, int, int, int]) -> np.ndarray:
    import mss
    with mss.MSS() as screen:
        left, top, w, h = region
        return np.asarray(screen.grab({"left": left, "top": top, "width": w, "height": h}))[..., 2::-1]


def _flat(size: tuple[int, int], rgb: tuple[float, float, float]) -> np.ndarray:
    return np.broadcast_to(np.asarray(rgb, np.float32), (size[1], size[0], 3)).copy()


def test_two_windows_of_their_own_sizes_are_shown_and_captured_at_once(xvfb):
    sizes = [(160, 120), (128, 96)]
    second = (ORIGIN[0] + sizes[0][0] + 16, ORIGIN[1])  # 16 px of bare (black) screen between the two
    span = (ORIGIN[0], ORIGIN[1], second[0] + sizes[1][0] - ORIGIN[0], sizes[0][1])
    # The camera films both windows 1:1 (no surface warp), a network camera with 0.1 s latency.
    loop = LoopbackRig(span, span[2:], delay_s=0.1)
    p1, p2 = _projector(sizes[0]), _projector(sizes[1])
    with LoopbackCamera(loop) as cam:
        spec = f"live:camera={cam.url},position={ORIGIN[0]}:{ORIGIN[1]}+{second[0]}:{second[1]},encoding=linear"
        with LiveDevice(spec, p1, others=(p2,)) as device:
            assert [w.size for w in device.windows] == sizes
            assert [w.position for w in device.windows] == [ORIGIN, second]
            # every projector was lit in its own latency measurement, and the wait covers the camera's delay
            assert len(device.report.latencies_s) == 3 and device.report.latency_s >= 0.1
            a, b = _flat(sizes[0], (0.8, 0.3, 0.1)), _flat(sizes[1], (0.2, 0.5, 0.9))
            device.project_all([a, b])
            time.sleep(0.05)
            screen = _grab((*ORIGIN, span[2], span[3]))
            np.testing.assert_array_equal(screen[:120, :160], np.rint(a * 255).astype(np.uint8))
            np.testing.assert_array_equal(screen[:96, 176:], np.rint(b * 255).astype(np.uint8))
            # Alternating levels on the two windows: each capture holds both frames of its own call, none of the
            # previous one (the capture waits for the last flip plus the latency).
            levels = [(0.9, 0.1), (0.2, 0.8), (0.7, 0.3), (0.1, 0.6), (0.5, 0.95)]
            for one, two in levels:
                shot = device.project_all([_flat(sizes[0], (one,) * 3), _flat(sizes[1], (two,) * 3)])
                assert shot.shape == (span[3], span[2], 3)
                seen1 = float(shot[10:110, 10:150].mean())
                seen2 = float(shot[10:86, 186:298].mean())
                assert abs(seen1 - one) < 0.03 and abs(seen2 - two) < 0.03, (one, two, seen1, seen2)
                assert float(shot[100:, 186:].max()) < 0.05  # below the smaller window: bare screen
            off = device.capture_off()
            assert float(off.max()) < 0.05
            with pytest.raises(LiveError, match="shows 2 projectors: give each its frame with project_all"):
                device.project(a)
            with pytest.raises(CaptureError, match="projector 2.s frame must be 128×96"):
                device.project_all([a, a])
            # One projector of the two, the other black: what a projector's own sequence is captured with.
            shot = OneProjector(device, 1).project(_flat(sizes[1], (0.9,) * 3))
            assert float(shot[10:110, 10:150].max()) < 0.05 and float(shot[10:86, 186:298].mean()) > 0.85
    time.sleep(0.1)
    assert _grab((*ORIGIN, span[2], span[3])).max() == 0  # both windows given back


def test_live_capture_of_two_projectors_writes_one_capture_set(xvfb, tmp_path, capsys):
    size = (96, 72)
    second = (ORIGIN[0] + size[0] + 8, ORIGIN[1])
    span = (ORIGIN[0], ORIGIN[1], second[0] + size[0] - ORIGIN[0], size[1])
    loop = LoopbackRig(span, span[2:], offset=0.02)
    projector = _projector(size)
    with LoopbackCamera(loop) as cam:
        one = f"live:camera={cam.url},position={ORIGIN[0]}:{ORIGIN[1]},encoding=linear"
        device = one.replace(",encoding", f"+{second[0]}:{second[1]},encoding")
        args = ["--projector-width", str(size[0]), "--projector-height", str(size[1]), "--throw-ratio", "1.25",
                "--no-validation", "--camera-fov", "58", "--out", str(tmp_path / "set"), "--projectors", "2"]
        # Fewer displays than projectors: refused before anything is written.
        assert main(["capture", "--device", one, *args]) == 2
        assert "rig has 2 projectors but the live device names 1 display" in capsys.readouterr().err
        assert not (tmp_path / "set.session").exists() and not (tmp_path / "set").exists()

        options = LiveCaptureOptions(device, projector, tmp_path / "set", validation=False, camera_fov=58.0,
                                     others=(projector,))
        calls: list[str] = []
        with pytest.raises(Cancelled, match=r"of \d+ frames are captured and kept"):
            run_live_capture(options, cancel=lambda: len(calls) > 40,
                             progress=lambda m, f: calls.append(m) if m.startswith("capturing") else None)
        assert any(m.startswith("capturing projector 2's frame") for m in calls)  # stopped inside projector 2's
        kept = [len(list((tmp_path / "set.session" / d).glob("*.png"))) for d in ("photos", "photos_p2")]
        assert kept[0] > 0 and kept[1] > 0 and sum(kept) == 41
        # the session of two projectors is not resumed as one of one
        assert main(["capture", "--device", one, *args[:-2]]) == 2
        assert "other settings (projectors" in capsys.readouterr().err
        assert main(["capture", "--device", device, *args]) == 0
        out = capsys.readouterr()
        assert "resuming the live session" in out.err and "of 2 projectors" in out.out
    assert not (tmp_path / "set.session").exists()
    captures = CaptureSet.load(tmp_path / "set")
    assert len(captures.projectors) == 2 and len(captures.entries_of("surface")) == 1
    left, right = (slice(4, 68), slice(4, 92)), (slice(4, 68), slice(size[0] + 12, size[0] + 100))
    for k in range(2):
        view = captures.for_projector(k)
        assert len(view.entries_of("surface")) == 1
        for kind in ("white", "black"):
            assert np.all(view.pattern(kind) == (1.0 if kind == "white" else 0.0))
        mine, other = (left, right) if k == 0 else (right, left)
        white = view.image("white")
        assert float(white[mine].mean()) > 0.9 and float(white[other].max()) < 0.1, k
        checker = view.entries_of("checker")[0]
        pattern = view.pattern("checker", **checker.params)
        seen = view.image("checker", **checker.params)[mine]
        # the capture is the pattern, 1:1 (the camera films the window), plus the stray light
        np.testing.assert_allclose(seen[..., 0], pattern[4:68, 4:92, 0] + 0.02, atol=0.06)


def _one_projector_set(path, camera, projector, *, depth: float | None = None, level: float = 0.5) -> CaptureSet:
    w, h = projector.intrinsics.size
    info = DepthInfo(camera.intrinsics, camera.intrinsics.size) if depth is not None else None
    with CaptureSetWriter(path, camera, projector, depth_info=info) as writer:
        cw, ch = camera.intrinsics.size
        writer.add("surface", np.full((ch, cw, 3), 0.1, np.float32), projector="off")
        writer.add("white", np.full((ch, cw, 3), level, np.float32), frame=np.ones((h, w, 3), np.float32))
        if depth is not None:
            writer.add_depth(np.full((ch, cw), depth, np.float32))
    return CaptureSet.load(path)


def test_combining_one_set_per_projector(tmp_path):
    camera = Camera(intrinsics_from_fov(64, 48, 60.0))
    p1, p2 = _projector((40, 30)), _projector((32, 24))
    a = _one_projector_set(tmp_path / "a", camera, p1, depth=1.5, level=0.4)
    b = _one_projector_set(tmp_path / "b", camera, p2, depth=2.5, level=0.7)
    both = combine_projector_sets([a, b], tmp_path / "both")
    assert [p.intrinsics.size for p in both.projectors] == [(40, 30), (32, 24)]
    # the surface photo and the depth once, from projector 1's set; each projector's own white
    assert len(both.entries_of("surface")) == 1 and len(both.entries_of("depth")) == 1
    assert float(both.depth().mean()) == pytest.approx(1.5)
    assert [float(both.for_projector(k).image("white").mean()) for k in range(2)] == pytest.approx([0.4, 0.7],
                                                                                                   abs=1e-3)
    assert both.for_projector(1).pattern("white").shape == (24, 32, 3)
    other = _one_projector_set(tmp_path / "c", Camera(intrinsics_from_fov(80, 60, 60.0)), p2)
    with pytest.raises(CaptureError, match="projector 2's captures .* another camera"):
        combine_projector_sets([a, other], tmp_path / "bad")
    with pytest.raises(CaptureError, match="already holds 2 projectors"):
        combine_projector_sets([both, b], tmp_path / "bad")
    assert not (tmp_path / "bad").exists()
