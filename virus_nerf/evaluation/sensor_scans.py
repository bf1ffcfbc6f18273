"""Instantaneous sensor scans collapsed to 2D in the world frame (docs/method.md 6.4).

- LiDAR: the scan nearest in time, moved to the world by the LiDAR pose at the scan's time,
  points within +-band of the camera height, optionally only a horizontal angle range
  around the robot heading (the LiDAR x axis).
- IRS: every valid zone of both stacks, a point on the zone's centre ray at the measured
  z-depth (converted to ray length); kept only where that 3D point's real height lies within
  +-band of the camera height (the camera is pitched, so most zones look above or below).
- USS: both stacks, the cone's horizontal arc (+-27.5 deg around the camera heading) at the
  echo range, at camera height.
No return is no point; nothing is ever placed at the sensor origin (docs/method.md 9.8).
"""

from __future__ import annotations

import numpy as np

from virus_nerf.data.ethz import Recording
from virus_nerf.evaluation.testpoints import TestPoint, lidar_scan_index
from virus_nerf.maps.scans import FieldOfView, Scan2D, Sector
from virus_nerf.sensors import irs, uss
from virus_nerf.sensors.camera import z_depth_to_ray_length
from virus_nerf.sensors.geometry import transform_points, yaw_of

USS_HALF_FOV_RAD = np.deg2rad(uss.USS_FOV_H_DEG / 2)  # 27.5 deg
IRS_HALF_FOV_RAD = np.deg2rad(irs.IRS_FOV_DEG / 2)  # 22.5 deg


def lidar_fov(lidar_pose: np.ndarray, angle_range_deg: float) -> FieldOfView:
    """Sector of `angle_range_deg` (full circle at >= 360) centred on the LiDAR x axis."""
    if not angle_range_deg > 0:
        raise ValueError(f"LiDAR angle range must be positive (degrees), got {angle_range_deg}")
    apex = lidar_pose[:2, 3]
    half = np.pi if angle_range_deg >= 360.0 else np.deg2rad(angle_range_deg) / 2
    return FieldOfView((Sector(apex.copy(), float(yaw_of(lidar_pose, axis=0)), float(half)),))


def lidar_fov_between(lidar_pose: np.ndarray, lo_deg: float, hi_deg: float) -> FieldOfView:
    """Sector from lo_deg to hi_deg (degrees, counter-clockwise) relative to the LiDAR x axis,
    e.g. (-140, 60); a span of 360 degrees or more is the full circle."""
    if not hi_deg > lo_deg:
        raise ValueError(f"LiDAR angle range must have hi > lo (degrees), got ({lo_deg}, {hi_deg})")
    apex = lidar_pose[:2, 3]
    span = hi_deg - lo_deg
    half = np.pi if span >= 360.0 else np.deg2rad(span) / 2
    heading = float(yaw_of(lidar_pose, axis=0)) + np.deg2rad((lo_deg + hi_deg) / 2)
    return FieldOfView((Sector(apex.copy(), heading, float(half)),))


def lidar_scan_2d(
    recording: Recording, test_point: TestPoint, band: float = 0.05, angle_range_deg: float = 360.0,
    angles_deg: tuple[float, float] | None = None,
) -> Scan2D:
    """LiDAR points at camera height from the scan taken at the test point's time (the nearest,
    within SYNC_TOLERANCE_S; none: an empty scan of no field of view, which scores nothing), within
    `angle_range_deg` centred on the LiDAR heading or, when given, `angles_deg` (lo, hi) relative
    to it."""
    k = lidar_scan_index(recording, test_point.time)
    if k is None:
        return Scan2D("LiDAR", np.zeros((0, 2)), test_point.origin_xy, FieldOfView(()))
    t_scan = float(recording.lidar_times[k])
    pose = recording.lidar_pose_at(t_scan)  # (4, 4) LiDAR to world
    pts = transform_points(pose, recording.lidar_scan(k).astype(np.float64))  # (M, 3) world
    pts = pts[np.abs(pts[:, 2] - test_point.height) <= band]
    fov = lidar_fov(pose, angle_range_deg) if angles_deg is None else lidar_fov_between(pose, *angles_deg)
    xy = pts[:, :2]
    keep = fov.contains(xy)
    return Scan2D("LiDAR", xy[keep], test_point.origin_xy, fov, extra={"z": pts[keep, 2], "time": np.array([t_scan])})


