"""The evaluation of one recording (docs/method.md 6): GT scans, sensor scans, model scans, metrics.

Reusable by the trainer: build the ground truth once (`build_ground_truth`) and pass it to
`evaluate` at every evaluation interval together with the model(s); sensor scans can be left
out (`sensors=()`) when only a model is scored.

Ground truth under several protocols (docs/method.md 6.7, `EvaluationConfig.gt`): every scan is made
once per test point and scored against each protocol's GT; the first protocol is the primary
one (`EvaluationResult.metrics`, the plots' scan maps, the trainer's metric-vs-time curve), the
others are in `EvaluationResult.by_gt`. Under `paper` the LiDAR is scored over the authors'
horizontal range of the room (`gt.PAPER_ROOMS`) instead of `lidar_angle_range_deg`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from virus_nerf.data.ethz import Recording
from virus_nerf.errors import DataFormatError
from virus_nerf.evaluation.config import (  # noqa: F401  (importable from here as before)
    DEFAULT_ZONES,
    INLIER_M,
    SENSOR_NAMES,
    EvaluationConfig,
    GtProtocol,
    Zone,
    check_gt_protocols,
    parse_gt_flag,
)
from virus_nerf.evaluation.gt import (
    GT_DESCRIPTIONS,
    GT_PROTOCOLS,
    GroundTruth,
    MapSlice,
    exact_gt_scan,
    gt_scan,
    paper_extent,
    paper_gt_scan,
    paper_lidar_deg,
)
from virus_nerf.evaluation.metrics import (
    NNDSamples,
    SensorMetrics,
    format_table,
    metrics_document,
    nnd_samples,
    zone_metrics,
)
from virus_nerf.evaluation.scans import model_scan
from virus_nerf.evaluation.sensor_scans import irs_scan_2d, lidar_scan_2d, uss_scan_2d
from virus_nerf.evaluation.testpoints import TestPoint, make_test_points
from virus_nerf.maps.scans import RangeModel, Scan2D

SCENE_FILE = "scene.json"  # the simulator's exact scene, in the room folder


@dataclass
class PointGroundTruth:
    """The ground truth of one test point under every protocol asked (the first is the primary).

    `scan`, `ranges` and `slice_xy` are the primary protocol's.
    """

    test_point: TestPoint
    by_protocol: dict[str, GroundTruth]

    @property
    def primary(self) -> GroundTruth:
        return next(iter(self.by_protocol.values()))

    @property
    def scan(self) -> Scan2D:
        return self.primary.scan

    @property
    def ranges(self) -> np.ndarray:
        return self.primary.ranges

    @property
    def slice_xy(self) -> np.ndarray:
        return self.primary.slice_xy

    @staticmethod
    def of(gt: PointGroundTruth | GroundTruth) -> PointGroundTruth:
        return gt if isinstance(gt, PointGroundTruth) else PointGroundTruth(gt.test_point, {gt.protocol: gt})


@dataclass
class TestPointScans:
    """Everything scanned at one test point (the scans and GT of the primary protocol)."""

    __test__ = False  # not a pytest test class

    ground_truth: GroundTruth
    scans: dict[str, Scan2D]  # sensor/model name -> scan
    all_gt: dict[str, GroundTruth] = field(default_factory=dict)  # every protocol's GT (plots)

    @property
    def test_point(self) -> TestPoint:
        return self.ground_truth.test_point

    def fov_gt(self, name: str) -> Scan2D:
        """The GT restricted to scan `name`'s field of view (docs/method.md 6.5)."""
        return fov_gt(self.ground_truth, self.scans[name])


def fov_gt(gt: GroundTruth, scan: Scan2D) -> Scan2D:
    """The GT points inside `scan`'s field of view (docs/method.md 6.5)."""
    keep = scan.fov.contains(gt.scan.points)
    return Scan2D(f"GT[{scan.name}]", gt.scan.points[keep], gt.scan.origin, scan.fov)


