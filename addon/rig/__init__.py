"""Camera and projector models, and the one place that converts between OpenCV, Blender and Mitsuba frames."""
