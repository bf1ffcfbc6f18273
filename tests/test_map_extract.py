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
    poses[:, 2, 3] = [0.5, 0.5, 0.5, 1.7, 0.5]  # a median, not a mean (0.8): one camera lifted
    assert camera_height(poses[:4], np.ones(4, dtype=int)) == 0.5


def test_a_raster_too_large_or_not_positive_is_one_line_naming_the_argument():
    lo, hi = np.array([0.0, 0.0]), np.array([10.0, 5.0])
    assert check_raster("--resolution", lo, hi, 0.5) == (20, 10)
    with pytest.raises(UsageError, match=r"--resolution 1e-05: the 10.0 x 5.0 m box would be a 1000000x500000 px"):
        check_raster("--resolution", lo, hi, 1e-5)
    with pytest.raises(UsageError, match="Mapper.map2d resolution 0: expected a positive number"):
        check_raster("Mapper.map2d resolution", lo, hi, 0)


def test_a_raster_whose_working_memory_cannot_fit_is_refused_before_any_work():
    """The pixel cap alone let `export --resolution 0.001` compute for minutes and die in numpy:
    the rasters' working memory (64 bytes a pixel, D48, D101) is checked against half of memory."""
    lo, hi = np.array([0.0, 0.0]), np.array([10.0, 5.0])
    # 0.001 m: 10000 x 5000 = 50 M px, under the 100 M px cap; 50e6 * 64 B = 2.98 GiB
    assert check_raster("--resolution", lo, hi, 0.001, limit=6 * 2**30) == (10000, 5000)  # 3 GiB allowed
    with pytest.raises(UsageError, match=r"^--resolution 0.001: the 10000x5000 px map's rasters: would need 3.0 GiB "
                                         r"and this machine has 4.0 GiB; expected a coarser resolution$"):
        check_raster("--resolution", lo, hi, 0.001, limit=4 * 2**30)


def test_scan_counts_in_chunks_are_the_counts_of_the_whole():
    """Pass points go in chunks (bounded memory at a fine resolution); the counts are exact sums,
    so any chunking gives the same raster: a chunk of one ray each against the whole at once."""
    from virus_nerf.maps import occupancy

    rng = np.random.default_rng(3)
    origins = rng.uniform(1, 4, (50, 2))
    ang = rng.uniform(-np.pi, np.pi, 50)
    dirs = np.stack([np.cos(ang), np.sin(ang)], 1)
    ranges = rng.uniform(0.2, 3.0, 50)
    lo, hi = np.array([0.0, 0.0]), np.array([5.0, 5.0])
    whole = occupancy.scan_counts(origins, dirs, ranges, lo, hi, 0.05)
    old = occupancy.SCAN_POINTS_PER_CHUNK
    try:
        occupancy.SCAN_POINTS_PER_CHUNK = 7  # below one ray's points: every ray alone
        chunked = occupancy.scan_counts(origins, dirs, ranges, lo, hi, 0.05)
    finally:
        occupancy.SCAN_POINTS_PER_CHUNK = old
    assert np.array_equal(whole[0], chunked[0]) and np.array_equal(whole[1], chunked[1])
    # one ray along +x from (1.01, 2.52) of 1.01 m at 0.05 m: points every 0.025 m while at least
    # one pixel before the end (floor(0.96 / 0.025) = 38 points, x 1.01..1.935): pixels ix 20..38
    # twice each (no point on a pixel edge); its end (x 2.02) in pixel 40
    passes, hits = occupancy.scan_counts(np.array([[1.01, 2.52]]), np.array([[1.0, 0.0]]), np.array([1.01]),
                                         lo, hi, 0.05)
    assert hits[40, 50] == 1 and hits.sum() == 1
    assert passes.sum() == 38 and passes[20, 50] == 2 and passes[38, 50] == 2 and passes[39, 50] == 0


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


def test_the_probability_map_is_unknown_where_no_sensor_looked():
    """mode raw: round(100 p) where a sensor looked, 255 (map_server's -1) where none did (before:
    p = 0.5, which map_server served as a probability a trinary costmap takes for free)."""
    prob = np.full((4, 2, 2), 0.9)  # a 4 x 2 x 2 grid over [0, 4] x [0, 2] x [0, 2]
    observed = np.ones((4, 2), dtype=bool)
    observed[0, 0] = False
    m = probability_map(prob, (0, 0, 0), (4, 2, 2), 1.0, 0.1, np.array([0.0, 0.0]), np.array([4.0, 2.0]), 1.0,
                        observed)
    value = m.image[::-1].T  # [ix, iy]
    assert m.mode == "raw" and value[0, 0] == 255 and value[1, 1] == 90
    assert (value[observed] == 90).all()


