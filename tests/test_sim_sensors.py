"""Sensor models and rig of the simulator (docs/method.md 5): mounting from the sample, USS vs bench."""

from __future__ import annotations

import numpy as np
import pytest

from virus_nerf.data.voxel_map import VoxelMap
from virus_nerf.sensors import irs
from virus_nerf.sensors.geometry import invert_pose
from virus_nerf.sensors.rig import CAMERA_INTRINSICS, camera_in_lidar
from virus_nerf.sim.scene import Box, Material, Scene, SceneObject
from virus_nerf.sim.sensors import (
    IrsModel,
    LidarModel,
    UssModel,
    format_bench_table,
    irs_row_mm,
    uss_bench_comparison,
)

# camera looking along world +x (OpenCV axes: x right = -y world, y down = -z world)
LOOK_X = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])


def wall_at(x: float, smooth: bool = True) -> Scene:
    return Scene([SceneObject("wall", "wall", (Box((x + 0.05, 0, 0), (0.1, 20, 20)),),
                              Material((0.8, 0.8, 0.8), smooth=smooth, ir_reflectance=0.8))])


def test_mounting_matches_the_sample(sample_recording):
    for s, st in sample_recording.stacks.items():
        t = invert_pose(st.lidar_to_world) @ st.cam_to_world  # (N, 4, 4)
        np.testing.assert_allclose(camera_in_lidar(s)[None].repeat(len(t), 0), t, atol=2e-6)
        assert st.intrinsics.fx == pytest.approx(CAMERA_INTRINSICS[s].fx)


def test_mounting_facts():
    for s, yaw_sign in ((1, -1), (3, 1)):
        r = camera_in_lidar(s)[:3, :3]
        yaw = np.degrees(np.arctan2(r[1, 2], r[0, 2]))
        pitch = np.degrees(np.arcsin(r[2, 2]))
        assert yaw_sign * yaw == pytest.approx(14.5, abs=0.5)
        assert 4.5 < pitch < 6.5
        assert r[2, 1] > 0.99  # image y (down) points up: mounted upside down
    assert np.linalg.norm(camera_in_lidar(1)[:3, 3] - camera_in_lidar(3)[:3, 3]) == pytest.approx(0.28, abs=0.02)


def test_irs_on_a_flat_wall_gives_its_z_depth_in_every_zone():
    rng = np.random.default_rng(0)
    grid, std = IrsModel(sigma0=0.0, sigma_per_m=0.0).measure(wall_at(2.0), LOOK_X, rng)
    np.testing.assert_allclose(grid, 2.0, atol=1e-9)  # z-depth, not radial: all zones equal
    grid, _ = IrsModel().measure(wall_at(5.0), LOOK_X, rng)
    assert np.isnan(grid).all()  # beyond 4 m
    # sensor order on disk round-trips to the image zone order
    g = np.arange(64, dtype=float).reshape(8, 8) / 10 + 0.5
    mm, smm = irs_row_mm(g, np.full((8, 8), 0.02))
    np.testing.assert_allclose(irs.grid_from_measurements(mm) / 1000, g)
    assert (smm == 20).all()


def test_uss_first_echo_and_grazing_floor():
    rng = np.random.default_rng(0)
    m = UssModel(dropout=0.0)
    r = [m.measure(wall_at(1.5), LOOK_X, rng) for _ in range(50)]
    assert np.nanmean(r) == pytest.approx(1.5 + m.bias0 + m.bias_per_m * 1.5, abs=0.01)
    # only a smooth floor 0.6 m below: rays hit it at >= 72 deg incidence -> no echo
    floor = Scene([SceneObject("floor", "floor", (Box((0, 0, -0.65), (40, 40, 0.1)),), Material((0.5,) * 3))])
    assert np.isnan([m.measure(floor, LOOK_X, rng) for _ in range(20)]).all()


