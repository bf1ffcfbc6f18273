"""`virus-nerf online`: offline vs online training (paper IV-F.2, Fig. 6).

Offline: all frames from the start. Online: frames appear as the training clock (scaled by
the playback speed) passes their timestamps, and the NeRF is scored at intervals on the test
points seen so far. Both for several seeds; the plot shows zone 3 accuracy vs training time
with the spread over seeds.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from virus_nerf.evaluation.metrics import mean_std
from virus_nerf.experiments.executors import run_all
from virus_nerf.experiments.folder import refuse_existing, take_experiment_folder
from virus_nerf.experiments.runs import RunSpec
from virus_nerf.trainer.run_folder import METRICS_VS_TIME, EvalPoint, read_eval_history


def band(histories: list[list[EvalPoint]], key: str, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and std over runs of `key`, each run interpolated onto the time grid (NaN outside);
    per time, the same statistics as `metrics.mean_std` (sample std, 0 where one run covers it)."""
    rows = []
    for h in histories:
        h = [e for e in h if getattr(e, key) is not None]
        if len(h) < 1:
            continue
        t = np.array([e.seconds for e in h])
        v = np.array([getattr(e, key) for e in h])
        rows.append(np.where((grid >= t[0]) & (grid <= t[-1]), np.interp(grid, t, v), np.nan))
    if not rows:
        return np.full_like(grid, np.nan), np.full_like(grid, np.nan)
    stats = [mean_std(None if np.isnan(x) else float(x) for x in column) for column in np.array(rows).T]
    mean = np.array([np.nan if m is None else m for m, _ in stats])
    std = np.array([np.nan if s is None else s for _, s in stats])
    return mean, std




