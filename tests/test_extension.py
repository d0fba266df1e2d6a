"""The extension as a user gets it: manifest, per-platform zips checked by Blender's validator, install into a
fresh Blender user folder, bpy-free import, and finding LLVM on each platform."""

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
PLATFORMS = ["linux-x64", "windows-x64", "macos-arm64"]


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
    assert manifest["blender_version_min"] == "4.2.0" and manifest["platforms"] == PLATFORMS
    assert set(PLATFORMS) == set(script.PLATFORM_TAGS)
    pins = {script._canonical(p): v for p, v in script.pinned_versions(REPO).items()}
    assert {"drjit", "mitsuba", "pygame_ce"} <= set(pins)
    served: dict[str, dict[str, str]] = {p: {} for p in PLATFORMS}
    for wheel in manifest["wheels"]:
        assert wheel.startswith("./wheels/") and wheel.endswith(".whl")
        name, version, python = Path(wheel).name.split("-")[:3]
        assert python in ("cp311", "cp37", "py3"), wheel
        platforms = script.wheel_platforms(wheel) & set(PLATFORMS)
        assert platforms, f"{wheel} serves none of the manifest's platforms"
        for platform in platforms:
            assert script._canonical(name) not in served[platform], f"two {name} wheels for {platform}"
            served[platform][script._canonical(name)] = version
    for platform in PLATFORMS:  # every platform claimed has every pinned package
        assert served[platform] == pins, platform
    assert "bpy" not in pins and "numpy" not in pins  # Blender provides both


def test_wheel_platforms_read_like_blender():
    script = _build_script()
    assert script.wheel_platforms("a-1-cp311-cp311-manylinux_2_27_x86_64.manylinux_2_28_x86_64.whl") == {"linux-x64"}
    assert script.wheel_platforms("a-1-cp37-abi3-win_amd64.whl") == {"windows-x64"}
    assert script.wheel_platforms("a-1-cp311-cp311-macosx_13_0_arm64.whl") == {"macos-arm64"}
    assert script.wheel_platforms("a-1-cp311-cp311-macosx_10_11_universal2.whl") == {"macos-arm64"}
    assert script.wheel_platforms("a-1-cp311-cp311-macosx_10_9_x86_64.whl") == set()  # Intel Macs: not built
    assert script.wheel_platforms("a-1-py3-none-any.whl") == set(PLATFORMS)
    assert script.wheel_platforms("a-1-cp311-cp311-manylinux_2_17_aarch64.whl") == set()


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
    if _blender_ext_cli() is None:
        pytest.skip("bpy (with Blender's extension tool, which writes the zips) is not installed")
    script = _build_script()
    [path] = script.build(tmp_path, with_wheels=False)
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
    assert "wheels" not in manifest and manifest["platforms"] == PLATFORMS


def test_unknown_or_unclaimed_platform_is_refused(tmp_path):
    script = _build_script()
    with pytest.raises(script.BuildError, match="macos-x64 is not among the platforms"):
        script.build(tmp_path, with_wheels=False, platforms=["macos-x64"])
    with pytest.raises(script.BuildError, match="unknown platform"):
        script.fetch_wheels(tmp_path, {"drjit": "1.5.0"}, "linux-arm64")
    assert list(tmp_path.iterdir()) == []


def test_a_platform_without_a_wheel_is_not_built(tmp_path):
    """karellen-llvm-core has Linux wheels only: asking for its Windows wheel must stop with a reason, not a zip."""
    script = _build_script()
    with pytest.raises(script.BuildError) as err:
        script.fetch_wheels(tmp_path, {script.LLVM_PACKAGE[0]: script.LLVM_PACKAGE[1]}, "windows-x64")
    if "could not download" in str(err.value):
        pytest.skip(f"PyPI cannot be reached here: {err.value}")
    assert "no Python 3.11 wheel of karellen-llvm-core" in str(err.value) and "windows-x64" in str(err.value)
    assert "cannot run there" in str(err.value)


