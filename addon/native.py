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
"""

from __future__ import annotations

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
