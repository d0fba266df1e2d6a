"""ProCam: projector compensation with differentiable rendering, as a Blender extension.

Inside Blender this folder is the extension (``bl_ext.<repo>.procam``); outside
Blender it is the Python package ``procam``. Importing it pulls in nothing
heavy: ``register()`` imports the Blender side only when Blender calls it.
"""


def register() -> None:
    from . import blender_registration

    blender_registration.register()


def unregister() -> None:
    from . import blender_registration

    blender_registration.unregister()
