"""Can a planner trust the map? The share of real obstacles that the exported 2D map marks free.

The paper's accuracy and coverage judge the NeRF's scans; a planner reads the map instead, and
what hurts it is an obstacle the map calls free. For every ground-truth obstacle pixel (the
LiDAR map's points within +-band of the camera height, drawn into the map's own raster) the map
is asked whether it marks that pixel free with no occupied or unknown pixel within `tolerance`
metres (so a wall placed a pixel or two off, inside the paper's 10 cm inlier distance, is not a
miss). Obstacle pixels are grouped by their distance to the robot's path (the training cameras'
positions): within 1 m, within 2 m, and all. Lower is safer; 0 means no known obstacle is free.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

SAFETY_ZONES_M = (1.0, 2.0, math.inf)  # obstacle distance to the robot's path
SAFETY_TOLERANCE_M = 0.1  # the paper's inlier distance


@dataclass(frozen=True)
class SafetyZone:
    within_m: float  # obstacle pixels at most this far from the path (inf = all)
    obstacles: int  # ground-truth obstacle pixels in the zone
    marked_free: int  # of them, free in the map with nothing but free within the tolerance

    @property
    def free_share(self) -> float | None:
        return self.marked_free / self.obstacles if self.obstacles else None


def obstacle_pixels(points_xy: np.ndarray, origin: tuple[float, float], resolution: float,
                    shape_hw: tuple[int, int]) -> np.ndarray:
    """(H, W) bool image (row 0 = largest y, the maps.occupancy raster): pixels holding a point."""
    h, w = shape_hw
    out = np.zeros((h, w), dtype=bool)
    ij = np.floor((np.asarray(points_xy, dtype=np.float64).reshape(-1, 2) - np.asarray(origin)) / resolution).astype(int)
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    out[h - 1 - ij[ok, 1], ij[ok, 0]] = True
    return out


def free_for_sure(image: np.ndarray, free_value: int, resolution: float, tolerance: float) -> np.ndarray:
    """(H, W) bool: free pixels whose every pixel within `tolerance` metres is free too."""
    from scipy.ndimage import binary_erosion

    free = np.asarray(image) == free_value
    r = int(math.floor(tolerance / resolution + 1e-9))
    if r <= 0:
        return free
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    disk = (xx * xx + yy * yy) <= r * r
    return binary_erosion(free, structure=disk, border_value=1)


def map_safety(image: np.ndarray, origin: tuple[float, float], resolution: float, obstacles_xy: np.ndarray,
               path_xy: np.ndarray, free_value: int = 254, zones: tuple[float, ...] = SAFETY_ZONES_M,
               tolerance: float = SAFETY_TOLERANCE_M) -> list[SafetyZone]:
    """Per zone, the ground-truth obstacle pixels and how many the map `image` marks free for sure.

    image (H, W) trinary map (maps.occupancy raster); obstacles_xy (K, 2) ground-truth points at
    camera height (m); path_xy (P, 2) the robot's camera positions (m).
    """
    from scipy.spatial import cKDTree

    h, w = np.asarray(image).shape
    obst = obstacle_pixels(obstacles_xy, origin, resolution, (h, w))
    rows, cols = np.nonzero(obst)
    centres = np.column_stack([origin[0] + (cols + 0.5) * resolution, origin[1] + (h - rows - 0.5) * resolution])
    path = np.asarray(path_xy, dtype=np.float64).reshape(-1, 2)
    dist = cKDTree(path).query(centres)[0] if len(path) and len(centres) else np.full(len(centres), np.inf)
    missed = free_for_sure(image, free_value, resolution, tolerance)[rows, cols]
    return [SafetyZone(float(z), int((dist <= z).sum()), int((missed & (dist <= z)).sum())) for z in zones]


def safety_document(zones: list[SafetyZone], observed: float, gt: str, resolution: float) -> dict:
    """metrics.json's "safety" block."""
    return {
        "gt": gt,
        "resolution": resolution,
        "tolerance_m": SAFETY_TOLERANCE_M,
        "observed": round(float(observed), 4),
        "zones": {("all" if math.isinf(z.within_m) else f"{z.within_m:g}m"): {
            "obstacles": z.obstacles, "marked_free": z.marked_free,
            "free_share": None if z.free_share is None else round(z.free_share, 4)} for z in zones},
    }


def safety_line(doc: dict) -> str:
    """One line for the table: obstacles marked free per zone and the observed share."""
    parts = [f"{name} " + ("-" if b["free_share"] is None else f"{b['free_share']:.1%}")
             for name, b in doc["zones"].items()]
    return (f"map safety ({doc['gt']} ground truth): obstacles the map marks free: {', '.join(parts)} "
            f"(of obstacles within that distance of the path); map observed {doc['observed']:.1%}")
