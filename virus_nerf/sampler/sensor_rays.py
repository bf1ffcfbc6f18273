"""Whole-frame sensor rays of the training frames: every IRS zone and the USS cone as world rays.

The batch sampler draws camera pixels; the grid's start-up pass (VirusGrid.initialise) wants
every reading of the recording once instead, each IRS zone covered by a few rays so that its
footprint reaches every cell it spans.
"""

from __future__ import annotations

import numpy as np
import torch

from virus_nerf.grid.base import SensorRays
from virus_nerf.sampler.frames import FrameStore
from virus_nerf.sensors import irs, uss
from virus_nerf.sensors.camera import pixel_directions
from virus_nerf.stereo.depth import StereoDepth


def _world_rays(store: FrameStore, frames: np.ndarray, dirs_cam: np.ndarray, ranges: np.ndarray) -> SensorRays:
    """frames (F,), camera-frame unit directions (K, 3), ranges (F, K) m -> F*K world rays."""
    pose = store.cam_to_world[frames]  # (F, 4, 4)
    dirs = np.einsum("fij,kj->fki", pose[:, :3, :3], dirs_cam)  # (F, K, 3)
    return _as_rays(np.broadcast_to(pose[:, None, :3, 3], dirs.shape), dirs, ranges)


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


def stereo_target_rays(store: FrameStore, depth: StereoDepth, frames: np.ndarray,
                       back_sigmas: float = 0.0) -> SensorRays:
    """The stereo targets of store rows `frames` as world rays through their pixels, range = the
    target's distance minus `back_sigmas` standard deviations (m)."""
    start, count = depth.frame_slices(np.asarray(frames))
    idx = np.concatenate([np.arange(s, s + c) for s, c in zip(start, count, strict=True)]) if len(start) \
        else np.zeros(0, np.int64)
    f = depth.frames[idx]
    dirs_cam = np.zeros((len(idx), 3))
    for s, intr in store.intrinsics.items():
        sel = store.stack_ids[f] == s
        dirs_cam[sel] = pixel_directions(intr, depth.uv[idx[sel], 0], depth.uv[idx[sel], 1])
    pose = store.cam_to_world[f]  # (K, 4, 4)
    dirs = np.einsum("kij,kj->ki", pose[:, :3, :3], dirs_cam)
    ranges = depth.ranges[idx].astype(np.float64) - back_sigmas * depth.sigmas[idx]
    return SensorRays(
        origins=torch.from_numpy(np.ascontiguousarray(pose[:, :3, 3], dtype=np.float32)),
        directions=torch.from_numpy(dirs.astype(np.float32)),
        ranges=torch.from_numpy(ranges.astype(np.float32)),
    )


def uss_cone_rays(store: FrameStore, frames: np.ndarray | None = None, n_h: int = 12, n_v: int = 8) -> SensorRays:
    """Rays on an angular grid inside each frame's USS cone, range = the echo (radial, m; NaN = none)."""
    frames = np.arange(len(store)) if frames is None else np.asarray(frames)
    dirs_cam = uss.cone_directions(n_h, n_v)  # (K, 3)
    ranges = np.repeat(store.uss_range[frames][:, None], len(dirs_cam), axis=1)  # (F, K)
    return _world_rays(store, frames, dirs_cam, ranges)
