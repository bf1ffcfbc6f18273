"""Markdown pieces shared by the demo and the experiment reports."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

METRIC_COLUMNS = ("acc_mean", "acc_median", "acc_inlier", "cov_mean", "cov_median", "cov_inlier")


def _cell(v: Any, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def metrics_markdown(doc: Mapping[str, Any], zones: Sequence[str] = ("zone1", "zone2", "zone3"),
                     gt: str | None = None) -> str:
    """A markdown table (one row per sensor and zone) from a metrics.json document, for ground
    truth `gt` (default: the document's own). `gt unseen`: share of in-view GT points at test
    points where the sensor returned nothing (older documents: -)."""
    from virus_nerf.evaluation.metrics import sensors_block

    head = ("| sensor | zone | " + " | ".join(c.replace("_", " ") for c in METRIC_COLUMNS)
            + " | gt unseen | n pred | n gt |")
    sep = "|" + "---|" * (len(METRIC_COLUMNS) + 5)
    lines = [head, sep]
    for sensor, per_zone in sensors_block(doc, gt).items():
        for z in zones:
            m = per_zone.get(z, {})
            lo, hi = doc["zones"][z]
            lines.append(
                f"| {sensor} | {z} ({lo}-{hi} m) | "
                + " | ".join(_cell(m.get(c)) for c in METRIC_COLUMNS)
                + f" | {_cell(m.get('gt_unseen'))} | {_cell(m.get('n_pred'))} | {_cell(m.get('n_gt'))} |"
            )
    return "\n".join(lines)


def metrics_markdown_by_gt(doc: Mapping[str, Any], zones: Sequence[str] = ("zone1", "zone2", "zone3")) -> str:
    """One labelled table per ground-truth protocol the document holds (its own first)."""
    from virus_nerf.evaluation.gt import GT_DESCRIPTIONS
    from virus_nerf.evaluation.metrics import gt_protocols_of

    return "\n\n".join(f"Ground truth: **{p}** ({GT_DESCRIPTIONS[p]})\n\n{metrics_markdown(doc, zones, p)}"
                        for p in gt_protocols_of(doc))
