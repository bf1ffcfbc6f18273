"""Training: the scene model (field + grid + marcher), the loop, checkpoints and logs (docs/method.md 3.6)."""

# its public modules; none is imported here, so `import virus_nerf.trainer` loads nothing else
__all__ = ["command", "config", "loop", "report", "run", "run_folder", "train_log", "trust"]
