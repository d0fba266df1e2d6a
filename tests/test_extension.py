"""The extension as a user gets it: manifest, zip build, install into a fresh Blender user folder, bpy-free import."""

from __future__ import annotations

import importlib.util
import shutil
import sys
import time
import tomllib
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BLENDER_EXT = "addons_core/bl_pkg/cli/blender_ext.py"


def _build_script():
    spec = importlib.util.spec_from_file_location("procam_build_extension", REPO / "scripts" / "build_extension.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _blender_ext_cli() -> Path | None:
    """Blender's own extension tool (ships inside the bpy wheel)."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        return None
    found = sorted(Path(spec.submodule_search_locations[0]).glob(f"*/scripts/{BLENDER_EXT}"))
    return found[-1] if found else None


def test_import_outside_blender_does_not_import_bpy(run_python):
    proc = run_python("""
        import sys
        import procam, procam.addon.cli.app
        procam.addon.cli.app.build_parser()  # imports every subcommand module
        heavy = [m for m in ("bpy", "mathutils", "bpy_extras") if m in sys.modules]
        assert not heavy, heavy
    """)
    assert proc.returncode == 0, proc.stderr


def test_manifest_matches_pinned_requirements():
    script = _build_script()
    manifest = tomllib.loads((REPO / "blender_manifest.toml").read_text(encoding="utf-8"))
    assert manifest["schema_version"] == "1.0.0" and manifest["id"] == "procam" and manifest["type"] == "add-on"
    assert manifest["blender_version_min"] == "4.2.0" and manifest["platforms"] == ["linux-x64"]
    pins = script.pinned_versions(REPO)
    listed = {}
    for wheel in manifest["wheels"]:
        assert wheel.startswith("./wheels/") and wheel.endswith(".whl")
        name, version, python = Path(wheel).name.split("-")[:3]
        assert python in ("cp311", "cp37", "py3"), wheel
        listed[script._canonical(name)] = version
    assert listed == {script._canonical(p): v for p, v in pins.items()}
    assert "bpy" not in listed and "numpy" not in listed  # Blender provides both


def test_manifest_wheel_list_rewrite():
    script = _build_script()
    text = (REPO / "blender_manifest.toml").read_text(encoding="utf-8")
    names = [Path(w).name for w in tomllib.loads(text)["wheels"]]
    assert script.manifest_with_wheels(text, names) == text  # the committed list is what a build writes
    stripped = tomllib.loads(script.manifest_with_wheels(text, []))
    assert "wheels" not in stripped and stripped["permissions"] == tomllib.loads(text)["permissions"]
    added = tomllib.loads(script.manifest_with_wheels(script.manifest_with_wheels(text, []), ["a-1-py3-none-any.whl"]))
    assert added["wheels"] == ["./wheels/a-1-py3-none-any.whl"] and added["id"] == "procam"


def test_build_without_wheels_is_small_and_clean(tmp_path):
    script = _build_script()
    path = script.build(tmp_path, with_wheels=False)
    assert path == tmp_path / "procam-0.1.0-no-wheels.zip"
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporary file left behind
    with zipfile.ZipFile(path) as zf:
        names = zf.namelist()
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
    for required in ("blender_manifest.toml", "__init__.py", "blender_registration.py", "addon/cli/app.py",
                     "addon/blender/rig.py", "addon/lab/cycles.py", "operators/create_rig.py", "panels/rig.py"):
        assert required in names
    for name in names:
        assert not name.startswith(("tests/", "scripts/", ".venv/", "wheels/", "dist/")), name
        assert "__pycache__" not in name and not name.endswith(".pyc"), name
    assert "wheels" not in manifest


def test_blender_validates_the_manifest(tmp_path, run_python):
    tool = _blender_ext_cli()
    if tool is None:
        pytest.skip("bpy (with Blender's extension tool) is not installed")
    path = _build_script().build(tmp_path, with_wheels=False)
    proc = run_python(f"import runpy, sys; sys.argv = ['blender_ext', 'validate', {str(path)!r}]; "
                      f"runpy.run_path({str(tool)!r}, run_name='__main__')")
    assert proc.returncode == 0 and "Success" in proc.stdout, proc.stdout + proc.stderr


_INSTALL = """
    import glob, json, os, sys, time
    zip_path, home = sys.argv[1], sys.argv[2]
    import bpy  # Blender's user folders come from the environment set by the caller
    assert bpy.utils.user_resource("EXTENSIONS").startswith(home), bpy.utils.user_resource("EXTENSIONS")
    t = time.perf_counter()
    result = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    seconds = time.perf_counter() - t
    assert result == {"FINISHED"}, result
    assert "bl_ext.user_default.procam" in bpy.context.preferences.addons.keys()
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    assert bpy.ops.procam.create_rig(camera_width=32, camera_height=24, projector_width=40,
                                     projector_height=30, surface="plane") == {"FINISHED"}
    mod = sys.modules["bl_ext.user_default.procam"]
    assert mod.__file__.startswith(home), mod.__file__
    from bl_ext.user_default.procam.addon.blender import rig as blender_rig
    rig = blender_rig.read_rig(bpy.context.scene)
    from bl_ext.user_default.procam import blender_registration
    help_code = blender_registration.run_cli(["--help"])
    site = glob.glob(os.path.join(home, "extensions", ".local", "lib", "python*", "site-packages"))
    packages = sorted(os.listdir(site[0])) if site else []
    print(json.dumps({"seconds": seconds, "help": help_code, "camera": list(rig.camera.intrinsics.size),
                      "objects": sorted(o.name for o in bpy.context.scene.objects), "packages": packages}))
"""


def _install(zip_path: Path, home: Path, run_python) -> dict:
    import json

    env = {f"BLENDER_USER_{k}": str(home / k.lower()) for k in ("RESOURCES", "CONFIG", "SCRIPTS", "EXTENSIONS",
                                                                 "DATAFILES")}
    proc = run_python(_INSTALL, str(zip_path), str(home), env=env)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_install_without_wheels_and_run_operator(tmp_path, run_python):
    pytest.importorskip("bpy")
    path = _build_script().build(tmp_path / "dist", with_wheels=False)
    info = _install(path, tmp_path / "blender", run_python)
    assert info["help"] == 0 and info["camera"] == [32, 24]
    assert {"ProCam Camera", "ProCam Projector", "ProCam Surface"} <= set(info["objects"])


def test_build_and_install_with_wheels(tmp_path, run_python):
    """The release zip: wheels downloaded (cached in ~/.cache/procam-wheels), installed by Blender itself."""
    pytest.importorskip("bpy")
    script = _build_script()
    t = time.perf_counter()
    try:
        path = script.build(tmp_path / "dist", update_manifest=False)
    except script.BuildError as exc:
        if "could not download" in str(exc):
            pytest.skip(f"wheels cannot be downloaded here: {exc}")
        raise
    build_s = time.perf_counter() - t
    size = path.stat().st_size / 2 ** 20
    with zipfile.ZipFile(path) as zf:
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
        names = set(zf.namelist())
    committed = tomllib.loads((REPO / "blender_manifest.toml").read_text(encoding="utf-8"))
    assert manifest["wheels"] == committed["wheels"]
    assert {w.removeprefix("./") for w in manifest["wheels"]} <= names
    try:
        info = _install(path, tmp_path / "blender", run_python)
    finally:
        shutil.rmtree(tmp_path, ignore_errors=True)  # ~1 GB unpacked: do not leave it to pytest's tmp rotation
    for package in ("mitsuba", "drjit", "cv2", "pymeshlab"):
        assert package in info["packages"], info["packages"]
    assert info["help"] == 0
    print(f"\nextension zip {size:.0f} MiB, build {build_s:.1f} s, install {info['seconds']:.1f} s", file=sys.stderr)
