"""Sidebar panels (View3D ▸ Sidebar ▸ ProCam): they only draw state and buttons.

Imported only by ``blender_registration`` (they need ``bpy``).
"""
