"""The planner's map (issue 42): the range sensors' evidence at camera height and the rules that
turn the NeRF's free pixels occupied where the IRS or an unexplained USS echo touched something.
Hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_map_safety import camera_looking

from virus_nerf.maps.evidence import irs_rays_2d, sensor_rays_2d, uss_rays_2d
from virus_nerf.maps.occupancy import FREE, OCCUPIED, UNKNOWN, from_image, to_image
from virus_nerf.maps.planner import (
    RangeEvidence,
    planner_image,
    track_free,
    track_points,
    unexplained_echoes,
    uss_arcs,
)


def test_irs_rays_at_camera_height_end_on_the_wall_they_measured():
    # a camera at (1, 0.5), 0.4 m high, looking along +x at a wall: every zone reads z-depth 2 m.
    # Sub-rays sit at elevations +-0.9375, +-2.8125, +-4.6875 ... deg (8 zones of 5.625 deg, 3
    # sub-rays each); their hits lie 2 tan(elev) = 0.033, 0.098, 0.164 m off the camera height,
    # so with a 0.1 m band two elevations a side stay: 4 x 24 azimuths = 96 rays
    pose = camera_looking(1.0, 0.5, 0.0, z=0.4)
    rays = irs_rays_2d(pose[None], np.full((1, 8, 8), 2.0), height=0.4, band=0.1)
    assert len(rays) == 96
    ends = rays.ends()
    np.testing.assert_allclose(ends[:, 0], 3.0, atol=1e-9)  # z-depth 2 m ahead, whatever the azimuth
    assert np.abs(ends[:, 1] - 0.5).max() == pytest.approx(2.0 * math.tan(math.radians(22.5 - 0.9375)))
    np.testing.assert_allclose(rays.ranges, np.hypot(2.0, ends[:, 1] - 0.5))  # horizontal distance
    np.testing.assert_allclose(rays.origins, np.tile([1.0, 0.5], (96, 1)))
    # invalid zones give nothing; 0.5 m above the camera the hits with 2 tan(elev) in [0.4, 0.6]
    # stay: elevations 12.1875, 14.0625, 15.9375 deg, 3 x 24 rays, still 2 m ahead
    assert len(irs_rays_2d(pose[None], np.full((1, 8, 8), np.nan), 0.4)) == 0
    up = irs_rays_2d(pose[None], np.full((1, 8, 8), 2.0), 0.9, band=0.1)
    assert len(up) == 72
    np.testing.assert_allclose(up.ends()[:, 0], 3.0, atol=1e-9)
    # the range evidence keeps each hit's sensor position (the 0.3 m band: every sub-ray within it)
    ev = RangeEvidence.of_frames(pose[None], np.array([np.nan]), np.full((1, 8, 8), 2.0), 0.4, ("camera", "irs"))
    assert len(ev.irs_hits) == len(ev.irs_origins) > 96
    np.testing.assert_allclose(ev.irs_origins, np.tile([1.0, 0.5], (len(ev.irs_hits), 1)))


def test_irs_rays_of_many_frames_come_in_frame_order_across_chunks_and_none_for_no_frame():
    """A drive longer than one chunk of frames (evidence.FRAMES_PER_CHUNK) gives each frame's 96
    rays of the hand case above, frame after frame; no frame gives no ray."""
    from virus_nerf.maps.evidence import FRAMES_PER_CHUNK

    n = FRAMES_PER_CHUNK + 3
    poses = np.stack([camera_looking(1.0 + 0.01 * k, 0.5, 0.0, z=0.4) for k in range(n)])
    rays = irs_rays_2d(poses, np.full((n, 8, 8), 2.0), height=0.4, band=0.1)
    assert len(rays) == 96 * n
    np.testing.assert_allclose(rays.origins[:, 0], np.repeat(1.0 + 0.01 * np.arange(n), 96), atol=1e-12)
    np.testing.assert_allclose(rays.ends()[:, 0], np.repeat(3.0 + 0.01 * np.arange(n), 96), atol=1e-9)
    assert len(irs_rays_2d(np.zeros((0, 4, 4)), np.zeros((0, 8, 8)), 0.4)) == 0


def test_a_uss_echo_is_a_fan_across_the_cone_ending_on_its_arc():
    pose = camera_looking(0.0, 0.0, math.pi / 2)  # looking along +y
    rays = uss_rays_2d(np.stack([pose, pose]), np.array([1.5, np.nan]), fan_step_deg=5.0)
    assert len(rays) == 12  # 55 / 5 + 1 rays for the echo, none for the frame without one
    ang = np.degrees(np.arctan2(rays.directions[:, 1], rays.directions[:, 0]))
    np.testing.assert_allclose(ang, 90.0 + np.linspace(-27.5, 27.5, 12))
    np.testing.assert_allclose(np.linalg.norm(rays.ends(), axis=1), 1.5)
    both = sensor_rays_2d(pose[None], np.array([1.5]), np.full((1, 8, 8), np.nan), 0.5, ("camera", "uss", "irs"))
    assert len(both) == 56  # 1 deg fan: 55 + 1 rays, no IRS reading
    assert len(sensor_rays_2d(pose[None], np.array([1.5]), np.full((1, 8, 8), np.nan), 0.5, ("camera",))) == 0


def test_an_echo_is_explained_by_an_occupied_pixel_near_its_arc():
    res, lo = 0.1, np.array([0.0, 0.0])
    occupied = np.zeros((40, 40), dtype=bool)  # [ix, iy]
    occupied[30, 20] = True  # the pixel of (3.05, 2.05)
    ev = RangeEvidence(np.zeros((0, 2)), np.array([[1.05, 2.05], [1.05, 2.05], [1.05, 2.05]]),
                       np.array([0.0, 0.0, math.pi]), np.array([2.0, 1.7, 1.0]))
    arcs = uss_arcs(ev)
    assert arcs.shape == (3, 56, 2)
    np.testing.assert_allclose(arcs[0, 27:29].mean(axis=0), [3.05, 2.05], atol=0.01)  # the arc's middle
    # echo 0 ends on the pixel; echo 1's arc passes 0.3 m short of it; echo 2 looks the other way
    np.testing.assert_array_equal(unexplained_echoes(occupied, arcs, lo, res, 0.1), [False, True, True])
    np.testing.assert_array_equal(unexplained_echoes(occupied, arcs, lo, res, 0.35), [False, False, True])


def test_an_echo_is_explained_within_one_pixel_of_the_map_by_default():
    # D91: USS_EXPLAINED_M is 0.05 m, one pixel of the 0.05 m map. Echoes from (1.025, 2.025) along
    # +x: the arc's middle at 2.00 m lies in the occupied pixel (3.025, 2.025), at 2.05 m in the pixel
    # beside it (0.05 m), at 2.10 m two pixels beyond (0.10 m; its other points, every degree, curve
    # back toward the sensor and away in y: none nearer); D47's 0.1 m explained all three
    res, lo = 0.05, np.zeros(2)
    occupied = np.zeros((80, 80), dtype=bool)  # [ix, iy]
    occupied[60, 40] = True
    ev = RangeEvidence(np.zeros((0, 2)), np.tile([[1.025, 2.025]], (3, 1)), np.zeros(3), np.array([2.0, 2.05, 2.1]))
    arcs = uss_arcs(ev)
    np.testing.assert_array_equal(unexplained_echoes(occupied, arcs, lo, res), [False, False, True])
    np.testing.assert_array_equal(unexplained_echoes(occupied, arcs, lo, res, 0.1), [False, False, False])


def test_the_planner_map_adds_irs_hits_and_unexplained_arcs_where_the_scans_said_free():
    res, lo = 0.1, np.array([0.0, 0.0])
    grid = np.full((40, 40), FREE, dtype=np.uint8)  # [ix, iy]
    grid[:, 30:] = UNKNOWN  # y >= 3 m: no sensor looked
    grid[30, 20] = OCCUPIED  # the NeRF's wall pixel at (3.05, 2.05)
    image = to_image(grid)
    ev = RangeEvidence(irs_hits=np.array([[0.55, 0.55]]),
                       uss_origins=np.array([[1.05, 2.05], [2.05, 0.55]]), uss_yaw=np.array([0.0, math.pi / 2]),
                       uss_range=np.array([2.0, 2.7]))
    out = from_image(planner_image(image, lo, res, ev))
    assert out[5, 5] == OCCUPIED  # the IRS hit (no sensor positions: every hit counts)
    # echo 0 ends on the NeRF's pixel: explained, nothing added around (3.05, 2.05)
    assert (out[25:40, 10:28] == grid[25:40, 10:28]).all()
    # echo 1 (from (2.05, 0.55) looking +y, 2.7 m) meets nothing: its arc is occupied where free...
    arc = uss_arcs(RangeEvidence(np.zeros((0, 2)), ev.uss_origins[1:], ev.uss_yaw[1:], ev.uss_range[1:]))[0]
    ij = np.floor((arc - lo) / res).astype(int)
    was_free = grid[ij[:, 0], ij[:, 1]] == FREE
    assert was_free.any() and (~was_free).any()
    assert (out[ij[was_free, 0], ij[was_free, 1]] == OCCUPIED).all()
    # ...and stays unknown where no sensor looked (the middle of the arc, y up to 3.25 m)
    assert (out[ij[~was_free, 0], ij[~was_free, 1]] == UNKNOWN).all()
    assert out[20, 35] == UNKNOWN
    changed = out != grid
    assert changed.sum() == 1 + len({tuple(p) for p in ij[was_free]})  # nothing else moved
    assert image[0, 0] == from_image(image)[0, 39]  # the input is untouched
    assert (from_image(image) == grid).all()


def test_an_irs_hit_marks_its_pixel_only_when_something_corroborates_it():
    from virus_nerf.maps.planner import corroborated_irs

    res, lo = 0.05, np.zeros(2)
    occupied = np.zeros((60, 60), dtype=bool)  # 3 x 3 m at 5 cm, [ix, iy]
    occupied[10, 30] = True  # a scan's end pixel at (0.525, 1.525)
    hits = np.array([
        [0.625, 1.525],  # 2 pixels (0.10 m) from the scan's end: corroborated
        [0.675, 1.525],  # 3 pixels (0.15 m), seen from one place
        [2.025, 0.525], [2.075, 0.575],  # neighbours seen from places 0.21 m apart: both corroborated
        [1.025, 2.525], [1.075, 2.525],  # neighbours seen from places 0.19 m apart
        [2.525, 2.025],  # a stereo point 0.19 m away
        [2.525, 1.025],  # a stereo point 0.21 m away
    ])
    origins = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 1.0], [1.12, 1.17], [2.0, 2.0], [2.0, 2.19],
                        [1.0, 2.0], [1.0, 1.0]])
    stereo = np.array([[2.525, 2.215], [2.525, 1.235]])
    ev = RangeEvidence(hits, np.zeros((0, 2)), np.zeros(0), np.zeros(0), stereo_points=stereo, irs_origins=origins)
    kept = corroborated_irs(occupied, ev, lo, res)
    assert {tuple(p) for p in np.argwhere(kept)} == {(12, 30), (40, 10), (41, 11), (50, 40)}
    # without the sensor positions every hit counts
    unknown = RangeEvidence(hits, np.zeros((0, 2)), np.zeros(0), np.zeros(0), stereo_points=stereo)
    assert corroborated_irs(occupied, unknown, lo, res).sum() == len(hits)
    # the planner's map: the corroborated hits' pixels and the stereo points' occupied, the rest free
    out = from_image(planner_image(to_image(np.where(occupied, OCCUPIED, FREE).astype(np.uint8)), lo, res, ev))
    assert {tuple(p) for p in np.argwhere(out == OCCUPIED)} == \
        {(10, 30), (12, 30), (40, 10), (41, 11), (50, 40), (50, 44), (50, 24)}


def test_stereo_points_at_camera_height_mark_their_pixels_occupied():
    pose = camera_looking(0.0, 0.0, 0.0, z=0.5)
    pts = np.array([[1.05, 0.05, 0.55], [2.05, 0.05, 0.95], [0.55, 0.35, 0.22]])  # +0.05, +0.45, -0.28 m
    ev = RangeEvidence.of_frames(pose[None], np.array([np.nan]), np.full((1, 8, 8), np.nan), 0.5,
                                 ("camera", "stereo"), stereo_points=pts)
    np.testing.assert_allclose(ev.stereo_points, [[1.05, 0.05], [0.55, 0.35]])  # the one 0.45 m up is left out (0.3 m band)
    np.testing.assert_allclose(ev.surfaces, pts[:, :2])  # all three within the scan rules' 0.5 m (SURFACE_BAND_M)
    np.testing.assert_allclose(ev.touched(), [[1.05, 0.05], [0.55, 0.35]])  # no IRS hit: the stereo points
    assert len(RangeEvidence.of_frames(pose[None], np.array([np.nan]), np.full((1, 8, 8), np.nan), 0.5,
                                       ("camera",), stereo_points=pts).stereo_points) == 0  # not a sensor of the run
    image = np.full((10, 30), FREE, dtype=np.uint8)  # 3 x 1 m at 0.1 m
    out = from_image(planner_image(image, np.zeros(2), 0.1, ev))
    assert out[10, 0] == OCCUPIED and out[5, 3] == OCCUPIED and (out == OCCUPIED).sum() == 2


def test_an_irs_hit_near_a_scan_end_at_a_fine_resolution_against_a_brute_force_search():
    """At 1 cm, IRS_SCAN_NEAR_M is 10 pixels: the hits whose pixel has an occupied pixel within 10
    pixels (centre to centre), found by looking at every occupied pixel, are the ones kept (the
    hits are measured from one place, and no stereo point backs them)."""
    from virus_nerf.maps.planner import IRS_SCAN_NEAR_M, corroborated_irs

    rng = np.random.default_rng(5)
    res, lo = 0.01, np.zeros(2)
    occupied = rng.random((150, 120)) < 0.002  # [ix, iy], 1.5 x 1.2 m
    hits = rng.uniform([-0.05, -0.05], [1.55, 1.25], (400, 2))  # some off the raster: left out
    ev = RangeEvidence(hits, np.zeros((0, 2)), np.zeros(0), np.zeros(0), irs_origins=np.zeros((400, 2)))
    kept = corroborated_irs(occupied, ev, lo, res)
    occ = np.argwhere(occupied)
    expected, far = np.zeros(occupied.shape, dtype=bool), 0
    for ix, iy in np.floor(hits / res).astype(int):
        if 0 <= ix < 150 and 0 <= iy < 120:
            near = bool((((occ - [ix, iy]) ** 2).sum(axis=1) <= (IRS_SCAN_NEAR_M / res) ** 2).any())
            expected[ix, iy] |= near
            far += not near
    assert expected.sum() > 20 and far > 20  # both kinds are there
    assert (kept == expected).all()
    assert not corroborated_irs(np.zeros_like(occupied), ev, lo, res).any()  # nothing occupied, nothing near


def test_the_pixels_where_a_camera_stood_are_free_whatever_the_rules_said():
    grid = np.full((30, 10), OCCUPIED, dtype=np.uint8)  # [ix, iy], 3 x 1 m at 0.1 m from (-1, 2)
    grid[20:, :] = UNKNOWN
    image = to_image(grid)
    # a camera at (-0.95, 2.05) stands in pixel (0, 0), one at (1.25, 2.99) in (22, 9), one exactly
    # on the corner between (4, 4) and (5, 5) in (5, 5); (2.0, 2.5) lies 1 pixel past the raster
    positions = np.array([[-0.95, 2.05, 0.4], [1.25, 2.99, 0.4], [-0.5, 2.5, 0.4], [2.0, 2.5, 0.4]])
    out = from_image(track_free(image, np.array([-1.0, 2.0]), 0.1, positions))
    assert {tuple(p) for p in np.argwhere(out == FREE)} == {(0, 0), (22, 9), (5, 5)}
    assert (out[grid == UNKNOWN] != OCCUPIED).all() and (out == OCCUPIED).sum() == 200 - 2
    assert (from_image(image) == grid).all()  # the input is not changed
    observed = np.ones(grid.shape, dtype=bool)
    observed[22, 9] = False  # no sensor looked there: the map stays unknown, whatever stood there
    out = from_image(track_free(image, np.array([-1.0, 2.0]), 0.1, positions, observed))
    assert {tuple(p) for p in np.argwhere(out == FREE)} == {(0, 0), (5, 5)} and out[22, 9] == UNKNOWN
    assert (track_free(image, np.array([-1.0, 2.0]), 0.1, np.zeros((0, 3))) == image).all()  # no camera yet


def test_the_way_between_a_stacks_consecutive_camera_positions_is_free_too():
    grid = np.full((10, 10), OCCUPIED, dtype=np.uint8)  # [ix, iy], 1 x 1 m at 0.1 m from (0, 0)
    image = to_image(grid)
    # stack 1 drove from (0.05, 0.05) to (0.45, 0.05) (0.4 m: a dropped frame or three between) and
    # back up to (0.45, 0.35); stack 3 stood at (0.05, 0.65) and then 0.9 m away at (0.95, 0.65):
    # farther than TRACK_GAP_M, so only its two pixels. The rows are not in time order, and rows 1
    # and 2 of different stacks are not a way
    positions = np.array([[0.45, 0.05], [0.05, 0.65], [0.05, 0.05], [0.95, 0.65], [0.45, 0.35]])
    stacks, times = np.array([1, 3, 1, 3, 1]), np.array([1.0, 0.0, 0.0, 1.0, 2.0])
    out = from_image(track_free(image, np.zeros(2), 0.1, positions, stack_ids=stacks, times=times))
    way = {(ix, 0) for ix in range(5)} | {(4, iy) for iy in range(4)}
    assert {tuple(p) for p in np.argwhere(out == FREE)} == way | {(0, 6), (9, 6)}
    # without the times the rows' order is the way: (0.45, 0.05) -> (0.05, 0.05) -> (0.45, 0.35)
    # (0.5 m, as long as TRACK_GAP_M: kept), a diagonal through pixels (0..4, 0..3)
    out = from_image(track_free(image, np.zeros(2), 0.1, positions, stack_ids=stacks))
    free = {tuple(p) for p in np.argwhere(out == FREE)}
    assert {(ix, 0) for ix in range(5)} <= free and (2, 1) in free and (4, 3) in free and (4, 1) not in free
    # the points: every half pixel or closer along each way, both ends included
    pts = track_points(positions[[2, 0]], np.array([1, 1]), None, 0.05)
    assert len(pts) == 9 and np.allclose(pts[:, 0], np.linspace(0.05, 0.45, 9)) and np.allclose(pts[:, 1], 0.05)
    assert len(track_points(positions[:1], np.array([1]), None, 0.05)) == 0  # one position: no way


def test_cones_passing_counts_the_echoes_whose_cone_held_a_point_before_its_echo():
    from virus_nerf.maps.planner import cones_passing

    ev = RangeEvidence(np.zeros((0, 2)), np.array([[0.0, 0.0], [0.0, 0.0], [4.0, 0.0]]),
                       np.array([0.0, math.pi / 2, math.pi]), np.array([3.0, 3.0, 1.0]))
    pts = np.array([[1.0, 0.0], [2.0, 1.0], [2.95, 0.0], [3.5, 0.0], [0.0, 1.0]])
    # (1, 0): cone 0 (2.9 m reach); (2, 1): 26.6 deg off cone 0's axis, 2.24 m; (2.95, 0): beyond
    # 3.0 - 0.1; (3.5, 0): cone 2 (looking -x from 4 m, 0.5 m < 0.9); (0, 1): cone 1
    expected = [1, 1, 0, 1, 1]
    np.testing.assert_array_equal(cones_passing(pts, ev), expected)
    np.testing.assert_array_equal(cones_passing(pts, ev, pairs=2), expected)  # one point at a time


def test_band_parts_keep_what_a_segment_runs_within_the_band_projected_on_the_floor():
    from virus_nerf.maps.evidence import band_parts

    # from (1, 2, 0.3) down along (0.8, 0, -0.6): z = 0.3 - 0.6 t enters the band 0 +- 0.1 at t = 1/3
    # and leaves it at t = 2/3, 0.8 / 3 m apart on the floor; cut at t = 0.5, half of that stays
    o = np.array([[1.0, 2.0, 0.3]] * 2)
    d = np.array([[0.8, 0.0, -0.6]] * 2)
    parts = band_parts(o, d, np.array([1.0, 0.5]), height=0.0, band=0.1)
    np.testing.assert_allclose(parts.origins, [[1.0 + 0.8 / 3, 2.0]] * 2)
    np.testing.assert_allclose(parts.directions, [[1.0, 0.0]] * 2)
    np.testing.assert_allclose(parts.ranges, [0.8 / 3, 0.8 / 6])
    # level inside the band: all of it; level outside, vertical, or ending before the band: nothing
    level = band_parts(np.array([[0.0, 0.0, 0.05]]), np.array([[0.0, 1.0, 0.0]]), np.array([2.0]), 0.0, 0.1)
    np.testing.assert_allclose(level.origins, [[0.0, 0.0]])
    np.testing.assert_allclose(level.ranges, [2.0])
    none = band_parts(np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.05], [1.0, 2.0, 0.3]]),
                      np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.8, 0.0, -0.6]]), np.array([2.0, 2.0, 0.2]), 0.0,
                      0.1)
    assert len(none) == 0


def test_a_stereo_view_is_free_space_up_to_its_point_less_the_margin_or_two_sigma():
    from virus_nerf.maps.evidence import stereo_sight_lines
    from virus_nerf.sensors.camera import Intrinsics
    from virus_nerf.stereo.depth import StereoDepth

    intr = Intrinsics(fx=100.0, fy=100.0, cx=50.0, cy=50.0, width=100, height=100)
    pose = camera_looking(0.0, 0.0, 0.0, z=0.5)  # along +x, 0.5 m high
    # frame row 1 (row 0 a camera elsewhere); views: the image centre at 3 m (sigma 0.02: margin 0.1 m;
    # sigma 0.2: 2 sigma = 0.4 m), 100 px right (45 deg to the camera's right, -y) at 2 sqrt(2) m;
    # none from: 50 px down (descending 1 in 2, it leaves the band 0.5 +- 0.1 0.2 m from the camera,
    # shorter than SIGHT_MIN_LENGTH_M), the centre at 5.5 m (past SIGHT_MAX_RANGE_M), a frame row 2
    # that the poses do not hold
    views = StereoDepth(frames=np.array([1, 1, 1, 1, 1, 2]),
                        uv=np.array([[50.0, 50.0], [50.0, 50.0], [150.0, 50.0], [50.0, 100.0], [50.0, 50.0],
                                     [50.0, 50.0]], dtype=np.float32),
                        ranges=np.array([3.0, 3.0, 2 * math.sqrt(2), 3.0, 5.5, 3.0], dtype=np.float32),
                        sigmas=np.full(6, 0.02, dtype=np.float32) + np.array([0, 0.18, 0, 0, 0, 0], dtype=np.float32),
                        points=np.zeros((6, 3)))
    lines = stereo_sight_lines(views, np.stack([np.eye(4), pose]), np.array([0, 0]), {0: intr}, height=0.5)
    np.testing.assert_allclose(lines.origins, np.zeros((3, 2)), atol=1e-9)
    s = 1 / math.sqrt(2)
    np.testing.assert_allclose(lines.directions, [[1, 0], [1, 0], [s, -s]], atol=1e-6)
    np.testing.assert_allclose(lines.ranges, [2.9, 2.6, 2 * math.sqrt(2) - 0.1], atol=1e-5)


def test_the_mapper_keeps_its_sight_lines_until_the_stereo_targets_or_the_height_change():
    """engine/views.py: the sight lines are computed once per set of stereo targets and height; new
    targets (a refresh while driving) or another camera height give the new lines."""
    from types import SimpleNamespace

    from virus_nerf.engine.views import MapViews
    from virus_nerf.sensors.camera import Intrinsics
    from virus_nerf.stereo.depth import StereoDepth, _extend

    intr = Intrinsics(fx=100.0, fy=100.0, cx=50.0, cy=50.0, width=100, height=100)
    views = MapViews()
    views.store = SimpleNamespace(cam_to_world=camera_looking(0.0, 0.0, 0.0, z=0.5)[None], stack_ids=np.array([0]),
                                  intrinsics={0: intr})

    def targets(*ranges):  # image-centre views of frame row 0 (along +x at 0.5 m) at these ranges
        n = len(ranges)
        return StereoDepth(np.zeros(n, np.int64), np.full((n, 2), 50.0, np.float32), np.array(ranges, np.float32),
                           np.full(n, 0.02, np.float32), np.zeros((n, 3), np.float32))

    first = targets(3.0)
    lines = views._sight_lines(first, 0.5)
    np.testing.assert_allclose(lines.ranges, [2.9], atol=1e-5)
    assert views._sight_lines(first, 0.5) is lines  # kept
    more = _extend(first, targets(2.0))  # a refresh: the same targets and one more
    np.testing.assert_allclose(np.sort(views._sight_lines(more, 0.5).ranges), [1.9, 2.9], atol=1e-5)
    assert len(views._sight_lines(more, 0.75)) == 0  # 0.25 m below the band: nothing


def test_the_range_evidence_keeps_the_sight_lines_only_for_a_run_with_the_stereo_sensor():
    from virus_nerf.maps.evidence import Rays2D

    sight = Rays2D(np.zeros((1, 2)), np.array([[1.0, 0.0]]), np.array([2.0]))
    poses = camera_looking(0.0, 0.0, 0.0)[None]
    args = (poses, np.array([np.nan]), np.full((1, 8, 8), np.nan), 0.5)
    assert len(RangeEvidence.of_frames(*args, ("camera", "stereo"), sight_lines=sight).sight_lines) == 1
    assert len(RangeEvidence.of_frames(*args, ("camera", "irs", "uss"), sight_lines=sight).sight_lines) == 0


def test_the_mapper_keeps_its_range_evidence_until_a_frame_arrives():
    """engine/views.py: offline every map after the first reuses the frames' evidence; a new frame
    (the store only grows) gives the evidence again, with its USS echo."""
    from types import SimpleNamespace

    from virus_nerf.engine.views import MapViews

    def store(n):  # n frames along +x at 0.5 m, each with a 2 m echo
        poses = np.stack([camera_looking(0.1 * k, 0.0, 0.0) for k in range(n)])
        return SimpleNamespace(cam_to_world=poses, stack_ids=np.zeros(n, np.int64), uss_range=np.full(n, 2.0),
                               irs_range=np.full((n, 8, 8), np.nan))

    views = MapViews()
    views.config = SimpleNamespace(sensors=("camera", "uss"))
    views.box = SimpleNamespace(center=np.zeros(3))
    views.store, views.frames = store(1), 1
    first = views.range_evidence()
    np.testing.assert_allclose(first.uss_range, [2.0])
    assert views.range_evidence() is first  # kept
    views.store, views.frames = store(2), 2
    again = views.range_evidence()
    np.testing.assert_allclose(again.uss_origins, [[0.0, 0.0], [0.1, 0.0]], atol=1e-9)
