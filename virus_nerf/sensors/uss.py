"""Ultrasonic sensor (URM37): one range, the first echo inside a 55x35 deg elliptic cone.

The cone shares its stack camera's origin and optical axis; its wide (55 deg) axis is the
camera's x axis, which is horizontal on the robot. Ranges are radial (time of flight).
"""

from __future__ import annotations

import numpy as np

USS_FOV_H_DEG = 55.0
USS_FOV_V_DEG = 35.0
USS_NO_ECHO_RAW = 50000.0  # raw echo time (us) at or above which there was no echo
USS_RAW_PER_M = 5000.0  # raw microseconds per metre of range (docs/method.md 4)
USS_MIN_RANGE_M = 0.02  # the URM37 V5.0's nearest range (datasheet: 2-800 cm)
USS_MAX_RANGE_M = 8.0  # the URM37 V5.0's range (datasheet, docs/uss-range.md); bounds the box when there is no map
# A sensor_msgs/Range of an ultrasonic sensor beyond this (a reading or its max_range) is a unit
# mistake (centimetres: 800 cm read as 800 m), refused where a message enters, naming the field
USS_MAX_PLAUSIBLE_M = 100.0


# A raw reading beyond this is no echo time in microseconds (nanoseconds? the sensor's own no-echo
# code is USS_NO_ECHO_RAW): refused where a table is read, naming the row
USS_MAX_PLAUSIBLE_RAW = 10 * USS_NO_ECHO_RAW


def raw_unit_problem(raw: np.ndarray) -> tuple[int | None, str] | None:
    """A USS table's echo times (N,) that are not microseconds: (the first bad row's index or None,
    the problem) or None. A reading beyond USS_MAX_PLAUSIBLE_RAW (nanoseconds?), or every echo
    below the sensor's nearest range (USS_MIN_RANGE_M, 100 us: metres?); no echo (0, NaN, the
    no-echo code) says nothing of the unit."""
    raw = np.asarray(raw, dtype=np.float64)
    beyond = np.flatnonzero(np.isfinite(raw) & (raw > USS_MAX_PLAUSIBLE_RAW))
    if beyond.size:
        value = float(raw[beyond[0]])
        return int(beyond[0]), (f"{value:g} is beyond any echo time (> {USS_MAX_PLAUSIBLE_RAW:g} us; the sensor's "
                                f"no-echo code is {USS_NO_ECHO_RAW:g}); expected microseconds (the file holds "
                                "nanoseconds?)")
    echoes = raw[np.isfinite(raw) & (raw > 0) & (raw < USS_NO_ECHO_RAW)]
    nearest_raw = USS_MIN_RANGE_M * USS_RAW_PER_M
    if echoes.size and echoes.max() < nearest_raw:
        return None, (f"every echo time is below {nearest_raw:g} us, the sensor's nearest range of "
                      f"{USS_MIN_RANGE_M * 100:g} cm (the largest {echoes.max():g}); expected microseconds "
                      "(the file holds metres?)")
    return None


def range_from_raw(raw: np.ndarray) -> np.ndarray:
    """Raw echo times (us) -> ranges in metres, NaN where there was no echo."""
    raw = np.asarray(raw, dtype=np.float64)
    out = raw / USS_RAW_PER_M
    out[~np.isfinite(raw) | (raw >= USS_NO_ECHO_RAW) | (raw <= 0)] = np.nan
    return out


def raw_from_range(range_m: np.ndarray) -> np.ndarray:
    """Inverse of `range_from_raw`; NaN (no echo) becomes the no-echo code."""
    r = np.asarray(range_m, dtype=np.float64)
    return np.where(np.isfinite(r), np.round(r * USS_RAW_PER_M), USS_NO_ECHO_RAW)


def in_cone(dirs_cam: np.ndarray) -> np.ndarray:
    """Whether camera-frame directions (N, 3) lie inside the elliptic cone (in angle space)."""
    d = np.asarray(dirs_cam)
    ax = np.arctan2(d[..., 0], d[..., 2])
    ay = np.arctan2(d[..., 1], d[..., 2])
    a = np.deg2rad(USS_FOV_H_DEG / 2)
    b = np.deg2rad(USS_FOV_V_DEG / 2)
    return ((ax / a) ** 2 + (ay / b) ** 2 <= 1.0) & (d[..., 2] > 0)


def cone_directions(n_h: int = 56, n_v: int = 36) -> np.ndarray:
    """Camera-frame unit directions on a regular angular grid inside the cone: (M, 3)."""
    ax = np.deg2rad(np.linspace(-USS_FOV_H_DEG / 2, USS_FOV_H_DEG / 2, n_h))
    ay = np.deg2rad(np.linspace(-USS_FOV_V_DEG / 2, USS_FOV_V_DEG / 2, n_v))
    ay, ax = np.meshgrid(ay, ax, indexing="ij")
    d = np.stack([np.tan(ax), np.tan(ay), np.ones_like(ax)], axis=-1).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return d[in_cone(d)]


def fan_offsets(step_deg: float = 1.0) -> np.ndarray:
    """(A,) rad: bearings across the cone's horizontal opening (+-27.5 deg around its axis), edges
    included, about `step_deg` apart: where the echo's arc lies at camera height."""
    half = np.deg2rad(USS_FOV_H_DEG / 2)
    return np.linspace(-half, half, int(np.ceil(USS_FOV_H_DEG / step_deg)) + 1)
