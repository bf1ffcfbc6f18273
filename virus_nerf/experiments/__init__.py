"""What a user runs end to end: the demo, the ablation table, offline vs online (docs/method.md 1, 8)."""
