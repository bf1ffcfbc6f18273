"""2D scan evaluation (docs/method.md 6): GT scans from the LiDAR map, sensor and model scans, NND metrics.

Import from the modules (`virus_nerf.evaluation.evaluate`, `.metrics`, `.gt`, ...): none is
imported here, so that `virus_nerf.evaluation.config` (a run's config, its flags, `train --help`)
loads nothing heavy (D110), and plots (matplotlib) and the `sensors` command load on demand.
"""

# its public modules; none is imported here, so `import virus_nerf.evaluation` loads nothing else
__all__ = ["command", "config", "evaluate", "gt", "metrics", "plots", "safety", "scans", "sensor_scans",
           "testpoints", "trajectory"]
