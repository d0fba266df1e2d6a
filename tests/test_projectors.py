"""Several projectors in one show: the overlap figures, the combined range, the per-projector diagnosis verdict, and
the whole path (lab → calibration → joint compensation → evaluation) on a small two-projector lab."""

from __future__ import annotations

import numpy as np
import pytest

from procam.addon.stages.display_area import DisplayArea
from procam.addon.steps import diagnose as diagnose_step
from procam.addon.steps import projectors


def test_seam_step_sees_a_step_at_the_overlap_edge_and_not_a_smooth_blend():
    h, w = 60, 90
    overlap = np.zeros((h, w), bool)
    overlap[:, 40:60] = True
    target = np.full((h, w, 3), 0.5, np.float32)
    seam = target.copy()
    seam[:, 40:60] += 0.1  # the overlap 0.1 too bright: a visible step at both edges
    ramp = target.copy()
    ramp += (0.1 * np.clip(1 - np.abs(np.arange(w) - 50) / 30, 0, 1)).astype(np.float32)[None, :, None]
    assert projectors.seam_step(seam, target, overlap) == pytest.approx(0.1, abs=0.02)
    assert projectors.seam_step(ramp, target, overlap) < 0.03
    assert projectors.seam_step(target, target, overlap) == 0.0
    assert projectors.seam_step(seam, target, np.zeros_like(overlap)) is None  # no overlap: no seam to measure


def test_overlap_masks_split_the_area_by_how_many_projectors_light_it():
    cover = np.zeros((2, 40, 60), bool)
    cover[0, :, :35] = True
    cover[1, :, 25:] = True
    area = DisplayArea(5, 5, 50, 30)
    masks = projectors.overlap_masks(cover, area)
    assert masks["overlap"].shape == (30, 50)
    assert masks["overlap"][:, 20:30].all() and not masks["overlap"][:, :20].any()
    assert masks["outside"][:, :20].all() and not masks["outside"][:, 20:30].any()
    assert masks["border"][:, 18:22].all() and not masks["border"][:, 24:27].any()
    scores = projectors.region_scores(np.full((30, 50, 3), 0.5, np.float32), np.full((30, 50, 3), 0.5, np.float32),
                                      masks)
    assert scores["overlap_share"] == pytest.approx(0.2)


class _Captures:
    """Two projectors' white and black captures (what CaptureSet.for_projector gives), and the room's photo."""

    def __init__(self, room: float, blacks: list[float], whites: list[float], photo: bool = True) -> None:
        self.projectors = [object()] * len(blacks)
        self.room, self.blacks, self.whites, self.photo = room, blacks, whites, photo

    def for_projector(self, k: int) -> _Captures:
        return _Captures(self.room, [self.blacks[k]], [self.whites[k]], self.photo)

    def entries_of(self, kind: str) -> list[str]:
        return ["surface"] if kind == "surface" and self.photo else []

    def image(self, kind: str) -> np.ndarray:
        value = {"surface": self.room, "black": self.blacks[0], "white": self.whites[0]}[kind]
        return np.full((4, 4, 3), value, np.float32)


@pytest.mark.parametrize("photo", [True, False])
def test_projectors_together_reach_the_sum_of_their_light_with_the_black_counted_once(photo):
    """Each projector's black capture was taken while the others showed black (capture/others_black.py): every one
    is the rig's black, up to noise. The rig's black is their mean, whatever the room's photo says (it once added
    every projector's black level again beside the photo), and each projector adds its own white − black."""
    caps = _Captures(0.02, [0.040, 0.044], [0.4, 0.3], photo)
    black, white = projectors.combined_black_white(caps)
    assert black[0, 0, 0] == pytest.approx(0.042)
    assert white[0, 0, 0] == pytest.approx(0.042 + (0.4 - 0.040) + (0.3 - 0.044))


