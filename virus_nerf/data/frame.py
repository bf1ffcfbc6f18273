"""One synchronised sample of a sensor stack: what a robot hands the mapper while it drives.

The same units and conventions as `data.ethz.SensorStack` (docs/method.md 4): metres, seconds,
RGB, NaN for invalid readings, camera-to-world poses in OpenCV camera axes. A ROS node fills one
per synchronised (camera, depth, USS, IRS, pose) tuple; `SensorStack.frame(i)` reads one from a
recording.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from virus_nerf.errors import UsageError
from virus_nerf.sensors.camera import Intrinsics


@dataclass(frozen=True, eq=False)
class SyncFrame:
    """Sensor stack `stack_id`'s readings at `time`."""

    time: float  # s, the camera timestamp
    stack_id: int  # which stack (its intrinsics were given to the mapper)
    rgb: np.ndarray  # (H, W, 3) uint8 RGB at the camera's full resolution (its Intrinsics' size)
    cam_to_world: np.ndarray  # (4, 4) camera pose, OpenCV axes (x right, y down, z forward), metres
    uss_range: float  # m, radial echo range of the ultrasonic sensor; NaN = no echo
    irs_range: np.ndarray  # (8, 8) m, IRS zone z-depths in image zone order (row 0 = image top); NaN = invalid
    depth: np.ndarray | None = None  # (H, W) m, aligned depth image (z-depth); NaN = invalid; None = none


def check_frame(frame: SyncFrame, intrinsics: Mapping[int, Intrinsics]) -> None:
    """A frame the mapper can use, or a one-line UsageError naming the field and what was expected."""
    if not isinstance(frame, SyncFrame):
        raise UsageError(f"Mapper.add_frame frame: got a {type(frame).__name__}; expected a SyncFrame")
    sid = frame.stack_id
    if sid not in intrinsics:
        raise UsageError(f"SyncFrame.stack_id {sid!r}: unknown stack; expected one of {sorted(intrinsics)} "
                         "(the stacks whose intrinsics the Mapper was given)")
    intr = intrinsics[sid]
    if not isinstance(frame.time, int | float) or not math.isfinite(frame.time):
        raise UsageError(f"SyncFrame.time {frame.time!r}: expected a finite number of seconds")
    rgb = frame.rgb
    want = (intr.height, intr.width, 3)
    if not isinstance(rgb, np.ndarray) or rgb.shape != want or rgb.dtype != np.uint8:
        got = f"{rgb.dtype} array of shape {rgb.shape}" if isinstance(rgb, np.ndarray) else type(rgb).__name__
        raise UsageError(f"SyncFrame.rgb (stack {sid}): got a {got}; expected uint8 of shape {want} "
                         "(RGB at the intrinsics' height x width)")
    if frame.depth is not None and np.shape(frame.depth) != want[:2]:
        raise UsageError(f"SyncFrame.depth (stack {sid}): shape {np.shape(frame.depth)}; expected {want[:2]} "
                         "metres (NaN = invalid) or None")
    if frame.depth is not None:
        d = np.asarray(frame.depth, dtype=np.float64)
        if (d[np.isfinite(d)] < 0).any() or np.isinf(d).any():
            raise UsageError(f"SyncFrame.depth (stack {sid}): holds negative or infinite values (min "
                             f"{np.nanmin(d):g}); expected z-depths >= 0 m, NaN where invalid")
    pose = np.asarray(frame.cam_to_world, dtype=np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all() or not np.allclose(pose[3], (0, 0, 0, 1)) \
            or not np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-3) \
            or not np.linalg.det(pose[:3, :3]) > 0:  # a mirror image (det -1) is not a pose
        raise UsageError(f"SyncFrame.cam_to_world (stack {sid}, time {frame.time}): expected a finite (4, 4) "
                         "rigid transform (rotation with det +1, translation in metres, last row 0 0 0 1)")
    if np.shape(frame.irs_range) != (8, 8):
        raise UsageError(f"SyncFrame.irs_range (stack {sid}): shape {np.shape(frame.irs_range)}; expected (8, 8) "
                         "zone depths in metres in image zone order (NaN = invalid)")
    irs = np.asarray(frame.irs_range, dtype=np.float64)
    if (irs[np.isfinite(irs)] < 0).any() or np.isinf(irs).any():
        raise UsageError(f"SyncFrame.irs_range (stack {sid}): expected ranges >= 0 m or NaN")
    uss = frame.uss_range
    if not isinstance(uss, int | float | np.floating) or np.isinf(uss) or uss < 0:
        raise UsageError(f"SyncFrame.uss_range (stack {sid}) {uss!r}: expected a range >= 0 m or NaN (no echo)")
