"""`virus-nerf train` and `virus-nerf evaluate` (design 7)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Literal

from virus_nerf.utils.io import write_json_atomic


@dataclasses.dataclass
class RunInfo:
    """Where a run's data came from (run.json), so `evaluate --run` can find it again."""

    data: str
    room: str


def _resolve_config(
    config: Path | None,
    grid: str | None,
    sensors: str | None,
    max_time: float | None,
    max_steps: int | None,
    batch_size: int | None,
    seed: int | None,
    online: bool,
    odometry_poses: bool,
    playback_speed: float | None,
    image_scale: float | None,
    eval_interval: float | None,
):
    from virus_nerf.config_io import load_json_config
    from virus_nerf.trainer.config import TrainConfig

    cfg = load_json_config(TrainConfig, config) if config is not None else TrainConfig()
    overrides = {
        "grid": grid,
        "sensors": tuple(s.strip() for s in sensors.split(",")) if sensors else None,
        "max_steps": max_steps,
        "batch_size": batch_size,
        "seed": seed,
        "playback_speed": playback_speed,
        "image_scale": image_scale,
        "eval_interval": eval_interval,
    }
    changes = {k: v for k, v in overrides.items() if v is not None}
    if max_time is not None:
        changes["max_time"] = max_time
    elif max_steps is not None and config is None:
        changes["max_time"] = None  # --max-steps alone: a step-bounded, bit-reproducible run
    if online:
        changes["online"] = True
    if odometry_poses:
        changes["odometry_poses"] = True
    return dataclasses.replace(cfg, **changes)


def run_training(data: Path, room: str, out: Path, cfg, quiet: bool | None = None, resume: bool = False) -> dict:
    """Train, evaluate and write everything into the run folder; returns the metrics document."""
    from virus_nerf.config_io import to_dict
    from virus_nerf.data.ethz import load_recording
    from virus_nerf.trainer.loop import Trainer, write_run_metrics
    from virus_nerf.trainer.report import write_run_plots
    from virus_nerf.utils.io import create_new_dir
    from virus_nerf.utils.seeding import seed_everything

    seed_everything(cfg.seed)
    recording = load_recording(data, room, poses="odometry" if cfg.odometry_poses else "optimised")
    if resume:
        if not (out / "checkpoint.pt").is_file():
            raise FileNotFoundError(f"{out}: no checkpoint.pt to resume from")
    else:
        create_new_dir(out)
        write_json_atomic(out / "config.json", to_dict(cfg))
        write_json_atomic(out / "run.json", dataclasses.asdict(RunInfo(data=str(Path(data).resolve()), room=room)))
    trainer = Trainer(recording, cfg, out, quiet=quiet)
    if resume:
        trainer.load_checkpoint(out / "checkpoint.pt")
    summary = trainer.fit()
    if cfg.odometry_poses:
        # the map and test points are judged in the true (optimised) frame
        trainer.recording = load_recording(data, room, poses="optimised")
        trainer._gt = None
    result = trainer.evaluate(with_sensors=True)
    trainer.record_eval(result, None)  # the final point of the metric-vs-time curve
    doc = write_run_metrics(out, result, cfg, summary)
    write_run_plots(out, result, trainer.eval_history)
    print(result.table())
    print(
        f"trained {summary.steps} steps in {summary.seconds:.1f} s "
        f"({summary.steps_per_s:.2f} steps/s, {summary.samples_per_s / 1e6:.3f} M samples/s); "
        f"results in {out}"
    )
    return doc


