"""Plots of the evaluation (paper Fig. 3, 4/5), written as PNG atomically (matplotlib Agg).

- `plot_test_point`: top-down map of one test point, one panel with every scan and one panel
  per sensor/model with its field-of-view GT, in metres with equal aspect.
- `plot_metric_bars`: per zone and sensor, mean NND (bars) with the median (markers), and the
  inlier / too-close / too-far shares as stacked bars, for accuracy and coverage; the coverage
  shares are of all in-view GT points, with the GT at test points where the sensor returned
  nothing (gt_unseen) as a grey "unseen" part on top.
Every title names the ground-truth protocol (docs/method.md 6.7).
"""

from __future__ import annotations

import functools
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from virus_nerf.evaluation.evaluate import spread_indices
from virus_nerf.evaluation.metrics import DEFAULT_ZONES, SensorMetrics, Zone
from virus_nerf.maps.scans import FieldOfView
from virus_nerf.utils.io import atomic_path, new_output_dir

if TYPE_CHECKING:
    import matplotlib.pyplot as plt

COLOURS = {"GT": "black", "LiDAR": "tab:blue", "USS": "tab:orange", "IRS": "tab:green", "NeRF": "tab:red"}
GT_MARKERS = {"map": "o", "exact": "x", "paper": "+"}  # the further protocols' GT in the "all" panel
EXTRA_COLOURS = ("tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan")


@functools.cache
def pyplot():
    """matplotlib.pyplot on the Agg backend (files, no display), imported when the first plot is
    drawn: 1.7 s of start-up on a 2-core machine that `evaluate --no-plots`, `train --no-plots`
    and `plots_dir_for` do not need."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def colour_of(name: str, order: Sequence[str] = ()) -> str:
    if name in COLOURS:
        return COLOURS[name]
    others = [n for n in order if n not in COLOURS]
    k = others.index(name) if name in others else 0
    return EXTRA_COLOURS[k % len(EXTRA_COLOURS)]


def save_png(fig: plt.Figure, path: str | Path, dpi: int = 110, tight: bool = True) -> Path:
    """Write `fig` to `path` in one rename (never a half-written PNG) and close it. `tight`
    crops to the drawn content, at the cost of drawing the figure twice; a figure laid out by
    hand passes False."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight" if tight else None)
    pyplot().close(fig)
    return path


def _draw_fov(ax: plt.Axes, fov: FieldOfView, radius: float, colour: str) -> None:
    for s in fov.sectors:
        if s.half_angle >= np.pi:
            continue
        for a in (s.heading - s.half_angle, s.heading + s.half_angle):
            end = s.apex + radius * np.array([np.cos(a), np.sin(a)])
            ax.plot([s.apex[0], end[0]], [s.apex[1], end[1]], color=colour, lw=0.7, ls="--", alpha=0.7)


