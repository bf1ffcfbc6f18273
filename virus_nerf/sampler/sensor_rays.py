"""Whole-frame sensor rays of the training frames: every IRS zone as world rays.

The batch sampler draws camera pixels; the grid's start-up pass (VirusGrid.initialise) wants
every reading of the recording once instead, each IRS zone covered by a few rays so that its
footprint reaches every cell it spans.
"""

from __future__ import annotations

import numpy as np
import torch

from virus_nerf.grid.base import SensorRays
from virus_nerf.sampler.frames import FrameStore
from virus_nerf.sensors import irs


def _as_rays(origins: np.ndarray, dirs: np.ndarray, ranges: np.ndarray) -> SensorRays:
    """(F, K, 3) origins and directions, (F, K) ranges -> F*K float32 SensorRays."""
    return SensorRays(
        origins=torch.from_numpy(np.ascontiguousarray(origins.reshape(-1, 3), dtype=np.float32)),
        directions=torch.from_numpy(np.ascontiguousarray(dirs.reshape(-1, 3), dtype=np.float32)),
        ranges=torch.from_numpy(np.ascontiguousarray(ranges.reshape(-1), dtype=np.float32)),
    )


def irs_zone_rays(store: FrameStore, frames: np.ndarray | None = None, samples_per_axis: int = 3) -> SensorRays:
    """samples_per_axis^2 rays per IRS zone of each frame, range = distance along the ray (m).

    The zone's z-depth becomes z / d_z along each sub-ray; invalid zones give NaN ranges (use
    `SensorRays.valid()` to drop them).
    """
    frames = np.arange(len(store)) if frames is None else np.asarray(frames)
    origins, dirs, ranges = irs.zone_rays(store.cam_to_world[frames], store.irs_range[frames], samples_per_axis)
    return _as_rays(origins, dirs, ranges)
