"""The virtual lab: Cycles renders of the Blender rig with injected real-world effects."""
