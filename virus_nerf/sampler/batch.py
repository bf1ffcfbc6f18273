"""The batch sampler (docs/method.md 3.6): random pixels + USS-cone pixels + IRS-zone pixels.

Every ray is a camera pixel and carries colour; rays whose pixel lies in a sensor's footprint
also carry that sensor's range, converted to a distance along the ray in metres (the IRS
z-depth divided by the pixel direction's z; the USS range is radial already).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from virus_nerf.sampler.frames import FrameStore
from virus_nerf.sampler.shares import SENSORS, BatchShares
from virus_nerf.sensors.camera import pixel_directions
from virus_nerf.sensors.irs import IRS_ZONE_COUNT
from virus_nerf.stereo.depth import StereoDepth


@dataclass
class RayBatch:
    """B training rays, world frame, metres. NaN target = that sensor has no value on the ray."""

    origins: torch.Tensor  # (B, 3)
    directions: torch.Tensor  # (B, 3) unit
    rgb: torch.Tensor  # (B, 3) in [0, 1]
    irs_range: torch.Tensor  # (B,) distance along the ray from the IRS zone reading
    uss_range: torch.Tensor  # (B,) echo range (radial) for rays inside the USS cone
    rgbd_range: torch.Tensor  # (B,) distance along the ray from the RGB-D depth
    frames: torch.Tensor  # (B,) int64 frame rows in the FrameStore
    stereo_range: torch.Tensor | None = None  # (B,) distance to a triangulated point (stereo sensor)
    stereo_sigma: torch.Tensor | None = None  # (B,) its standard deviation, m

    def __len__(self) -> int:
        return self.origins.shape[0]

    def to(self, device: torch.device) -> RayBatch:
        return RayBatch(**{k: None if v is None else v.to(device) for k, v in self.__dict__.items()})


def recent_frame_odds(times: np.ndarray, share: float, window: float) -> np.ndarray:
    """(N,) odds of each frame for one ray: `share` spread evenly over the frames within `window`
    seconds of the newest one (times (N,) in seconds), the rest evenly over all N frames."""
    n = len(times)
    recent = times >= times.max() - window  # (N,) bool, the newest frame included
    return np.full(n, (1.0 - share) / n) + np.where(recent, share / recent.sum(), 0.0)


class BatchSampler:
    """Draws RayBatches from a FrameStore with a numpy Generator (seeded, resumable)."""

    def __init__(self, store: FrameStore, sensors: tuple[str, ...], shares: BatchShares = BatchShares(),
                 stereo: StereoDepth | None = None):
        unknown = set(sensors) - set(SENSORS)
        if unknown:
            raise ValueError(f"unknown sensors {sorted(unknown)}; expected a subset of {SENSORS}")
        self.store = store
        self.sensors = tuple(sensors)
        self.share_irs = shares.irs if "irs" in sensors else 0.0
        self.share_uss = shares.uss if "uss" in sensors else 0.0
        self.share_stereo = shares.stereo if "stereo" in sensors else 0.0
        if self.share_irs + self.share_uss + self.share_stereo > 1:
            raise ValueError("batch shares of IRS, USS and stereo rays must add up to at most 1")
        # triangulated depth targets of the store's frames (rows as in the store); None: none yet
        self.stereo = stereo

    def sample(self, rng: np.random.Generator, n_rays: int, frames: np.ndarray | None = None,
               frame_p: np.ndarray | None = None) -> RayBatch:
        """Draw n_rays rays from the given frame rows (default: all frames of the store), each
        ray's frame uniformly or, with `frame_p` ((len(frames),) summing to 1), with those odds."""
        store = self.store
        if frames is None:
            frames = np.arange(len(store))
        if len(frames) == 0:
            raise ValueError("no frames available to sample rays from")
        if frame_p is not None and len(frame_p) != len(frames):
            raise ValueError(f"frame_p has {len(frame_p)} entries for {len(frames)} frames")
        n_irs = int(round(self.share_irs * n_rays))
        n_uss = int(round(self.share_uss * n_rays))
        # stereo rays are drawn only once there are targets: the share stays random pixels before
        n_stereo = int(round(self.share_stereo * n_rays)) if self.stereo is not None and len(self.stereo) else 0
        kind = np.zeros(n_rays, dtype=np.int8)  # 0 random, 1 uss cone, 2 irs zone, 3 stereo target
        kind[:n_uss] = 1
        kind[n_uss : n_uss + n_irs] = 2
        kind[n_uss + n_irs : n_uss + n_irs + n_stereo] = 3
        if frame_p is None:
            f = frames[rng.integers(0, len(frames), size=n_rays)]
        else:
            f = rng.choice(frames, size=n_rays, p=frame_p)
        pix = np.empty(n_rays, dtype=np.int64)
        u01 = rng.random(n_rays)
        zone_pick = rng.random((n_rays, IRS_ZONE_COUNT))
        hw = store.height * store.width
        for s, fp in store.footprints.items():
            in_stack = store.stack_ids[f] == s
            sel = in_stack & (kind == 0)
            pix[sel] = np.minimum((u01[sel] * hw).astype(np.int64), hw - 1)
            sel = in_stack & (kind == 1)
            pix[sel] = fp.uss_pixels[np.minimum((u01[sel] * len(fp.uss_pixels)).astype(np.int64), len(fp.uss_pixels) - 1)]
            sel = np.flatnonzero(in_stack & (kind == 2))
            if sel.size:
                valid = np.isfinite(store.irs_range[f[sel]].reshape(-1, IRS_ZONE_COUNT))  # (n, 64)
                # a valid zone of the frame, uniformly; frames without one fall back to any zone
                weights = np.where(valid.any(axis=1, keepdims=True), valid, True)
                zone = np.argmax(zone_pick[sel] * weights, axis=1)
                start, count = fp.zone_start[zone], np.diff(fp.zone_start)[zone]
                pix[sel] = fp.zone_pixels[start + np.minimum((u01[sel] * count).astype(np.int64), count - 1)]
        target = np.full(n_rays, -1, dtype=np.int64)  # stereo target index per ray, -1 none
        sel = np.flatnonzero(kind == 3)
        if sel.size:
            start, count = self.stereo.frame_slices(f[sel])
            has = count > 0  # a frame without targets gives a random pixel of that frame instead
            target[sel[has]] = start[has] + np.minimum((u01[sel[has]] * count[has]).astype(np.int64), count[has] - 1)
            loose = sel[~has]
            pix[loose] = np.minimum((u01[loose] * hw).astype(np.int64), hw - 1)
        return self._rays(f, pix, target)

    def _rays(self, f: np.ndarray, pix: np.ndarray, target: np.ndarray | None = None) -> RayBatch:
        """Rays of pixels `pix` (N,) of frames `f` (N,); rays with a stereo `target` index (>= 0)
        go through that target's sub-pixel position instead (their colour: the pixel it is in)."""
        store = self.store
        n = len(f)
        stereo_range = stereo_sigma = None
        if target is not None and (target >= 0).any():
            has = target >= 0
            uv = self.stereo.uv[target[has]].astype(np.float64)  # (k, 2) training-image pixels
            col = np.clip(np.round(uv[:, 0]).astype(np.int64), 0, store.width - 1)
            row = np.clip(np.round(uv[:, 1]).astype(np.int64), 0, store.height - 1)
            pix = pix.copy()
            pix[has] = row * store.width + col
        dirs_cam = np.empty((n, 3), dtype=np.float64)
        irs_range = np.full(n, np.nan)
        uss_range = np.full(n, np.nan)
        for s, fp in store.footprints.items():
            sel = store.stack_ids[f] == s
            dirs_cam[sel] = fp.dirs_cam[pix[sel]]
            zone = fp.irs_zone[pix[sel]].astype(np.int64)
            z = np.where(zone >= 0, store.irs_range[f[sel]].reshape(-1, IRS_ZONE_COUNT)[np.arange(sel.sum()), np.maximum(zone, 0)], np.nan)
            irs_range[sel] = z / dirs_cam[sel, 2]
            uss_range[sel] = np.where(fp.in_uss[pix[sel]], store.uss_range[f[sel]], np.nan)
        if "irs" not in self.sensors:
            irs_range[:] = np.nan
        if "uss" not in self.sensors:
            uss_range[:] = np.nan
        rgbd_range = np.full(n, np.nan)
        if "rgbd" in self.sensors and store.depths_mm is not None:
            mm = store.pixels("depths_mm", f, pix).astype(np.float64)
            rgbd_range = np.where(mm > 0, mm / 1000.0, np.nan) / dirs_cam[:, 2]
        if target is not None and "stereo" in self.sensors:
            stereo_range, stereo_sigma = np.full(n, np.nan), np.full(n, np.nan)
            has = np.flatnonzero(target >= 0)
            if has.size:
                for s, intr in store.intrinsics.items():
                    sel = has[store.stack_ids[f[has]] == s]
                    uv = self.stereo.uv[target[sel]]
                    dirs_cam[sel] = pixel_directions(intr, uv[:, 0], uv[:, 1])
                stereo_range[has] = self.stereo.ranges[target[has]]
                stereo_sigma[has] = self.stereo.sigmas[target[has]]
            stereo_range = torch.from_numpy(stereo_range.astype(np.float32))
            stereo_sigma = torch.from_numpy(stereo_sigma.astype(np.float32))
        pose = store.cam_to_world[f]  # (n, 4, 4)
        dirs = np.einsum("nij,nj->ni", pose[:, :3, :3], dirs_cam)
        rgb = store.pixels("images", f, pix).astype(np.float32) / 255.0
        return RayBatch(
            origins=torch.from_numpy(pose[:, :3, 3].astype(np.float32)),
            directions=torch.from_numpy(dirs.astype(np.float32)),
            rgb=torch.from_numpy(rgb),
            irs_range=torch.from_numpy(irs_range.astype(np.float32)),
            uss_range=torch.from_numpy(uss_range.astype(np.float32)),
            rgbd_range=torch.from_numpy(rgbd_range.astype(np.float32)),
            frames=torch.from_numpy(f.astype(np.int64)),
            stereo_range=stereo_range,
            stereo_sigma=stereo_sigma,
        )
