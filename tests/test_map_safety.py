"""Maps a planner can trust (issue 29, item 6): pixels no sensor looked at stay unknown, and the
safety figure counts real obstacles that a map marks free. Hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from virus_nerf.evaluation.safety import (
    judge_map,
    map_safety,
    obstacle_pixels,
    safety_document,
    safety_line,
)
from virus_nerf.maps.observed import apply_mask, camera_half_fov, observed_mask, observed_share
from virus_nerf.maps.occupancy import FREE, OCCUPIED, UNKNOWN, to_image


def camera_looking(x: float, y: float, yaw: float, z: float = 0.5) -> np.ndarray:
    """(4, 4) camera-to-world, optical axis (camera z) horizontal along yaw, camera y down."""
    fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    right = np.cross(down, fwd)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, fwd, (x, y, z)
    return pose


def test_half_fov_of_a_pinhole():
    assert camera_half_fov(640, 320.0) == pytest.approx(math.pi / 4)
    assert camera_half_fov(848, 424.0 / math.tan(math.radians(30))) == pytest.approx(math.radians(30))


def test_the_mask_is_the_wedge_of_the_camera_up_to_its_reach():
    lo, res, shape = np.array([-2.0, -2.0]), 0.5, (8, 8)
    half = math.radians(50.0)
    mask = observed_mask(camera_looking(0.0, 0.0, 0.0)[None], np.array([half]), lo, shape, res, reach=2.0)
    # pixel centres -1.75 .. 1.75: inside iff angle to +x <= 50 deg and distance <= 2 m (by atan2)
    c = lo[0] + (np.arange(8) + 0.5) * res
    x, y = np.meshgrid(c, c, indexing="ij")
    expected = (np.abs(np.degrees(np.arctan2(y, x))) <= 50.0) & (np.hypot(x, y) <= 2.0)
    np.testing.assert_array_equal(mask, expected)
    assert mask[7, 4] and not mask[4, 5]  # (1.75, 0.25) seen; (0.25, 0.75) at 72 deg is not
    assert not mask[7, 6]  # (1.75, 1.25) lies 2.15 m away
    assert int(mask.sum()) == 16 and observed_share(mask) == pytest.approx(16 / 64)  # 2 + 4 + 6 + 4 per column
    # a second camera looking the other way adds the mirror wedge; the same pose twice adds nothing
    both = observed_mask(np.stack([camera_looking(0, 0, 0), camera_looking(0, 0, math.pi), camera_looking(0, 0, 0)]),
                         np.full(3, half), lo, shape, res, reach=2.0)
    np.testing.assert_array_equal(both, expected | expected[::-1, :])
    # one spot, headings 0 and 25 deg: two frames, not one (frames are thinned by heading to the degree)
    turned = camera_looking(0, 0, math.radians(25.0))
    alone = observed_mask(turned[None], np.array([half]), lo, shape, res, reach=2.0)
    pair = observed_mask(np.stack([camera_looking(0, 0, 0), turned]), np.full(2, half), lo, shape, res, reach=2.0)
    assert (alone & ~expected).any()
    np.testing.assert_array_equal(pair, expected | alone)


def test_the_pixel_a_camera_stood_in_is_observed():
    """A view wedge starts at the lens: the camera's own pixel centre may lie behind it. The robot
    stood there, so that pixel counts as observed (by hand: cameras in pixels (1, 0) and, on a
    corner, (2, 1); one outside the raster changes nothing)."""
    from virus_nerf.maps.observed import with_camera_pixels

    mask = np.zeros((3, 2), dtype=bool)  # [ix, iy], 0.5 m pixels from (-1, 0)
    cams = np.array([[-0.4, 0.2, 0.3], [0.0, 0.5, 0.3], [5.0, 0.2, 0.3]])
    out = with_camera_pixels(mask, cams, np.array([-1.0, 0.0]), 0.5)
    np.testing.assert_array_equal(out, [[False, False], [True, False], [False, True]])
    assert not mask.any()  # the input is untouched


def test_unobserved_pixels_become_unknown_whatever_the_map_said():
    mask = np.zeros((3, 2), dtype=bool)  # [ix, iy]: 3 columns, 2 rows
    mask[0, 1] = mask[2, 0] = True
    image = np.full((2, 3), FREE, dtype=np.uint8)
    image[0, 0] = OCCUPIED
    out = apply_mask(image, mask, UNKNOWN)
    # image row 0 = iy 1: (ix 0, iy 1) kept occupied; row 1 = iy 0: (ix 2, iy 0) kept free
    np.testing.assert_array_equal(out, [[OCCUPIED, UNKNOWN, UNKNOWN], [UNKNOWN, UNKNOWN, FREE]])
    assert image[0, 1] == FREE  # the input is untouched
    np.testing.assert_array_equal(to_image(mask), out != UNKNOWN)


def test_obstacles_marked_free_counted_per_zone_with_the_inlier_tolerance():
    res, origin = 0.1, (0.0, 0.0)
    wall = np.column_stack([np.full(10, 0.55), 0.05 + 0.1 * np.arange(10)])  # column 5, every row
    assert obstacle_pixels(wall, origin, res, (10, 10))[:, 5].all()
    path = np.array([[-1.0, 0.5]])  # obstacle pixels lie 1.50-1.61 m from it
    free = np.full((10, 10), FREE, dtype=np.uint8)

    def zones(image):
        return [(z.within_m, z.obstacles, z.marked_free) for z in map_safety(image, origin, res, wall, path)]

    assert zones(free) == [(1.0, 0, 0), (2.0, 10, 10), (math.inf, 10, 10)]  # the wall is all free: 100 %
    for column, missed in ((5, 0), (6, 0), (7, 10)):  # the wall drawn where it is, 10 cm off, 20 cm off
        image = free.copy()
        image[:, column] = OCCUPIED
        assert zones(image)[2] == (math.inf, 10, missed), column
    unknown = free.copy()
    unknown[:, 4] = UNKNOWN  # unknown next to the wall: not free for sure
    assert zones(unknown)[2] == (math.inf, 10, 0)
    walled = free.copy()
    walled[:, 5] = OCCUPIED
    doc = safety_document(judge_map(free, origin, res, wall, path), 0.25, "map", res,
                          {"lidar": judge_map(walled, origin, res, wall, path)})
    assert doc["zones"]["1m"] == {"obstacles": 0, "marked_free": 0, "free_share": None}
    assert doc["zones"]["all"]["free_share"] == 1.0 and doc["observed"] == 0.25
    # the path at x = -1 m lies outside the 1 m raster: no true free pixel is on it, no recall
    assert doc["free_recall"] is None and doc["anchors"]["lidar"]["zones"]["all"]["free_share"] == 0.0
    assert "all 100.0%" in safety_line(doc) and "1m -" in safety_line(doc)
    assert "LiDAR 2D map: 1m -, 2m 0.0%, all 0.0%" in safety_line(doc)


def test_a_scored_run_reports_its_map_safety_and_the_snapshot_its_observed_share(tiny_office, tmp_path):
    import json

    from helpers import run_cli, tiny_train_config

    from virus_nerf.config_io import to_dict

    cfg = tmp_path / "small.json"
    cfg.write_text(json.dumps(to_dict(tiny_train_config(plots=True))))  # the safety picture is in plots/
    run = tmp_path / "run"
    code, out, err = run_cli(["train", "--data", tiny_office, "--room", "office", "--out", run, "--config", cfg,
                              "--quiet"])
    assert code == 0, err
    safety = json.loads((run / "metrics.json").read_text())["safety"]
    assert safety["gt"] == "map" and safety["resolution"] == 0.05 and 0.0 < safety["observed"] < 1.0
    z = safety["zones"]
    assert z["1m"]["obstacles"] <= z["2m"]["obstacles"] <= z["all"]["obstacles"] and z["all"]["obstacles"] > 100
    for block in z.values():
        assert 0 <= block["marked_free"] <= block["obstacles"]
    assert 0.0 < safety["free_recall"] <= 1.0 and 0.0 < safety["free_recall_drivable"] <= 1.0
    assert 0.0 <= safety["planner_reach"] <= 1.0
    assert safety["drivable_from_floor_m"] == 0.1
    assert set(safety["anchors"]) == {"sensors", "lidar"}
    for anchor in safety["anchors"].values():
        assert anchor["zones"]["all"]["obstacles"] == z["all"]["obstacles"] and 0.0 <= anchor["free_recall"] <= 1.0
    assert (run / "plots" / "map_safety.png").is_file()
    # issue 42 item 5: a planner on the map finds paths and none of them passes a real obstacle
    assert safety["planner"]["paths"] > 0 and safety["planner"]["crossing"] == 0, safety["planner"]
    # and nowhere may it put the robot's centre touching one, whatever the random ends (D99)
    assert safety["planner"]["unsafe_m2"] == 0.0 and safety["planner"]["unsafe_share"] == 0.0
    assert safety["planner"]["unsafe_near_m2"] == {"1m": 0.0, "2m": 0.0}
    # nor what the body meets below the band (D114)
    assert safety["planner"]["crossing_below"] == 0 and safety["planner"]["unsafe_below_m2"] == 0.0
    assert (f"paths between random free points pass a real obstacle, {safety['planner']['crossing_below']} more pass "
            "only what the body meets below the band") in out
    assert "m^2 where its centre may touch that); it may put the robot's centre where" in out
    # `evaluate` judges the same map: the same safety block
    code, out_eval, err = run_cli(["evaluate", "--run", run, "--out", tmp_path / "eval.json", "--no-plots"])
    assert code == 0, err
    evaluated, trained = json.loads((tmp_path / "eval.json").read_text()), json.loads((run / "metrics.json").read_text())
    assert evaluated["safety"] == safety
    # and says the run's warnings (a run this short ends inside the grid's warm-up)
    assert evaluated["warnings"] == trained["warnings"] and any("warm-up" in w for w in trained["warnings"])
    assert all(f"warning: {w}" in out_eval for w in trained["warnings"])
    assert not (tmp_path / "eval_plots").exists() and "eval_plots" not in out_eval  # --no-plots: the JSON alone
    assert "map safety (map ground truth; shares of the obstacles within that distance of the path" in out_eval
    assert "map safety (map ground truth; shares of the obstacles within that distance of the path" in out
    # export: the map and probability map are unknown / 255 outside the observed wedges; the ESDF is NaN
    # wherever the map is unknown (outside the wedges, and the shadows inside them)
    code, _, err = run_cli(["export", "--run", run, "--out", tmp_path / "export", "--what", "map,esdf,prob"])
    assert code == 0, err
    summary = json.loads((tmp_path / "export" / "export.json").read_text())
    from PIL import Image

    from virus_nerf.trainer.run import load_trained

    image = np.asarray(Image.open(tmp_path / "export" / "map.pgm"))
    esdf = np.load(tmp_path / "export" / "esdf.npy")
    prob = np.asarray(Image.open(tmp_path / "export" / "prob.pgm"))
    trainer, _, _ = load_trained(run, "--run")
    trainer.prepare()
    unseen = ~to_image(trainer.mapper.observed(0.05))  # (H, W) as the PGMs: no training frame looked there
    assert summary["observed"] == pytest.approx(1.0 - unseen.mean(), abs=1e-4)
    assert np.array_equal(np.isnan(esdf), image == UNKNOWN) and (image[~unseen] == UNKNOWN).any()
    assert (esdf[image == OCCUPIED] < 0).all() and (esdf[image == FREE] > 0).all()
    # map_server's raw mode: 255 unknown (-1), elsewhere round(100 p); the raster is rounded up past the
    # grid's box (at its high x and y: the last column, the top row), where no cell knows the pixels
    assert (image[unseen] == UNKNOWN).all() and (prob[unseen] == 255).all()
    past_box = np.zeros(prob.shape, dtype=bool)
    past_box[0, :] = past_box[:, -1] = True
    assert (prob[~unseen & ~past_box] <= 100).all()
    # free wherever a camera stood (usage.md), the drive's first frames too: the view wedges start at
    # the lens, and the robot standing still at the start would leave its own pixel unknown
    cams = trainer.mapper.store.cam_to_world[:, :2, 3]  # (N, 2) the frames the map was made from
    origin = np.array([float(v) for v in next(ln for ln in (tmp_path / "export" / "map.yaml").read_text().splitlines()
                                               if ln.startswith("origin:")).split("[")[1].split(",")[:2]])
    ix, iy = np.floor((cams - origin) / 0.05).astype(int).T
    assert len(cams) > 10 and (image[image.shape[0] - 1 - iy, ix] == FREE).all()


def test_true_free_space_near_the_path_keeps_clear_of_obstacles_and_stays_on_the_path_side():
    from virus_nerf.evaluation.safety import free_recall, true_free_near_path

    res, origin = 0.1, (0.0, 0.0)
    obst = np.zeros((10, 20), dtype=bool)  # rows = y 0.95 .. 0.05 (row 0 on top), columns x 0.05 .. 1.95
    obst[:, 10] = True  # a wall at x 1.0-1.1 m, every row
    path = np.array([[0.25, 0.45]])  # on the left of the wall
    free = true_free_near_path(obst, origin, res, path, within=3.0, clearance=0.15)
    # left of the wall: columns whose centre is more than 0.15 m from the wall pixel's centre,
    # i.e. columns 0..8 (0.2 m from column 10 for column 8, 0.1 m for column 9); the right side
    # (columns 11..19) is cut off by the wall, so it is not the path's free space
    expected = np.zeros_like(obst)
    expected[:, :9] = True
    np.testing.assert_array_equal(free, expected)
    near = true_free_near_path(obst, origin, res, path, within=0.5, clearance=0.15)
    assert near[4, 2] and not near[4, 8]  # (0.25, 0.55) is 0.1 m from the path; (0.85, 0.55) 0.61 m
    image = np.full(obst.shape, UNKNOWN, dtype=np.uint8)
    image[:, :3] = FREE  # a third of the 9 free columns
    assert free_recall(image, FREE, free) == pytest.approx(3 / 9)
    assert free_recall(image, FREE, np.zeros_like(obst)) is None


def test_true_free_space_stays_inside_the_ground_truths_extent_where_a_wall_slice_has_a_gap():
    from virus_nerf.evaluation.safety import true_free_near_path

    res, origin = 0.1, (0.0, 0.0)
    obst = np.zeros((10, 20), dtype=bool)  # rows = y 0.95 .. 0.05, columns x 0.05 .. 1.95
    obst[:, 10] = True  # the room's wall at x 1.0-1.1 m ...
    obst[4:7, 10] = False  # ... with a 0.3 m gap where furniture hid it from the LiDAR
    path = np.array([[0.25, 0.45]])
    leaked = true_free_near_path(obst, origin, res, path, within=3.0, clearance=0.05)
    assert leaked[5, 15]  # (1.55, 0.45) beyond the wall, reached through the gap
    inside = true_free_near_path(obst, origin, res, path, within=3.0, clearance=0.05,
                                 extent=((0.0, 0.0), (1.1, 1.0)))
    # the same pixels left of x = 1.1 m (centres 0.05 .. 1.05: columns 0..10), none beyond it
    np.testing.assert_array_equal(inside[:, :11], leaked[:, :11])
    assert not inside[:, 11:].any()
    assert inside[5, 10]  # the gap's own pixel (centre 1.05 m) is inside the extent


def test_the_planner_check_finds_paths_and_counts_the_ones_through_a_wall_the_map_lost():
    from virus_nerf.evaluation.safety import planner_check

    res, origin = 0.1, (0.0, 0.0)
    image = np.full((30, 60), FREE, dtype=np.uint8)  # a 6 x 3 m room, free inside...
    image[[0, -1], :] = OCCUPIED
    image[:, [0, -1]] = OCCUPIED
    # ...split by a true wall at x = 3.05 m with no gap: every path from one side to the other crosses it
    wall = np.column_stack([np.full(30, 3.05), 0.05 + 0.1 * np.arange(30)])
    lost = planner_check(image, origin, res, wall, seed=3)
    assert lost.paths == 1000 and lost.crossing > 0
    # the two halves are the same size: a goal lies across the wall from its start half the time
    assert 0.4 < lost.crossing / lost.paths < 0.6, lost
    drawn = image.copy()
    drawn[:, 30] = OCCUPIED  # the map holds the wall: the two halves are apart, no path crosses it
    kept = planner_check(drawn, origin, res, wall, seed=3)
    assert kept.crossing == 0 and 0 < kept.paths < 1000  # goals on the other side are unreachable
    # a robot of radius 0.3 m keeps its centre 0.3 m from anything not free: a 0.4 m corridor is shut
    corridor = np.full((30, 60), OCCUPIED, dtype=np.uint8)
    corridor[12:16, :] = FREE
    assert planner_check(corridor, origin, res, np.zeros((0, 2))).paths == 0
    corridor[8:21, :] = FREE  # 1.3 m wide: passable, nothing to cross
    wide = planner_check(corridor, origin, res, np.zeros((0, 2)))
    assert wide.paths == 1000 and wide.crossing == 0


def _walled_room(res: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """An n x n pixel room at `res` m: the map (walls on the border rows and columns occupied, the
    rest free) and the walls' true points (the border pixels' centres, (4n, 2) m)."""
    image = np.full((n, n), FREE, dtype=np.uint8)
    image[[0, -1], :] = OCCUPIED
    image[:, [0, -1]] = OCCUPIED
    centres = (np.arange(n) + 0.5) * res
    walls = np.concatenate([np.column_stack([centres, np.full(n, v)]) for v in (centres[0], centres[-1])]
                           + [np.column_stack([np.full(n, v), centres]) for v in (centres[0], centres[-1])])
    return image, walls


def test_the_planner_checks_unsafe_space_is_where_its_robot_would_touch_a_lost_obstacle():
    """A 2.5 m square room at 0.125 m (20 x 20 pixels, walls on the border rows and columns, every
    other pixel free). A 0.3 m robot may put its centre 2.4 pixels or more from anything not free:
    rows and columns 3-16, 14 x 14 = 196 pixels. A true obstacle the map lost at pixel (row 9,
    column 9) endangers the pixels within radius - tolerance = 0.2 m = 1.6 pixels of it: itself,
    its 4 sides and its 4 corners (sqrt 2 = 1.41), all 9 in that space; the walls' own danger
    (rows and columns 0-1) lies outside it. The map that holds the obstacle keeps the robot's
    centre 2.4 pixels from it: none."""
    from virus_nerf.evaluation.safety import planner_check, safety_line

    res, n = 0.125, 20
    image, walls = _walled_room(res, n)
    lost = np.array([[9.5 * res, (n - 1 - 9 + 0.5) * res]])  # image row 9, column 9
    check = planner_check(image, (0.0, 0.0), res, np.concatenate([walls, lost]))
    assert check.space_m2 == pytest.approx(196 * res * res) and check.unsafe_m2 == pytest.approx(9 * res * res)
    assert check.block()["unsafe_m2"] == round(9 * res * res, 4) and check.unsafe_share == pytest.approx(9 / 196)
    assert check.crossing > 0  # paths pass it: the space is on the way between the room's halves
    assert planner_check(image, (0.0, 0.0), res, walls).unsafe_m2 == 0.0  # nothing lost
    held = image.copy()
    held[9, 9] = OCCUPIED
    kept = planner_check(held, (0.0, 0.0), res, np.concatenate([walls, lost]))
    assert kept.unsafe_m2 == 0.0 and kept.crossing == 0 and kept.space_m2 < check.space_m2
    doc = {"gt": "map", "observed": 1.0, "zones": {"all": {"free_share": 0.0}}, "planner": check.block()}
    assert "touches a real obstacle in 0.1406 m^2 (4.59% of where it may put it)" in safety_line(doc)
    # the robot drove by at (0.1875, 1.3125), pixel (row 9, column 1): of the 9 unsafe pixels (columns
    # 8-10 at x 1.0625-1.3125 m, rows 8-10), column 8's three lie 0.875-0.884 m from it and column 9's
    # middle one 1.0 m; the rest 1.008-1.132 m: 4 within 1 m, all 9 within 2 m
    near = planner_check(image, (0.0, 0.0), res, np.concatenate([walls, lost]), path_xy=np.array([[0.1875, 1.3125]]))
    assert near.unsafe_near_m2 == pytest.approx({"1m": 4 * res * res, "2m": 9 * res * res})
    assert near.block()["unsafe_near_m2"] == {"1m": 0.0625, "2m": 0.1406} and "unsafe_near_m2" not in check.block()
    doc["planner"] = near.block()
    assert "(4.59% of where it may put it), 0.0625 m^2 within 1 m of the path, 0.1406 m^2 within 2 m" in safety_line(doc)


def test_the_planner_check_counts_paths_past_what_the_body_meets_below_the_band_apart():
    """The room of the test above, its lost obstacle at pixel (row 9, column 9) now a pallet below the
    band (gt.body_slice): no band obstacle is lost, so no path crosses one, and the same 9 pixels and
    the same paths (the same seed) as before count for the body instead. A body point on a wall's
    pixel (a wall reaches below the band too) and a pallet under a band obstacle add nothing: the
    band's count has them."""
    from virus_nerf.evaluation.safety import planner_check, safety_line

    res, n = 0.125, 20
    image, walls = _walled_room(res, n)
    pallet = np.array([[9.5 * res, (n - 1 - 9 + 0.5) * res]])
    as_band = planner_check(image, (0.0, 0.0), res, np.concatenate([walls, pallet]))
    below = planner_check(image, (0.0, 0.0), res, walls, body_xy=np.concatenate([walls, pallet]))
    assert below.crossing == 0 and below.unsafe_m2 == 0.0 and below.paths == as_band.paths
    assert below.crossing_below == as_band.crossing > 0 and below.unsafe_below_m2 == pytest.approx(9 * res * res)
    assert below.block()["crossing_below"] == as_band.crossing and below.block()["unsafe_below_m2"] == 0.1406
    both = planner_check(image, (0.0, 0.0), res, np.concatenate([walls, pallet]), body_xy=np.concatenate([walls, pallet]))
    assert both.crossing == as_band.crossing and both.crossing_below == 0 and both.unsafe_below_m2 == 0.0
    assert as_band.crossing_below is None and "crossing_below" not in as_band.block()  # no body's ground truth
    doc = {"gt": "map", "observed": 1.0, "zones": {"all": {"free_share": 0.0}}, "planner": below.block()}
    assert (f"0 of {below.paths} paths between random free points pass a real obstacle, {as_band.crossing} more "
            "pass only what the body meets below the band (0.1406 m^2 where its centre may touch that)") in safety_line(doc)


