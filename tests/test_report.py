"""`procam report`: one self-contained HTML page of a real step tree (calibrated, compensated, evaluated, diagnosed,
a show), opened in headless Chromium — no console error, no broken image, a screenshot — and what it does with bad
input: it lists what it skipped and why, and still writes the page."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from procam.addon.cli.app import EXIT_OK, EXIT_USER, main
from procam.addon.imageio import write_image
from procam.addon.report import figures
from procam.addon.steps.report_sections import Reader

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_browser = pytest.mark.skipif(CHROMIUM is None, reason="no chromium on this machine (scripts/setup.sh installs "
                                                            "Debian's chromium when run as root)")

#: appended to a copy of the page: the title says how many images there are and how many did not decode
CHECK = """<script>window.addEventListener("load", () => {
  const imgs = [...document.images];
  const broken = imgs.filter(i => !(i.complete && i.naturalWidth > 0));
  document.title = "PROCAM-CHECK images=" + imgs.length + " broken=" + broken.length;
});</script>"""


def browse(page: Path, shot: Path | None = None) -> tuple[int, int, list[str]]:
    """Open ``page`` in headless Chromium: (images, broken images, console lines); with ``shot``, a screenshot of
    the top of the page too."""
    checked = page.with_name(page.stem + ".checked.html")
    checked.write_text(page.read_text(encoding="utf-8").replace("</body>", CHECK + "</body>"), encoding="utf-8")
    common = [CHROMIUM, "--headless=new", "--disable-gpu", "--no-sandbox", "--hide-scrollbars",
              "--virtual-time-budget=5000", "--enable-logging=stderr", "--v=0"]
    run = subprocess.run([*common, "--dump-dom", checked.as_uri()], capture_output=True, text=True, timeout=60)
    title = re.search(r"PROCAM-CHECK images=(\d+) broken=(\d+)", run.stdout)
    assert title, f"the check did not run: {run.stderr[-2000:]}"
    console = [line for line in run.stderr.splitlines() if ":CONSOLE" in line or "Uncaught" in line]
    if shot is not None:
        subprocess.run([*common, "--window-size=1280,2400", f"--screenshot={shot}", page.as_uri()],
                       capture_output=True, text=True, timeout=60, check=True)
    return int(title.group(1)), int(title.group(2)), console


@pytest.fixture(scope="module")
def tree(lab_set, tmp_path_factory) -> Path:
    """A small real step tree: captures, calibration (stages A and B), compensation of two targets, their
    evaluation through the lab, a diagnosis of two effects, a show of three frames (camera 128×96)."""
    from procam.addon.capture.targets import natural_target
    from procam.addon.imageio import write_image

    captures, truth = lab_set("plane", "response=0.8", scale=0.2, samples=8)
    root = tmp_path_factory.mktemp("report") / "project"
    root.mkdir()
    shutil.copytree(captures, root / "captures")
    assert main(["calibrate", str(root / "captures"), "--out", str(root / "calibration"), "--no-blend-output"]) == 0
    (root / "targets").mkdir()
    targets = [str(write_image(root / "targets" / f"{n}.png", natural_target(n, (64, 48)))) for n in ("city", "forest")]
    fast = ["--iterations", "4", "--spp", "1", "--no-bias"]
    assert main(["compensate", str(root / "calibration"), *targets, "--out", str(root / "compensation"), *fast]) == 0
    assert main(["evaluate", str(root / "calibration"), "--inputs", str(root / "compensation"), "--targets", *targets,
                 "--device", f"lab:{truth}", "--out", str(root / "evaluation")]) == 0
    assert main(["diagnose", str(root / "calibration"), "--out", str(root / "diagnosis"), "--effects",
                 "black_level,response", "--spp", "4", "--max-effects", "2"]) == 0
    (root / "clip").mkdir()
    for k, name in enumerate(("city", "forest", "city")):
        shutil.copy(root / "targets" / f"{name}.png", root / "clip" / f"shot_{k + 1:04d}.png")
    assert main(["show", str(root / "calibration"), str(root / "clip"), "--out", str(root / "show"), *fast]) == 0
    return root


def test_the_checker_sees_a_broken_image_and_a_console_error(tmp_path):
    """The browser check is not vacuous: a page with an image that does not load and a script error fails it."""
    if CHROMIUM is None:
        pytest.skip("no chromium on this machine")
    page = tmp_path / "bad.html"
    page.write_text('<html><head><title>x</title></head><body><img src="missing.png"><img src="data:image/png;'
                    'base64,AAAA"><script>undefinedFunction();</script></body></html>')
    images, broken, console = browse(page)
    assert (images, broken) == (2, 2) and any("undefinedFunction" in line for line in console)


@needs_browser
def test_the_report_of_a_step_tree_opens_in_a_real_browser(tree, tmp_path, capsys):
    out = tmp_path / "report.html"
    t0 = time.perf_counter()
    assert main(["report", str(tree), "--out", str(out)]) == EXIT_OK
    printed = capsys.readouterr().out
    assert f"report: {out}" in printed and "MB, built in" in printed
    html = out.read_text(encoding="utf-8")
    # self-contained: no file, stylesheet, script or address outside the page
    assert not re.search(r"""(src|href)\s*=\s*["'](?!data:|#)""", html), "a resource outside the page"
    assert "<script" not in html and "<link" not in html and "url(" not in html
    for title in ("Calibration", "Compensation", "Evaluation", "Diagnosis", "Show"):
        assert f"<h2>{title}</h2>" in html, title
    for heading in ("Pose (stage A)", "Warp (stage B)", "Gray-code coverage", "Surface", "Each target",
                    "Flicker", "Where the simulation differs", "Which effects explain it"):
        assert f"<h3>{heading}</h3>" in html, heading
    gap = json.loads((tree / "diagnosis" / "gap.json").read_text())
    headline = gap["headline"].replace("'", "&#39;")
    assert html.index(headline) < html.index("Where the simulation differs")  # the plain sentence first
    assert "Skipped" not in html  # a clean tree: nothing left out
    images, broken, console = browse(out, tmp_path / "report.png")
    assert images >= 15 and broken == 0, (images, broken)
    assert console == []
    assert (tmp_path / "report.png").stat().st_size > 20_000  # a picture, not a blank page
    assert time.perf_counter() - t0 < 60


