"""The lab's injectable effects: identity at strength 0, each effect's own signature, parsing, truth round trip."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from procam.addon.capture.patterns import checkerboard
from procam.addon.errors import ProCamError
from procam.addon.lab.depth import depth_capture, grazing_angle
from procam.addon.lab.effects import (
    NAMES, PRESETS, REGISTRY, EffectSet, LabError, apply_camera, apply_projector, camera_margin,
    camera_render_intrinsics, distort_points, parse_effects, quantise16, render_settings,
)
from procam.addon.rig.model import Intrinsics, Projector, intrinsics_from_fov

PROJ = Projector(Intrinsics(200, 150, 240.0, 240.0, 100.0, 75.0), input_size=(150, 150))
CAM = intrinsics_from_fov(160, 120, 60.0)
PROJECTOR_SIDE = {"response", "crosstalk", "vignetting", "defocus", "response_scurve", "defocus_depth", "warmup"}
CAMERA_SIDE = {"camera_response", "distortion", "distortion_tangential", "noise"}
RENDER_SIDE = {"interreflection", "glossy", "lamp", "surface_moved", "subsurface"}


def _rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def _test_frame() -> np.ndarray:
    """A projector frame with greys, colours and edges inside the input area."""
    rng = _rng(1)
    img = rng.random((150, 150, 3)).astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), 4)
    img[40:80, 40:80] = 1.0
    img[90:120, 30:60] = (1.0, 0.0, 0.0)
    return PROJ.frame_from_input(img)


def _test_camera_image(intr: Intrinsics = CAM) -> np.ndarray:
    rng = _rng(2)
    img = cv2.GaussianBlur(rng.random((intr.height, intr.width, 3)).astype(np.float32), (0, 0), 3)
    return np.clip(img * 0.8 + 0.1, 0, 1)


def _plane_depth(intr: Intrinsics, z: float = 1.0) -> np.ndarray:
    return np.full((intr.height, intr.width), z, dtype=np.float64)


def _slanted_depth(intr: Intrinsics = PROJ.intrinsics) -> np.ndarray:
    """A wall turned about the vertical axis: 1 m at the frame's left edge, 2 m at its right."""
    return np.tile(np.linspace(1.0, 2.0, intr.width), (intr.height, 1))


# --------------------------------------------------------------------------- identity and isolation

def test_registry_names_match_the_design():
    assert NAMES == ("response", "crosstalk", "black_level", "vignetting", "defocus", "interreflection", "glossy",
                     "camera_response", "distortion", "noise", "depth_noise",
                     "response_scurve", "defocus_depth", "lamp", "distortion_tangential", "warmup", "surface_moved",
                     "subsurface")


def test_every_lab_effect_names_a_diagnosis_model_or_none():
    from procam.addon.gap.models import NAMES as MODELLED

    for kind in REGISTRY.values():
        name = kind.diagnosis_name
        assert name is None or name in MODELLED or name == "noise", kind.name
    assert [k.name for k in REGISTRY.values() if k.diagnosis_name is None] == ["warmup", "surface_moved",
                                                                              "subsurface"]
    assert REGISTRY["defocus_depth"].diagnosis_name == "defocus" and REGISTRY["lamp"].diagnosis_name == "black_level"
    assert REGISTRY["distortion_tangential"].diagnosis_name == "distortion"


@pytest.mark.parametrize("name", NAMES)
def test_strength_zero_is_identity(name):
    off = parse_effects(f"{name}=0")
    assert off == EffectSet.none() and not off[name].active and off.active == ()
    frame = _test_frame()
    np.testing.assert_array_equal(apply_projector(frame, off, PROJ, _rng()), frame)
    img = _test_camera_image()
    np.testing.assert_array_equal(apply_camera(img, off, CAM, _rng()), quantise16(img))
    assert render_settings(off) == {"diffuse_bounces": 0, "indirect_gain": 0.0, "glossy_weight": 0.0,
                                    "glossy_roughness": REGISTRY["glossy"].resolve(0.0)["roughness"],
                                    "glossy_bounces": 0, "max_bounces": 0}
    assert camera_margin(off, CAM) == (0, 0)


