"""From a recording to training rays: decoded frames and the batch sampler (design 2, 3.6)."""
