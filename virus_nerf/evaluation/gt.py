"""Ground-truth 2D scans (docs/method.md 6.2, 6.7), under three protocols.

- `map` (default): the LiDAR map is a cloud of 3 cm voxel centres. Points within +-band of the
  camera height are drawn into a 2D occupancy raster (<= 2 cm cells), each point as its voxel's
  square footprint ("solid 3 cm voxels") so that a wall of voxel centres 3 cm apart has no gaps
  rays could leak through. Horizontal rays from the scan origin are traversed cell by cell
  (Amanatides-Woo DDA, vectorised over rays): the first occupied cell gives the hit, at the exact
  distance where the ray enters that cell.
- `exact` (simulated recordings): the same rays cast into the simulator's exact scene
  (`scene.json`) at camera height; no map, no raster.
- `paper`: the authors' raster: map points within +-band of the mean camera height of all test
  points, each one pixel of a 512 x 512 raster over the scene's square extent (pixel =
  extent / 511, pixel centres on the grid nodes, points outside clamped to the border), every
  ray sampled at 725 equidistant radii from 0 to the extent, the first sample in an occupied
  pixel giving the distance to that pixel's centre; the LiDAR is scored over its configured
  horizontal range per room (`PAPER_ROOMS`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from virus_nerf.evaluation.config import GT_PROTOCOLS  # noqa: F401  (importable from here as before)
from virus_nerf.evaluation.testpoints import TestPoint
from virus_nerf.maps.scans import FieldOfView, Scan2D, horizontal_directions, scan_angles

GT_DESCRIPTIONS = {
    "map": "LiDAR map slice as solid 3 cm voxels, 2 cm raster",
    "exact": "exact simulated scene at camera height",
    "paper": "authors' protocol: one pixel per map point, 512 x 512 raster, 725 samples per ray",
}
PAPER_RASTER_PX = 512  # pixels per side of the authors' slice raster
PAPER_RAY_SAMPLES = 725  # ceil(sqrt(2) * 512) equidistant radii per ray, 0 .. extent
PAPER_SCALE_MARGIN = 1.05  # the authors' scene cube: largest box side times this margin


@dataclass(frozen=True)
class PaperRoom:
    """The authors' configuration of one of their real rooms (metres, degrees).

    lidar_deg: horizontal LiDAR range scored, relative to the LiDAR heading (their
    `angle_min_max`); box_xy: (x_lo, y_lo, x_hi, y_hi) of their hand-set scene box, whose largest
    side times 1.05 is the raster's extent (office: 9 m -> 9.45 m, 1.85 cm pixels; None: use
    the map's bounding box).
    """

    lidar_deg: tuple[float, float]
    box_xy: tuple[float, float, float, float] | None = None


PAPER_ROOMS: dict[str, PaperRoom] = {
    "office": PaperRoom((-120.0, 120.0), (-2.0, -1.0, 6.0, 8.0)),
    "commonroom": PaperRoom((-140.0, 60.0), (-3.0, -3.0, 15.0, 9.0)),
    "common": PaperRoom((-140.0, 60.0)),  # the simulator's name for the common room
}
FULL_CIRCLE_DEG = (-180.0, 180.0)


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


# the robot's body meets what stands from this high above the floor (m; thresholds and cables lie
# lower) up to its cameras: what the drivable free space leaves out (evaluation/safety.py)
BODY_FLOOR_CLEARANCE_M = 0.1
FLOOR_BELOW_CAMERAS_M = 0.2  # the floor is looked for this far (m) or more below the cameras
FLOOR_BIN_M = 0.02  # m, the height bins of that search


def floor_height(points: np.ndarray, camera_height: float) -> float | None:
    """The floor's height (m, world z): the centre of the most populated FLOOR_BIN_M height bin of
    the map points (P, 3) more than FLOOR_BELOW_CAMERAS_M below `camera_height` (the floor is the
    largest level surface under a ground robot); None when the map holds no point there (a map
    cut above its floor)."""
    z = np.asarray(points, dtype=np.float64).reshape(-1, 3)[:, 2]
    z = z[z < camera_height - FLOOR_BELOW_CAMERAS_M]
    if not len(z):
        return None
    counts = np.bincount(np.floor((z - z.min()) / FLOOR_BIN_M).astype(np.int64))
    return float(z.min() + (np.argmax(counts) + 0.5) * FLOOR_BIN_M)


def body_slice(points: np.ndarray, camera_height: float, band: float) -> np.ndarray | None:
    """(K, 2) x, y of the map points (P, 3) that the robot's body meets below the camera band: from
    BODY_FLOOR_CLEARANCE_M above the floor (`floor_height`) up to camera_height - band; None when
    the map has no floor."""
    floor = floor_height(points, camera_height)
    if floor is None:
        return None
    pts = np.asarray(points)
    z = pts[:, 2].astype(np.float64)
    keep = (z >= floor + BODY_FLOOR_CLEARANCE_M) & (z < camera_height - band)
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


@dataclass(frozen=True)
class MapSlice:
    """The map points within `band` of `height`, cut when asked for (`xy`). A test point keeps
    this and not the cut: the thousands of test points of a long drive share one map, where a
    copy each (0.14 MB for the simulated office) grew the evaluation by ~16 MB a minute of
    driving (docs/decisions.md D59)."""

    cloud: np.ndarray  # (P, 3) map points, metres, world frame (shared, never written)
    height: float  # m
    band: float  # m

    def xy(self) -> np.ndarray:
        """(K, 2) x, y of the map points with |z - height| <= band."""
        return height_slice(self.cloud, self.height, self.band)


@dataclass
class GroundTruth:
    """GT scan of one test point plus the map slice it came from (for plots)."""

    test_point: TestPoint
    scan: Scan2D  # name "GT", full 360 deg
    ranges: np.ndarray  # (n_rays,) m, NaN = no hit, ray k at angle scan_angles(n_rays)[k]
    map_slice: MapSlice | None  # the map slice the scan was cast into (for plots; None: none)
    protocol: str = "map"  # which protocol made it (GT_PROTOCOLS)
    # LiDAR horizontal range scored under this protocol, degrees relative to the LiDAR heading;
    # None: the evaluation's own setting (EvaluationConfig.lidar_angle_range_deg)
    lidar_deg: tuple[float, float] | None = None

    @property
    def slice_xy(self) -> np.ndarray:
        """(K, 2) map points within the height band (may be empty), cut anew on each call."""
        return np.zeros((0, 2)) if self.map_slice is None else self.map_slice.xy()


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
        raise ValueError(f"GT raster resolution must be <= 0.02 m (docs/method.md 6.2), got {res}")
    cut = MapSlice(map_points, test_point.height, band)
    origin = test_point.origin_xy
    raster = rasterise(cut.xy(), res=res, footprint=footprint, include=origin)
    dirs = horizontal_directions(n_rays)  # (N, 3)
    r = cast_rays(raster, origin, dirs[:, :2])
    return _ground_truth(test_point, r, cut, "map")


def _ground_truth(test_point: TestPoint, ranges: np.ndarray, map_slice: MapSlice | None, protocol: str,
                  lidar_deg: tuple[float, float] | None = None) -> GroundTruth:
    """GroundTruth of ranges (n_rays,) along horizontal_directions(n_rays) from the scan origin."""
    origin = test_point.origin_xy
    r = np.asarray(ranges, dtype=np.float64).reshape(-1)
    dirs = horizontal_directions(len(r))
    ok = np.isfinite(r) & (r > 0)
    r = np.where(ok, r, np.nan)
    scan = Scan2D(
        name="GT",
        points=origin[None, :] + dirs[ok, :2] * r[ok, None],
        origin=origin,
        fov=FieldOfView.full(origin),
        extra={"angle": scan_angles(len(r))[ok]},
    )
    return GroundTruth(test_point=test_point, scan=scan, ranges=r, map_slice=map_slice, protocol=protocol,
                       lidar_deg=lidar_deg)


# ---------------------------------------------------------------------------------- exact
def exact_gt_scan(scene, test_point: TestPoint, n_rays: int = 512, map_slice: MapSlice | None = None) -> GroundTruth:
    """`n_rays` horizontal rays from the test point's camera-1 position (at camera height) cast
    into an exact scene (anything with `ranges(origins, directions)`, e.g. sim.scene.Scene);
    `map_slice`, the LiDAR map's slice, is drawn beside it in the plots."""
    dirs = horizontal_directions(n_rays)
    origins = np.broadcast_to(test_point.origin, dirs.shape).copy()
    r = np.asarray(scene.ranges(origins, dirs), dtype=np.float64).reshape(-1)
    return _ground_truth(test_point, r, map_slice, "exact")


