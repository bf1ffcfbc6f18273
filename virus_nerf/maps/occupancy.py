"""2D maps in the ROS map_server convention: PGM (P5) + YAML.

Raster convention (shared by every 2D export): pixel (row r, column c) of an (H, W) image covers
x in [ox + c*res, ox + (c+1)*res) and y in [oy + (H-1-r)*res, oy + (H-r)*res): row 0 is the top
(largest y), `origin` = world (x, y) of the lower-left corner of the lower-left pixel, yaw 0.

Two maps are written beside each other on the same raster:
- trinary (`mode: trinary`): the NeRF's own 360 deg scans at camera height, cells a ray passed
  free (254), end cells occupied (0), the rest unknown (205);
- raw (`mode: raw`): the Bayesian VIRUS grid's occupancy probability p as the OccupancyGrid
  value itself, round(100 p) in 0..100, and RAW_UNKNOWN (255) where no sensor looked; map_server
  (ROS 1 and nav2) serves a raw pixel of 0..100 as that value and any other as -1 (unknown), so
  it serves exactly what /map_probability carries. (A `mode: scale` PGM cannot mark a cell
  unknown: scale mode's only mark is an alpha channel, which a PGM has not; map_server served
  the p = 0.5 of unseen cells as a probability, which a costmap reading it as trinary takes for
  free space.) `preview` gives the picture to look at: 255 (1 - p), unknown mid grey.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

OCCUPIED, FREE, UNKNOWN = 0, 254, 205
RAW_UNKNOWN = 255  # a raw map's pixel where no sensor looked (map_server: any value over 100 is -1)
PREVIEW_UNKNOWN = 128  # ... and its preview's (p = 0.5: no knowledge)
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196
MAX_PIXELS = 100_000_000  # a finer --resolution is refused (memory) before anything is computed
# pass points rasterised at once: ~100 bytes of temporaries each (the points, their rays' origins
# and directions, pixel indices), ~100 MB a chunk, whatever the raster or the number of rays
SCAN_POINTS_PER_CHUNK = 1 << 20
# every consumer's map (the Mapper's snapshots and map2d, map-bag, the node, `export`'s map.pgm and
# the safety figure) scans with this many rays a position from at most this many positions: the
# rules of maps/extract.py (the scan rule, the shadows) were measured at these counts, and twice the
# rays made them less safe (D75: offline warehouse 83, obstacles within 1 m marked free 0.8 -> 6.8 %)
MAP_RAYS = 360
MAP_POSES = 30


@dataclass
class OccupancyMap2D:
    image: np.ndarray  # (H, W) uint8, row 0 = largest y (image top)
    resolution: float  # metres per pixel
    origin: tuple[float, float]  # world (x, y) of the lower-left pixel corner
    mode: Literal["trinary", "scale", "raw"] = "trinary"

    def __post_init__(self) -> None:
        # Python floats whatever the caller gave (numpy scalars): the YAML and JSON written from
        # them must read back as numbers (`np.float32(0.1)` is a string to a YAML reader)
        self.resolution = float(self.resolution)
        self.origin = (float(self.origin[0]), float(self.origin[1]))


def raster_shape(lo: np.ndarray, hi: np.ndarray, resolution: float) -> tuple[int, int]:
    """(nx, ny) pixels covering the box [lo, hi] (x, y) at `resolution` metres per pixel."""
    with np.errstate(over="ignore", divide="ignore"):
        cells = np.ceil((np.asarray(hi[:2], dtype=np.float64) - np.asarray(lo[:2], dtype=np.float64)) / resolution
                        - 1e-9)
    cells = np.where(np.isfinite(cells), np.minimum(cells, 1e12), 1e12)  # a tiny resolution: huge, not overflowed
    return max(int(cells[0]), 1), max(int(cells[1]), 1)


def to_image(grid_xy: np.ndarray) -> np.ndarray:
    """An [ix, iy] array -> image rows (row 0 = largest y), columns = x."""
    return np.ascontiguousarray(np.flipud(np.asarray(grid_xy).T))


def from_image(image: np.ndarray) -> np.ndarray:
    """Inverse of `to_image`: image -> [ix, iy]."""
    return np.ascontiguousarray(np.flipud(np.asarray(image)).T)


def world_pixels(points: np.ndarray, lo: np.ndarray, resolution: float, shape: tuple[int, int]):
    """(..., 2) world points -> ((..., 2) int [ix, iy] of the raster at `lo`, clipped into `shape`,
    (...) bool whether each lies inside it). `resolution`: one pixel size, or (2,) along x and y."""
    ij = np.floor((np.asarray(points, dtype=np.float64) - lo) / resolution).astype(np.int64)
    inside = (ij[..., 0] >= 0) & (ij[..., 0] < shape[0]) & (ij[..., 1] >= 0) & (ij[..., 1] < shape[1])
    return np.clip(ij, 0, np.array(shape) - 1), inside


def ray_ends(origins: np.ndarray, directions: np.ndarray, ranges: np.ndarray, lo: np.ndarray, resolution: float,
             shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The 2D rays (origins (N, 2), directions (N, 2) unit, ranges (N,) m) with a finite, positive
    range: which they are ((N,) bool, M of them), their ends (M, 2) m, their end pixels (M, 2) int
    [ix, iy] of the raster at `lo`, and whether each end pixel lies inside `shape` (M,) bool."""
    ranges = np.asarray(ranges, dtype=np.float64)
    ok = np.isfinite(ranges) & (ranges > 0)
    end = np.asarray(origins)[ok] + np.asarray(directions)[ok] * ranges[ok, None]
    ij = np.floor((end - lo) / resolution).astype(np.int64)
    return ok, end, ij, np.all((ij >= 0) & (ij < shape), axis=1)


