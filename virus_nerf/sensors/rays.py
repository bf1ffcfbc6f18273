"""World-frame rays of a sensor's pixels (`camera.pixel_rays`), in numpy: what the exports render
from a pose. Training batches are built in torch by the sampler (`sampler.batch.RayBatch`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Rays:
    """World-frame rays in metres. origins (N, 3), directions (N, 3) unit length."""

    origins: np.ndarray
    directions: np.ndarray

    def __len__(self) -> int:
        return self.origins.shape[0]


def rays_to_world(pose: np.ndarray, dirs_cam: np.ndarray) -> Rays:
    """Rays from a sensor at `pose` (4, 4 sensor-to-world) along sensor-frame unit dirs (N, 3)."""
    dirs = dirs_cam @ pose[:3, :3].T
    origins = np.broadcast_to(pose[:3, 3], dirs.shape).copy()
    return Rays(origins=origins, directions=dirs)