class _LowWall:
    """A range model: a wall at x = 2 m whose top is 3 cm below the camera (z < 0.97 m)."""

    def ranges(self, origins, directions):
        o, d = np.asarray(origins), np.asarray(directions)[:, 0]
        t = (2.0 - o[:, 0]) / np.where(d > 1e-9, d, np.nan)
        return np.where((d > 1e-9) & (o[:, 2] < 0.97), t, np.nan)


def test_the_maps_scans_sample_the_height_band_so_a_wall_below_the_camera_plane_is_kept():
    from virus_nerf.maps.extract import MAP_SCAN_HEIGHTS_M
    from virus_nerf.maps.scans import scan_ranges

    origins, _, r = scan_ranges(_LowWall(), np.array([0.25, 0.25, 1.0]), 360, MAP_SCAN_HEIGHTS_M)
    assert origins[:3, 2] == pytest.approx([0.95, 1.0, 1.05])  # ray i at heights[i % 3]
    assert np.isnan(scan_ranges(_LowWall(), np.array([0.25, 0.25, 1.0]), 360)[2]).all()  # one plane: no wall
    assert r[0] == pytest.approx(1.75) and np.isnan(r[1]) and np.isnan(r[2])  # +x: only the low ray ends
    lo, hi, res = np.array([0.0, -1.0]), np.array([3.0, 1.0]), 0.5
    m = occupancy_map(_LowWall(), np.array([[0.25, 0.25, 1.0]]), lo, hi, res, 360, 30, np.ones((6, 4), dtype=bool))
    grid = m.image[::-1].T  # [ix, iy]
    # the wall cell on the scan's row: a third of the rays through it end there (the low ones)
    # and two thirds pass, and a third is at least half of two thirds: occupied
    assert grid[4, 2] == OCCUPIED
    assert grid[1, 2] == FREE


class _PalletBeforeWall:
    """A range model: a wall at x = 3.1 m, and before it a box from x = 2.1 m whose top is 10 cm
    below the camera (z < 0.9 m): only rays starting below 0.9 m meet the box."""

    wall_x = 3.1

    def ranges(self, origins, directions):
        o, d = np.asarray(origins), np.asarray(directions)[:, 0]
        front = np.where(o[:, 2] < 0.9, 2.1, self.wall_x)
        t = (front - o[:, 0]) / np.where(d > 1e-9, d, np.nan)
        return np.where(d > 1e-9, t, np.nan)


def test_what_the_rays_below_the_band_hit_is_occupied_and_their_passes_claim_nothing():
    from virus_nerf.maps.extract import MAP_LOW_HEIGHTS_M, MAP_SCAN_HEIGHTS_M
    from virus_nerf.maps.scans import scan_ranges

    camera = np.array([0.25, 0.25, 1.0])
    _, _, band = scan_ranges(_PalletBeforeWall(), camera, 360, MAP_SCAN_HEIGHTS_M)
    _, _, low = scan_ranges(_PalletBeforeWall(), camera, 180, MAP_LOW_HEIGHTS_M)
    assert band[0] == pytest.approx(2.85) and low[0] == pytest.approx(1.85)  # +x: over the box, into it
    lo, hi, res = np.array([0.0, -1.0]), np.array([3.5, 1.0]), 0.25  # 14 x 8 pixels
    m = occupancy_map(_PalletBeforeWall(), camera[None], lo, hi, res, 360, 30, np.ones((14, 8), dtype=bool))
    row = m.image[::-1].T[:, 5]  # [ix] on the scan's row, y in [0.25, 0.5)
    # the band's rays pass from the camera (x 0.25) to a pixel before their end (x 2.625) and end at
    # it (x in [3, 3.25)); the low rays end at the box's front (x in [2, 2.25)), which the band
    # passed: occupied there; behind it no low ray looked, so what the band passed there is
    # unknown (MAP_LOW_SHADOW_M, 1 m from the front: x up to 3.1); the low rays' passes claim nothing
    assert list(row[1:13]) == [FREE] * 7 + [OCCUPIED, UNKNOWN, UNKNOWN, UNKNOWN, OCCUPIED]


class _TableBeforeBox(_PalletBeforeWall):
    """The band's rays (from z >= 0.9 m) end on a table's edge at x = 1.1 m; the low rays pass
    under it and end on a box at x = 2.1 m, where no band ray looked."""

    wall_x = 1.1


def test_the_low_rays_occupy_only_what_the_band_called_free():
    """What the low rays end on beyond the band's view stays unknown: the low rays add obstacles
    where the band's rays said free (D60), they do not map what the band never saw."""
    from virus_nerf.maps.extract import scan_map

    camera = np.array([0.25, 0.25, 1.0])
    lo, hi, res = np.array([0.0, -1.0]), np.array([3.5, 1.0]), 0.25
    row = scan_map(_TableBeforeBox(), camera[None], lo, hi, res, 360).image[::-1].T[:, 5]  # [ix], y in [0.25, 0.5)
    assert list(row[1:3]) == [FREE] * 2 and row[4] == OCCUPIED  # the table's edge at x 1.1
    assert (row[5:] == UNKNOWN).all()  # beyond it the band saw nothing: the box's pixel 8 stays unknown