def plot_test_point(tps, path: str | Path, title: str = "", window_m: float | None = None) -> Path:
    """Top-down map of one test point (a `TestPointScans`): grey map slice, GT, every scan."""
    gt = tps.ground_truth
    names = list(tps.scans)
    panels = ["all"] + names
    ncol = min(len(panels), 2)
    nrow = int(np.ceil(len(panels) / ncol))
    fig, axes = pyplot().subplots(nrow, ncol, figsize=(7.0 * ncol, 6.0 * nrow), squeeze=False)
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.05, top=0.94, wspace=0.22, hspace=0.18)
    origin = gt.scan.origin
    # view window: around what was seen (GT and scans), with a margin
    seen = [gt.scan.points] + [s.points for s in tps.scans.values()] + [origin[None, :]]
    seen_pts = np.concatenate(seen)
    lo = seen_pts.min(axis=0) - 0.5
    hi = seen_pts.max(axis=0) + 0.5
    if window_m is not None:
        lo = np.maximum(lo, origin - window_m)
        hi = np.minimum(hi, origin + window_m)
    radius = float(np.max(hi - lo))
    sl = gt.slice_xy
    in_view = np.all((sl >= lo) & (sl <= hi), axis=1)
    for ax, panel in zip(axes.ravel(), panels, strict=False):
        ax.scatter(sl[in_view, 0], sl[in_view, 1], s=1, c="0.78", marker=".", linewidths=0, label="map slice")
        if panel == "all":
            ax.scatter(gt.scan.points[:, 0], gt.scan.points[:, 1], s=4, c=COLOURS["GT"],
                       label=f"GT {gt.protocol} ({len(gt.scan)})")
            for p, other in getattr(tps, "all_gt", {}).items():
                if p == gt.protocol:
                    continue
                ax.scatter(other.scan.points[:, 0], other.scan.points[:, 1], s=10, c="0.35", linewidths=0.6,
                           marker=GT_MARKERS.get(p, "."), label=f"GT {p} ({len(other.scan)})")
            for name, scan in tps.scans.items():
                ax.scatter(scan.points[:, 0], scan.points[:, 1], s=6, c=colour_of(name, names), label=f"{name} ({len(scan)})")
            ax.set_title("all scans")
        else:
            scan = tps.scans[panel]
            fgt = tps.fov_gt(panel)
            c = colour_of(panel, names)
            ax.scatter(fgt.points[:, 0], fgt.points[:, 1], s=4, c=COLOURS["GT"],
                       label=f"GT {gt.protocol} in FoV ({len(fgt)})")
            ax.scatter(scan.points[:, 0], scan.points[:, 1], s=8, c=c, label=f"{panel} ({len(scan)})")
            _draw_fov(ax, scan.fov, radius, c)
            ax.set_title(panel)
        ax.plot(*origin, marker="*", ms=12, c="red", mec="k", ls="none", label="scan origin")
        for _, pose in tps.test_point.camera_poses().values():
            head = pose[:2, 2] / max(np.linalg.norm(pose[:2, 2]), 1e-9) * 0.4
            ax.annotate("", xy=pose[:2, 3] + head, xytext=pose[:2, 3], arrowprops=dict(arrowstyle="->", color="red"))
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.grid(True, lw=0.3, alpha=0.5)
        ax.legend(loc="upper right", fontsize=7, markerscale=1.0, framealpha=0.85)
    for ax in axes.ravel()[len(panels):]:
        ax.axis("off")
    tp = tps.test_point
    fig.suptitle(title or f"test point: stack-1 frame {tp.index1}, t = {tp.time:.3f} s, the camera at world "
                          f"z = {tp.height:.3f} m; ground truth: {gt.protocol}")
    return save_png(fig, path, tight=False)  # laid out by hand above: drawn once