def test_blender_validates_the_manifest(tmp_path, run_python):
    tool = _blender_ext_cli()
    if tool is None:
        pytest.skip("bpy (with Blender's extension tool) is not installed")
    [path] = _build_script().build(tmp_path, with_wheels=False)
    _validate(path, tool, run_python)


def _validate(path: Path, tool: Path, run_python) -> None:
    """Blender's own validator on an extension zip."""
    proc = run_python(f"import runpy, sys; sys.argv = ['blender_ext', 'validate', {str(path)!r}]; "
                      f"runpy.run_path({str(tool)!r}, run_name='__main__')")
    assert proc.returncode == 0 and "Success" in proc.stdout, proc.stdout + proc.stderr


def _zip_manifest(zf: zipfile.ZipFile) -> dict:
    """The manifest as Blender reads it: a split build's [build.generated] replaces platforms and wheels."""
    manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
    generated = manifest.get("build", {}).get("generated", {})
    return {**manifest, **{k: generated[k] for k in ("platforms", "wheels") if k in generated}}


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
    [path] = _build_script().build(tmp_path / "dist", with_wheels=False)
    info = _install(path, tmp_path / "blender", run_python)
    assert info["help"] == 0 and info["camera"] == [32, 24]
    assert {"ProCam Camera", "ProCam Projector", "ProCam Surface"} <= set(info["objects"])


@pytest.fixture(scope="module")
def platform_zips(tmp_path_factory):
    """The release zips, one per platform, with real wheels (downloaded once into ~/.cache/procam-wheels)."""
    if _blender_ext_cli() is None:
        pytest.skip("bpy (with Blender's extension tool, which writes the zips) is not installed")
    script = _build_script()
    out = tmp_path_factory.mktemp("dist")
    t = time.perf_counter()
    try:
        paths = script.build(out, update_manifest=False)
    except script.BuildError as exc:
        if "could not download" in str(exc):
            pytest.skip(f"wheels cannot be downloaded here: {exc}")
        raise
    build_s = time.perf_counter() - t
    yield dict(zip(PLATFORMS, paths)), build_s
    shutil.rmtree(out, ignore_errors=True)  # ~560 MB: do not leave it to pytest's tmp rotation


def test_each_platform_zip_passes_blender_validation(platform_zips, run_python):
    """One zip per platform (Blender's split convention) holding exactly that platform's pinned wheels."""
    script = _build_script()
    zips, build_s = platform_zips
    pins = {script._canonical(p): v for p, v in script.pinned_versions(REPO).items()}
    committed = tomllib.loads((REPO / "blender_manifest.toml").read_text(encoding="utf-8"))
    sizes = []
    for platform, path in zips.items():
        assert path.name == f"procam-0.1.0-{platform.replace('-', '_')}.zip"
        _validate(path, _blender_ext_cli(), run_python)
        with zipfile.ZipFile(path) as zf:
            manifest = _zip_manifest(zf)
            shipped = sorted(n for n in zf.namelist() if n.startswith("wheels/"))
        assert manifest["platforms"] == [platform]
        assert sorted(w.removeprefix("./") for w in manifest["wheels"]) == shipped
        assert set(manifest["wheels"]) <= set(committed["wheels"])
        packages = {}
        for wheel in shipped:
            assert platform in script.wheel_platforms(wheel), (platform, wheel)
            name, version = Path(wheel).name.split("-")[:2]
            packages[script._canonical(name)] = version
        assert packages == pins, platform
        sizes.append(f"{platform} {path.stat().st_size / 2 ** 20:.0f} MiB")
    print(f"\nextension zips {', '.join(sizes)}; build {build_s:.1f} s", file=sys.stderr)


def test_build_and_install_with_wheels(platform_zips, tmp_path, run_python):
    """The Linux release zip, installed by Blender itself, registers and runs."""
    pytest.importorskip("bpy")
    path = platform_zips[0]["linux-x64"]
    try:
        info = _install(path, tmp_path / "blender", run_python)
    finally:
        shutil.rmtree(tmp_path, ignore_errors=True)  # ~1 GB unpacked: do not leave it to pytest's tmp rotation
    for package in ("mitsuba", "drjit", "cv2", "pymeshlab", "pygame"):
        assert package in info["packages"], info["packages"]
    assert info["help"] == 0
    print(f"\nlinux-x64 zip installed in {info['seconds']:.1f} s", file=sys.stderr)