def test_the_floor_and_what_the_body_meets_below_the_band_by_hand():
    from virus_nerf.evaluation.gt import body_slice, floor_height

    rng = np.random.default_rng(0)
    floor = np.column_stack([rng.uniform(0, 2, (500, 2)), rng.uniform(-0.5049, -0.4951, 500)])  # z -0.5 +- 5 mm
    others = np.array([[0.5, 0.5, -0.3],  # a pallet's top, 0.2 m above the floor: the body meets it
                       [0.6, 0.5, -0.45],  # a cable 5 cm above the floor: under the body
                       [0.7, 0.5, -0.1],  # 10 cm under the cameras, below the +-5 cm band: the body meets it
                       [0.8, 0.5, 0.0]])  # in the band: the map's own ground truth, not the body's
    points = np.concatenate([floor, others])
    assert floor_height(points, camera_height=0.0) == pytest.approx(-0.5, abs=0.01)  # a 2 cm bin's centre
    # the bins start at the lowest point: heights in [-0.51, -0.49) m are one bin, its centre -0.50 m
    level = np.column_stack([np.zeros((100, 2)), np.r_[-0.51, rng.uniform(-0.51, -0.49, 99)]])
    assert floor_height(level, camera_height=0.0) == pytest.approx(-0.50, abs=1e-9)
    np.testing.assert_allclose(body_slice(points, 0.0, 0.05), [[0.5, 0.5], [0.7, 0.5]])
    assert floor_height(others[2:], camera_height=0.0) is None  # nothing 0.2 m under the cameras
    assert body_slice(others[2:], 0.0, 0.05) is None


