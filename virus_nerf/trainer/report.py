"""Plots of a training run: scan maps, metric bars (via evaluation.plots) and metric vs time."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path


def plot_metric_vs_time(curves: dict[str, Sequence[dict]], path: Path, key: str = "acc_mean",
                        title: str = "NeRF zone 3 vs training time") -> Path | None:
    """One line per run label: `key` (e.g. acc_mean, m) vs training seconds (paper Fig. 6)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from virus_nerf.evaluation.plots import save_png

    curves = {k: [e for e in v if e.get(key) is not None] for k, v in curves.items()}
    curves = {k: v for k, v in curves.items() if v}
    if not curves:
        return None
    fig, ax = plt.subplots(figsize=(6, 3.6))
    for label, hist in curves.items():
        ax.plot([e["seconds"] for e in hist], [e[key] for e in hist], marker="o", ms=3, label=label)
    ax.set_xlabel("training time [s]")
    ax.set_ylabel(f"zone 3 {key.replace('_', ' ')} [m]" if "mean" in key else f"zone 3 {key}")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    return save_png(fig, path)


def write_run_plots(run_dir: Path, result, eval_history: list[dict], max_maps: int = 8,
                    replace: bool = False) -> list[Path]:
    """RUN/plots/: scan maps at up to `max_maps` test points, metric bars, metric vs time.

    Built in a temporary folder and renamed into place when every plot is written, so
    RUN/plots/ is never half made. An existing RUN/plots/ is refused unless `replace` (a
    resumed run replaces its own plots only once the new ones are complete).
    """
    from virus_nerf.evaluation.command import write_plot_files
    from virus_nerf.utils.io import new_output_dir

    folder = Path(run_dir) / "plots"
    with new_output_dir(folder, replace=replace) as tmp:
        names = write_plot_files(result, tmp, max_maps=max_maps)
        curve = plot_metric_vs_time({"NeRF": eval_history}, tmp / "metric_vs_time.png")
        if curve is not None:
            names.append(curve.name)
    return [folder / n for n in names]