def test_bad_input_is_listed_and_the_page_still_written(tree, tmp_path, capsys):
    bad = tmp_path / "bad"
    (bad / "notes").mkdir(parents=True)
    (bad / "notes" / "readme.txt").write_text("not ProCam's")
    old = bad / "old-evaluation"
    shutil.copytree(tree / "evaluation", old)
    doc = json.loads((old / "metrics.json").read_text())
    (old / "metrics.json").write_text(json.dumps({**doc, "version": 0}))
    thin = bad / "thin-diagnosis"  # a manifest without what this version records
    shutil.copytree(tree / "diagnosis", thin)
    doc = json.loads((thin / "gap.json").read_text())
    (thin / "gap.json").write_text(json.dumps({k: v for k, v in doc.items() if k != "residual"}))
    holes = bad / "evaluation-with-holes"
    shutil.copytree(tree / "evaluation", holes)
    (holes / "city_capture.png").unlink()
    out = tmp_path / "bad.html"
    assert main(["report", str(bad / "notes"), str(old), str(thin), str(holes), str(tmp_path / "nowhere"),
                 "--out", str(out)]) == EXIT_OK
    printed = capsys.readouterr().out
    html = out.read_text(encoding="utf-8")
    reasons = {"notes": "not a ProCam step folder", "old-evaluation": "format version 0",
               "thin-diagnosis": "written by an older version", "evaluation-with-holes": "city_capture.png",
               "nowhere": "does not exist"}
    for where, why in reasons.items():
        assert re.search(rf"skipped \S*{where}\S*: [^\n]*{why}", printed), (where, printed)
        assert why in html
    assert "<h2>Evaluation</h2>" in html  # the evaluation with a missing image is still shown, less that image
    if CHROMIUM is not None:
        images, broken, console = browse(out)
        assert images >= 2 and broken == 0 and console == []  # the ceilings and the target with its images


