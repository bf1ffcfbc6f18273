"""The Instant-NGP grid's parameters (`NgpGridConfig`), apart from the grid so that a config, a
flag or `--help` reads them without loading torch."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class NgpGridConfig:
    """Instant-NGP grid parameters (the ablation's baseline grid)."""

    max_resolution: int = 128  # cells along the longest box axis (GridSpec.from_box)
    decay: float = 0.95  # per update
    warmup_steps: int = 256  # training steps during which every cell is evaluated
    update_interval: int = 16  # training steps between updates (used by the trainer)
    min_alpha: float = 0.01  # alpha of one marching step at sigma_max
    chunk_size: int = 65536  # points per density_fn call
