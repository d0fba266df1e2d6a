"""Blender operators, one per module: validate → call one engine function → write into the scene → report.

Imported only by ``blender_registration`` (they need ``bpy``).
"""