def _evidence(surfaces=(), irs_hits=()):
    """RangeEvidence with IRS hits (K, 2) and stereo surface points (P, 2), no USS echo."""
    from virus_nerf.maps.planner import RangeEvidence

    return RangeEvidence(np.asarray(irs_hits, dtype=float).reshape(-1, 2), np.zeros((0, 2)), np.zeros(0), np.zeros(0),
                         surfaces=np.asarray(surfaces, dtype=float).reshape(-1, 2))


def test_a_low_end_casts_its_shadow_only_near_a_surface_the_cameras_measured():
    from virus_nerf.maps.extract import scan_map

    camera = np.array([[0.25, 0.25, 1.0]])
    lo, hi, res = np.array([0.0, -1.0]), np.array([3.5, 1.0]), 0.25  # as the test above: 14 x 8 pixels

    def row(evidence):
        return scan_map(_PalletBeforeWall(), camera, lo, hi, res, 360, evidence).image[::-1].T[1:13, 5]

    shadow = [FREE] * 7 + [OCCUPIED, UNKNOWN, UNKNOWN, UNKNOWN, OCCUPIED]  # the test above's row
    assert list(row(None)) == shadow
    # stereo points on the box's front (x 2.1, where the low rays end): the ends are real, their
    # shadow stays
    front = [[2.1, 0.3], [2.15, 0.45]]
    assert list(row(_evidence(surfaces=front))) == shadow
    # stereo points only on the wall (x 3.1, 1 m behind the ends): nothing measured the ends, which
    # stay occupied (the scan rule) but cast no shadow; what the band passed behind them (to x 2.625)
    # is free
    wall = [[3.1, 0.3], [3.1, 0.4]]
    assert list(row(_evidence(surfaces=wall))) == [FREE] * 7 + [OCCUPIED, FREE, FREE, UNKNOWN, OCCUPIED]
    assert list(row(_evidence())) == shadow  # no stereo point at all (a run without stereo): D64's rule


class _PalletBeforeFarWall(_PalletBeforeWall):
    """The same box from x = 2.1 m, its wall 1 m farther: at x = 4.1 m."""

    wall_x = 4.1


def test_the_shadow_reaches_half_a_metre_in_a_small_fitted_room():
    from virus_nerf.maps.extract import low_shadow_depth, scan_map

    camera = np.array([[0.25, 0.25, 1.0]])
    lo, hi, res = np.array([0.0, -1.0]), np.array([4.5, 1.0]), 0.25  # 18 x 8 pixels

    def row(shadow):
        return list(scan_map(_PalletBeforeFarWall(), camera, lo, hi, res, 360, shadow=shadow).image[::-1].T[1:17, 5])

    # the low rays end at the box's front (x 2.1, pixel [2.0, 2.25)); the band passes to x 3.625 and
    # ends at the wall (x 4.1, pixel [4.0, 4.25)); the shadow covers the pixels its rays from the
    # front pass: to x 3.1 (1 m) through pixel [3.0, 3.25), to x 2.6 (0.5 m) through [2.5, 2.75)
    assert row(1.0) == [FREE] * 7 + [OCCUPIED] + [UNKNOWN] * 4 + [FREE, FREE, UNKNOWN, OCCUPIED]
    assert row(0.5) == [FREE] * 7 + [OCCUPIED] + [UNKNOWN] * 2 + [FREE] * 4 + [UNKNOWN, OCCUPIED]
    # an office's fitted box (9.2 x 8.2 m) and one of exactly 12 m: 0.5 m; a common area's 18.2 m
    # box or a grown box of any size: 1 m (D111)
    assert low_shadow_depth((-4.6, -4.1), (4.6, 4.1), growing=False) == 0.5
    assert low_shadow_depth((0.0, 0.0), (12.0, 3.0), growing=False) == 0.5
    assert low_shadow_depth((-9.1, -6.1), (9.1, 6.1), growing=False) == 1.0
    assert low_shadow_depth((-4.6, -4.1), (4.6, 4.1), growing=True) == 1.0


class _NothingStops:
    """A range model whose rays nothing stops (the grid emptied every wall): NaN everywhere."""

    def ranges(self, origins, directions):
        return np.full(len(origins), np.nan)


