"""NND metrics on hand-placed points with known answers (docs/method.md 6.5, 6.6, 7)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from virus_nerf.evaluation.metrics import (
    DEFAULT_ZONES,
    METRIC_KEYS,
    NNDSamples,
    Zone,
    check_metrics_document,
    format_table,
    mean_std,
    metrics_document,
    nnd_samples,
    sensor_metrics_from_json,
    write_metrics_json,
    zone_metrics,
)
from virus_nerf.maps.scans import FieldOfView, Sector

ORIGIN = np.zeros(2)


def square_room(half: float = 1.5, step: float = 0.01) -> np.ndarray:
    """Points on the walls of the square [-half, half]^2, `step` apart (M, 2)."""
    s = np.arange(-half, half, step)
    return np.concatenate([
        np.stack([s, np.full_like(s, -half)], 1), np.stack([np.full_like(s, half), s], 1),
        np.stack([-s, np.full_like(s, half)], 1), np.stack([np.full_like(s, -half), -s], 1),
    ])


def metrics_of(pred, gt, zones=DEFAULT_ZONES, origin=ORIGIN):
    return zone_metrics(nnd_samples(pred, gt, origin), zones)


def test_scan_shifted_5cm_outward_has_accuracy_5cm_all_too_far():
    gt = square_room(1.5)
    # the right wall's GT points moved 5 cm further out (x = 1.55): every point 5 cm off
    right = gt[gt[:, 0] >= 1.5 - 1e-9]
    pred = right + [0.05, 0.0]
    z3 = metrics_of(pred, gt).zones["zone3"]
    assert z3.acc_mean == pytest.approx(0.05, abs=1e-9)
    assert z3.acc_median == pytest.approx(0.05, abs=1e-9)
    assert z3.acc_inlier == 1.0  # 5 cm < 0.1 m
    assert z3.n_pred == len(pred)
    # shifted by 0.15 m outwards: all outliers and all too far (prediction deeper than the GT)
    z3 = metrics_of(right + [0.15, 0.0], gt).zones["zone3"]
    assert z3.acc_mean == pytest.approx(0.15, abs=1e-6)  # float32 samples: to the micrometre
    assert (z3.acc_inlier, z3.acc_too_close, z3.acc_too_far) == (0.0, 0.0, 1.0)
    # shifted inwards (away from the corners, where the top/bottom walls would be nearer): too close
    z3 = metrics_of(right[np.abs(right[:, 1]) < 1.0] - [0.15, 0.0], gt).zones["zone3"]
    assert (z3.acc_inlier, z3.acc_too_close, z3.acc_too_far) == (0.0, 1.0, 0.0)


def test_scan_of_half_the_room_gives_expected_coverage():
    gt = square_room(1.0, step=0.01)  # 800 points, 200 per wall, corners at +-1
    y = np.arange(-100, 101) / 100.0
    pred = np.stack([np.ones_like(y), y], 1)  # exactly the right wall x = 1, y in [-1, 1]
    z3 = metrics_of(pred, gt).zones["zone3"]
    assert z3.acc_mean == pytest.approx(0.0, abs=1e-12)
    assert z3.n_gt == 800 and z3.n_pred == 201
    # coverage: right wall 0; bottom/top point (x, +-1) -> corner (1, +-1): 1 - x, averaging 1
    # over each wall; left wall (-1, y) -> (1, y): 2.  Mean = (0 + 200 + 200 + 400) / 800 = 1.
    assert z3.cov_mean == pytest.approx(1.0, rel=1e-9)
    # inliers: the 200 right-wall points plus ~9 + 10 top/bottom points within 0.1 m of a corner
    assert z3.cov_inlier == pytest.approx(219 / 800, abs=1.5 / 800)
    # seen from (-0.5, 0) every GT point's nearest prediction (right wall) is deeper than the
    # GT point itself, so all coverage outliers are "too far" (from the centre, the left wall
    # would tie in depth with its right-wall partner)
    zs = metrics_of(pred, gt, origin=np.array([-0.5, 0.0])).zones["zone3"]
    assert zs.cov_mean == pytest.approx(1.0, rel=1e-9)
    assert zs.cov_too_close == 0.0
    assert zs.cov_too_far == pytest.approx(1.0 - zs.cov_inlier)
    # zone 1 holds only GT points within 1 m: the wall centres (0, +-1), (+-1, 0)
    z1 = metrics_of(pred, gt).zones["zone1"]
    assert z1.n_gt == 4 and z1.cov_mean == pytest.approx((0 + 1 + 1 + 2) / 4)


def test_zone_borders_at_exactly_1_and_2_m_are_inclusive():
    gt = np.array([[1.0, 0.0], [0.0, 2.0], [-3.0, 0.0]])  # depths exactly 1.0, 2.0, 3.0
    pred = gt + [[0.02, 0.0], [0.0, -0.5], [0.3, 0.0]]  # errors 0.02, 0.5, 0.3
    m = metrics_of(pred, gt).zones
    assert (m["zone1"].n_gt, m["zone2"].n_gt, m["zone3"].n_gt) == (1, 2, 3)
    assert (m["zone1"].n_pred, m["zone2"].n_pred, m["zone3"].n_pred) == (1, 2, 3)
    assert m["zone1"].acc_mean == pytest.approx(0.02)
    assert m["zone2"].acc_mean == pytest.approx(0.26)
    assert m["zone3"].acc_mean == pytest.approx((0.02 + 0.5 + 0.3) / 3)
    # a GT point at 1.0000001 m is not in zone 1 (float depths, no rounding: docs/method.md 9.7)
    m = metrics_of(np.array([[1.0000001, 0.0]]), np.array([[1.0000001, 0.0]])).zones
    assert m["zone1"].n_gt == 0 and m["zone1"].acc_mean is None and m["zone2"].n_gt == 1
    # nor one at 2.0000001 m in zone 2, though float32 (the pooled samples) has no number between
    # 2 and 2.00000024: the depths are rounded up, never onto a bound
    assert np.float32(2.0000001) == 2.0
    m = metrics_of(np.array([[2.0000001, 0.0]]), np.array([[2.0000001, 0.0]])).zones
    assert m["zone2"].n_gt == 0 and m["zone2"].n_pred == 0 and m["zone3"].n_gt == 1
    # accuracy zone follows the nearest GT point's depth, not the prediction's own depth
    m = metrics_of(np.array([[1.5, 0.0]]), np.array([[0.9, 0.0]])).zones
    assert m["zone1"].n_pred == 1 and m["zone1"].acc_mean == pytest.approx(0.6)
    assert m["zone1"].acc_too_far == 1.0


def test_too_close_and_too_far_split_on_a_placed_case():
    gt = np.array([[2.0, 0.0], [0.0, 3.0]])
    pred = np.array([[1.7, 0.0], [0.0, 3.4], [2.05, 0.0]])
    m = metrics_of(pred, gt).zones["zone3"]
    # accuracy: 0.3 too close, 0.4 too far, 0.05 inlier
    assert m.acc_mean == pytest.approx((0.3 + 0.4 + 0.05) / 3)
    assert (m.acc_inlier, m.acc_too_close, m.acc_too_far) == pytest.approx((1 / 3, 1 / 3, 1 / 3))
    # coverage: GT (2,0) -> (2.05,0) inlier; GT (0,3) -> nearest prediction (0, 3.4): 0.4, too far
    assert m.cov_mean == pytest.approx((0.05 + 0.4) / 2)
    assert (m.cov_inlier, m.cov_too_close, m.cov_too_far) == pytest.approx((0.5, 0.0, 0.5))
    # the prediction nearer to the origin than the GT point: coverage says "too close"
    m = metrics_of(np.array([[0.0, 2.5]]), np.array([[0.0, 3.0]])).zones["zone3"]
    assert (m.cov_too_close, m.cov_too_far) == (1.0, 0.0)
    assert (m.acc_too_close, m.acc_too_far) == (1.0, 0.0)


def test_empty_inputs_give_none_not_nan_and_valid_json(tmp_path):
    empty = np.zeros((0, 2))
    gt = square_room(1.0, 0.05)
    for pred, g in ((empty, gt), (gt, empty), (empty, empty)):
        m = metrics_of(pred, g)
        for zm in m.zones.values():
            d = zm.to_json()
            assert all(d[k] is None for k in METRIC_KEYS if not k.startswith("n_") and k != "gt_unseen")
            assert d["n_pred"] == 0 and d["n_gt"] == 0
            # a sensor silent where GT is in view: every GT point is unseen; no GT: no share
            assert d["gt_unseen"] == (1.0 if len(pred) == 0 and len(g) else None)
    # one zone empty, another not
    m = metrics_of(np.array([[3.0, 0.0]]), np.array([[3.0, 0.0]]))
    assert m.zones["zone1"].acc_mean is None and m.zones["zone3"].acc_mean == 0.0
    doc = write_metrics_json(tmp_path / "m.json", {"USS": metrics_of(empty, gt), "IRS": m})
    text = (tmp_path / "m.json").read_text()
    assert "NaN" not in text and "null" in text
    assert json.loads(text) == doc


def test_pooling_over_test_points_weights_points_not_test_points():
    a = nnd_samples(np.array([[1.1, 0.0]]), np.array([[1.0, 0.0]]), ORIGIN)  # 0.1
    b = nnd_samples(np.array([[0.0, 2.0]] * 3), np.array([[0.0, 2.0]]), ORIGIN)  # 0, 0, 0
    m = zone_metrics(NNDSamples.concat([a, b])).zones["zone3"]
    assert m.acc_mean == pytest.approx(0.1 / 4)
    assert m.n_pred == 4 and m.n_gt == 2


def test_field_of_view_sectors():
    s = Sector(np.array([1.0, 1.0]), np.deg2rad(90.0), np.deg2rad(22.5))
    pts = np.array([[1.0, 3.0], [1.0 + np.tan(np.deg2rad(22.0)), 2.0], [1.0 + np.tan(np.deg2rad(23.0)), 2.0], [1.0, 0.0]])
    assert s.contains(pts).tolist() == [True, True, False, False]
    # wrap-around at +-180 deg
    s = Sector(np.zeros(2), np.pi, np.deg2rad(10.0))
    assert s.contains(np.array([[-1.0, 0.1], [-1.0, -0.1], [1.0, 0.0]])).tolist() == [True, True, False]
    fov = FieldOfView((Sector(np.zeros(2), 0.0, 0.1), Sector(np.zeros(2), np.pi / 2, 0.1)))
    assert fov.contains(np.array([[1, 0], [0, 1], [-1, 0]])).tolist() == [True, True, False]
    assert FieldOfView.full(np.zeros(2)).contains(np.array([[-1, 0], [0, -5]])).all()
    assert not FieldOfView(()).contains(np.array([[1.0, 0.0]])).any()


def test_metrics_document_schema_and_table():
    m = metrics_of(np.array([[1.05, 0.0], [0.0, 1.5]]), np.array([[1.0, 0.0], [0.0, 1.5], [-4.0, 0.0]]))
    train = {"steps": 800, "seconds": 80.0, "steps_per_s": 10.0, "samples_per_s": 1.0e6,
             "grid": "virus", "sensors": ["camera", "uss", "irs"], "seed": 0}
    doc = metrics_document({"NeRF": m, "LiDAR": m}, DEFAULT_ZONES, train)
    assert doc["zones"] == {"zone1": [0, 1], "zone2": [0, 2], "zone3": [0, 100]}
    assert list(doc) == ["gt", "zones", "inlier_m", "sensors", "train"] and doc["train"] == train and doc["gt"] == "map"
    assert list(doc["sensors"]["NeRF"]) == ["zone1", "zone2", "zone3"]
    assert tuple(doc["sensors"]["NeRF"]["zone3"]) == METRIC_KEYS
    assert doc["sensors"]["NeRF"]["zone3"]["n_gt"] == 3 and doc["sensors"]["NeRF"]["zone1"]["n_gt"] == 1
    json.dumps(doc, allow_nan=False)
    bad = json.loads(json.dumps(doc))
    bad["sensors"]["NeRF"]["zone3"]["acc_mean"] = math.nan
    with pytest.raises(ValueError, match="finite"):
        check_metrics_document(bad)
    del bad["sensors"]["LiDAR"]["zone1"]["cov_mean"]
    with pytest.raises(ValueError):
        check_metrics_document(bad)
    assert "train" not in metrics_document({"NeRF": m})
    scored = metrics_document({"NeRF": m}, scoring={"n_rays": 128, "test_points": 7})
    assert list(scored)[:4] == ["gt", "zones", "inlier_m", "scoring"] and scored["scoring"]["n_rays"] == 128
    with pytest.raises(ValueError, match="scoring"):
        check_metrics_document({**scored, "scoring": {"n_rays": -1}})
    back = sensor_metrics_from_json(json.loads(json.dumps(doc)))
    assert back["NeRF"] == m and list(back) == ["NeRF", "LiDAR"]
    table = format_table({"NeRF": m, "USS": metrics_of(np.zeros((0, 2)), np.ones((1, 2)))})
    lines = table.splitlines()
    assert len(lines) == 1 + 6 and lines[0].split()[:3] == ["sensor", "zone", "acc_mean"]
    assert lines[3].split()[:3] == ["NeRF", "zone3", "0.025"]  # (0.05 + 0) / 2 predictions
    assert lines[4].split()[2] == "-"  # USS without points


def test_mean_std_is_the_sample_std_over_runs():
    # hand-computed: values .1 .2 .3 -> mean .2, sample variance ((.1)^2 + 0 + (.1)^2) / 2 = .01
    assert mean_std([0.1, 0.2, 0.3]) == pytest.approx((0.2, 0.1))
    assert mean_std([0.1, None, 0.3]) == pytest.approx((0.2, math.sqrt(0.02)))  # None skipped
    assert mean_std([0.5]) == (0.5, 0.0)  # one run: no spread
    assert mean_std([None, None]) == (None, None)


def test_custom_zones():
    zones = (Zone("near", 0.0, 0.5), Zone("far", 0.5, 10.0))
    m = metrics_of(np.array([[0.5, 0.0]]), np.array([[0.5, 0.0]]), zones)
    assert m.zones["near"].n_gt == 1 and m.zones["far"].n_gt == 1  # 0.5 belongs to both
    assert list(metrics_document({"X": m}, zones)["zones"]) == ["near", "far"]
