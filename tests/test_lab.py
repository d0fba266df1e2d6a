"""The virtual lab end to end: each effect's signature in rendered captures, seeds, the sealed truth,
``procam lab`` on good and bad input, and the Run Virtual Lab operator on a user's scene.

Renders are small (camera 160×120, projector 200×150, 8 spp) so the whole file runs in about a minute on 2 cores.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from procam.addon.capture.format import CaptureSet  # noqa: E402
from procam.addon.capture.others_black import BLACK_TOLERANCE, check_others_black  # noqa: E402
from procam.addon.capture.patterns import checkerboard  # noqa: E402
from procam.addon.cli.app import main  # noqa: E402
from procam.addon.errors import CaptureError, LabError, RenderError  # noqa: E402
from procam.addon.lab.effects import distort_points, parse_effects  # noqa: E402
from procam.addon.lab.truth import LabTruth, lab_depth, make_truth  # noqa: E402
from procam.addon.lab.cycles_device import LAB_SCENE_NAME, LabDevice  # noqa: E402
from procam.addon.lab.lab import run_lab  # noqa: E402
from procam.addon.blender import rig as blender_rig  # noqa: E402

pytestmark = pytest.mark.blender

CAMERA, PROJECTOR, SAMPLES = (160, 120), (200, 150), 8
FRAME_NAMES = ("black", "white", "grey", "red", "checker", "half")


@pytest.fixture(scope="module")
def base() -> LabTruth:
    """A vedge lab (concave vertical corner) with no effects."""
    return make_truth("vedge", seed=3, samples=SAMPLES, camera_size=CAMERA, projector_size=PROJECTOR)


@pytest.fixture(scope="module")
def frames(base) -> dict[str, np.ndarray]:
    proj = base.rig.projector
    w, h = proj.input_size

    def place(img) -> np.ndarray:
        return proj.frame_from_input(np.asarray(img, dtype=np.float32))

    half = np.zeros((h, w, 3))
    half[:, : int(0.35 * w)] = 1.0  # lights only the left face of the corner
    return {"black": place(np.zeros((h, w, 3))), "white": place(np.ones((h, w, 3))),
            "grey": place(np.full((h, w, 3), 0.5)), "red": place(np.tile([1.0, 0.0, 0.0], (h, w, 1))),
            "checker": place(checkerboard((w, h), 15)), "half": place(half)}


@pytest.fixture(scope="module")
def shoot(base, frames):
    """Captures of every test frame (same order, so the same per-shot seeds) for an effects spec; cached."""
    cache: dict[str, dict[str, np.ndarray]] = {}

    def run(spec: str) -> dict[str, np.ndarray]:
        if spec not in cache:
            with LabDevice(replace(base, effects=parse_effects(spec))) as device:
                cache[spec] = {name: device.project(frames[name]) for name in FRAME_NAMES}
        return cache[spec]

    return run


@pytest.fixture(scope="module")
def lit(shoot) -> np.ndarray:
    """Camera pixels the white frame lights (effects off)."""
    return shoot("")["white"].mean(axis=2) > 0.05


def _footprint_corners(mask: np.ndarray, n: int = 10) -> np.ndarray:
    """Top-left, top-right, bottom-right, bottom-left corners of a lit quadrilateral (pixel centres)."""
    v, u = np.nonzero(mask)
    u, v = u + 0.5, v + 0.5
    out = []
    for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        idx = np.argsort(-(su * u + sv * v))[:n]
        out.append([u[idx].mean(), v[idx].mean()])
    return np.array(out)


def _same(a: np.ndarray, b: np.ndarray, tol: float = 1e-6) -> bool:
    return float(np.abs(a - b).max()) <= tol


# --------------------------------------------------------------------------- effects in the rendered captures


def test_no_effect_gives_clean_captures(shoot, lit):
    off = shoot("")
    assert off["black"].max() == 0.0  # a dark room: nothing but the projector lights it
    assert 0.2 < lit.mean() < 0.8
    assert off["red"][..., 1:].max() == 0.0  # Lambertian + no crosstalk: red light stays red


def test_response_moves_mid_greys_not_black_and_white(shoot, lit):
    on, off = shoot("response=1"), shoot("")
    assert _same(on["black"], off["black"]) and _same(on["white"], off["white"])
    ratio = np.median(on["grey"][lit] / off["grey"][lit])
    gamma = parse_effects("response=1")["response"]["gamma"]
    assert ratio == pytest.approx(0.5 ** (gamma - 1.0), abs=0.03)  # out = in^γ on the emitted light


def test_crosstalk_leaks_red_into_green_and_blue(shoot, lit):
    on, off = shoot("crosstalk=1"), shoot("")
    r, g, b = on["red"][lit].mean(axis=0)
    assert g > 0.05 * r and b > 0.05 * r
    assert off["red"][lit][:, 1:].max() == 0.0
    assert _same(on["white"], off["white"], 1e-4)  # rows sum to 1: white stays white


def test_black_level_lifts_black_everywhere(shoot, lit):
    on, off = shoot("black_level=1"), shoot("")
    assert off["black"].max() == 0.0
    assert on["black"].min() > 0.02  # ambient light reaches every pixel
    assert on["black"][lit].mean() > on["black"][~lit].mean() + 0.003  # plus the projector's leak where it shines


def test_vignetting_darkens_the_footprint_corners_not_its_centre(shoot, lit):
    on, off = shoot("vignetting=1"), shoot("")
    ratio = np.where(lit, on["white"].mean(axis=2) / np.maximum(off["white"].mean(axis=2), 1e-6), np.nan)

    def around(u: float, v: float) -> float:
        return float(np.nanmean(ratio[int(v) - 3:int(v) + 3, int(u) - 3:int(u) + 3]))

    cv, cu = np.argwhere(lit).mean(axis=0)
    centre = around(cu + 0.5, cv + 0.5)
    corners = [around(u, v) for u, v in _footprint_corners(lit)]
    assert centre > 0.95
    assert max(corners) < centre - 0.08
    assert min(corners) < 0.8


def test_defocus_widens_checker_edges(shoot, lit):
    def mid_share(caps: dict[str, np.ndarray]) -> float:
        q = caps["checker"].mean(axis=2)[lit] / np.maximum(caps["white"].mean(axis=2)[lit], 1e-6)
        return float(np.mean((q > 0.2) & (q < 0.8)))  # pixels on a blurred edge, between black and white

    sharp, blurred = mid_share(shoot("")), mid_share(shoot("defocus=1,defocus.sigma=8"))
    assert blurred > 3 * sharp and blurred > 0.15


def test_interreflection_lights_the_unlit_face_of_the_corner(shoot, lit):
    on, off = shoot("interreflection=1"), shoot("")
    cols = np.arange(CAMERA[0])[None, :]
    unlit_face = lit & (off["half"].max(axis=2) == 0.0) & (cols > 0.62 * CAMERA[0])
    assert unlit_face.sum() > 500
    assert off["half"][unlit_face].max() == 0.0  # direct light only: the right face stays black
    assert on["half"][unlit_face].mean() > 2e-3  # light bounced over from the lit left face
    assert _same(on["black"], off["black"])
    # strength 0.25: one bounce, half of the indirect light kept (direct + gain·indirect)
    half_gain, full_gain = shoot("interreflection=0.25"), shoot("interreflection=0.25,interreflection.gain=1")
    ratio = half_gain["half"][unlit_face].mean() / full_gain["half"][unlit_face].mean()
    assert ratio == pytest.approx(parse_effects("interreflection=0.25")["interreflection"]["gain"], abs=0.1)
    lit_face = off["half"].mean(axis=2) > 0.05
    np.testing.assert_allclose(half_gain["half"][lit_face].mean(), off["half"][lit_face].mean(), rtol=0.05)


def test_glossy_changes_the_image_not_as_a_gain(shoot, lit):
    on, off = shoot("glossy=1"), shoot("")
    ratio = on["white"].mean(axis=2)[lit] / np.maximum(off["white"].mean(axis=2)[lit], 1e-6)
    assert np.abs(on["white"] - off["white"])[lit].mean() > 0.01
    assert ratio.std() > 0.1  # view-dependent highlights, not a uniform scale of the diffuse image
    assert _same(on["black"], off["black"])


def test_camera_response_changes_white_balance(shoot, lit):
    spec = "camera_response=1,camera_response.curve=0"  # white balance alone
    on, off = shoot(spec), shoot("")
    e = parse_effects(spec)["camera_response"]
    ok = lit & (on["white"].max(axis=2) < 0.99)
    gains = np.median(on["white"][ok] / np.maximum(off["white"][ok], 1e-6), axis=0)
    np.testing.assert_allclose(gains, [e["gain_r"], 1.0, e["gain_b"]], atol=0.01)
    with_curve = shoot("camera_response=1")
    assert np.median(with_curve["grey"][lit] / off["grey"][lit]) > 1.2  # the tone curve lifts mid-greys


def test_distortion_moves_features_radially(shoot, lit, base):
    spec = "distortion=1,distortion.k1=-0.3,distortion.k2=0"
    on = shoot(spec)
    lit_on = on["white"].mean(axis=2) > 0.05
    before, after = _footprint_corners(lit), _footprint_corners(lit_on)
    k = base.rig.camera.intrinsics
    predicted = distort_points(before, k, parse_effects(spec))
    centre = np.array([k.cx, k.cy])
    moved_in = np.linalg.norm(before - centre, axis=1) - np.linalg.norm(after - centre, axis=1)
    assert np.all(moved_in > 1.5)  # barrel distortion pulls the corners towards the centre
    np.testing.assert_allclose(after, predicted, atol=1.2)
    assert lit_on.sum() < lit.sum()


def test_noise_has_the_configured_std(shoot, lit):
    on, off = shoot("noise=1"), shoot("")
    e = parse_effects("noise=1")["noise"]
    diff = (on["white"] - off["white"])[lit]
    expected = np.sqrt(np.mean(e["gain"] * off["white"][lit] + e["sigma"] ** 2))
    assert diff.std() == pytest.approx(expected, rel=0.15)
    assert abs(diff.mean()) < 0.2 * expected


def test_depth_noise_changes_depth_only(shoot, base):
    spec = "depth_noise=1"
    clean, _ = lab_depth(base)
    noisy, info = lab_depth(replace(base, effects=parse_effects(spec)))
    assert info.native_size[0] < CAMERA[0]  # sensed at low resolution, then upsampled
    both = np.isfinite(clean) & np.isfinite(noisy)
    d = (noisy - clean)[both]
    assert np.median(d) == pytest.approx(parse_effects(spec)["depth_noise"]["bias"], abs=0.005)
    assert d.std() > 0.01
    assert all(_same(a, b, 0.0) for a, b in zip(shoot(spec).values(), shoot("").values()))


# --------------------------------------------------------------------------- seeds, cleanup, truth


def test_same_seed_same_captures_other_seed_other_noise(base, frames):
    truth = replace(base, effects=parse_effects("realistic"))
    shots = []
    for seed in (None, None, 11):
        with LabDevice(truth, seed=seed) as device:
            shots.append([device.project(frames["grey"]), device.capture_off()])
    assert all(np.array_equal(a, b) for a, b in zip(shots[0], shots[1]))
    assert not np.array_equal(shots[0][0], shots[2][0])
    # and the depth does not depend on how many frames were shot before it
    np.testing.assert_array_equal(lab_depth(truth)[0], lab_depth(truth)[0])


def test_a_truth_without_an_effect_switches_it_off_everywhere_and_keeps_the_rest(base):
    """``LabTruth.without``: the effect off in the shared effects and in every projector's own, the others and the
    truth it came from as they were."""
    truth = replace(base, effects=parse_effects("realistic"),
                    projector_effects={0: parse_effects("defocus=0.5,response=0.6")})
    off = truth.without("defocus", "noise")
    assert not off.effects["noise"].active and not off.effects["defocus"].active
    assert not off.effects_of(0)["defocus"].active
    assert off.effects_of(0)["response"].strength == truth.effects_of(0)["response"].strength == 0.6
    assert off.effects["distortion"] == truth.effects["distortion"] and off.rig is truth.rig
    assert truth.effects_of(0)["defocus"].active and truth.effects["noise"].active


def test_repeated_draws_capture_a_frame_shown_twice_alike(base, frames):
    """``repeat_draws``: every shot draws the first one's samples and sensor noise, so the same frame gives the same
    capture (the flicker benchmark's camera without noise of its own); a device without it draws afresh."""
    truth = replace(base, effects=parse_effects("realistic"))
    with LabDevice(truth, repeat_draws=True) as device:
        first, again = device.project(frames["grey"]), device.project(frames["grey"])
        assert device.shots == 2
    np.testing.assert_array_equal(first, again)
    with LabDevice(truth) as device:
        assert not np.array_equal(device.project(frames["grey"]), device.project(frames["grey"]))


def test_device_renders_in_its_own_scene_and_cleans_up(base, frames):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    user = bpy.context.scene
    bpy.ops.mesh.primitive_cube_add()
    names = {c: sorted(b.name for b in getattr(bpy.data, c)) for c in ("scenes", "objects", "meshes", "materials",
                                                                     "images", "lights", "cameras", "worlds")}
    device = LabDevice(replace(base, effects=parse_effects("glossy=0.5")))
    assert LAB_SCENE_NAME in bpy.data.scenes and bpy.context.scene == user
    device.project(frames["white"])
    device.close()
    device.close()  # twice is harmless
    assert {c: sorted(b.name for b in getattr(bpy.data, c)) for c in names} == names
    with pytest.raises(LabError, match="closed"):
        device.project(frames["white"])


def test_truth_round_trip_reopens_the_same_lab(base, tmp_path, frames):
    truth = replace(base, effects=parse_effects("realistic"))
    run_lab(truth, tmp_path / "set", truth_path=tmp_path / "truth.json", graycode=False, validation=False)
    files = {p.relative_to(tmp_path / "set").as_posix() for p in (tmp_path / "set").rglob("*")}
    assert not any("truth" in f for f in files)
    loaded = LabTruth.load(tmp_path / "truth.json")
    assert loaded.effects == truth.effects and loaded.seed == truth.seed
    np.testing.assert_array_equal(loaded.rig.projector.camera_from_projector, truth.rig.projector.camera_from_projector)
    cs = CaptureSet.load(tmp_path / "set")
    assert cs.projector.camera_from_projector.tolist() != truth.rig.projector.camera_from_projector.tolist()  # nominal
    with LabDevice(loaded) as again:
        # Shots in the session order (surface, black, white), so each gets the same per-shot seed.
        surface_off, _black, white = again.capture_off(), again.project(frames["black"]), again.project(frames["white"])
    np.testing.assert_array_equal(white, cs.image("white"))  # shot 3 of the session, re-rendered identically
    np.testing.assert_array_equal(surface_off, cs.image("surface"))


@pytest.mark.parametrize("truth_rel", ["set/truth.json", "set/sub/truth.json", "set"])
def test_run_lab_refuses_a_truth_inside_the_capture_set(base, tmp_path, truth_rel):
    with pytest.raises(LabError, match="outside the capture set"):
        run_lab(base, tmp_path / "set", truth_path=tmp_path / truth_rel)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- procam lab


def _tree(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha1(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


SMALL = ["--scale", "0.2", "--samples", "2", "--no-graycode"]


@pytest.fixture(scope="module")
def cli_set(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cli")
    assert main(["lab", "--surface", "plane", "--out", str(root / "set"), *SMALL]) == 0
    return root


def test_cli_writes_set_and_truth_and_reports_progress_on_stderr(cli_set, capsys):
    cs = CaptureSet.load(cli_set / "set")
    assert cs.camera.intrinsics.size == (128, 96)
    assert {e.kind for e in cs.entries} >= {"surface", "black", "white", "checker", "validation", "depth"}
    assert (cli_set / "set.truth.json").is_file() and (cli_set / "set.truth.surface.npz").is_file()
    assert sorted(p.name for p in cli_set.iterdir()) == ["set", "set.truth.json", "set.truth.surface.npz"]


@pytest.mark.parametrize("args, message", [
    (["--surface", "blob"], "unknown surface 'blob'"),
    (["--effects", "blurr=0.5"], "unknown effect 'blurr'"),
    (["--effects", "noise=2"], "strength of 'noise' must lie in [0, 1]"),
    (["--effects", "noise.sigma=9"], "noise.sigma must lie in"),
    (["--samples", "0"], "--samples must be a whole number ≥ 1, got 0"),
    (["--samples", "2.5"], "argument --samples: --samples takes a whole number, got '2.5'"),
    (["--scale", "9"], "--scale must be between 0.05 and 2, got 9.0"),
    (["--scale", "nan"], "--scale must be a finite number"),
    (["--projector-shift", "0,nan"], "expected two finite percentages"),
    (["--supersample", "0"], "supersampling must be a whole number from 1 to 4"),
    (["--camera-fov-error", "200"], "keep it in 1–170°"),
    (["--projectors", "9"], "--projectors must be a whole number between 1 and 8, got 9"),
    (["--projectors", "2", "--layout", "ring"], "--layout must be one of side-by-side, stacked, grid, got 'ring'"),
    (["--projectors", "2", "--overlap", "1"], "--overlap must be between 0 and 0.9, got 1.0"),
])
def test_cli_bad_input_fails_early_and_writes_nothing(tmp_path, capsys, args, message):
    code = main(["lab", "--out", str(tmp_path / "out" / "set"), *SMALL, *args])
    err = capsys.readouterr().err
    assert code == 2
    assert message in err, err
    assert list(tmp_path.iterdir()) == []


def test_cli_refuses_an_unwritable_output_folder(tmp_path, capsys):
    (tmp_path / "file").write_text("not a folder")
    code = main(["lab", "--out", str(tmp_path / "file" / "set"), *SMALL])
    assert code == 2 and "is a file, not a folder" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_cli_refuses_a_surface_out_of_view(tmp_path, capsys):
    mesh = tmp_path / "behind.obj"
    mesh.write_text("v -1 -1 -1.5\nv 1 -1 -1.5\nv 1 1 -1.5\nv -1 1 -1.5\nf 1 2 3\nf 1 3 4\n")
    code = main(["lab", "--surface", str(mesh), "--out", str(tmp_path / "set"), *SMALL])
    assert code == 2 and "covers only 0% of the camera view" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["behind.obj"]


def test_cli_never_overwrites_without_force_and_replaces_only_when_complete(cli_set, tmp_path, capsys, monkeypatch):
    import shutil

    for name in ("set", "set.truth.json", "set.truth.surface.npz"):
        src = cli_set / name
        (shutil.copytree if src.is_dir() else shutil.copy2)(src, tmp_path / name)
    before = {**_tree(tmp_path)}
    out = ["--out", str(tmp_path / "set")]

    assert main(["lab", *out, *SMALL]) == 2
    assert "already holds a capture set" in capsys.readouterr().err
    assert _tree(tmp_path) == before

    assert main(["lab", *out, "--truth", str(tmp_path / "other.json"), *SMALL]) == 2  # the set still protects itself
    assert _tree(tmp_path) == before

    calls = {"n": 0}
    project = LabDevice.project

    def failing(self, frame):
        calls["n"] += 1
        if calls["n"] == 4:
            raise RenderError("the renderer died half-way")
        return project(self, frame)

    monkeypatch.setattr(LabDevice, "project", failing)
    assert main(["lab", *out, *SMALL, "--force", "--seed", "5"]) == 2
    assert "half-way" in capsys.readouterr().err
    assert _tree(tmp_path) == before  # the old set and truth are intact, no half-written set
    assert sorted(p.name for p in tmp_path.iterdir()) == ["set", "set.truth.json", "set.truth.surface.npz"]

    monkeypatch.setattr(LabDevice, "project", project)
    assert main(["lab", *out, *SMALL, "--force", "--seed", "5"]) == 0
    after = _tree(tmp_path)
    assert after["set/capture.json"] != before["set/capture.json"]  # replaced (validation images follow the seed)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["set", "set.truth.json", "set.truth.surface.npz"]
    assert LabTruth.load(tmp_path / "set.truth.json").seed == 5


def test_cli_takes_a_user_mesh_file(tmp_path, capfd):
    mesh = tmp_path / "wall.obj"
    mesh.write_text("v -1.4 -1.1 1.5\nv 1.4 -1.1 1.5\nv 1.4 1.1 1.5\nv -1.4 1.1 1.5\n"
                    "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")
    out = tmp_path / "set"
    assert main(["lab", "--surface", str(mesh), "--out", str(out), *SMALL, "--effects", "noise=0.3"]) == 0
    streams = capfd.readouterr()  # file-descriptor level: Blender's own prints would show here
    assert "lab:" in streams.err and "lab:" not in streams.out and "Saved:" not in streams.out + streams.err
    assert streams.out.startswith("capture set:")
    cs = CaptureSet.load(out)
    white = cs.image("white")
    assert (white.mean(axis=2) > 0.1).mean() > 0.2  # the projector lights the user's wall
    truth = LabTruth.load(tmp_path / "set.truth.json")
    assert truth.surface_source == str(mesh.resolve()) and len(truth.surface.faces) == 2


# --------------------------------------------------------------------------- the operator


def _scene_state(scene) -> dict:
    return {"objects": {o.name: (o.type, [list(r) for r in o.matrix_world], blender_rig.role(o))
                        for o in scene.objects},
            "data": {c: len(getattr(bpy.data, c)) for c in ("scenes", "objects", "meshes", "materials", "images",
                                                             "lights", "cameras", "worlds")},
            "render": (scene.render.engine, scene.render.resolution_x, scene.render.resolution_y, scene.camera.name),
            "frame": blender_rig.projector_image(blender_rig.find_rig_objects(scene).projector).tobytes()}


def test_operator_runs_the_lab_on_the_scene_and_leaves_it_alone(registered, tmp_path):
    from procam.panels.captures import capture_set_status

    bpy.ops.procam.create_rig(camera_width=64, camera_height=48, projector_width=80, projector_height=60,
                              input_width=60, input_height=60, surface="vedge")
    scene = bpy.context.scene
    before = _scene_state(scene)
    out = tmp_path / "set"
    assert bpy.ops.procam.run_lab(out_dir=str(out), samples=2, graycode=False, effects="noise=0.5") == {"FINISHED"}
    assert _scene_state(scene) == before  # the lab rendered in a scratch scene and removed it
    assert LAB_SCENE_NAME not in bpy.data.scenes
    cs = CaptureSet.load(out)
    assert cs.camera.intrinsics.size == (64, 48) and cs.projector.intrinsics.size == (80, 60)
    truth = LabTruth.load(tmp_path / "set.truth.json")
    np.testing.assert_allclose(truth.rig.projector.camera_from_projector,
                               blender_rig.read_rig(scene).projector.camera_from_projector, atol=1e-9)
    assert "Blender object" in truth.surface_source
    assert scene.procam_capture_dir == str(out)
    icon, text = capture_set_status(scene.procam_capture_dir)
    assert icon == "CHECKMARK" and text.startswith(f"{len(cs.entries) - 2} images + depth + wall")

    # a second run onto the same set is refused without Replace; the scene and the set stay as they are
    files = _tree(out)
    with pytest.raises(RuntimeError, match="already holds a capture set"):
        bpy.ops.procam.run_lab(out_dir=str(out), samples=2, graycode=False)
    assert _scene_state(scene) == before and _tree(out) == files


def test_operator_reports_a_missing_surface(registered, tmp_path):
    from procam.panels.captures import capture_set_status

    bpy.ops.procam.create_rig(camera_width=64, camera_height=48, projector_width=80, projector_height=60)
    with pytest.raises(RuntimeError, match="no ProCam Surface"):
        bpy.ops.procam.run_lab(out_dir=str(tmp_path / "set"), samples=2, graycode=False)
    assert list(tmp_path.iterdir()) == [] and bpy.context.scene.procam_capture_dir == ""
    (tmp_path / "empty").mkdir()
    icon, text = capture_set_status(str(tmp_path / "empty"))
    assert icon == "ERROR" and "capture.json is missing" in text
    assert bpy.ops.procam.run_lab(out_dir=str(tmp_path / "set"), surface="plane", samples=2, graycode=False,
                                  use_scene_rig=False, scale=0.1) == {"FINISHED"}
    assert CaptureSet.load(tmp_path / "set").camera.intrinsics.size == (64, 48)


# --------------------------------------------------------------------------- effects the diagnosis does not model

def test_a_knocked_surface_moves_only_after_the_calibration_patterns(base, frames):
    moved = replace(base, effects=parse_effects("surface_moved=1"))
    with LabDevice(base) as plain:
        ref = plain.project(frames["checker"])
    with LabDevice(moved) as device:
        device.phase = "calibration"
        before = device.project(frames["checker"])
    with LabDevice(moved) as device:  # a fresh device: same shot number, so the same noise draw
        device.phase = "validation"
        after = device.project(frames["checker"])
    np.testing.assert_array_equal(before, ref)
    assert np.abs(after - ref).mean() > 0.002  # the edges of the checker land elsewhere


def test_a_room_lamp_lights_the_paint_unevenly_and_translucent_paint_spreads_light(shoot, lit):
    black, lamp = shoot("")["black"], shoot("lamp=1")["black"]
    extra = (lamp - black).mean(axis=2)[lit]
    assert extra.mean() > 0.01 and np.percentile(extra, 90) > 2 * np.percentile(extra, 10)
    half, sss = shoot("")["half"], shoot("subsurface=1")["half"]
    # the unlit part of the corner next to the lit stripe gets light that entered the surface beside it
    w = half.shape[1]
    dark = (half.mean(axis=2) < 0.02) & lit
    dark[:, : int(0.3 * w)] = False
    assert sss.mean(axis=2)[dark].mean() > 10 * half.mean(axis=2)[dark].mean() + 1e-4


# --------------------------------------------------------------------------- several projectors


def footprints(cs: CaptureSet) -> list[np.ndarray]:
    """Each projector's lit area in the camera: its white capture minus its black one, above half its peak."""
    out = []
    for k in range(len(cs.projectors)):
        view = cs.for_projector(k)
        lit = (view.image("white") - view.image("black")).mean(axis=2)
        out.append(lit > 0.5 * np.percentile(lit, 99))
    return out


def test_truth_of_two_projectors_round_trips_and_one_projector_truth_is_unchanged(tmp_path):
    one = make_truth("plane", camera_size=(64, 48), projector_size=(80, 60))
    one.save(tmp_path / "one.json")
    doc = json.loads((tmp_path / "one.json").read_text())
    assert "nominal_projectors" not in doc and "projectors" not in doc["rig"]
    two = make_truth("plane", camera_size=(64, 48), projector_size=(80, 60), projectors=2, nominal_error=(0.05, 0),
                     effects="noise=0.5,vignetting=0.5", projector_effects="2:response=0.8")
    # the first projector's nominal pose is off its true one by what it is with one projector (the layout moved it)
    np.testing.assert_allclose(two.nominal_pose[:3, 3] - two.rig.projector.position,
                               one.nominal_pose[:3, 3] - one.rig.projector.position)
    assert len(two.rig.projectors) == 2 and len(two.nominal_projectors) == 2
    two.save(tmp_path / "two.json")
    back = LabTruth.load(tmp_path / "two.json")
    assert len(json.loads((tmp_path / "two.json").read_text())["camera_from_projectors"]) == 2
    for k in range(2):
        np.testing.assert_allclose(back.rig.projectors[k].camera_from_projector,
                                   two.rig.projectors[k].camera_from_projector)
        np.testing.assert_allclose(back.nominal_projectors[k].camera_from_projector,
                                   two.nominal_projectors[k].camera_from_projector)
        assert back.nominal_projectors[k].intrinsics.fx == pytest.approx(two.rig.projectors[k].intrinsics.fx * 1.05)
        view = back.for_projector(k)
        assert view.rig.projector is back.rig.projectors[k] and view.rig.others == ()
        np.testing.assert_allclose(view.nominal_projector.camera_from_projector,
                                   back.nominal_projectors[k].camera_from_projector)
    assert back.for_projector(0).seed == back.seed != back.for_projector(1).seed  # noise of its own
    # mixed projectors: projector 1 has its own projector effects, the camera's are everyone's
    first, second = back.for_projector(0).effects, back.for_projector(1).effects
    assert first["vignetting"].strength == 0.5 and first["response"].strength == 0
    assert second["vignetting"].strength == 0 and second["response"].strength == 0.8
    assert first["noise"] == second["noise"] == two.effects["noise"]
    assert back.for_projector(1).projector_effects == {}


def test_a_projector_black_level_of_its_own_is_its_panel_leak_the_room_stays_shared():
    two = make_truth("plane", camera_size=(64, 48), projector_size=(80, 60), projectors=2,
                     effects="black_level.projector=0.006,black_level.ambient=0.02,response=0.5",
                     projector_effects="2:black_level.projector=0.03,crosstalk=0.3")
    first, second = two.effects_of(0)["black_level"], two.effects_of(1)["black_level"]
    assert first["projector"] == pytest.approx(0.006) and second["projector"] == pytest.approx(0.03)
    assert first["ambient"] == second["ambient"] == pytest.approx(0.02)  # one room
    assert two.effects_of(1)["response"].strength == 0 and two.effects_of(1)["crosstalk"].active
    # naming another effect leaves the panel's leak as the shared effects give it
    other = make_truth("plane", camera_size=(64, 48), projector_size=(80, 60), projectors=2,
                       effects="black_level.projector=0.006", projector_effects="2:response=0.8")
    assert other.effects_of(1)["black_level"]["projector"] == pytest.approx(0.006)


def test_one_projector_leaking_black_is_in_every_projector_s_captures(tmp_path):
    out = tmp_path / "set"
    assert main(["lab", "--surface", "plane", "--out", str(out), *SMALL, "--projectors", "2",
                 "--projector-effects", "2:black_level.projector=0.08"]) == 0
    cs = CaptureSet.load(out)
    first, second = footprints(cs)
    alone = second & ~first
    # projector 0's black capture: projector 1, showing black beside it, leaks 8 % of its white
    black0 = cs.for_projector(0).image("black").mean(axis=2)
    white1 = cs.for_projector(1).image("white").mean(axis=2)
    assert black0[alone].mean() > 0.04 * white1[alone].mean()
    assert max(check_others_black(cs).values()) < BLACK_TOLERANCE  # the same dark scene in both sequences


@pytest.mark.parametrize("spec, message", [
    ("1:noise=0.3", "noise act.* shared by every projector"),
    ("1:black_level.ambient=0.1", "black_level.ambient is the room's light"),
    ("3:response=0.5", r"projector 3, but the lab has 2 projector\(s\), numbered from 1"),
    ("0:response=0.5", "numbered from 1 .*add 1 to each number"),
    ("response=0.5", "K:EFFECTS items"),
    ("1:response=0.5;1:crosstalk=0.2", "projector 1 twice"),
    ("1:respons=0.5", "unknown effect 'respons'"),
])
def test_bad_projector_effects_are_refused(spec, message):
    with pytest.raises(LabError, match=message):
        make_truth("plane", camera_size=(64, 48), projector_size=(80, 60), projectors=2, projector_effects=spec)


def test_projector_effects_number_projectors_from_1_as_every_other_message_does():
    """``--projector-effects 1:…`` is the first projector (it was the second when the option counted from 0)."""
    two = make_truth("plane", camera_size=(64, 48), projector_size=(80, 60), projectors=2,
                     projector_effects="1:response=0.7")
    assert two.effects_of(0)["response"].strength == pytest.approx(0.7)
    assert two.effects_of(1)["response"].strength == 0
    assert set(two.projector_effects) == {0}
    with pytest.raises(LabError, match="gives effects of projector.s. 3, but has 2 projector.s., numbered from 1"):
        replace(two, projector_effects={2: two.effects})


def test_cli_two_projectors_side_by_side_overlap_by_the_fraction_asked(tmp_path, capsys):
    out = tmp_path / "set"
    assert main(["lab", "--surface", "plane", "--out", str(out), *SMALL, "--projectors", "2",
                 "--layout", "side-by-side", "--overlap", "0.25", "--projector-effects", "2:response=1"]) == 0
    assert "of 2 projectors" in capsys.readouterr().out
    truth = LabTruth.load(tmp_path / "set.truth.json")
    poses = [p.camera_from_projector for p in truth.rig.projectors]
    assert len(poses) == 2 and np.linalg.norm(poses[0][:3, 3] - poses[1][:3, 3]) > 0.3
    cs = CaptureSet.load(out)
    assert len(cs.projectors) == 2 and len(cs.entries_of("surface")) == 1 and len(cs.entries_of("depth")) == 2
    assert max(check_others_black(cs).values()) < BLACK_TOLERANCE  # each sequence taken with the other dark
    first, second = footprints(cs)
    for mask in (first, second):
        assert 0.1 < mask.mean() < 0.8  # each lights a part of what the camera sees
    columns = [np.flatnonzero(m.any(axis=0)) for m in (first, second)]
    assert columns[0].mean() < columns[1].mean()  # the first on the left
    shared = (first & second).sum() / min(first.sum(), second.sum())
    assert 0.15 < shared < 0.35, shared  # 0.25 asked
    assert (first | second).sum() > 1.5 * max(first.sum(), second.sum())  # together they cover more than one
    # projector 1's own response (gamma 2.2) darkens its mid-grey; projector 0 has none
    ratios = []
    for k, mask in enumerate((first, second)):
        view = cs.for_projector(k)
        black = view.image("black")
        lit = (view.image("validation", pattern="grey", level=0.5) - black) / (view.image("white") - black + 1e-6)
        ratios.append(float(np.median(lit.mean(axis=2)[mask])))
    assert ratios[0] > 0.4 and ratios[1] < 0.3, ratios


def test_the_other_projectors_black_level_is_in_every_projectors_captures(tmp_path):
    """With a projector black level, each projector's sequence is taken with the others showing black, their
    panels' leak included: every projector's black capture is the same scene (all black), so none is darker than
    another inside that other's footprint (without the leak it would be by b/(1−b) = 25 % of its white there)."""
    truth = make_truth("plane", effects="black_level.projector=0.2", samples=4, camera_size=(64, 48),
                       projector_size=(80, 60), projectors=2, overlap=0.2)
    run_lab(truth, tmp_path / "set", truth_path=tmp_path / "truth.json", graycode=False, validation=False,
            depth_wall=False)
    cs = CaptureSet.load(tmp_path / "set")
    excess = check_others_black(cs)
    assert len(excess) == 2 and all(abs(v) < 0.03 for v in excess.values()), excess
    first, second = footprints(cs)
    black_2 = cs.for_projector(1).image("black").mean(axis=2)
    assert black_2[first & ~second].mean() > 0.5 * cs.for_projector(0).image("black").mean(axis=2)[
        first & ~second].mean() > 0  # projector 1's leak where projector 2 does not reach


def test_stacked_projectors_light_nearly_the_same_area(tmp_path):
    truth = make_truth("plane", samples=2, scale=0.2, projectors=2, layout="stacked")
    run_lab(truth, tmp_path / "set", truth_path=tmp_path / "truth.json", graycode=False, validation=False,
            depth_wall=False)
    first, second = footprints(CaptureSet.load(tmp_path / "set"))
    assert (first & second).sum() / (first | second).sum() > 0.8


def test_two_projectors_shown_at_once_in_one_render():
    """project_all lights every projector in one render: projector 1 alone is its own device's capture, both
    together in the overlap are the sum of each alone (no effects, and below the sensor's white: a linear camera)."""
    truth = make_truth("plane", seed=5, samples=16, camera_size=(64, 48), projector_size=(80, 60), projectors=2,
                       overlap=0.3)
    white = [np.ones((p.intrinsics.height, p.intrinsics.width, 3), np.float32) for p in truth.rig.projectors]
    black = [np.zeros_like(w) for w in white]
    grey = [np.full_like(w, 0.3) for w in white]
    with LabDevice(truth.for_projector(0)) as alone:
        reference = alone.project(white[0])
    with LabDevice(truth) as device:
        assert len(device.projectors) == 2
        first = device.project_all([white[0], black[1]])  # shot 0: the same seeds as the one-projector device's
        second = device.project_all([black[0], white[1]])
        dim = [device.project_all([grey[0], black[1]]), device.project_all([black[0], grey[1]])]
        both = device.project_all(grey)
        dark = device.project_all(black)
        with pytest.raises(CaptureError, match="project_all"):
            device.project(white[0])
        with pytest.raises(CaptureError, match="takes one frame for each, got 1"):
            device.project_all([white[0]])
        with pytest.raises(CaptureError, match="projector 2's frame must be 80×60"):
            device.project_all([white[0], white[1][:30]])
    lit = [img.mean(axis=2) > 0.5 * np.percentile(img.mean(axis=2), 99) for img in (first, second)]
    assert 0.1 < lit[0].mean() < 0.8 and 0.1 < lit[1].mean() < 0.8
    overlap = lit[0] & lit[1]
    assert overlap.sum() > 20 and (lit[0] & ~lit[1]).sum() > 20
    level = float(first.mean(axis=2)[lit[0]].mean())
    # projector 1 with projector 2 black is what projector 1's own device captures (the same seeds)
    assert float(np.abs(first - reference).mean(axis=2)[lit[0]].mean()) < 0.05 * level
    assert float(dark.max()) < 0.02 * level
    alone_each = [float(d.mean(axis=2)[overlap].mean()) for d in dim]
    together = float(both.mean(axis=2)[overlap].mean())
    assert together > 1.5 * max(alone_each)
    assert together == pytest.approx(sum(alone_each), rel=0.05)
    # where only projector 1 reaches, both together are projector 1 alone
    only_first = lit[0] & (second.mean(axis=2) < 0.01 * level)
    assert only_first.sum() > 20
    assert float(both.mean(axis=2)[only_first].mean()) == pytest.approx(float(dim[0].mean(axis=2)[only_first].mean()),
                                                                         rel=0.05)


def test_each_projector_shown_at_once_through_its_own_effects():
    truth = make_truth("plane", seed=5, samples=8, camera_size=(64, 48), projector_size=(80, 60), projectors=2,
                       overlap=0.3, projector_effects="2:response=1")
    w, b = np.ones((60, 80, 3), np.float32), np.zeros((60, 80, 3), np.float32)
    g = np.full_like(w, 0.3)
    with LabDevice(truth) as device:
        shots = [device.project_all(frames) for frames in ([w, b], [g, b], [b, w], [b, g])]
    ratios = []
    for white, grey in (shots[:2], shots[2:]):
        lit = white.mean(axis=2) > 0.5 * np.percentile(white.mean(axis=2), 99)
        ratios.append(float(np.median(grey.mean(axis=2)[lit] / white.mean(axis=2)[lit])))
    assert ratios[0] == pytest.approx(0.3, abs=0.05) and ratios[1] < 0.15, ratios  # projector 2: gamma 2.2


def test_overlap_with_stacked_projectors_is_refused_not_ignored(tmp_path, capsys):
    """Stacked projectors all light one area: an --overlap given with them was ignored without a word (issue 53)."""
    from procam.addon.cli.app import main

    out = tmp_path / "lab"
    assert main(["lab", "--projectors", "2", "--layout", "stacked", "--overlap", "0.4", "--scale", "0.05",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--overlap" in err and "stacked" in err and "%" not in err, err
    assert not out.exists()