@dataclass
class EvaluationResult:
    config: EvaluationConfig
    points: list[TestPointScans]  # the test points whose scans were kept (all, or `evaluate`'s keep_scans)
    metrics: dict[str, SensorMetrics]  # name -> per-zone metrics, pooled over test points (protocol `gt`)
    gt: str = "map"  # the protocol of `metrics`
    by_gt: dict[str, dict[str, SensorMetrics]] = field(default_factory=dict)  # every protocol -> metrics
    n_points: int | None = None  # test points scored (None: len(points))

    def __post_init__(self) -> None:
        if self.n_points is None:
            self.n_points = len(self.points)

    def document(self, train: Mapping[str, Any] | None = None, **extra: Any) -> dict[str, Any]:
        """extra: safety, warnings (metrics_document)."""
        return metrics_document(self.metrics, self.config.zones, train, gt=self.gt, by_gt=self.by_gt or None,
                                inlier_m=self.config.inlier_m, scoring=self.scoring(), **extra)

    def scoring(self) -> dict[str, int]:
        """What the figures depend on beyond the zones: the scans' rays, the positions scored."""
        return {"n_rays": int(self.config.n_rays), "test_points": int(self.n_points)}

    def write_json(self, path: str | Path, train: Mapping[str, Any] | None = None, **extra: Any) -> dict[str, Any]:
        """metrics.json (`document`), written atomically; returns the written object."""
        from virus_nerf.utils.io import write_json_atomic

        doc = self.document(train, **extra)
        write_json_atomic(path, doc)
        return doc

    def table(self) -> str:
        """The metrics table of every protocol, each under a line naming its ground truth."""
        by_gt = self.by_gt or {self.gt: self.metrics}
        zones = ", ".join(f"{z.name} {z.lo:g}-{z.hi:g} m" for z in self.config.zones)
        return "\n".join(f"ground truth: {p} ({GT_DESCRIPTIONS[p]}); distances in metres, shares in [0, 1], "
                         f"inliers < {self.config.inlier_m:g} m; {zones}\n"
                         + format_table(m, self.config.zones)
                         for p, m in by_gt.items())


def scene_path(recording: Recording) -> Path:
    return recording.room_dir / SCENE_FILE


def load_exact_scene(recording: Recording):
    """The simulator's exact scene of a recording; a DataFormatError naming the file if it has none."""
    from virus_nerf.sim.scene import Scene

    path = scene_path(recording)
    if not path.is_file():
        raise DataFormatError(path, "not found: ground truth 'exact' (--gt exact) casts into the simulator's exact "
                                    "scene, which only simulated recordings have; expected --gt map or paper here")
    return Scene.load(path)


LIDAR_OWN_MAP = ("the LiDAR map of this imported bag was built from the same LiDAR scans: the LiDAR row "
                 "scores their consistency with their own map, not accuracy")


def lidar_scored_against_own_map(recording: Recording) -> bool:
    """True for a recording `import-bag` wrote with a map (it builds the map from the same scans)."""
    from virus_nerf.data.bags.report import REPORT_NAME

    return recording.map_path is not None and (recording.root / REPORT_NAME).is_file()


def check_ground_truth_inputs(recording: Recording, protocols: Sequence[str]) -> None:
    """Fail now, not after training, when a protocol lacks its input (the map, scene.json)."""
    if any(p in ("map", "paper") for p in protocols):
        recording.lidar_map()
    if "exact" in protocols:
        load_exact_scene(recording)


def protocol_ground_truth(
    recording: Recording, protocol: str, config: EvaluationConfig, test_points: Sequence[TestPoint]
) -> list[GroundTruth]:
    """GT scans of `test_points` under one protocol (docs/method.md 6.7)."""
    if protocol == "map":
        cloud = recording.lidar_map()
        return [gt_scan(cloud, tp, config.n_rays, config.height_band_m, config.raster_res_m, config.map_voxel_m)
                for tp in test_points]
    if protocol == "exact":
        scene = load_exact_scene(recording)
        cloud = recording.lidar_map() if recording.map_path is not None else None
        return [exact_gt_scan(scene, tp, config.n_rays,
                              None if cloud is None else MapSlice(cloud, tp.height, config.height_band_m))
                for tp in test_points]
    if protocol == "paper":
        cloud = recording.lidar_map()
        if not test_points:
            return []
        extent = paper_extent(recording.room, cloud, real_recording=not scene_path(recording).is_file())
        height = float(np.mean([tp.height for tp in test_points]))
        lidar_deg = paper_lidar_deg(recording.room)
        return [paper_gt_scan(cloud, tp, extent, height, config.n_rays, config.height_band_m, lidar_deg)
                for tp in test_points]
    raise ValueError(f"unknown ground-truth protocol {protocol!r}; expected one of {GT_PROTOCOLS}")