def test_the_drivable_free_recall_leaves_out_what_the_body_meets():
    """A wall at x 1.0-1.1 m (the band's ground truth) and a pallet under the band at x 0.2-0.4,
    y 0.4-0.6 m that the map marks occupied: of the band's 90 true free pixels (columns 0-8) the
    map keeps 86; the drivable truth leaves out the pallet's 4 pixels and the 12 within the 0.15 m
    clearance around them, 74 pixels, all kept."""
    from virus_nerf.evaluation.safety import judge_map

    res, origin = 0.1, (0.0, 0.0)
    wall = np.column_stack([np.full(10, 1.05), np.arange(10) * 0.1 + 0.05])
    pallet = np.array([[0.25, 0.45], [0.35, 0.45], [0.25, 0.55], [0.35, 0.55]])
    path = np.array([[0.05, 0.05]])
    image = np.full((10, 20), UNKNOWN, dtype=np.uint8)  # rows y 0.95 .. 0.05, columns x 0.05 .. 1.95
    image[:, :9] = FREE
    image[4:6, 2:4] = OCCUPIED  # the pallet: rows 4-5 (y 0.5-0.6, 0.4-0.5), columns 2-3
    judged = judge_map(image, origin, res, wall, path, body_xy=pallet)
    assert judged.free_recall == pytest.approx(86 / 90)
    assert judged.free_recall_drivable == pytest.approx(1.0)
    image[0, 0] = OCCUPIED  # a corner pixel far from the pallet: lost in both
    judged = judge_map(image, origin, res, wall, path, body_xy=pallet)
    assert judged.free_recall == pytest.approx(85 / 90) and judged.free_recall_drivable == pytest.approx(73 / 74)
    assert judge_map(image, origin, res, wall, path).block()["free_recall_drivable"] is None  # no body truth