def _gap(selected: list[str], fitted: dict[str, dict[str, float]]) -> dict:
    """One projector's gap.json as attribute reads it: the effects selected and each one's parameters fitted."""
    return {"selected": selected, "effects": [{"name": n, "params": p} for n, p in fitted.items()],
            "headline": "…"}


def _response(gamma: float) -> dict[str, float]:
    return {"gamma_r": gamma, "gamma_g": gamma, "gamma_b": gamma, "contrast": 0.0, "pivot": 0.5}


def _vignetting(falloff: float) -> dict[str, float]:
    return {"falloff": falloff, "exponent": 2.0}


def test_the_projector_whose_fitted_effect_stands_out_is_named_with_it():
    # the plane's figures: the camera's tone curve alone fits γ 0.78 on projector 1, projector 2's own curve on top 1.3
    docs = [_gap(["camera_response", "response", "vignetting"],
                 {"response": _response(0.78), "vignetting": _vignetting(0.10)}),
            _gap(["response", "vignetting"], {"response": _response(1.30), "vignetting": _vignetting(0.11)})]
    verdict = diagnose_step.attribute(docs)
    assert verdict["differs"]["projector"] == 2 and verdict["differs"]["effect"] == "response"
    assert verdict["headline"].startswith("Projector 2 differs from the others by its response")
    assert verdict["ranking"][0]["effect"] == "response"
    same = diagnose_step.attribute([_gap(["vignetting"], {"vignetting": _vignetting(0.3)}),
                                    _gap(["vignetting"], {"vignetting": _vignetting(0.31)})])
    assert same["differs"] is None and same["headline"] == "The projectors agree: each shows vignetting alike."
    none = diagnose_step.attribute([_gap([], {}), _gap([], {})])
    assert none["differs"] is None and "none shows" in none["headline"]


def test_a_camera_or_surface_effect_is_never_one_projectors_difference():
    """The camera and the surface are shared: an effect of theirs is never one projector's difference, however
    differently the projectors' diagnoses fit it."""
    docs = [_gap(["camera_response", "vignetting"], {"camera_response": {"curve": 0.9},
                                                     "vignetting": _vignetting(0.1)}),
            _gap(["camera_response", "vignetting"], {"camera_response": {"curve": 0.0},
                                                     "vignetting": _vignetting(0.1)})]
    verdict = diagnose_step.attribute(docs)
    assert verdict["differs"] is None
    assert all(r["effect"] != "camera_response" for r in verdict["ranking"])


# -- the whole path on a small lab -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def two_projectors(two_projector_lab):
    """The shared two-projector lab, calibrated (projector 2 alone with a tone curve), and two targets."""
    from procam.addon.capture.targets import natural_target
    from procam.addon.imageio import write_image

    root = two_projector_lab
    targets = [write_image(root / f"{n}.png", natural_target(n, (120, 90))) for n in ("city", "forest")]
    return root, targets


