"""`virus-nerf tune` (issue 14): search space, objective, runs retried once and stopped on request,
trials that crash or get pruned, a resumable study on a tiny simulated room, the best trial as a
config file `train --config` reads, and one-line errors (a missing extra included)."""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path

import pytest
from helpers import ctrl_c_raises, run_cli, tiny_train_config

from virus_nerf.config_io import load_json_config, to_dict
from virus_nerf.experiments import search_space as ss
from virus_nerf.experiments.runs import RunResult, RunSpec, execute_run, request_stop, stop_file
from virus_nerf.experiments.study import Objective
from virus_nerf.trainer.config import TrainConfig
from virus_nerf.trainer.run_folder import EvalPoint, write_eval_history

optuna = pytest.importorskip("optuna")


# ------------------------------------------------------------------------------ search space
def test_search_space_ranges_hold_the_defaults_and_build_valid_configs():
    assert ss.defaults_inside() == []
    keys = [p.key for p in ss.SEARCH_SPACE]
    assert len(keys) == len(set(keys)) == 11
    base = to_dict(TrainConfig())
    for pick in (lambda p: p.low, lambda p: p.high):  # both ends of every range pass the config checks
        params = {p.key: int(pick(p)) if p.integer else pick(p) for p in ss.SEARCH_SPACE}
        cfg = ss.build_config(base, params)
        assert cfg.virus_grid.zeta == params["virus_grid.zeta"] and cfg.optim.lr == params["optim.lr"]
    with pytest.raises(KeyError, match="virus_grid.bogus"):
        ss.apply_params(base, {"virus_grid.bogus": 1})
    assert set(ss.distributions()) == set(keys)
    assert ss.space_table().count("\n") == len(keys) + 1


def test_objective_weighted_and_multi():
    assert Objective("weighted", 0.25).values(0.2, 0.6) == [pytest.approx(0.25 * 0.2 + 0.75 * 0.6)]
    assert Objective("multi").values(0.2, 0.6) == [0.2, 0.6]
    assert Objective().values(None, 0.3) is None


# ------------------------------------------------------------------------------ one run: retry, stop
@dataclass(frozen=True)
class ScriptSpec(RunSpec):
    """A RunSpec whose process is a small Python script (argv[1] = the run folder)."""

    script: str = ""

    def command(self) -> list[str]:
        return [sys.executable, "-c", self.script, str(self.out)]


CRASH_ONCE = ("import sys, pathlib\no = pathlib.Path(sys.argv[1]); o.mkdir(); m = o.with_name('crashed')\n"
              "if not m.exists(): m.touch(); sys.exit(3)\n(o / 'metrics.json').write_text('{}')")


def spec(tmp_path: Path, script: str) -> ScriptSpec:
    return ScriptSpec("s", tmp_path, "office", tmp_path / "run", script=script)


def test_a_run_that_dies_is_retried_once(tmp_path):
    res = execute_run(spec(tmp_path, CRASH_ONCE), poll_s=0.05)
    assert res.ok and res.attempts == 2 and res.returncode == 0
    # the folder of the dead attempt is kept aside, never deleted
    assert len(list(tmp_path.glob("run.incomplete-*"))) == 1
    assert execute_run(spec(tmp_path, "import sys; sys.exit(9)")).attempts == 0  # finished: never rerun


def test_a_run_that_dies_twice_fails_and_usage_errors_are_not_retried(tmp_path):
    res = execute_run(spec(tmp_path, "import sys; sys.exit(3)"), poll_s=0.05)
    assert not res.ok and res.attempts == 2 and res.returncode == 3
    res = execute_run(spec(tmp_path / "u", "import sys; sys.exit(2)"), poll_s=0.05)
    assert not res.ok and res.attempts == 1
    assert (tmp_path / "run.log").read_text().count("# ") == 2


def test_a_run_stopped_by_a_signal_is_not_retried(tmp_path):
    """A training ended by SIGINT or SIGTERM (a Ctrl-C to the whole process group, a shutdown)
    was stopped, not dead: one attempt, reported stopped."""
    for code in (130, 143):
        res = execute_run(spec(tmp_path / str(code), f"import sys; sys.exit({code})"), poll_s=0.05)
        assert res.stopped and res.attempts == 1 and res.returncode == code and not res.ok
    res = execute_run(spec(tmp_path / "term", "import os, signal; os.kill(os.getpid(), signal.SIGTERM)"), poll_s=0.05)
    assert res.stopped and res.attempts == 1 and res.returncode == -15