def test_the_output_file_is_guarded(tree, tmp_path, capsys):
    mine = tmp_path / "mine.html"
    mine.write_text("<html>my own page</html>")
    assert main(["report", str(tree / "show"), "--out", str(mine), "--force"]) == EXIT_USER
    assert "not a ProCam report" in capsys.readouterr().err and mine.read_text() == "<html>my own page</html>"
    out = tmp_path / "r.html"
    assert main(["report", str(tree / "show"), "--out", str(out)]) == EXIT_OK
    assert main(["report", str(tree / "show"), "--out", str(out)]) == EXIT_USER
    assert "--force" in capsys.readouterr().err
    assert main(["report", str(tree / "show"), "--out", str(out), "--force"]) == EXIT_OK
    # never into a folder it reads
    assert main(["report", str(tree), "--out", str(tree / "calibration" / "report.html")]) == EXIT_USER
    assert not (tree / "calibration" / "report.html").exists()
    assert main(["report", str(tree / "show"), "--out", str(tmp_path / "r.txt")]) == EXIT_USER


@pytest.mark.blender
def test_open_report_builds_the_scenes_report_and_opens_it(tree, registered, monkeypatch):
    import bpy

    opened = []
    monkeypatch.setattr("webbrowser.open", lambda uri: opened.append(uri) or True)
    scene = bpy.context.scene
    assert not bpy.ops.procam.open_report.poll()  # no step folder yet
    scene.procam_calibration_dir = str(tree / "calibration")
    scene.procam_diagnosis_dir = str(tree / "diagnosis")
    assert bpy.ops.procam.open_report() == {"FINISHED"}
    page = tree / "report.html"  # in the folder that holds the scene's step folders
    assert opened == [page.as_uri()]
    html = page.read_text(encoding="utf-8")
    assert "<h2>Calibration</h2>" in html and "<h2>Diagnosis</h2>" in html and "<h2>Show</h2>" not in html
    assert bpy.ops.procam.open_report() == {"FINISHED"}  # built again over its own report
    page.unlink()


def test_several_projectors_each_projector_s_images_are_shown(tmp_path, monkeypatch):
    drawn: list[list[str]] = []
    pictures = figures.pictures
    monkeypatch.setattr(figures, "pictures", lambda imgs, caps, **kw: drawn.append(caps) or pictures(imgs, caps, **kw))
    rng = np.random.default_rng(0)
    for name in ("t_target.png", "t_simulated.png", "t_input_p1.png", "t_input_p2.png",
                 "0001_p1.png", "0001_p2.png", "0002_p1.png", "0002_p2.png"):
        write_image(tmp_path / name, rng.random((12, 16, 3)).astype(np.float32))
    skipped: list[str] = []
    reader = Reader([], lambda folder, why: skipped.append(why))
    doc = {"mode": "open", "targets": [{
        "name": "t", "status": "done", "target": "t_target.png", "simulated": "t_simulated.png",
        "input": "t_input_p1.png", "projectors": [{"input": "t_input_p1.png", "share": 0.6},
                                                  {"input": "t_input_p2.png", "share": 0.4}]}]}
    _, blocks = reader.compensation(tmp_path, doc)
    assert drawn[-1][2:] == ["projector 1 input (share 60%)", "projector 2 input (share 40%)"]
    assert "images the projectors are given" in " ".join(str(b) for b in blocks)
    intr = {"width": 16, "height": 12, "fx": 20.0, "cx": 8.0, "cy": 6.0}
    poses = [np.eye(4), np.eye(4)]
    poses[1][0, 3] = 0.4
    posed: list[int] = []
    monkeypatch.setattr(figures, "pose_views", lambda where, axes, points: posed.append(len(where)) or "")
    rig = {"camera": {"intrinsics": intr}, "projector": {"intrinsics": intr, "input_size": [16, 12]},
           "projectors": [{"intrinsics": intr, "input_size": [16, 12]}] * 2}
    _, blocks = reader.calibration(tmp_path, {"rig": rig, "camera_from_projector": poses[0].tolist(),
                                              "projectors": [{"camera_from_projector": p.tolist()} for p in poses]})
    facts = dict(blocks[0]["items"])
    assert facts["projector 2 position"].startswith("x 0.400") and posed == [2]
    assert skipped == ["Gray-code coverage not shown: the capture set None is not there"]
    skipped.clear()
    target = {"name": "t", "status": "done", "psnr": 25.0, "ssim": 0.9, "psnr_overlap": 28.8, "seam_step": 0.02,
              "overlap_share": 0.2, "area": {"x": 0, "y": 0, "width": 16, "height": 12}, "image": "t_strip.png",
              "uncompensated": {"psnr": 16.0, "ssim": 0.6, "psnr_overlap": 15.6, "seam_step": 0.015}}
    _, blocks = reader.evaluation(tmp_path, {"projector_count": 2, "targets": [target],
                                             "mean": {"psnr_overlap": 28.8, "seam_step": 0.0203},
                                             "mean_uncompensated": {"psnr_overlap": 15.61, "seam_step": 0.0151}})
    facts = dict(blocks[0]["items"])
    assert facts["PSNR inside the overlap (mean)"] == "15.61 dB → 28.80 dB"
    assert facts["seam step (mean)"].startswith("0.0151 → 0.0203")
    assert ["t", "20%", "15.60 dB → 28.80 dB", "– → –", "– → –", "0.0150 → 0.0200"] in blocks[2]["rows"]
    skipped.clear()  # the comparison strip is not in this folder
    frames = {str(n): {"number": n, "status": "done", "file": f"000{n}_p1.png", "psnr_model": 40.0,
                       "projectors": [{"file": f"000{n}_p1.png"}, {"file": f"000{n}_p2.png"}]} for n in (1, 2)}
    _, blocks = reader.show(tmp_path, {"frames": frames, "complete": True, "projector_count": 2})
    strips = [b for b in blocks if b["type"] == "strip"]
    assert len(strips) == 2 and "projector 2's input" in strips[1]["caption"]
    assert [len(s["thumbs"]) for s in strips] == [2, 2] and strips[0]["thumbs"][0] != strips[1]["thumbs"][0]
    assert skipped == []