@pytest.mark.parametrize("name", [n for n in NAMES if n != "black_level"])
def test_each_effect_acts_only_at_its_own_stage(name):
    on = parse_effects(f"{name}=1")
    assert on.active == (name,)
    frame, img = _test_frame(), _test_camera_image()
    proj_changed = not np.array_equal(apply_projector(frame, on, PROJ, _rng(), depth=_slanted_depth()), frame)
    cam_changed = not np.array_equal(apply_camera(img, on, CAM, _rng()), quantise16(img))
    render_changed = render_settings(on) != render_settings(EffectSet.none())
    assert proj_changed == (name in PROJECTOR_SIDE)
    assert cam_changed == (name in CAMERA_SIDE)
    assert render_changed == (name in RENDER_SIDE)
    depth = _plane_depth(CAM)
    depth_changed = not np.allclose(depth_capture(depth, CAM, on, _rng()),
                                    depth_capture(depth, CAM, EffectSet.none(), _rng()), equal_nan=True)
    assert depth_changed == (name == "depth_noise")


# --------------------------------------------------------------------------- projector effects

def test_response_moves_mid_greys_but_not_black_and_white():
    levels = np.array([0.0, 0.25, 0.5, 0.75, 1.0], dtype=np.float32)
    frame = np.repeat(levels, 40)[None, :, None].repeat(150, 0).repeat(3, 2)
    out = apply_projector(frame, parse_effects("response=1"), PROJ, _rng())
    row = out[75, 20::40]  # one pixel per level, RGB
    np.testing.assert_array_equal(row[0], 0.0)
    np.testing.assert_allclose(row[-1], 1.0, atol=1e-6)
    assert np.all(row[2] < 0.5 - 0.2)  # gamma ≈ 2.2: 0.5 → ≈ 0.22
    assert np.all(np.abs(row[1:4] - levels[1:4, None]) > 0.1)
    assert row[2, 0] < row[2, 1] < row[2, 2]  # per-channel spread: red has the largest exponent


def test_crosstalk_leaks_red_into_green_and_blue_and_keeps_white():
    frame = np.zeros((150, 200, 3), np.float32)
    frame[:, :100] = (1.0, 0.0, 0.0)
    frame[:, 100:] = 1.0
    out = apply_projector(frame, parse_effects("crosstalk=1"), PROJ, _rng())
    red = out[75, 50]
    assert red[1] > 0.05 and red[2] > 0.05 and red[0] < 0.9
    np.testing.assert_allclose(out[75, 150], 1.0, atol=1e-6)


