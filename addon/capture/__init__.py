"""Capture sets (folder + capture.json), projected patterns, and capture devices (lab, folder, live)."""
