"""The evaluation of one recording (design 6): GT scans, sensor scans, model scans, metrics.

Reusable by the trainer: build the ground truth once (`build_ground_truth`) and pass it to
`evaluate` at every evaluation interval together with the model(s); sensor scans can be left
out (`sensors=()`) when only a model is scored.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from virus_nerf.data.ethz import Recording
from virus_nerf.evaluation.gt import GroundTruth, gt_scan
from virus_nerf.evaluation.metrics import (
    DEFAULT_ZONES,
    INLIER_M,
    NNDSamples,
    SensorMetrics,
    Zone,
    format_table,
    metrics_document,
    nnd_samples,
    write_metrics_json,
    zone_metrics,
)
from virus_nerf.evaluation.scans import RangeModel, Scan2D, model_scan
from virus_nerf.evaluation.sensor_scans import irs_scan_2d, lidar_scan_2d, uss_scan_2d
from virus_nerf.evaluation.testpoints import TestPoint, make_test_points

SENSOR_NAMES = ("LiDAR", "USS", "IRS")


@dataclass(frozen=True)
class EvaluationConfig:
    """Evaluation settings (metres, degrees where named)."""

    n_rays: int = 512  # rays of the 360 deg GT and model scans
    height_band_m: float = 0.05  # +- around the camera height for map slice, LiDAR and IRS
    raster_res_m: float = 0.02  # GT occupancy raster cell (<= 0.02, design 6.2)
    map_voxel_m: float = 0.03  # footprint drawn for each map point (its voxel size)
    lidar_angle_range_deg: float = 360.0  # LiDAR horizontal range centred on the robot heading
    uss_arc_step_deg: float = 1.0  # spacing of the points on the USS arc
    inlier_m: float = INLIER_M
    zones: tuple[Zone, ...] = DEFAULT_ZONES
    sensors: tuple[str, ...] = SENSOR_NAMES  # which instantaneous sensors to score


@dataclass
class TestPointScans:
    """Everything scanned at one test point."""

    __test__ = False  # not a pytest test class

    ground_truth: GroundTruth
    scans: dict[str, Scan2D]  # sensor/model name -> scan

    @property
    def test_point(self) -> TestPoint:
        return self.ground_truth.test_point

    def fov_gt(self, name: str) -> Scan2D:
        """The GT restricted to scan `name`'s field of view (design 6.5)."""
        scan = self.scans[name]
        gt = self.ground_truth.scan
        keep = scan.fov.contains(gt.points)
        return Scan2D(f"GT[{name}]", gt.points[keep], gt.origin, scan.fov)


@dataclass
class EvaluationResult:
    config: EvaluationConfig
    points: list[TestPointScans]
    metrics: dict[str, SensorMetrics]  # name -> per-zone metrics, pooled over test points
    samples: dict[str, NNDSamples] = field(repr=False, default_factory=dict)

    def document(self, train: Mapping[str, Any] | None = None) -> dict[str, Any]:
        return metrics_document(self.metrics, self.config.zones, train)

    def write_json(self, path: str | Path, train: Mapping[str, Any] | None = None) -> dict[str, Any]:
        return write_metrics_json(path, self.metrics, self.config.zones, train)

    def table(self) -> str:
        return format_table(self.metrics, self.config.zones)


def build_ground_truth(
    recording: Recording, config: EvaluationConfig = EvaluationConfig(), test_points: Sequence[TestPoint] | None = None
) -> list[GroundTruth]:
    """GT scans of every test point (reads the LiDAR map; raises DataFormatError without one)."""
    tps = list(test_points) if test_points is not None else make_test_points(recording)
    cloud = recording.lidar_map()
    return [
        gt_scan(cloud, tp, config.n_rays, config.height_band_m, config.raster_res_m, config.map_voxel_m)
        for tp in tps
    ]


def sensor_scan(recording: Recording, tp: TestPoint, name: str, config: EvaluationConfig) -> Scan2D:
    if name == "LiDAR":
        return lidar_scan_2d(recording, tp, config.height_band_m, config.lidar_angle_range_deg)
    if name == "USS":
        return uss_scan_2d(recording, tp, config.uss_arc_step_deg)
    if name == "IRS":
        return irs_scan_2d(recording, tp, config.height_band_m)
    raise ValueError(f"unknown sensor {name!r}; expected one of {SENSOR_NAMES}")


def evaluate(
    recording: Recording,
    models: Mapping[str, RangeModel] | None = None,
    config: EvaluationConfig = EvaluationConfig(),
    ground_truth: Sequence[GroundTruth] | None = None,
) -> EvaluationResult:
    """Scan every test point with the configured sensors and the given models; score them."""
    gts = list(ground_truth) if ground_truth is not None else build_ground_truth(recording, config)
    names = list(config.sensors) + list(models or {})
    if len(set(names)) != len(names):
        raise ValueError(f"model names must differ from sensor names: {names}")
    per_point: list[TestPointScans] = []
    samples: dict[str, list[NNDSamples]] = {n: [] for n in names}
    for gt in gts:
        tp = gt.test_point
        scans = {s: sensor_scan(recording, tp, s, config) for s in config.sensors}
        for name, model in (models or {}).items():
            scans[name] = model_scan(model, tp, config.n_rays, name=name)
        tps = TestPointScans(ground_truth=gt, scans=scans)
        for name, scan in scans.items():
            samples[name].append(nnd_samples(scan.points, tps.fov_gt(name).points, tp.origin_xy))
        per_point.append(tps)
    pooled = {n: NNDSamples.concat(v) for n, v in samples.items()}
    metrics = {n: zone_metrics(s, config.zones, config.inlier_m) for n, s in pooled.items()}
    return EvaluationResult(config=config, points=per_point, metrics=metrics, samples=pooled)
