"""Plots of a training run: scan maps, metric bars (via evaluation.plots) and metric vs time."""

from __future__ import annotations

from pathlib import Path

from virus_nerf.trainer.run_folder import PLOTS, EvalPoint

SAFETY_PICTURE = "map_safety.png"
# scan maps of a run (evenly over its test points): each is a five-panel figure of ~1 s on a
# 2-core CPU, drawn after training; 8 took ~9 s at the end of every run
RUN_SCAN_MAPS = 4


def write_run_plots(run_dir: Path, result, eval_history: list[EvalPoint], max_maps: int = RUN_SCAN_MAPS,
                    replace: bool = False, safety=None) -> list[Path]:
    """RUN/plots/: scan maps at up to `max_maps` test points, metric bars, metric vs time and,
    given, the map's safety picture (`safety`, an evaluation.safety.RunSafety).

    Built in a temporary folder and renamed into place when every plot is written, so
    RUN/plots/ is never half made. An existing RUN/plots/ is refused unless `replace` (a
    resumed run replaces its own plots only once the new ones are complete).
    """
    from virus_nerf.evaluation.plots import plot_metric_vs_time, write_plot_files
    from virus_nerf.utils.io import new_output_dir

    folder = Path(run_dir) / PLOTS
    with new_output_dir(folder, replace=replace) as tmp:
        names = write_plot_files(result, tmp, max_maps=max_maps)
        # one curve per ground truth the points were scored against (a run resumed with another
        # --gt continues its history under the new one)
        curves: dict[str, list[EvalPoint]] = {}
        for e in eval_history:
            curves.setdefault(f"NeRF, ground truth {e.ground_truth or result.gt}", []).append(e)
        zone3 = next((f"{z.lo:g}-{z.hi:g} m" for z in result.config.zones if z.name == "zone3"), "")
        curve = plot_metric_vs_time(curves, tmp / "metric_vs_time.png",
                                    title=f"NeRF zone 3 ({zone3}) vs training time")
        if curve is not None:
            names.append(curve.name)
        if safety is not None:
            from virus_nerf.evaluation.plots import plot_safety_picture

            body = (safety.document.get("planner") or {}).get("crossing_below") is not None
            plot_safety_picture(safety.picture, safety.origin, safety.resolution, tmp / SAFETY_PICTURE,
                                gt=safety.document.get("gt", result.gt), body=body)
            names.append(SAFETY_PICTURE)
    return [folder / n for n in names]
