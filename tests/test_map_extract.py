"""The one map extraction (maps/extract.py) shared by `export` and the Mapper (issue 27, item 4)."""

from __future__ import annotations

import numpy as np
import pytest

from virus_nerf.errors import UsageError
from virus_nerf.maps.extract import (
    camera_height,
    check_raster,
    occupancy_map,
    probability_map,
    spread_positions,
)
from virus_nerf.maps.occupancy import FREE, OCCUPIED, UNKNOWN


def test_positions_are_spread_evenly_with_both_ends():
    pos = np.arange(30, dtype=float).reshape(10, 3)  # rows 0..9
    picked = spread_positions(pos, 4)  # linspace(0, 9, 4) = 0, 3, 6, 9
    np.testing.assert_array_equal(picked[:, 0], [0.0, 9.0, 18.0, 27.0])
    assert len(spread_positions(pos, 50)) == 10  # never more than given
    assert spread_positions(np.zeros((0, 3)), 5).shape == (0, 3)


def test_camera_height_is_the_main_stacks_median():
    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, 2, 3] = [0.5, 0.7, 2.0, 0.9, 5.0]
    stacks = np.array([1, 1, 3, 1, 3])
    assert camera_height(poses, stacks) == pytest.approx(0.7)  # median of 0.5, 0.7, 0.9
    assert camera_height(poses[2:3], stacks[2:3]) == pytest.approx(2.0)  # no stack 1: all stacks
    assert camera_height(poses[:0], stacks[:0], default=1.25) == 1.25


def test_a_raster_too_large_or_not_positive_is_one_line_naming_the_argument():
    lo, hi = np.array([0.0, 0.0]), np.array([10.0, 5.0])
    assert check_raster("--resolution", lo, hi, 0.5) == (20, 10)
    with pytest.raises(UsageError, match=r"--resolution 1e-05: the 10.0 x 5.0 m box would be a 1000000x500000 px"):
        check_raster("--resolution", lo, hi, 1e-5)
    with pytest.raises(UsageError, match="Mapper.map2d resolution 0: expected a positive number"):
        check_raster("Mapper.map2d resolution", lo, hi, 0)


class _Wall:
    """A range model: a wall at x = 2 m, nothing elsewhere."""

    def ranges(self, origins, directions):
        d = np.asarray(directions)[:, 0]
        t = (2.0 - np.asarray(origins)[:, 0]) / np.where(d > 1e-9, d, np.nan)
        return np.where(d > 1e-9, t, np.nan)


def test_the_map_is_the_scans_and_unknown_where_no_sensor_looked():
    lo, hi, res = np.array([0.0, -1.0]), np.array([3.0, 1.0]), 0.5  # 6 x 4 pixels
    observed = np.ones((6, 4), dtype=bool)
    observed[5, :] = False  # x in [2.5, 3): nobody looked
    m = occupancy_map(_Wall(), np.array([[0.25, 0.25, 1.0]]), lo, hi, res, 360, 30, observed)
    grid = m.image[::-1].T  # [ix, iy]
    assert grid[4, 2] == OCCUPIED  # the wall cell x in [2, 2.5) on the scan's row
    assert grid[1, 2] == FREE  # passed by the +x ray
    assert (grid[5, :] == UNKNOWN).all()


def test_the_probability_map_is_half_where_no_sensor_looked():
    prob = np.full((4, 2, 2), 0.9)  # a 4 x 2 x 2 grid over [0, 4] x [0, 2] x [0, 2]
    observed = np.ones((4, 2), dtype=bool)
    observed[0, 0] = False
    m = probability_map(prob, (0, 0, 0), (4, 2, 2), 1.0, 0.1, np.array([0.0, 0.0]), np.array([4.0, 2.0]), 1.0,
                        observed)
    p = 1.0 - m.image[::-1].T / 255.0  # [ix, iy]
    assert p[0, 0] == pytest.approx(0.5, abs=0.003)
    assert p[1, 1] == pytest.approx(0.9, abs=0.003)
