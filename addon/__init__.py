"""ProCam engine: everything that is not Blender UI (rig, capture, render, stages, lab, gap)."""
