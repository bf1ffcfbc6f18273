"""Experiment plumbing with known answers: map export, ablation aggregation, online bands, demo."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from virus_nerf.evaluation.metrics import RunMetrics
from virus_nerf.experiments import ablation as abl
from virus_nerf.experiments.online import band
from virus_nerf.maps.occupancy import FREE, OCCUPIED, UNKNOWN, scan_occupancy, write_map_server
from virus_nerf.trainer.run_folder import EvalPoint


def test_scan_occupancy_marks_path_free_and_end_occupied(tmp_path):
    # four rays from (0.5, 0.5) along +-x, +-y, each ending 1 m away; map 3 x 3 m at 0.1 m
    origins = np.full((4, 2), 0.5) + 1.0
    dirs = np.array([[1.0, 0], [-1, 0], [0, 1], [0, -1]])
    m = scan_occupancy(origins, dirs, np.ones(4), np.zeros(2), np.full(2, 3.0), 0.1)
    img = np.flipud(m.image).T  # back to [ix, iy]
    assert img.shape == (30, 30)
    assert img[25, 15] == OCCUPIED and img[5, 15] == OCCUPIED and img[15, 25] == OCCUPIED and img[15, 5] == OCCUPIED
    assert img[20, 15] == FREE and img[15, 10] == FREE
    assert img[0, 0] == UNKNOWN and img[28, 28] == UNKNOWN
    assert np.count_nonzero(img == OCCUPIED) == 4
    pgm, yaml = write_map_server(m, tmp_path)
    assert pgm.read_bytes().startswith(b"P5\n30 30\n255\n") and len(pgm.read_bytes()) == 13 + 900
    assert "origin: [0.0, 0.0, 0.0]" in yaml.read_text() and "resolution: 0.1\n" in yaml.read_text()
    assert "mode: trinary" in yaml.read_text()
    # a box corner in float32 (-2.995 is -2.99499998...): map.yaml keeps it to the bit, so a point on
    # a pixel edge falls in the same pixel for a map_server reader as for the safety figures
    import dataclasses

    odd = dataclasses.replace(m, origin=(float(np.float32(-2.995)), float(np.float32(1.1))))
    _, yaml = write_map_server(odd, tmp_path / "odd")
    got = [float(v) for v in yaml.read_text().split("origin: [")[1].split("]")[0].split(",")]
    assert got[:2] == list(odd.origin) and got[2] == 0.0


def test_a_grown_box_gets_one_raster_size_everywhere():
    """A box grown by whole 8 cm cells from an odd corner: 5 cells = 0.4 m, 8 pixels of 5 cm,
    though (hi - lo) / 0.05 comes out a hair above 8 in floating point. The scans' raster and the
    observed mask must agree (before: the scans' raster was 9 x 9 and masking it raised an
    IndexError in a warehouse run while driving)."""
    from virus_nerf.maps.observed import apply_mask
    from virus_nerf.maps.occupancy import raster_shape

    lo = np.array([0.24198999999999998, -5.23161])
    hi = lo + 5 * 0.08
    assert (hi - lo)[0] / 0.05 > 8.0 and raster_shape(lo, hi, 0.05) == (8, 8)
    m = scan_occupancy(np.array([lo + 0.2]), np.array([[1.0, 0.0]]), np.array([0.1]), lo, hi, 0.05)
    assert m.image.shape == (8, 8)
    masked = apply_mask(m.image, np.zeros((8, 8), dtype=bool), UNKNOWN)
    assert np.all(masked == UNKNOWN)


def test_missed_rays_mark_nothing():
    m = scan_occupancy(np.zeros((2, 2)) + 1, np.array([[1.0, 0], [0, 1]]), np.array([np.nan, -1.0]),
                       np.zeros(2), np.full(2, 2.0), 0.1)
    assert np.all(m.image == UNKNOWN)


def fake_metrics(acc: float, cov: float, steps_per_s: float) -> dict:
    """A metrics.json of a run whose NeRF zone 3 scored `acc`/`cov` (m), written by hand."""
    keys = ("acc_mean", "acc_median", "acc_inlier", "acc_too_close", "acc_too_far", "cov_mean", "cov_median",
            "cov_inlier", "cov_too_close", "cov_too_far", "gt_unseen", "n_pred", "n_gt")
    given = {"acc_mean": acc, "cov_mean": cov, "acc_inlier": 0.5, "cov_inlier": 0.25, "n_pred": 10, "n_gt": 10}
    zone = {k: given.get(k) for k in keys}
    empty = {k: (0 if k.startswith("n_") else None) for k in keys}
    return {"gt": "map", "zones": {"zone1": [0, 1], "zone2": [0, 2], "zone3": [0, 100]},
            "sensors": {"NeRF": {"zone1": empty, "zone2": empty, "zone3": zone}},
            "train": {"steps_per_s": steps_per_s}}


def test_ablation_aggregates_mean_and_std(tmp_path):
    for row, (accs, sps) in {2: ([0.2, 0.4], 2.0), 8: ([0.1, 0.3], 3.0)}.items():
        for seed, acc in enumerate(accs):
            run = tmp_path / "runs" / "office" / f"row{row}_seed{seed}"
            run.mkdir(parents=True)
            (run / "metrics.json").write_text(json.dumps(fake_metrics(acc, 2 * acc, sps)))
    records = abl.aggregate(tmp_path, ("office",), seeds=2)
    assert len(records) == 9  # Table I's eight rows and row 9 (the stereo sensor)
    r8 = next(r for r in records if r["row"] == 8)
    # sample std (ddof 1) of 0.1 and 0.3: sqrt(((0.1)^2 + (0.1)^2) / 1) = 0.1414
    assert r8["runs"] == 2 and r8["acc_mean"] == pytest.approx(0.2) and r8["acc_mean_std"] == pytest.approx(0.02**0.5)
    assert r8["cov_mean"] == pytest.approx(0.4) and r8["paper_acc_mean"] == 0.148
    r1 = next(r for r in records if r["row"] == 1)
    assert r1["runs"] == 0 and r1["acc_mean"] is None
    assert abl.grid_speed(records) == {"office": pytest.approx(1.5)}
    md = abl.table_markdown(records)
    assert "0.200 ± 0.141" in md and md.count("\n") == 10 and "authors' scoring" in md
    assert r8["zone3"] == "0-100 m"  # the runs' own zone, as their metrics.json give it
    moved = fake_metrics(0.1, 0.2, 1.0)
    moved["zones"]["zone3"] = [2, 3]
    assert abl.zone_bounds([RunMetrics.from_document(moved)]) == "2-3 m"
    abl.plot_rows(records, tmp_path / "ablation.png")
    from PIL import Image

    with Image.open(tmp_path / "ablation.png") as im:  # a decodable figure with something drawn on it
        assert im.width > 300 and im.height > 200 and len(im.convert("L").getcolors(1 << 16) or []) > 10


def test_the_runs_warnings_reach_the_experiment_summary(tmp_path):
    """ablation.md/json and online.md/json list the runs' own warnings (a --quick budget ends inside
    the grid's warm-up), run by run; runs without any are left out."""
    from virus_nerf.experiments.report import runs_warnings, warnings_markdown

    warned, fine = tmp_path / "runs" / "office" / "row8_seed0", tmp_path / "runs" / "office" / "row8_seed1"
    for run, warnings in ((warned, ["the run ended inside the occupancy grid's warm-up (step 6)"]), (fine, [])):
        run.mkdir(parents=True)
        (run / "metrics.json").write_text(json.dumps({**fake_metrics(0.2, 0.3, 1.0), "warnings": warnings}))
    found = runs_warnings([warned, fine, tmp_path / "runs" / "never_ran"], tmp_path)
    assert found == {"runs/office/row8_seed0": ["the run ended inside the occupancy grid's warm-up (step 6)"]}
    md = warnings_markdown(found)
    assert md.startswith("## Warnings\n") and "- `runs/office/row8_seed0`: the run ended inside" in md
    assert warnings_markdown({}) == ""