# ---------------------------------------------------------------------------------- paper
@dataclass(frozen=True)
class SquareExtent:
    """The square the paper raster covers: centre (x, y) and side, metres."""

    centre: tuple[float, float]
    side: float

    @property
    def pixel(self) -> float:
        """Pixel pitch (m): side / (pixels - 1), the pixel centres lying on the grid nodes."""
        return self.side / (PAPER_RASTER_PX - 1)

    @property
    def corner(self) -> np.ndarray:
        """(2,) centre of pixel (0, 0), the square's lower-left corner."""
        return np.asarray(self.centre, dtype=np.float64) - self.side / 2

    @staticmethod
    def of_box(lo_xy, hi_xy, margin: float = PAPER_SCALE_MARGIN) -> SquareExtent:
        """The authors' cube: centred on the box, side = its largest side times `margin`."""
        lo, hi = np.asarray(lo_xy, dtype=np.float64), np.asarray(hi_xy, dtype=np.float64)
        c = (lo + hi) / 2
        return SquareExtent((float(c[0]), float(c[1])), float((hi - lo).max() * margin))


def paper_extent(room: str, map_points: np.ndarray, real_recording: bool) -> SquareExtent:
    """The raster's square: the authors' box of their room for a real recording of it, else the
    bounding box of the map's x, y (both grown by their 5 % margin)."""
    cfg = PAPER_ROOMS.get(room)
    if real_recording and cfg is not None and cfg.box_xy is not None:
        x0, y0, x1, y1 = cfg.box_xy
        return SquareExtent.of_box((x0, y0), (x1, y1))
    xy = np.asarray(map_points, dtype=np.float64).reshape(-1, 3)[:, :2] if len(map_points) else np.zeros((1, 2))
    return SquareExtent.of_box(xy.min(axis=0), xy.max(axis=0))


