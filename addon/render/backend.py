"""Choosing and loading the Mitsuba variant: ``cuda_ad_rgb`` on a GPU, else ``llvm_ad_rgb`` with LLVM ≥ 16.

Dr.Jit's LLVM backend aborts a backward pass with LLVM 15 ("Cannot select:
fmaximum"), and Dr.Jit itself looks for LLVM only under one name and one
folder per platform, so before Mitsuba is imported we point
``DRJIT_LIBLLVM_PATH`` at an LLVM ≥ 16 found in the usual places of the
platform (:data:`LLVM_LOCATIONS`): the user's own setting, then on Linux the
distribution's ``libllvm19`` (or 16–20) or the ``karellen-llvm-core`` wheel
(self-contained, no root), on macOS Homebrew's ``llvm``, on Windows the
official LLVM installer's ``LLVM-C.dll``. When none is found the error says
what to install on that platform (:func:`llvm_help`). Import Mitsuba only
through :func:`mitsuba`.
"""

from __future__ import annotations

import ctypes
import glob
import os
import re
import sys
from pathlib import Path
from types import ModuleType

from ..errors import RenderError

_MIN_LLVM = 16

#: Where each platform's usual installs put the LLVM library Dr.Jit loads (glob patterns, keyed by
#: ``sys.platform``; ``{NAME}`` is an environment variable). Linux: Debian/Ubuntu and Fedora packages.
#: macOS: Homebrew on Apple silicon and on Intel (``opt/llvm`` links the newest keg). Windows: the
#: official installer (also what winget and Chocolatey install) and Scoop; the PATH is searched too.
LLVM_LOCATIONS: dict[str, tuple[str, ...]] = {
    "linux": ("/usr/lib/x86_64-linux-gnu/libLLVM*.so*", "/usr/lib/llvm-*/lib/libLLVM*.so*",
              "/usr/lib64/libLLVM*.so*", "/usr/lib/libLLVM*.so*"),
    "darwin": ("/opt/homebrew/opt/llvm/lib/libLLVM.dylib", "/opt/homebrew/opt/llvm@*/lib/libLLVM.dylib",
               "/usr/local/opt/llvm/lib/libLLVM.dylib", "/usr/local/opt/llvm@*/lib/libLLVM.dylib"),
    "win32": ("{ProgramFiles}/LLVM/bin/LLVM-C.dll", "{ProgramW6432}/LLVM/bin/LLVM-C.dll",
              "{USERPROFILE}/scoop/apps/llvm/current/bin/LLVM-C.dll"),
}
#: The library file Dr.Jit can load on each platform (the C API; LLVM-C.dll on Windows).
_LLVM_NAME = {"linux": r"libLLVM.*\.so.*", "darwin": r"libLLVM.*\.dylib", "win32": r"LLVM-C\.dll"}


def _platform_key(platform: str) -> str:
    return "linux" if platform.startswith("linux") else platform


def _llvm_major(path: str) -> int:
    """LLVM major version read off the file name or its folder (0 when the path does not say)."""
    majors = []
    # Homebrew's and Debian's unversioned names are links to versioned files or folders: read both.
    for p in {path, os.path.realpath(path) if os.path.exists(path) else path}:
        p = p.replace("\\", "/")
        m = re.search(r"LLVM(?:-|\.so\.)(\d+)", os.path.basename(p))
        if m:
            majors.append(int(m.group(1)))
        # /usr/lib/llvm-19/…, Homebrew's …/Cellar/llvm/21.1.5/… and …/llvm@18/…
        majors += [int(v) for v in re.findall(r"/llvm(?:-|@|/)(\d+)(?=[./])", p, re.IGNORECASE)]
    return max(majors, default=0)


def llvm_candidates(platform: str = sys.platform, env: dict[str, str] | None = None) -> list[str]:
    """Existing files in the usual LLVM places of ``platform`` (see :data:`LLVM_LOCATIONS`)."""
    env = dict(os.environ if env is None else env)
    key = _platform_key(platform)
    found: list[str] = []
    for pattern in LLVM_LOCATIONS.get(key, ()):
        try:
            pattern = pattern.format_map(env)
        except KeyError:  # that variable is not set here, so that place does not exist
            continue
        found += sorted(glob.glob(pattern))
    if key == "win32":
        # The official installer offers to put its bin folder on the PATH (Dr.Jit also relies on that).
        for folder in env.get("PATH", "").split(os.pathsep):
            dll = os.path.join(folder, "LLVM-C.dll")
            if folder and os.path.isfile(dll):
                found.append(dll)
    return list(dict.fromkeys(found))