def scan_counts(
    origins: np.ndarray, directions: np.ndarray, ranges: np.ndarray, lo: np.ndarray, hi: np.ndarray, resolution: float
) -> tuple[np.ndarray, np.ndarray]:
    """(passes, hits), each (nx, ny) int64 [ix, iy], of 2D scan rays over the box [lo, hi]:
    how many rays ended in a pixel (hits) and how many sample points of rays passed through it
    (every half pixel up to one pixel before the end; passes). origins (N, 2), directions (N, 2)
    unit, ranges (N,) m (rays with a range that is not finite and positive are left out)."""
    shape = raster_shape(lo, hi, resolution)  # (nx, ny), as every other raster of the box (observed mask)
    passes = np.zeros(shape, dtype=np.int64)
    hits = np.zeros(shape, dtype=np.int64)
    ok, _, ij, inside = ray_ends(origins, directions, ranges, lo, resolution, shape)
    o, d, r = np.asarray(origins)[ok], np.asarray(directions)[ok], np.asarray(ranges, dtype=np.float64)[ok]
    hits += _pixel_counts(ij[inside, 0], ij[inside, 1], shape)
    n_steps = np.floor(np.maximum(r - resolution, 0) / (resolution / 2)).astype(np.int64)  # (N,) pass points a ray
    for _, _, _, ix, iy, inside in ray_points(o, d, n_steps, lo, resolution, shape):
        passes += _pixel_counts(ix[inside], iy[inside], shape)
    return passes, hits


def ray_points(origins: np.ndarray, directions: np.ndarray, counts: np.ndarray, lo: np.ndarray, resolution: float,
               shape: tuple[int, int]):
    """The points of 2D rays (origins (N, 2), directions (N, 2) unit) every half pixel from their
    origins, `counts` (N,) of them a ray, in chunks of at most SCAN_POINTS_PER_CHUNK points (bounded
    memory at any resolution): yields (rows (M,) the chunk's rays, k (M,) their points, t (K,) m
    along each ray, ix, iy (K,) pixel indices of the raster at `lo`, inside (K,) bool in `shape`)."""
    step = resolution / 2
    for rows in _bounded_chunks(counts, SCAN_POINTS_PER_CHUNK):
        k = counts[rows]
        t = (np.arange(k.sum()) - np.repeat(np.cumsum(k) - k, k)) * step  # (K,) m along each ray
        # per axis, each ray's values repeated over its points (a repeat, not a gather: ~3x faster)
        ix, iy = (np.floor((np.repeat(origins[rows, a], k) + np.repeat(directions[rows, a], k) * t - lo[a])
                           / resolution).astype(np.int64) for a in (0, 1))
        inside = (ix >= 0) & (ix < shape[0]) & (iy >= 0) & (iy < shape[1])
        yield rows, k, t, ix, iy, inside