def test_what_the_body_meets_below_the_band_marked_free_by_hand():
    """The pallet of the test above (4 pixels 0.45-0.58 m from the path at (0.05, 0.05)) and a body
    point inside the wall's band pixel (counted with the band's obstacles, not again): occupied in
    the map, none of the 4 is marked free; a map that marks them free marks 4 of 4 within 1 m; with
    one of them occupied only the pallet pixel diagonal to it stays free for sure (the 0.1 m
    tolerance is one pixel here: the 4 neighbours)."""
    from virus_nerf.evaluation.safety import judge_map

    res, origin = 0.1, (0.0, 0.0)
    wall = np.column_stack([np.full(10, 1.05), np.arange(10) * 0.1 + 0.05])
    body = np.array([[0.25, 0.45], [0.35, 0.45], [0.25, 0.55], [0.35, 0.55], [1.05, 0.05]])
    path = np.array([[0.05, 0.05]])
    image = np.full((10, 20), UNKNOWN, dtype=np.uint8)
    image[:, :9] = FREE
    image[4:6, 2:4] = OCCUPIED
    below = judge_map(image, origin, res, wall, path, body_xy=body).block()["below_band"]
    assert below == {"1m": {"obstacles": 4, "marked_free": 0, "free_share": 0.0},
                     "2m": {"obstacles": 4, "marked_free": 0, "free_share": 0.0},
                     "all": {"obstacles": 4, "marked_free": 0, "free_share": 0.0}}
    image[4:6, 2:4] = FREE
    assert judge_map(image, origin, res, wall, path, body_xy=body).block()["below_band"]["1m"]["marked_free"] == 4
    image[5, 2] = OCCUPIED  # y 0.4-0.5, x 0.2-0.3: the pallet pixel at (0.25, 0.45)
    zones = judge_map(image, origin, res, wall, path, body_xy=body).below_band
    assert [(z.obstacles, z.marked_free) for z in zones] == [(4, 1), (4, 1), (4, 1)]
    assert judge_map(image, origin, res, wall, path).block()["below_band"] is None  # no body truth
    doc = safety_document(judge_map(image, origin, res, wall, path, body_xy=body), 1.0, "map", res)
    assert "what the body meets below the band marked free: 1m 25.0%, 2m 25.0%, all 25.0%" in safety_line(doc)