def test_the_report_shows_the_spill_and_each_projector_s_share_of_the_area(tmp_path, monkeypatch):
    """Issue 50: the evaluation's facts and table say the light outside the display area, compensated beside
    uncompensated, and with several projectors what share of the area each lights."""
    drawn: list[list[str]] = []
    pictures = figures.pictures
    monkeypatch.setattr(figures, "pictures", lambda imgs, caps, **kw: drawn.append(caps) or pictures(imgs, caps, **kw))
    rng = np.random.default_rng(0)
    for name in ("t_target.png", "t_simulated.png", "t_input_p1.png", "t_input_p2.png"):
        write_image(tmp_path / name, rng.random((12, 16, 3)).astype(np.float32))
    reader = Reader([], lambda folder, why: None)
    reader.compensation(tmp_path, {"mode": "open", "targets": [{
        "name": "t", "status": "done", "target": "t_target.png", "simulated": "t_simulated.png",
        "input": "t_input_p1.png", "area_shares": [0.61, 0.65],
        "projectors": [{"input": "t_input_p1.png", "share": 0.5, "area_share": 0.61},
                       {"input": "t_input_p2.png", "share": 0.5, "area_share": 0.65}]}]})
    assert drawn[-1][2:] == ["projector 1 input (share 50%), lights 61% of the area",
                             "projector 2 input (share 50%), lights 65% of the area"]
    target = {"name": "t", "status": "done", "psnr": 25.0, "ssim": 0.9, "spill_mean": 0.012, "spill_p995": 0.21,
              "area_shares": [0.61, 0.65], "area": {"x": 0, "y": 0, "width": 16, "height": 12},
              "image": "t_strip.png",
              "uncompensated": {"psnr": 16.0, "ssim": 0.6, "spill_mean": 0.015, "spill_p995": 0.4}}
    spill = {"mean": 0.012, "p995": 0.21, "worst_p995": 0.21, "uncompensated_mean": 0.015,
             "uncompensated_p995": 0.4, "guard_px": 2}
    _, blocks = reader.evaluation(tmp_path, {"projector_count": 2, "targets": [target], "mean": {},
                                             "mean_uncompensated": {}, "spill": spill})
    facts = dict(blocks[0]["items"])
    assert facts["spill outside the area (mean)"].startswith("mean 1.5% → 1.2%, 99.5th pixel 40.0% → 21.0%")
    spill_table = next(b for b in blocks if b["type"] == "table" and "spill mean comp." in b["head"])
    assert spill_table["rows"] == [["t", "1.5%", "1.2%", "40.0%", "21.0%", "61%, 65%"]]
