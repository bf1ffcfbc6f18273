"""Nearest-neighbour distance metrics per distance zone (docs/method.md 6.5, 6.6) and metrics.json (docs/method.md 7).

Definitions (all distances 2D, metres; depth = distance from the test point's scan origin):
- accuracy: for each predicted point, the distance to its nearest FoV-GT point. The point's zone
  is decided by the depth of that nearest GT point. An outlier (distance >= inlier threshold)
  is "too close" when the predicted point's depth is shorter than its nearest GT point's depth,
  otherwise "too far".
- coverage: for each FoV-GT point, the distance to its nearest predicted point. The zone is
  decided by the GT point's own depth. An outlier is "too close" when that nearest predicted
  point is nearer to the origin than the GT point (the prediction is too close), else "too far".
- Zones are closed intervals lo <= depth <= hi on float depths (docs/method.md 9.7); zones nest.
- inlier + too_close + too_far = 1 in every zone with points.
- A test point contributes accuracy only if it has FoV-GT points, and coverage only if the
  sensor returned at least one point there (a nearest neighbour must exist: the paper's
  definition, kept as `cov_*`). Points are pooled over test points before the statistics.
  No points -> None (JSON null), never NaN.
- gt_unseen: the share of all FoV-GT points (pooled, zone by the GT depth) that lie at test
  points where the sensor returned nothing, i.e. the GT points `cov_*` leaves out. A sparse
  sensor that is silent at most test points has a flattering `cov_*` and a large `gt_unseen`.

metrics.json names the ground-truth protocol its numbers use ("gt": "map" | "exact" | "paper",
docs/method.md 6.7; a document without it is from before the protocols and used "map"). When several
protocols were asked, "sensors" holds the first and "by_gt" maps every protocol asked (the
first included) to {"sensors": ...} of the same form.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from dataclasses import field as dataclass_field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from virus_nerf.evaluation.config import DEFAULT_ZONES, GT_PROTOCOLS, INLIER_M, Zone  # noqa: F401  (importable from here as before)
from virus_nerf.utils.io import write_json_atomic

METRIC_KEYS = (
    "acc_mean", "acc_median", "acc_inlier", "acc_too_close", "acc_too_far",
    "cov_mean", "cov_median", "cov_inlier", "cov_too_close", "cov_too_far", "gt_unseen",
    "n_pred", "n_gt",
)
LEGACY_METRIC_KEYS = tuple(k for k in METRIC_KEYS if k != "gt_unseen")  # metrics.json before gt_unseen
DEFAULT_GT = "map"  # the protocol of a metrics.json that names none


@dataclass
class NNDSamples:
    """Per-point nearest-neighbour data of one sensor, pooled over any number of test points.

    Kept as float32 (steps of 0.12 um at 1 m, 61 um at 1 km; the statistics are taken in float64):
    an hour's drive pools millions of them, and they are the part of the evaluation that grows with
    the drive (D63). The depths are rounded up (`_up32`), so that a depth beyond a zone's bound (0,
    1, 2, 100 m: float32 numbers) stays beyond it, as in float64."""

    acc_dist: np.ndarray  # (M,) m, predicted point -> nearest GT point
    acc_pred_depth: np.ndarray  # (M,) m, depth of the predicted point
    acc_gt_depth: np.ndarray  # (M,) m, depth of its nearest GT point (decides the zone)
    cov_dist: np.ndarray  # (K,) m, GT point -> nearest predicted point
    cov_gt_depth: np.ndarray  # (K,) m, depth of the GT point (decides the zone)
    cov_pred_depth: np.ndarray  # (K,) m, depth of its nearest predicted point
    # (U,) m, depths of FoV-GT points at test points where the sensor returned nothing
    unseen_gt_depth: np.ndarray = dataclass_field(default_factory=lambda: np.zeros(0, np.float32))

    @staticmethod
    def empty() -> NNDSamples:
        return NNDSamples(*(np.zeros(0, np.float32) for _ in fields(NNDSamples)))

    @staticmethod
    def concat(items: Sequence[NNDSamples]) -> NNDSamples:
        if not items:
            return NNDSamples.empty()
        return NNDSamples(
            *(np.concatenate([getattr(s, f.name) for s in items]) for f in fields(NNDSamples))
        )


def nnd_samples(pred: np.ndarray, gt: np.ndarray, origin: np.ndarray) -> NNDSamples:
    """Nearest neighbours between predicted points (M, 2) and FoV-GT points (K, 2) of one test point."""
    pred = np.asarray(pred, dtype=np.float64).reshape(-1, 2)
    gt = np.asarray(gt, dtype=np.float64).reshape(-1, 2)
    origin = np.asarray(origin, dtype=np.float64).reshape(1, 2)
    pred_depth = np.linalg.norm(pred - origin, axis=1)
    gt_depth = np.linalg.norm(gt - origin, axis=1)
    out = NNDSamples.empty()
    if len(gt) and not len(pred):
        out.unseen_gt_depth = _up32(gt_depth)
    if len(gt) and len(pred):
        d_acc, j = cKDTree(gt).query(pred)
        d_cov, i = cKDTree(pred).query(gt)
        out = NNDSamples(np.asarray(d_acc, dtype=np.float32), _up32(pred_depth), _up32(gt_depth[j]),
                         np.asarray(d_cov, dtype=np.float32), _up32(gt_depth), _up32(pred_depth[i]))
    return out


def _up32(x: np.ndarray) -> np.ndarray:
    """float64 (N,) -> the smallest float32 at or above each (a depth just past 2 m stays past it)."""
    f = np.asarray(x, dtype=np.float64).astype(np.float32)
    low = f.astype(np.float64) < x
    f[low] = np.nextafter(f[low], np.float32(np.inf))
    return f


@dataclass
class ZoneMetrics:
    """The docs/method.md 7 numbers of one sensor in one zone; None where no point was scored."""

    acc_mean: float | None
    acc_median: float | None
    acc_inlier: float | None
    acc_too_close: float | None
    acc_too_far: float | None
    cov_mean: float | None
    cov_median: float | None
    cov_inlier: float | None
    cov_too_close: float | None
    cov_too_far: float | None
    n_pred: int
    n_gt: int
    gt_unseen: float | None = None  # share of FoV-GT points at test points with no return

    def to_json(self) -> dict[str, float | int | None]:
        d = asdict(self)
        return {k: d[k] for k in METRIC_KEYS}


@dataclass
class SensorMetrics:
    """Zone name -> metrics of one sensor (or model)."""

    zones: dict[str, ZoneMetrics]

    def to_json(self) -> dict[str, dict[str, float | int | None]]:
        return {name: zm.to_json() for name, zm in self.zones.items()}


def _stats(dist: np.ndarray, too_close: np.ndarray, inlier_m: float) -> tuple[float | None, ...]:
    """mean, median, inlier share, too-close share, too-far share (shares of all points)."""
    if dist.size == 0:
        return (None,) * 5
    inl = dist < inlier_m
    close = ~inl & too_close
    far = ~inl & ~too_close
    n = dist.size
    return (float(dist.mean(dtype=np.float64)), float(np.median(dist)), inl.sum() / n, close.sum() / n, far.sum() / n)


def zone_metrics(
    samples: NNDSamples, zones: Sequence[Zone] = DEFAULT_ZONES, inlier_m: float = INLIER_M
) -> SensorMetrics:
    """Statistics of pooled NND samples in every zone."""
    out: dict[str, ZoneMetrics] = {}
    for z in zones:
        a = z.contains(samples.acc_gt_depth)
        c = z.contains(samples.cov_gt_depth)
        acc = _stats(samples.acc_dist[a], samples.acc_pred_depth[a] < samples.acc_gt_depth[a], inlier_m)
        cov = _stats(samples.cov_dist[c], samples.cov_pred_depth[c] < samples.cov_gt_depth[c], inlier_m)
        vals = [None if v is None else float(v) for v in acc + cov]
        n_unseen = int(z.contains(samples.unseen_gt_depth).sum())
        n_in_view = int(c.sum()) + n_unseen
        unseen = n_unseen / n_in_view if n_in_view else None
        out[z.name] = ZoneMetrics(*vals, n_pred=int(a.sum()), n_gt=int(c.sum()), gt_unseen=unseen)
    return SensorMetrics(out)


def _json_number(v: float) -> float | int:
    return int(v) if float(v).is_integer() else float(v)


def metrics_document(
    sensors: Mapping[str, SensorMetrics],
    zones: Sequence[Zone] = DEFAULT_ZONES,
    train: Mapping[str, Any] | None = None,
    gt: str | None = DEFAULT_GT,
    by_gt: Mapping[str, Mapping[str, SensorMetrics]] | None = None,
    safety: Mapping[str, Any] | None = None,
    warnings: Sequence[str] = (),
    inlier_m: float = INLIER_M,
    scoring: Mapping[str, int] | None = None,
) -> dict[str, Any]:
    """The metrics.json object of docs/method.md 7: gt, zones, inlier_m[, scoring], sensors[, by_gt][, train][, safety][, warnings].

    `sensors` are the metrics under protocol `gt`; `by_gt` (every protocol asked -> metrics, `gt`
    among them) is written only when it holds more than that one protocol. gt None (with no
    sensors) = a run without ground truth. `safety`: the exported map's planner-safety figures
    (evaluation/safety.py); `warnings`: one line each on why the map may not be trusted;
    `scoring`: what the figures depend on beyond the zones ({"n_rays": rays of each 360 deg scan,
    "test_points": positions scored}: 128 rays give a LiDAR accuracy twice 512's).
    """
    doc: dict[str, Any] = {
        "gt": gt,
        "zones": {z.name: [_json_number(z.lo), _json_number(z.hi)] for z in zones},
        "inlier_m": _json_number(inlier_m),  # acc_inlier / cov_inlier: the share of distances below it
    }
    if scoring is not None:
        doc["scoring"] = {k: int(v) for k, v in scoring.items()}
    doc["sensors"] = {name: m.to_json() for name, m in sensors.items()}
    if by_gt is not None and list(by_gt) != [gt]:
        if gt not in by_gt:
            raise ValueError(f"by_gt {list(by_gt)} lacks the document's protocol {gt!r}")
        doc["by_gt"] = {p: {"sensors": {n: m.to_json() for n, m in ms.items()}} for p, ms in by_gt.items()}
    if train is not None:
        doc["train"] = dict(train)
    if safety is not None:
        doc["safety"] = dict(safety)
    if warnings:
        doc["warnings"] = [str(w) for w in warnings]
    check_metrics_document(doc)
    return doc


def _check_sensors_block(sensors: Mapping[str, Any], zone_names: list[str], where: str) -> None:
    for sensor, per_zone in sensors.items():
        if list(per_zone) != zone_names:
            raise ValueError(f"{where}sensor {sensor!r} has zones {list(per_zone)}, expected {zone_names}")
        for zname, block in per_zone.items():
            if tuple(block) not in (METRIC_KEYS, LEGACY_METRIC_KEYS):
                raise ValueError(f"{where}{sensor}/{zname} keys {list(block)} != {list(METRIC_KEYS)}")
            for k, v in block.items():
                if k.startswith("n_"):
                    if not isinstance(v, int) or v < 0:
                        raise ValueError(f"{where}{sensor}/{zname}/{k} must be a non-negative int, got {v!r}")
                elif v is not None and not (isinstance(v, float | int) and math.isfinite(v)):
                    raise ValueError(f"{where}{sensor}/{zname}/{k} must be a finite number or null, got {v!r}")


def check_metrics_document(doc: Mapping[str, Any]) -> None:
    """Raise ValueError unless `doc` follows the docs/method.md 7 schema (finite numbers or null).

    Documents written before the ground-truth protocols (no "gt", no "gt_unseen") are accepted.
    """
    allowed = {"gt", "zones", "inlier_m", "scoring", "sensors", "by_gt", "train", "safety", "warnings"}
    if set(doc) - allowed or not {"zones", "sensors"} <= set(doc):
        raise ValueError(f"metrics document keys must be [gt,] zones, [inlier_m,] [scoring,] sensors[, by_gt]"
                         f"[, train][, safety][, warnings]; got {sorted(doc)}")
    scoring = doc.get("scoring", {})
    if not isinstance(scoring, Mapping) or not all(
            isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in scoring.values()):
        raise ValueError(f"metrics document scoring must map names to counts, got {scoring!r}")
    inlier = doc.get("inlier_m", INLIER_M)  # documents written before it: the paper's 0.1 m
    if isinstance(inlier, bool) or not isinstance(inlier, int | float) or not math.isfinite(inlier) or inlier <= 0:
        raise ValueError(f"metrics document inlier_m must be a positive number of metres, got {inlier!r}")
    if not isinstance(doc.get("warnings", []), list) or not all(isinstance(w, str) for w in doc.get("warnings", [])):
        raise ValueError(f"metrics document warnings must be a list of strings, got {doc.get('warnings')!r}")
    gt = doc.get("gt", DEFAULT_GT)
    if gt is None:  # no ground truth: nothing scored
        if doc["sensors"] or "by_gt" in doc:
            raise ValueError("metrics document gt null (no ground truth) must have empty sensors and no by_gt")
        return
    if gt not in GT_PROTOCOLS:
        raise ValueError(f"metrics document gt {gt!r}: expected one of {', '.join(GT_PROTOCOLS)}")
    zone_names = list(doc["zones"])
    for name, bounds in doc["zones"].items():
        if not (isinstance(bounds, list) and len(bounds) == 2):
            raise ValueError(f"zone {name!r} must be [lo, hi], got {bounds!r}")
    _check_sensors_block(doc["sensors"], zone_names, "")
    if "by_gt" in doc:
        by_gt = doc["by_gt"]
        if not isinstance(by_gt, Mapping) or gt not in by_gt:
            raise ValueError(f"by_gt must map every protocol asked (including gt {gt!r}) to {{'sensors': ...}}")
        for p, block in by_gt.items():
            if p not in GT_PROTOCOLS or not isinstance(block, Mapping) or set(block) != {"sensors"}:
                raise ValueError(f"by_gt[{p!r}] must be {{'sensors': ...}} of a protocol in {GT_PROTOCOLS}")
            _check_sensors_block(block["sensors"], zone_names, f"by_gt[{p!r}]: ")
        if by_gt[gt]["sensors"] != doc["sensors"]:
            raise ValueError(f"by_gt[{gt!r}] differs from the document's sensors (protocol {gt!r})")


def gt_protocols_of(doc: Mapping[str, Any]) -> list[str]:
    """The protocols a metrics document holds, its own ("gt") first."""
    gt = doc.get("gt", DEFAULT_GT)
    return [gt] + [p for p in doc.get("by_gt", {}) if p != gt]


def sensors_block(doc: Mapping[str, Any], gt: str | None = None) -> Mapping[str, Any]:
    """The "sensors" object of protocol `gt` (default: the document's own); KeyError naming the
    protocols present when the document lacks it."""
    own = doc.get("gt", DEFAULT_GT)
    if gt is None or gt == own:
        return doc["sensors"]
    if gt in doc.get("by_gt", {}):
        return doc["by_gt"][gt]["sensors"]
    raise KeyError(f"no metrics for ground truth {gt!r}; the document holds {gt_protocols_of(doc)}")


def sensor_metrics_from_json(doc: Mapping[str, Any], gt: str | None = None) -> dict[str, SensorMetrics]:
    """Inverse of `metrics_document` for the sensors block of protocol `gt` (default: the
    document's own), e.g. to aggregate saved runs; older blocks without gt_unseen read as None."""
    check_metrics_document(doc)
    return {
        name: SensorMetrics({z: ZoneMetrics(**{k: block[k] for k in METRIC_KEYS if k in block})
                             for z, block in per_zone.items()})
        for name, per_zone in sensors_block(doc, gt).items()
    }


@dataclass(frozen=True)
class RunMetrics:
    """A metrics.json read back, typed: the metrics of every protocol it holds (its own, `gt`,
    first) and its "train" block (steps, seconds, steps_per_s, ...; empty for `sensors` files)."""

    gt: str
    by_gt: dict[str, dict[str, SensorMetrics]]
    zones: dict[str, tuple[float, float]]  # zone name -> (lo, hi) GT depth in metres
    train: Mapping[str, Any]
    inlier_m: float = INLIER_M  # m: the inlier shares count distances below it

    @staticmethod
    def from_document(doc: Mapping[str, Any]) -> RunMetrics:
        """A metrics.json object (as written by `metrics_document`) -> RunMetrics; ValueError
        when it does not follow the schema."""
        check_metrics_document(doc)
        protocols = gt_protocols_of(doc)
        return RunMetrics(gt=protocols[0], by_gt={p: sensor_metrics_from_json(doc, p) for p in protocols},
                          zones={z: (float(lo), float(hi)) for z, (lo, hi) in doc["zones"].items()},
                          train=doc.get("train", {}), inlier_m=float(doc.get("inlier_m", INLIER_M)))

    def sensors(self, gt: str | None = None) -> dict[str, SensorMetrics]:
        """name -> SensorMetrics under protocol `gt` (default: the document's own); KeyError
        naming the protocols present when it lacks `gt`."""
        key = self.gt if gt is None else gt
        if key not in self.by_gt:
            raise KeyError(f"no metrics for ground truth {key!r}; the document holds {list(self.by_gt)}")
        return self.by_gt[key]


def read_metrics(path: str | Path) -> RunMetrics:
    """metrics.json -> RunMetrics; a file that does not follow the schema is a DataFormatError."""
    import json

    from virus_nerf.errors import DataFormatError

    path = Path(path)
    try:
        return RunMetrics.from_document(json.loads(path.read_text()))
    except (ValueError, TypeError, AttributeError, KeyError) as exc:
        raise DataFormatError(path, f"not a metrics document: {exc}") from None


def write_metrics_json(
    path: str | Path,
    sensors: Mapping[str, SensorMetrics],
    zones: Sequence[Zone] = DEFAULT_ZONES,
    train: Mapping[str, Any] | None = None,
    gt: str | None = DEFAULT_GT,
    by_gt: Mapping[str, Mapping[str, SensorMetrics]] | None = None,
    safety: Mapping[str, Any] | None = None,
    warnings: Sequence[str] = (),
    inlier_m: float = INLIER_M,
    scoring: Mapping[str, int] | None = None,
) -> dict[str, Any]:
    """Write metrics.json atomically; returns the written object."""
    doc = metrics_document(sensors, zones, train, gt=gt, by_gt=by_gt, safety=safety, warnings=warnings,
                           inlier_m=inlier_m, scoring=scoring)
    write_json_atomic(path, doc)
    return doc


def _fmt(v: float | int | None, width: int = 7) -> str:
    if v is None:
        return "-".rjust(width)
    if isinstance(v, int):
        return str(v).rjust(width)
    return f"{v:.3f}".rjust(width)


def format_table(sensors: Mapping[str, SensorMetrics], zones: Sequence[Zone] = DEFAULT_ZONES) -> str:
    """Compact text table: one row per sensor and zone; NND in metres, shares in [0, 1].

    `unseen` is gt_unseen: the share of in-view GT points at test points where the sensor
    returned nothing (left out of cov_*).
    """
    head = ("sensor", "zone", "acc_mean", "acc_med", "acc_inl", "cov_mean", "cov_med", "cov_inl", "unseen",
            "n_pred", "n_gt")
    widths = (8, 6, 8, 8, 8, 8, 8, 8, 7, 7, 7)
    lines = [" ".join(h.rjust(w) if i > 1 else h.ljust(w) for i, (h, w) in enumerate(zip(head, widths, strict=True)))]
    for name, m in sensors.items():
        for z in zones:
            zm = m.zones.get(z.name)
            if zm is None:
                continue
            vals = (zm.acc_mean, zm.acc_median, zm.acc_inlier, zm.cov_mean, zm.cov_median, zm.cov_inlier,
                    zm.gt_unseen, zm.n_pred, zm.n_gt)
            cells = [name.ljust(widths[0]), z.name.ljust(widths[1])]
            cells += [_fmt(v, w) for v, w in zip(vals, widths[2:], strict=True)]
            lines.append(" ".join(cells))
    return "\n".join(lines)


def mean_std(values: Iterable[float | None]) -> tuple[float | None, float | None]:
    """The one aggregation over runs (ablation, online, reports): mean and sample standard
    deviation (ddof=1) of the values that are not None; std 0 for a single value, (None, None)
    for none.

    ddof=1 because the runs are a small sample of seeds and the spread reported is an estimate
    of the seed-to-seed spread a user will see (the population std of 3 runs understates it by
    ~18 %).
    """
    v = np.asarray([x for x in values if x is not None], dtype=np.float64)
    if v.size == 0:
        return None, None
    return float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else 0.0
