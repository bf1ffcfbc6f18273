"""Ray marching through the occupancy grid and volume rendering of packed samples (docs/method.md 2, 3.1).

samples = march_rays(origins, directions, grid.occupied, grid.spec, near, far, step_size, ...)
sigmas, rgbs = field(samples.positions(origins, directions), directions[samples.ray_indices])
out = composite(sigmas, rgbs, samples, n_rays, background)
"""

from virus_nerf.render.compositing import RenderOutput, composite, opacity_front, scan_depth
from virus_nerf.render.marching import Backend, march_rays, ray_box_interval
from virus_nerf.render.samples import PackedSamples

__all__ = [
    "Backend",
    "PackedSamples",
    "RenderOutput",
    "composite",
    "march_rays",
    "opacity_front",
    "ray_box_interval",
    "scan_depth",
]
