"""One seed for numpy, torch and Python's random, so CPU runs repeat bit for bit."""

from __future__ import annotations

import random

import numpy as np


def use_threads(threads: int | None) -> None:
    """The CPU threads of torch and of the numba kernels in this thread; None leaves the machine's
    default. Both are set: a parallel numba kernel sets OpenMP's count to numba's own when it
    starts, so torch's alone would not last past the first one. The thread count changes the order
    torch sums in, so a seed repeats bit for bit only at the same count (`TrainConfig.threads`)."""
    if threads is not None:
        import numba
        import torch

        n = max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS))  # numba's most: the cores, or its env
        numba.set_num_threads(n)
        torch.set_num_threads(n)


def seed_everything(seed: int) -> np.random.Generator:
    import torch

    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)
    return np.random.default_rng(seed)