def test_a_stop_file_terminates_the_run_and_keeps_its_folder(tmp_path):
    s = spec(tmp_path, "import sys, time, pathlib; pathlib.Path(sys.argv[1]).mkdir(); time.sleep(60)")
    threading.Timer(0.5, request_stop, args=(s.out, "test")).start()
    t0 = time.perf_counter()
    res = execute_run(s, poll_s=0.05)
    assert res.stopped and res.attempts == 1 and not res.ok
    assert time.perf_counter() - t0 < 20 and s.out.is_dir() and stop_file(s.out).is_file()


def test_a_training_slow_to_stop_is_given_its_grace_then_killed_and_the_log_says_so(tmp_path, monkeypatch):
    """Asked to stop, a training writes its map and checkpoint (seconds, more on a shared CPU):
    it is killed only after runs.STOP_GRACE_S, and the run's log says it was."""
    from virus_nerf.experiments import runs

    slow = ("import signal, sys, time, pathlib; o = pathlib.Path(sys.argv[1]); o.mkdir()\n"
            "def bye(*_): time.sleep(1.0); (o / 'kept').touch(); sys.exit(143)\n"
            "signal.signal(signal.SIGTERM, bye); time.sleep(60)")
    monkeypatch.setattr(runs, "STOP_GRACE_S", 5.0)
    s = spec(tmp_path / "slow", slow)
    threading.Timer(0.5, request_stop, args=(s.out, "test")).start()
    res = execute_run(s, poll_s=0.05)
    assert res.stopped and res.returncode == 143 and (s.out / "kept").is_file()  # 1 s of writing: not cut
    deaf = "import signal, sys, time, pathlib; pathlib.Path(sys.argv[1]).mkdir(); signal.signal(15, signal.SIG_IGN); time.sleep(60)"
    monkeypatch.setattr(runs, "STOP_GRACE_S", 0.5)
    s = spec(tmp_path / "deaf", deaf)
    threading.Timer(0.5, request_stop, args=(s.out, "test")).start()
    res = execute_run(s, poll_s=0.05)
    assert res.stopped and res.returncode == -9
    assert "did not stop within 0.5 s of SIGTERM; killed" in (tmp_path / "deaf" / "run.log").read_text()


# ------------------------------------------------------------------------------ trials: crash, prune
class FakeExecutor:
    """Runs `fn(spec)` in a thread instead of a training (what the study sees is the same)."""

    def __init__(self, fn):
        self.fn = fn

    def submit(self, spec):
        fut: Future = Future()

        def run() -> None:
            try:
                fut.set_result(self.fn(spec))
            except Exception as exc:
                fut.set_exception(exc)

        threading.Thread(target=run, daemon=True).start()
        return fut


def _context(tmp_path, fn, prune=True):
    from virus_nerf.experiments.study import open_study
    from virus_nerf.experiments.tune import _Context

    study, base = open_study("t", optuna.storages.InMemoryStorage(), Objective(), None, 0, "median",
                             tmp_path, "office")
    return _Context(study, FakeExecutor(fn), Objective(), base, tmp_path, "office", tmp_path / "trials",
                    eval_interval=10.0, prune=prune, poll_s=0.05)


def test_a_crashing_trial_is_failed_and_the_study_goes_on(tmp_path):
    from virus_nerf.experiments.tune import run_trials

    ctx = _context(tmp_path, lambda s: RunResult(s, 1, attempts=2))
    run_trials(ctx, 2, parallel=1)
    states = [t.state for t in ctx.study.trials]
    assert states == [optuna.trial.TrialState.FAIL] * 2
    assert json.loads((tmp_path / "trials" / "0001.json").read_text())["optim"]["lr"] == ctx.study.trials[1].params["optim.lr"]


def test_parallel_trials_get_the_configurations_sequential_ones_get(tmp_path):
    """The seeded sampler is asked one trial at a time, so trial n has the same configuration with
    --parallel 3 as one after another (the threads' asks interleaved its draws before)."""
    from virus_nerf.experiments.tune import run_trials

    params = []
    for parallel in (1, 3, 3):
        ctx = _context(tmp_path / f"p{parallel}_{len(params)}", lambda s: RunResult(s, 1, attempts=1))
        run_trials(ctx, 9, parallel=parallel)
        params.append({t.number: t.params for t in ctx.study.trials})
    assert len(params[0]) == 9 and params[1] == params[0] and params[2] == params[0]


