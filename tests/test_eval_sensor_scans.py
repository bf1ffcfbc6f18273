"""Sensor scans collapsed to 2D on hand-made poses and readings (docs/method.md 6.4)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from virus_nerf.evaluation.sensor_scans import irs_scan_2d, lidar_fov, uss_scan_2d
from virus_nerf.evaluation.testpoints import TestPoint, make_test_points, synchronous_index

CAM_AXES = np.array([[0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0]])  # cam x,y,z (columns) in world


def cam_pose(x: float, y: float, z: float, yaw_deg: float) -> np.ndarray:
    a = np.deg2rad(yaw_deg)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    pose = np.eye(4)
    pose[:3, :3] = rz @ CAM_AXES
    pose[:3, 3] = (x, y, z)
    return pose


def fake(uss1=np.nan, uss3=np.nan, irs1=None, irs3=None):
    nan_grid = np.full((8, 8), np.nan)
    stacks = {
        1: SimpleNamespace(uss_range=np.array([uss1]), irs_range=np.array([nan_grid if irs1 is None else irs1])),
        3: SimpleNamespace(uss_range=np.array([uss3]), irs_range=np.array([nan_grid if irs3 is None else irs3])),
    }
    return SimpleNamespace(stacks=stacks)


def tp_two_stacks() -> TestPoint:
    return TestPoint(index1=0, index3=0, time=0.0, time3=0.027,
                     pose1=cam_pose(0.3, -0.14, 0.0, -14.5), pose3=cam_pose(0.3, 0.13, 0.0, 14.5))


def test_uss_arc_at_echo_range_within_cone_and_no_echo_gives_no_points():
    tp = tp_two_stacks()
    scan = uss_scan_2d(fake(uss1=0.75, uss3=np.nan), tp)
    assert len(scan) == 56  # 55 deg in 1 deg steps, both ends
    d = scan.points - tp.pose1[:2, 3]
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 0.75, atol=1e-12)
    ang = np.rad2deg(np.arctan2(d[:, 1], d[:, 0]))
    assert ang.min() == pytest.approx(-14.5 - 27.5) and ang.max() == pytest.approx(-14.5 + 27.5)
    assert (scan.extra["stack"] == 1).all()
    # both stacks echo: stack 3's arc is centred on camera 3
    scan = uss_scan_2d(fake(uss1=0.75, uss3=1.97), tp)
    p3 = scan.points[scan.extra["stack"] == 3]
    np.testing.assert_allclose(np.linalg.norm(p3 - tp.pose3[:2, 3], axis=1), 1.97, atol=1e-12)
    # FoV: union of +-27.5 deg around each camera heading
    at = np.deg2rad(np.array([-40.0, -43.0]))
    pts = tp.pose1[:2, 3] + 2.0 * np.stack([np.cos(at), np.sin(at)], 1)  # seen from camera 1
    assert scan.fov.contains(pts).tolist() == [True, False]  # -40 deg inside, -43 deg outside
    assert not scan.fov.contains(np.array([[0.3, 2.0]])).any()  # 90 deg left: nobody
    assert len(uss_scan_2d(fake(), tp)) == 0


def test_irs_level_camera_keeps_only_zone_rows_near_camera_height():
    tp = TestPoint(index1=0, index3=None, time=0.0, time3=None, pose1=cam_pose(1.0, 2.0, 0.3, 0.0), pose3=None)
    grid = np.full((8, 8), 0.5)  # z-depth 0.5 m everywhere
    scan = irs_scan_2d(fake(irs1=grid), tp, band=0.05)
    # zone rows are 5.625 deg apart: centres at +-2.81, +-8.44, ... deg -> heights 0.5 * tan(.)
    # = +-0.025 (kept), +-0.074, ... (dropped): the two middle rows, 8 columns each
    assert len(scan) == 16
    np.testing.assert_allclose(scan.points[:, 0], 1.5, atol=1e-12)  # z-depth along world x
    np.testing.assert_allclose(np.abs(scan.extra["z"] - 0.3), 0.5 * np.tan(np.deg2rad(45 / 16)), atol=1e-12)
    # the same at 2 m: no zone ray is within +-5 cm of camera height (0.098 m off) -> nothing
    assert len(irs_scan_2d(fake(irs1=np.full((8, 8), 2.0)), tp)) == 0
    # invalid zones give no point; zone (3, 0) is image column 0, camera x < 0, world +y here
    g = np.full((8, 8), np.nan)
    g[3, 0] = 0.5
    scan = irs_scan_2d(fake(irs1=g), tp)
    assert len(scan) == 1
    lateral = 0.5 * np.tan(np.deg2rad(-22.5 + 45 / 16))  # camera x of the zone's point
    np.testing.assert_allclose(scan.points[0], [1.5, 2.0 - lateral], atol=1e-12)


def test_irs_pitched_camera_uses_true_heights():
    # pitched up 5 deg about the camera x axis: the middle rows rise above the band at 1 m
    a = np.deg2rad(5.0)
    pitch = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])  # about cam x
    pose = cam_pose(0.0, 0.0, 0.0, 0.0)
    pose[:3, :3] = pose[:3, :3] @ pitch.T  # optical axis tilted 5 deg out of the horizontal
    axis_z = pose[:3, 2]
    tp = TestPoint(index1=0, index3=None, time=0.0, time3=None, pose1=pose, pose3=None)
    scan = irs_scan_2d(fake(irs1=np.full((8, 8), 1.0)), tp)
    assert abs(axis_z[2]) == pytest.approx(np.sin(a))
    assert (np.abs(scan.extra["z"]) <= 0.05).all()
    # rows whose rays are within ~2.9 deg of horizontal survive: centre angles -2.8+5=2.2 and
    # -8.4+5 = -3.4 (or mirrored) -> exactly one row of 8 at 1 m z-depth
    assert len(scan) == 8


def test_lidar_fov_is_centred_on_the_lidar_x_axis():
    pose = np.eye(4)
    pose[:3, 3] = (1.0, 0.0, 0.0)
    fov = lidar_fov(pose, 90.0)
    assert fov.contains(np.array([[3.0, 1.9], [3.0, -1.9], [1.0, 3.0], [0.0, 0.0]])).tolist() == [True, True, False, False]
    assert lidar_fov(pose, 360.0).contains(np.array([[-5.0, 0.0]])).all()
    with pytest.raises(ValueError):
        lidar_fov(pose, 0.0)


def test_test_points_pair_nearest_stack3_frame():
    times = np.array([0.0, 1.0, 2.0])
    assert synchronous_index(times, 1.4, 0.5) == 1 and synchronous_index(times, 1.6, 0.5) == 2
    assert synchronous_index(times, 1.5, 0.5) == 1  # a tie: the earlier stamp
    assert synchronous_index(times, -0.4, 0.5) == 0 and synchronous_index(times, -0.6, 0.5) is None
    assert synchronous_index(times, 2.4, 0.5) == 2 and synchronous_index(times, 2.6, 0.5) is None
    assert synchronous_index(np.zeros(0), 1.0, 0.5) is None
    class Stack(SimpleNamespace):
        def __len__(self) -> int:
            return len(self.times)

        def indices(self, label: str) -> np.ndarray:
            return np.flatnonzero(self.split == label)

    poses = np.stack([cam_pose(i, 0, 0.2, 0) for i in range(4)])
    s1 = Stack(times=np.array([0.0, 0.2, 0.4, 0.6]), cam_to_world=poses,
               split=np.array(["train", "test", "train", "test"]))
    # stack 3 is 0.13 s late: frame 3 of stack 1 (t = 0.6) pairs with frame 2 (0.53), not 3 (0.73)
    s3 = Stack(times=np.array([0.13, 0.33, 0.53, 0.73]), cam_to_world=poses + 1.0)
    tps = make_test_points(SimpleNamespace(stacks={1: s1, 3: s3}, room_dir=None))
    assert [(t.index1, t.index3) for t in tps] == [(1, 0), (3, 2)]
    assert tps[1].time == 0.6 and tps[1].time3 == pytest.approx(0.53)
    np.testing.assert_allclose(tps[1].pose3, poses[2] + 1.0)
    np.testing.assert_allclose(tps[1].origin, [3.0, 0.0, 0.2])
    assert tps[1].height == pytest.approx(0.2)