def test_a_ray_nothing_stops_is_free_up_to_the_first_surface_a_sensor_touched():
    from virus_nerf.maps.extract import scan_map, through_lengths

    # the box x in [0, 5], y in [-1, 1.5] at 0.25 m; the camera at (0.25, 0.25), its row y in [0.25, 0.5)
    camera = np.array([[0.25, 0.25, 1.0]])
    lo, hi, res = np.array([0.0, -1.0]), np.array([5.0, 1.5]), 0.25
    o, d = np.array([[0.25, 0.25]]), np.array([[1.0, 0.0]])
    # +x: the box's side 4.75 m away, free to 1 m before it (MAP_THROUGH_MARGIN_M)
    assert through_lengths(o, d, np.zeros((0, 2)), lo, hi, res) == pytest.approx([3.75])
    # an IRS hit at x 2.05: its pixel (x 2.0-2.25) is the only one within 0.1 m of it, entered at x 2.0
    assert through_lengths(o, d, np.array([[2.05, 0.3]]), lo, hi, res) == pytest.approx([1.75])

    def row(evidence):
        return scan_map(_NothingStops(), camera, lo, hi, res, 360, evidence).image[::-1].T[:, 5]

    assert (row(None) == UNKNOWN).all()  # the scans alone: a ray that ended nowhere claims nothing
    # +x, the pass points every half pixel up to a pixel short of the end: x 0.25 .. 3.875 (1.875
    # with the hit); pixel 0 is passed by the rays leaving up and to the left
    assert list(row(_evidence())) == [FREE] * 16 + [UNKNOWN] * 4
    assert list(row(_evidence(irs_hits=[[2.05, 0.3]]))) == [FREE] * 8 + [UNKNOWN] * 12


def test_a_lone_low_end_occupies_its_pixel_only_where_a_sensor_backs_it():
    from virus_nerf.maps.extract import lone_unsupported

    # 0.1 m pixels from (0, 0); occupied: a lone pixel [2, 2] (centre (0.25, 0.25)) met by one ray, a
    # lone pixel [2, 6] met by two, and two touching pixels [6, 2], [6, 3] met by one each
    occupied = np.zeros((9, 9), dtype=bool)
    hits = np.zeros((9, 9), dtype=np.int64)
    for ix, iy, n in ((2, 2, 1), (2, 6, 2), (6, 2, 1), (6, 3, 1)):
        occupied[ix, iy], hits[ix, iy] = True, n
    lo = np.zeros(2)

    def lone(support):
        return sorted(map(tuple, np.argwhere(lone_unsupported(occupied, hits, _evidence(irs_hits=support), lo, 0.1))))

    far = [[0.85, 0.85]]  # 0.85 m from every occupied pixel: backs none
    assert lone(far) == [(2, 2)]  # only the lone, once-met pixel; two ends or a neighbour keep a pixel
    assert lone([[0.25, 0.44]]) == []  # a support point 0.19 m from its centre (MAP_LOW_SUPPORT_M 0.2) backs it
    assert lone([[0.25, 0.46]]) == [(2, 2)]  # 0.21 m: not
    assert lone(np.zeros((0, 2))) == []  # no stereo point or IRS hit at all: every end stays


class _PostInRing:
    """A round room (a wall 3 m around the z axis) with a post of 1 cm radius and 0.9 m high at 2 m
    from the axis, 0.5 deg from +x: the cameras at 1.0 m look over it, and of the low rays (0.85 and
    0.7 m) only the one leaving at 0.5 deg meets it."""

    post = 2.0 * np.array([np.cos(np.deg2rad(0.5)), np.sin(np.deg2rad(0.5))])

    def ranges(self, origins, directions):
        o, d = np.asarray(origins, float), np.asarray(directions, float)
        d2 = d[:, :2] / np.linalg.norm(d[:, :2], axis=1, keepdims=True)
        b = (o[:, :2] * d2).sum(1)
        wall = -b + np.sqrt(b**2 - (o[:, :2] ** 2).sum(1) + 9.0)  # |o + t d| = 3
        along = ((self.post - o[:, :2]) * d2).sum(1)
        miss2 = ((self.post - o[:, :2]) ** 2).sum(1) - along**2
        post = np.where((miss2 <= 0.01**2) & (along > 0) & (o[:, 2] < 0.9), along - np.sqrt(np.maximum(0.01**2 - miss2, 0)),
                        np.inf)
        return np.minimum(wall, post)