def paper_lidar_deg(room: str) -> tuple[float, float]:
    """The LiDAR's horizontal range in the authors' configuration; the full circle when unknown."""
    cfg = PAPER_ROOMS.get(room)
    return cfg.lidar_deg if cfg is not None else FULL_CIRCLE_DEG


def paper_pixel_of(xy: np.ndarray, extent: SquareExtent) -> np.ndarray:
    """(K, 2) points -> (K, 2) pixel indices: nearest pixel centre, clamped to the raster."""
    q = (np.asarray(xy, dtype=np.float64) - extent.corner) / extent.pixel
    return np.clip(np.floor(q + 0.5), 0, PAPER_RASTER_PX - 1).astype(np.int64)


def paper_raster(slice_xy: np.ndarray, extent: SquareExtent) -> np.ndarray:
    """(512, 512) bool raster, pixel (i, j) centred at corner + (i, j) * pixel; one pixel per point."""
    occ = np.zeros((PAPER_RASTER_PX, PAPER_RASTER_PX), dtype=bool)
    idx = paper_pixel_of(np.asarray(slice_xy, dtype=np.float64).reshape(-1, 2), extent)
    occ[idx[:, 0], idx[:, 1]] = True
    return occ


def paper_cast(occupied: np.ndarray, extent: SquareExtent, origin: np.ndarray, directions: np.ndarray,
               n_samples: int = PAPER_RAY_SAMPLES) -> np.ndarray:
    """Distance (N,) m from origin (2,) to the centre of the first occupied pixel met by each ray's
    `n_samples` equidistant samples at radii 0 .. extent.side (the first at the origin itself);
    NaN where none is occupied. directions (N, 2) unit."""
    o = np.asarray(origin, dtype=np.float64).reshape(1, 1, 2)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 1, 2)
    radii = np.linspace(0.0, extent.side, n_samples).reshape(1, -1, 1)
    idx = paper_pixel_of((o + radii * d).reshape(-1, 2), extent).reshape(len(d), n_samples, 2)
    occ = occupied[idx[..., 0], idx[..., 1]]  # (N, S)
    hit = occ.any(axis=1)
    first = np.argmax(occ, axis=1)
    centre = extent.corner + idx[np.arange(len(d)), first] * extent.pixel  # (N, 2)
    out = np.linalg.norm(centre - o[0], axis=1)
    return np.where(hit, out, np.nan)


def paper_gt_scan(
    map_points: np.ndarray,
    test_point: TestPoint,
    extent: SquareExtent,
    slice_height: float,
    n_rays: int = 512,
    band: float = 0.05,
    lidar_deg: tuple[float, float] = FULL_CIRCLE_DEG,
) -> GroundTruth:
    """The authors' GT scan of one test point: the slice at `slice_height` (the mean camera height
    of all test points) +-band, rasterised and sampled as in `paper_cast`."""
    cut = MapSlice(map_points, slice_height, band)
    occ = paper_raster(cut.xy(), extent)
    r = paper_cast(occ, extent, test_point.origin_xy, horizontal_directions(n_rays)[:, :2])
    return _ground_truth(test_point, r, cut, "paper", lidar_deg=lidar_deg)
