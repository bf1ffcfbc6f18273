"""Pose and camera geometry with known answers."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from virus_nerf.sensors import uss
from virus_nerf.sensors.camera import Intrinsics, pixel_directions, pixel_rays, project
from virus_nerf.sensors.geometry import (
    interpolate_poses,
    invert_pose,
    matrix_to_quat,
    pose_matrix,
    quat_to_matrix,
)

INTR = Intrinsics(388.0, 388.4, 327.6, 244.3)

quats = st.tuples(*[st.floats(-1, 1, allow_nan=False) for _ in range(4)]).filter(
    lambda q: np.linalg.norm(q) > 0.1
)
vec3 = st.tuples(*[st.floats(-50, 50, allow_nan=False) for _ in range(3)])


def test_principal_point_ray_is_the_optical_axis():
    pose = pose_matrix(np.array([1.0, 2.0, 0.5]), np.array([0.3, -0.2, 0.1, 0.9]))
    rays = pixel_rays(INTR, pose, np.array([INTR.cx]), np.array([INTR.cy]))
    np.testing.assert_allclose(rays.directions[0], pose[:3, 2], atol=1e-12)
    np.testing.assert_allclose(rays.origins[0], [1.0, 2.0, 0.5])


def test_pixel_right_of_centre_points_to_camera_x():
    d = pixel_directions(INTR, np.array([INTR.cx + INTR.fx]), np.array([INTR.cy]))[0]
    np.testing.assert_allclose(d, np.array([1.0, 0.0, 1.0]) / np.sqrt(2), atol=1e-12)


def test_quaternion_known_rotation():
    # 90 deg about z: x -> y
    r = quat_to_matrix(np.array([0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)]))
    np.testing.assert_allclose(r @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(q=quats, t=vec3)
def test_pose_round_trips(q, t):
    pose = pose_matrix(np.array(t), np.array(q))
    np.testing.assert_allclose(pose @ invert_pose(pose), np.eye(4), atol=1e-9)
    q_back = matrix_to_quat(pose[:3, :3])
    np.testing.assert_allclose(quat_to_matrix(q_back), pose[:3, :3], atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(u=st.floats(0, 639), v=st.floats(0, 479), z=st.floats(0.1, 20))
def test_project_inverts_pixel_directions(u, v, z):
    d = pixel_directions(INTR, np.array([u]), np.array([v]))
    pu, pv, pz = project(INTR, d * z / d[:, 2:3])
    np.testing.assert_allclose([pu[0], pv[0], pz[0]], [u, v, z], rtol=1e-9, atol=1e-9)


def test_uss_raw_conversion_and_cone():
    np.testing.assert_allclose(uss.range_from_raw(np.array([3752.0, 50000.0]))[0], 0.7504)
    assert np.isnan(uss.range_from_raw(np.array([50000.0]))[0])
    dirs = uss.cone_directions()
    ax = np.degrees(np.arctan2(dirs[:, 0], dirs[:, 2]))
    ay = np.degrees(np.arctan2(dirs[:, 1], dirs[:, 2]))
    assert ax.max() <= 27.5 + 1e-9 and ax.min() >= -27.5 - 1e-9
    assert ay.max() <= 17.5 + 1e-9 and ay.min() >= -17.5 - 1e-9
    assert uss.in_cone(np.array([[np.tan(np.radians(27)), 0, 1.0]]))[0]
    assert not uss.in_cone(np.array([[0, np.tan(np.radians(20)), 1.0]]))[0]


def test_every_written_quaternion_has_w_not_negative():
    """matrix_to_quat (scipy's canonical form): w >= 0, so the recording's pose files, the bags and
    export's poses.csv write one sign (a review: poses.csv took scipy's plain as_quat, w < 0 for
    38 % of random rotations). By hand: 350 deg about z is q = (0, 0, sin 175, cos 175) = -(0, 0,
    sin 5, cos 5) -> (0, 0, -0.0872, 0.9962); 180 deg about z has w = 0 -> (0, 0, 1, 0)."""
    from virus_nerf.exports.views import PoseSet

    a = np.deg2rad(350.0)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    np.testing.assert_allclose(matrix_to_quat(rz), [0, 0, -np.sin(np.deg2rad(5)), np.cos(np.deg2rad(5))], atol=1e-12)
    np.testing.assert_allclose(matrix_to_quat(np.diag([-1.0, -1.0, 1.0])), [0, 0, 1, 0], atol=1e-12)
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[0, :3, :3] = rz
    rows = PoseSet(np.array([0.0, 1.0]), poses, "test").csv().splitlines()[1:]
    assert [float(r.split(",")[-1]) for r in rows] == pytest.approx([np.cos(np.deg2rad(5)), 1.0])


def _yaw_pose(yaw_rad: float, x: float) -> np.ndarray:
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0, x], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def test_pose_interpolation_by_hand():
    """Identity at 0 s, a quarter turn about z 2 m along x at 2 s: at 1 s half of each; outside the
    track its end; at a time two samples share (two stacks) the first."""
    times = np.array([0.0, 2.0, 2.0, 3.0])
    poses = np.stack([_yaw_pose(0, 0), _yaw_pose(np.pi / 2, 2), _yaw_pose(np.pi / 2, 2.2), _yaw_pose(np.pi, 2.2)])
    out = interpolate_poses(times, poses, np.array([1.0, 0.5, -4.0, 2.5, 9.0, 2.0, 3.0]))
    np.testing.assert_allclose(out[0], _yaw_pose(np.pi / 4, 1.0), atol=1e-12)
    np.testing.assert_allclose(out[1], _yaw_pose(np.pi / 8, 0.5), atol=1e-12)
    np.testing.assert_array_equal(out[2], poses[0])
    np.testing.assert_allclose(out[3], _yaw_pose(3 * np.pi / 4, 2.2), atol=1e-12)
    np.testing.assert_array_equal(out[4], poses[-1])
    np.testing.assert_array_equal(out[5:], poses[[1, 3]])  # at a sample: that sample, bit for bit
    np.testing.assert_allclose(interpolate_poses(times[:1], poses[:1], np.array([5.0, -1.0])), poses[[0, 0]])


@settings(max_examples=30, deadline=None, derandomize=True)
@given(st.lists(st.tuples(quats, vec3), min_size=2, max_size=6), st.floats(0, 1))
def test_pose_interpolation_matches_scipy_slerp(samples, where):
    """Against scipy's Slerp and numpy's interp over a track of strictly increasing times."""
    from scipy.spatial.transform import Rotation, Slerp

    poses = np.stack([pose_matrix(np.array(t), np.array(q)) for q, t in samples])
    times = np.cumsum(np.linspace(0.5, 1.5, len(samples)))
    t = np.array([times[0] + where * (times[-1] - times[0])])
    out = interpolate_poses(times, poses, t)[0]
    np.testing.assert_allclose(out[:3, :3], Slerp(times, Rotation.from_matrix(poses[:, :3, :3]))(t).as_matrix()[0],
                               atol=1e-9)
    np.testing.assert_allclose(out[:3, 3], [np.interp(t[0], times, poses[:, k, 3]) for k in range(3)], atol=1e-9)