def irs_points_3d(irs_range: np.ndarray, cam_to_world: np.ndarray) -> np.ndarray:
    """(8, 8) z-depths (image zone order, NaN invalid) -> (V, 3) world points on the zone centre rays."""
    dirs = irs.zone_directions(1)[:, :, 0, :]  # (8, 8, 3) camera frame, unit
    z = np.asarray(irs_range, dtype=np.float64)
    ok = np.isfinite(z) & (z > 0)
    length = z_depth_to_ray_length(z[ok], dirs[ok])  # (V,) m along the ray
    pts_cam = dirs[ok] * length[:, None]
    return transform_points(cam_to_world, pts_cam)


def _camera_fov(test_point: TestPoint, half_rad: float) -> FieldOfView:
    """Union of +-half_rad sectors around each camera heading, apex at each camera."""
    return FieldOfView(tuple(Sector(p[:2, 3].copy(), float(yaw_of(p)), float(half_rad))
                             for _, p in test_point.camera_poses().values()))


def irs_fov(test_point: TestPoint) -> FieldOfView:
    """Union of +-22.5 deg sectors around each camera heading, apex at each camera."""
    return _camera_fov(test_point, IRS_HALF_FOV_RAD)


def uss_fov(test_point: TestPoint) -> FieldOfView:
    """Union of +-27.5 deg sectors around each camera heading, apex at each camera."""
    return _camera_fov(test_point, USS_HALF_FOV_RAD)


def irs_scan_2d(recording: Recording, test_point: TestPoint, band: float = 0.05) -> Scan2D:
    """IRS zone hits of both stacks whose 3D height lies within +-band of the camera height."""
    xy, zs, stacks = [], [], []
    for s, (i, pose) in test_point.camera_poses().items():
        pts = irs_points_3d(recording.stacks[s].irs_range[i], pose)
        pts = pts[np.abs(pts[:, 2] - test_point.height) <= band]
        xy.append(pts[:, :2])
        zs.append(pts[:, 2])
        stacks.append(np.full(len(pts), s))
    return Scan2D(
        "IRS", np.concatenate(xy), test_point.origin_xy, irs_fov(test_point),
        extra={"z": np.concatenate(zs), "stack": np.concatenate(stacks)},
    )


def uss_arc(cam_to_world: np.ndarray, range_m: float, step_deg: float = 1.0) -> np.ndarray:
    """(A, 2) points on the cone's horizontal arc at radial `range_m` around the camera heading."""
    a = yaw_of(cam_to_world) + uss.fan_offsets(step_deg)
    return cam_to_world[:2, 3][None, :] + range_m * np.stack([np.cos(a), np.sin(a)], axis=1)


def uss_scan_2d(recording: Recording, test_point: TestPoint, step_deg: float = 1.0) -> Scan2D:
    """The horizontal echo arc of each stack's USS; no echo gives no points."""
    xy, stacks = [], []
    for s, (i, pose) in test_point.camera_poses().items():
        r = float(recording.stacks[s].uss_range[i])
        if not (np.isfinite(r) and r > 0):
            continue
        arc = uss_arc(pose, r, step_deg)
        xy.append(arc)
        stacks.append(np.full(len(arc), s))
    pts = np.concatenate(xy) if xy else np.zeros((0, 2))
    st = np.concatenate(stacks) if stacks else np.zeros(0, dtype=np.int64)
    return Scan2D("USS", pts, test_point.origin_xy, uss_fov(test_point), extra={"stack": st})
