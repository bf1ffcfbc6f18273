"""Infrared time-of-flight sensor (VL53L5CX): 8x8 zones over 45x45 deg, ranges as z-depth.

Zone layout and range convention were determined from the real sample (docs/method.md 4): comparing
the 64 ranges with the aligned RGB-D depth over all dihedral re-orderings of the 8x8 block and
both range conventions, the best agreement is

    grid[r, c] = meas[8 * (7 - c) + r]        (r = image zone row, c = image zone column)

i.e. the sensor's rows run along the image columns in reverse, and ranges are z-depth
(perpendicular to the sensor plane), not radial. `tests/test_irs_layout.py` shows it.
Zones are equal angular steps of 45/8 deg around the camera's optical axis, in the camera's
image orientation (the IRS shares its stack camera's origin and axis).
"""

from __future__ import annotations

import numpy as np

IRS_FOV_DEG = 45.0
IRS_ZONES = 8  # zones per axis
IRS_ZONE_COUNT = IRS_ZONES * IRS_ZONES  # 64 ranges per reading
IRS_MIN_VALID_M = 0.1  # readings at or below this are invalid (docs/method.md 4)
IRS_MAX_RANGE_M = 4.0
# A zone reading (mm) beyond 100 m cannot be a distance (the VL53L5CX reaches 4 m): it is a unit
# mix-up or garbage, refused wherever a reading enters (a TOF file, a bag, a stream), naming the zone.
IRS_MAX_PLAUSIBLE_MM = 100_000


def implausible_zones(meas_mm: np.ndarray) -> np.ndarray:
    """Indices (K, ndim) of the readings (mm) beyond IRS_MAX_PLAUSIBLE_MM, row-major (the first first)."""
    return np.argwhere(np.abs(np.asarray(meas_mm)) > IRS_MAX_PLAUSIBLE_MM)


# a target reading below this (mm) is metres: no VL53L5CX measures under 20 mm
METRES_BELOW_MM = 10.0


def metres_problem(meas_mm: np.ndarray, min_targets: int = 1) -> str | None:
    """The refusal of readings that look like metres: every target reading (finite, above 0, the
    sensor's "no target") below 10 mm, which no VL53L5CX measures (its range starts at 20 mm);
    None where they read as millimetres or fewer than `min_targets` zones hold a target (one
    message: a stray reading alone is no evidence of the unit)."""
    mm = np.asarray(meas_mm, dtype=np.float64)
    targets = mm[np.isfinite(mm) & (mm > 0)]
    if targets.size < max(1, min_targets) or targets.max() >= METRES_BELOW_MM:
        return None
    return (f"every reading is below 10 mm (the largest {targets.max():g}); expected millimetres "
            "(the file holds metres?)")


def implausible_problem(value_mm: float) -> str:
    """The refusal of a reading beyond IRS_MAX_PLAUSIBLE_MM, in one wording for files and messages."""
    return (f"{value_mm:g} mm ({value_mm / 1000:g} m) is beyond any IRS reading (> {IRS_MAX_PLAUSIBLE_MM} mm "
            f"= {IRS_MAX_PLAUSIBLE_MM // 1000} m); expected millimetres")


def grid_from_mm(meas_mm: np.ndarray) -> np.ndarray:
    """(..., 64) zone readings in mm, sensor order -> (..., 8, 8) metres in image zone order, NaN
    where invalid (non-finite, or at or below IRS_MIN_VALID_M: 0 is the sensor's "no target")."""
    mm = np.asarray(meas_mm, dtype=np.float64)
    metres = mm / 1000.0
    metres[~np.isfinite(mm) | (metres <= IRS_MIN_VALID_M)] = np.nan
    return grid_from_measurements(metres)


