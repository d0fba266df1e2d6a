#!/usr/bin/env python3
"""Build the ProCam extension: one zip per platform, ``dist/procam-<version>-<platform>.zip``, with its wheels inside.

Usage: ``python scripts/build_extension.py [--out DIR] [--platform P ...] [--wheels-cache DIR]
[--no-wheels] [--with-llvm]`` (also ``procam build-extension``). Standard library only; the zips
are written by Blender's own extension tool, which ships in the bpy wheel (requirements.txt), so
run it with the Python of the README's set-up.

1. For each platform the manifest supports (``platforms`` in ``blender_manifest.toml``:
   linux-x64, windows-x64, macos-arm64), downloads the wheels of the runtime dependencies that
   Blender lacks (:data:`WHEEL_PACKAGES`, at the versions pinned in ``requirements.txt``, for
   CPython 3.11 and that platform's tags, :data:`PLATFORM_TAGS`) into a cache folder, once. A
   package without a wheel for a platform stops the build with a message naming both: ProCam
   cannot run there, so no zip may claim it.
2. Mirrors this machine's wheels into ``wheels/`` beside the manifest (gitignored), so that a
   source checkout linked into Blender's extension folder also works (Blender installs only the
   listed wheels of its own platform, and skips the files that are absent).
3. Rewrites the manifest's ``wheels = [...]`` list to every platform's files.
4. Lays out the code (no tests, scripts, caches or virtual environment), the manifest and the
   wheels in a staging folder and runs ``blender_ext.py build --split-platforms`` on it: Blender's
   per-platform convention, one zip per platform whose manifest ``[build.generated]`` table names
   that platform and its wheels only. Blender writes each zip under a temporary name and renames it.

Blender installs the wheels itself when the extension is installed: nothing is pip-installed
at run time (the largest class of complaints about mitsuba-blender).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import platform as _platform
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = "blender_manifest.toml"
#: Runtime dependencies shipped as wheels (bpy is Blender itself; Blender ships numpy).
WHEEL_PACKAGES = ("drjit", "mitsuba", "opencv-contrib-python-headless", "pymeshlab", "pygame-ce")
#: Optional LLVM for Dr.Jit's CPU backend on machines without an LLVM >= 16 (docs/developer.md, dependency facts).
#: PyPI has it for Linux x86-64 only, so it goes into the linux-x64 zip only.
LLVM_PACKAGE = ("karellen-llvm-core", "23.1.4.post8")
LLVM_PLATFORM = "linux-x64"
PYTHON_VERSION = "3.11"
#: pip ``--platform`` tags per Blender platform. pip does not imply older manylinux tags when several are
#: wanted, so list them; a macOS tag implies the older macOS versions and universal2. macOS 13 because
#: opencv-contrib-python-headless 4.11 has arm64 wheels for macOS >= 13 only (the others need 11).
PLATFORM_TAGS: dict[str, tuple[str, ...]] = {
    "linux-x64": ("manylinux_2_35_x86_64", "manylinux_2_28_x86_64", "manylinux_2_27_x86_64",
                  "manylinux_2_17_x86_64", "manylinux2014_x86_64"),
    "windows-x64": ("win_amd64",),
    "macos-arm64": ("macosx_13_0_arm64",),
}
#: What goes into the zip (relative to the repository root).
INCLUDE = ("__init__.py", "blender_registration.py", "addon", "operators", "panels")
BLENDER_EXT = "scripts/addons_core/bl_pkg/cli/blender_ext.py"
_SKIP_DIRS = {"__pycache__", ".pytest_cache", ".mypy_cache"}
_SKIP_SUFFIXES = {".pyc", ".pyo"}


class BuildError(Exception):
    """The build cannot go on; the message says what to do."""


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "_", name).lower()


def pinned_versions(root: Path = ROOT, packages: tuple[str, ...] = WHEEL_PACKAGES) -> dict[str, str]:
    """``{package: version}`` for ``packages`` from ``requirements.txt`` (each must be pinned with ==)."""
    req = root / "requirements.txt"
    pins: dict[str, str] = {}
    for line in req.read_text(encoding="utf-8").splitlines():
        line = line.split("#", 1)[0].strip()
        m = re.fullmatch(r"([A-Za-z0-9._-]+)\s*==\s*([A-Za-z0-9._+!-]+)", line)
        if m:
            pins[_canonical(m.group(1))] = m.group(2)
    missing = [p for p in packages if _canonical(p) not in pins]
    if missing:
        raise BuildError(f"{req} must pin {', '.join(missing)} with '=='")
    return {p: pins[_canonical(p)] for p in packages}


def wheel_platforms(filename: str) -> set[str]:
    """Blender platforms a wheel file serves, from its platform tags (as Blender's own tool reads them)."""
    found: set[str] = set()
    for tag in Path(filename).stem.split("-")[-1].split("."):
        if tag == "any":
            found |= set(PLATFORM_TAGS)
        elif "linux" in tag and tag.endswith("x86_64"):
            found.add("linux-x64")
        elif tag == "win_amd64":
            found.add("windows-x64")
        elif tag.startswith("macosx_") and tag.endswith(("_arm64", "_universal2")):
            found.add("macos-arm64")
    return found


def this_platform() -> str:
    """This machine as a Blender platform name (linux-x64, windows-x64, macos-arm64, …)."""
    system = {"darwin": "macos"}.get(_platform.system().lower(), _platform.system().lower())
    machine = {"x86_64": "x64", "amd64": "x64", "aarch64": "arm64"}.get(_platform.machine().lower(),
                                                                        _platform.machine().lower())
    return f"{system}-{machine}"


def _cached_wheel(cache: Path, package: str, version: str, platform: str) -> Path | None:
    prefix = f"{_canonical(package)}-{version}-".lower()
    found = sorted(p for p in cache.glob("*.whl")
                   if p.name.lower().startswith(prefix) and platform in wheel_platforms(p.name))
    return found[-1] if found else None


def fetch_wheels(cache: Path, pins: dict[str, str], platform: str, *, python: str = sys.executable) -> list[Path]:
    """Wheel files of ``pins`` for the Blender ``platform`` in ``cache``, downloading the missing ones with pip."""
    if platform not in PLATFORM_TAGS:
        raise BuildError(f"unknown platform {platform!r}: ProCam builds for {', '.join(PLATFORM_TAGS)}")
    cache.mkdir(parents=True, exist_ok=True)
    missing = [f"{p}=={v}" for p, v in pins.items() if _cached_wheel(cache, p, v, platform) is None]
    if missing:
        cmd = [python, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", "--disable-pip-version-check",
               "--python-version", PYTHON_VERSION, "-d", str(cache)]
        for tag in PLATFORM_TAGS[platform]:
            cmd += ["--platform", tag]
        print(f"build-extension: downloading {platform} wheels of {', '.join(missing)} into {cache}", file=sys.stderr)
        proc = subprocess.run(cmd + missing, capture_output=True, text=True)
        if proc.returncode != 0:
            absent = re.search(r"No matching distribution found for (\S+)", proc.stderr)
            if absent:
                raise BuildError(
                    f"PyPI has no Python {PYTHON_VERSION} wheel of {absent.group(1)} for {platform} "
                    f"({', '.join(PLATFORM_TAGS[platform])}): ProCam cannot run there. Take {platform} out of "
                    f"'platforms' in {MANIFEST} (or build the others with --platform), or pin a version that has one")
            tail = "\n".join(line for line in proc.stderr.splitlines() if "is ignored" not in line)[-2000:]
            raise BuildError(f"pip could not download the wheels (network or index?):\n{tail}")
    wheels = []
    for p, v in pins.items():
        w = _cached_wheel(cache, p, v, platform)
        if w is None:
            raise BuildError(f"no Python {PYTHON_VERSION} {platform} wheel of {p}=={v} in {cache}")
        wheels.append(w)
    return sorted(wheels, key=lambda w: w.name)


def _link(src: Path, dest: Path) -> None:
    # A hard link costs nothing; across file systems a symbolic link (Blender's tool reads through it); else a copy.
    for make in (os.link, os.symlink, shutil.copy2):
        try:
            make(src, dest)
            return
        except OSError:
            continue


def sync_wheels_folder(root: Path, wheels: list[Path]) -> list[Path]:
    """Make ``root/wheels`` hold exactly ``wheels`` (hard links where possible); returns the new paths."""
    folder = root / "wheels"
    folder.mkdir(exist_ok=True)
    wanted = {w.name for w in wheels}
    for old in folder.glob("*.whl"):
        if old.name not in wanted:
            old.unlink()
    out = []
    for w in wheels:
        dest = folder / w.name
        if not dest.exists() or dest.stat().st_size != w.stat().st_size:
            dest.unlink(missing_ok=True)
            try:
                os.link(w, dest)
            except OSError:
                shutil.copy2(w, dest)
        out.append(dest)
    return out


def manifest_with_wheels(text: str, wheel_names: list[str]) -> str:
    """The manifest text with its ``wheels = [...]`` list replaced (removed when empty)."""
    pattern = re.compile(r"^wheels\s*=\s*\[[^\]]*\]\s*?\n", re.MULTILINE)
    block = "".join(f'  "./wheels/{n}",\n' for n in wheel_names)
    new = f"wheels = [\n{block}]\n" if wheel_names else ""
    if pattern.search(text):
        return pattern.sub(lambda _: new, text, count=1)
    if not wheel_names:
        return text
    # No list yet: put it before the first table so that it stays a top-level key.
    m = re.search(r"^\[", text, re.MULTILINE)
    at = m.start() if m else len(text)
    return text[:at] + new + "\n" + text[at:]


def manifest_with_platforms(text: str, platforms: list[str]) -> str:
    """The manifest text with its ``platforms = [...]`` list replaced."""
    new = "platforms = [" + ", ".join(f'"{p}"' for p in platforms) + "]\n"
    text, n = re.subn(r"^platforms\s*=\s*\[[^\]]*\]\s*?\n", lambda _: new, text, count=1, flags=re.MULTILINE)
    if n != 1:
        raise BuildError(f"{MANIFEST} needs a 'platforms = [...]' list")
    return text


def _write_atomic(path: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _source_files(root: Path) -> list[Path]:
    files: list[Path] = []
    for name in INCLUDE:
        path = root / name
        if path.is_file():
            files.append(path)
        elif path.is_dir():
            for dirpath, dirnames, filenames in os.walk(path):
                dirnames[:] = sorted(d for d in dirnames if d not in _SKIP_DIRS and not d.startswith("."))
                for f in sorted(filenames):
                    if Path(f).suffix not in _SKIP_SUFFIXES and not f.startswith("."):
                        files.append(Path(dirpath) / f)
        else:
            raise BuildError(f"{path} is missing: run the build from a complete ProCam source tree")
    return files


def blender_ext_tool() -> Path:
    """Blender's extension command-line tool, from the bpy wheel of this Python (bpy is not imported)."""
    spec = importlib.util.find_spec("bpy")
    if spec is not None and spec.submodule_search_locations:
        found = sorted(Path(spec.submodule_search_locations[0]).glob(f"*/{BLENDER_EXT}"))
        if found:
            return found[-1]
    raise BuildError(f"the zips are written by Blender's extension tool, which ships in the bpy wheel, "
                     f"and {sys.executable} has no bpy: run `procam build-extension` (or this script with "
                     ".venv/bin/python) after the README's set-up")


def _blender_build(tool: Path, stage: Path, out: Path, *, split: bool, output_file: Path | None = None) -> None:
    cmd = [sys.executable, str(tool), "build", "--source-dir", str(stage)]
    cmd += ["--output-filepath", str(output_file)] if output_file else ["--output-dir", str(out)]
    if split:
        cmd.append("--split-platforms")
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise BuildError(f"Blender's extension build failed:\n{(proc.stdout + proc.stderr)[-2000:]}")


def build(out_dir: Path | None = None, *, wheels_cache: Path | None = None, with_wheels: bool = True,
          with_llvm: bool = False, root: Path = ROOT, update_manifest: bool = True,
          platforms: list[str] | None = None) -> list[Path]:
    """Build the extension zips (one per platform; one ``-no-wheels`` zip without wheels) and return their paths."""
    manifest_path = root / MANIFEST
    text = manifest_path.read_text(encoding="utf-8")
    try:
        manifest = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise BuildError(f"{manifest_path} is not valid TOML: {exc}") from None
    version, ext_id, supported = manifest.get("version"), manifest.get("id"), manifest.get("platforms")
    if not version or not ext_id or not supported:
        raise BuildError(f"{manifest_path} needs 'id', 'version' and 'platforms'")
    wanted = list(dict.fromkeys(platforms or supported))
    unsupported = [p for p in wanted if p not in supported]
    if unsupported:
        raise BuildError(f"{', '.join(unsupported)} is not among the platforms of {MANIFEST} ({', '.join(supported)})")
    tool = blender_ext_tool()

    by_platform: dict[str, list[Path]] = {}
    if with_wheels:
        cache = Path(wheels_cache or os.environ.get("PROCAM_WHEELS_CACHE") or Path.home() / ".cache" / "procam-wheels")
        pins = pinned_versions(root)
        for plat in wanted:
            plat_pins = dict(pins)
            if with_llvm and plat == LLVM_PLATFORM:
                plat_pins[LLVM_PACKAGE[0]] = LLVM_PACKAGE[1]
            by_platform[plat] = fetch_wheels(cache, plat_pins, plat)
        if this_platform() in by_platform:
            sync_wheels_folder(root, by_platform[this_platform()])
    names = list(dict.fromkeys(w.name for plat in wanted for w in by_platform.get(plat, [])))
    staged = manifest_with_platforms(manifest_with_wheels(text, names), wanted)
    if (with_wheels and not with_llvm and update_manifest and set(wanted) == set(supported)
            and (committed := manifest_with_wheels(text, names)) != text):
        _write_atomic(manifest_path, committed.encode("utf-8"))  # keep the committed list true

    out = Path(out_dir) if out_dir else root / "dist"
    out.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{ext_id}-stage-", dir=out))
    try:
        (stage / MANIFEST).write_text(staged, encoding="utf-8")
        for f in _source_files(root):
            dest = stage / f.relative_to(root)
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(f, dest)
        if with_wheels:
            (stage / "wheels").mkdir()
            for plat in wanted:
                for w in by_platform[plat]:
                    if not (stage / "wheels" / w.name).exists():
                        _link(w, stage / "wheels" / w.name)
            _blender_build(tool, stage, out, split=True)
            targets = [out / f"{ext_id}-{version}-{p.replace('-', '_')}.zip" for p in wanted]
        else:
            targets = [out / f"{ext_id}-{version}-no-wheels.zip"]
            _blender_build(tool, stage, out, split=False, output_file=targets[0])
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    missing = [t for t in targets if not t.is_file()]
    if missing:
        raise BuildError(f"Blender's extension build did not write {', '.join(map(str, missing))}")
    return targets


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: dist/ in the source tree)")
    parser.add_argument("--platform", action="append", default=None, choices=sorted(PLATFORM_TAGS),
                        help="build only this platform's zip (repeatable; default: every platform in "
                             f"{MANIFEST})")
    parser.add_argument("--wheels-cache", type=Path, default=None,
                        help="where downloaded wheels are kept between builds "
                             "(default: $PROCAM_WHEELS_CACHE or ~/.cache/procam-wheels)")
    parser.add_argument("--no-wheels", action="store_true",
                        help="one zip without the dependency wheels, for Blenders that already have them")
    parser.add_argument("--with-llvm", action="store_true",
                        help=f"also ship {LLVM_PACKAGE[0]} (LLVM for Dr.Jit's CPU backend, ~34 MB) in the "
                             f"{LLVM_PLATFORM} zip, for machines without an LLVM >= 16 (PyPI has it for Linux only)")


def run(args: argparse.Namespace) -> list[Path]:
    paths = build(args.out, wheels_cache=args.wheels_cache, with_wheels=not args.no_wheels,
                  with_llvm=args.with_llvm, platforms=args.platform)
    for path in paths:
        print(f"{path} ({path.stat().st_size / 2**20:.1f} MiB)")
    return paths


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="build_extension", description=__doc__.split("\n\n")[0])
    add_arguments(parser)
    try:
        run(parser.parse_args(argv))
    except BuildError as exc:
        print(f"build-extension: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