def test_scan_map_drops_a_lone_low_end_no_sensor_backs():
    from virus_nerf.maps.extract import scan_map

    camera = np.array([[0.0, 0.0, 1.0]])
    lo, hi, res = np.array([-3.5, -3.5]), np.array([3.5, 3.5]), 0.1  # 70 x 70 pixels; the post (1.99, 0.01) in [54, 35]

    def post_pixel(evidence):
        grid = scan_map(_PostInRing(), camera, lo, hi, res, 360, evidence).image[::-1].T  # [ix, iy]
        assert grid[45, 35] == FREE and grid[65, 35] == OCCUPIED  # the band passed over it; the wall
        return grid[54, 35]

    assert post_pixel(None) == OCCUPIED  # the scans alone: the low rays' end
    assert post_pixel(_evidence(irs_hits=[[-2.9, 0.0]])) == FREE  # a lone end, one ray, nothing near it
    assert post_pixel(_evidence(surfaces=[[2.0, 0.1]])) == OCCUPIED  # a stereo point 0.07 m from its centre (1.95, 0.05)
    assert post_pixel(_evidence(irs_hits=[[2.0, -0.1]])) == OCCUPIED  # an IRS hit 0.16 m from it
    assert post_pixel(_evidence()) == OCCUPIED  # no stereo point or IRS hit at all: kept
    # a USS echo from the axis along +x: its arc (+-27.5 deg at its range, every degree) passes 0.016 m
    # from the pixel's centre (1.95, 0.05) at 1.95 m (its 1 deg point (1.9497, 0.0340), within
    # USS_EXPLAINED_M, 0.05 m: backed), 0.35 m at 2.3 m (not)
    from virus_nerf.maps.planner import RangeEvidence

    def echo(r):
        return RangeEvidence(np.array([[-2.9, 0.0]]), np.zeros((1, 2)), np.zeros(1), np.array([r]))

    assert post_pixel(echo(1.95)) == OCCUPIED
    assert post_pixel(echo(2.3)) == FREE


def test_near_surfaces_is_a_distance_to_the_nearest_surface_point():
    from virus_nerf.maps.extract import near_surfaces

    points = np.array([[0.0, 0.0], [0.0, 0.2], [np.nan, 0.0]])
    out = near_surfaces(points, np.array([[0.05, 0.05], [3.0, 3.0]]), 0.1)  # 0.071 m, 0.158 m, never
    assert out.tolist() == [True, False, False]
    assert not near_surfaces(points, np.zeros((0, 2)), 0.1).any()


class _BoxSeenFromBothSides:
    """A range model: walls at x = -0.3 m and 4.2 m; between them a box over x in [2.1, 2.6]
    (every y) whose top is 10 cm below the camera: rays starting below 0.9 m meet its front from
    the -x side and its back from the +x side."""

    def ranges(self, origins, directions):
        o, d = np.asarray(origins), np.asarray(directions)[:, 0]
        low = o[:, 2] < 0.9
        with np.errstate(divide="ignore", invalid="ignore"):
            fwd = np.where(low & (o[:, 0] < 2.1), (2.1 - o[:, 0]) / d, (4.2 - o[:, 0]) / d)
            back = np.where(low & (o[:, 0] > 2.6), (o[:, 0] - 2.6) / -d, (o[:, 0] + 0.3) / -d)
        return np.where(d > 1e-9, fwd, np.where(d < -1e-9, back, np.nan))


def test_behind_what_the_low_rays_met_only_what_other_low_rays_passed_stays_free():
    # cameras at x 0.3 and 3.8 (y 0.3, 1 m high), 0.25 m pixels over x in [-0.5, 4.5), pixel i
    # holding x in [-0.5 + i / 4, -0.25 + i / 4). The band passes over the box from both cameras
    # and ends at the walls (pixels 0 and 18; pixel 1 is the one before the -x wall, which the
    # pass points, every half pixel up to a pixel short of the end, reach from neither camera).
    # The low rays of the first camera end at the box's front (x 2.1, pixel 10) and pass pixels
    # 3-8; those of the second end at its back (x 2.6, pixel 12) and pass pixels 14-17. Behind the
    # front (x 2.1-3.1: pixels 10-13) and behind the back (x 2.6-1.6: pixels 12 down to 8), what no
    # low ray passed is unknown: the box's inside (pixel 11) and the pixel before each face (9,
    # 13); the two faces are occupied; pixel 8 stays free (passed by the first camera's low rays).
    cameras = np.array([[0.3, 0.3, 1.0], [3.8, 0.3, 1.0]])
    lo, hi, res = np.array([-0.5, -1.0]), np.array([4.5, 1.0]), 0.25  # 20 x 8 pixels
    m = occupancy_map(_BoxSeenFromBothSides(), cameras, lo, hi, res, 360, 30, np.ones((20, 8), dtype=bool))
    row = m.image[::-1].T[:, 5]  # [ix] on the cameras' row, y in [0.25, 0.5)
    assert list(row[:19]) == ([OCCUPIED, UNKNOWN] + [FREE] * 7 + [UNKNOWN, OCCUPIED, UNKNOWN, OCCUPIED, UNKNOWN]
                              + [FREE] * 4 + [OCCUPIED])


