"""How long and how wide a training step is: the budget share and the rays per step."""

from __future__ import annotations


def budget_share(step: int, seconds: float, max_steps: int | None, max_time: float | None) -> float:
    """Share in [0, 1] of a step and/or time budget used (the larger of the two)."""
    parts = [0.0]
    if max_steps is not None:
        parts.append(step / max_steps)
    if max_time is not None:
        parts.append(seconds / max_time)
    return min(1.0, max(parts))


def rays_for_step(batch_size: int, max_samples: int | None, last_samples_per_ray: float) -> int:
    """Rays of the next step under a sample budget (TrainConfig.max_samples_per_step).

    min(batch_size, max_samples / last_samples_per_ray), never below batch_size // 8 (at least
    1); batch_size without a budget or before the first step (no samples per ray measured yet).
    """
    if max_samples is None or last_samples_per_ray <= 0.0:
        return batch_size
    floor = max(1, batch_size // 8)
    return int(min(batch_size, max(floor, max_samples // max(1.0, last_samples_per_ray))))
