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


def metrics_markdown(doc: Mapping[str, Any], zones: Sequence[str] = ("zone1", "zone2", "zone3")) -> str:
    """A markdown table (one row per sensor and zone) from a metrics.json document."""
    head = "| sensor | zone | " + " | ".join(c.replace("_", " ") for c in METRIC_COLUMNS) + " | n pred | n gt |"
    sep = "|" + "---|" * (len(METRIC_COLUMNS) + 4)
    lines = [head, sep]
    for sensor, per_zone in doc["sensors"].items():
        for z in zones:
            m = per_zone.get(z, {})
            lo, hi = doc["zones"][z]
            lines.append(
                f"| {sensor} | {z} ({lo}-{hi} m) | "
                + " | ".join(_cell(m.get(c)) for c in METRIC_COLUMNS)
                + f" | {_cell(m.get('n_pred'))} | {_cell(m.get('n_gt'))} |"
            )
    return "\n".join(lines)
