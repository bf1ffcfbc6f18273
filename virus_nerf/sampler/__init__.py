"""From a recording to training rays: decoded frames and the batch sampler (docs/method.md 2, 3.6)."""

# its public modules; none is imported here, so `import virus_nerf.sampler` loads nothing else
__all__ = ["batch", "frame_cache", "frames", "sensor_rays", "shares"]
