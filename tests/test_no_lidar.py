"""A robot without a LiDAR (issue 29, item 1): a recording with cameras, USS, IRS and odometry
poses only trains, writes its map and says in one line that nothing was scored; `--gt none` does
the same on any recording; asking for a ground truth the recording lacks is one clean line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli, tiny_train_config

from virus_nerf.config_io import to_dict


@pytest.fixture(scope="module")
def no_lidar(tiny_office, tmp_path_factory) -> Path:
    """The simulated office drive stripped of everything a LiDAR gives: scans, the map, the LiDAR
    poses and the LiDAR-optimised (balm) poses; no depth camera either."""
    root = tmp_path_factory.mktemp("nolidar") / "data"
    shutil.copytree(tiny_office, root)
    room = root / "office"
    shutil.rmtree(room / "lidars")
    shutil.rmtree(room / "maps")
    for p in (room / "poses").iterdir():
        if "lidar" in p.name or "balm" in p.name:
            p.unlink()
    for p in (room / "measurements").glob("CAM*_aligned_depth_to_color_image_raw"):
        shutil.rmtree(p)
    return root


@pytest.fixture(scope="module")
def small_config(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("cfg") / "small.json"
    path.write_text(json.dumps(to_dict(tiny_train_config())))
    return path


def read_pgm(path: Path) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(path))


def test_a_recording_without_lidar_trains_maps_and_says_nothing_was_scored(no_lidar, small_config, tmp_path):
    from virus_nerf.data.ethz import read_poses

    run = tmp_path / "run"
    code, out, err = run_cli(["train", "--data", no_lidar, "--room", "office", "--out", run, "--config",
                              small_config, "--quiet"])
    assert code == 0, err
    assert "no optimised poses" in out and "using the odometry poses" in out
    assert "no LiDAR map" in out and "no metrics computed" in out
    doc = json.loads((run / "metrics.json").read_text())
    assert doc["gt"] is None and doc["sensors"] == {} and doc["train"]["steps"] == 5
    assert json.loads((run / "config.json").read_text())["evaluation"]["gt"] == []
    # 5 steps end inside the grid's 16-step warm-up: said once, in metrics.json and on stdout
    assert any("warm-up" in w for w in doc["warnings"]) and "warning: the run ended inside" in out
    # the map: the box grown from the odometry camera positions by the USS reach (8 m), 1 px = 5 cm
    files = sorted((no_lidar / "office" / "poses").glob("poses_cam_sync*.csv"))
    assert len(files) >= 1
    cams = np.concatenate([read_poses(f)[1][:, :3, 3] for f in files])
    lo, hi = cams.min(axis=0) - 8.0, cams.max(axis=0) + 8.0
    meta = (run / "map" / "map.yaml").read_text()
    assert "resolution: 0.05" in meta
    origin = [float(v) for v in meta.split("origin: [")[1].split("]")[0].split(",")]
    np.testing.assert_allclose(origin[:2], lo[:2], atol=1e-6)
    img = read_pgm(run / "map" / "map.pgm")
    assert img.shape == (int(np.ceil((hi[1] - lo[1]) / 0.05 - 1e-9)), int(np.ceil((hi[0] - lo[0]) / 0.05 - 1e-9)))
    assert set(np.unique(img)) <= {0, 205, 254}
    snap = json.loads((run / "map" / "snapshot.json").read_text())
    assert snap["steps"] == 5 and 0.0 < snap["map_known"] < 1.0
    assert (run / "map" / "prob.pgm").is_file()  # the VIRUS grid's probability map
    # a finished run without ground truth: --resume refuses it like a scored one
    code, _, err = run_cli(["train", "--out", run, "--resume"])
    assert code == 2 and "nothing to resume" in err
    # evaluate without a ground truth to score against: one line
    code, _, err = run_cli(["evaluate", "--run", run])
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "the run was trained without ground truth (evaluation.gt none)" in err and "--gt names" not in err
    # the simulated room has its scene.json but no LiDAR map: only --gt exact can score it
    assert err.endswith("give --gt exact to score it (its recording has no LiDAR map, only the simulator's "
                        "scene.json)\n"), err
    code, _, err = run_cli(["evaluate", "--run", run, "--gt", "none"])
    assert code == 2 and "--gt none: nothing to score" in err and len(err.strip().splitlines()) == 1


def test_evaluate_on_a_run_of_a_recording_without_any_ground_truth_says_so(no_lidar, small_config, tmp_path):
    """No LiDAR map and no simulator scene (a user's own robot without a LiDAR): evaluate says that
    nothing can score the run, rather than suggesting a --gt that the next line refuses."""
    from virus_nerf.evaluation.evaluate import SCENE_FILE

    data = tmp_path / "data"
    shutil.copytree(no_lidar, data)
    run = tmp_path / "run"
    code, _, err = run_cli(["train", "--data", data, "--room", "office", "--out", run, "--config", small_config,
                            "--quiet"])
    assert code == 0, err
    (data / "office" / SCENE_FILE).unlink()
    code, _, err = run_cli(["evaluate", "--run", run])
    assert code == 2 and err == (f"virus-nerf: error: --run {run}: the run was trained without ground truth, and its "
                                 "recording has no LiDAR map (maps/map_*.pcd) to score it against; its map is in the "
                                 "run (export writes it again)\n"), err


def test_asking_for_the_lidar_map_on_a_recording_without_one_is_one_line(no_lidar, small_config, tmp_path):
    code, _, err = run_cli(["train", "--data", no_lidar, "--room", "office", "--out", tmp_path / "run",
                            "--config", small_config, "--gt", "map", "--quiet"])
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "maps" in err and "no map_*.pcd" in err
    assert not (tmp_path / "run").exists()


def test_gt_none_on_a_recording_with_lidar_scores_nothing(tiny_office, small_config, tmp_path):
    run = tmp_path / "run"
    code, out, err = run_cli(["train", "--data", tiny_office, "--room", "office", "--out", run, "--config",
                              small_config, "--gt", "none", "--quiet"])
    assert code == 0, err
    assert "no metrics computed" in out and "no LiDAR map" not in out
    assert json.loads((run / "metrics.json").read_text())["gt"] is None
    assert not (run / "plots").exists() and (run / "map" / "map.pgm").is_file()
    # `export` of the same run writes the very map the run wrote: one map for every consumer
    code, _, err = run_cli(["export", "--run", run, "--out", tmp_path / "export", "--what", "map,prob"])
    assert code == 0, err
    for name in ("map.pgm", "map.yaml", "prob.pgm", "prob.yaml"):
        assert (tmp_path / "export" / name).read_bytes() == (run / "map" / name).read_bytes(), name


def test_gt_flag_parses_none():
    from virus_nerf.errors import UsageError
    from virus_nerf.evaluation.evaluate import EvaluationConfig, parse_gt_flag

    assert parse_gt_flag("none") == ()
    assert parse_gt_flag("map,exact") == ("map", "exact")
    assert EvaluationConfig(gt=()).gt == ()
    with pytest.raises(UsageError, match="or none"):
        parse_gt_flag("nothing")


def test_a_configured_sensor_that_never_answers_is_a_warning(no_lidar, small_config, tmp_path):
    """Issue 30: a robot configured with USS whose recording has no echo at all trains (the USS
    loss is zero) and says so."""
    data = tmp_path / "data"
    shutil.copytree(no_lidar, data)
    for path in (data / "office" / "measurements").glob("USS*.csv"):
        rows = path.read_text().splitlines()
        path.write_text("\n".join([rows[0]] + [r.split(",")[0] + ",50000.0" for r in rows[1:]]) + "\n")  # no echo
    run = tmp_path / "run"
    code, out, err = run_cli(["train", "--data", data, "--room", "office", "--out", run, "--config", small_config,
                              "--quiet"])
    assert code == 0, err
    warnings = json.loads((run / "metrics.json").read_text())["warnings"]
    assert any(w.startswith("configured sensor(s) silent in the recording: uss (no echo") for w in warnings)
    assert "warning: configured sensor(s) silent" in out
