"""A map whose extent is not known in advance (issue 29, item 2; docs/extent.md).

`fitted` (the default for offline training): the scene box is fitted before the first step from
the LiDAR map and the whole drive (data/room_box.py fit_scene_box); the field's hash encoding and
the occupancy grid both span it.

`grow` (a robot in a room it has never seen): the Mapper starts from a small box around its first
frame and grows it, by whole grid cells, to hold what the robot has sensed (`grow_from` sensed,
the default): every camera position and every horizontal support cell (`support_cell_m`) with at
least `support_points` points the depth sensors measured (the cameras' stereo triangulations, the
IRS zones' returns), each grown by `margin_m`. So the box ends just behind the walls the robot
saw, as the fitted box does, and holds no space beyond them where the field is untrained
(docs/extent.md, D39). Without the stereo sensor (the only one that ranges as far as the cameras
see) it grows by `reach_m` around every camera position instead (`grow_from` reach, the first
design, D38). The box's height is the first camera's +- `height_m` (z is fixed). Two things keep
growing exact:

- the occupancy grid's cells keep their size (`grid_cell_m`) and position; growing pads the cell
  array on its sides, every existing cell keeps its value (`GridSpec.grown`, `OccupancyGrid.grow`);
- the field's hash encoding is normalised to a fixed cube (`frame_m` on a side, centred on the
  first box) that never moves, with its resolutions set in metres (`field_coarse_m`,
  `field_fine_m`), so a point's features do not change when the box grows.

Memory is bounded: the hash tables have a fixed size, the grid has one float per cell of the box,
the support counts one byte per support cell of the frame, the box at most the frame's cube.
Frames beyond the frame cube are refused with a one-line error naming the frame (a larger
`frame_m` maps a larger area).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass

import numpy as np

from virus_nerf.scene_box import SceneBox

EXTENT_MODES = ("fitted", "grow")
GROW_FROM = ("sensed", "reach")
FITTED_FRAMES = ("box", "cube")


@dataclass(frozen=True)
class ExtentConfig:
    """How the Mapper bounds its map (module docstring), metres."""

    mode: str = "fitted"  # fitted | grow
    # fitted: the frame the field's hash encoding is normalised to. "cube" (the default): the cube
    # around the box, its side the box's longest axis, so a level's cells have one size on every
    # axis; the occupancy grid still spans the box itself. "box": the box per axis, so the finest
    # cells are as many along the room's height as along its length (3.6 x 2.4 x 0.6 cm in an
    # 18 m common area). Over 3 rooms of each kind at 180 s (office 60 s), the cube's accuracy /
    # coverage: common area 13 % / 16 % better (29 % more steps), office 2 % worse / 7 % better,
    # warehouse 1 % / 2 % better (docs/decisions.md D58). configs/paper.json keeps "box"
    fitted_frame: str = "cube"
    # grow: what the box grows to hold: "sensed" (the default) the camera positions and the points
    # the depth sensors measured (stereo, IRS), each + margin_m, by single grid cells (needs the
    # stereo sensor; without it the reach); "reach" every camera position + reach_m (better
    # coverage of a large room's far walls while driving, worse accuracy and safety, more memory;
    # docs/decisions.md D44)
    grow_from: str = "sensed"
    reach_m: float = 8.0  # grow, reach: horizontal margin around every camera position (the URM37's reach)
    margin_m: float = 0.1  # grow, sensed: margin around the camera positions and the supported points
    support_cell_m: float = 0.16  # grow, sensed: horizontal cells in which sensed points are counted
    # grow, sensed: points a support cell needs before the box holds it. 1 (any measured point):
    # a far wall the stereo sees from afar gets too few points per cell for more; 3 ignores a
    # stray triangulation but leaves those walls outside the box (docs/decisions.md D45)
    support_points: int = 1
    height_m: float = 1.5  # grow: the box spans the first camera's height +- this
    grow_step_m: float = 2.0  # grow, reach: the box grows by at least this much on a side (fewer re-allocations)
    # grow: occupancy grid cell. 11 cm, between the fitted 10 m office's 8 cm and the fitted 18 m
    # common area's 14 cm, measured better than both while driving (docs/decisions.md D46)
    grid_cell_m: float = 0.11  # grow: occupancy grid cell (fitted: the longest box axis / max_resolution)
    frame_m: float = 64.0  # grow: side of the field's fixed cube, centred on the first box
    # grow: the field's coarsest and finest hash levels' cells, those the fitted box gives the 18 m
    # common area (18.2 m / 16, / 512), not the 10 m office's (0.6 m, 2 cm): a 2 cm finest level
    # over a large room overloads the 2^16-entry tables (D46)
    field_coarse_m: float = 1.14  # grow: coarsest hash level's cell
    field_fine_m: float = 0.036  # grow: finest hash level's cell

    def __post_init__(self) -> None:
        if self.mode not in EXTENT_MODES:
            raise ValueError(f"extent.mode {self.mode!r}: expected one of {', '.join(EXTENT_MODES)}")
        if self.fitted_frame not in FITTED_FRAMES:
            raise ValueError(f"extent.fitted_frame {self.fitted_frame!r}: expected one of {', '.join(FITTED_FRAMES)}")
        if self.grow_from not in GROW_FROM:
            raise ValueError(f"extent.grow_from {self.grow_from!r}: expected one of {', '.join(GROW_FROM)}")
        p = self.support_points
        if isinstance(p, bool) or not isinstance(p, int) or not 1 <= p <= 255:
            raise ValueError(f"extent.support_points {p!r}: expected a whole number from 1 to 255")
        for name in ("reach_m", "margin_m", "support_cell_m", "height_m", "grow_step_m", "grid_cell_m", "frame_m",
                     "field_coarse_m", "field_fine_m"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or v <= 0:
                raise ValueError(f"extent.{name} {v!r}: expected a positive number of metres")
        if self.field_fine_m > self.field_coarse_m:
            raise ValueError(f"extent.field_fine_m {self.field_fine_m}: expected at most field_coarse_m "
                             f"{self.field_coarse_m}")


def grows_from_sensors(cfg: ExtentConfig, sensors) -> bool:
    """True when the grown box follows the sensed points (`grow_from` sensed and the stereo
    sensor trained), False when it follows the reach around every camera."""
    return cfg.grow_from == "sensed" and "stereo" in tuple(sensors)


def camera_margin_m(cfg: ExtentConfig, sensors) -> float:
    """The horizontal margin the box keeps around every camera position."""
    return cfg.margin_m if grows_from_sensors(cfg, sensors) else cfg.reach_m


def growth_step_m(cfg: ExtentConfig, sensors) -> float:
    """The least a short side grows by: one grid cell when the box follows the sensed points (it
    ends a margin behind a wall), `grow_step_m` with the reach (fewer re-allocations)."""
    return cfg.grid_cell_m if grows_from_sensors(cfg, sensors) else cfg.grow_step_m


def first_box(camera_position: np.ndarray, cfg: ExtentConfig, sensors=()) -> SceneBox:
    """The box around the first frame: its camera position +- the camera margin (x, y; the reach,
    or with sensed growth `margin_m`) and +- height (z), whole grid cells on a side."""
    p = np.asarray(camera_position, dtype=np.float64).reshape(3)
    m = camera_margin_m(cfg, sensors)
    half = np.array([m, m, cfg.height_m])
    n = np.ceil(2 * half / cfg.grid_cell_m - 1e-9)  # cells per axis
    lo = p - n * cfg.grid_cell_m / 2
    return SceneBox(tuple(lo), tuple(lo + n * cfg.grid_cell_m))


def field_frame(box: SceneBox, cfg: ExtentConfig) -> SceneBox:
    """The field's fixed cube: `frame_m` on a side, centred on the first box."""
    return cube_around(box, cfg.frame_m)