def plot_metric_bars(
    metrics: Mapping[str, SensorMetrics],
    path: str | Path,
    zones: Sequence[Zone] = DEFAULT_ZONES,
    title: str = "",
    inlier_m: float = 0.1,
    gt: str | None = None,
) -> Path:
    """Fig. 3 style: mean NND per zone and sensor, and inlier / too-close / too-far shares
    (coverage: of all in-view GT points, with gt_unseen). `gt` names the protocol in the title."""
    names = list(metrics)
    fig, axes = pyplot().subplots(2, 2, figsize=(13, 8.5))
    nz = len(zones)
    width = 0.8 / max(len(names), 1)
    x = np.arange(nz)
    for row, kind in enumerate(("acc", "cov")):
        label = "accuracy" if kind == "acc" else "coverage"
        ax = axes[row, 0]
        for k, name in enumerate(names):
            zm = [metrics[name].zones.get(z.name) for z in zones]
            means = [getattr(m, f"{kind}_mean") if m else None for m in zm]
            meds = [getattr(m, f"{kind}_median") if m else None for m in zm]
            xs = x - 0.4 + width * (k + 0.5)
            ax.bar(xs, [v if v is not None else 0.0 for v in means], width * 0.9, color=colour_of(name, names), label=name)
            ok = [i for i, v in enumerate(meds) if v is not None]
            ax.plot(xs[ok], [meds[i] for i in ok], "k_", ms=10, mew=2, label="median" if k == 0 else None)
            for i, v in enumerate(means):
                if v is None:
                    ax.text(xs[i], 0, "n/a", ha="center", va="bottom", fontsize=7, rotation=90)
        ax.set_xticks(x, [f"{z.name}\n[{z.lo:g}, {z.hi:g}] m" for z in zones])
        ax.set_ylabel(f"{label} NND mean [m]")
        ax.set_title(f"{label}: mean (bars) and median (ticks)")
        ax.legend(fontsize=8, loc="upper left")  # "best" is searched over every bar: slow, and warned about
        ax.grid(True, axis="y", lw=0.3)

        ax = axes[row, 1]
        parts = (("inlier", "#59a14f"), ("too_close", "#e15759"), ("too_far", "#4e79a7"))
        for k, name in enumerate(names):
            xs = x - 0.4 + width * (k + 0.5)
            bottom = np.zeros(nz)
            zms = [metrics[name].zones.get(z.name) for z in zones]
            # coverage: shares of all in-view GT points; the unseen ones (no return) on top
            unseen = np.array([(zm.gt_unseen or 0.0) if (zm is not None and kind == "cov") else 0.0 for zm in zms])
            for part, c in parts:
                vals = np.array([(getattr(zm, f"{kind}_{part}") or 0.0) if zm is not None else 0.0 for zm in zms])
                vals = vals * (1.0 - unseen)
                ax.bar(xs, vals, width * 0.9, bottom=bottom, color=c, edgecolor="white", lw=0.5,
                       label=part.replace("_", " ") if k == 0 else None)
                bottom += vals
            if kind == "cov":
                ax.bar(xs, unseen, width * 0.9, bottom=bottom, color="0.75", edgecolor="white", lw=0.5, hatch="//",
                       label="unseen (no return)" if k == 0 else None)
                bottom += unseen
            for i in range(nz):
                ax.text(xs[i], 1.01, name, ha="center", va="bottom", fontsize=6, rotation=90)
        ax.set_xticks(x, [z.name for z in zones])
        ax.set_ylim(0, 1.25)
        ax.set_ylabel("share of points" if kind == "acc" else "share of in-view GT points")
        ax.set_title(f"{label}: inliers (< {inlier_m:g} m) and outliers"
                     + (", GT at test points with no return (gt_unseen)" if kind == "cov" else ""))
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=4)
    fig.suptitle(title or ("NND metrics per zone" + (f"; ground truth: {gt}" if gt else "")))
    fig.tight_layout()
    return save_png(fig, path)


def plot_metric_vs_time(curves: Mapping[str, Sequence], path: Path, key: str = "acc_mean",
                        title: str = "NeRF zone 3 vs training time") -> Path | None:
    """One line per run label: `key` of its EvalPoints (e.g. acc_mean, m) vs training seconds (paper Fig. 6)."""
    curves = {k: [e for e in v if getattr(e, key) is not None] for k, v in curves.items()}
    curves = {k: v for k, v in curves.items() if v}
    if not curves:
        return None
    fig, ax = pyplot().subplots(figsize=(6, 3.6))
    for label, hist in curves.items():
        ax.plot([e.seconds for e in hist], [getattr(e, key) for e in hist], marker="o", ms=3, label=label)
    ax.set_xlabel("training time [s]")
    ax.set_ylabel(f"zone 3 {key.replace('_', ' ')} [m]" if "mean" in key else f"zone 3 {key}")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right")  # the curves fall from the left
    return save_png(fig, path)