def test_a_trial_worse_than_the_median_is_pruned_and_its_run_kept(tmp_path):
    from virus_nerf.experiments.tune import run_trial

    def slow_bad_run(spec):
        spec.out.mkdir(parents=True)
        points = [EvalPoint(k * 10, 10.0 * k, 1.0, 2.0, 0.1, 0.1, 3) for k in (1, 2, 3)]
        write_eval_history(spec.out / "metrics_vs_time.csv", points)
        for _ in range(200):  # the study must ask it to stop
            if stop_file(spec.out).exists():
                return RunResult(spec, -15, 1, stopped=True)
            time.sleep(0.05)
        return RunResult(spec, 0, 1)

    ctx = _context(tmp_path, slow_bad_run)
    dists = ss.distributions()
    params = {k: d.low for k, d in dists.items()}
    for _ in range(3):  # three finished trials with good curves
        ctx.study.add_trial(optuna.trial.create_trial(params=params, distributions=dists, value=0.2,
                                                      intermediate_values={1: 0.3, 2: 0.25, 3: 0.2}))
    line = run_trial(ctx)
    trial = ctx.study.trials[-1]
    assert trial.state == optuna.trial.TrialState.PRUNED, line
    assert "pruned" in line and (tmp_path / "trials" / "0003").is_dir()
    assert trial.intermediate_values[1] == pytest.approx(1.5)  # 0.5 * acc 1.0 + 0.5 * cov 2.0


def test_a_stopped_tune_stops_its_trials_trainings_and_asks_no_more(tmp_path):
    """Ctrl-C or SIGTERM to tune alone: the trial waiting on a training (on a Dask worker it is
    no child of tune) writes its stop file, the training ends, the trial is failed and no trial is
    asked after it."""
    import signal

    from virus_nerf.experiments.runs import STOPPED_WITH_CALLER
    from virus_nerf.experiments.tune import run_trials

    def training(spec):  # ends only when asked to, as a training on a worker would
        spec.out.mkdir(parents=True)
        for _ in range(400):
            if stop_file(spec.out).exists():
                return RunResult(spec, -15, 1, stopped=True)
            time.sleep(0.05)
        return RunResult(spec, 0, 1)

    ctx = _context(tmp_path, training)
    with ctrl_c_raises():
        threading.Timer(0.5, os.kill, args=(os.getpid(), signal.SIGINT)).start()
        t0 = time.monotonic()
        with pytest.raises(KeyboardInterrupt):
            run_trials(ctx, 3, parallel=1)
    assert time.monotonic() - t0 < 10  # not the 20 s the training would run unasked
    assert [t.state for t in ctx.study.trials] == [optuna.trial.TrialState.FAIL]
    assert stop_file(tmp_path / "trials" / "0000").read_text().strip() == STOPPED_WITH_CALLER


# ------------------------------------------------------------------------------ the command
def _tune_args(tmp_path: Path, data: Path, *extra, room: str = "office", study: str = "s") -> list[str]:
    return ["tune", "--data", str(data), "--room", room, "--study", study, "--out", str(tmp_path / "study"),
            *[str(x) for x in extra]]