def test_two_projectors_are_compensated_together_and_evaluated_in_and_out_of_their_overlap(two_projectors, capsys):
    import json

    from procam.addon.cli.app import main as procam
    from procam.addon.imageio import read_image
    from procam.addon.steps import compensate as compensate_step

    root, targets = two_projectors
    device = f"lab:{root / 'lab.truth.json'}"
    assert procam(["compensate", str(root / "cal"), *map(str, targets), "--device", device, "--iterations", "20",
                   "--out", str(root / "comp")]) == 0
    doc = json.loads((root / "comp" / "compensation.json").read_text())
    assert doc["projector_count"] == 2 and len(doc["projectors"]) == 2 and doc["mode"] == "closed-loop"
    for t in doc["targets"]:
        assert [p["frame"] for p in t["projectors"]] == [f"{t['name']}_frame_p1.png", f"{t['name']}_frame_p2.png"]
        assert sum(p["share"] for p in t["projectors"]) == pytest.approx(1.0, abs=0.01)
        assert min(p["share"] for p in t["projectors"]) > 0.2  # both projectors carry the image
        for k, p in enumerate(t["projectors"]):
            frame = read_image(root / "comp" / p["frame"])
            assert frame.shape[1::-1] == tuple(doc["projectors"][k]["frame_size"])
    assert compensate_step.read(root / "comp").targets[0].frame_path.name == "city_frame_p1.png"
    assert procam(["evaluate", str(root / "cal"), "--inputs", str(root / "comp"), "--targets", *map(str, targets),
                   "--device", device, "--out", str(root / "eval")]) == 0
    out = capsys.readouterr().out
    assert "2 projectors: PSNR inside the overlap" in out
    metrics = json.loads((root / "eval" / "metrics.json").read_text())
    m, u = metrics["mean"], metrics["mean_uncompensated"]
    assert m["psnr"] > u["psnr"] + 5 and m["psnr_overlap"] > u["psnr_overlap"] + 5
    # the joint solve blends the overlap: no worse than where one projector lights alone, and no seam at its edge
    assert m["psnr_overlap"] > m["psnr_outside"] - 0.5
    assert m["seam_step"] < u["seam_step"]
    # a one-projector schedule or a one-projector device is refused, saying why
    assert procam(["compensate", str(root / "cal"), str(targets[0]), "--schedule", "fast", "--out",
                   str(root / "fast")]) == 2
    assert "--schedule transport" in capsys.readouterr().err
    assert not (root / "fast").exists()


def test_each_projector_is_diagnosed_on_its_own_patterns(two_projectors):
    from procam.addon.steps import diagnose as diagnose_step

    root, _ = two_projectors
    doc = diagnose_step.run(diagnose_step.DiagnoseOptions(root / "cal", root / "diag", scale=0.5, spp=8,
                                                          effects="response,vignetting", max_effects=2))
    assert doc["projector_count"] == 2 and len(doc["projectors"]) == 2
    for k in (1, 2):
        assert (root / "diag" / f"projector_{k}" / "gap.json").is_file()
        assert (root / "diag" / f"projector_{k}" / "residual_abs.png").is_file()
    # projector 2 alone has a tone curve (and none of projector 1's vignetting): the verdict names one of them
    assert doc["differs"] is not None
    assert (doc["differs"]["projector"], doc["differs"]["effect"]) in ((2, "response"), (1, "vignetting"))
    assert diagnose_step.summary(root / "diag").headline == doc["headline"]


def test_a_projector_whose_light_misses_the_area_shows_black_and_the_others_go_on(two_projectors, tmp_path):
    """A user area that only projector 1 reaches (projector 1 lights columns 16–68 of the 128×96 camera, projector 2
    56–111): the target is solved on projector 1, projector 2's frame is black with no share of the light, and the
    record and the summary say so; an area neither reaches is refused, nothing written."""
    import json

    from procam.addon.stages.compensate import CompensationError
    from procam.addon.imageio import read_image
    from procam.addon.steps import compensate as compensate_step
    from procam.addon.steps.stage_c import StageCOptions

    root, targets = two_projectors
    out = tmp_path / "left"
    compensate_step.run(compensate_step.CompensateOptions(root / "cal", (targets[0],), out, StageCOptions(
        iterations=10, area=(20, 30, 30, 30))))
    t = json.loads((out / "compensation.json").read_text())["targets"][0]
    assert t["status"] == "done" and [p["share"] for p in t["projectors"]] == [1.0, 0.0]
    assert any(w.startswith("projector 2 lights nothing inside the display area") for w in t["warnings"])
    assert read_image(out / "city_frame_p2.png").max() == 0.0 and read_image(out / "city_frame_p1.png").max() > 0.1
    assert t["psnr_simulated"] > t["psnr_simulated_start"]
    assert "projector 2 lights nothing" in " ".join(compensate_step.summary(out).lines)
    with pytest.raises(CompensationError, match="none of the 2 projectors lights the display area"):
        compensate_step.run(compensate_step.CompensateOptions(root / "cal", (targets[0],), tmp_path / "none",
                                                              StageCOptions(iterations=10, area=(0, 0, 10, 10))))
    assert not (tmp_path / "none").exists()