def test_behind_ends_covers_the_depth_beyond_the_ends_of_rays_that_met_an_occupied_pixel():
    from virus_nerf.maps.extract import behind_ends

    occupied = np.zeros((10, 2), dtype=bool)
    occupied[2, 0] = True  # x in [1, 1.5)
    origins = np.array([[0.0, 0.25], [0.0, 0.75]])
    dirs = np.array([[1.0, 0.0], [1.0, 0.0]])
    # the first ray ends in the occupied pixel (x 1.2): 1 m behind it is x 1.2 .. 2.2, pixels 2-4;
    # the second ends at the same x in a pixel that is not occupied: nothing behind it
    out = behind_ends(origins, dirs, np.array([1.2, 1.2]), occupied, 1.0, np.zeros(2), np.array([5.0, 1.0]), 0.5)
    assert np.flatnonzero(out[:, 0]).tolist() == [2, 3, 4] and not out[:, 1].any()
    assert not behind_ends(origins, dirs, np.array([1.2, 1.2]), occupied, 0.0, np.zeros(2),
                           np.array([5.0, 1.0]), 0.5).any()


def test_scan_rays_of_several_positions_turn_over_heights_and_start_at_the_first_angle():
    from virus_nerf.maps.scans import scan_rays

    origins, dirs = scan_rays(np.array([[0.0, 0.0, 1.0], [2.0, 0.0, 1.0]]), 4, (-0.3, -0.15), first_angle=np.pi / 4)
    h = np.sqrt(0.5)
    assert dirs[:4] == pytest.approx(np.array([[h, h, 0], [-h, h, 0], [-h, -h, 0], [h, -h, 0]]))
    assert np.array_equal(dirs[4:], dirs[:4])
    assert origins[:, 2] == pytest.approx([0.7, 0.85, 0.7, 0.85] * 2) and origins[4:, 0] == pytest.approx([2.0] * 4)


def test_grown_in_z_occupies_the_cells_above_and_below_each_occupied_cell():
    import torch

    from virus_nerf.maps.extract import grown_in_z

    occ = torch.zeros((2, 1, 6), dtype=torch.bool)
    occ[0, 0, 2] = True
    occ[1, 0, 0] = True
    grown = grown_in_z(occ, 1)
    assert grown[0, 0].tolist() == [False, True, True, True, False, False]
    assert grown[1, 0].tolist() == [True, True, False, False, False, False]  # clipped at the bottom
    assert grown_in_z(occ, 2)[0, 0].tolist() == [True, True, True, True, True, False]
    assert not occ[0, 0, 1]  # the input is not changed


class _GridScene:
    """A range model with an occupancy grid of 5 cells in z over z in [0, 1): a wall at x = 2 m
    that a ray meets only if the cell of its height is occupied (as the marcher skips empty
    cells); the grid holds only the cell z in [0.6, 0.8)."""

    class Grid:
        occupied = None

    wall_column = 0  # the grid column (y) the wall stands in

    def __init__(self):
        import torch

        self.grid = self.Grid()
        self.grid.occupied = torch.zeros((1, 1, 5), dtype=torch.bool)
        self.grid.occupied[0, 0, 3] = True

    fronts_asked = ()  # the `front` of each `ranges` call (a hard wall: the same range at any level)

    def ranges(self, origins, directions, occupied=None, front=None):
        self.fronts_asked = (*self.fronts_asked, front)
        occ = (self.grid.occupied if occupied is None else occupied)[0, self.wall_column].numpy()
        o, d = np.asarray(origins), np.asarray(directions)[:, 0]
        cell = np.clip(np.floor(o[:, 2] / 0.2).astype(int), 0, 4)
        t = (2.0 - o[:, 0]) / np.where(d > 1e-9, d, np.nan)
        return np.where((d > 1e-9) & occ[cell], t, np.nan)


def test_the_low_rays_march_the_grid_grown_by_a_cell_in_z_and_the_band_the_grid_as_trained():
    from virus_nerf.maps.extract import MAP_LOW_FRONT_OPACITY, low_ranges

    scene = _GridScene()
    origins = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.9], [0.0, 0.0, 0.3]])  # cells 2, 4 and 1
    dirs = np.array([[1.0, 0.0, 0.0]] * 3)
    assert np.isnan(scene.ranges(origins, dirs)).all()  # as trained: only cell 3 is occupied
    r = low_ranges(scene, origins, dirs)  # grown: cells 2, 3 and 4
    assert r[0] == pytest.approx(2.0) and r[1] == pytest.approx(2.0) and np.isnan(r[2])
    assert scene.fronts_asked == (None, MAP_LOW_FRONT_OPACITY)  # the low rays end at the opacity front (D94)
    low_ranges(scene, origins, dirs, front=None)  # a field still haze: at D / A
    assert scene.fronts_asked[-1] is None
    assert low_ranges(_LowWall(), origins[:1], dirs[:1]) == pytest.approx([2.0])  # a model without a grid: as before


