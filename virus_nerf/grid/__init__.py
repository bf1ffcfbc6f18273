"""Occupancy grids that decide where the ray marcher takes samples (docs/method.md 3.3, 3.4)."""

# its public modules; none is imported here, so `import virus_nerf.grid` loads nothing else
__all__ = ["base", "extent", "ngp", "ngp_config", "sensor_model", "virus", "virus_config"]
