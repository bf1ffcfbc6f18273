"""Rigid transforms. Poses are 4x4 sensor-to-world matrices in metres; quaternions (x, y, z, w)."""

from __future__ import annotations

import numpy as np

# A pose quaternion must have unit norm within this tolerance: | |q| - 1 | <= 1e-3, wherever a pose
# enters (a pose file, an Odometry or tf message). Rounding every component to 4 decimals moves |q|
# by at most ~1e-4, so any honest export passes (the real sample is unit to 2e-9); a quaternion
# further off is a column mix-up or garbage (zeros: an uninitialised publisher), which normalising
# would silently turn into a wrong rotation.
QUATERNION_NORM_TOLERANCE = 1e-3


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (x, y, z, w), normalised here -> (..., 3, 3) rotation matrices
    (scipy's Rotation; a zero quaternion is refused there: the pose readers check norms first)."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(q, dtype=np.float64)
    return Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) quaternions (x, y, z, w), canonical (w >= 0): the
    sign every pose file and message of the package writes."""
    from scipy.spatial.transform import Rotation

    r = np.asarray(r, dtype=np.float64)
    if r.size == 0:
        return np.zeros(r.shape[:-2] + (4,))
    return Rotation.from_matrix(r.reshape(-1, 3, 3)).as_quat(canonical=True).reshape(r.shape[:-2] + (4,))


def pose_matrix(translation: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """(..., 3) translation and (..., 4) quaternion -> (..., 4, 4) homogeneous pose."""
    translation = np.asarray(translation, dtype=np.float64)
    rot = quat_to_matrix(quat_xyzw)
    out = np.zeros(rot.shape[:-2] + (4, 4))
    out[..., :3, :3] = rot
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def interpolate_poses(times_s: np.ndarray, poses: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """Poses (N, 4, 4) at times (N,) s along a track of (K,) non-decreasing times and (K, 4, 4)
    poses: the rotation slerped, the translation linear between the two samples around each time.
    A time at a sample, before the first or after the last takes that sample's pose bit for bit
    (a time two samples share: the first), so a stream gives the same poses whether or not the
    track has grown past it yet."""
    from scipy.spatial.transform import Rotation

    times_s = np.asarray(times_s, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    t_s = np.asarray(t_s, dtype=np.float64).reshape(-1)
    if len(times_s) == 1:
        return np.repeat(poses[:1], len(t_s), axis=0)
    tc = np.clip(t_s, times_s[0], times_s[-1])
    j = np.clip(np.searchsorted(times_s, tc), 1, len(times_s) - 1)  # (N,) upper sample
    t0, t1 = times_s[j - 1], times_s[j]
    span = t1 - t0
    a = np.divide(tc - t0, span, out=np.zeros_like(tc), where=span > 0)  # (N,) in [0, 1]
    r0 = Rotation.from_matrix(poses[j - 1, :3, :3])
    turn = (r0.inv() * Rotation.from_matrix(poses[j, :3, :3])).as_rotvec()  # (N, 3) rad
    out = np.zeros((len(t_s), 4, 4))
    out[:, :3, :3] = (r0 * Rotation.from_rotvec(turn * a[:, None])).as_matrix()
    out[:, :3, 3] = (1 - a)[:, None] * poses[j - 1, :3, 3] + a[:, None] * poses[j, :3, 3]
    out[:, 3, 3] = 1.0
    out[a == 0] = poses[j - 1][a == 0]
    out[a == 1] = poses[j][a == 1]
    return out


def upside_down_share(poses: np.ndarray) -> float:
    """The share of (N, 4, 4) poses whose z axis points below the horizon (NaN poses left out): a
    ground robot's LiDAR or base stands upright, and quaternions read in the wrong order turn it over."""
    up = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)[:, 2, 2]
    up = up[np.isfinite(up)]
    return float(np.mean(up < 0.0)) if len(up) else 0.0


def upside_down_words(poses: np.ndarray, which: str) -> str | None:
    """The note on (N, 4, 4) poses (`which`: where they came from) of which more than half stand
    upside down (`upside_down_share`), in the one wording import-bag and the readers share; else None."""
    down = upside_down_share(poses)
    if down <= 0.5:
        return None
    return (f"the up axis of {down:.0%} of {which} points below the horizon: an upside-down LiDAR, or "
            "quaternions in w,x,y,z order? They are read as qx,qy,qz,qw")


def invert_pose(pose: np.ndarray) -> np.ndarray:
    """Inverse of (..., 4, 4) rigid transforms."""
    pose = np.asarray(pose, dtype=np.float64)
    rot_t = np.swapaxes(pose[..., :3, :3], -1, -2)
    out = np.zeros_like(pose)
    out[..., :3, :3] = rot_t
    out[..., :3, 3] = -(rot_t @ pose[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply one (4, 4) pose to (N, 3) points."""
    points = np.asarray(points)
    return points @ pose[:3, :3].T + pose[:3, 3]


def yaw_of(pose: np.ndarray, axis: int = 2) -> np.ndarray:
    """Heading (rad, about world z) of a sensor axis (default the camera's optical axis z)."""
    d = np.asarray(pose)[..., :3, axis]
    return np.arctan2(d[..., 1], d[..., 0])