def test_planner_reach_is_what_a_planner_reaches_from_the_path_and_a_lone_speck_cuts_it():
    """A corridor at 4 cm (20 x 60 pixels, walls on rows 0 and 19), the path along row 10. A 0.3 m
    robot may stand on rows 8-11 (0.32 m or more from both walls; row 7 is 0.28 m): 4 x 60 = 240
    pixels. The map of the walls alone reaches all of them; one occupied pixel at row 10, column 20
    takes every configuration pixel within 0.3 m of it (dr^2 + dc^2 <= 56.25 pixels^2: columns 13-27
    on rows 8-11) and cuts the corridor in two; a planner keeps the right part, which holds 32 of the
    path's pixels against the left's 13: 4 x 32 = 128 of the 240."""
    from virus_nerf.evaluation.safety import judge_map

    h, w, res = 20, 60, 0.04
    image = np.full((h, w), 254, dtype=np.uint8)
    image[[0, h - 1], :] = 0
    x = (np.arange(w) + 0.5) * res
    walls = np.concatenate([np.column_stack([x, np.full(w, (h - 0.5) * res)]), np.column_stack([x, np.full(w, 0.5 * res)])])
    path = np.column_stack([x, np.full(w, (h - 10 - 0.5) * res)])  # row 10
    whole = judge_map(image, (0.0, 0.0), res, walls, path, body_xy=np.zeros((0, 2)))
    assert whole.planner_reach == pytest.approx(1.0)
    image[10, 20] = 0
    cut = judge_map(image, (0.0, 0.0), res, walls, path, body_xy=np.zeros((0, 2)))
    assert cut.planner_reach == pytest.approx(128 / 240)
    assert cut.block()["planner_reach"] == round(128 / 240, 4)
    assert judge_map(image, (0.0, 0.0), res, walls, path).planner_reach is None  # no body: no drivable truth


