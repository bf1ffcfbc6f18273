"""Markdown pieces shared by the demo and the experiment reports."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from virus_nerf.evaluation.metrics import RunMetrics
from virus_nerf.trainer.run_folder import METRICS

METRIC_COLUMNS = ("acc_mean", "acc_median", "acc_inlier", "cov_mean", "cov_median", "cov_inlier")


def _cell(v: Any, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def metrics_markdown(metrics: RunMetrics, zones: Sequence[str] = ("zone1", "zone2", "zone3"),
                     gt: str | None = None) -> str:
    """A markdown table (one row per sensor and zone) of a run's metrics for ground truth `gt`
    (default: the document's own). `gt unseen`: share of in-view GT points at test points where
    the sensor returned nothing (older documents: -)."""
    head = ("| sensor | zone | " + " | ".join(c.replace("_", " ") for c in METRIC_COLUMNS)
            + " | gt unseen | n pred | n gt |")
    sep = "|" + "---|" * (len(METRIC_COLUMNS) + 5)
    lines = [head, sep]
    for sensor, sm in metrics.sensors(gt).items():
        for z in zones:
            m = sm.zones.get(z)
            lo, hi = metrics.zones[z]
            cells = [_cell(None if m is None else getattr(m, c)) for c in (*METRIC_COLUMNS, "gt_unseen", "n_pred", "n_gt")]
            lines.append(f"| {sensor} | {z} ({lo:g}-{hi:g} m) | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def metrics_markdown_by_gt(metrics: RunMetrics, zones: Sequence[str] = ("zone1", "zone2", "zone3")) -> str:
    """One labelled table per ground-truth protocol the run holds (its own first)."""
    from virus_nerf.evaluation.gt import GT_DESCRIPTIONS

    return "\n\n".join(f"Ground truth: **{p}** ({GT_DESCRIPTIONS[p]})\n\n{metrics_markdown(metrics, zones, p)}"
                        for p in metrics.by_gt)


def safety_markdown(doc: Mapping[str, Any], picture: str | None = None) -> list[str]:
    """Report lines for a metrics document's planner-safety block (the map beside its anchors,
    and the `picture` path if given) and warnings (none: no lines)."""
    lines: list[str] = []
    safety = doc.get("safety")
    if safety:
        from virus_nerf.evaluation.safety import ANCHOR_LABELS, below_words, unsafe_words

        def pct(v: Any) -> str:
            return "-" if v is None else f"{100 * v:.1f} %"

        # the map judged is the one `virus-nerf export --what map` writes (the demo writes no map.pgm)
        rows = [("the map (`export`'s `map.pgm`)", safety), *((ANCHOR_LABELS.get(k, k), b)
                                                   for k, b in safety.get("anchors", {}).items())]
        zones = list(safety["zones"])
        lines += ["## Can a planner trust the map?", "",
                  f"Share of the ground-truth obstacles ({safety['gt']}, camera height) that a 2D map marks free "
                  f"(nothing but free within {safety['tolerance_m']:g} m), by distance to the robot's path, and the "
                  f"free space it keeps (of the true free space within {safety.get('free_near_path_m', 3):g} m of the "
                  f"path and {safety.get('free_clearance_m', 0.15):g} m from obstacles, the share marked free); "
                  f"{safety['observed']:.0%} of the map observed by some sensor (the rest stays unknown); the "
                  "drivable free space leaves out, besides, what the LiDAR map holds from "
                  f"{safety.get('drivable_from_floor_m', 0.1):g} m above the floor up to the camera band (what the "
                  "robot's body meets). Beside the map, the same figures of the range sensors' own map (no NeRF) "
                  "and of a LiDAR's.", "",
                  "| map | " + " | ".join(f"marked free, within {z}" if z != "all" else "marked free, all"
                                         for z in zones) + " | free space kept | drivable free space kept |",
                  "|---|" + "---|" * (len(zones) + 2)]
        lines += [f"| {name} | " + " | ".join(pct(b["zones"][z]["free_share"]) for z in zones)
                  + f" | {pct(b.get('free_recall'))} | {pct(b.get('free_recall_drivable'))} |" for name, b in rows]
        lines.append("")
        below = [(name, b["below_band"]) for name, b in rows if b.get("below_band")]
        if below:  # what the band's ground truth does not hold but the robot's body meets
            within = " / ".join(z if z == "all" else z[:-1] + " m" for z in zones)
            shares = "; ".join(f"{name} " + " / ".join(pct(z["free_share"]) for z in block.values())
                               for name, block in below)
            lines += ["What the body meets below the band (the LiDAR map's points from "
                      f"{safety.get('drivable_from_floor_m', 0.1):g} m above the floor up to the band: a pallet, a low "
                      f"shelf, a seat), marked free within {within}: {shares}.", ""]
        if "planner" in safety:
            p = safety["planner"]
            reach = safety.get("planner_reach")
            lines += [f"A planner on the map (robot radius {p['radius_m']:g} m, shortest paths between random free "
                      f"points): {p['crossing']} of {p['paths']} paths pass a real obstacle"
                      + below_words(p) + unsafe_words(p) + "."
                      + ("" if reach is None else f" From where the robot drove it reaches {pct(reach)} of the drivable "
                         "space near the path where such a robot may stand (a lone occupied pixel in an aisle cuts it)."),
                      ""]
        if picture:
            lines += [f"![ground-truth obstacles over the map, the ones it marks free in red]({picture})", "",
                      "Blue: ground-truth obstacles; red: the ones the map marks free; green: the path"
                      + ("; brown: what the body meets below the band; orange: the part of it the map marks free"
                         if (safety.get("planner") or {}).get("crossing_below") is not None else "") + ".", ""]
    for w in doc.get("warnings", []):
        lines += [f"**Warning:** {w}", ""]
    return lines


def runs_warnings(runs: Sequence[Path], root: Path) -> dict[str, list[str]]:
    """Each finished run's metrics.json warnings (why its figures may not be trusted: a run that
    ended inside the grid's warm-up, ...), by run folder relative to `root`; runs without any left out."""
    import json

    out: dict[str, list[str]] = {}
    for run in runs:
        path = Path(run) / METRICS
        if path.is_file():
            warnings = json.loads(path.read_text()).get("warnings") or []
            if warnings:
                out[str(Path(run).relative_to(root))] = list(warnings)
    return out


def warnings_markdown(warnings: Mapping[str, list[str]]) -> str:
    """A '## Warnings' section (one line a run and warning), or "" without any."""
    if not warnings:
        return ""
    lines = ["## Warnings", "", "The runs' own (their metrics.json): figures of a run warned about may not be "
             "what the method gives with a longer budget.", ""]
    lines += [f"- `{run}`: {w}" for run, ws in warnings.items() for w in ws]
    return "\n".join(lines) + "\n"
