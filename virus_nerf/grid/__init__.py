"""Occupancy grids that decide where the ray marcher takes samples (docs/method.md 3.3, 3.4)."""