def test_study_on_a_tiny_room_resumes_from_its_journal_and_exports_the_best(tiny_office, tmp_path):
    cfg = tmp_path / "tiny.json"
    cfg.write_text(json.dumps(to_dict(tiny_train_config(max_steps=3))))
    args = _tune_args(tmp_path, tiny_office, "--trials", 2, "--max-steps", 3, "--config", cfg, "--parallel", 2)
    code, out, err = run_cli(args)
    assert code == 0, err
    journal = tmp_path / "study" / "optuna.journal"
    storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(journal)))
    first = optuna.load_study(study_name="s", storage=storage).trials
    assert [t.state.name for t in first] == ["COMPLETE"] * 2, out
    code, out, err = run_cli(args)  # the same command again adds two trials
    assert code == 0, err
    trials = optuna.load_study(study_name="s", storage=storage).trials
    assert [t.number for t in trials] == list(range(4)) and all(t.state.name == "COMPLETE" for t in trials)
    assert [t.params for t in trials[:2]] == [t.params for t in first]  # the first two untouched
    assert all(t.params != u.params for t in trials[2:] for u in first)  # new configurations
    for t in trials:
        run = tmp_path / "study" / "trials" / f"{t.number:04d}"
        assert (run / "metrics.json").is_file() and t.user_attrs["run"] == str(run)
        assert load_json_config(TrainConfig, run / "config.json").max_steps == 3
    assert (tmp_path / "study" / "trials.csv").read_text().count("COMPLETE") == 4
    best = tmp_path / "best.json"
    code, out, err = run_cli(_tune_args(tmp_path, tiny_office, "--trials", 0, "--export-config", best))
    assert code == 0, err
    winner = min(trials, key=lambda t: t.value)
    cfg_best = load_json_config(TrainConfig, best)  # what `train --config` reads
    assert cfg_best.virus_grid.update_interval == winner.params["virus_grid.update_interval"]
    assert cfg_best.weights.irs == winner.params["weights.irs"] and cfg_best.batch_size == 128
    code, _, err = run_cli(_tune_args(tmp_path, tiny_office, "--trials", 0, "--export-config", best))
    assert code == 2 and "already exists" in err  # never overwritten
    code, _, err = run_cli(_tune_args(tmp_path, tiny_office, "--trials", 1, "--max-steps", 4, "--config", cfg))
    assert code == 2 and "--max-steps" in err and "another base config" in err


@pytest.mark.parametrize("extra, names, fragment", [
    (("--trials", "-1"), {}, "--trials -1: expected an integer in [0, 1000000]"),
    (("--trials", "1", "--acc-weight", "2"), {}, "--acc-weight 2.0: expected a number in [0, 1]"),
    (("--trials", "1"), {"study": "a/b"}, "--study 'a/b': expected a name"),
    (("--trials", "1", "--max-steps", "0"), {}, "--max-steps 0: expected an integer >= 1"),
    (("--trials", "1", "--objective", "sum"), {}, "--objective"),
    (("--trials", "1"), {"room": "kitchen"}, "is not a room folder"),
    # a user's review: a trial trained, then a KeyError traceback, and the study folder left
    (("--trials", "1"), {}, "the recording has no LiDAR map (maps/map*.pcd), so no trial can be scored"),
])
def test_tune_errors_are_one_line(tmp_path, extra, names, fragment):
    (tmp_path / "d" / "office").mkdir(parents=True)
    code, _, err = run_cli(_tune_args(tmp_path, tmp_path / "d", *extra, **names))
    assert code == 2 and err.count("\n") == 1 and fragment in err, err
    assert not (tmp_path / "study").exists()


def test_ablation_rows_flag_is_checked(tmp_path):
    code, _, err = run_cli(["ablation", "--out", str(tmp_path / "abl"), "--rows", "2,10"])
    assert code == 2 and "--rows '2,10': '10' is not a row" in err, err
    assert not (tmp_path / "abl").exists()


def test_missing_extra_is_named(tmp_path, monkeypatch):
    (tmp_path / "d" / "office").mkdir(parents=True)
    monkeypatch.setitem(sys.modules, "optuna", None)  # import optuna -> ImportError
    code, _, err = run_cli(_tune_args(tmp_path, tmp_path / "d", "--trials", 1))
    assert code == 2 and "pip install -e '.[tune]' in the virus-nerf repository" in err and err.count("\n") == 1, err


def test_readme_shows_the_search_space():
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    assert ss.space_table() in readme


def _zone3_metrics(acc: float, cov: float) -> dict:
    keys = ("acc_mean", "acc_median", "acc_inlier", "acc_too_close", "acc_too_far", "cov_mean", "cov_median",
            "cov_inlier", "cov_too_close", "cov_too_far", "gt_unseen", "n_pred", "n_gt")
    zone = {k: {"acc_mean": acc, "cov_mean": cov, "n_pred": 10, "n_gt": 10}.get(k) for k in keys}
    empty = {k: (0 if k.startswith("n_") else None) for k in keys}
    return {"gt": "map", "zones": {"zone1": [0, 1], "zone2": [0, 2], "zone3": [0, 100]},
            "sensors": {"NeRF": {"zone1": empty, "zone2": empty, "zone3": zone}}, "train": {}}