def test_online_band_interpolates_and_spreads():
    grid = np.array([0.0, 5.0, 10.0, 20.0])
    def point(t: float, acc: float) -> EvalPoint:
        return EvalPoint(step=0, seconds=t, acc_mean=acc, cov_mean=None, acc_inlier=None, cov_inlier=None,
                         n_test_points=1)

    h1 = [point(0.0, 1.0), point(10.0, 0.0)]
    h2 = [point(0.0, 3.0), point(10.0, 2.0)]
    mean, std = band([h1, h2], "acc_mean", grid)
    np.testing.assert_allclose(mean[:3], [2.0, 1.5, 1.0])
    np.testing.assert_allclose(std[:3], [2.0**0.5] * 3)  # sample std of two values 2 apart
    assert np.isnan(mean[3])


@pytest.mark.slow
def test_demo_end_to_end(tmp_path: Path):
    from virus_nerf.experiments.demo import demo

    out = tmp_path / "demo"
    demo(out=out, seed=1, duration=3.0, train_time=4.0, quiet=True)
    report = (out / "report.md").read_text()
    assert "| NeRF | zone3" in report and "| LiDAR | zone3" in report
    doc = json.loads((out / "metrics.json").read_text())
    assert f"s of training on the {doc['train']['device']} device: {doc['train']['steps']} steps" in report
    assert doc["train"]["grid"] == "virus" and doc["train"]["sensors"] == ["camera", "uss", "irs", "stereo"]
    assert "VIRUS-NeRF trained on the cameras' colour, their triangulated depth, USS and IRS with" in report
    # the planner-safety figure and the warnings (a 4 s run ends in the grid's warm-up) in the report too
    def pct(v):
        return "-" if v is None else f"{100 * v:.1f} %"

    safety = doc["safety"]
    shares = " | ".join(pct(b["free_share"]) for b in safety["zones"].values())
    assert "## Can a planner trust the map?" in report
    assert (f"| the map (`export`'s `map.pgm`) | {shares} | {pct(safety['free_recall'])} | "
            f"{pct(safety['free_recall_drivable'])} |") in report
    lidar = safety["anchors"]["lidar"]
    assert f"| LiDAR 2D map | {' | '.join(pct(b['free_share']) for b in lidar['zones'].values())} |" in report
    below = " / ".join(pct(b["free_share"]) for b in safety["below_band"].values())
    assert f"marked free within 1 m / 2 m / all: the map (`export`'s `map.pgm`) {below}; USS + IRS alone" in report
    assert "(run/plots/map_safety.png)" in report and (out / "run" / "plots" / "map_safety.png").is_file()
    assert "brown: what the body meets below the band; orange: the part of it the map marks free." in report
    assert all(f"**Warning:** {w}" in report for w in doc["warnings"]) and doc["warnings"]
    for image in ("metrics_bars.png",):
        assert (out / "run" / "plots" / image).is_file()
    from virus_nerf.errors import OutputExistsError

    with pytest.raises(OutputExistsError):
        demo(out=out, duration=3.0, train_time=4.0, quiet=True)
