"""2D scans and horizontal fields of view (docs/method.md 6.3, 6.5, 9.9): the scan geometry
shared by the map (maps/extract.py), the engine's scans and the evaluation.

A scan is a set of 2D points in the world frame (x, y in metres) seen from one scan origin. A
sensor's field of view is a union of horizontal sectors; the ground truth used to score that
sensor keeps only the points inside it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True, eq=False)
class Sector:
    """A horizontal wedge: apex (2,) m, heading (rad, about world z), half opening angle (rad).

    A half angle >= pi is the full circle.
    """

    apex: np.ndarray  # (2,) m
    heading: float  # rad
    half_angle: float  # rad

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(K, 2) points -> (K,) bool, inside the wedge (boundary included)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if self.half_angle >= np.pi:
            return np.ones(len(points), dtype=bool)
        d = points - np.asarray(self.apex, dtype=np.float64)[None, :]
        ang = np.arctan2(d[:, 1], d[:, 0]) - self.heading
        ang = (ang + np.pi) % (2 * np.pi) - np.pi  # wrap to [-pi, pi)
        return np.abs(ang) <= self.half_angle + 1e-12


@dataclass(frozen=True, eq=False)
class FieldOfView:
    """Union of sectors; an empty union sees nothing."""

    sectors: tuple[Sector, ...]

    @staticmethod
    def full(apex: np.ndarray) -> FieldOfView:
        return FieldOfView((Sector(np.asarray(apex, dtype=np.float64), 0.0, np.pi),))

    def contains(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        inside = np.zeros(len(points), dtype=bool)
        for s in self.sectors:
            inside |= s.contains(points)
        return inside


@dataclass
class Scan2D:
    """One sensor's (or model's, or the ground truth's) scan of one test point."""

    name: str  # "GT", "LiDAR", "USS", "IRS", "NeRF", ...
    points: np.ndarray  # (M, 2) world x, y in metres; never a placeholder at the origin
    origin: np.ndarray  # (2,) the test point's scan origin, metres
    fov: FieldOfView  # where this scan could have seen something
    extra: dict[str, np.ndarray] = field(default_factory=dict)  # e.g. "z": (M,) heights, "stack": (M,)

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 2)
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(2)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def depths(self) -> np.ndarray:
        """(M,) distance of each point from the scan origin, metres."""
        return np.linalg.norm(self.points - self.origin[None, :], axis=1)


@runtime_checkable
class RangeModel(Protocol):
    """Anything that can render ray lengths: the NeRF (docs/method.md 6.3) or an analytic test scene."""

    def ranges(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """origins (N, 3) m, unit directions (N, 3) -> (N,) distance along each ray in metres,
        NaN where the ray hits nothing."""
        ...


def scan_angles(n_rays: int) -> np.ndarray:
    """(n_rays,) horizontal ray angles (rad, world frame), evenly over 360 deg from +x."""
    if n_rays < 1:
        raise ValueError(f"n_rays must be >= 1, got {n_rays}")
    return np.arange(n_rays) * (2 * np.pi / n_rays)


def horizontal_directions(n_rays: int, first_angle: float = 0.0) -> np.ndarray:
    """(n_rays, 3) unit directions in the horizontal plane, the same for GT and model scans;
    turned by `first_angle` rad (the map's rays below the band point between the band's)."""
    a = scan_angles(n_rays) + first_angle
    return np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)


def points_from_ranges(origin_xy: np.ndarray, directions: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """Hit points (M, 2) of rays with a finite positive range; misses are dropped (docs/method.md 9.8)."""
    r = np.asarray(ranges, dtype=np.float64).reshape(-1)
    ok = np.isfinite(r) & (r > 0)
    return np.asarray(origin_xy, dtype=np.float64)[None, :2] + directions[ok, :2] * r[ok, None]


def scan_rays(positions: np.ndarray, n_rays: int, heights: tuple[float, ...] = (0.0,),
              first_angle: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The rays of 360 deg horizontal scans from camera `positions` (P, 3) m: origins (P n_rays, 3)
    and unit directions (P n_rays, 3), position by position; within a scan, ray i points
    `first_angle` + i 2 pi / n_rays rad from +x and starts heights[i % len(heights)] m above its
    position (a height band at the cost of one plane)."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    dirs = horizontal_directions(n_rays, first_angle)  # (n, 3)
    offsets = np.zeros((n_rays, 3))
    offsets[:, 2] = np.asarray(heights, dtype=np.float64)[np.arange(n_rays) % len(heights)]
    origins = (positions[:, None, :] + offsets[None, :, :]).reshape(-1, 3)
    return origins, np.tile(dirs, (len(positions), 1))


def scan_ranges(model: RangeModel, position: np.ndarray, n_rays: int,
                heights: tuple[float, ...] = (0.0,)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A model's 360 deg horizontal scan from `position` (3,) m: ray origins (N, 3), unit
    directions (N, 3) and ranges (N,) float64 m (NaN: no hit); the same rays for every consumer
    (maps, exports, the Mapper's scans, the evaluation). `heights` (m): ray i starts
    heights[i % len(heights)] above `position` (`scan_rays`; the default is the plane itself)."""
    origins, dirs = scan_rays(position, n_rays, heights)
    return origins, dirs, np.asarray(model.ranges(origins, dirs), dtype=np.float64).reshape(-1)