def test_inputs_of_another_number_of_projectors_are_refused_before_projecting(two_projectors, tmp_path, capsys):
    """A two-projector compensation evaluated with a one-projector calibration, and a one-projector one with the
    two-projector calibration: refused, naming both numbers, nothing written."""
    import json
    import shutil

    from procam.addon.cli.app import main as procam
    from procam.addon.steps.calibrate import read as read_calibration
    from procam.addon.steps.evaluate import CompensationInputs, MismatchError

    root, targets = two_projectors
    cal = read_calibration(root / "cal")
    comp = tmp_path / "comp"
    assert procam(["compensate", str(root / "cal"), str(targets[0]), "--iterations", "4", "--out", str(comp)]) == 0
    inputs = CompensationInputs.load(comp)
    inputs.check_against(cal)  # its own calibration: accepted
    with pytest.raises(MismatchError, match="are for 2 projector.*the calibration has 1"):
        inputs.check_against(cal.for_projector(0))
    one = tmp_path / "one"  # the same folder as one projector's: the projectors list dropped
    shutil.copytree(comp, one)
    doc = json.loads((one / "compensation.json").read_text())
    del doc["projectors"]
    for t in doc["targets"]:
        del t["projectors"]
    (one / "compensation.json").write_text(json.dumps(doc))
    with pytest.raises(MismatchError, match="are for 1 projector.*the calibration has 2"):
        CompensationInputs.load(one).check_against(cal)
    device = f"lab:{root / 'lab.truth.json'}"
    assert procam(["evaluate", str(root / "cal"), "--inputs", str(one), "--targets", str(targets[0]), "--device",
                   device, "--out", str(tmp_path / "eval")]) == 2
    assert "are for 1 projector(s), but the calibration has 2" in capsys.readouterr().err
    assert not (tmp_path / "eval").exists()



def test_the_overlap_measures_each_projectors_falloff_that_calibration_absorbed():
    from procam.addon.gap.overlap import fit_falloffs

    rng = np.random.default_rng(0)
    ys, xs = np.mgrid[0:40, 0:30] / np.array([39.0, 29.0])[:, None, None]
    rho_1 = np.sqrt((0.6 + 0.4 * xs) ** 2 + (ys - 0.5) ** 2)  # the overlap: projector 1's right edge …
    rho_2 = np.sqrt((1.0 - 0.4 * xs) ** 2 + (ys - 0.5) ** 2)  # … projector 2's left edge
    ratio = 0.1 + np.log(1 - 0.2 * rho_2 ** 2) - np.log(1 - 0.0 * rho_1 ** 2) + rng.normal(0, 0.003, xs.shape)
    f_1, f_2 = fit_falloffs(ratio, rho_1, rho_2)
    assert f_1 == pytest.approx(0.0, abs=0.03) and f_2 == pytest.approx(0.2, abs=0.04)
    # radii whose squares add up to a constant pin only the sum of the falloffs: nothing is said
    assert fit_falloffs(ratio, rho_1, np.sqrt(2.0 - rho_1 ** 2)) is None
    assert fit_falloffs(ratio[:5, :5], rho_1[:5, :5], rho_2[:5, :5]) is None  # too few pixels
    # the verdict takes the overlap's falloffs over the fits of each projector's own patterns
    docs = [_gap(["vignetting"], {"vignetting": _vignetting(-0.04)}),
            _gap(["vignetting"], {"vignetting": _vignetting(-0.04)})]
    assert diagnose_step.attribute(docs)["differs"] is None
    verdict = diagnose_step.attribute(docs, [f_1, f_2])
    assert (verdict["differs"]["projector"], verdict["differs"]["effect"]) == (2, "vignetting")