def test_the_low_rays_end_at_the_opacity_front_once_the_field_has_trained_100_steps():
    from virus_nerf.maps.extract import MAP_LOW_FRONT_OPACITY, low_front_level

    assert MAP_LOW_FRONT_OPACITY == 0.1
    assert low_front_level(0) is None and low_front_level(99) is None  # a field of a few steps is haze
    assert low_front_level(100) == 0.1 and low_front_level(5000) == 0.1


def test_grown_around_occupies_the_26_neighbours_of_each_occupied_cell_clipped_at_the_borders():
    import torch

    from virus_nerf.maps.extract import grown_around

    occ = torch.zeros((4, 3, 5), dtype=torch.bool)
    occ[1, 1, 2] = True  # inside: its 3 x 3 x 3 block
    occ[3, 0, 0] = True  # in a corner: the 2 x 2 x 2 block inside the grid
    grown = grown_around(occ)
    expected = torch.zeros_like(occ)
    expected[0:3, 0:3, 1:4] = True
    expected[2:4, 0:2, 0:2] = True
    assert torch.equal(grown, expected)
    assert int(grown.sum()) == 27 + 8 - 2  # the blocks share cells (2, 0..1, 1)
    assert int(occ.sum()) == 2  # the input is not changed


class _GridSceneXY(_GridScene):
    """_GridScene with two columns in y: the wall at x = 2 m stands in column y = 1 only, and the
    grid holds the cell z in [0.6, 0.8) of column y = 0 only (a box top the grid left out)."""

    wall_column = 1

    def __init__(self):
        import torch

        self.grid = self.Grid()
        self.grid.occupied = torch.zeros((1, 2, 5), dtype=torch.bool)
        self.grid.occupied[0, 0, 3] = True


def test_the_low_rays_flagged_around_march_the_grid_grown_in_x_and_y_as_well():
    from virus_nerf.maps.extract import low_ranges

    scene = _GridSceneXY()
    origins = np.array([[0.0, 0.0, 0.7], [0.0, 0.0, 0.7], [0.0, 0.0, 0.1]])  # cells 3, 3 and 0
    dirs = np.array([[1.0, 0.0, 0.0]] * 3)
    # grown in z only, the wall's column stays empty: no ray meets it
    assert np.isnan(low_ranges(scene, origins, dirs)).all()
    # grown around, its cells 2, 3 and 4 are occupied: the second ray meets the wall, the third
    # (cell 0) does not
    r = low_ranges(scene, origins, dirs, around=np.array([False, True, True]))
    assert np.isnan(r[0]) and r[1] == pytest.approx(2.0) and np.isnan(r[2])


def test_the_map_flags_the_low_rays_15_cm_below_the_cameras_to_march_the_grid_grown_around(monkeypatch):
    import virus_nerf.maps.extract as extract

    seen = {}

    def spy(model, origins, directions, around=None, front=None):
        seen["z"], seen["around"], seen["front"] = np.asarray(origins)[:, 2].copy(), np.asarray(around).copy(), front
        return np.full(len(origins), np.nan)

    monkeypatch.setattr(extract, "low_ranges", spy)
    positions = np.array([[0.25, 0.25, 1.0], [0.5, 0.25, 1.2]])
    extract.scan_map(_LowWall(), positions, np.array([0.0, -1.0]), np.array([3.0, 1.0]), 0.5, 36)
    below = seen["z"] - np.repeat(positions[:, 2], 18)  # 18 low rays a position, -0.15 and -0.3 m in turn
    assert below[:4] == pytest.approx([-0.15, -0.3, -0.15, -0.3])
    assert np.array_equal(seen["around"], np.isclose(below, -0.15)) and seen["around"].sum() == 18
    assert seen["front"] == extract.MAP_LOW_FRONT_OPACITY  # scan_map's default: the opacity front (D94)
    extract.scan_map(_LowWall(), positions, np.array([0.0, -1.0]), np.array([3.0, 1.0]), 0.5, 36, low_front=None)
    assert seen["front"] is None


class _Ring:
    """A range model whose band rays (camera at z 1) end 1 m from where they start (D67's sheets
    around a camera) and whose low rays nothing stops."""

    def ranges(self, origins, directions):
        return np.where(origins[:, 2] > 0.9, 1.0, np.nan)


