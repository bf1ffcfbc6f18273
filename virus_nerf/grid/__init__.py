"""Occupancy grids that decide where the ray marcher takes samples (design 3.3, 3.4)."""
