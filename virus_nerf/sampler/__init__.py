"""From a recording to training rays: decoded frames and the batch sampler (docs/method.md 2, 3.6)."""
