"""The ETHZ reader on the real one-second office sample (docs/method.md 4)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from virus_nerf.data.ethz import load_recording
from virus_nerf.sensors.geometry import transform_points


def test_counts_and_first_values(sample_recording):
    rec = sample_recording
    assert sorted(rec.stacks) == [1, 3]
    for s in rec.stacks.values():
        assert len(s) == 5
        assert s.cam_to_world.shape == (5, 4, 4)
        assert s.irs_range.shape == (5, 8, 8)
    assert len(rec.lidar_paths) == 11
    assert rec.lidar_map().shape == (266008, 3)
    assert rec.stacks[1].uss_range[0] == pytest.approx(0.7504)
    intr = rec.stacks[1].intrinsics
    assert (intr.fx, intr.fy, intr.cx, intr.cy) == pytest.approx(
        (388.0472148, 388.3651136, 327.5759548, 244.2966786)
    )
    assert (intr.width, intr.height) == (640, 480)


def test_split_matches_file(sample_recording):
    for s in sample_recording.stacks.values():
        assert list(s.split) == ["train", "test", "train", "test", "train"]
        assert list(s.indices("test")) == [1, 3]


def test_images_rgb_and_depth_metres(sample_recording):
    s = sample_recording.stacks[1]
    img = s.image(0)
    assert img.shape == (480, 640, 3) and img.dtype == np.uint8
    depth = s.depth(0)
    raw = np.load(s.depth_paths[0])
    assert depth.dtype == np.float32
    assert np.isnan(depth[raw == 0]).all()
    valid = (raw > 0) & (raw < 65535)
    np.testing.assert_allclose(depth[valid], raw[valid] / 1000.0, rtol=1e-6)


def test_camera_below_lidar_and_poses_are_rigid(sample_recording):
    for s in sample_recording.stacks.values():
        rot = s.cam_to_world[:, :3, :3]
        np.testing.assert_allclose(rot @ np.swapaxes(rot, 1, 2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-9)
        np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-9)
        height = s.cam_to_world[:, 2, 3] - s.lidar_to_world[:, 2, 3]
        assert np.all((height > -0.2) & (height < -0.1)), height  # ~0.15 m below the LiDAR


def test_lidar_scans_land_on_the_map(sample_recording):
    rec = sample_recording
    tree = cKDTree(rec.lidar_map())
    for k, t in enumerate(rec.lidar_times):
        pts = transform_points(rec.lidar_pose_at(t), rec.lidar_scan(k))
        dist, _ = tree.query(pts[::7])
        assert np.median(dist) < 0.05, (k, np.median(dist))


def test_odometry_poses_missing_is_a_clear_error(sample_dir):
    from virus_nerf.errors import DataFormatError

    with pytest.raises(DataFormatError, match="poses_cam_sync1.csv"):
        load_recording(sample_dir, "office", poses="odometry")
