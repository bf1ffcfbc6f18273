"""A map whose extent is not known in advance (issue 29, item 2; docs/extent.md).

`fitted` (the default for offline training): the scene box is fitted before the first step from
the LiDAR map and the whole drive (engine/model.py fit_scene_box); the field's hash encoding and
the occupancy grid both span it.

`grow` (a robot in a room it has never seen): the Mapper starts from a box around its first
frame, the camera position grown by `reach_m` horizontally (the USS's 8 m reach) and the
no-map box's +-1.5 m vertically, and the box grows whenever a new frame's position plus `reach_m`
leaves it, by whole grid cells and at least `grow_step_m` at a time. Two things keep that exact:

- the occupancy grid's cells keep their size (`grid_cell_m`) and position; growing pads the cell
  array on its sides, every existing cell keeps its value (`GridSpec.grown`, `OccupancyGrid.grow`);
- the field's hash encoding is normalised to a fixed cube (`frame_m` on a side, centred on the
  first box) that never moves, with its resolutions set in metres (`field_coarse_m`,
  `field_fine_m`), so a point's features do not change when the box grows.

Memory is bounded: the hash tables have a fixed size, the grid has one float per cell of the
area driven (plus `reach_m`), at most the frame's cube. Frames beyond the frame cube are refused
with a one-line error naming the frame (a larger `frame_m` maps a larger area).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from virus_nerf.scene_box import SceneBox

EXTENT_MODES = ("fitted", "grow")


@dataclass(frozen=True)
class ExtentConfig:
    """How the Mapper bounds its map (module docstring), metres."""

    mode: str = "fitted"  # fitted | grow
    reach_m: float = 8.0  # grow: horizontal margin around every camera position (the URM37's reach)
    height_m: float = 1.5  # grow: the box spans the first camera's height +- this
    grow_step_m: float = 2.0  # grow: the box grows by at least this much on a side (fewer re-allocations)
    grid_cell_m: float = 0.08  # grow: occupancy grid cell (fitted: the longest box axis / max_resolution)
    frame_m: float = 64.0  # grow: side of the field's fixed cube, centred on the first box
    field_coarse_m: float = 0.6  # grow: coarsest hash level's cell (fitted office: 10 m / 16)
    field_fine_m: float = 0.02  # grow: finest hash level's cell (fitted office: 10 m / 512)

    def __post_init__(self) -> None:
        if self.mode not in EXTENT_MODES:
            raise ValueError(f"extent.mode {self.mode!r}: expected one of {', '.join(EXTENT_MODES)}")
        for name in ("reach_m", "height_m", "grow_step_m", "grid_cell_m", "frame_m", "field_coarse_m",
                     "field_fine_m"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v <= 0:
                raise ValueError(f"extent.{name} {v!r}: expected a positive number of metres")
        if self.field_fine_m > self.field_coarse_m:
            raise ValueError(f"extent.field_fine_m {self.field_fine_m}: expected at most field_coarse_m "
                             f"{self.field_coarse_m}")


def first_box(camera_position: np.ndarray, cfg: ExtentConfig) -> SceneBox:
    """The box around the first frame: its camera position +- reach (x, y) and +- height (z),
    whole grid cells on a side."""
    p = np.asarray(camera_position, dtype=np.float64).reshape(3)
    half = np.array([cfg.reach_m, cfg.reach_m, cfg.height_m])
    n = np.ceil(2 * half / cfg.grid_cell_m - 1e-9)  # cells per axis
    lo = p - n * cfg.grid_cell_m / 2
    return SceneBox(tuple(lo), tuple(lo + n * cfg.grid_cell_m))


def field_frame(box: SceneBox, cfg: ExtentConfig) -> SceneBox:
    """The field's fixed cube: `frame_m` on a side, centred on the first box."""
    c = np.asarray(box.center, dtype=np.float64)
    return SceneBox(tuple(c - cfg.frame_m / 2), tuple(c + cfg.frame_m / 2))


def field_config_for_frame(field, cfg: ExtentConfig):
    """The FieldConfig with its coarsest and finest resolutions set from metres over the frame."""
    return dataclasses.replace(field, base_resolution=max(1, round(cfg.frame_m / cfg.field_coarse_m)),
                               max_resolution=max(1, round(cfg.frame_m / cfg.field_fine_m)))


def needed_box(box: SceneBox, camera_position: np.ndarray, cfg: ExtentConfig, frame: SceneBox) -> SceneBox | None:
    """The grown box once a frame at `camera_position` arrives, or None when `box` already holds
    its reach. Grows each side that is short by at least `grow_step_m`, by whole cells of
    `grid_cell_m` (so cells keep their places), never beyond the field's frame (x, y); z is fixed."""
    p = np.asarray(camera_position, dtype=np.float64).reshape(3)
    lo, hi = np.array(box.lo, dtype=np.float64), np.array(box.hi, dtype=np.float64)
    want_lo, want_hi = p[:2] - cfg.reach_m, p[:2] + cfg.reach_m
    short_lo, short_hi = want_lo < lo[:2] - 1e-9, want_hi > hi[:2] + 1e-9
    if not (short_lo.any() or short_hi.any()):
        return None
    cell = cfg.grid_cell_m
    step = math.ceil(cfg.grow_step_m / cell - 1e-9)  # cells
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