def _pixel_counts(ix: np.ndarray, iy: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(K,) int pixel indices ix, iy inside `shape` -> (nx, ny) int64 count of each pixel
    (np.bincount over the flat index: faster than np.add.at)."""
    return np.bincount(ix.astype(np.int64) * shape[1] + iy, minlength=shape[0] * shape[1]).reshape(shape)


def _bounded_chunks(counts: np.ndarray, budget: int):
    """Index arrays over consecutive rows of `counts` (N,) whose counts sum to at most `budget`
    (a row over the budget alone goes alone): the pass points of a chunk of rays."""
    ends = np.cumsum(counts)
    start = 0
    while start < len(counts):
        base = ends[start - 1] if start else 0
        stop = max(start + 1, int(np.searchsorted(ends, base + budget, side="right")))
        yield np.arange(start, stop)
        start = stop


def scan_rule_occupied(passes: np.ndarray, hits: np.ndarray) -> np.ndarray:
    """The scan rule (nx, ny) bool: a pixel where rays ended at least half as often as rays
    passed it is occupied (a floater that most rays pass is not an obstacle)."""
    return (hits > 0) & (hits >= 0.5 * passes)


def scan_occupancy(
    origins: np.ndarray, directions: np.ndarray, ranges: np.ndarray, lo: np.ndarray, hi: np.ndarray, resolution: float
) -> OccupancyMap2D:
    """Occupancy raster from 2D scan rays. origins (N, 2), directions (N, 2) unit, ranges (N,) m:
    passed pixels free, a pixel where at least half as many rays ended as passed occupied."""
    passes, hits = scan_counts(origins, directions, ranges, lo, hi, resolution)
    img = np.full(passes.shape, UNKNOWN, dtype=np.uint8)
    img[passes > 0] = FREE
    img[scan_rule_occupied(passes, hits)] = OCCUPIED
    return OccupancyMap2D(image=to_image(img), resolution=resolution, origin=(float(lo[0]), float(lo[1])))


def probability_slice(
    probability: np.ndarray, box_lo, box_hi, height: float, band: float,
    lo: np.ndarray, hi: np.ndarray, resolution: float,
) -> np.ndarray:
    """(nx, ny) occupancy probability of a 3D grid in a horizontal band around `height`.

    Why a band and a maximum: the 2D map is judged at camera height (docs/method.md 6.3), where a wheeled
    robot carrying the cameras collides; a grid layer is ~8 cm thick and a wall seen a little
    above or below camera height still blocks the robot, so every layer whose centre lies within
    `band` metres of `height` (at least the layer containing `height`) is taken, and a column's
    probability is the largest in the band (the conservative projection for a planner).
    Pixel centres look up the grid cell containing them (the cell-index formula of
    `grid.base.cell_index`); a pixel whose centre lies outside the grid's box is NaN: no cell holds
    knowledge of it (a raster's size is rounded up, so its last row and column may stick out).

    probability: (rx, ry, rz) array indexed [ix, iy, iz]; box_lo/box_hi: the grid's box (m).
    """
    probability = np.asarray(probability, dtype=np.float64)
    res = np.asarray(probability.shape)
    blo, bhi = np.asarray(box_lo, dtype=np.float64), np.asarray(box_hi, dtype=np.float64)
    size = bhi - blo
    zc = blo[2] + (np.arange(res[2]) + 0.5) * size[2] / res[2]
    layers = np.abs(zc - height) <= band
    iz = int(np.floor((height - blo[2]) / size[2] * res[2]))
    if 0 <= iz < res[2]:
        layers[iz] = True
    nx, ny = raster_shape(lo, hi, resolution)
    if not layers.any():  # the height is outside the box: nothing known there
        return np.full((nx, ny), np.nan)
    column = probability[:, :, layers].max(axis=2)  # (rx, ry)
    x = lo[0] + (np.arange(nx) + 0.5) * resolution
    y = lo[1] + (np.arange(ny) + 0.5) * resolution
    ix = np.floor((x - blo[0]) / size[0] * res[0]).astype(int)
    iy = np.floor((y - blo[1]) / size[1] * res[1]).astype(int)
    ok_x, ok_y = (ix >= 0) & (ix < res[0]), (iy >= 0) & (iy < res[1])
    out = np.full((nx, ny), np.nan)
    sub = column[np.ix_(ix[ok_x], iy[ok_y])]
    out[np.ix_(ok_x, ok_y)] = sub
    return out


def raw_map(p_xy: np.ndarray, lo: np.ndarray, resolution: float, known_xy: np.ndarray | None = None) -> OccupancyMap2D:
    """Probabilities [ix, iy] in [0, 1] -> a `mode: raw` map: value = round(100 p), RAW_UNKNOWN
    where p is NaN (no knowledge) and outside `known_xy` ([ix, iy] bool; None: wherever p is a number)."""
    p_xy = np.asarray(p_xy, dtype=np.float64)
    known = np.isfinite(p_xy)
    if known_xy is not None:
        known &= np.asarray(known_xy, dtype=bool)
    value = np.full(p_xy.shape, RAW_UNKNOWN, dtype=np.uint8)
    value[known] = np.rint(100.0 * np.clip(p_xy[known], 0.0, 1.0)).astype(np.uint8)
    return OccupancyMap2D(image=to_image(value), resolution=resolution, origin=(float(lo[0]), float(lo[1])),
                          mode="raw")


def preview(m: OccupancyMap2D) -> np.ndarray:
    """(H, W) uint8 picture of a map to look at: a raw map as 255 (1 - p) (dark = occupied, as the
    trinary map), PREVIEW_UNKNOWN where unknown; the other modes' images are pictures already."""
    img = np.asarray(m.image, dtype=np.uint8)
    if m.mode != "raw":
        return img
    known = img <= 100
    out = np.full(img.shape, PREVIEW_UNKNOWN, dtype=np.uint8)
    out[known] = np.rint(255.0 * (1.0 - img[known] / 100.0)).astype(np.uint8)
    return out


def write_pgm(path: Path, image: np.ndarray) -> None:
    """8-bit binary PGM (P5), maxval 255, atomically."""
    from virus_nerf.utils.io import atomic_path

    h, w = image.shape
    with atomic_path(path) as tmp:
        tmp.write_bytes(f"P5\n{w} {h}\n255\n".encode() + np.ascontiguousarray(image, dtype=np.uint8).tobytes())


def yaml_float(value: float) -> str:
    """A float as YAML text that every YAML reader reads back as the same float: the shortest
    text (repr), with a decimal point before any exponent (YAML 1.1 readers such as PyYAML read
    `3e-05` as a string, `3.0e-05` as the number)."""
    text = repr(float(value))
    mantissa, e, exponent = text.partition("e")
    if e and "." not in mantissa:
        text = f"{mantissa}.0e{exponent}"
    return text


def map_yaml(image_name: str, resolution: float, origin: tuple[float, float], mode: str = "trinary") -> str:
    """The map_server YAML (written by hand: a flat document of scalars and one list). The origin
    is written to the last bit (the shortest text that reads back as the same float): a LiDAR
    point on a pixel edge then falls in the same pixel for a reader of map.yaml as for the safety
    figures that judged the map."""
    return (f"image: {image_name}\nmode: {mode}\nresolution: {yaml_float(resolution)}\n"
            f"origin: [{yaml_float(origin[0])}, {yaml_float(origin[1])}, 0.0]\nnegate: 0\n"
            f"occupied_thresh: {OCCUPIED_THRESH}\nfree_thresh: {FREE_THRESH}\n")


def write_map_server(m: OccupancyMap2D, folder: Path, name: str = "map") -> tuple[Path, Path]:
    """PGM (binary P5) + YAML, atomically."""
    from virus_nerf.utils.io import write_text_atomic

    pgm, yaml = Path(folder) / f"{name}.pgm", Path(folder) / f"{name}.yaml"  # a str folder as well
    write_pgm(pgm, m.image)
    write_text_atomic(yaml, map_yaml(pgm.name, m.resolution, m.origin, m.mode))
    return pgm, yaml


def read_map_server(yaml_path: Path) -> OccupancyMap2D:
    """A map written by `write_map_server` (its YAML's image, mode, resolution and origin; the PGM
    as it is): to publish again what a snapshot folder holds."""
    from PIL import Image

    yaml_path = Path(yaml_path)
    fields = {}
    for line in yaml_path.read_text().splitlines():
        key, _, value = line.partition(":")
        fields[key.strip()] = value.strip()
    x, y, _ = (float(v) for v in fields["origin"].strip("[]").split(","))
    with Image.open(yaml_path.parent / fields["image"]) as img:
        image = np.asarray(img, dtype=np.uint8).copy()
    mode = fields.get("mode", "trinary")
    return OccupancyMap2D(image=image, resolution=float(fields["resolution"]), origin=(x, y),
                          mode=mode if mode in ("scale", "raw") else "trinary")


def write_png(path: Path, image: np.ndarray) -> None:
    """8-bit grey/RGB or 16-bit grey (uint16) PNG, atomically."""
    from PIL import Image

    from virus_nerf.utils.io import atomic_path

    with atomic_path(path) as tmp:
        Image.fromarray(np.ascontiguousarray(image)).save(tmp, format="PNG")