def test_trials_left_running_by_a_dead_process_are_settled(tmp_path):
    import socket
    import subprocess

    from virus_nerf.experiments.study import open_study, settle_stale_trials, storage_for

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    study, _ = open_study("s", storage_for(None, tmp_path), Objective(), None, 0, "median", tmp_path, "office")
    for n, finished in enumerate((True, False)):
        trial = study.ask(ss.distributions())
        run = tmp_path / f"{n:04d}"
        if finished:
            run.mkdir()
            (run / "metrics.json").write_text(json.dumps(_zone3_metrics(0.2, 0.4)))
        for key, value in (("run", str(run)), ("host", socket.gethostname()), ("pid", int(dead))):
            trial.set_user_attr(key, value)
    live = study.ask(ss.distributions())  # this process's own trial stays running
    live.set_user_attr("host", socket.gethostname())
    live.set_user_attr("pid", os.getpid())
    assert settle_stale_trials(study, Objective()) == [0, 1]
    states = [t.state.name for t in study.trials]
    assert states == ["COMPLETE", "FAIL", "RUNNING"] and study.trials[0].value == pytest.approx(0.3)
    # the settled trial's row in trials.csv has its figures, as a trial told by run_trial has
    assert {k: study.trials[0].user_attrs.get(k) for k in ("acc_mean", "cov_mean")} == {"acc_mean": 0.2,
                                                                                      "cov_mean": 0.4}


def test_an_rdb_study_keeps_its_objective(tmp_path):
    from virus_nerf.errors import UsageError
    from virus_nerf.experiments.study import open_study, storage_for

    url = f"sqlite:///{tmp_path / 'studies.db'}"
    assert storage_for(url, tmp_path) == url
    study, base = open_study("s", url, Objective("multi"), None, 0, "none", tmp_path, "office")
    assert study.directions[1].name == "MINIMIZE" and base["optim"]["lr"] == TrainConfig().optim.lr
    with pytest.raises(UsageError, match="--objective weighted --acc-weight 0.5: study 's' optimises"):
        open_study("s", url, Objective("weighted"), None, 0, "none", tmp_path, "office")
    # continued on another recording, its trials would rank configurations on other data
    with pytest.raises(UsageError, match=f"--data {tmp_path / 'other'}: study 's' was started on --data {tmp_path}; "
                                         "give the same or a new --study"):
        open_study("s", url, Objective("multi"), None, 0, "none", tmp_path / "other", "office")
    with pytest.raises(UsageError, match="--room lab: study 's' was started on --room office"):
        open_study("s", url, Objective("multi"), None, 0, "none", tmp_path, "lab")


def test_a_study_folder_holds_one_study(tmp_path):
    (tmp_path / "d" / "office" / "maps").mkdir(parents=True)
    (tmp_path / "d" / "office" / "maps" / "map.pcd").write_text("not read: the folder is refused before")
    (tmp_path / "study").mkdir()
    (tmp_path / "study" / "study.json").write_text('{"study": "other"}')
    code, _, err = run_cli(_tune_args(tmp_path, tmp_path / "d", "--trials", 1))
    assert code == 2 and "holds the trials of study 'other'; give study 's' its own --out" in err, err
    assert sorted(p.name for p in (tmp_path / "study").iterdir()) == ["study.json"]
    # a folder of something else (notes, a training run) is not written in either
    (tmp_path / "study" / "study.json").unlink()
    (tmp_path / "study" / "notes.txt").write_text("mine")
    code, _, err = run_cli(_tune_args(tmp_path, tmp_path / "d", "--trials", 1))
    assert code == 2 and "exists and is not a study's folder (no study.json); give study 's' a new --out" in err, err
    assert sorted(p.name for p in (tmp_path / "study").iterdir()) == ["notes.txt"]


def test_a_run_whose_every_trial_failed_exits_1(tmp_path):
    """As ablation and online: a script sees that nothing was tuned (a room without measurements:
    its trial's training refuses it; the study and its table are kept)."""
    (tmp_path / "d" / "office" / "maps").mkdir(parents=True)
    (tmp_path / "d" / "office" / "maps" / "map.pcd").write_text("x")
    code, out, err = run_cli(_tune_args(tmp_path, tmp_path / "d", "--trials", 1, "--max-steps", 2))
    assert code == 1 and "trial 0: FAILED" in out, (out, err)
    assert (tmp_path / "study" / "trials.csv").is_file()
