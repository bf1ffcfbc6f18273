"""What a user runs end to end: the demo, the ablation table, offline vs online (design 1, 8)."""
