"""`virus-nerf ablation`: the eight rows of the paper's Table I on simulated rooms (docs/method.md 8), and row 9 (row 8 with the stereo sensor).

Each (row, scene, seed) is one training process with the same time budget; finished runs are
not redone, interrupted ones resume. The table gives mean +- std over seeds of zone 3 NND
accuracy/coverage means and inlier shares, the paper's figures beside them, and steps/s.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from virus_nerf.evaluation.metrics import RunMetrics, ZoneMetrics, mean_std, read_metrics
from virus_nerf.experiments.executors import run_all
from virus_nerf.experiments.runs import RunSpec
from virus_nerf.trainer.run_folder import METRICS


@dataclass(frozen=True)
class AblationRow:
    number: int
    grid: str
    sensors: str
    odometry: bool = False

    @property
    def label(self) -> str:
        grid = "Instant-NGP" if self.grid == "ngp" else "VIRUS"
        sensors = {"camera": "CAM", "camera,uss,irs": "CAM, USS, IRS", "camera,uss": "CAM, USS",
                   "camera,irs": "CAM, IRS", "camera,rgbd": "RGB-D",
                   "camera,uss,irs,stereo": "CAM, USS, IRS, camera stereo"}[self.sensors]
        return f"{grid}: {sensors}{', odometry poses' if self.odometry else ''}"

    def args(self) -> tuple[str, ...]:
        return ("--grid", self.grid, "--sensors", self.sensors) + (("--odometry-poses",) if self.odometry else ())


ROWS = (
    AblationRow(1, "ngp", "camera"),
    AblationRow(2, "ngp", "camera,uss,irs"),
    AblationRow(3, "virus", "camera"),
    AblationRow(4, "virus", "camera,uss"),
    AblationRow(5, "virus", "camera,irs"),
    AblationRow(6, "virus", "camera,rgbd"),
    AblationRow(7, "virus", "camera,uss,irs", odometry=True),
    AblationRow(8, "virus", "camera,uss,irs"),
    # beyond the paper: row 8 plus depth triangulated from the cameras (docs/method.md 3.7), the
    # default sensors of this repository
    AblationRow(9, "virus", "camera,uss,irs,stereo"),
)

# Table I of the paper: (acc mean, cov mean, acc inlier, cov inlier), zone 3, mean of 10 runs
PAPER = {
    (1, "common"): (0.712, 1.287, 0.056, 0.059), (1, "office"): (0.281, 0.497, 0.221, 0.201),
    (2, "common"): (0.509, 0.501, 0.131, 0.220), (2, "office"): (0.164, 0.214, 0.497, 0.506),
    (3, "common"): (0.704, 1.412, 0.052, 0.056), (3, "office"): (0.277, 0.476, 0.231, 0.215),
    (4, "common"): (0.490, 0.568, 0.146, 0.146), (4, "office"): (0.262, 0.349, 0.212, 0.176),
    (5, "common"): (0.625, 0.643, 0.097, 0.169), (5, "office"): (0.230, 0.374, 0.415, 0.460),
    (6, "common"): (0.324, 0.378, 0.324, 0.389), (6, "office"): (0.154, 0.139, 0.575, 0.633),
    (7, "common"): (0.728, 0.922, 0.113, 0.186), (7, "office"): (0.168, 0.238, 0.531, 0.554),
    (8, "common"): (0.403, 0.448, 0.206, 0.256), (8, "office"): (0.148, 0.237, 0.528, 0.531),
}
KEYS = ("acc_mean", "cov_mean", "acc_inlier", "cov_inlier")


@dataclass(frozen=True)
class Profile:
    scenes: tuple[str, ...]
    seeds: int
    train_time: float
    duration: float


WAREHOUSE_DRIVE_S = 140.0  # seconds of drive in the warehouse (one loop)
PROFILES = {
    "full": Profile(("office", "common"), 3, 75.0, 60.0),
    # (--scenes warehouse: a 140 s drive, its loop takes 135 s; the paper has no figure for it)
    "quick": Profile(("office",), 1, 15.0, 12.0),
}


def run_zone3(metrics: RunMetrics, gt: str, run: Path) -> ZoneMetrics:
    """The NeRF zone-3 metrics of a run under protocol `gt` (a UsageError naming the run when it
    was scored under other protocols, e.g. an earlier ablation with another --gt)."""
    from virus_nerf.errors import UsageError

    try:
        return metrics.sensors(gt)["NeRF"].zones["zone3"]
    except KeyError:
        raise UsageError(f"--gt {gt}: {run / METRICS} holds ground truth {list(metrics.by_gt)} only; "
                         f"evaluate it with `virus-nerf evaluate --run {run} --gt {gt}` or use a new --out") from None


def select_rows(rows: str | None) -> tuple[AblationRow, ...]:
    """`--rows 3,8` -> those rows of Table I (all nine when None)."""
    from virus_nerf.errors import UsageError

    if rows is None:
        return ROWS
    by_number = {r.number: r for r in ROWS}
    picked = []
    for text in rows.split(","):
        if not text.strip().isdigit() or int(text) not in by_number:
            raise UsageError(f"--rows {rows!r}: {text.strip()!r} is not a row; expected a comma-separated "
                             f"subset of {','.join(str(n) for n in by_number)}")
        picked.append(by_number[int(text)])
    return tuple(dict.fromkeys(picked))


def aggregate(out: Path, scenes: tuple[str, ...], seeds: int, gt: str = "map",
              rows: tuple[AblationRow, ...] = ROWS) -> list[dict]:
    """One record per (row, scene): mean and std over seeds under ground truth `gt`, the paper's
    figure, steps/s; `failed` counts the row's runs without a metrics.json (died twice, or not
    run yet)."""
    records = []
    for row in rows:
        for scene in scenes:
            runs = [out / "runs" / scene / f"row{row.number}_seed{s}" for s in range(seeds)]
            done = [(r, read_metrics(r / METRICS)) for r in runs if (r / METRICS).is_file()]
            blocks = [run_zone3(m, gt, r) for r, m in done]
            docs = [m for _, m in done]
            rec: dict = {"row": row.number, "label": row.label, "scene": scene, "gt": gt, "runs": len(docs),
                         "failed": len(runs) - len(docs), "zone3": zone_bounds(docs)}
            for key in KEYS:
                vals = [getattr(b, key) for b in blocks]
                rec[key], rec[key + "_std"] = mean_std(vals)
            rec["steps_per_s"], rec["steps_per_s_std"] = mean_std([m.train.get("steps_per_s") for m in docs])
            for k, v in zip(KEYS, PAPER.get((row.number, scene), (None,) * len(KEYS)), strict=True):
                rec["paper_" + k] = v
            records.append(rec)
    return records


def zone_bounds(docs, name: str = "zone3") -> str:
    """"lo-hi m" of zone `name` as the runs' metrics.json give it (a --config may set other zones
    than the paper's 0-100 m; runs that disagree are named so)."""
    bounds = {tuple(d.zones[name]) for d in docs if name in d.zones}
    if not bounds:
        return "0-100 m"
    return " / ".join(f"{lo:g}-{hi:g} m" for lo, hi in sorted(bounds))