def grid_from_measurements(meas: np.ndarray) -> np.ndarray:
    """(..., 64) ranges in sensor order -> (..., 8, 8) grid in image zone order [row, col]."""
    m = np.asarray(meas).reshape(np.shape(meas)[:-1] + (8, 8))  # m[a, b] = meas[8a + b]
    # grid[r, c] = m[7 - c, r]  (a 90-degree clockwise rotation of the sensor block)
    return np.rot90(m, k=3, axes=(-2, -1)).copy()


def measurements_from_grid(grid: np.ndarray) -> np.ndarray:
    """Inverse of `grid_from_measurements`: (..., 8, 8) image order -> (..., 64) sensor order."""
    g = np.asarray(grid)
    m = np.rot90(g, k=1, axes=(-2, -1))
    return m.reshape(g.shape[:-2] + (IRS_ZONE_COUNT,)).copy()


def zone_edges_rad() -> np.ndarray:
    """(9,) zone boundary angles (rad) along either image axis, from -22.5 to +22.5 deg."""
    return np.deg2rad(np.linspace(-IRS_FOV_DEG / 2, IRS_FOV_DEG / 2, IRS_ZONES + 1))


def zone_of_directions(dirs_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zone (row, col) of camera-frame directions (N, 3); -1 where outside the field of view."""
    d = np.asarray(dirs_cam)
    ax = np.arctan2(d[..., 0], d[..., 2])  # horizontal angle (image columns)
    ay = np.arctan2(d[..., 1], d[..., 2])  # vertical angle (image rows)
    step = np.deg2rad(IRS_FOV_DEG / IRS_ZONES)
    col = np.floor((ax + np.deg2rad(IRS_FOV_DEG / 2)) / step).astype(np.int64)
    row = np.floor((ay + np.deg2rad(IRS_FOV_DEG / 2)) / step).astype(np.int64)
    outside = (col < 0) | (col >= IRS_ZONES) | (row < 0) | (row >= IRS_ZONES) | (d[..., 2] <= 0)
    col[outside] = -1
    row[outside] = -1
    return row, col


def zone_directions(samples_per_axis: int = 1) -> np.ndarray:
    """Camera-frame unit directions sampling each zone: (8, 8, s*s, 3).

    With s = 1 these are the zone centres; larger s covers each zone evenly.
    """
    edges = zone_edges_rad()
    step = edges[1] - edges[0]
    sub = (np.arange(samples_per_axis) + 0.5) / samples_per_axis * step
    angles = (edges[:-1, None] + sub[None, :]).reshape(-1)  # (8*s,)
    ay, ax = np.meshgrid(angles, angles, indexing="ij")
    d = np.stack([np.tan(ax), np.tan(ay), np.ones_like(ax)], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    s = samples_per_axis
    d = d.reshape(IRS_ZONES, s, IRS_ZONES, s, 3).transpose(0, 2, 1, 3, 4)
    return d.reshape(IRS_ZONES, IRS_ZONES, s * s, 3)


def zone_rays(cam_to_world: np.ndarray, z_depth: np.ndarray, samples_per_axis: int = 3,
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World rays covering every zone of frames (cam_to_world (F, 4, 4), z_depth (F, 8, 8) m,
    NaN = invalid) with samples_per_axis^2 rays each: origins (F, K, 3), unit directions
    (F, K, 3) and ranges (F, K) m along each ray (the zone's z-depth over the ray's d_z), float64,
    K = 64 s^2, zone-major."""
    s2 = samples_per_axis * samples_per_axis
    dirs_cam = zone_directions(samples_per_axis).reshape(-1, 3)  # (64 s^2, 3), zone-major
    poses = np.asarray(cam_to_world).reshape(-1, 4, 4)
    z = np.asarray(z_depth).reshape(len(poses), IRS_ZONE_COUNT)  # (F, 64)
    ranges = np.repeat(z, s2, axis=1) / dirs_cam[None, :, 2]  # (F, K)
    dirs = np.einsum("fij,kj->fki", poses[:, :3, :3], dirs_cam)  # (F, K, 3)
    return np.broadcast_to(poses[:, None, :3, 3], dirs.shape), dirs, ranges
