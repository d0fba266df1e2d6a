#!/usr/bin/env python3
"""Build the ProCam extension zip: ``dist/procam-<version>.zip`` with its dependency wheels inside.

Usage: ``python scripts/build_extension.py [--out DIR] [--wheels-cache DIR] [--no-wheels]``
(also ``procam build-extension``). Standard library only, so it runs with any
Python 3.11 that has pip.

1. Downloads the wheels of the runtime dependencies that Blender lacks
   (:data:`WHEEL_PACKAGES`, at the versions pinned in ``requirements.txt``,
   for CPython 3.11 on manylinux x86-64) into a cache folder, once.
2. Mirrors them into ``wheels/`` beside the manifest (gitignored), so that a
   source checkout linked into Blender's extension folder also works.
3. Rewrites the manifest's ``wheels = [...]`` list to exactly those files.
4. Zips the manifest, the code and the wheels (no tests, scripts, caches or
   virtual environment) under a temporary name and renames it into place.

Blender installs the wheels itself when the extension is installed: nothing is
pip-installed at run time (the largest class of complaints about
mitsuba-blender).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = "blender_manifest.toml"
#: Runtime dependencies shipped as wheels (bpy is Blender itself; Blender ships numpy).
WHEEL_PACKAGES = ("drjit", "mitsuba", "opencv-contrib-python-headless", "pymeshlab")
#: Optional LLVM for Dr.Jit's CPU backend on machines without an LLVM >= 16 (DESIGN.md §4).
LLVM_PACKAGE = ("karellen-llvm-core", "23.1.4.post8")
PYTHON_VERSION = "3.11"
#: pip's --platform does not imply older manylinux tags when several are wanted, so list them.
PLATFORMS = ("manylinux_2_35_x86_64", "manylinux_2_28_x86_64", "manylinux_2_27_x86_64",
             "manylinux_2_17_x86_64", "manylinux2014_x86_64")
#: What goes into the zip (relative to the repository root).
INCLUDE = ("__init__.py", "blender_registration.py", "addon", "operators", "panels")
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


def _cached_wheel(cache: Path, package: str, version: str) -> Path | None:
    prefix = f"{_canonical(package)}-{version}-"
    found = sorted(p for p in cache.glob("*.whl") if p.name.lower().startswith(prefix.lower()))
    return found[-1] if found else None


def fetch_wheels(cache: Path, pins: dict[str, str], *, python: str = sys.executable) -> list[Path]:
    """Wheel files for ``pins`` in ``cache``, downloading the missing ones with pip."""
    cache.mkdir(parents=True, exist_ok=True)
    missing = [f"{p}=={v}" for p, v in pins.items() if _cached_wheel(cache, p, v) is None]
    if missing:
        cmd = [python, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", "--disable-pip-version-check",
               "--python-version", PYTHON_VERSION, "-d", str(cache)]
        for tag in PLATFORMS:
            cmd += ["--platform", tag]
        print(f"build-extension: downloading {', '.join(missing)} into {cache}", file=sys.stderr)
        proc = subprocess.run(cmd + missing, capture_output=True, text=True)
        if proc.returncode != 0:
            tail = "\n".join(line for line in proc.stderr.splitlines() if "is ignored" not in line)[-2000:]
            raise BuildError(f"pip could not download the wheels (network or index?):\n{tail}")
    wheels = []
    for p, v in pins.items():
        w = _cached_wheel(cache, p, v)
        if w is None:
            raise BuildError(f"no Python {PYTHON_VERSION} manylinux x86-64 wheel of {p}=={v} in {cache}")
        wheels.append(w)
    return sorted(wheels, key=lambda w: w.name)


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


def build(out_dir: Path | None = None, *, wheels_cache: Path | None = None, with_wheels: bool = True,
          with_llvm: bool = False, root: Path = ROOT, update_manifest: bool = True) -> Path:
    """Build the extension zip and return its path."""
    manifest_path = root / MANIFEST
    text = manifest_path.read_text(encoding="utf-8")
    try:
        manifest = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise BuildError(f"{manifest_path} is not valid TOML: {exc}") from None
    version, ext_id = manifest.get("version"), manifest.get("id")
    if not version or not ext_id:
        raise BuildError(f"{manifest_path} needs 'id' and 'version'")

    wheel_files: list[Path] = []
    if with_wheels:
        cache = Path(wheels_cache or os.environ.get("PROCAM_WHEELS_CACHE") or Path.home() / ".cache" / "procam-wheels")
        pins = pinned_versions(root)
        if with_llvm:
            pins[LLVM_PACKAGE[0]] = LLVM_PACKAGE[1]
        wheel_files = sync_wheels_folder(root, fetch_wheels(cache, pins))
    names = [w.name for w in wheel_files]
    zipped_manifest = manifest_with_wheels(text, names)
    if with_wheels and not with_llvm and update_manifest and zipped_manifest != text:
        _write_atomic(manifest_path, zipped_manifest.encode("utf-8"))  # keep the committed list true

    out = Path(out_dir) if out_dir else root / "dist"
    out.mkdir(parents=True, exist_ok=True)
    suffix = "" if with_wheels else "-no-wheels"
    target = out / f"{ext_id}-{version}{suffix}.zip"
    fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=".zip", dir=out)
    os.close(fd)
    try:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            zf.writestr(MANIFEST, zipped_manifest)
            for f in _source_files(root):
                zf.write(f, f.relative_to(root).as_posix())
            for w in wheel_files:
                # Wheels are zips already: storing them is as small and much faster.
                zf.write(w, f"wheels/{w.name}", compress_type=zipfile.ZIP_STORED)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o644 & ~umask)  # mkstemp makes it private; a release zip is an ordinary file
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return target


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: dist/ in the source tree)")
    parser.add_argument("--wheels-cache", type=Path, default=None,
                        help="where downloaded wheels are kept between builds "
                             "(default: $PROCAM_WHEELS_CACHE or ~/.cache/procam-wheels)")
    parser.add_argument("--no-wheels", action="store_true",
                        help="leave the dependency wheels out (a small zip for Blenders that already have them)")
    parser.add_argument("--with-llvm", action="store_true",
                        help=f"also ship {LLVM_PACKAGE[0]} (LLVM for Dr.Jit's CPU backend, ~34 MB) for machines "
                             "without an LLVM >= 16")


def run(args: argparse.Namespace) -> Path:
    path = build(args.out, wheels_cache=args.wheels_cache, with_wheels=not args.no_wheels, with_llvm=args.with_llvm)
    print(f"{path} ({path.stat().st_size / 2**20:.1f} MiB)")
    return path


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