def test_a_missing_operator_of_the_second_projector_is_said_recorded_and_not_written_into_the_calibration(
        two_projectors, tmp_path, capsys):
    """Issue 53: without ``transport_p2.npz`` every compensation rendered projector 2's operator again without a
    word (the progress line was throttled away). The run says so on stderr and in its record and summary, names the
    command that stores it, and leaves the calibration folder as it was (an input)."""
    import json
    import shutil

    from procam.addon.cli.app import main as procam
    from procam.addon.steps import calibrate as calibrate_step
    from procam.addon.steps import transport as transport_step

    root, targets = two_projectors
    cal = tmp_path / "cal"
    shutil.copytree(root / "cal", cal)
    (cal / "transport_p2.npz").unlink()
    before = sorted((p.name, p.stat().st_mtime_ns) for p in cal.rglob("*"))
    view = calibrate_step.read(cal).for_projector(1)
    assert "is missing (transport_p2.npz not in" in transport_step.find(view, bounces=1, seed=0).problem
    assert "was made with --bounces 1 --seed 0, and this run uses --bounces 0" in \
        transport_step.find(calibrate_step.read(cal).for_projector(0), bounces=0, seed=0).problem
    capsys.readouterr()
    assert procam(["compensate", str(cal), str(targets[0]), "--iterations", "5", "--out",
                   str(tmp_path / "comp")]) == 0
    out, err = capsys.readouterr()
    said = "projector 2: the stored light-transport operator transport_p2.npz is missing"
    assert said in err and f"procam precompute {cal}`" in err and "projector 1: the stored" not in err
    doc = json.loads((tmp_path / "comp" / "compensation.json").read_text())
    assert len(doc["transport_notes"]) == 1 and doc["transport_notes"][0].startswith(said)
    assert f"note: {said}" in out  # the summary
    assert sorted((p.name, p.stat().st_mtime_ns) for p in cal.rglob("*")) == before  # nothing written into it


def test_a_closed_loop_through_another_rig_with_as_many_projectors_is_refused_and_leaves_nothing(
        two_projectors, tmp_path, capsys):
    """Issue 53: the side-by-side calibration compensated through a lab truth of stacked projectors (same count, same
    camera) exited 0 while the loop chased light that landed elsewhere (the simulated PSNR fell from 20.9 to 7.3 dB
    on the issue's rig). The first capture's departure from the operator's prediction refuses it, exit 2, no folder
    left; the calibrated rig's own device passes the same check (the test above, and the share measured here)."""
    from procam.addon.cli.app import main as procam
    from procam.addon.lab.truth import make_truth

    root, targets = two_projectors
    other = make_truth("curve", projectors=2, layout="stacked", scale=0.2, samples=4, effects="realistic")
    other.save(tmp_path / "stacked.truth.json")
    capsys.readouterr()
    out = tmp_path / "comp"
    device = f"lab:{tmp_path / 'stacked.truth.json'}"
    assert procam(["compensate", str(root / "cal"), str(targets[1]), "--device", device, "--iterations", "10",
                   "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "is not the rig of this calibration" in err and "departs from what the calibration predicts" in err
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_the_other_rig_share_ignores_exposure_black_level_and_noise_and_sees_light_moved():
    from procam.addon.stages.closed_loop import OTHER_RIG_SHARE, other_rig_share

    rng = np.random.default_rng(3)
    q = np.clip(rng.uniform(0.1, 0.8, (2000, 3)), 0, 1).astype(np.float32)
    sigma = 0.02
    same = 0.8 * q + 0.03 + rng.normal(0, sigma, q.shape)  # another exposure, the room's light, sensor noise
    assert other_rig_share(same, q, sigma ** 2) < 0.03
    moved = 0.8 * np.roll(q, 700, axis=0) + 0.03  # the same light, landing on other pixels
    assert other_rig_share(moved, q) > OTHER_RIG_SHARE
    # a dim target: the noise is no reason to refuse
    dim = 0.03 * q / q.mean()
    assert other_rig_share(dim + rng.normal(0, 0.01, q.shape), dim) < OTHER_RIG_SHARE
