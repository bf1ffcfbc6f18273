"""What a user runs end to end: the demo, the ablation table, offline vs online (docs/method.md 1, 8)."""

# its public modules; none is imported here, so `import virus_nerf.experiments` loads nothing else
__all__ = [
    "ablation", "demo", "executors", "folder", "online", "report", "runs", "search_space", "study", "tune",
]
