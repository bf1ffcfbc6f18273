"""Training: the scene model (field + grid + marcher), the loop, checkpoints and logs (design 3.6)."""
