"""What the robot's own range sensors measured at camera height, as 2D rays (issue 42).

A planner's map must not call free what the infrared and ultrasonic sensors touched: they exist
for the obstacles a camera misses (thin legs, round objects, glass). Both become 2D rays in the
world frame (origin, unit direction, range in metres) that `maps.occupancy.scan_occupancy`
turns into a classic inverse-sensor map (Moravec and Elfes 1985: cells a ray passed free, its end
cell occupied), the same rasteriser as the NeRF's scans:

- IRS: every valid zone, on a 3 x 3 grid of sub-rays (sensors/irs.zone_rays, as in training), whose
  hit point lies within +-`band` of the map's height: its end is an obstacle at that height. For
  a camera at the map's height (the main stack, maps/extract.camera_height) the ray's height is
  linear along it, so the space it passed at that height is free as well.
- USS: the echo is the nearest surface anywhere in the 55 x 35 deg cone; at camera height the
  horizontal slice of the cone is free up to the echo and the echo's arc holds the obstacle
  somewhere along it (Elfes 1987's sonar model, without its angular weighting): a fan of rays one
  per `fan_step_deg` across the cone's horizontal opening, each ending at the echo range. With no
  echo nothing is claimed (the reading may have been absorbed).
- Stereo sight lines: a point the cameras triangulated was seen through the space before it, so
  every view of it (the tracked pixel's ray and the point's range) passed free space up to
  max(`SIGHT_MARGIN_M`, 2 sigma) short of the point; its part within +-`SIGHT_BAND_M` of the map's
  height, projected on the floor, is a 2D ray that passed free space (`stereo_sight_lines`, D81).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from virus_nerf.sensors import irs, uss
from virus_nerf.sensors.camera import Intrinsics, pixel_directions
from virus_nerf.sensors.geometry import yaw_of

SENSOR_BAND_M = 0.1  # IRS hits this close to the camera height count at camera height
# a stereo view's sight line counts at the map's height where it runs within this far (m) of it:
# the band's +-5 cm and the cameras' own spread about their median height (D81)
SIGHT_BAND_M = 0.1
SIGHT_MARGIN_M = 0.1  # free space ends this far (m) short of a triangulated point, or 2 sigma if larger
SIGHT_SIGMAS = 2.0
# only views of points at most this far (m) count: past it the cameras' short baseline matches
# wrongly often enough to carve the far furniture of the common areas (D81)
SIGHT_MAX_RANGE_M = 5.0
# sight lines shorter than this (m) at camera height are left out: steep views, whose part in the
# band lies by the camera, where the map's own scans already pass (offices 81-83: the same free
# recall without them, 60 % fewer lines to rasterise, D81)
SIGHT_MIN_LENGTH_M = 0.5
VIEWS_PER_CHUNK = 1 << 17  # stereo views turned into sight lines at once (~17 MB of poses)
FRAMES_PER_CHUNK = 256  # IRS frames turned into sub-rays at once (~8 MB of float64 each): a long drive's
# ~10^4 frames would otherwise hold 576 sub-rays each at once, though few hit at camera height


@dataclass(frozen=True)
class Rays2D:
    """Horizontal rays in the world frame."""

    origins: np.ndarray  # (N, 2) m
    directions: np.ndarray  # (N, 2) unit
    ranges: np.ndarray  # (N,) m, finite and positive

    def __len__(self) -> int:
        return len(self.ranges)

    @staticmethod
    def empty() -> Rays2D:
        return Rays2D(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))

    def ends(self) -> np.ndarray:
        """(N, 2) end points, m."""
        return self.origins + self.directions * self.ranges[:, None]

    def concat(self, other: Rays2D) -> Rays2D:
        return Rays2D(np.concatenate([self.origins, other.origins]), np.concatenate([self.directions, other.directions]),
                      np.concatenate([self.ranges, other.ranges]))


def irs_rays_2d(cam_to_world: np.ndarray, irs_range: np.ndarray, height: float, band: float = SENSOR_BAND_M,
                samples_per_axis: int = 3) -> Rays2D:
    """The IRS sub-rays of frames (cam_to_world (F, 4, 4), irs_range (F, 8, 8) z-depth m, NaN
    invalid) whose hit lies within +-band of `height`, projected on the floor (range = the
    horizontal distance to the hit). Each zone is covered by samples_per_axis^2 rays
    (sensors/irs.zone_rays, as the training's IRS rays)."""
    poses = np.asarray(cam_to_world, dtype=np.float64).reshape(-1, 4, 4)
    if not len(poses):
        return Rays2D.empty()
    z_depth = np.asarray(irs_range, dtype=np.float64).reshape(len(poses), -1)
    parts = []  # (origins, directions, ranges) of each chunk's rays hitting at camera height
    for s in range(0, len(poses), FRAMES_PER_CHUNK):  # bounded memory on long drives
        origins, dirs, ranges = irs.zone_rays(poses[s : s + FRAMES_PER_CHUNK], z_depth[s : s + FRAMES_PER_CHUNK],
                                              samples_per_axis)
        o, d, r = origins.reshape(-1, 3), dirs.reshape(-1, 3), ranges.reshape(-1)  # (F K, ...)
        ok = np.isfinite(r) & (r > 0)
        o, d, r = o[ok], d[ok], r[ok]
        end_z = o[:, 2] + d[:, 2] * r
        flat = np.linalg.norm(d[:, :2], axis=1)  # (K,) horizontal part of the direction
        keep = (np.abs(end_z - height) <= band) & (flat > 1e-6)
        parts.append((o[keep, :2], d[keep, :2] / flat[keep, None], (r * flat)[keep]))
    return Rays2D(*(np.concatenate(a) for a in zip(*parts, strict=True)))


def uss_rays_2d(cam_to_world: np.ndarray, uss_range: np.ndarray, fan_step_deg: float = 1.0) -> Rays2D:
    """A fan across each echo's horizontal opening (+-27.5 deg around the camera's heading),
    every ray ending at the echo's range (uss_range (F,) radial m, NaN = no echo: no rays)."""
    poses = np.asarray(cam_to_world, dtype=np.float64).reshape(-1, 4, 4)
    r = np.asarray(uss_range, dtype=np.float64).reshape(-1)
    ok = np.isfinite(r) & (r > 0)
    if not ok.any():
        return Rays2D.empty()
    poses, r = poses[ok], r[ok]
    offsets = uss.fan_offsets(fan_step_deg)  # (A,)
    n = len(offsets)
    ang = (yaw_of(poses)[:, None] + offsets[None, :]).reshape(-1)  # (F A,)
    origins = np.repeat(poses[:, :2, 3], n, axis=0)
    return Rays2D(origins, np.column_stack([np.cos(ang), np.sin(ang)]), np.repeat(r, n))


class StereoViews(Protocol):
    """The views of triangulated points (stereo/depth.StereoDepth): a tracked pixel of a frame row
    and the range along its ray to the point."""

    frames: np.ndarray  # (M,) int frame rows
    uv: np.ndarray  # (M, 2) sub-pixel (u column, v row) at training resolution
    ranges: np.ndarray  # (M,) m along the pixel's ray
    sigmas: np.ndarray  # (M,) m, the range's standard deviation


def band_parts(origins: np.ndarray, directions: np.ndarray, lengths: np.ndarray, height: float,
               band: float) -> Rays2D:
    """The parts of 3D segments (origins (M, 3) m, unit directions (M, 3), lengths (M,) m) that run
    within +-band of `height`, projected on the floor: each segment's part as one 2D ray (a straight
    segment crosses the band once); segments that never do, or run vertically, give none."""
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    length = np.asarray(lengths, dtype=np.float64).reshape(-1)
    level = np.abs(d[:, 2]) < 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):  # (M,) where each line meets the band's two planes
        t_a, t_b = (height - band - o[:, 2]) / d[:, 2], (height + band - o[:, 2]) / d[:, 2]
    inside = np.abs(o[:, 2] - height) <= band
    start = np.maximum(np.where(level, np.where(inside, 0.0, np.inf), np.minimum(t_a, t_b)), 0.0)
    stop = np.minimum(np.where(level, np.where(inside, np.inf, -np.inf), np.maximum(t_a, t_b)), length)
    flat = np.linalg.norm(d[:, :2], axis=1)  # (M,) the horizontal part of each direction
    ok = (stop > start) & (flat > 1e-6)
    return Rays2D(o[ok, :2] + d[ok, :2] * start[ok, None], d[ok, :2] / flat[ok, None], (stop - start)[ok] * flat[ok])