def plot_safety_picture(picture: np.ndarray, origin: tuple[float, float], resolution: float, path: Path,
                        gt: str = "map", body: bool = False) -> Path:
    """The safety picture (evaluation.safety.safety_picture: (H, W, 3) uint8, row 0 = largest y)
    with axes in metres, a title naming the ground truth and a legend of its colours (`body`:
    with what the body meets below the band). Drawn pixel for pixel (nearest), at least one
    image pixel a map pixel."""
    from matplotlib.patches import Patch

    from virus_nerf.evaluation import safety as s

    h, w = picture.shape[:2]
    x0, y0 = origin
    plt = pyplot()
    width_in = 8.0
    fig, ax = plt.subplots(figsize=(width_in, width_in * h / w + 1.6))
    ax.imshow(picture, extent=(x0, x0 + w * resolution, y0, y0 + h * resolution), interpolation="nearest")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"2D map ({resolution:g} m pixels) and the {gt} ground truth's obstacles at camera height", fontsize=9)
    items = [(s.MAP_FREE_RGB, "map: free"), (s.MAP_UNKNOWN_RGB, "map: unknown"), (s.MAP_OCCUPIED_RGB, "map: occupied"),
             (s.OBSTACLE_RGB, "obstacle (ground truth)"), (s.MISSED_RGB, "obstacle the map marks free"),
             (s.PATH_RGB, "path")]
    if body:
        items += [(s.BODY_RGB, "body meets below the band"), (s.BODY_MISSED_RGB, "... the map marks it free")]
    ax.legend(handles=[Patch(facecolor=np.array(c) / 255, edgecolor="0.4", label=t) for c, t in items],
              fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=4)
    return save_png(fig, path, dpi=int(max(110, np.ceil(w / (width_in * 0.8)))))


def plots_dir_for(out: Path) -> Path:
    """Plot folder beside a metrics file: results/metrics.json -> results/metrics_plots/."""
    out = Path(out)
    return out.parent / f"{out.stem}_plots"


PLOT_NAME = re.compile(r"scan_frame\d{4,}\.png|metrics_bars(?:_gt-[a-z]+)?\.png")  # write_plot_files' names


def stopped_attempts_plots(folder: Path, out: Path) -> bool:
    """True when the plot folder `folder` of the metrics file `out` is there from an attempt
    stopped before its metrics file (it is then drawn again whole and replaced); False when it is
    absent. A folder holding anything else (a user's own files) is refused in one line, never
    replaced."""
    folder = Path(folder)
    if not folder.exists():
        return False
    others = sorted(p.name for p in folder.iterdir() if not (PLOT_NAME.fullmatch(p.name) and p.is_file())) \
        if folder.is_dir() else [folder.name]
    if others:
        from virus_nerf.errors import UsageError

        raise UsageError(f"{folder}: the plots of --out {out} go there, but it holds what this command did not "
                         f"write ({others[0]}{f' and {len(others) - 1} more' if len(others) > 1 else ''}); "
                         "expected no such folder: choose another --out (nothing was touched)")
    return True


def write_plots(result, folder: Path, max_maps: int | None = None, replace: bool = False) -> list[Path]:
    """Plots of an EvaluationResult into a new folder (refuses an existing one unless `replace`).

    One scan map per test point (at most `max_maps`, evenly spread) and the metric bars. The
    folder is built under a temporary name and renamed when complete.
    """
    with new_output_dir(folder, replace=replace) as tmp:
        names = write_plot_files(result, tmp, max_maps=max_maps)
    return [Path(folder) / n for n in names]


def write_plot_files(result, folder: Path, max_maps: int | None = None) -> list[str]:
    """The scan maps and the metric bars into an existing folder; returns the file names.

    The scan maps show the primary protocol's GT (the others' GT overlaid in the "all" panel);
    metrics_bars.png is the primary protocol's, metrics_bars_gt-<protocol>.png each further one.
    """
    names: list[str] = []
    points = [result.points[i] for i in spread_indices(len(result.points), max_maps)]
    for tps in points:
        name = f"scan_frame{tps.test_point.index1:04d}.png"
        plot_test_point(tps, Path(folder) / name)
        names.append(name)
    by_gt = result.by_gt or {result.gt: result.metrics}
    for k, (protocol, metrics) in enumerate(by_gt.items()):
        name = "metrics_bars.png" if k == 0 else f"metrics_bars_gt-{protocol}.png"
        plot_metric_bars(metrics, Path(folder) / name, result.config.zones, inlier_m=result.config.inlier_m,
                         gt=protocol)
        names.append(name)
    return names