def test_the_stereo_cameras_sight_lines_free_what_the_scans_left_unknown_and_clear_no_end():
    from virus_nerf.maps.evidence import Rays2D
    from virus_nerf.maps.extract import scan_map
    from virus_nerf.maps.planner import RangeEvidence

    camera = np.array([[0.25, 0.25, 1.0]])
    lo, hi, res = np.array([0.0, -1.0]), np.array([3.5, 1.5]), 0.25  # 14 x 10 pixels, row 5: y in [0.25, 0.5)

    def row(evidence):
        return list(scan_map(_Ring(), camera, lo, hi, res, 360, evidence).image[::-1].T[:, 5])

    # the band's rays end on the ring, 14 of them in pixel 4 (x 1.0-1.25) of this row and one in
    # pixel 5, which none passes: free before them, unknown behind
    assert row(None) == [FREE] * 4 + [OCCUPIED] * 2 + [UNKNOWN] * 8
    # 50 sight lines along the row, free 2.4 m from x 0.25 (to x 2.65, pixel 10): what they passed
    # behind the ring is free; the ring's pixels, where band rays ended, stay occupied (a thin leg
    # beside a sight line in the same pixel keeps its pixel)
    sight = Rays2D(np.tile([0.25, 0.3], (50, 1)), np.tile([1.0, 0.0], (50, 1)), np.full(50, 2.4))
    evidence = RangeEvidence(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0), sight_lines=sight)
    assert row(evidence) == [FREE] * 4 + [OCCUPIED] * 2 + [FREE] * 5 + [UNKNOWN] * 3


class _TableTop:
    """A range model: a table top 4 cm thick at the camera's height (z 0.98-1.02 m) from x = 2.2 m,
    and a wall at x = 3.2 m: only the band's rays that start at the camera's own height meet the
    top; those 5 cm above and below it pass to the wall."""

    def ranges(self, origins, directions):
        o, d = np.asarray(origins), np.asarray(directions)[:, 0]
        front = np.where(np.abs(o[:, 2] - 1.0) < 0.02, 2.2, 3.2)
        t = (front - o[:, 0]) / np.where(d > 1e-9, d, np.nan)
        return np.where(d > 1e-9, t, np.nan)


def test_the_scan_rule_holds_height_by_height_so_a_thin_table_top_is_kept():
    from virus_nerf.maps.extract import MAP_SCAN_HEIGHTS_M, band_counts
    from virus_nerf.maps.occupancy import scan_counts, scan_rule_occupied

    # two scans of three rays along +x (ray i at MAP_SCAN_HEIGHTS_M[i % 3]) on a 7 x 1 raster of
    # 0.5 m: the middle rays end on the top in pixel 4, the others pass it and end on the wall in 6
    assert MAP_SCAN_HEIGHTS_M == (-0.05, 0.0, 0.05)
    origins = np.array([[0.3, 0.25, 1.0 + h] for _ in range(2) for h in MAP_SCAN_HEIGHTS_M])
    directions = np.tile([1.0, 0.0, 0.0], (6, 1))
    ranges = np.array([2.9, 1.9, 2.9] * 2)
    lo, hi = np.array([0.0, 0.0]), np.array([3.5, 0.5])
    passes, hits, occupied = band_counts(origins, directions, ranges, 3, lo, hi, 0.5)
    together = scan_counts(origins[:, :2], directions[:, :2], ranges, lo, hi, 0.5)
    assert np.array_equal(passes, together[0]) and np.array_equal(hits, together[1])
    # counted together the four rays that pass pixel 4 outvote the two that end there (2 < 8 / 2)...
    assert hits[4, 0] == 2 and passes[4, 0] == 8 and not scan_rule_occupied(passes, hits)[4, 0]
    # ...height by height the middle rays end there and none of their height passes it
    assert occupied[:, 0].tolist() == [False, False, False, False, True, False, True]
    # scans of 4 rays (not a multiple of the 3 heights): ray j of every scan is at height j % 3, so the
    # top's rays (j = 1) stay one height, 3 ends and no pass; grouped across scans (ray i % 3) each
    # height would get one end against three passes and lose the top
    origins4 = np.array([[0.3, 0.25, 1.0 + MAP_SCAN_HEIGHTS_M[j % 3]] for _ in range(3) for j in range(4)])
    ranges4 = np.array([2.9, 1.9, 2.9, 2.9] * 3)
    _, _, occupied4 = band_counts(origins4, np.tile([1.0, 0.0, 0.0], (12, 1)), ranges4, 4, lo, hi, 0.5)
    assert occupied4[:, 0].tolist() == [False, False, False, False, True, False, True]
    # the whole map: the top's pixel on the scan's row is occupied, the floor before it free
    lo, hi, res = np.array([0.0, -1.0]), np.array([3.5, 1.0]), 0.5
    m = occupancy_map(_TableTop(), np.array([[0.25, 0.25, 1.0]]), lo, hi, res, 360, 30, np.ones((7, 4), dtype=bool))
    grid = m.image[::-1].T  # [ix, iy]
    assert grid[4, 2] == OCCUPIED and grid[6, 2] == OCCUPIED
    assert (grid[1:4, 2] == FREE).all()