def pick_llvm(platform: str, candidates: list[str]) -> str | None:
    """The best of ``candidates`` for ``platform``: the newest LLVM ≥ 16, else one whose version the path does not tell.

    Files of another platform's name are ignored; a known LLVM < 16 is refused (the backward pass aborts).
    """
    name = _LLVM_NAME.get(_platform_key(platform))
    if name is None:
        return None
    usable = [p for p in candidates if re.fullmatch(name, os.path.basename(p.replace("\\", "/")), re.IGNORECASE)]
    known = sorted((p for p in usable if _llvm_major(p) >= _MIN_LLVM), key=_llvm_major)
    if known:
        return known[-1]
    unknown = [p for p in usable if _llvm_major(p) == 0]
    return unknown[0] if unknown else None


def llvm_help(platform: str = sys.platform) -> str:
    """What to install on ``platform`` so that Dr.Jit's CPU backend has an LLVM ≥ 16."""
    key = _platform_key(platform)
    if key == "darwin":
        how = ("Install LLVM with Homebrew: `brew install llvm` (ProCam then finds "
               "/opt/homebrew/opt/llvm/lib/libLLVM.dylib)")
    elif key == "win32":
        how = ("Install LLVM 16 or later for Windows (x64) from https://github.com/llvm/llvm-project/releases "
               "(LLVM-<version>-win64.exe, or `winget install LLVM.LLVM`); ProCam then finds "
               "C:\\Program Files\\LLVM\\bin\\LLVM-C.dll")
    else:
        how = ("Install your distribution's LLVM library (Debian/Ubuntu: `sudo apt-get install libllvm19`; "
               "Fedora: `sudo dnf install llvm-libs`), or without root `pip install karellen-llvm-core` into "
               "Blender's Python (or install the extension built with `procam build-extension --with-llvm`)")
    return f"{how}, or set DRJIT_LIBLLVM_PATH to the LLVM library, then restart Blender."


def _karellen_llvm() -> str | None:
    for base in map(Path, sys.path):
        lib = base / "karellen" / "llvm" / "lib"
        if not lib.is_dir():
            continue
        libs = sorted(lib.glob("libLLVM.so.*"))
        if not libs:
            continue
        # libLLVM from this wheel links against its own libc++; load those first, globally.
        triple = lib / "x86_64-unknown-linux-gnu"
        for name in ("libunwind.so.1.0", "libc++abi.so.1.0", "libc++.so.1.0"):
            if (triple / name).exists():
                ctypes.CDLL(str(triple / name), mode=ctypes.RTLD_GLOBAL)
        return str(libs[-1])
    return None


def find_llvm(platform: str = sys.platform, candidates: list[str] | None = None) -> str | None:
    """Path of an LLVM ≥ 16 shared library for ``platform`` (default: the usual places here), or None."""
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env and os.path.exists(env):
        return env
    found = pick_llvm(platform, llvm_candidates(platform) if candidates is None else candidates)
    if found is None and _platform_key(platform) == "linux" and candidates is None:
        return _karellen_llvm()  # the only LLVM wheel on PyPI; Linux x86-64 only
    return found


def has_cuda() -> bool:
    """True when an NVIDIA driver library is loadable (Dr.Jit's CUDA backend needs only that)."""
    # Windows names the driver library nvcuda.dll; macOS has no CUDA.
    for name in ("libcuda.so.1", "libcuda.so", "nvcuda.dll"):
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            continue
    return False


def default_variant() -> str:
    """``PROCAM_VARIANT`` if set, else ``cuda_ad_rgb`` when a GPU is present, else ``llvm_ad_rgb``."""
    env = os.environ.get("PROCAM_VARIANT")
    if env:
        return env
    return "cuda_ad_rgb" if has_cuda() else "llvm_ad_rgb"


def mitsuba(variant: str | None = None) -> ModuleType:
    """Import Mitsuba with a working backend and set the variant; raises RenderError with what to do."""
    variant = variant or default_variant()
    if variant.startswith("llvm") and "mitsuba" not in sys.modules:
        given = os.environ.get("DRJIT_LIBLLVM_PATH")
        if given and os.path.dirname(given) and not os.path.isfile(given):  # a bare name is the loader's to find
            raise RenderError(f"DRJIT_LIBLLVM_PATH is {given!r}, which is not a file. {llvm_help()}")
        if not given:
            path = find_llvm()
            if path is None:
                raise RenderError(f"no LLVM ≥ 16 found for Dr.Jit's CPU backend (variant {variant}). {llvm_help()}")
            os.environ["DRJIT_LIBLLVM_PATH"] = path
    try:
        import mitsuba as mi
    except ImportError as exc:
        raise RenderError(f"Mitsuba is not installed ({exc}); run the set-up command from the README") from None
    try:
        if mi.variant() != variant:
            mi.set_variant(variant)
    except (ImportError, AttributeError, RuntimeError) as exc:
        raise RenderError(f"Mitsuba variant {variant!r} is not usable here: {exc}") from None
    return mi
