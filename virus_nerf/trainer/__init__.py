"""Training: the scene model (field + grid + marcher), the loop, checkpoints and logs (docs/method.md 3.6)."""
