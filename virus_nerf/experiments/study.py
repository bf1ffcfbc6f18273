"""Optuna plumbing of `virus-nerf tune`: objective, storage, opening and checking a study, stale
trials, the trials table and the best trial as a config file. Optuna is imported lazily (the
[tune] extra); everything here is independent of how the trainings are executed.
"""

from __future__ import annotations

import json
import os
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from virus_nerf.experiments.search_space import build_config
from virus_nerf.trainer.run_folder import METRICS
from virus_nerf.utils.io import pid_alive

JOURNAL = "optuna.journal"  # default storage: a journal file in the study folder


@dataclass(frozen=True)
class Objective:
    """Zone-3 NeRF accuracy and coverage means (m, lower is better): their weighted sum
    acc_weight * acc + (1 - acc_weight) * cov ("weighted", prunable), or both ("multi", a
    Pareto front; Optuna cannot prune multi-objective trials)."""

    mode: str = "weighted"
    acc_weight: float = 0.5

    @property
    def directions(self) -> list[str]:
        return ["minimize"] if self.mode == "weighted" else ["minimize", "minimize"]

    def weighted(self, acc: float | None, cov: float | None) -> float | None:
        if acc is None or cov is None:
            return None
        return self.acc_weight * acc + (1.0 - self.acc_weight) * cov

    def values(self, acc: float | None, cov: float | None) -> list[float] | None:
        """What the study is told for a finished run (None: the NeRF gave no scan points)."""
        if acc is None or cov is None:
            return None
        return [self.weighted(acc, cov)] if self.mode == "weighted" else [acc, cov]

    def as_dict(self) -> dict:
        return {"mode": self.mode, "acc_weight": self.acc_weight}


def storage_for(url: str | None, study_dir: Path):
    """--storage -> an Optuna storage: None (the journal file STUDY_DIR/optuna.journal), a path or
    journal:PATH (a journal file: resumable, one machine or a shared disk), or an RDB URL
    (sqlite:///..., postgresql://..., mysql://...: many machines at once)."""
    import optuna

    from virus_nerf.errors import UsageError, one_line

    if url is not None and "://" in url:
        return url  # optuna builds its RDBStorage from the URL (opened, and checked, by open_study)
    path = Path(url.removeprefix("journal:")) if url else study_dir / JOURNAL
    if path.is_dir():
        raise UsageError(f"--storage {url or path}: is a folder; expected a journal file (a path) or an RDB URL")
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        return optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(path)))
    except Exception as exc:  # a damaged journal: its log is replayed on opening
        raise UsageError(f"--storage {path}: not a readable Optuna journal ({type(exc).__name__}: "
                         f"{one_line(exc, 160)}); expected a journal file this tool wrote (or a new path)") from None


def open_study(name: str, storage, objective: Objective, base: dict | None, seed: int, pruner: str,
               data: Path, room: str):
    """Create or load study `name`; returns (study, the base config document it tunes).

    A new study records its objective and base config (budget included) in its user attrs; a
    loaded one must match what is asked now (else a UsageError naming the flag); `base` None
    takes the stored one. The sampler is seeded with seed + the number of trials so far, so a
    resumed study proposes new configurations, the same ones for the same history.
    """
    import optuna

    from virus_nerf.errors import UsageError, one_line

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        study = optuna.create_study(study_name=name, storage=storage, load_if_exists=True,
                                    directions=objective.directions, pruner=_pruner(pruner))
    except ValueError as exc:  # e.g. a loaded study with other directions
        raise UsageError(f"--objective {objective.mode}: study {name!r} cannot be opened so ({exc})") from None
    except Exception as exc:  # a storage that cannot be opened or read: SQLAlchemy, journal and decoding errors
        where = storage if isinstance(storage, str) else "the journal file"
        raise UsageError(f"--storage {where}: cannot open study {name!r} there ({type(exc).__name__}: "
                         f"{one_line(exc, 160)}); expected a journal file this tool wrote, or an RDB URL "
                         "such as sqlite:///study.db whose database can be created or opened") from None
    attrs = study.user_attrs
    if "objective" in attrs:
        if attrs["objective"] != objective.as_dict():
            raise UsageError(f"--objective {objective.mode} --acc-weight {objective.acc_weight:g}: study {name!r} "
                             f"optimises {attrs['objective']}; give the same or a new --study")
        stored = attrs["base_config"]
        if base is not None and _canon(base) != _canon(stored):
            raise UsageError(f"--config/--max-steps/--max-time/--eval-interval: study {name!r} was started with "
                             "another base config or budget; give the same (or none, to reuse the study's) "
                             "or a new --study")
        for key, flag, value in (("data", "--data", str(data)), ("room", "--room", room)):
            if attrs.get(key, value) != value:  # its trials would rank configurations on other recordings
                raise UsageError(f"{flag} {value}: study {name!r} was started on {flag} {attrs[key]}; give the same "
                                 "or a new --study")
        from virus_nerf.config_io import with_added_keys

        base = with_added_keys(stored)  # a study started by an earlier version runs on as it began
    else:
        if base is None:
            from virus_nerf.config_io import to_dict
            from virus_nerf.trainer.config import TrainConfig

            base = to_dict(TrainConfig())
        study.set_user_attr("objective", objective.as_dict())
        study.set_user_attr("base_config", base)
        study.set_user_attr("data", str(data))
        study.set_user_attr("room", room)
    study.sampler = optuna.samplers.TPESampler(seed=seed + len(study.trials))
    return study, base


