"""Sim-to-real diagnosis: effect models, fitting, attribution, report."""