def test_black_level_lifts_black_and_keeps_white():
    frame = np.zeros((150, 200, 3), np.float32)
    frame[:, 100:] = 1.0
    e = parse_effects("black_level=1")
    out = apply_projector(frame, e, PROJ, _rng())
    np.testing.assert_allclose(out[75, 50], e["black_level"]["projector"], rtol=1e-5)
    np.testing.assert_allclose(out[75, 150], 1.0, atol=1e-6)
    cam = apply_camera(np.zeros((CAM.height, CAM.width, 3), np.float32), e, CAM, _rng())
    assert cam.mean() == pytest.approx(e["black_level"]["ambient"], rel=1e-3)
    assert cam[..., 0].mean() > cam[..., 2].mean()  # default ambient tint is warm
    # with a rendered ambient image the ambient light follows it
    amb = np.zeros((CAM.height, CAM.width), np.float32)
    amb[:, : CAM.width // 2] = 1.0
    cam = apply_camera(np.zeros((CAM.height, CAM.width, 3), np.float32), e, CAM, _rng(), ambient_irradiance_image=amb)
    assert cam[:, : CAM.width // 2].mean() == pytest.approx(e["black_level"]["ambient"], rel=1e-3)
    assert cam[:, CAM.width // 2 + 1:].max() == 0.0


def test_vignetting_darkens_corners_not_the_centre():
    frame = np.ones((150, 200, 3), np.float32)
    e = parse_effects("vignetting=1")
    out = apply_projector(frame, e, PROJ, _rng())
    assert out[75, 100].min() > 0.999
    for y, x in ((0, 0), (0, 199), (149, 0), (149, 199)):
        assert out[y, x].max() < 1 - 0.9 * e["vignetting"]["falloff"]
    # with a lens shift the brightest point follows the optical axis (principal point), not the frame centre
    shifted = Projector(Intrinsics(200, 150, 240.0, 240.0, 100.0, 140.0))
    out = apply_projector(frame, e, shifted, _rng())
    assert out[139, 100, 0] > 0.999 and out[10, 100, 0] < out[139, 100, 0] - 0.05


def _edge_width(profile: np.ndarray) -> float:
    """10–90 % rise width (pixels) of a rising edge, by linear interpolation."""
    p = (profile - profile.min()) / (profile.max() - profile.min())
    x = np.arange(len(p), dtype=float)
    return float(np.interp(0.9, p, x) - np.interp(0.1, p, x))


def test_defocus_widens_edges_and_keeps_the_mean():
    frame = np.zeros((150, 200, 3), np.float32)
    frame[40:110, 100:160] = 0.8  # well inside the frame, so no light blurs past its border
    e = parse_effects("defocus=1")
    out = apply_projector(frame, e, PROJ, _rng())
    before, after = _edge_width(frame[75, 80:130, 0]), _edge_width(out[75, 80:130, 0])
    sigma = e["defocus"]["sigma"]
    assert before < 1.0 and after > 1.8 * sigma  # a Gaussian's 10–90 % width is 2.56 σ
    np.testing.assert_allclose(out.mean(), frame.mean(), rtol=1e-4)
    # sigma is in native projector pixels: a half-resolution frame is blurred by half as many of its pixels
    small = cv2.resize(frame, (100, 75), interpolation=cv2.INTER_AREA)
    out_small = apply_projector(small, e, PROJ, _rng())
    assert _edge_width(out_small[37, 40:65, 0]) == pytest.approx(after / 2, rel=0.2)


def test_projector_output_stays_in_the_physical_range():
    out = apply_projector(_test_frame() * 1.5, parse_effects("realistic,response=1,crosstalk=1,black_level=1"),
                          PROJ, _rng())
    assert out.min() >= 0.0 and out.max() <= 1.0 and out.dtype == np.float32


# --------------------------------------------------------------------------- render settings

def test_render_settings_for_interreflection_and_glossy():
    s = render_settings(parse_effects("interreflection=1,glossy=1"))
    assert s["diffuse_bounces"] >= 3 and s["indirect_gain"] == 1.0
    assert 0 < s["glossy_weight"] <= 1 and 0 < s["glossy_roughness"] < 0.5 and s["glossy_bounces"] == 1
    weak = render_settings(parse_effects("interreflection=0.1"))
    assert weak["diffuse_bounces"] == 1 and 0 < weak["indirect_gain"] < 1


# --------------------------------------------------------------------------- camera effects

def test_camera_response_changes_white_balance():
    grey = np.full((CAM.height, CAM.width, 3), 0.4, np.float32)
    e = parse_effects("camera_response=1,camera_response.curve=0")
    out = apply_camera(grey, e, CAM, _rng())
    r, g, b = out[60, 80]
    assert r / g == pytest.approx(e["camera_response"]["gain_r"], rel=1e-3)
    assert b / g == pytest.approx(e["camera_response"]["gain_b"], rel=1e-3)
    curved = apply_camera(grey, parse_effects("camera_response=1"), CAM, _rng())
    assert curved[60, 80, 1] > 0.6  # the sRGB curve lifts a linear 0.4 to ≈ 0.67
    np.testing.assert_array_equal(apply_camera(np.zeros_like(grey), parse_effects("camera_response=1"), CAM, _rng()), 0)


def _blob_image(intr: Intrinsics, centres: np.ndarray, margin: tuple[int, int] = (0, 0)) -> np.ndarray:
    mx, my = margin
    h, w = intr.height + 2 * my, intr.width + 2 * mx
    yy, xx = np.mgrid[0:h, 0:w] + 0.5  # pixel centres, corner convention
    img = np.zeros((h, w), np.float32)
    for cx, cy in centres:
        img += np.exp(-((xx - cx - mx) ** 2 + (yy - cy - my) ** 2) / (2 * 1.5 ** 2)).astype(np.float32)
    return np.repeat(img[..., None], 3, axis=2) * 0.9 + 0.05  # a grey background shows black corners if any


def _centroid(img: np.ndarray, near: np.ndarray, r: int = 8) -> np.ndarray:
    x0, y0 = int(near[0]), int(near[1])
    win = img[y0 - r:y0 + r + 1, x0 - r:x0 + r + 1, 0].astype(np.float64) - 0.05
    yy, xx = np.mgrid[y0 - r:y0 + r + 1, x0 - r:x0 + r + 1] + 0.5
    return np.array([(win * xx).sum() / win.sum(), (win * yy).sum() / win.sum()])


def test_distortion_moves_points_radially_and_keeps_the_principal_point():
    e = parse_effects("distortion=1")
    pts = np.array([[CAM.cx, CAM.cy], [130.0, 95.0], [25.0, 30.0], [140.0, 20.0]])
    margin = camera_margin(e, CAM)
    assert margin[0] > 0 and camera_render_intrinsics(e, CAM).width == CAM.width + 2 * margin[0]
    out = apply_camera(_blob_image(CAM, pts, margin), e, CAM, _rng())
    expected = distort_points(pts, CAM, e)
    # our convention agrees with OpenCV's distortion model (pixel centres at integers there)
    cv_pts, _ = cv2.projectPoints(np.c_[(pts - [CAM.cx, CAM.cy]) / [CAM.fx, CAM.fy], np.ones(len(pts))],
                                  np.zeros(3), np.zeros(3), CAM.opencv_matrix(),
                                  np.array([e["distortion"]["k1"], e["distortion"]["k2"], 0, 0]))
    np.testing.assert_allclose(cv_pts.reshape(-1, 2) + 0.5, expected, atol=1e-6)
    pp = np.array([CAM.cx, CAM.cy])
    for p, q in zip(pts, expected):
        found = _centroid(out, q)
        assert np.linalg.norm(found - q) < 0.1
        radial, moved = p - pp, found - p
        if np.linalg.norm(radial) < 1e-9:
            assert np.linalg.norm(moved) < 0.05  # the principal point stays
        else:
            assert np.linalg.norm(moved) > 1.0  # off-centre points move...
            cos = moved @ radial / (np.linalg.norm(moved) * np.linalg.norm(radial))
            assert cos < -0.999  # ...inwards along the radius (barrel, k1 < 0)
    assert out[0, 0].min() > 0  # with the render margin, the corners are not black


def test_a_decentred_lens_moves_points_as_opencv_says_and_not_radially():
    """distortion_tangential (p1, p2 beside a small k1): the rendered blobs land where OpenCV's full lens model
    puts them, and points on a diagonal move partly across their radius (a radial lens cannot do that)."""
    e = parse_effects("distortion_tangential=1")
    t = e["distortion_tangential"]
    k1, k2, p1, p2 = t["k1"], 0.0, t["p1"], t["p2"]
    pts = np.array([[CAM.cx, CAM.cy], [130.0, 95.0], [25.0, 30.0], [140.0, 20.0]])
    margin = camera_margin(e, CAM)
    out = apply_camera(_blob_image(CAM, pts, margin), e, CAM, _rng())
    expected = distort_points(pts, CAM, e)
    cv_pts, _ = cv2.projectPoints(np.c_[(pts - [CAM.cx, CAM.cy]) / [CAM.fx, CAM.fy], np.ones(len(pts))],
                                  np.zeros(3), np.zeros(3), CAM.opencv_matrix(), np.array([k1, k2, p1, p2]))
    np.testing.assert_allclose(cv_pts.reshape(-1, 2) + 0.5, expected, atol=1e-6)
    pp = np.array([CAM.cx, CAM.cy])
    across = []
    for p, q in zip(pts, expected):
        assert np.linalg.norm(_centroid(out, q) - q) < 0.1
        radial, moved = p - pp, q - p
        if np.linalg.norm(radial) > 1e-9:
            across.append(abs(radial[0] * moved[1] - radial[1] * moved[0]) / np.linalg.norm(radial))
    assert max(across) > 0.3  # pixels moved across the radius


def test_distortion_rejects_a_camera_image_of_the_wrong_size():
    with pytest.raises(LabError, match="margin"):
        apply_camera(np.zeros((CAM.height + 3, CAM.width, 3), np.float32), parse_effects("distortion=1"), CAM, _rng())


def test_noise_has_the_configured_std_and_is_seeded():
    flat = np.full((120, 160, 3), 0.5, np.float32)
    read = parse_effects("noise.sigma=0.01")
    out = apply_camera(flat, read, CAM, _rng(3))
    assert out.std() == pytest.approx(0.01, rel=0.05) and out.mean() == pytest.approx(0.5, abs=1e-3)
    e = parse_effects("noise=1")
    out = apply_camera(flat, e, CAM, _rng(3))
    expected = np.sqrt(e["noise"]["gain"] * 0.5 + e["noise"]["sigma"] ** 2)
    assert out.std() == pytest.approx(expected, rel=0.05)
    dark = apply_camera(flat * 0.1, e, CAM, _rng(3))
    assert dark.std() < out.std()  # shot noise grows with the signal
    np.testing.assert_array_equal(apply_camera(flat, e, CAM, _rng(7)), apply_camera(flat, e, CAM, _rng(7)))
    assert not np.array_equal(apply_camera(flat, e, CAM, _rng(7)), apply_camera(flat, e, CAM, _rng(8)))


def test_camera_output_is_clipped_and_quantised_to_16_bits():
    img = _test_camera_image()
    img[:20] = 1.5  # over-exposed band
    out = apply_camera(img, parse_effects("noise=0.5"), CAM, _rng())
    assert out.min() >= 0 and out.max() == 1.0
    np.testing.assert_array_equal(np.round(out * 65535) / 65535, out)


# --------------------------------------------------------------------------- depth

DEPTH_CAM = intrinsics_from_fov(640, 480, 60.0)


def test_depth_noise_has_the_configured_std_and_bias():
    # at the camera's own resolution the resampling is exact, so the noise shows as configured
    e = parse_effects("depth_noise=1,depth_noise.width=640,depth_noise.height=480,depth_noise.holes=0,"
                      "depth_noise.dropout=0")
    z = 2.0
    d = depth_capture(_plane_depth(DEPTH_CAM, z), DEPTH_CAM, e, _rng(4))
    p = e["depth_noise"]
    assert np.isfinite(d).all()
    assert float(np.mean(d - z)) == pytest.approx(p["bias"], abs=2e-4)
    assert float(np.std(d)) == pytest.approx(p["std"] * z, rel=0.03)
    np.testing.assert_array_equal(d, depth_capture(_plane_depth(DEPTH_CAM, z), DEPTH_CAM, e, _rng(4)))


def test_depth_is_low_resolution_even_at_strength_zero():
    rng = _rng(5)
    fine = 1.5 + 0.05 * rng.standard_normal((480, 640))  # detail finer than the sensor can see
    d = depth_capture(fine, DEPTH_CAM, EffectSet.none(), None)
    assert d.shape == (480, 640) and np.isfinite(d).all()
    assert np.std(d - 1.5) < 0.25 * np.std(fine - 1.5)
    assert float(np.mean(d)) == pytest.approx(1.5, abs=1e-3)
    # a smooth surface comes back nearly exact
    plane = 1.0 + 0.3 * (np.arange(640) / 640.0)[None, :].repeat(480, 0)
    np.testing.assert_allclose(depth_capture(plane, DEPTH_CAM, EffectSet.none(), None)[4:-4, 4:-4],
                               plane[4:-4, 4:-4], atol=2e-3)
    # noise is drawn at the sensor's pixels: after upsampling, neighbours are correlated
    noisy = depth_capture(_plane_depth(DEPTH_CAM), DEPTH_CAM, parse_effects("depth_noise.std=0.01"), _rng(6)) - 1.0
    corr = np.corrcoef(noisy[:, :-1].ravel(), noisy[:, 1:].ravel())[0, 1]
    assert corr > 0.5


def test_depth_keeps_missing_surfaces_and_loses_grazing_returns():
    d = _plane_depth(DEPTH_CAM, 1.0)
    d[:, :200] = np.nan
    out = depth_capture(d, DEPTH_CAM, EffectSet.none(), None)
    assert np.isnan(out[:, :195]).all() and np.isfinite(out[:, 205:]).all()
    # a floor seen at a grazing angle: depth grows fast towards the top of the image
    v = (np.arange(480) + 0.5 - DEPTH_CAM.cy) / DEPTH_CAM.fy
    floor = np.where(v > 0.02, 0.3 / np.maximum(v, 1e-6), np.nan)[:, None].repeat(640, 1)
    angles = grazing_angle(floor, DEPTH_CAM)
    assert np.nanmax(angles) > 80
    lost = depth_capture(floor, DEPTH_CAM, parse_effects("depth_noise.holes=1"), _rng(7))
    kept = depth_capture(floor, DEPTH_CAM, EffectSet.none(), None)
    assert np.isnan(lost).sum() > np.isnan(kept).sum() + 1000
    assert np.isfinite(lost[-20:]).all()  # steep views keep their returns


def test_depth_rejects_wrong_shape():
    with pytest.raises(LabError, match="640×480"):
        depth_capture(np.ones((100, 100)), DEPTH_CAM, EffectSet.none(), None)


# --------------------------------------------------------------------------- parsing and the truth file

@pytest.mark.parametrize("spec, match", [
    ("speckle=0.5", "unknown effect 'speckle'"),
    ("respons=0.5", "did you mean 'response'"),
    ("noise.sigmaa=0.01", "no parameter 'sigmaa'"),
    ("noise=1.5", r"\[0, 1\]"),
    ("noise=-0.1", r"\[0, 1\]"),
    ("noise=lots", "must be a number"),
    ("noise=nan", "finite"),
    ("noise.sigma=5", r"\[0, 0.2\]"),
    ("interreflection.bounces=2.5", "whole number"),
    ("noise", "needs a strength"),
    ("unrealistic", "unknown effect"),
])
def test_parse_errors_are_clear(spec, match):
    with pytest.raises(LabError, match=match) as info:
        parse_effects(spec)
    assert isinstance(info.value, ProCamError)


def test_parse_strengths_and_overrides():
    e = parse_effects(" response=0.5 , crosstalk=0.3,noise.sigma=0.01 ")
    assert e.active == ("response", "crosstalk", "noise")
    assert e["response"]["gamma"] == pytest.approx(1.6)
    assert e["noise"]["sigma"] == 0.01 and e["noise"]["gain"] == 0.0 and e["noise"].overrides == {"sigma": 0.01}
    # overrides win over strengths wherever they stand; later strengths win over presets
    assert parse_effects("noise.sigma=0.01,noise=1")["noise"]["sigma"] == 0.01
    later = parse_effects("realistic,noise=0")
    assert "noise" not in later.active and "response" in later.active
    assert parse_effects("") == parse_effects(None) == parse_effects("none") == EffectSet.none()
    assert parse_effects({"noise": 0.5, "noise.sigma": 0.02}) == parse_effects("noise=0.5,noise.sigma=0.02")


def test_realistic_preset_parses_and_round_trips():
    e = parse_effects("realistic")
    # the preset is a plausible room in the diagnosis's own vocabulary; the other forms and unmodelled causes
    # are for testing the diagnosis and stay off
    core = {k.name for k in REGISTRY.values() if k.cause == ""}
    assert set(e.active) == core == set(PRESETS["realistic"])
    assert all(0 < e[n].strength <= 0.75 for n in core)
    d = json.loads(json.dumps(e.to_dict()))
    assert EffectSet.from_dict(d) == e
    assert d["effects"]["defocus"]["params"]["sigma"] == pytest.approx(0.9)
    assert parse_effects(e.spec) == e
    tweaked = parse_effects("realistic,noise.sigma=0.02,defocus=0.25")
    assert EffectSet.from_dict(json.loads(json.dumps(tweaked.to_dict()))) == tweaked
    assert parse_effects(tweaked.spec) == tweaked
    assert EffectSet.from_dict({"effects": {}}) == EffectSet.none()
    with pytest.raises(LabError, match="unknown effect"):
        EffectSet.from_dict({"effects": {"bloom": {"strength": 0.1}}})


def test_effect_set_is_immutable_and_editable_by_copy():
    e = parse_effects("noise=0.5")
    with pytest.raises(AttributeError):
        e.effects = ()  # type: ignore[misc]
    f = e.with_effect("defocus", 0.5, disk=0.0)
    assert f.active == ("defocus", "noise") and f["defocus"]["disk"] == 0.0 and e.active == ("noise",)
    assert parse_effects("realistic").only("noise", "defocus").active == ("defocus", "noise")


def test_black_level_acts_in_the_projector_and_the_camera_only():
    on = parse_effects("black_level=1")
    frame, img = _test_frame(), _test_camera_image()
    assert not np.array_equal(apply_projector(frame, on, PROJ, _rng()), frame)
    assert not np.array_equal(apply_camera(img, on, CAM, _rng()), quantise16(img))
    assert render_settings(on) == render_settings(EffectSet.none())
    # the projector's part leaves the camera alone
    np.testing.assert_array_equal(apply_camera(img, parse_effects("black_level.projector=0.1"), CAM, _rng()),
                                  quantise16(img))


def test_projector_needs_the_whole_native_frame():
    with pytest.raises(LabError, match="frame_from_input"):
        apply_projector(np.zeros((150, 150, 3), np.float32), parse_effects("vignetting=1"), PROJ, _rng())


# --------------------------------------------------------------------------- forms the diagnosis does not model

def test_s_curve_has_a_toe_and_a_shoulder_that_no_power_law_has():
    from procam.addon.lab.effects import s_curve

    x = np.linspace(0, 1, 101, dtype=np.float32)
    y = s_curve(x, 9.0, 0.4)
    assert y[0] == pytest.approx(0, abs=1e-6) and y[-1] == pytest.approx(1, abs=1e-6)
    assert np.all(np.diff(y) > 0)
    assert y[10] < 0.1 and y[90] > 0.9  # toe below the pivot, shoulder above it
    # a power law through (0.1, y(0.1)) bends the same way everywhere: it cannot also pass above 0.9 at 0.9
    g = np.log(y[10]) / np.log(0.1)
    assert 0.9 ** g < y[90] - 0.05


def test_depth_dependent_defocus_is_sharp_at_the_focus_depth_only():
    frame = PROJ.frame_from_input(checkerboard((150, 150), 6))
    out = apply_projector(frame, parse_effects("defocus_depth=1"), PROJ, depth=_slanted_depth())
    ys, xs = np.nonzero(frame.mean(axis=2) > 0)  # the input area
    near = out[ys.min():ys.max(), xs.min():xs.min() + 12].mean(axis=2)
    far = out[ys.min():ys.max(), xs.max() - 12:xs.max()].mean(axis=2)
    assert near.std() > 2 * far.std()  # focused on the nearest depth (focus = 0): the far side blurs
    with pytest.raises(LabError, match="depth"):
        apply_projector(frame, parse_effects("defocus_depth=1"), PROJ)


def test_warmup_dims_blue_most_at_the_start_and_settles():
    frame = np.ones((150, 200, 3), np.float32)
    fx = parse_effects("warmup=1")
    start, end = apply_projector(frame, fx, PROJ, t=0.0), apply_projector(frame, fx, PROJ, t=3.0)
    loss = 1 - start.mean(axis=(0, 1))
    assert loss[2] > loss[1] > loss[0] > 0 and loss[2] == pytest.approx(0.12, rel=0.01)
    assert np.allclose(end, 1.0, atol=2e-4)


def test_render_side_effects_ask_the_renderer_only_when_on():
    off = render_settings(EffectSet.none())
    for name, keys in (("lamp", {"lamp_power", "lamp_position"}),
                       ("surface_moved", {"surface_shift", "surface_turn_deg"}),
                       ("subsurface", {"subsurface_weight", "subsurface_radius"})):
        on = render_settings(parse_effects(f"{name}=0.5"))
        assert set(on) - set(off) == keys and not keys & set(off)


def test_a_supersampled_render_is_distorted_at_its_own_resolution_and_averaged_down():
    """Rendered at 2× with its margin, the image is distorted where it is fine and averaged to the camera's
    pixels: each output pixel shows what the lens model says, as without supersampling."""
    from procam.addon.lab.effects import _undistort_normalised, apply_camera, camera_render_intrinsics, parse_effects
    from procam.addon.rig.model import Intrinsics

    cam = Intrinsics(160, 120, 144.0, 144.0, 80.0, 60.0)
    eff = parse_effects("distortion=0.5")
    fine = camera_render_intrinsics(eff, cam)
    fine = fine.scaled(2 * fine.width, 2 * fine.height)
    ys, xs = np.mgrid[0:fine.height, 0:fine.width] + 0.5
    ramp = np.zeros((fine.height, fine.width, 3), np.float32)
    ramp[..., 0] = 0.5 + 0.3 * (xs - fine.cx) / fine.fx  # normalised pinhole coordinates, encoded in [0, 1]
    ramp[..., 1] = 0.5 + 0.3 * (ys - fine.cy) / fine.fy
    out = apply_camera(ramp, eff, cam, None, supersample=2)
    assert out.shape == (120, 160, 3)
    v, u = np.mgrid[0:120, 0:160] + 0.5
    xu, yu = _undistort_normalised((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, eff["distortion"]["k1"],
                                   eff["distortion"]["k2"])
    err = np.hypot((out[..., 0] - 0.5) / 0.3 - xu, (out[..., 1] - 0.5) / 0.3 - yu) * cam.fx
    assert np.median(err) < 0.02 and np.percentile(err[2:-2, 2:-2], 99) < 0.1
    with pytest.raises(LabError, match="supersampling"):
        apply_camera(ramp[:-1], eff, cam, None, supersample=2)