def stereo_sight_lines(stereo: StereoViews, cam_to_world: np.ndarray, stack_ids: np.ndarray,
                       intrinsics: dict[int, Intrinsics], height: float, band: float = SIGHT_BAND_M) -> Rays2D:
    """The free space the stereo views looked through at `height` +- band (m): each view's ray
    (the camera of frame row `stereo.frames`, with cam_to_world (F, 4, 4) and stack_ids (F,) of
    the frame rows, through its sub-pixel `uv` at its stack's training `intrinsics`) up to
    max(SIGHT_MARGIN_M, SIGHT_SIGMAS sigma) short of its triangulated range (`band_parts`); views
    of points farther than SIGHT_MAX_RANGE_M, or of frames past cam_to_world's, and parts shorter
    than SIGHT_MIN_LENGTH_M give none."""
    out = Rays2D.empty()
    for a in range(0, len(stereo.frames), VIEWS_PER_CHUNK):  # bounded memory on long drives
        ranges = np.asarray(stereo.ranges[a : a + VIEWS_PER_CHUNK], dtype=np.float64)  # (m,)
        rows = np.asarray(stereo.frames[a : a + VIEWS_PER_CHUNK], dtype=np.int64)
        near = (ranges <= SIGHT_MAX_RANGE_M) & (rows < len(cam_to_world))  # views of frames given only
        rows = rows[near]
        poses = np.asarray(cam_to_world[rows], dtype=np.float64)  # (m, 4, 4)
        stacks = np.asarray(stack_ids)[rows]
        uv = np.asarray(stereo.uv[a : a + VIEWS_PER_CHUNK], dtype=np.float64)[near]
        dirs_cam = np.zeros((len(rows), 3))
        for s, intr in intrinsics.items():
            sel = stacks == s
            dirs_cam[sel] = pixel_directions(intr, uv[sel, 0], uv[sel, 1])
        dirs = np.einsum("mij,mj->mi", poses[:, :3, :3], dirs_cam)  # (m, 3) world, unit
        sigmas = np.asarray(stereo.sigmas[a : a + VIEWS_PER_CHUNK], dtype=np.float64)[near]
        free = ranges[near] - np.maximum(SIGHT_MARGIN_M, SIGHT_SIGMAS * sigmas)
        lines = band_parts(poses[:, :3, 3], dirs, free, height, band)
        long = lines.ranges >= SIGHT_MIN_LENGTH_M
        out = out.concat(Rays2D(lines.origins[long], lines.directions[long], lines.ranges[long]))
    return out


def sensor_rays_2d(cam_to_world: np.ndarray, uss_range: np.ndarray, irs_range: np.ndarray, height: float,
                   sensors: tuple[str, ...], band: float = SENSOR_BAND_M) -> Rays2D:
    """The IRS and USS rays of frames, for those of `sensors` the robot trained with: the rays of
    a classic inverse-sensor map of the range sensors alone (no NeRF)."""
    out = Rays2D.empty()
    if "irs" in sensors:
        out = out.concat(irs_rays_2d(cam_to_world, irs_range, height, band))
    if "uss" in sensors:
        out = out.concat(uss_rays_2d(cam_to_world, uss_range))
    return out
