"""`virus-nerf demo`: the main job on an embedded default (docs/method.md 1, issue 'main job').

Simulate an office (fixed seed), train VIRUS-NeRF (the default sensors, VIRUS grid) on a CPU
time budget, evaluate it beside the instantaneous LiDAR, USS and IRS scans, write a report.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

from virus_nerf.trainer.run_folder import METRICS, PLOTS

SENSOR_WORDS = {"camera": "the cameras' colour", "stereo": "their triangulated depth", "rgbd": "depth images",
                "uss": "USS", "irs": "IRS"}


def sensor_words(sensors) -> str:
    """('camera', 'uss', 'irs', 'stereo') -> "the cameras' colour, their triangulated depth, USS and IRS"."""
    order = [k for k in SENSOR_WORDS if k in sensors] + [k for k in sensors if k not in SENSOR_WORDS]
    words = [SENSOR_WORDS.get(k, k) for k in order]
    return words[0] if len(words) == 1 else ", ".join(words[:-1]) + " and " + words[-1]


def demo(
    out: Path = Path("demo-output"),
    seed: int = 0,
    duration: float = 40.0,
    train_time: float = 180.0,
    quiet: bool = False,
    gt: str = "map",
    resume: bool = False,
) -> None:
    """Simulate an office, train VIRUS-NeRF on it, evaluate, and write OUT/report.md.

    A demo stopped part-way (Ctrl-C, SIGTERM, a kill) is finished with `--resume --out OUT`: the
    simulation is made if it is missing, the training continues from its checkpoint, then the
    report is written, all with the settings the demo was begun with (OUT/demo.json).

    Args:
        out: New folder for everything (refused if it exists; with --resume the stopped demo's).
        seed: Seed of the simulated room, the drive and the training.
        duration: Seconds of simulated robot drive, in (0, 3600].
        train_time: Seconds of training (the CPU budget; evaluation excluded), > 0.
        quiet: No progress bars.
        gt: Ground truth, one or more of map (default), exact, paper, comma-separated; a table
            per protocol in the report, the first one's in the plots and metrics.json's own.
        resume: Finish the stopped demo in --out (the other flags are its own: not needed).
    """
    from virus_nerf.errors import require_int, require_number
    from virus_nerf.evaluation.config import parse_gt_flag
    from virus_nerf.evaluation.metrics import RunMetrics
    from virus_nerf.experiments.report import metrics_markdown_by_gt, safety_markdown
    from virus_nerf.sim.command import simulate
    from virus_nerf.trainer.config import TrainConfig
    from virus_nerf.trainer.run import run_training
    from virus_nerf.utils.io import (
        copy_file_atomic,
        create_new_dir,
        require_new_folder,
        write_json_atomic,
        write_text_atomic,
    )
    from virus_nerf.utils.stop import Stopped

    require_int("--seed", seed, 0, 2**32 - 1)
    require_number("--duration", duration, 0.0, 3600.0)
    require_number("--train-time", train_time, 0.0)
    parse_gt_flag(gt, scores=True)
    out = Path(out)
    settings = {"seed": seed, "duration": duration, "train_time": train_time, "gt": gt}
    if resume:
        settings = _stopped_demo(out, settings)
        seed, duration, train_time, gt = (settings[k] for k in ("seed", "duration", "train_time", "gt"))
    else:
        require_new_folder("--out", out)  # not there yet, and makeable (a file above it, a read-only place)
    protocols = parse_gt_flag(gt, scores=True)
    t_start = time.perf_counter()
    if not resume:
        create_new_dir(out)
        write_json_atomic(out / SETTINGS, settings)
    data = out / "data"
    base = TrainConfig()
    cfg = dataclasses.replace(
        base, seed=seed, max_time=train_time, image_scale=1.0, eval_interval=max(10.0, train_time / 8),
        evaluation=dataclasses.replace(base.evaluation, gt=protocols),
    )
    try:
        if not (data / "office").is_dir():
            print(f"[1/3] simulating a {duration:.0f} s drive through an office (seed {seed}) -> {data}")
            simulate(scene="office", out=data, seed=seed, duration=duration, resolution_scale=0.5)
        t_sim = time.perf_counter() - t_start
        run = out / "run"
        if (run / METRICS).is_file():  # trained and scored before the stop
            doc = json.loads((run / METRICS).read_text())
        elif resume and run.is_dir():
            print(f"[2/3] training VIRUS-NeRF on from its checkpoint, to {train_time:.0f} s of training")
            doc = run_training(data, "office", run, cfg, quiet=True if quiet else None, resume=True)
        else:
            print(f"[2/3] training VIRUS-NeRF ({sensor_words(cfg.sensors)}; VIRUS grid) for {train_time:.0f} s")
            doc = run_training(data, "office", run, cfg, quiet=True if quiet else None)
    except Stopped:
        print(f"demo: stopped; `virus-nerf demo --resume --out {out}` finishes it (trains on, writes the report)")
        raise
    print("[3/3] writing the report")
    copy_file_atomic(out / "run" / METRICS, out / METRICS)
    train = doc["train"]
    run_metrics = RunMetrics.from_document(doc)
    plots = sorted(p.name for p in (out / "run" / PLOTS).glob("*.png"))
    maps = [p for p in plots if p.startswith("scan_")]
    lines = [
        "# VIRUS-NeRF demo",
        "",
        f"Simulated office (seed {seed}, {duration:.0f} s drive), VIRUS-NeRF trained on {sensor_words(train['sensors'])} "
        f"with the Bayesian VIRUS occupancy grid for {train['seconds']:.0f} s of training{on_device(train)}: "
        f"{train['steps']} steps, {train['steps_per_s']:.2f} steps/s, {train['samples_per_s'] / 1e6:.3f} M samples/s.",
        "",
        "## 2D scan metrics (nearest-neighbour distances in metres, shares in [0, 1])",
        "",
        "Accuracy: distance from each scan point to the nearest ground-truth point; coverage: from each",
        f"ground-truth point (inside the sensor's field of view) to the nearest scan point. Inliers: < {run_metrics.inlier_m:g} m.",
        "",
        metrics_markdown_by_gt(run_metrics),
        "",
        *safety_markdown(doc, "run/plots/map_safety.png" if "map_safety.png" in plots else None),
        f"## Metrics per sensor and zone (paper Fig. 3; ground truth: {protocols[0]})",
        "",
        "![metric bars](run/plots/metrics_bars.png)",
        "",
        *[f"![metric bars, ground truth {p}](run/plots/metrics_bars_gt-{p}.png)\n" for p in protocols[1:]],
        f"## Accuracy vs training time (paper Fig. 6; ground truth: {protocols[0]})",
        "",
        "![accuracy vs time](run/plots/metric_vs_time.png)" if "metric_vs_time.png" in plots else "(no intermediate evaluations)",
        "",
        "## Scans at the test points (paper Fig. 4/5)",
        "",
    ]
    lines += [f"![{m}](run/plots/{m})" for m in maps[:6]]
    lines += [
        "",
        f"Total time {time.perf_counter() - t_start:.0f} s (simulation {t_sim:.0f} s). "
        "Files: `metrics.json`, `run/` (config, logs, checkpoint, plots), `data/` (the simulated recording).",
    ]
    write_text_atomic(out / "report.md", "\n".join(lines) + "\n")
    print(f"done in {time.perf_counter() - t_start:.0f} s: {out / 'report.md'}")


SETTINGS = "demo.json"  # the demo's flags, for --resume


def _stopped_demo(out: Path, given: dict) -> dict:
    """--resume: the settings of the stopped demo in OUT; a one-line UsageError for a folder that
    is not one, a finished demo, or a flag that asks for other settings."""
    from virus_nerf.errors import UsageError

    if not (out / SETTINGS).is_file():
        raise UsageError(f"--resume --out {out}: not a stopped demo (no {SETTINGS}); expected the --out of a demo "
                         "that was stopped")
    if (out / "report.md").exists():
        raise UsageError(f"--resume --out {out}: this demo is finished ({out / 'report.md'}); nothing to resume")
    import inspect

    begun = json.loads((out / SETTINGS).read_text())
    defaults = inspect.signature(demo).parameters  # a flag left at its default asks for nothing
    for key, value in given.items():
        if value != defaults[key].default and value != begun.get(key):
            flag = "--" + key.replace("_", "-")
            raise UsageError(f"{flag} {value}: --resume finishes the demo as it was begun ({flag} {begun.get(key)}, "
                             f"{out / SETTINGS}); drop {flag}")
    return begun


def on_device(train: dict) -> str:
    """' on the cuda device' where metrics.json names it: a GPU's seconds buy more steps than a CPU's."""
    return f" on the {train['device']} device" if train.get("device") else ""