def test_the_safety_picture_shows_what_the_body_meets_below_the_band():
    """A 5 x 5 map at 1 m (the 0.1 m tolerance is within a pixel: each pixel judged alone), free but
    for pixel (row 4, column 4), occupied, and (4, 0), unknown. A band obstacle at (2, 2) is red; the
    body's points at (0, 0) (free: orange), at (4, 4) and (4, 0) (held: brown) and at (2, 2) (a band
    obstacle's pixel: red, the band's)."""
    from virus_nerf.evaluation.safety import BODY_MISSED_RGB, BODY_RGB, safety_picture

    image = np.full((5, 5), FREE, dtype=np.uint8)
    image[4, 4] = OCCUPIED
    image[4, 0] = UNKNOWN
    centre = lambda row, col: [col + 0.5, 5 - row - 0.5]  # noqa: E731 - pixel centre (m), row 0 = largest y
    band = np.array([centre(2, 2)])
    body = np.array([centre(0, 0), centre(4, 4), centre(2, 2), centre(4, 0)])
    path = np.array([centre(0, 4)])
    rgb = safety_picture(image, (0.0, 0.0), 1.0, band, path, body_xy=body)
    assert tuple(rgb[0, 0]) == BODY_MISSED_RGB and tuple(rgb[4, 4]) == BODY_RGB and tuple(rgb[4, 0]) == BODY_RGB
    assert tuple(rgb[2, 2]) == (255, 0, 0) and tuple(rgb[0, 4]) == (0, 160, 0) and tuple(rgb[1, 1]) == (255, 255, 255)
    plain = safety_picture(image, (0.0, 0.0), 1.0, band, path)  # without the body's truth: as before
    assert tuple(plain[0, 0]) == (255, 255, 255) and tuple(plain[4, 4]) == (0, 0, 0)