def build_ground_truth(
    recording: Recording, config: EvaluationConfig = EvaluationConfig(), test_points: Sequence[TestPoint] | None = None
) -> list[PointGroundTruth]:
    """GT scans of every test point under every protocol of `config.gt` (raises DataFormatError
    without the LiDAR map for map/paper, without scene.json for exact)."""
    tps = list(test_points) if test_points is not None else make_test_points(recording)
    per = {p: protocol_ground_truth(recording, p, config, tps) for p in config.gt}
    return [PointGroundTruth(tp, {p: per[p][k] for p in config.gt}) for k, tp in enumerate(tps)]


def sensor_scan(recording: Recording, tp: TestPoint, name: str, config: EvaluationConfig,
                lidar_deg: tuple[float, float] | None = None) -> Scan2D:
    if name == "LiDAR":
        return lidar_scan_2d(recording, tp, config.height_band_m, config.lidar_angle_range_deg, angles_deg=lidar_deg)
    if name == "USS":
        return uss_scan_2d(recording, tp, config.uss_arc_step_deg)
    if name == "IRS":
        return irs_scan_2d(recording, tp, config.height_band_m)
    raise ValueError(f"unknown sensor {name!r}; expected one of {SENSOR_NAMES}")


def evaluate(
    recording: Recording,
    models: Mapping[str, RangeModel] | None = None,
    config: EvaluationConfig = EvaluationConfig(),
    ground_truth: Sequence[PointGroundTruth | GroundTruth] | None = None,
    keep_scans: int | None = None,
) -> EvaluationResult:
    """Scan every test point with the configured sensors and the given models; score them
    against the ground truth of every protocol (given, or built for `config.gt`).

    keep_scans: None keeps every test point's scans in `points`; k keeps those of k test points
    evenly spread (`spread_indices`, the ones the plots draw). A long drive's thousands of test
    points are scored all the same; only their scans are not held (~70 KB a point, D59).
    """
    if ground_truth is not None:
        gts = [PointGroundTruth.of(g) for g in ground_truth]
    else:
        gts = build_ground_truth(recording, config)
    protocols = list(gts[0].by_protocol) if gts else list(config.gt)
    names = list(config.sensors) + list(models or {})
    if len(set(names)) != len(names):
        raise ValueError(f"model names must differ from sensor names: {names}")
    per_point: list[TestPointScans] = []
    samples: dict[str, dict[str, list[NNDSamples]]] = {p: {n: [] for n in names} for p in protocols}
    kept = set(spread_indices(len(gts), keep_scans).tolist())  # None: every point
    for i, pg in enumerate(gts):
        tp = pg.test_point
        if list(pg.by_protocol) != protocols:
            raise ValueError(f"every test point needs the same protocols {protocols}, got {list(pg.by_protocol)}")
        scans = {s: sensor_scan(recording, tp, s, config) for s in config.sensors}
        for name, model in (models or {}).items():
            scans[name] = model_scan(model, tp, config.n_rays, name=name)
        primary_scans = scans
        for k, (p, gt) in enumerate(pg.by_protocol.items()):
            own = scans
            if gt.lidar_deg is not None and "LiDAR" in scans:
                own = {**scans, "LiDAR": sensor_scan(recording, tp, "LiDAR", config, lidar_deg=gt.lidar_deg)}
            for name, scan in own.items():
                samples[p][name].append(nnd_samples(scan.points, fov_gt(gt, scan).points, tp.origin_xy))
            if k == 0:
                primary_scans = own
        if i in kept:
            per_point.append(TestPointScans(ground_truth=pg.primary, scans=primary_scans, all_gt=dict(pg.by_protocol)))
    by_gt: dict[str, dict[str, SensorMetrics]] = {p: {} for p in protocols}
    for p, per in samples.items():
        for name in list(per):  # one sensor's pool at a time, its per-point parts dropped first (D63)
            by_gt[p][name] = zone_metrics(NNDSamples.concat(per.pop(name)), config.zones, config.inlier_m)
    first = protocols[0]
    return EvaluationResult(config=config, points=per_point, metrics=by_gt[first], gt=first, by_gt=by_gt,
                            n_points=len(gts))


def spread_indices(n: int, k: int | None) -> np.ndarray:
    """Indices of k of n items evenly spread, first and last included (all n when k is None or
    k >= n): the test points whose scans are kept and drawn."""
    if k is None or k >= n:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max(k, 0)).astype(int))
