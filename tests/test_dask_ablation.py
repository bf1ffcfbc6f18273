"""Ablation on a Dask cluster (issue 14): 2 rows x 1 seed on a LocalCluster give the same table as
local processes for the same seeds and step budgets (steps/s aside: that is the machine's clock)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from helpers import ctrl_c_raises, tiny_train_config

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


def _hold_lock(out: Path, seconds: float, then_checkpoint: bool):
    """A training's stand-in in another process: holds OUT's run lock for `seconds`, then (as a
    stopped training does) leaves its checkpoint and exits."""
    import subprocess
    import sys

    script = (f"import time, pathlib\nfrom virus_nerf.trainer.run_folder import RunLock\n"
              f"out = pathlib.Path({str(out)!r})\nRunLock(out).acquire()\nprint('locked', flush=True)\n"
              f"time.sleep({seconds})\n" + ("(out / 'checkpoint.pt').write_bytes(b'x')\n" if then_checkpoint else ""))
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_an_attempt_waits_for_a_training_still_stopping_in_its_folder(tmp_path):
    """A training stopped a moment ago (its Dask worker lost, the same ablation run again at once)
    ends its step and keeps its checkpoint before it lets go of the lock; the next attempt waits
    for that instead of setting the live folder aside (it then resumes it). Still held after the
    wait: not started, said in the run's log."""
    import time

    from virus_nerf.experiments import runs

    out = tmp_path / "runs" / "office" / "row8_seed0"
    out.mkdir(parents=True)
    spec = runs.RunSpec("row 8", tmp_path / "data", "office", out)
    holder = _hold_lock(out, 1.5, then_checkpoint=True)
    t0 = time.monotonic()
    assert runs._wait_for_the_holder(spec) is True
    assert time.monotonic() - t0 >= 1.0 and (out / "checkpoint.pt").is_file()  # so the attempt resumes it
    holder.wait(timeout=30)
    holder = _hold_lock(out, 30.0, then_checkpoint=False)
    try:
        assert runs._wait_for_the_holder(spec, wait_s=0.5) is False
        assert "is still locked by another training after 0.5 s; not started" in runs.log_file(out).read_text()
    finally:
        holder.kill()
        holder.wait(timeout=30)


def test_a_failed_new_run_removes_only_its_own_folder(tmp_path):
    """RunLock.holds: the folder renamed aside by another process is still ours, the new folder
    that took its name is not (train's clean-up must not delete another run)."""
    from virus_nerf.trainer.run_folder import RunLock

    out = tmp_path / "row8_seed0"
    out.mkdir()
    lock = RunLock(out).acquire()
    aside = out.rename(tmp_path / "row8_seed0.incomplete-1")
    out.mkdir()
    (out / "run.lock").write_text("")
    assert not lock.holds(out) and lock.holds(aside)


def test_a_port_that_is_no_scheduler_is_one_line_before_anything_is_written(tmp_path, monkeypatch):
    """--scheduler at a port that accepts and never answers (a dashboard's, any other service's):
    distributed's own timeout does not end it; ours does, in one line naming the flag, before the
    ablation or the study writes anything (loopback only; the listener stops with the test)."""
    import socket

    pytest.importorskip("distributed")
    from helpers import run_cli

    from virus_nerf.experiments import executors

    monkeypatch.setattr(executors, "CONNECT_TIMEOUT_S", 2.0)
    (tmp_path / "office" / "maps").mkdir(parents=True)
    (tmp_path / "office" / "maps" / "map.pcd").write_text("not read: refused before")  # tune's room has a LiDAR map
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(8)  # accepts (the kernel does), never answers
    try:
        address = f"tcp://127.0.0.1:{listener.getsockname()[1]}"
        for argv, out in ((["ablation", "--out", tmp_path / "abl", "--quick"], tmp_path / "abl"),
                          (["tune", "--data", tmp_path, "--room", "office", "--study", "s", "--trials", "1",
                            "--out", tmp_path / "study"], tmp_path / "study")):
            code, _, err = run_cli([*argv, "--scheduler", address])
            assert code == 2 and err.count("\n") == 1, err
            assert f"--scheduler {address}: nothing answered as a Dask scheduler within 2 s" in err
            assert not out.exists()
    finally:
        listener.close()


@pytest.mark.slow
@pytest.mark.parametrize("scheduler", [None, "dask"])
def test_a_stopped_command_stops_its_trainings_and_the_same_command_continues_them(tiny_office, tmp_path,
                                                                                  scheduler):
    """The command alone is stopped (a supervisor's SIGTERM to its pid, not the terminal's Ctrl-C to
    the whole group): its training ends its step and keeps its checkpoint, on a Dask worker too,
    whose child a training is (the cluster stays up: no worker dies to end it). Run again, the
    same runs continue from their checkpoints to the end."""
    import os
    import signal
    import threading
    import time

    from virus_nerf.experiments.executors import run_all
    from virus_nerf.experiments.runs import STOP_GRACE_S, STOPPED_WITH_CALLER, RunSpec, stop_file
    from virus_nerf.trainer.run_folder import RunLock

    cfg = tmp_path / "tiny.json"
    cfg.write_text(json.dumps(to_dict(tiny_train_config())))
    out = tmp_path / "runs" / "r"
    spec = RunSpec("r", tiny_office, "office", out, ("--config", str(cfg), "--max-steps", "100"))

    def interrupt_once_training() -> None:
        t0 = time.monotonic()  # a few steps in: train_log.csv has a row every 2 steps (flushed)
        while time.monotonic() - t0 < 120:
            log = out / "train_log.csv"
            if log.is_file() and log.read_text().count("\n") >= 3:
                break
            time.sleep(0.05)
        os.kill(os.getpid(), signal.SIGINT)  # to this process alone: the training is not in its group

    def run(address):
        threading.Thread(target=interrupt_once_training, daemon=True).start()
        with ctrl_c_raises(), pytest.raises(KeyboardInterrupt):
            run_all([spec], workers=1, threads_per_worker=1, scheduler=address)
        t0 = time.monotonic()  # the training ends its step on its own (the cluster is still up)
        while RunLock(out).held_by_another() and time.monotonic() - t0 < STOP_GRACE_S + 30:
            time.sleep(0.2)
        shown = f"the run's log:\n{log_text(out)}"  # what the attempts and the training said, if it fails
        assert not RunLock(out).held_by_another(), shown
        assert stop_file(out).read_text().strip() == STOPPED_WITH_CALLER, shown
        assert (out / "checkpoint.pt").is_file() and not (out / "metrics.json").exists(), shown
        assert run_all([spec], workers=1, threads_per_worker=1, scheduler=address) == []

    if scheduler is None:
        run(None)
    else:
        distributed = pytest.importorskip("distributed")
        with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                      dashboard_address=None) as cluster:
            run(cluster.scheduler_address)
    assert not stop_file(out).exists()
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["train"]["steps"] == 100
    assert "--resume" in log_text(out)


def log_text(out: Path) -> str:
    from virus_nerf.experiments.runs import log_file

    return log_file(out).read_text()
