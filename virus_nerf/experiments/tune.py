"""`virus-nerf tune`: an Optuna study over the knobs the authors tuned (search_space.py).

Each trial is one `virus-nerf train --config STUDY/trials/NNNN.json` process into the run folder
STUDY/trials/NNNN/, executed locally or on a Dask cluster (executors.py); its zone-3 accuracy
and coverage (metrics.json) are the objective. While it runs, its metrics_vs_time.csv is read and
each evaluation reported to Optuna; a trial the pruner stops is terminated (its stop file), its
run folder kept and the trial marked PRUNED. A trial whose training dies is retried once, then
marked FAIL; the study goes on. The study lives in its storage (a journal file by default), so
the same command again adds trials to it, and with an RDB URL many machines can run it at once.
"""

from __future__ import annotations

import os
import shutil
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from virus_nerf.experiments.study import Objective
from virus_nerf.trainer.run_folder import METRICS


@dataclass
class _Context:
    study: object
    executor: object
    objective: Objective
    base: dict
    data: Path
    room: str
    trials_dir: Path
    eval_interval: float
    prune: bool
    poll_s: float = 1.0
    # one trial asked at a time: the seeded sampler's draws then go to the trials in number order
    # (threads asking at once interleaved them: parallel studies were not reproducible)
    ask_lock: threading.Lock = field(default_factory=threading.Lock)
    # set when the command stops (Ctrl-C, SIGTERM): each trial stops its training and asks no more
    stopping: threading.Event = field(default_factory=threading.Event)


def _eval_index(point, eval_interval: float) -> int:
    """The Optuna step of an evaluation: its index on the eval_interval grid of the training
    clock (so trials of different speeds are compared at the same training time)."""
    return int(round(point.seconds / eval_interval)) if eval_interval > 0 else int(point.step)


def _report(trial, ctx: _Context, run: Path, reported: set[int]) -> bool:
    """Report the run's new evaluations; True when the pruner says stop."""
    from virus_nerf.errors import DataFormatError
    from virus_nerf.trainer.run_folder import METRICS_VS_TIME, read_eval_history

    try:
        points = read_eval_history(run / METRICS_VS_TIME)
    except (DataFormatError, OSError):  # written atomically, but a foreign file must not kill the study
        return False
    max_steps, max_time = ctx.base.get("max_steps"), ctx.base.get("max_time")
    new = False
    for p in points:
        step = _eval_index(p, ctx.eval_interval)
        value = ctx.objective.weighted(p.acc_mean, p.cov_mean)
        # the final evaluation (budget reached) is the objective itself: stopping the run while it
        # writes its metrics would throw a finished trial away
        final = (max_steps is not None and p.step >= max_steps) or (max_time is not None and p.seconds >= max_time)
        if step in reported or value is None or final:
            continue
        trial.report(value, step)
        reported.add(step)
        new = True
    return new and trial.should_prune()


