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
    _keys: list[np.ndarray] = field(default_factory=list)

    def add(self, points_world: np.ndarray) -> None:
        idx = np.floor(np.asarray(points_world, dtype=np.float64) / self.voxel).astype(np.int64)
        idx += 1 << 20  # non-negative for packing (rooms are far below 30 km)
        self._keys.append((idx[:, 0] << 42) | (idx[:, 1] << 21) | idx[:, 2])

    def points(self) -> np.ndarray:
        """(P, 3) float32 voxel centres, sorted by voxel key (deterministic)."""
        if not self._keys:
            return np.zeros((0, 3), dtype=np.float32)
        keys, counts = np.unique(np.concatenate(self._keys), return_counts=True)
        keys = keys[counts >= self.min_hits]
        mask = (1 << 21) - 1
        idx = np.stack([(keys >> 42) & mask, (keys >> 21) & mask, keys & mask], 1) - (1 << 20)
        return ((idx + 0.5) * self.voxel).astype(np.float32)
