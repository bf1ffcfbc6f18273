"""Ground-truth 2D scans from the LiDAR map (design 6.2).

The map is a cloud of 3 cm voxel centres. Points within +-band of the camera height are drawn
into a 2D occupancy raster (<= 2 cm cells), each point as its voxel's square footprint so that
a wall of voxel centres 3 cm apart has no gaps rays could leak through. Horizontal rays from
the scan origin are traversed cell by cell (Amanatides-Woo DDA, vectorised over rays): the
first occupied cell gives the hit, at the exact distance where the ray enters that cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from virus_nerf.evaluation.scans import FieldOfView, Scan2D, horizontal_directions, scan_angles
from virus_nerf.evaluation.testpoints import TestPoint


@dataclass
class Raster2D:
    """Boolean occupancy raster; cell (i, j) spans lo + [i, i+1) * res in x and [j, j+1) * res in y."""

    occupied: np.ndarray  # (nx, ny) bool
    lo: np.ndarray  # (2,) m, corner of cell (0, 0)
    res: float  # m, cell edge

    @property
    def shape(self) -> tuple[int, int]:
        return self.occupied.shape  # type: ignore[return-value]

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """(K, 2) points -> (K, 2) int cell indices (may be outside the raster)."""
        return np.floor((np.asarray(xy, dtype=np.float64) - self.lo) / self.res).astype(np.int64)


def height_slice(points: np.ndarray, height: float, band: float = 0.05) -> np.ndarray:
    """Map points (P, 3) with |z - height| <= band -> their (K, 2) x, y."""
    pts = np.asarray(points)
    keep = np.abs(pts[:, 2].astype(np.float64) - height) <= band
    return pts[keep, :2].astype(np.float64)


def rasterise(
    xy: np.ndarray,
    res: float = 0.02,
    footprint: float = 0.03,
    include: np.ndarray | None = None,
    margin: float = 0.1,
) -> Raster2D:
    """Occupancy raster of 2D points, each drawn as a footprint x footprint square.

    A cell is occupied when its centre lies inside some point's square (a footprint of 0 marks
    only the cell containing the point). `include` (2,) is a point the raster must cover
    (the scan origin), so rays always start inside it.
    """
    if res <= 0:
        raise ValueError(f"raster resolution must be positive, got {res}")
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    corners = [xy] if len(xy) else []
    if include is not None:
        corners.append(np.asarray(include, dtype=np.float64).reshape(-1, 2))
    if not corners:
        return Raster2D(np.zeros((1, 1), dtype=bool), np.zeros(2), res)
    allpts = np.concatenate(corners)
    lo = allpts.min(axis=0) - footprint / 2 - margin
    hi = allpts.max(axis=0) + footprint / 2 + margin
    shape = np.maximum(np.ceil((hi - lo) / res).astype(np.int64), 1)
    occ = np.zeros(tuple(shape), dtype=bool)
    if len(xy):
        h = footprint / 2
        if h <= 0:
            idx = np.floor((xy - lo) / res).astype(np.int64)
            occ[idx[:, 0], idx[:, 1]] = True
        else:
            # cells whose centre (lo + (i + 0.5) res) lies in [c - h, c + h]
            first = np.ceil((xy - h - lo) / res - 0.5 - 1e-9).astype(np.int64)  # (K, 2)
            last = np.floor((xy + h - lo) / res - 0.5 + 1e-9).astype(np.int64)  # (K, 2)
            span = int((last - first).max()) + 1
            for di in range(span):
                for dj in range(span):
                    i = first[:, 0] + di
                    j = first[:, 1] + dj
                    ok = (i <= last[:, 0]) & (j <= last[:, 1])
                    occ[np.clip(i[ok], 0, shape[0] - 1), np.clip(j[ok], 0, shape[1] - 1)] = True
    return Raster2D(occ, lo, float(res))


def cast_rays(raster: Raster2D, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Distance (N,) m along each 2D ray to where it enters its first occupied cell; NaN = no hit.

    origin (2,) must lie inside the raster; directions (N, 2) need not be unit length (the
    distance is in units of |direction|, metres for unit directions). The origin's own cell
    is ignored, so a ray never hits at distance 0.
    """
    o = np.asarray(origin, dtype=np.float64).reshape(2)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 2)
    n = len(d)
    out = np.full(n, np.nan)
    nx, ny = raster.shape
    cell = raster.cell_of(o[None, :])[0]
    if not (0 <= cell[0] < nx and 0 <= cell[1] < ny):
        raise ValueError(f"scan origin {o} lies outside the raster")
    res = raster.res
    with np.errstate(divide="ignore", invalid="ignore"):
        step = np.sign(d).astype(np.int64)  # (N, 2)
        next_edge = raster.lo + (cell[None, :] + (step > 0)) * res  # (N, 2) first boundary crossed
        t_max = np.where(step != 0, (next_edge - o) / d, np.inf)  # (N, 2) distance to it
        t_delta = np.where(step != 0, res / np.abs(d), np.inf)  # (N, 2) distance between boundaries
    ix = np.full(n, cell[0])
    iy = np.full(n, cell[1])
    active = np.flatnonzero((step != 0).any(axis=1))
    occ = raster.occupied
    while active.size:
        tx, ty = t_max[active, 0], t_max[active, 1]
        move_x = tx <= ty
        t_enter = np.where(move_x, tx, ty)
        ix[active] += np.where(move_x, step[active, 0], 0)
        iy[active] += np.where(move_x, 0, step[active, 1])
        t_max[active, 0] += np.where(move_x, t_delta[active, 0], 0.0)
        t_max[active, 1] += np.where(move_x, 0.0, t_delta[active, 1])
        a_ix, a_iy = ix[active], iy[active]
        inside = (a_ix >= 0) & (a_ix < nx) & (a_iy >= 0) & (a_iy < ny)
        hit = np.zeros(active.size, dtype=bool)
        hit[inside] = occ[a_ix[inside], a_iy[inside]]
        out[active[hit]] = t_enter[hit]
        active = active[inside & ~hit]
    return out


@dataclass
class GroundTruth:
    """GT scan of one test point plus the map slice it came from (for plots)."""

    test_point: TestPoint
    scan: Scan2D  # name "GT", full 360 deg
    ranges: np.ndarray  # (n_rays,) m, NaN = no hit, ray k at angle scan_angles(n_rays)[k]
    slice_xy: np.ndarray  # (K, 2) map points within the height band


def gt_scan(
    map_points: np.ndarray,
    test_point: TestPoint,
    n_rays: int = 512,
    band: float = 0.05,
    res: float = 0.02,
    footprint: float = 0.03,
) -> GroundTruth:
    """Cast `n_rays` horizontal rays over 360 deg from the test point's scan origin into the map slice."""
    if res > 0.02 + 1e-12:
        raise ValueError(f"GT raster resolution must be <= 0.02 m (design 6.2), got {res}")
    slice_xy = height_slice(map_points, test_point.height, band)
    origin = test_point.origin_xy
    raster = rasterise(slice_xy, res=res, footprint=footprint, include=origin)
    dirs = horizontal_directions(n_rays)  # (N, 3)
    r = cast_rays(raster, origin, dirs[:, :2])
    ok = np.isfinite(r)
    scan = Scan2D(
        name="GT",
        points=origin[None, :] + dirs[ok, :2] * r[ok, None],
        origin=origin,
        fov=FieldOfView.full(origin),
        extra={"angle": scan_angles(n_rays)[ok]},
    )
    return GroundTruth(test_point=test_point, scan=scan, ranges=r, slice_xy=slice_xy)