def cube_around(box: SceneBox, side_m: float) -> SceneBox:
    """The cube `side_m` on a side with the same centre as `box`."""
    c = np.asarray(box.center, dtype=np.float64)
    return SceneBox(tuple(c - side_m / 2), tuple(c + side_m / 2))


def fitted_field_frame(box: SceneBox, cfg: ExtentConfig) -> SceneBox:
    """The field's frame over a fitted box: the box itself, or the cube around it (`fitted_frame`)."""
    if cfg.fitted_frame == "box":
        return box
    return cube_around(box, float(box.size.max()))


def field_config_for_frame(field, cfg: ExtentConfig):
    """The FieldConfig with its coarsest and finest resolutions set from metres over the frame."""
    return dataclasses.replace(field, base_resolution=max(1, round(cfg.frame_m / cfg.field_coarse_m)),
                               max_resolution=max(1, round(cfg.frame_m / cfg.field_fine_m)))


def needed_box(box: SceneBox, camera_position: np.ndarray, cfg: ExtentConfig, frame: SceneBox,
               margin_m: float | None = None, step_m: float | None = None) -> SceneBox | None:
    """The grown box once a frame at `camera_position` arrives, or None when `box` already holds
    the camera +- `margin_m` (default: the reach) horizontally (`holding_box`)."""
    p = np.asarray(camera_position, dtype=np.float64).reshape(3)
    m = cfg.reach_m if margin_m is None else margin_m
    return holding_box(box, p[:2] - m, p[:2] + m, cfg, frame, step_m)