def run_trial(ctx: _Context) -> str:
    """Ask for a trial, train it, tell its outcome; returns a one-line summary."""
    import optuna

    from virus_nerf.config_io import to_dict
    from virus_nerf.evaluation.metrics import read_metrics
    from virus_nerf.experiments.runs import STOPPED_WITH_CALLER, RunSpec, log_file, request_stop
    from virus_nerf.experiments.search_space import build_config, distributions
    from virus_nerf.utils.io import write_json_atomic

    study = ctx.study
    with ctx.ask_lock:
        trial = study.ask(distributions())
    n = trial.number
    run = ctx.trials_dir / f"{n:04d}"
    future = None
    try:
        import os
        import socket

        for key, value in (("run", str(run)), ("host", socket.gethostname()), ("pid", os.getpid())):
            trial.set_user_attr(key, value)
        ctx.trials_dir.mkdir(parents=True, exist_ok=True)
        cfg_path = ctx.trials_dir / f"{n:04d}.json"
        if cfg_path.exists() or run.exists():  # a fresh trial number: never take over a foreign run
            study.tell(trial, state=optuna.trial.TrialState.FAIL)
            return f"trial {n}: FAILED ({run} exists already, not from this trial; not reused)"
        write_json_atomic(cfg_path, to_dict(build_config(ctx.base, trial.params, where=str(cfg_path))))
        spec = RunSpec(name=f"trial {n}", data=ctx.data, room=ctx.room, out=run, args=("--config", str(cfg_path)))
        future = ctx.executor.submit(spec)
        reported: set[int] = set()
        pruned = stopped = False
        while not future.done():
            time.sleep(ctx.poll_s)
            if ctx.stopping.is_set() and not stopped:  # the training ends its step, keeps its checkpoint
                request_stop(run, STOPPED_WITH_CALLER)
                stopped = True
            if ctx.prune and not pruned and not stopped and _report(trial, ctx, run, reported):
                request_stop(run, f"pruned by the study at evaluation {max(reported)}")
                pruned = True
        if stopped:
            study.tell(trial, state=optuna.trial.TrialState.FAIL)
            return f"trial {n}: stopped with the command (run kept in {run})"
        try:
            result = future.result()
        except Exception as exc:  # the task broke (lost worker, unreadable shared folder)
            study.tell(trial, state=optuna.trial.TrialState.FAIL)
            return f"trial {n}: FAILED ({type(exc).__name__}: {exc})"
        trial.set_user_attr("attempts", result.attempts)
        if pruned or result.stopped:
            study.tell(trial, state=optuna.trial.TrialState.PRUNED)
            return f"trial {n}: pruned at evaluation {max(reported, default=0)} (run kept in {run})"
        if not result.ok:
            study.tell(trial, state=optuna.trial.TrialState.FAIL)
            return (f"trial {n}: FAILED after {result.attempts} attempt(s) (exit {result.returncode}, "
                    f"see {log_file(run)})")
        zone = read_metrics(run / METRICS).sensors()["NeRF"].zones["zone3"]
        values = ctx.objective.values(zone.acc_mean, zone.cov_mean)
        trial.set_user_attr("acc_mean", zone.acc_mean)
        trial.set_user_attr("cov_mean", zone.cov_mean)
        if values is None:
            study.tell(trial, state=optuna.trial.TrialState.FAIL)
            return f"trial {n}: FAILED (the NeRF returned no zone-3 scan points)"
        study.tell(trial, values)
        return (f"trial {n}: {' '.join(f'{v:.4f}' for v in values)} (acc {zone.acc_mean:.3f} m, "
                f"cov {zone.cov_mean:.3f} m) in {result.seconds:.0f} s")
    except BaseException:
        study.tell(trial, state=optuna.trial.TrialState.FAIL, skip_if_finished=True)
        if future is not None and not future.done():  # a training on a Dask worker would run on
            request_stop(run, STOPPED_WITH_CALLER)
            future.cancel()
        raise


STOP_WAIT_S = 60.0  # how long a stopped tune waits for its trials' trainings to end their step


def run_trials(ctx: _Context, n_trials: int, parallel: int) -> None:
    """`n_trials` trials, `parallel` at a time (each a thread asking, waiting and telling)."""
    lock = threading.Lock()
    left = [n_trials]
    errors: list[BaseException] = []

    def worker(finished: threading.Event) -> None:
        try:
            while True:
                with lock:
                    if left[0] <= 0 or errors or ctx.stopping.is_set():
                        return
                    left[0] -= 1
                try:
                    print("  " + run_trial(ctx), flush=True)
                except BaseException as exc:  # a bug or a storage error: stop asking, re-raise below
                    errors.append(exc)
                    return
        finally:
            finished.set()

    # Events, not Thread.join: a join that a signal interrupted may return early when called again
    finished = [threading.Event() for _ in range(max(1, min(parallel, n_trials)))]
    for event in finished:
        threading.Thread(target=worker, args=(event,), daemon=True).start()
    try:
        for event in finished:
            while not event.wait(0.5):
                pass
    except BaseException:  # Ctrl-C, SIGTERM: the trials stop their trainings (wherever they run) first
        ctx.stopping.set()
        deadline = time.monotonic() + STOP_WAIT_S
        for event in finished:
            event.wait(max(0.0, deadline - time.monotonic()))
        raise
    if errors:
        raise errors[0]


def _base_config(config: Path | None, max_steps: int | None, max_time: float | None,
                 eval_interval: float | None) -> dict | None:
    """The config every trial starts from (None: nothing asked, reuse the study's)."""
    import dataclasses

    from virus_nerf.config_io import to_dict
    from virus_nerf.errors import UsageError, one_line
    from virus_nerf.trainer.config import TrainConfig
    from virus_nerf.trainer.run_folder import load_config_file

    if config is None and max_steps is None and max_time is None and eval_interval is None:
        return None
    cfg = load_config_file(config) if config is not None else TrainConfig()
    changes: dict = {}
    if max_steps is not None:
        changes["max_steps"] = max_steps
        changes["max_time"] = max_time  # --max-steps without --max-time: a step budget alone
    elif max_time is not None:
        changes["max_time"] = max_time
    budget = changes.get("max_time", cfg.max_time)
    if eval_interval is not None:
        changes["eval_interval"] = eval_interval
    elif cfg.eval_interval == 0 and budget:
        changes["eval_interval"] = budget / 4  # three evaluations during the run to prune on
    try:
        return to_dict(dataclasses.replace(cfg, **changes))
    except ValueError as exc:
        raise UsageError(f"{config or 'flags'}: {one_line(exc)}") from None