def test_the_safety_picture_file_has_metres_a_title_and_a_legend(tmp_path, monkeypatch):
    """plots/map_safety.png: a 40 x 20 picture at 0.05 m with its lower left corner at (-1, 2) m
    spans x -1..1 m and y 2..3 m, drawn pixel for pixel; the title names the ground truth and the
    legend every colour (8 with what the body meets below the band)."""
    from virus_nerf.evaluation import plots

    drawn = {}
    real_save = plots.save_png

    def spy(fig, path, dpi=110, tight=True):
        ax = fig.axes[0]
        drawn.update(extent=ax.images[0].get_extent(), title=ax.get_title(), xlabel=ax.get_xlabel(),
                     legend=[t.get_text() for t in ax.get_legend().get_texts()],
                     interpolation=ax.images[0].get_interpolation(), dpi=dpi)
        return real_save(fig, path, dpi, tight)

    monkeypatch.setattr(plots, "save_png", spy)
    picture = np.zeros((20, 40, 3), dtype=np.uint8)
    out = plots.plot_safety_picture(picture, (-1.0, 2.0), 0.05, tmp_path / "map_safety.png", gt="map", body=True)
    assert out.is_file() and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert drawn["extent"] == pytest.approx((-1.0, 1.0, 2.0, 3.0)) and drawn["interpolation"] == "nearest"
    assert "map ground truth" in drawn["title"] and "0.05 m pixels" in drawn["title"] and drawn["xlabel"] == "x [m]"
    assert len(drawn["legend"]) == 8 and "obstacle the map marks free" in drawn["legend"]
    plots.plot_safety_picture(picture, (-1.0, 2.0), 0.05, tmp_path / "plain.png", gt="scan")
    assert len(drawn["legend"]) == 6 and "scan ground truth" in drawn["title"]


def test_distances_on_the_pixel_lattice_keep_their_boundary_pixels():
    """At 0.05 m every radius, clearance and tolerance is a whole number of pixels, and floating
    point must not decide the pixels on it (0.3 - 0.1 = 0.19999999999999998 < 4 * 0.05;
    6 * 0.05 = 0.30000000000000004 > 0.3). By hand, one obstacle pixel in a free 21 x 21 raster:
    within 0.2 m (4 px) lie the pixels with dx^2 + dy^2 <= 16, 49 of them, the four 4 px away on
    the axes among them; the centre of a 0.3 m robot must stand more than 6 px from it, so not on
    the 4 pixels exactly 6 px away on the axes."""
    from virus_nerf.evaluation.safety import configuration_space, pixels_within, true_free_near_path

    res = 0.05
    mask = np.zeros((21, 21), dtype=bool)
    mask[10, 10] = True
    dy, dx = np.mgrid[-10:11, -10:11]
    within = pixels_within(mask, res, 0.3 - 0.1)
    assert within.sum() == int((dx * dx + dy * dy <= 16).sum()) == 49 and within[10, 14] and within[6, 10]
    image = np.full((21, 21), FREE, dtype=np.uint8)
    image[10, 10] = OCCUPIED
    space = configuration_space(to_image(image), res, 0.3)
    assert not space[10, 16] and not space[4, 10] and space[10, 17]
    assert space.sum() == int((dx * dx + dy * dy > 36).sum())
    # the free space a planner needs keeps more than 0.15 m (3 px) from the obstacle: not at 3 px
    free = true_free_near_path(mask, (0.0, 0.0), res, np.array([[0.025, 0.025]]))
    assert not free[10, 13] and free[10, 14] and free.sum() == int((dx * dx + dy * dy > 9).sum())


