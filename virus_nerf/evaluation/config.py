"""What the evaluation scores and against which ground truth (`EvaluationConfig`, its zones and
protocols), apart from the evaluation so that a run's config, its flags or `--help` read them
without loading scipy, numba or torch."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

GT_PROTOCOLS = ("map", "exact", "paper")  # ground-truth protocols (docs/method.md 6.7; evaluation.gt)
GtProtocol = Literal["map", "exact", "paper"]
SENSOR_NAMES = ("LiDAR", "USS", "IRS")
INLIER_M = 0.1


@dataclass(frozen=True)
class Zone:
    """Distance zone [lo, hi] metres, both ends included."""

    name: str
    lo: float
    hi: float

    def contains(self, depth: np.ndarray) -> np.ndarray:
        depth = np.asarray(depth, dtype=np.float64)
        return (depth >= self.lo) & (depth <= self.hi)


DEFAULT_ZONES: tuple[Zone, ...] = (Zone("zone1", 0.0, 1.0), Zone("zone2", 0.0, 2.0), Zone("zone3", 0.0, 100.0))


def check_gt_protocols(protocols: object, name: str = "evaluation.gt") -> tuple[str, ...]:
    """A tuple of distinct known protocols, or a ValueError naming `name`. Empty = no ground
    truth (`--gt none`: a robot without a LiDAR map trains and maps, nothing is scored)."""
    ok = isinstance(protocols, tuple | list) and all(p in GT_PROTOCOLS for p in protocols)
    if not ok or len(set(protocols)) != len(protocols):  # type: ignore[arg-type]
        raise ValueError(f"{name} {protocols!r}: expected distinct protocols out of {', '.join(GT_PROTOCOLS)}")
    return tuple(protocols)  # type: ignore[arg-type]


def parse_gt_flag(text: str, flag: str = "--gt", scores: bool = False) -> tuple[str, ...]:
    """`--gt map,exact` -> ("map", "exact"), `--gt none` -> () unless the command `scores` (it
    exists to compare with a ground truth); a one-line UsageError naming the flag otherwise."""
    from virus_nerf.errors import UsageError

    if str(text).strip() == "none":
        if scores:
            raise UsageError(f"{flag} none: nothing to score; give {flag} map, exact or paper (comma-separated)")
        return ()
    names = tuple(s.strip() for s in str(text).split(","))
    unknown = [s for s in names if s not in GT_PROTOCOLS]
    if unknown or len(set(names)) != len(names):
        what = f"unknown protocol {unknown[0]!r}" if unknown else "a protocol named twice"
        raise UsageError(f"{flag} {text!r}: {what}; expected one or more of {','.join(GT_PROTOCOLS)}, "
                         f"comma-separated (e.g. map,exact){'' if scores else ', or none'}")
    return names


@dataclass(frozen=True)
class EvaluationConfig:
    """Evaluation settings (metres, degrees where named)."""

    n_rays: int = 512  # rays of the 360 deg GT and model scans
    height_band_m: float = 0.05  # +- around the camera height for map slice, LiDAR and IRS
    raster_res_m: float = 0.02  # GT occupancy raster cell (<= 0.02, docs/method.md 6.2)
    map_voxel_m: float = 0.03  # footprint drawn for each map point (its voxel size)
    lidar_angle_range_deg: float = 360.0  # LiDAR horizontal range centred on the robot heading
    uss_arc_step_deg: float = 1.0  # spacing of the points on the USS arc
    inlier_m: float = INLIER_M  # m: a scan point closer than this to the ground truth is an inlier
    zones: tuple[Zone, ...] = DEFAULT_ZONES
    sensors: tuple[str, ...] = SENSOR_NAMES  # which instantaneous sensors to score
    gt: tuple[GtProtocol, ...] = ("map",)  # ground-truth protocols (docs/method.md 6.7); the first is the primary;
    # () = none: nothing is scored (a recording without a LiDAR map)

    def __post_init__(self) -> None:
        check_gt_protocols(self.gt)