def _claim_folder(out: Path, study: str) -> None:
    """OUT/study.json names the one study whose trials live in OUT: trial numbers restart in
    every study, so a second study in the same folder would find the first one's finished runs
    under its own trial numbers (and take their results)."""
    import json

    from virus_nerf.errors import UsageError
    from virus_nerf.utils.io import write_json_atomic

    marker = out / "study.json"
    if marker.is_file():
        owner = json.loads(marker.read_text()).get("study")
        if owner != study:
            raise UsageError(f"--out {out}: holds the trials of study {owner!r}; give study {study!r} its own --out")
    elif (out / "trials").exists():
        raise UsageError(f"--out {out}: holds trials/ of an unnamed study; give study {study!r} its own --out")
    elif out.is_dir() and any(out.iterdir()):  # notes, a training run, another experiment: not ours to write in
        raise UsageError(f"--out {out}: exists and is not a study's folder (no study.json); give study {study!r} "
                         "a new --out (nothing was written)")
    elif out.exists() and not out.is_dir():
        raise UsageError(f"--out {out}: is a file; expected a study's folder (a new one or the study's own)")
    else:
        write_json_atomic(marker, {"study": study})


@contextmanager
def _removed_unless_a_trial_ran(out: Path) -> Iterator[None]:
    """An --out this call makes is removed again when the call fails before any trial ran (a
    storage that cannot be opened, a best config to export with no finished trial): nothing is lost."""
    made = not os.path.lexists(out)
    try:
        yield
    except BaseException:
        if made and out.is_dir() and not (out / "trials").exists():
            shutil.rmtree(out, ignore_errors=True)
        raise


