"""Devices of photographs taken by a command: ``live:…,shoot='…{out}'`` (the projector window, then a command
photographs it) and ``command:run='…{frame}…{out}'`` (a command shows and photographs), with commands that are small
Python scripts, the lab rendering each frame in a process of its own, and a screen grab of the window on Xvfb."""

from __future__ import annotations

import json
import shlex
import struct
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from procam.addon.capture.command import CommandDevice, CommandSpec, PhotoCommand, exif_exposure
from procam.addon.capture.devices import ShownTogether
from procam.addon.cli.app import main
from procam.addon.errors import CaptureError, LiveError
from procam.addon.live.device import LiveSpec
from procam.addon.live.shoot import ShootDevice, open_camera_device
from procam.addon.rig.model import Projector, projector_intrinsics_from_throw
from procam.addon.steps.stage_c import device_kind

PY = shlex.quote(sys.executable)
#: A camera that photographs the frame exactly (its photograph is the 16-bit frame file, copied).
COPY = f"{PY} -c 'import shutil, sys; shutil.copyfile(sys.argv[1], sys.argv[2])' {{frame}} {{out}}"


def _projector(size=(64, 48)) -> Projector:
    return Projector(projector_intrinsics_from_throw(size[0], size[1], 1.25))


def _script(tmp_path: Path, name: str, body: str) -> str:
    path = tmp_path / name
    path.write_text(body)
    return f"{PY} {shlex.quote(str(path))}"


# -- specs ---------------------------------------------------------------------------------------------------------

def test_specs_are_parsed_and_refused_before_anything_opens():
    quoted = LiveSpec.parse("live:display=1,shoot='gphoto2 --capture-image-and-download --filename {out}'")
    assert quoted.shoot == ("gphoto2", "--capture-image-and-download", "--filename", "{out}")
    assert quoted.camera is None and quoted.encoding == "auto" and quoted.display == 1
    # the shell took the quotes off: the command runs on to the next key, commas and all
    bare = LiveSpec.parse("live:position=5:6,shoot=tool --a,b {out},latency=0.1,suffix=png")
    assert bare.shoot == ("tool", "--a,b", "{out}") and bare.latency == 0.1 and bare.suffix == "png"
    assert LiveSpec.parse("live:camera=0,display=1").shoot == ()  # a streaming camera as before
    for bad, why in [("live:display=1,shoot='gphoto2 --capture-image'", r"must name \{out\}"),
                     ("live:camera=0,display=1,shoot='x {out}'", "not both"),
                     ("live:display=1,shoot='x {out}',noise=0.01", "average=N"),
                     ("live:camera=0,display=1,timeout=3", "shooting command's"),
                     ("live:display=1,shoot='x {out}", "not closed"),
                     ("live:display=1,shoot=x {out},suffix=raw", "suffix must be")]:
        with pytest.raises(LiveError, match=why):
            LiveSpec.parse(bad)
    spec = CommandSpec.parse("command:run='tool show {frame} --photo {out}',timeout=5,average=2")
    assert spec.argv == ("tool", "show", "{frame}", "--photo", "{out}") and spec.timeout == 5 and spec.average == 2
    for bad, why in [("command:timeout=5", "which command"), ("command:run='tool {out}'", r"\{frame\}"),
                     ("command:run='tool {frame}'", r"\{out\}"), ("command:run='t {frame} {out}',average=0", "1 …")]:
        with pytest.raises(CaptureError, match=why):
            CommandSpec.parse(bad)
    with pytest.raises(CaptureError, match=r"missing \{frame2\}"):
        spec.check_projectors(2)
    assert device_kind("command:run='t {frame} {out}'") == "command"
    assert device_kind("live:display=0,shoot='t {out}'") == "live"
    with pytest.raises(CaptureError, match="shoot="):
        device_kind("camera:0")
    # A rig of two projectors with one window is refused before any window opens (no display here).
    with pytest.raises(LiveError, match="2 projectors"):
        open_camera_device("live:position=0:0,shoot='t {out}'", _projector(), others=[_projector()])


# -- the command ---------------------------------------------------------------------------------------------------