def train(
    data: Path,
    room: str,
    out: Path,
    grid: Literal["virus", "ngp"] | None = None,
    sensors: str | None = None,
    max_time: float | None = None,
    max_steps: int | None = None,
    batch_size: int | None = None,
    seed: int | None = None,
    online: bool = False,
    odometry_poses: bool = False,
    playback_speed: float | None = None,
    image_scale: float | None = None,
    eval_interval: float | None = None,
    config: Path | None = None,
    resume: bool = False,
    quiet: bool = False,
) -> None:
    """Train a VIRUS-NeRF (or Instant-NGP) on a recording, then evaluate its 2D scans.

    Writes OUT/ (refused if it exists, unless --resume): config.json, run.json, train_log.csv,
    checkpoint.pt, metrics.json (design 7), metrics_vs_time.csv and plots/.

    Args:
        data: Dataset folder in the ETHZ format (holds camera_intrinsics.CSV and ROOM/).
        room: Room folder name inside DATA (e.g. office).
        out: New run folder.
        grid: Occupancy grid for ray marching: virus (Bayesian, default) or ngp (Instant-NGP).
        sensors: Comma-separated sensors to train on: camera,uss,irs,rgbd (default camera,uss,irs).
        max_time: Seconds of training (evaluation excluded); default 120 unless --max-steps is given.
        max_steps: Training steps; alone, it makes the run bit-reproducible on CPU.
        batch_size: Rays per step (default 2048).
        seed: Seed for everything random (default 0).
        online: Replay the recording by its timestamps (frames appear as the clock passes them).
        odometry_poses: Train on the odometry poses instead of the optimised ones.
        playback_speed: Online mode: recording seconds per training second.
        image_scale: Training image resolution relative to the recording (default 0.5).
        eval_interval: Seconds of training between NeRF-scan evaluations (0: only at the end).
        config: JSON config file (a run's config.json works); flags given here override it.
        resume: Continue the run in OUT from its checkpoint.
        quiet: No progress bar.
    """
    if resume:
        cfg_path = config or out / "config.json"
        info = json.loads((out / "run.json").read_text())
        cfg = _resolve_config(cfg_path, grid, sensors, max_time, max_steps, batch_size, seed, online,
                              odometry_poses, playback_speed, image_scale, eval_interval)
        run_training(Path(info["data"]), info["room"], out, cfg, quiet=quiet or None, resume=True)
        return
    cfg = _resolve_config(config, grid, sensors, max_time, max_steps, batch_size, seed, online, odometry_poses,
                          playback_speed, image_scale, eval_interval)
    run_training(data, room, out, cfg, quiet=True if quiet else None)


def evaluate(run: Path, out: Path | None = None, n_rays: int | None = None) -> None:
    """Evaluate a trained run's 2D scans against the map, beside the LiDAR, USS and IRS scans.

    Args:
        run: A run folder written by `virus-nerf train`.
        out: metrics.json to write (default RUN/evaluation/metrics.json; never overwritten).
        n_rays: Rays per 360 deg scan (default: the run's setting, 512).
    """
    from virus_nerf.config_io import load_json_config
    from virus_nerf.data.ethz import load_recording
    from virus_nerf.errors import OutputExistsError
    from virus_nerf.evaluation.command import plots_dir_for, write_plots
    from virus_nerf.trainer.config import TrainConfig
    from virus_nerf.trainer.loop import Trainer, TrainSummary, train_summary_block

    cfg = load_json_config(TrainConfig, run / "config.json")
    if n_rays is not None:
        cfg = dataclasses.replace(cfg, evaluation=dataclasses.replace(cfg.evaluation, n_rays=n_rays))
    info = json.loads((run / "run.json").read_text())
    out = out or run / "evaluation" / "metrics.json"
    if out.exists() or plots_dir_for(out).exists():
        raise OutputExistsError(out if out.exists() else plots_dir_for(out))
    recording = load_recording(info["data"], info["room"], poses="optimised")
    trainer = Trainer(recording, cfg, run, quiet=True)
    trainer.load_checkpoint(run / "checkpoint.pt")
    result = trainer.evaluate(with_sensors=True)
    summary = TrainSummary(trainer.step, trainer.seconds, trainer.samples)
    result.write_json(out, train=train_summary_block(cfg, summary))
    write_plots(result, plots_dir_for(out), max_maps=8)
    print(result.table())
    print(f"wrote {out} and {plots_dir_for(out)}/")