def tune(
    data: Path,
    room: str,
    study: str,
    trials: int,
    storage: str | None = None,
    out: Path | None = None,
    max_time: float | None = None,
    max_steps: int | None = None,
    eval_interval: float | None = None,
    objective: Literal["weighted", "multi"] = "weighted",
    acc_weight: float = 0.5,
    pruner: Literal["median", "none"] = "median",
    config: Path | None = None,
    seed: int = 0,
    parallel: int | None = None,
    scheduler: str | None = None,
    threads_per_run: int | None = None,
    export_config: Path | None = None,
) -> None:
    """Tune VIRUS-NeRF's loss weights, learning rate and grid parameters with Optuna (needs the
    [tune] extra: pip install -e '.[tune]').

    Runs --trials more trials of study --study (created, or continued: the same command again
    adds trials) and prints the best; each trial trains in its own process into OUT/trials/NNNN/.

    Args:
        data: Dataset folder in the ETHZ format (holds camera_intrinsics.CSV and ROOM/).
        room: Room folder name inside DATA.
        study: Study name (in the storage).
        trials: Trials to run in this call (0: only report and --export-config).
        storage: Journal file (a path or journal:PATH; default OUT/optuna.journal) or an RDB URL
            (sqlite:///study.db, postgresql://...) for many machines at once.
        out: Study folder holding trials/ and trials.csv (default studies/STUDY); with --scheduler
            on other machines it must be on a shared file system, like --data.
        max_time: Seconds of training per trial (default: the config's, 120).
        max_steps: Training steps per trial (alone: a step budget, reproducible trainings).
        eval_interval: Seconds of training between the evaluations pruning reads (default: a
            quarter of --max-time; 0: only the final one, no pruning).
        objective: weighted (acc_weight * acc + (1 - acc_weight) * cov of zone 3, prunable) or
            multi (both, Optuna's multi-objective mode; no pruning).
        acc_weight: Weight of the accuracy in the weighted objective, in [0, 1] (default 0.5).
        pruner: median (stop a trial worse than the median of earlier ones at the same
            evaluation) or none.
        config: JSON config every trial starts from (default: the built-in defaults).
        seed: Seed of the sampler (trial configurations are deterministic given the study).
        parallel: Trials at a time (default 1; with --scheduler the cluster's worker count).
        scheduler: Dask scheduler address (tcp://HOST:8786) or 'local' to run the trials on
            (needs the [dask] extra); default: local processes.
        threads_per_run: Threads of each training (default: cores / parallel locally, 1 on Dask).
        export_config: Write the best trial as a config file for `train --config` (never overwritten).
    """
    from virus_nerf.errors import (
        OutputExistsError,
        UsageError,
        is_plain_name,
        require_int,
        require_number,
        require_room_name,
    )
    from virus_nerf.experiments.executors import require_extra
    from virus_nerf.utils.io import require_makeable

    require_int("--trials", trials, 0, 1_000_000)
    require_number("--acc-weight", acc_weight, 0.0, 1.0, lo_open=False)
    require_int("--seed", seed, 0, 2**31 - 1)
    for flag, value in (("--max-steps", max_steps), ("--parallel", parallel), ("--threads-per-run", threads_per_run)):
        if value is not None:
            require_int(flag, value, 1)
    if max_time is not None:
        require_number("--max-time", max_time, 0.0)
    if eval_interval is not None:
        require_number("--eval-interval", eval_interval, 0.0, lo_open=False)
    if not is_plain_name(study):
        raise UsageError(f"--study {study!r}: expected a name (no slashes)")
    require_room_name(room)
    if not (Path(data) / room).is_dir():
        raise UsageError(f"--data {data} --room {room}: {Path(data) / room} is not a room folder")
    if export_config is not None and Path(export_config).exists():
        raise OutputExistsError(export_config, "--export-config")
    require_extra("optuna", "tune", "virus-nerf tune")
    if not any((Path(data) / room / "maps").glob("map*.pcd")):
        raise UsageError(f"--data {data} --room {room}: the recording has no LiDAR map (maps/map*.pcd), so no trial "
                         "can be scored; tune needs a recording with one")
    base = _base_config(config, max_steps, max_time, eval_interval)
    out = Path(out if out is not None else Path("studies") / study).absolute()
    require_makeable("--out", out)
    if export_config is not None:
        require_makeable("--export-config", export_config, Path(export_config).parent)
    from virus_nerf.experiments import study as studies
    from virus_nerf.experiments.executors import DaskExecutor, LocalExecutor, check_scheduler
    from virus_nerf.utils.io import write_text_atomic

    check_scheduler(scheduler)  # the extra and a scheduler that answers, before the study is opened
    with _removed_unless_a_trial_ran(out):
        _claim_folder(out, study)
        obj = Objective(objective, acc_weight)
        handle, base = studies.open_study(study, studies.storage_for(storage, out), obj, base, seed, pruner,
                                          Path(data).absolute(), room)
        settled = studies.settle_stale_trials(handle, obj)
        before = len(handle.trials)
        if settled:
            print(f"settled trial(s) {settled} left running by a tune process that died")
        if trials:
            executor = (LocalExecutor(parallel or 1, threads_per_run) if scheduler is None
                        else DaskExecutor(scheduler, parallel or 2, threads_per_run))
            with executor:
                n_parallel = parallel or (1 if scheduler is None else max(1, executor.n_workers))
                print(f"study {study!r}: {len(handle.trials)} trial(s) so far; running {trials} more, "
                      f"{n_parallel} at a time on {executor.describe()}", flush=True)
                (out / "trials").mkdir(parents=True, exist_ok=True)
                ctx = _Context(handle, executor, obj, base, Path(data).absolute(), room, out / "trials",
                               float(base.get("eval_interval") or 0.0),
                               prune=obj.mode == "weighted" and pruner != "none" and bool(base.get("eval_interval")))
                run_trials(ctx, trials, n_parallel)
        out.mkdir(parents=True, exist_ok=True)
        write_text_atomic(out / "trials.csv", studies.trials_table(handle))  # derived from the storage, rewritten
        best = studies.best_trial(handle, obj)
        states = [t.state.name for t in handle.trials]
        counts = ", ".join(f"{states.count(s)} {s.lower()}" for s in sorted(set(states)))
        print(f"study {study!r}: {len(states)} trial(s) ({counts}); table in {out / 'trials.csv'}" if states
              else f"study {study!r}: no trials yet (run more with --trials N); empty table in {out / 'trials.csv'}")
        if best is not None:
            print(f"best: trial {best.number}, values {best.values}, params {best.params}")
        if export_config is not None:
            trial = studies.export_config(handle, obj, base, Path(export_config))
            print(f"wrote trial {trial.number}'s config to {export_config} (use: virus-nerf train --config {export_config})")
    ran = handle.trials[before:]
    if ran and all(t.state.name == "FAIL" for t in ran):  # as ablation and online: a script sees it (exit 1)
        raise SystemExit(f"all {len(ran)} trial(s) of this run failed (each trial's log lies in {out / 'trials'})")
