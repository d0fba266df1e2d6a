"""Choosing and loading the Mitsuba variant: ``cuda_ad_rgb`` on a GPU, else ``llvm_ad_rgb`` with LLVM ≥ 16.

Dr.Jit's LLVM backend aborts a backward pass with LLVM 15 ("Cannot select:
fmaximum"), so before Mitsuba is imported we point ``DRJIT_LIBLLVM_PATH`` at
an LLVM ≥ 16: the user's own setting, Debian's ``libllvm19`` (or 16–20), or
the ``karellen-llvm-core`` wheel, which makes the extension self-contained on
machines without root. Import Mitsuba only through :func:`mitsuba`.
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


def _llvm_major(path: str) -> int:
    m = re.search(r"LLVM(?:-|\.so\.)(\d+)", os.path.basename(path))
    return int(m.group(1)) if m else 0


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


def find_llvm() -> str | None:
    """Path of an LLVM ≥ 16 shared library, or None."""
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env and os.path.exists(env):
        return env
    candidates = glob.glob("/usr/lib/x86_64-linux-gnu/libLLVM*.so*") + glob.glob("/usr/lib/llvm-*/lib/libLLVM*.so*")
    candidates += glob.glob("/usr/lib64/libLLVM*.so*") + glob.glob("/opt/homebrew/opt/llvm/lib/libLLVM.dylib")
    good = sorted((p for p in candidates if _llvm_major(p) >= _MIN_LLVM), key=_llvm_major)
    if good:
        return good[-1]
    return _karellen_llvm()


def has_cuda() -> bool:
    """True when an NVIDIA driver library is loadable (Dr.Jit's CUDA backend needs only that)."""
    for name in ("libcuda.so.1", "libcuda.so"):
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
    if variant.startswith("llvm") and "DRJIT_LIBLLVM_PATH" not in os.environ and "mitsuba" not in sys.modules:
        path = find_llvm()
        if path is None:
            raise RenderError(
                "no LLVM ≥ 16 found for Dr.Jit's CPU backend. Install Debian's libllvm19 "
                "(apt-get install libllvm19), or `pip install karellen-llvm-core`, or set DRJIT_LIBLLVM_PATH.")
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
