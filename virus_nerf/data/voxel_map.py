"""The LiDAR map as the real robot's is built (3 cm voxels hit at least twice): used by the
simulator and by `import-bag`, which builds a recording's map from its scans."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class VoxelMap:
    """The global map as the real one is built: world points into voxels of `voxel` m, voxels
    hit at least `min_hits` times kept, their centres returned (docs/method.md 4). Fed with the exact
    poses: the real map shows no registration shell beyond what its 3 mm range noise and the
    3 cm voxels explain (see LidarModel), so none is added."""

    voxel: float = 0.03
    min_hits: int = 2
    merge_every: int = 4_000_000  # pending keys merged into (voxel, hits) beyond this many: memory bound
    _keys: list[np.ndarray] = field(default_factory=list)  # pending packed keys, one array a scan
    _pending: int = 0
    _voxels: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # sorted unique keys
    _hits: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # (V,) hits of each

    def add(self, points_world: np.ndarray) -> None:
        idx = np.floor(np.asarray(points_world, dtype=np.float64) / self.voxel).astype(np.int64)
        idx += 1 << 20  # non-negative for packing (rooms are far below 30 km)
        self._keys.append((idx[:, 0] << 42) | (idx[:, 1] << 21) | idx[:, 2])
        self._pending += len(idx)
        if self._pending > self.merge_every:
            self._merge()

    def _merge(self) -> None:
        """Fold the pending keys into the voxels' hit counts: a long drive's memory stays that of
        the room's voxels, not of every point ever scanned (~145 MB a minute of a 10 Hz LiDAR)."""
        keys = np.concatenate([self._voxels, *self._keys])
        weights = np.concatenate([self._hits, np.ones(self._pending, dtype=np.int64)])
        self._voxels, inverse = np.unique(keys, return_inverse=True)
        self._hits = np.bincount(inverse.reshape(-1), weights=weights, minlength=len(self._voxels)).astype(np.int64)
        self._keys, self._pending = [], 0

    def points(self) -> np.ndarray:
        """(P, 3) float32 voxel centres, sorted by voxel key (deterministic)."""
        if self._keys:
            self._merge()
        keys = self._voxels[self._hits >= self.min_hits]
        mask = (1 << 21) - 1
        idx = np.stack([(keys >> 42) & mask, (keys >> 21) & mask, keys & mask], 1) - (1 << 20)
        return ((idx + 0.5) * self.voxel).astype(np.float32)
