"""Native libraries whose load order matters, in one place.

Two real constraints, both measured:

* pymeshlab and bpy both bundle Embree. Once pymeshlab's is loaded, a later
  ``import bpy`` in the same process fails ("undefined symbol
  rtcGetSceneTraversable"), while the other order works; inside Blender bpy
  is always first. :func:`import_pymeshlab` loads bpy first when it is
  installed. This is the one engine module outside ``blender/`` and ``lab/``
  that imports bpy, and only for this.
* pymeshlab loads its filter plugins when the first ``MeshSet`` is made; when
  that happens in a worker thread the process aborts at exit with a corrupted
  heap (``malloc_consolidate(): unaligned fastbin chunk``, exit 134, after a
  surface reconstruction in a thread; none when a ``MeshSet`` was made on the
  main thread first). :func:`prepare_worker_libraries` does that on the main
  thread before the UI starts a job that calibrates.
* numpy's OpenBLAS keeps its threads spinning after every product. Where
  ProCam runs many small products (the diagnosis's fits: a Jacobian's
  17 × 240,000 product a step) that spinning took the second of two cores
  in system time (30 s of a 31 s selection) for no gain, and it starves
  threads of our own. :func:`blas_threads` holds it to one thread there.
"""

from __future__ import annotations

import ctypes
import glob
import os
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import ModuleType


def import_pymeshlab() -> ModuleType:
    """Import pymeshlab, loading bpy first when it is installed (module doc)."""
    try:
        import bpy  # noqa: F401
    except ImportError:
        pass
    import pymeshlab

    return pymeshlab


def prepare_worker_libraries() -> None:
    """Initialise, on the main thread, native libraries that a worker thread must not initialise first."""
    import_pymeshlab().MeshSet()


#: OpenBLAS's thread-count functions under the names its builds export (numpy 1.26's 64-bit-integer build, numpy
#: 2's scipy-openblas, a system OpenBLAS).
_BLAS_SETTERS = (("openblas_set_num_threads64_", "openblas_get_num_threads64_"),
                 ("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
                 ("openblas_set_num_threads", "openblas_get_num_threads"))
_blas_lock = threading.Lock()
_blas_users = 0
_blas_before: list[tuple[Callable[[int], None], int]] = []


def _openblas() -> list[tuple[Callable[[int], None], Callable[[], int]]]:
    """The (set, get) thread-count functions of each OpenBLAS numpy has loaded (none found: an empty list)."""
    import numpy

    root = os.path.dirname(os.path.dirname(numpy.__file__))
    paths = sorted({*glob.glob(os.path.join(root, "numpy.libs", "*openblas*")),
                    *glob.glob(os.path.join(os.path.dirname(numpy.__file__), ".dylibs", "*openblas*"))})
    found = []
    for path in paths:
        try:  # the copy numpy loaded, not a second one (RTLD_NOLOAD where the platform has it)
            lib = ctypes.CDLL(path, mode=getattr(os, "RTLD_NOLOAD", 0) | getattr(os, "RTLD_LAZY", 0))
        except OSError:
            continue
        for set_name, get_name in _BLAS_SETTERS:
            setter, getter = getattr(lib, set_name, None), getattr(lib, get_name, None)
            if setter is not None and getter is not None:
                setter.argtypes, setter.restype, getter.restype = [ctypes.c_int], None, ctypes.c_int
                found.append((setter, getter))
                break
    return found


@contextmanager
def blas_threads(count: int) -> Iterator[None]:
    """numpy's OpenBLAS held to ``count`` threads inside the block (module doc), then set back; nested and
    concurrent blocks share one setting, restored when the last leaves. Without an OpenBLAS it finds (another
    BLAS, another platform's layout) it changes nothing."""
    global _blas_users
    with _blas_lock:
        if _blas_users == 0:
            _blas_before[:] = [(setter, getter()) for setter, getter in _openblas()]
            for setter, _ in _blas_before:
                setter(count)
        _blas_users += 1
    try:
        yield
    finally:
        with _blas_lock:
            _blas_users -= 1
            if _blas_users == 0:
                for setter, before in _blas_before:
                    setter(before)
                _blas_before.clear()
