"""How much memory a training step needs, checked before any work (issue 39 item 3, D48).

A step's working memory follows its marched samples, not its rays; `check_batch_memory` bounds the
marcher's worst case against the memory this process may use. `train`, `map-bag` and the ROS 2
node call it on the config they are given.
"""

from __future__ import annotations

from virus_nerf.errors import UsageError

# bytes of working memory a marched sample takes in a training step (its positions, the hash
# encoding's levels and the MLPs' activations, forward and backward): the slope of peak RSS over
# the samples of a step, benchmarks/bench_step_memory.py (results/step_memory_d48.json, D48)
SAMPLE_BYTES = 2232


def check_batch_memory(cfg, limit: int | None = None, what: str = "--batch-size") -> None:
    """Refuse, before any work, a --batch-size whose step could need more than half the memory
    this process may use (utils.memory's rule). What a step needs grows with its samples, not its
    rays: the bound is the marcher's worst case, every ray keeping march.max_samples samples (a
    step in the grid's warm-up comes within a few times of it)."""
    from virus_nerf.utils.memory import memory_limit

    limit = memory_limit() if limit is None else limit
    per_ray = cfg.march.max_samples * SAMPLE_BYTES
    need = cfg.batch_size * per_ray
    if limit is not None and need > limit / 2:
        raise UsageError(
            f"{what} {cfg.batch_size}: a step may march up to {cfg.march.max_samples} samples a ray "
            f"(march.max_samples), {need / 2**30:.1f} GiB at {SAMPLE_BYTES} bytes a sample, and this machine has "
            f"{limit / 2**30:.1f} GiB; expected at most {int(limit // 2 // per_ray)} (the default is 2048)"
        )
