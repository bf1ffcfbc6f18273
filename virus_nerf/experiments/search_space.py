"""The tuning search space (`virus-nerf tune`): every tuned knob and its range, in one place.

What the authors tuned (as listed in issue 14; the knobs: docs/method.md 3.2-3.4): the loss
weights of colour, IRS and USS, the learning rate, the Depth-Update's false-detection rate and range
noise, the NeRF-Update's threshold and slope, the grid's update interval, rays per update and
warm-up. Each `Param` names the TrainConfig key it sets (dotted, as in config.json), so a trial
is a config file `train --config` reads, and the best trial exports as one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Param:
    """One tuned knob: TrainConfig key (dotted), range [low, high], log scale, integer."""

    key: str
    low: float
    high: float
    log: bool = True
    integer: bool = False
    why: str = ""

    def __post_init__(self) -> None:
        if not (self.low < self.high and (self.low > 0 or not self.log)):
            raise ValueError(f"Param {self.key}: expected 0 < low < high on a log scale, got [{self.low}, {self.high}]")


# Ranges: about a decade around this package's earlier defaults (now configs/paper.json; the
# paper's values where they differ), inside what the config accepts (VirusGridConfig.__post_init__,
# TrainConfig checks). The current defaults are the best trial of docs/results/tune_office41;
# its false_rate (2.40 of at most 3) and std_per_m (0.0066 of at least 0.005) lie near the edges.
SEARCH_SPACE: tuple[Param, ...] = (
    Param("weights.colour", 0.25, 4.0, why="colour MSE weight (default 0.3189; earlier 1)"),
    Param("weights.irs", 0.05, 5.0, why="IRS depth loss weight, m^-2 (default 1.0379; earlier 0.5, the authors' 50 on ~10 m units)"),
    Param("weights.uss", 0.05, 5.0, why="one-sided USS loss weight, m^-2 (default 0.0505; earlier 0.5)"),
    Param("optim.lr", 1e-3, 3e-2, why="Adam learning rate (default 0.0094; earlier 1e-2; paper 5e-3 on a GPU)"),
    Param("virus_grid.false_rate", 0.03, 3.0, why="Depth-Update false detections per metre (default 2.4043; earlier 0.3)"),
    Param("virus_grid.std_per_m", 0.005, 0.15, why="Depth-Update range noise per metre of range (default 0.0066; earlier 0.03)"),
    Param("virus_grid.threshold_alpha", 1e-3, 0.3,
          why="NeRF-Update threshold: alpha of a threshold_step step at sigma_T_max (default 0.15; study 0.0438; earlier 0.01)"),
    Param("virus_grid.zeta", 0.05, 1.0, why="NeRF-Update slope (default 0.4196; earlier 0.25)"),
    Param("virus_grid.update_interval", 4, 64, integer=True, why="training steps between grid updates (default 21; earlier 16)"),
    Param("virus_grid.rays_per_update", 256, 4096, integer=True, why="rays per grid update (default 438; earlier 1024)"),
    Param("virus_grid.warmup_steps", 16, 2048, integer=True, why="grid warm-up in training steps (default 660; earlier 330 and 128; D70)"),
)


def distributions() -> dict[str, Any]:
    """Optuna distributions of the search space, by key (optuna imported here, lazily)."""
    import optuna

    out: dict[str, Any] = {}
    for p in SEARCH_SPACE:
        if p.integer:
            out[p.key] = optuna.distributions.IntDistribution(int(p.low), int(p.high), log=p.log)
        else:
            out[p.key] = optuna.distributions.FloatDistribution(p.low, p.high, log=p.log)
    return out


def apply_params(base: dict, params: dict[str, Any]) -> dict:
    """A copy of the config document `base` (to_dict of a TrainConfig) with each dotted key set."""
    import copy

    doc = copy.deepcopy(base)
    for key, value in params.items():
        node = doc
        *parents, leaf = key.split(".")
        for part in parents:
            node = node[part]
        if leaf not in node:
            raise KeyError(f"search space key {key!r} is not a TrainConfig key")
        node[leaf] = value
    return doc


def build_config(base: dict, params: dict[str, Any], where: str = "trial config"):
    """The TrainConfig of a trial (checked like any config file: a bad range is a ConfigError)."""
    from virus_nerf.config_io import from_dict
    from virus_nerf.trainer.config import TrainConfig

    return from_dict(TrainConfig, apply_params(base, params), file=where)


def space_table() -> str:
    """The search space as markdown (README, `tune --help` readers)."""
    lines = ["| key | range | scale | what |", "|---|---|---|---|"]
    for p in SEARCH_SPACE:
        rng = f"{int(p.low)}..{int(p.high)}" if p.integer else f"{p.low:g}..{p.high:g}"
        lines.append(f"| `{p.key}` | {rng} | {'log' if p.log else 'linear'}{', integer' if p.integer else ''} | {p.why} |")
    return "\n".join(lines)


def defaults_inside() -> list[str]:
    """Keys whose TrainConfig default lies outside its range (a test keeps this empty)."""
    from virus_nerf.config_io import to_dict
    from virus_nerf.trainer.config import TrainConfig

    doc = to_dict(TrainConfig())
    bad = []
    for p in SEARCH_SPACE:
        node: Any = doc
        for part in p.key.split("."):
            node = node[part]
        if not p.low <= node <= p.high:
            bad.append(p.key)
    return bad