def holding_box(box: SceneBox, want_lo: np.ndarray, want_hi: np.ndarray, cfg: ExtentConfig,
                frame: SceneBox, step_m: float | None = None) -> SceneBox | None:
    """The grown box that holds the horizontal interval `want_lo`..`want_hi` (2,), or None when
    `box` already does. Grows each side that is short by at least `step_m` (default
    `grow_step_m`), by whole cells of `grid_cell_m` (so cells keep their places), never beyond the
    field's frame; z is fixed."""
    lo, hi = np.array(box.lo, dtype=np.float64), np.array(box.hi, dtype=np.float64)
    want_lo, want_hi = np.asarray(want_lo, dtype=np.float64), np.asarray(want_hi, dtype=np.float64)
    short_lo, short_hi = want_lo < lo[:2] - 1e-9, want_hi > hi[:2] + 1e-9
    if not (short_lo.any() or short_hi.any()):
        return None
    cell = cfg.grid_cell_m
    step = math.ceil((cfg.grow_step_m if step_m is None else step_m) / cell - 1e-9)  # cells
    add_lo = np.where(short_lo, np.maximum(np.ceil((lo[:2] - want_lo) / cell - 1e-9), step), 0)
    add_hi = np.where(short_hi, np.maximum(np.ceil((want_hi - hi[:2]) / cell - 1e-9), step), 0)
    # never beyond the frame: only whole cells that fit inside it
    add_lo = np.minimum(add_lo, np.floor((lo[:2] - np.asarray(frame.lo[:2])) / cell + 1e-9))
    add_hi = np.minimum(add_hi, np.floor((np.asarray(frame.hi[:2]) - hi[:2]) / cell + 1e-9))
    if not ((add_lo > 0).any() or (add_hi > 0).any()):
        return None
    lo[:2] -= add_lo * cell
    hi[:2] += add_hi * cell
    return SceneBox(tuple(lo), tuple(hi))


def inside_frame(camera_position: np.ndarray, frame: SceneBox) -> bool:
    p = np.asarray(camera_position, dtype=np.float64).reshape(3)
    return bool(np.all(p >= np.asarray(frame.lo)) and np.all(p <= np.asarray(frame.hi)))


class SensedSupport:
    """Points the depth sensors measured, counted per horizontal support cell of the field's
    frame (`support_cell_m`, one byte each, saturating at 255); `bounds` is the horizontal extent
    of the cells with at least `support_points` points (above 1, a stray point, a wrong
    triangulation, does not grow the box). Points outside the frame or outside the box's height
    are not counted (the map cannot hold them)."""

    def __init__(self, cfg: ExtentConfig, frame: SceneBox, z_range: tuple[float, float]):
        self.cell = float(cfg.support_cell_m)
        self.need = int(cfg.support_points)
        self.lo = np.asarray(frame.lo[:2], dtype=np.float64)
        self.shape = tuple(int(n) for n in np.ceil(np.asarray(frame.size[:2]) / self.cell - 1e-9))
        self.z_range = (float(z_range[0]), float(z_range[1]))
        self.counts = np.zeros(self.shape, dtype=np.uint8)
        self._lo_cell: np.ndarray | None = None  # (2,) int, lowest supported cell index per axis
        self._hi_cell: np.ndarray | None = None

    def add(self, points: np.ndarray) -> bool:
        """Count world points (N, 3) m; True when the supported extent grew."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        p = p[np.isfinite(p).all(axis=1) & (p[:, 2] >= self.z_range[0]) & (p[:, 2] <= self.z_range[1])]
        ij = np.floor((p[:, :2] - self.lo) / self.cell).astype(np.int64)
        ij = ij[((ij >= 0) & (ij < np.asarray(self.shape))).all(axis=1)]
        if not len(ij):
            return False
        flat, n = np.unique(ij[:, 0] * self.shape[1] + ij[:, 1], return_counts=True)
        counts = self.counts.reshape(-1)
        counts[flat] = np.minimum(counts[flat].astype(np.int64) + n, 255).astype(np.uint8)
        ok = flat[counts[flat] >= self.need]
        if not len(ok):
            return False
        cells = np.stack([ok // self.shape[1], ok % self.shape[1]], axis=1)
        lo, hi = cells.min(axis=0), cells.max(axis=0)
        if self._lo_cell is not None:
            lo, hi = np.minimum(lo, self._lo_cell), np.maximum(hi, self._hi_cell)
            if (lo == self._lo_cell).all() and (hi == self._hi_cell).all():
                return False
        self._lo_cell, self._hi_cell = lo, hi
        return True

    def bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(lo, hi) (2,) m: the horizontal extent of the supported cells; None before any."""
        if self._lo_cell is None:
            return None
        return self.lo + self._lo_cell * self.cell, self.lo + (self._hi_cell + 1) * self.cell
