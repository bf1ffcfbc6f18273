"""Whole-frame IRS and USS rays for the grid's start-up pass, against hand-computed geometry."""

import math

import numpy as np
import torch

from virus_nerf.sampler.frames import FrameStore
from virus_nerf.sampler.sensor_rays import irs_zone_rays


def _store(pose: np.ndarray, irs: np.ndarray, uss: float) -> FrameStore:
    return FrameStore(
        stack_ids=np.array([1]), rows=np.array([0]), times=np.array([0.0]), cam_to_world=pose[None],
        images=np.zeros((1, 2, 2, 3), np.uint8), depths_mm=None, uss_range=np.array([uss]),
        irs_range=irs[None], intrinsics={}, footprints={},
    )


def test_irs_zone_ray_is_the_zone_centre_with_z_depth_turned_into_ray_length():
    # camera 1 m up, looking along world +x (camera z -> world x, camera x -> world -y)
    pose = np.eye(4)
    pose[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    pose[:3, 3] = (2.0, 3.0, 1.0)
    irs = np.full((8, 8), np.nan)
    irs[3, 4] = 2.0  # image zone row 3, column 4: just right of and above the optical axis
    rays = irs_zone_rays(_store(pose, irs, 1.0), samples_per_axis=1)
    assert len(rays) == 64 and int(torch.isfinite(rays.ranges).sum()) == 1
    valid = rays.valid()
    a = math.radians(-22.5 + 4.5 * 45 / 8)  # horizontal angle of column 4's centre
    b = math.radians(-22.5 + 3.5 * 45 / 8)  # vertical angle of row 3's centre
    d_cam = np.array([math.tan(a), math.tan(b), 1.0])
    d_cam /= np.linalg.norm(d_cam)
    expected_dir = pose[:3, :3] @ d_cam
    np.testing.assert_allclose(valid.origins[0].numpy(), [2.0, 3.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(valid.directions[0].numpy(), expected_dir, atol=1e-6)
    assert valid.ranges[0].item() == np.float32(2.0 / d_cam[2])
    # the end point lies 2 m in front of the camera plane (z-depth)
    end = valid.origins[0].double() + valid.directions[0].double() * valid.ranges[0].double()
    assert abs(end[0].item() - 4.0) < 1e-5


def test_irs_sub_rays_cover_the_zone_and_share_its_z_depth():
    irs = np.full((8, 8), 1.5)
    rays = irs_zone_rays(_store(np.eye(4), irs, 1.0), samples_per_axis=3)
    assert len(rays) == 64 * 9
    z = (rays.directions[:, 2].double() * rays.ranges.double()).numpy()
    np.testing.assert_allclose(z, 1.5, rtol=1e-6)
