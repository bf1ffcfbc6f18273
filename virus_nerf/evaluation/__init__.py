"""2D scan evaluation (docs/method.md 6): GT scans from the LiDAR map, sensor and model scans, NND metrics.

Plots (matplotlib) and the `sensors` command live in `plots` and `command` and are imported
on demand, so importing this package stays light.
"""

from virus_nerf.evaluation.evaluate import (
    SENSOR_NAMES,
    EvaluationConfig,
    EvaluationResult,
    PointGroundTruth,
    TestPointScans,
    build_ground_truth,
    evaluate,
    parse_gt_flag,
)
from virus_nerf.evaluation.gt import (
    GT_PROTOCOLS,
    PAPER_ROOMS,
    GroundTruth,
    MapSlice,
    Raster2D,
    SquareExtent,
    cast_rays,
    exact_gt_scan,
    gt_scan,
    height_slice,
    paper_cast,
    paper_gt_scan,
    paper_raster,
    rasterise,
)
from virus_nerf.evaluation.metrics import (
    DEFAULT_ZONES,
    METRIC_KEYS,
    NNDSamples,
    SensorMetrics,
    Zone,
    ZoneMetrics,
    check_metrics_document,
    format_table,
    gt_protocols_of,
    mean_std,
    metrics_document,
    nnd_samples,
    sensor_metrics_from_json,
    sensors_block,
    write_metrics_json,
    zone_metrics,
)
from virus_nerf.evaluation.scans import model_scan
from virus_nerf.evaluation.sensor_scans import irs_scan_2d, lidar_scan_2d, uss_scan_2d
from virus_nerf.evaluation.testpoints import TestPoint, make_test_points
from virus_nerf.maps.scans import (
    FieldOfView,
    RangeModel,
    Scan2D,
    Sector,
    horizontal_directions,
    scan_angles,
)

__all__ = [
    "DEFAULT_ZONES", "GT_PROTOCOLS", "METRIC_KEYS", "PAPER_ROOMS", "SENSOR_NAMES",
    "EvaluationConfig", "EvaluationResult", "FieldOfView", "GroundTruth", "MapSlice",
    "NNDSamples", "PointGroundTruth", "RangeModel", "Raster2D", "Scan2D", "Sector", "SensorMetrics",
    "SquareExtent", "TestPoint", "TestPointScans", "Zone", "ZoneMetrics",
    "mean_std", "build_ground_truth", "cast_rays", "check_metrics_document", "evaluate",
    "exact_gt_scan", "format_table", "gt_protocols_of", "gt_scan", "height_slice", "horizontal_directions",
    "irs_scan_2d", "lidar_scan_2d", "make_test_points", "metrics_document", "model_scan", "nnd_samples",
    "paper_cast", "paper_gt_scan", "paper_raster", "parse_gt_flag", "rasterise", "scan_angles",
    "sensor_metrics_from_json", "sensors_block", "uss_scan_2d", "write_metrics_json", "zone_metrics",
]