def _canon(doc: dict) -> str:
    return json.dumps(doc, sort_keys=True)


def _pruner(name: str):
    import optuna

    if name == "none":
        return optuna.pruners.NopPruner()
    # prune a trial whose curve is worse than the median of earlier trials at the same evaluation,
    # once 3 trials have finished and from its second evaluation on
    return optuna.pruners.MedianPruner(n_startup_trials=3, n_warmup_steps=1)


def settle_stale_trials(study, objective: Objective) -> list[int]:
    """Trials left RUNNING by a tune process of this host that has died: a finished run is told
    its value, any other one FAIL. Trials of other hosts or live processes are left alone."""
    import optuna

    from virus_nerf.evaluation.metrics import read_metrics
    from virus_nerf.experiments.runs import run_done

    host, settled = socket.gethostname(), []
    for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,)):
        pid = t.user_attrs.get("pid")
        if t.user_attrs.get("host") != host or not isinstance(pid, int) or pid == os.getpid() or pid_alive(pid):
            continue
        run = Path(t.user_attrs.get("run", ""))
        values = None
        if run_done(run):
            zone = read_metrics(run / METRICS).sensors()["NeRF"].zones["zone3"]
            values = objective.values(zone.acc_mean, zone.cov_mean)
            trial = optuna.trial.Trial(study, t._trial_id)  # the trial as run_trial would have left it
            trial.set_user_attr("acc_mean", zone.acc_mean)
            trial.set_user_attr("cov_mean", zone.cov_mean)
        if values is None:
            study.tell(t.number, state=optuna.trial.TrialState.FAIL)
        else:
            study.tell(t.number, values)
        settled.append(t.number)
    return settled


def best_trial(study, objective: Objective):
    """The best finished trial: the lowest value, or (multi) the Pareto trial with the lowest
    weighted sum; None when no trial has finished."""
    import optuna

    done = study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
    if not done:
        return None
    if objective.mode == "weighted":
        return study.best_trial
    return min(study.best_trials, key=lambda t: objective.weighted(*t.values))


def export_config(study, objective: Objective, base: dict, path: Path) -> Any:
    """Write the best trial as a config file `train --config` accepts (the base config, its
    budget included, with the trial's parameters); never overwrites. Returns the trial."""
    from virus_nerf.config_io import to_dict
    from virus_nerf.errors import OutputExistsError, UsageError
    from virus_nerf.utils.io import write_json_atomic

    if Path(path).exists():
        raise OutputExistsError(path, "--export-config")
    trial = best_trial(study, objective)
    if trial is None:
        raise UsageError(f"--export-config {path}: study {study.study_name!r} has no finished trial yet")
    cfg = build_config(base, trial.params, where=f"trial {trial.number}")
    write_json_atomic(Path(path), to_dict(cfg))
    return trial


def trials_table(study) -> str:
    """CSV of every trial: number, state, values, zone-3 metrics, run folder, parameters."""
    import csv
    import io

    from virus_nerf.experiments.search_space import SEARCH_SPACE

    keys = [p.key for p in SEARCH_SPACE]
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["number", "state", "values", "acc_mean", "cov_mean", "attempts", "run", *keys])
    for t in study.get_trials(deepcopy=False):
        a = t.user_attrs
        w.writerow([t.number, t.state.name, "" if t.values is None else " ".join(f"{v:.6g}" for v in t.values),
                    a.get("acc_mean", ""), a.get("cov_mean", ""), a.get("attempts", ""), a.get("run", ""),
                    *[t.params.get(k, "") for k in keys]])
    return buf.getvalue()
