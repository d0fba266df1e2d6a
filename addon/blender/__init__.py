"""The engine's bpy side: rig objects in a Blender scene (``rig``) and calibration ``.blend`` files (``blend_file``).

The only engine package besides ``lab`` that imports bpy; everything else runs without Blender.
"""