# --- LLVM for Dr.Jit's CPU backend, per platform -------------------------------------------------------------


def test_llvm_is_found_in_each_platforms_usual_places(tmp_path, monkeypatch):
    from procam.addon.render import backend

    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    # Homebrew: opt/llvm links the newest keg; an llvm@15 beside it is refused (backward pass aborts).
    assert backend.find_llvm("darwin", ["/opt/homebrew/opt/llvm@15/lib/libLLVM.dylib",
                                        "/opt/homebrew/opt/llvm/lib/libLLVM.dylib"]) == \
        "/opt/homebrew/opt/llvm/lib/libLLVM.dylib"
    assert backend.find_llvm("darwin", ["/opt/homebrew/Cellar/llvm/21.1.5/lib/libLLVM.dylib",
                                        "/opt/homebrew/opt/llvm@18/lib/libLLVM.dylib"]).endswith("21.1.5/lib/libLLVM.dylib")
    assert backend.find_llvm("darwin", ["/opt/homebrew/opt/llvm@15/lib/libLLVM.dylib"]) is None
    # Windows: the official installer's LLVM-C.dll (the only name Dr.Jit loads there); a .so is not for Windows.
    dll = r"C:\Program Files\LLVM\bin\LLVM-C.dll"
    assert backend.find_llvm("win32", ["/usr/lib/llvm-19/lib/libLLVM.so.1", dll]) == dll
    assert backend.find_llvm("win32", []) is None
    # Linux: the newest of the distribution's, never LLVM 15.
    assert backend.find_llvm("linux", ["/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1",
                                       "/usr/lib/llvm-19/lib/libLLVM.so.1"]) == "/usr/lib/llvm-19/lib/libLLVM.so.1"
    # Where the Windows places are: Program Files, Scoop, the PATH.
    for folder in ("pf/LLVM/bin", "path/bin"):
        (tmp_path / folder).mkdir(parents=True)
        (tmp_path / folder / "LLVM-C.dll").touch()
    env = {"ProgramFiles": str(tmp_path / "pf"), "PATH": str(tmp_path / "path" / "bin")}
    assert backend.llvm_candidates("win32", env) == [str(tmp_path / "pf/LLVM/bin/LLVM-C.dll"),
                                                     str(tmp_path / "path/bin/LLVM-C.dll")]
    assert backend.llvm_candidates("win32", {}) == []
    # What to install, per platform.
    assert "brew install llvm" in backend.llvm_help("darwin")
    assert "LLVM-C.dll" in backend.llvm_help("win32") and "llvm-project/releases" in backend.llvm_help("win32")
    assert "libllvm19" in backend.llvm_help("linux") and "karellen-llvm-core" in backend.llvm_help("linux")
    assert all("DRJIT_LIBLLVM_PATH" in backend.llvm_help(p) for p in ("linux", "darwin", "win32"))


def test_missing_llvm_says_what_to_install(run_python):
    proc = run_python("""
        import os, sys
        from procam.addon.render import backend
        from procam.addon.errors import RenderError
        backend.find_llvm = lambda *a, **k: None  # as on a machine without any LLVM
        try:
            backend.mitsuba("llvm_ad_rgb")
        except RenderError as exc:
            assert "mitsuba" not in sys.modules
            print(exc)
        os.environ["DRJIT_LIBLLVM_PATH"] = "/nowhere/libLLVM.so"
        try:
            backend.mitsuba("llvm_ad_rgb")
        except RenderError as exc:
            print(exc)
    """, env={"DRJIT_LIBLLVM_PATH": ""})
    assert proc.returncode == 0, proc.stderr
    first, second = proc.stdout.strip().splitlines()
    assert first.startswith("no LLVM ≥ 16 found") and "libllvm19" in first
    assert "/nowhere/libLLVM.so" in second and "not a file" in second