def test_uss_reach_is_the_datasheet_range_on_the_axis():
    """URM37 V5.0: 2-800 cm (datasheet, docs/uss-range.md): a wall 7.5 m ahead echoes, one at
    8.5 m does not; the reach shrinks to 2 m at the cone's edge (8 m * (1 - 0.75))."""
    rng = np.random.default_rng(0)
    m = UssModel(dropout=0.0)
    assert m.max_range == 8.0 and m.max_range * (1 - m.edge_loss) == pytest.approx(2.0)
    r = [m.measure(wall_at(7.5), LOOK_X, rng) for _ in range(10)]
    assert np.isfinite(r).all() and np.mean(r) == pytest.approx(7.5 + m.bias0 + m.bias_per_m * 7.5, abs=0.1)
    assert np.isnan([m.measure(wall_at(8.5), LOOK_X, rng) for _ in range(10)]).all()


def test_uss_reach_falls_off_towards_the_cone_edge():
    """A pole 0.1 m wide 26 deg off the axis (rho ~0.95 of the 27.5 deg half-angle): its rays reach
    at most 8 m * (1 - 0.75 * 0.85) = 2.9 m, so the pole echoes at 2 m and is silent at 4 m, where
    the same pole on the axis echoes."""
    rng = np.random.default_rng(0)
    m = UssModel(dropout=0.0)

    def pole(distance: float, bearing_deg: float) -> Scene:
        a = np.deg2rad(bearing_deg)
        return Scene([SceneObject("pole", "pole", (Box((distance * np.cos(a), distance * np.sin(a), 0), (0.1, 0.1, 20)),),
                                  Material((0.8,) * 3, smooth=False))])

    assert np.isfinite([m.measure(pole(2.0, 26.0), LOOK_X, rng) for _ in range(10)]).all()
    assert np.isnan([m.measure(pole(4.0, 26.0), LOOK_X, rng) for _ in range(10)]).all()
    assert np.isfinite([m.measure(pole(4.0, 0.0), LOOK_X, rng) for _ in range(10)]).all()


def test_uss_model_matches_the_bench(uss_bench_dir):
    rows = uss_bench_comparison(uss_bench_dir, n_model=100)
    print("\n" + format_bench_table(rows))
    assert [r.distance for r in rows] == [0.25, 0.5, 1.0, 2.0]
    for r in rows:
        assert abs(r.model_mean - r.bench_mean) < 0.015, r
        assert abs(r.model_std - r.bench_std) < 0.006, r


def test_lidar_scan_and_voxel_map():
    rng = np.random.default_rng(0)
    lid = LidarModel(sigma=0.0)
    pts = lid.scan(wall_at(3.0), np.eye(4), rng)
    assert len(pts) > 0 and np.allclose(pts[:, 0], 3.0, atol=1e-5)
    assert lid.dirs.shape == (16 * 900, 3)
    vm = VoxelMap(voxel=0.03, min_hits=2)
    vm.add(np.array([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [1.0, 1.0, 1.0]]))
    np.testing.assert_allclose(vm.points(), [[0.015, 0.015, 0.015]], atol=1e-7)


def test_voxel_map_hits_count_across_merges_and_give_the_same_map():
    """A voxel hit once before a merge and once after is kept (two hits), one hit in all is not;
    merging every few points gives the very map of no merging (a long drive's memory bound)."""
    vm = VoxelMap(voxel=0.03, min_hits=2, merge_every=0)  # merge after every scan
    vm.add(np.array([[0.01, 0.01, 0.01], [1.0, 1.0, 1.0]]))
    vm.add(np.array([[0.02, 0.02, 0.02]]))
    np.testing.assert_allclose(vm.points(), [[0.015, 0.015, 0.015]], atol=1e-7)
    rng = np.random.default_rng(1)
    scans = [rng.uniform(-0.3, 0.3, (int(rng.integers(1, 60)), 3)) for _ in range(40)]
    whole, merged = VoxelMap(), VoxelMap(merge_every=50)
    for pts in scans:
        whole.add(pts)
        merged.add(pts)
    assert len(whole.points()) > 10
    np.testing.assert_array_equal(merged.points(), whole.points())