@pytest.mark.slow
def test_evaluate_scores_a_driving_run_on_the_frames_it_trained_on(tiny_office, tmp_path, monkeypatch):
    """A driving run (train --online) adds frames as its clock passes them, at each step's start:
    frames that come due during the last step were never the mapper's. `evaluate` loads the
    checkpoint with exactly the frames its mapper held, so it gives the run's own figures (it
    added every frame due by the final clock, and judged another map, with more camera positions).
    Neither it nor `export` writes into the run, even with no user cache (a review: both decoded
    the frames into RUN/cache/images.npy, which failed on read-only media, and two exports sharing
    the run's lock truncated the same file)."""
    import json

    import torch
    from helpers import run_cli, tiny_train_config

    from virus_nerf.config_io import to_dict

    cfg = tmp_path / "small.json"
    cfg.write_text(json.dumps(to_dict(tiny_train_config(max_steps=None, max_time=4.0, online=True,
                                                        playback_speed=0.5))))
    run = tmp_path / "run"
    code, _, err = run_cli(["train", "--data", tiny_office, "--room", "office", "--out", run, "--config", cfg,
                            "--quiet", "--no-plots"])
    assert code == 0, err
    held = torch.load(run / "checkpoint.pt", map_location="cpu", weights_only=False)["frames"]
    assert 1 < held < 30  # a 3 s drive at half speed in 4 s of training: the drive is not over
    monkeypatch.setenv("VIRUS_NERF_CACHE_DIR", "off")  # every frame decoded again
    (run / "run.lock").unlink()  # the readers: none makes it again (evaluate, a writer, would)

    def files():
        return {str(p.relative_to(run)): p.stat().st_mtime_ns for p in run.rglob("*")}

    before = files()
    code, _, err = run_cli(["export", "--run", run, "--out", tmp_path / "export", "--what", "map"])
    assert code == 0, err
    assert files() == before
    code, _, err = run_cli(["evaluate", "--run", run, "--out", tmp_path / "again.json", "--no-plots"])
    assert code == 0, err
    assert {k: v for k, v in files().items() if k != "run.lock"} == before
    own, again = (json.loads(p.read_text()) for p in (run / "metrics.json", tmp_path / "again.json"))
    assert again["safety"] == own["safety"]
    assert again["sensors"]["NeRF"] == own["sensors"]["NeRF"]


def test_the_planner_moves_diagonally_and_counts_a_path_past_both_kinds_once():
    """By hand, a robot of 1 cm on 10 cm pixels (its configuration space: the free pixels) with no
    tolerance (a danger pixel is the obstacle's own):
    - free pixels only on a diagonal: 8-connected, every start reaches both others (3 x 2 paths);
    - a corridor of 5 pixels, the body's pallet on column 1, a band obstacle on column 3: of the
      20 ordered paths, 14 pass column 3 (crossing) and 6 pass column 1 but not 3 (crossing_below);
      a path past both is the band's alone, wherever its walk meets them first."""
    from virus_nerf.evaluation.safety import planner_check

    res = 0.1
    diagonal = np.full((3, 3), OCCUPIED, dtype=np.uint8)
    diagonal[[0, 1, 2], [0, 1, 2]] = FREE
    check = planner_check(diagonal, (0.0, 0.0), res, np.zeros((0, 2)), radius=0.01, tolerance=0.0)
    assert (check.paths, check.crossing) == (6, 0)
    corridor = np.full((3, 5), OCCUPIED, dtype=np.uint8)
    corridor[1] = FREE  # y 0.1-0.2 m
    band, pallet = np.array([[0.35, 0.15]]), np.array([[0.15, 0.15]])
    check = planner_check(corridor, (0.0, 0.0), res, band, radius=0.01, tolerance=0.0, body_xy=pallet)
    assert (check.paths, check.crossing, check.crossing_below) == (20, 14, 6)
    assert check.unsafe_m2 == pytest.approx(res * res) and check.unsafe_below_m2 == pytest.approx(res * res)


def test_an_obstacle_exactly_1_m_from_the_path_is_within_1_m():
    """The zones are 'at most this far': on 0.25 m pixels an obstacle pixel 4 pixels (1.00 m) from
    the path's pixel counts in the 1 m zone, one 5 pixels away (1.25 m) only in the 2 m zone."""
    res = 0.25
    image = np.full((3, 8), FREE, dtype=np.uint8)
    path = np.array([[0.125, 0.375]])
    for column, zones in ((4, [1, 1, 1]), (5, [0, 1, 1])):
        obstacle = np.array([[(column + 0.5) * res, 0.375]])
        got = [z.obstacles for z in map_safety(image, (0.0, 0.0), res, obstacle, path)]
        assert got == zones, column
