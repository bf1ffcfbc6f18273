"""Ablation on a Dask cluster (issue 14): 2 rows x 1 seed on a LocalCluster give the same table as
local processes for the same seeds and step budgets (steps/s aside: that is the machine's clock)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from helpers import tiny_train_config

from virus_nerf.config_io import to_dict


def _ablate(out: Path, data: Path, cfg: Path, **executor) -> list[dict]:
    from virus_nerf.experiments.ablation import ablation

    (out / "data").mkdir(parents=True)
    (out / "data" / "office").symlink_to(data)  # the tiny recording, not a fresh simulation
    ablation(out=out, seeds=1, rows="2,8", max_steps=4, scenes=("office",), config=cfg, threads_per_run=1,
             **executor)
    doc = json.loads((out / "ablation.json").read_text())
    assert doc["max_steps"] == 4 and doc["failed"] == [] and doc["train_time"] is None
    for run in (out / "runs" / "office").glob("row*_seed*"):
        if run.is_dir():
            assert json.loads((run / "metrics.json").read_text())["train"]["steps"] == 4
    return [{k: v for k, v in r.items() if not k.startswith("steps_per_s")} for r in doc["records"]]


def test_ablation_on_a_local_dask_cluster_equals_local_processes(tiny_office, tmp_path):
    distributed = pytest.importorskip("distributed")
    cfg = tmp_path / "tiny.json"
    cfg.write_text(json.dumps(to_dict(tiny_train_config())))
    local = _ablate(tmp_path / "local", tiny_office, cfg, workers=2)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        dask = _ablate(tmp_path / "dask", tiny_office, cfg, scheduler=cluster.scheduler_address)
    assert [(r["row"], r["runs"], r["failed"]) for r in local] == [(2, 1, 0), (8, 1, 0)]
    assert all(r["acc_mean"] is not None for r in local)
    assert dask == local
    # the run folders look the same whichever executor ran them
    names = sorted(p.name for p in (tmp_path / "local" / "runs" / "office").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "dask" / "runs" / "office").iterdir())
    assert names == ["row2_seed0", "row2_seed0.log", "row8_seed0", "row8_seed0.log"]


def test_a_finished_ablation_run_is_never_rerun(tmp_path):
    """run_all skips a run whose metrics.json exists, whichever executor would run it."""
    from virus_nerf.experiments.executors import run_all
    from virus_nerf.experiments.runs import RunSpec

    run = tmp_path / "runs" / "r"
    run.mkdir(parents=True)
    (run / "metrics.json").write_text("{}")
    before = (run / "metrics.json").stat().st_mtime_ns
    assert run_all([RunSpec("r", tmp_path / "no-data", "office", run)], workers=1) == []
    assert (run / "metrics.json").stat().st_mtime_ns == before and not (tmp_path / "runs" / "r.log").exists()
