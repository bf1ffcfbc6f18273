"""The level geometry of the multiresolution hash encoding (docs/method.md 3.5), shared by the
PyTorch twin (hash_encoding.py) and the fused numba kernels (hash_kernels.py), so neither
backend module imports the other."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch

PRIMES = (1, 2654435761, 805459861)


@dataclass(frozen=True)
class HashGridLayout:
    """Level geometry shared by both backends; pure function of the five hyper-parameters."""

    n_levels: int = 16
    n_features: int = 2
    log2_table_size: int = 16
    base_resolution: int = 16
    max_resolution: int = 512

    def __post_init__(self) -> None:
        if self.n_levels < 1 or self.n_features < 1:
            raise ValueError(f"need n_levels >= 1 and n_features >= 1, got {self.n_levels}, {self.n_features}")
        if not 4 <= self.log2_table_size <= 30:
            raise ValueError(f"log2_table_size must be in [4, 30], got {self.log2_table_size}")
        if not 1 <= self.base_resolution <= self.max_resolution:
            raise ValueError(
                f"need 1 <= base_resolution <= max_resolution, got {self.base_resolution}, {self.max_resolution}"
            )

    @property
    def table_size(self) -> int:
        return 1 << self.log2_table_size

    @property
    def per_level_scale(self) -> float:
        """Growth factor b between levels (paper eq. 3)."""
        if self.n_levels == 1:
            return 1.0
        return math.exp((math.log(self.max_resolution) - math.log(self.base_resolution)) / (self.n_levels - 1))

    @cached_property
    def resolutions(self) -> tuple[int, ...]:
        """Cells per axis of every level; the last is max_resolution (float rounding guarded)."""
        b = self.per_level_scale
        res = [int(math.floor(self.base_resolution * b**lvl + 1e-6)) for lvl in range(self.n_levels)]
        return tuple(res)

    @cached_property
    def dense(self) -> tuple[bool, ...]:
        return tuple((r + 1) ** 3 <= self.table_size for r in self.resolutions)

    @cached_property
    def sizes(self) -> tuple[int, ...]:
        return tuple((r + 1) ** 3 if d else self.table_size for r, d in zip(self.resolutions, self.dense, strict=True))

    @cached_property
    def offsets(self) -> tuple[int, ...]:
        return tuple(int(v) for v in np.concatenate([[0], np.cumsum(self.sizes)[:-1]]))

    @property
    def n_entries(self) -> int:
        return int(sum(self.sizes))

    @property
    def out_dim(self) -> int:
        return self.n_levels * self.n_features

    @cached_property
    def arrays(self) -> LayoutArrays:
        """Numpy copies for the numba kernels (built once)."""
        return LayoutArrays(
            res_f=np.asarray(self.resolutions, dtype=np.float32),
            res_i=np.asarray(self.resolutions, dtype=np.int64),
            offsets=np.asarray(self.offsets, dtype=np.int64),
            sizes=np.asarray(self.sizes, dtype=np.int64),
            dense=np.asarray(self.dense, dtype=np.bool_),
            hash_mask=np.int64(self.table_size - 1),
        )


@dataclass(frozen=True)
class LayoutArrays:
    res_f: np.ndarray  # (L,) float32 cells per axis
    res_i: np.ndarray  # (L,) int64
    offsets: np.ndarray  # (L,) int64 first row of the level in the flat table
    sizes: np.ndarray  # (L,) int64 rows of the level
    dense: np.ndarray  # (L,) bool
    hash_mask: np.int64  # T - 1


def prepare_coords(x: torch.Tensor) -> torch.Tensor:
    """(N, 3) -> contiguous float32 (N, 3) clamped to [0, 1], NaN -> 0, detached."""
    import torch  # here, not above: the layout itself is checked by configs that need no torch

    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"hash encoding expects points of shape (N, 3), got {tuple(x.shape)}")
    x = x.detach().to(torch.float32)
    return torch.nan_to_num(x, nan=0.0).clamp_(0.0, 1.0).contiguous()
