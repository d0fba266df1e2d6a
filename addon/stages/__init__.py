"""The three optimisations of the method: projector pose (A), warp (B), projector input (C)."""