def online(
    out: Path,
    quick: bool = False,
    seeds: int | None = None,
    duration: float | None = None,
    playback: float | None = None,
    eval_interval: float | None = None,
    workers: int = 1,
    gt: str = "map",
    playback_speed: float | None = None,
) -> None:
    """Offline vs online training on a simulated office; writes OUT/online.{png,json,md}.

    OUT may be new or hold an unfinished experiment of this command (experiments/folder.py; any
    other folder is refused): finished runs in OUT/runs are kept and interrupted ones resume. A
    finished experiment (any of OUT/online.{json,md,png} present) is refused before anything
    runs: the summaries are never overwritten; choose a new --out
    (or move the summary files away to aggregate OUT's runs again). The summaries are written
    atomically.

    Args:
        out: Experiment folder (created; an empty folder is taken; continued if it holds an unfinished
            online experiment; refused if it holds summaries or anything else).
        quick: Smoke profile: 1 seed, a 10 s drive.
        seeds: Training seeds (default 3; quick 1).
        duration: Seconds of simulated drive (default 40; quick 10).
        playback: Online: recording seconds per training second (default 0.5; below 1 for slow
            machines); the online run trains for duration / playback seconds, the offline run as long.
        eval_interval: Seconds of training between evaluations (default: 1/10 of the run).
        workers: Trainings in parallel (default 1: the online run is timed against the
            wall clock, so each training gets the whole machine; two at once on a 2-core machine
            halve the steps of both and the online run falls behind its frames).
        gt: Ground truth of the evaluations, one or more of map, exact, paper, comma-separated
            (default map); the curves use the first.
        playback_speed: Deprecated: the old name of --playback.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from virus_nerf.errors import renamed_flag, require_int, require_number, say_notes
    from virus_nerf.evaluation.config import parse_gt_flag
    from virus_nerf.evaluation.plots import save_png
    from virus_nerf.sim.command import simulate
    from virus_nerf.utils.io import write_json_atomic, write_text_atomic

    if seeds is not None:
        require_int("--seeds", seeds, 1, 1000)
    if duration is not None:
        require_number("--duration", duration, 0.0, 3600.0)
    playback_flag = "--playback-speed" if playback is None and playback_speed is not None else "--playback"
    playback_speed = renamed_flag("--playback", playback, "--playback-speed", playback_speed)
    playback_speed = 0.5 if playback_speed is None else playback_speed
    require_number(playback_flag, playback_speed, 0.0)
    if eval_interval is not None:
        require_number("--eval-interval", eval_interval, 0.0)
    require_int("--workers", workers, 1, 64)
    protocols = parse_gt_flag(gt, scores=True)
    summaries = [out / "online.json", out / "online.md", out / "online.png"]
    n_seeds = seeds or (1 if quick else 3)
    duration = duration or (10.0 if quick else 40.0)
    t_train = duration / playback_speed
    interval = eval_interval or t_train / 10
    settings = {"--duration": duration, "--playback": playback_speed, "--eval-interval": interval,
                "--gt": ",".join(protocols)}  # what every run shares
    say_notes()
    take_experiment_folder(out, "online", summaries, settings)  # new, or this command's unfinished experiment
    data = out / "data"
    if not (data / "office").is_dir():
        simulate(scene="office", out=data, seed=0, duration=duration, resolution_scale=0.5)
    common = ("--eval-interval", str(interval), "--image-scale", "1.0", "--gt", ",".join(protocols))
    specs = []
    for s in range(n_seeds):
        specs.append(RunSpec(f"offline seed {s}", data, "office", out / "runs" / f"offline_seed{s}",
                             common + ("--seed", str(s), "--max-time", str(t_train))))
        specs.append(RunSpec(f"online seed {s}", data, "office", out / "runs" / f"online_seed{s}",
                             common + ("--seed", str(s), "--online", "--playback", str(playback_speed))))
    failed = run_all(specs, workers)
    grid = np.linspace(0, t_train, 101)
    summary = {}
    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    labels = {"offline": "offline (all test points)", "online": "online (the test points driven past so far)"}
    for mode, colour in (("offline", "tab:blue"), ("online", "tab:orange")):
        hist = [read_eval_history(out / "runs" / f"{mode}_seed{s}" / METRICS_VS_TIME) for s in range(n_seeds)]
        mean, std = band(hist, "acc_mean", grid)
        ax.plot(grid, mean, color=colour, label=labels[mode])
        ax.fill_between(grid, mean - std, mean + std, color=colour, alpha=0.25)
        finals = [h[-1].acc_mean for h in hist if h and h[-1].acc_mean is not None]
        final_mean, final_std = mean_std(finals)
        summary[mode] = {"final_acc_mean": final_mean, "final_acc_std": final_std, "runs": len(finals)}
    ax.set_xlabel("training time [s]")
    ax.set_ylabel("NeRF zone 3 (0-100 m) accuracy mean [m]")
    ax.set_title(f"offline vs online (playback x{playback_speed:g}), mean ± std over {n_seeds} seed(s); "
                 f"GT {protocols[0]}", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend()
    refuse_existing(summaries)  # again: another process may have finished the same folder meanwhile
    save_png(fig, out / "online.png")
    from virus_nerf.experiments.report import runs_warnings, warnings_markdown

    warnings = runs_warnings([s.out for s in specs], out)
    write_json_atomic(out / "online.json", {"gt": protocols[0], "summary": summary, "train_time": t_train,
                                            "seeds": n_seeds, "playback_speed": playback_speed, "warnings": warnings})
    write_text_atomic(out / "online.md", f"# Offline vs online\n\nGround truth: {protocols[0]}\n\n" + "\n".join(
        f"- {m}: final zone 3 (0-100 m) accuracy {_metres(v['final_acc_mean'])} ± {_metres(v['final_acc_std'])} m over "
        f"{v['runs']} run(s)" for m, v in summary.items())
        + "\n\n![accuracy vs time](online.png)\n(before its end, the online curve is scored on the test points "
          "the drive has passed so far, as in the paper; the offline curve and both final figures on all of them)\n"
          "(the paper's figures, the authors' scoring on their real "
          "office with a GPU: 0.148 m offline, 0.161 m online)\n"
        + ("\n" + warnings_markdown(warnings) if warnings else ""))
    for m, v in summary.items():  # the lines of online.md: ground truth, zone, unit
        print(f"{m}: final zone 3 (0-100 m) accuracy {_metres(v['final_acc_mean'])} ± {_metres(v['final_acc_std'])} m "
              f"over {v['runs']} run(s), ground truth {protocols[0]}")
    if failed:
        raise SystemExit(f"{len(failed)} run(s) failed")


def _metres(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f}"
