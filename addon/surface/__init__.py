"""Projection surfaces: the textured-mesh model, built-in lab shapes, and (later) RGBD reconstruction."""