def test_command_failures_are_clear(tmp_path):
    def take(line: str, **kwargs) -> np.ndarray:
        command = PhotoCommand(shlex.split(line), **kwargs)
        try:
            return command.take()
        finally:
            command.close()
            assert not command.folder.exists()  # close() removes the private folder

    with pytest.raises(CaptureError, match="'no-such-camera-tool' was not found"):
        take("no-such-camera-tool {out}")
    fails = _script(tmp_path, "fails.py", "import sys\nsys.stderr.write('*** no camera found on usb\\n')\nsys.exit(3)")
    with pytest.raises(CaptureError, match=r"exit status 3.*no camera found on usb"):
        take(f"{fails} {{out}}")
    with pytest.raises(CaptureError, match=r"wrote no photograph to .*shot-00000\.jpg"):
        take(f"{PY} -c pass {{out}}")
    with pytest.raises(CaptureError, match="cannot be read"):
        take(f"{PY} -c 'import sys; open(sys.argv[1], \"w\").write(\"not a photo\")' {{out}}")
    with pytest.raises(CaptureError, match=r"more than 0.5 s"):
        take(f"{PY} -c 'import time; time.sleep(5)' {{out}}", timeout=0.5)


def test_no_shell_sees_the_command_and_a_tool_may_add_its_own_suffix(tmp_path):
    marker = tmp_path / "injected"
    # Written as a shell would run it, `$(touch …)` and `;` would run; split into arguments they are text.
    writer = _script(tmp_path, "writer.py", "import sys, numpy as np, cv2\n"
                     "assert sys.argv[1].startswith('$(touch') and sys.argv[2] == ';'\n"
                     "cv2.imwrite(sys.argv[3][:-4] + '.png', np.full((4, 6, 3), 51, np.uint8))\n")
    command = PhotoCommand(shlex.split(f"{writer} '$(touch {marker})' ';' {{out}}"))
    try:
        photo = command.take()  # the tool wrote shot-00000.png for {out} = shot-00000.jpg
    finally:
        command.close()
    assert not marker.exists()
    assert photo.shape == (4, 6, 3)
    np.testing.assert_allclose(photo, _srgb_decoded(51), atol=1e-6)  # an 8-bit file: sRGB, linearised


def _srgb_decoded(level: int) -> float:
    c = level / 255.0
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4