def _fmt(m: float | None, s: float | None) -> str:
    if m is None:
        return "-"
    return f"{m:.3f} ± {s:.3f}"


def _runs(r: dict) -> str:
    """Finished runs, and how many of the row's runs failed (no metrics.json)."""
    return f"{r['runs']}" + (f" ({r['failed']} failed)" if r.get("failed") else "")


def table_markdown(records: list[dict]) -> str:
    lines = [
        "| row | grid, sensors | scene | runs | acc mean [m] | cov mean [m] | acc inlier | cov inlier | steps/s "
        "| paper acc / cov mean (authors' scoring, real rooms, 0-100 m) | paper acc / cov inlier |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in records:
        lines.append(
            f"| {r['row']} | {r['label']} | {r['scene']} | {_runs(r)} | {_fmt(r['acc_mean'], r['acc_mean_std'])} | "
            f"{_fmt(r['cov_mean'], r['cov_mean_std'])} | {_fmt(r['acc_inlier'], r['acc_inlier_std'])} | "
            f"{_fmt(r['cov_inlier'], r['cov_inlier_std'])} | {_fmt(r['steps_per_s'], r['steps_per_s_std'])} | "
            f"{_pair(r['paper_acc_mean'], r['paper_cov_mean'])} | {_pair(r['paper_acc_inlier'], r['paper_cov_inlier'])} |"
        )
    return "\n".join(lines)


def _pair(a: float | None, b: float | None) -> str:
    """A paper figure pair, '-' for a room the paper has none for (the warehouse)."""
    return "-" if a is None or b is None else f"{a:.3f} / {b:.3f}"


def grid_speed(records: list[dict]) -> dict[str, float | None]:
    """Steps/s of the VIRUS vs Instant-NGP grid for the same sensors (rows 8 vs 2)."""
    out: dict[str, float | None] = {}
    for scene in sorted({r["scene"] for r in records}):
        v = next((r["steps_per_s"] for r in records if r["scene"] == scene and r["row"] == 8), None)
        n = next((r["steps_per_s"] for r in records if r["scene"] == scene and r["row"] == 2), None)
        out[scene] = (v / n) if v and n else None
    return out


def plot_rows(records: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from virus_nerf.evaluation.plots import save_png

    scenes = sorted({r["scene"] for r in records})
    fig, axes = plt.subplots(len(scenes), 2, figsize=(11, 3.2 * len(scenes)), squeeze=False)
    for i, scene in enumerate(scenes):
        recs = [r for r in records if r["scene"] == scene]
        x = np.arange(len(recs))
        for j, (key, title) in enumerate((("mean", "NND mean [m]"), ("inlier", "inlier share"))):
            ax = axes[i, j]
            for k, (kind, colour) in enumerate((("acc", "tab:blue"), ("cov", "tab:orange"))):
                vals = [r[f"{kind}_{key}"] if r[f"{kind}_{key}"] is not None else math.nan for r in recs]
                errs = [r[f"{kind}_{key}_std"] or 0.0 for r in recs]
                ax.bar(x + (k - 0.5) * 0.38, vals, 0.38, yerr=errs, color=colour, label=kind, capsize=2)
                paper = [math.nan if r[f"paper_{kind}_{key}"] is None else r[f"paper_{kind}_{key}"] for r in recs]
                ax.scatter(x + (k - 0.5) * 0.38, paper, color="k", marker="_", s=120, zorder=3,
                           label="paper" if k == 0 else None)
            ax.set_xticks(x, [str(r["row"]) for r in recs])
            ax.set_xlabel("Table I row")
            ax.set_title(f"{scene}: zone 3 ({recs[0].get('zone3', '0-100 m')}) {title} (GT {recs[0].get('gt', 'map')})")
            ax.grid(axis="y", alpha=0.3)
            ax.legend(fontsize=8)
    fig.tight_layout()
    return save_png(fig, path)


def ablation(
    out: Path,
    quick: bool = False,
    seeds: int | None = None,
    workers: int = 2,
    train_time: float | None = None,
    max_steps: int | None = None,
    scenes: tuple[str, ...] | None = None,
    rows: str | None = None,
    config: Path | None = None,
    scheduler: str | None = None,
    threads_per_run: int | None = None,
    gt: str = "map",
) -> None:
    """Run the paper's Table I ablation on simulated rooms and aggregate it.

    Writes OUT/data/<scene> (simulated once, seed 0), OUT/runs/<scene>/row<k>_seed<s>/ (one
    training each), and OUT/ablation.{md,csv,json} plus OUT/ablation.png. Re-running the same
    command continues where it stopped: finished runs are kept (never rerun or overwritten),
    interrupted ones resume; a run that dies is retried once, then counted as failed in the
    table. The runs go to local processes, or with --scheduler to a Dask cluster (the same run
    folders: an ablation may be continued with the other executor).
    The summaries are never overwritten: if OUT already holds any of ablation.{md,csv,json,png}
    (a finished ablation) the command is refused before anything runs; to aggregate OUT's runs
    again (e.g. with more seeds), move those files away first, and the finished runs are reused.
    Each summary file is written atomically.

    Args:
        out: Experiment folder (created; an empty folder is taken; continued if it holds an unfinished
            ablation; any other existing folder is refused).
        quick: Smoke profile: office only, 1 seed, 15 s per run.
        seeds: Training seeds per row and scene (default 3; quick 1).
        workers: Trainings in parallel (local: each gets cores / workers threads; with
            --scheduler local: the LocalCluster's workers).
        train_time: Seconds of training per run (default 75; quick 15); not with --max-steps alone.
        max_steps: Training steps per run instead of a time budget (bit-reproducible on CPU);
            with --train-time too, whichever comes first.
        scenes: Scenes to run (default office and common; quick office; warehouse: a 140 s drive,
            no paper figure).
        rows: Table I rows to run, comma-separated (default all nine: Table I and row 9, e.g. 3,8).
        config: JSON config every run starts from (`train --config`); the row's grid and
            sensors, the seed and the budget are set on top.
        scheduler: Dask scheduler address (tcp://HOST:8786) to send the runs to, or 'local' for a
            LocalCluster of --workers workers; default: local processes (needs the [dask] extra).
        threads_per_run: Threads of each training (default: cores / workers locally, 1 on Dask).
        gt: Ground truth of the runs' evaluation, one or more of map, exact, paper, comma-separated
            (default map); a table per protocol, the first one's in the plot.
    """
    import json

    from virus_nerf.errors import UsageError, require_int, require_number
    from virus_nerf.evaluation.config import parse_gt_flag
    from virus_nerf.experiments.folder import (
        config_setting,
        refuse_existing,
        take_experiment_folder,
    )
    from virus_nerf.sim.command import simulate
    from virus_nerf.utils.io import write_json_atomic, write_text_atomic

    if seeds is not None:
        require_int("--seeds", seeds, 1, 1000)
    require_int("--workers", workers, 1, 64)
    protocols = parse_gt_flag(gt, scores=True)
    if train_time is not None:
        require_number("--train-time", train_time, 0.0)
    if max_steps is not None:
        require_int("--max-steps", max_steps, 1)
    if threads_per_run is not None:
        require_int("--threads-per-run", threads_per_run, 1, 1024)
    from virus_nerf.sim.rooms import ROOM_NAMES

    for scene in scenes or ():
        if scene not in ROOM_NAMES:
            raise UsageError(f"--scenes {scene!r}: expected one or more of {', '.join(ROOM_NAMES)} (space-separated)")
    chosen = select_rows(rows)
    if config is not None:
        from virus_nerf.config_io import load_json_config
        from virus_nerf.trainer.config import TrainConfig

        load_json_config(TrainConfig, config)  # a bad file fails now, not in every run
        config = Path(config).absolute()
    prof = PROFILES["quick" if quick else "full"]
    scenes = tuple(dict.fromkeys(scenes)) if scenes else prof.scenes
    n_seeds = seeds or prof.seeds
    t_train = train_time or (None if max_steps is not None else prof.train_time)
    budget = (("--max-steps", str(max_steps)) if max_steps is not None else ()) + \
        (("--max-time", str(t_train)) if t_train is not None else ())
    budget_text = " and ".join(([f"{max_steps} steps"] if max_steps is not None else []) +
                               ([f"{t_train:.0f} s"] if t_train is not None else []))
    out = Path(out).absolute()  # Dask workers may run in other folders
    summaries = [out / f"ablation.{ext}" for ext in ("md", "csv", "json", "png")]
    from virus_nerf.experiments.executors import check_scheduler

    check_scheduler(scheduler)  # the extra and a scheduler that answers, before anything is written
    settings = {"--quick": quick, "--train-time": t_train, "--max-steps": max_steps, "--config": config_setting(config),
                "--gt": ",".join(protocols)}  # what every run shares (the drive simulated: --quick's)
    take_experiment_folder(out, "ablation", summaries, settings)  # new, or this command's unfinished ablation
    for scene in scenes:
        data = out / "data" / scene
        duration = WAREHOUSE_DRIVE_S if scene == "warehouse" else prof.duration
        if not (data / scene).is_dir():
            print(f"simulating {scene} ({duration:.0f} s drive) -> {data}")
            simulate(scene=scene, out=data, seed=0, duration=duration, resolution_scale=0.5)
    base = ("--config", str(config)) if config is not None else ()
    specs = [
        RunSpec(
            name=f"{scene} row {row.number} seed {s}",
            data=out / "data" / scene,
            room=scene,
            out=out / "runs" / scene / f"row{row.number}_seed{s}",
            args=base + row.args() + ("--seed", str(s)) + budget + ("--image-scale", "1.0",
                                                                    "--gt", ",".join(protocols)),
        )
        for scene in scenes
        for row in chosen
        for s in range(n_seeds)
    ]
    failed = run_all(specs, workers=workers, threads_per_worker=threads_per_run, scheduler=scheduler)
    by_gt = {p: aggregate(out, scenes, n_seeds, p, chosen) for p in protocols}
    records = by_gt[protocols[0]]
    refuse_existing(summaries)  # again: another process may have finished the same folder meanwhile
    from virus_nerf.evaluation.gt import GT_DESCRIPTIONS

    md = "\n\n".join(f"Ground truth: **{p}** ({GT_DESCRIPTIONS[p]}); zone 3 ({r[0]['zone3'] if r else '0-100 m'}), "
                     f"mean ± std over the seeds; the paper's columns are the authors' figures (their scoring, "
                     f"real rooms, a GPU)\n\n{table_markdown(r)}" for p, r in by_gt.items())
    speed = grid_speed(records)
    speed_md = ", ".join(f"{k}: {v:.2f}x" if v else f"{k}: -" for k, v in speed.items())
    from virus_nerf.experiments.report import runs_warnings, warnings_markdown

    warnings = runs_warnings([s.out for s in specs], out)
    write_text_atomic(
        out / "ablation.md",
        f"# Table I ablation ({n_seeds} seed(s), {budget_text} of training per run)\n\n{md}\n\n"
        f"Grid speed, VIRUS / Instant-NGP steps/s (row 8 vs row 2): {speed_md} (paper: 1.46x)\n"
        + ("\n" + warnings_markdown(warnings) if warnings else ""),
    )
    buf = io.StringIO()
    all_records = [r for recs in by_gt.values() for r in recs]
    writer = csv.DictWriter(buf, fieldnames=list(all_records[0]))
    writer.writeheader()
    writer.writerows(all_records)
    write_text_atomic(out / "ablation.csv", buf.getvalue())
    write_json_atomic(out / "ablation.json", {"gt": protocols[0], "records": records, "grid_speed_ratio": speed,
                                              "seeds": n_seeds, "train_time": t_train, "max_steps": max_steps,
                                              "failed": [s.name for s in failed], "warnings": warnings,
                                              **({"by_gt": by_gt} if len(by_gt) > 1 else {})})
    plot_rows(records, out / "ablation.png")
    print(md)
    print(f"grid speed VIRUS / Instant-NGP: {json.dumps(speed)}")
    if failed:
        raise SystemExit(f"{len(failed)} run(s) failed (counted in the table): " + ", ".join(s.name for s in failed))
