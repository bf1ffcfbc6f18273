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