def _jpeg_with_exposure(path: Path, level: int, exposure: tuple[int, int]) -> None:
    """A JPEG whose EXIF block holds an exposure time, as cameras write it (IFD0 → Exif IFD → 0x829A)."""
    ok, data = cv2.imencode(".jpg", np.full((8, 8, 3), level, np.uint8))
    assert ok
    e = "<"
    ifd0 = struct.pack(e + "H", 1) + struct.pack(e + "HHII", 0x8769, 4, 1, 26) + struct.pack(e + "I", 0)
    exif_ifd = struct.pack(e + "H", 1) + struct.pack(e + "HHII", 0x829A, 5, 1, 44) + struct.pack(e + "I", 0)
    tiff = b"II*\x00" + struct.pack(e + "I", 8) + ifd0 + exif_ifd + struct.pack(e + "II", *exposure)
    app1 = b"Exif\x00\x00" + tiff
    raw = data.tobytes()
    path.write_bytes(raw[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + raw[2:])


def test_a_photograph_whose_exposure_changed_is_refused(tmp_path):
    for i, exposure in enumerate([(1, 60), (1, 60), (1, 30)]):
        _jpeg_with_exposure(tmp_path / f"{i}.jpg", 128, exposure)
    assert exif_exposure(tmp_path / "0.jpg") == {"exposure time": pytest.approx(1 / 60)}
    camera = _script(tmp_path, "camera.py", f"import shutil, sys\nshutil.copyfile('{tmp_path}/' + sys.argv[1] + "
                                            "'.jpg', sys.argv[2])\n")
    command = PhotoCommand(shlex.split(f"{camera} {{n}} {{out}}"))
    try:
        first = command.take()  # 8-bit JPEG: sRGB, linearised
        np.testing.assert_allclose(first, _srgb_decoded(128), atol=0.01)
        command.take()
        with pytest.raises(CaptureError, match=r"photograph 2 .*exposure time 0.0166667 → 0.0333333.*on auto"):
            command.take()
    finally:
        command.close()


# -- the command device ----------------------------------------------------------------------------------------------

def test_command_device_shows_and_photographs_and_checks_exposure(tmp_path):
    frame = np.random.default_rng(0).random((48, 64, 3)).astype(np.float32)
    with CommandDevice(f"command:run={COPY},suffix=png", _projector()) as device:
        assert device.camera_size == (64, 48)  # known from the photographs it took at open
        assert device.report.contrast == pytest.approx(1.0) and device.report.exposure_drift < 1e-6
        np.testing.assert_allclose(device.project(frame), frame, atol=0.5 / 65535)
        np.testing.assert_allclose(device.capture_off(), 0.0)
        folder = device._command.folder
    assert not folder.exists()
    # A camera on auto: every photograph brighter than the last (the shot's number scales it).
    auto = _script(tmp_path, "auto.py", "import sys, cv2\nimg = cv2.imread(sys.argv[1], cv2.IMREAD_UNCHANGED)\n"
                   "cv2.imwrite(sys.argv[3], (img * (0.5 + 0.2 * int(sys.argv[2]))).astype(img.dtype))\n")
    with pytest.raises(CaptureError, match="exposure is not locked"):
        CommandDevice(f"command:run={auto} {{frame}} {{n}} {{out}},suffix=png", _projector())
    blind = _script(tmp_path, "blind.py", "import sys, numpy as np, cv2\n"
                    "cv2.imwrite(sys.argv[1], np.full((48, 64, 3), 9000, np.uint16))\n")
    with pytest.raises(CaptureError, match="did not see the projector"):
        CommandDevice(f"command:run={blind} {{out}} {{frame}},suffix=png", _projector())


def test_closed_loop_through_the_command_device_matches_the_lab_device(lab_calibration, tmp_path):
    """The lab renders each frame in a process of its own behind ``command:``; the same closed loop through the lab
    device directly, evaluated the same way, scores the same (the shots' noise differs)."""
    from procam.addon.capture.targets import natural_target
    from procam.addon.imageio import write_image

    import shutil

    shared, _, truth = lab_calibration("vedge", scale=0.2, samples=4)
    cal = shutil.copytree(shared, tmp_path / "cal")  # its transport operator, once for both loops
    assert main(["precompute", str(cal)]) == 0
    target = str(write_image(tmp_path / "city.png", natural_target("city", (120, 90))))
    shoot = shlex.join([sys.executable, "-m", "procam.addon.lab.shoot", "--truth", str(truth), "--frame", "{frame}",
                        "--out", "{out}", "--shot", "{n}"])
    scores = {}
    for label, device in (("lab", f"lab:{truth}"), ("command", f"command:run={shoot},suffix=png")):
        assert main(["compensate", str(cal), target, "--device", device, "--iterations", "16",
                     "--out", str(tmp_path / label)]) == 0
        assert main(["evaluate", str(cal), "--inputs", str(tmp_path / label), "--targets", target,
                     "--device", f"lab:{truth}", "--out", str(tmp_path / f"eval-{label}")]) == 0
        scores[label] = json.loads((tmp_path / f"eval-{label}" / "metrics.json").read_text())["targets"][0]
    assert scores["lab"]["psnr"] > scores["lab"]["uncompensated"]["psnr"] + 5
    assert abs(scores["command"]["psnr"] - scores["lab"]["psnr"]) < 0.2, scores


# -- the projector window and a shooting command, on a virtual X server -------------------------------------------

def test_shooting_command_photographs_the_window_after_it_shows_through_the_lab(xvfb, lab_set, tmp_path):
    """The command grabs the window's screen area and renders it through the lab: each photograph is the lab's
    render of the frame the window showed when the command ran, shot for shot, never the previous frame."""
    from procam.addon.lab.cycles_device import LabDevice
    from procam.addon.lab.truth import LabTruth

    _, truth_path = lab_set("vedge", scale=0.2, samples=4)
    truth = LabTruth.load(truth_path)
    origin = (30, 20)
    shoot = shlex.join([sys.executable, "-m", "procam.addon.lab.shoot", "--truth", str(truth_path), "--grab",
                        f"{origin[0]}:{origin[1]}", "--out", "{out}", "--shot", "{n}"])
    w, h = truth.rig.projector.intrinsics.size
    rng = np.random.default_rng(2)
    frames = [np.rint(rng.random((h, w, 3)) * 255).astype(np.float32) / 255 for _ in range(2)]
    spec = f"live:position={origin[0]}:{origin[1]},shoot={shoot},suffix=png,latency=0.3"
    with ShootDevice(spec, truth.rig.projector) as device:
        assert device.report.latency_s == 0.3
        t0 = time.perf_counter()
        shots = [device.project(f) for f in frames]
        assert time.perf_counter() - t0 >= 2 * 0.3  # the settle time is waited out before each shot
    with LabDevice(truth, first_shot=3) as lab:  # the device took black, white, white at open: shots 0–2
        expected = [lab.project(f) for f in frames]
    for shot, want, other in zip(shots, expected, expected[::-1]):
        np.testing.assert_allclose(shot, want, atol=1.0 / 65535)
        assert np.abs(shot - other).mean() > 0.02


def test_a_live_capture_session_with_a_shooting_command_resumes(xvfb, tmp_path):
    """``procam capture``'s resumable session with ``shoot=``: interrupted, resumed, imported."""
    from procam.addon.errors import Cancelled
    from procam.addon.steps.live import LiveCaptureOptions, run_live_capture

    origin, size = (40, 30), (96, 72)
    grab = _script(tmp_path, "grab.py", "import sys, mss, numpy as np, cv2\n"
                   f"with mss.MSS() as s:\n    g = np.asarray(s.grab({{'left': {origin[0]}, 'top': {origin[1]}, "
                   f"'width': {size[0]}, 'height': {size[1]}}}))\n"
                   "cv2.imwrite(sys.argv[1], (g[..., :3].astype(np.uint16) * 257 * 0.8 + 800).astype(np.uint16))\n")
    options = LiveCaptureOptions(f"live:position={origin[0]}:{origin[1]},shoot={grab} {{out}},suffix=png,latency=0",
                                 _projector(size), tmp_path / "set", validation=False, camera_fov=58.0)
    calls: list[str] = []
    with pytest.raises(Cancelled, match="6 of"):
        run_live_capture(options, cancel=lambda: len(calls) > 5,
                         progress=lambda m, f: calls.append(m) if m.startswith("capturing") else None)
    said: list[str] = []
    captures = run_live_capture(options, progress=lambda m, f: said.append(m))
    assert any("6 of" in m and "already captured" in m for m in said)
    assert captures.camera.intrinsics.size == size and "exposure" in captures.notes
    np.testing.assert_allclose(captures.image("white").mean(), 0.8 + 800 / 65535, atol=2e-3)


def test_a_device_photographing_projectors_together_keeps_its_size_and_wants_every_frame():
    class Rig(ShownTogether):
        error, what = LiveError, "this rig"

        def __init__(self, sizes: list[tuple[int, int]]) -> None:
            proj = Projector(projector_intrinsics_from_throw(16, 12, 1.5), np.eye(4))
            self.projector, self.others, self.sizes, self.shown = proj, (proj,), sizes, []

        def _capture(self, frames):
            self.shown.append([float(f.mean()) for f in frames])
            w, h = self.sizes.pop(0)
            return self._same_size(np.zeros((h, w, 3), np.float32), len(self.shown))

    rig = Rig([(8, 6), (8, 6), (9, 6)])
    assert rig.camera_size is None
    rig.capture_off()
    assert rig.camera_size == (8, 6) and rig.shown == [[0.0, 0.0]]
    with pytest.raises(LiveError, match="this rig shows 2 projectors: give each its frame with project_all"):
        rig.project(np.zeros((12, 16, 3), np.float32))
    rig.project_all([np.ones((12, 16, 3), np.float32), np.zeros((12, 16, 3), np.float32)])
    assert rig.shown[-1] == [1.0, 0.0]
    with pytest.raises(LiveError, match="photograph 3 is 9×6, the first was 8×6: keep the camera's image size"):
        rig._capture(rig._flat(0.5, lit=1))
    assert rig.shown[-1] == [0.0, 0.5]
