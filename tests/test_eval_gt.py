"""GT ray caster on analytic rooms, and model scans through the RangeModel interface (docs/method.md 6.2, 6.3)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import horizontal_test_point

from virus_nerf.evaluation.gt import cast_rays, gt_scan, height_slice, rasterise
from virus_nerf.evaluation.metrics import nnd_samples, zone_metrics
from virus_nerf.evaluation.scans import model_scan
from virus_nerf.maps.scans import RangeModel, horizontal_directions, scan_angles

HALF = 2.0  # the square room spans [-2, 2]^2


def room_cloud(half: float = HALF, voxel: float = 0.03, heights=(-0.1, -0.07, -0.04, 0.5)) -> np.ndarray:
    """Voxel centres (P, 3) of the four walls of a square room, like the LiDAR map (3 cm voxels)."""
    s = np.arange(-half, half + 1e-9, voxel)
    walls = [np.stack([s, np.full_like(s, e)], 1) for e in (-half, half)]
    walls += [np.stack([np.full_like(s, e), s], 1) for e in (-half, half)]
    xy = np.concatenate(walls)
    return np.concatenate([np.column_stack([xy, np.full(len(xy), z)]) for z in heights])


def exact_square_ranges(origin: np.ndarray, half: float, n: int) -> np.ndarray:
    d = horizontal_directions(n)[:, :2]
    with np.errstate(divide="ignore"):
        tx = np.where(d[:, 0] != 0, (np.sign(d[:, 0]) * half - origin[0]) / d[:, 0], np.inf)
        ty = np.where(d[:, 1] != 0, (np.sign(d[:, 1]) * half - origin[1]) / d[:, 1], np.inf)
    return np.minimum(tx, ty)


def test_512_rays_hit_the_square_walls_within_raster_resolution():
    tp = horizontal_test_point(0.31, -0.47, -0.07)
    res, footprint = 0.02, 0.03
    gt = gt_scan(room_cloud(), tp, n_rays=512, band=0.05, res=res, footprint=footprint)
    assert len(gt.scan) == 512 and np.isfinite(gt.ranges).all()
    # every hit lies on the front face of the wall voxels: within footprint/2 + res of the wall
    wall_dist = HALF - np.abs(gt.scan.points).max(axis=1)
    assert wall_dist.min() >= -1e-9  # never beyond the wall
    assert wall_dist.max() <= footprint / 2 + res + 1e-9
    # and along each ray the range is the exact one up to that band (grazing rays aside)
    exact = exact_square_ranges(tp.origin_xy, HALF, 512)
    err = exact - gt.ranges
    assert np.median(err) == pytest.approx(footprint / 2, abs=res)
    # the points are where the rays are: angle k of scan_angles
    d = gt.scan.points - tp.origin_xy
    np.testing.assert_allclose(np.arctan2(d[:, 1], d[:, 0]) % (2 * np.pi), scan_angles(512), atol=1e-9)


def test_band_drops_points_at_other_heights_and_first_hit_wins():
    cloud = room_cloud(heights=(0.0,))
    box = np.array([[1.0, y, 0.0] for y in np.arange(-0.3, 0.31, 0.03)])  # a post 1 m ahead
    high = np.array([[0.5, y, 0.2] for y in np.arange(-0.3, 0.31, 0.03)])  # above the band
    tp = horizontal_test_point(0.0, 0.0, 0.0)
    gt = gt_scan(np.concatenate([cloud, box, high]), tp, n_rays=360, res=0.01, footprint=0.03)
    assert len(height_slice(np.concatenate([cloud, box, high]), 0.0, 0.05)) == len(cloud) + len(box)
    # ray 0 (+x): the post's front face at 1.0 - 0.015 (1 cm raster: within one cell)
    assert gt.ranges[0] == pytest.approx(0.985, abs=0.01)
    # ray 180 (-x): the wall at -2
    assert gt.ranges[180] == pytest.approx(1.985, abs=0.01)


def test_a_gt_scan_keeps_the_shared_map_not_a_copy_of_its_slice():
    # a long drive's thousands of test points each kept a copy of the slice (D59): now they
    # share the map, and the slice is cut when a plot asks for it
    cloud = np.array([[0.0, 0.0, 1.00], [1.0, 0.0, 1.04], [2.0, 0.0, 1.20], [3.0, 0.0, 0.96]])
    tp = horizontal_test_point(0.0, 0.0, 1.0)
    gts = [gt_scan(cloud, tp, n_rays=8, band=0.05) for _ in range(3)]
    assert all(g.map_slice.cloud is cloud for g in gts)
    # |z - 1.0| <= 0.05: the points at 1.00, 1.04 and 0.96, not the one at 1.20
    np.testing.assert_array_equal(gts[0].slice_xy, [[0.0, 0.0], [1.0, 0.0], [3.0, 0.0]])


def test_no_map_points_no_hits_and_origin_cell_ignored():
    tp = horizontal_test_point(0.0, 0.0, 0.0)
    gt = gt_scan(room_cloud(heights=(1.0,)), tp, n_rays=64)
    assert len(gt.scan) == 0 and np.isnan(gt.ranges).all()
    # an occupied cell at the origin itself is not a hit at distance 0 (docs/method.md 9.8)
    raster = rasterise(np.array([[0.0, 0.0], [1.0, 0.0]]), res=0.02, footprint=0.0)
    r = cast_rays(raster, np.array([0.001, 0.001]), np.array([[1.0, 0.0], [-1.0, 0.0]]))
    assert r[0] == pytest.approx(1.0 - 0.001, abs=0.021) and np.isnan(r[1])


class CircleRoom:
    """Analytic RangeModel: the inside of a vertical cylinder of radius R about the z axis."""

    def __init__(self, radius: float, miss_below_x: float | None = None) -> None:
        self.radius = radius
        self.miss_below_x = miss_below_x

    def ranges(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        o, d = origins[:, :2], directions[:, :2]
        a = (d * d).sum(1)
        b = 2 * (o * d).sum(1)
        c = (o * o).sum(1) - self.radius**2
        t = (-b + np.sqrt(b * b - 4 * a * c)) / (2 * a)
        if self.miss_below_x is not None:
            t = np.where(directions[:, 0] < self.miss_below_x, np.nan, t)
        return t


def test_model_scan_uses_the_gt_origin_and_rays_and_drops_misses():
    model = CircleRoom(2.5)
    assert isinstance(model, RangeModel)
    tp = horizontal_test_point(0.4, -0.3, 0.7)
    scan = model_scan(model, tp, n_rays=256)
    assert len(scan) == 256
    np.testing.assert_allclose(np.linalg.norm(scan.points, axis=1), 2.5, atol=1e-9)
    np.testing.assert_allclose(scan.origin, [0.4, -0.3])
    d = scan.points - scan.origin
    np.testing.assert_allclose(np.arctan2(d[:, 1], d[:, 0]) % (2 * np.pi), scan_angles(256), atol=1e-9)
    # rays with NaN (no hit) give no point, never one at the origin
    half = model_scan(CircleRoom(2.5, miss_below_x=0.0), tp, n_rays=256)
    assert len(half) == 128
    assert np.linalg.norm(half.points - half.origin, axis=1).min() > 1.0


def test_model_scan_of_the_room_scores_against_the_gt():
    """A perfect analytic model of the square room scores ~the raster offset; a 10 cm smaller one doesn't."""

    tp = horizontal_test_point(0.31, -0.47, 0.0)
    gt = gt_scan(room_cloud(heights=(0.0,)), tp, n_rays=512)

    class SquareModel:
        def __init__(self, half: float) -> None:
            self.half = half

        def ranges(self, origins, directions):
            o, d = origins[:, :2], directions[:, :2]
            with np.errstate(divide="ignore"):
                tx = np.where(d[:, 0] != 0, (np.sign(d[:, 0]) * self.half - o[:, 0]) / d[:, 0], np.inf)
                ty = np.where(d[:, 1] != 0, (np.sign(d[:, 1]) * self.half - o[:, 1]) / d[:, 1], np.inf)
            return np.minimum(tx, ty)

    good = zone_metrics(nnd_samples(model_scan(SquareModel(HALF), tp, 512).points, gt.scan.points, tp.origin_xy))
    bad = zone_metrics(nnd_samples(model_scan(SquareModel(HALF - 0.2), tp, 512).points, gt.scan.points, tp.origin_xy))
    assert good.zones["zone3"].acc_median < 0.03 and good.zones["zone3"].acc_inlier == 1.0
    assert bad.zones["zone3"].acc_median == pytest.approx(0.2 - 0.015, abs=0.02)
    assert bad.zones["zone3"].acc_too_close > 0.9
