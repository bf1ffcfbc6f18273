"""One synchronised sample of a sensor stack: what a robot hands the mapper while it drives.

The same units and conventions as `data.ethz.SensorStack` (docs/method.md 4): metres, seconds,
RGB, NaN for invalid readings, camera-to-world poses in OpenCV camera axes. A ROS node fills one
per synchronised (camera, depth, USS, IRS, pose) tuple; `SensorStack.frame(i)` reads one from a
recording.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from virus_nerf.data.csvtable import MAX_TIME_S
from virus_nerf.data.images import DEPTH_MAX_MM
from virus_nerf.errors import UsageError
from virus_nerf.sensors.camera import Intrinsics, image_side_problem, intrinsics_problem
from virus_nerf.sensors.irs import IRS_MAX_PLAUSIBLE_MM, IRS_MIN_VALID_M

MAX_DEPTH_M = DEPTH_MAX_MM / 1000.0  # the frame store keeps depth as uint16 millimetres (data/images.depth_to_mm)
TIME_RESOLUTION_S = 1e-3  # a stamp's type must hold it at least this finely (a float32 epoch time holds 128 s)
MAX_RANGE_M = IRS_MAX_PLAUSIBLE_MM / 1000  # no USS, IRS or depth camera of a robot reads 100 m: millimetres
# A camera whose optical axis lies within this of the vertical sees no room at camera height: its
# pose is in another axis convention (a ROS body frame: x forward, z up), as ros_maps.base_pose says
MIN_AXIS_TILT_DEG = 10.0


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


def _pose_problem(cam_to_world) -> str | None:
    """What keeps `cam_to_world` from being a rigid transform, in a few words; None when it is one."""
    try:
        pose = np.asarray(cam_to_world, dtype=np.float64)
    except (TypeError, ValueError):
        return f"got a {type(cam_to_world).__name__} that is not an array of numbers"
    if pose.shape != (4, 4):
        return f"shape {pose.shape}"
    if not np.isfinite(pose).all():
        return "a value is not finite"
    if not np.allclose(pose[3], (0, 0, 0, 1)):
        return f"last row {pose[3].tolist()}"
    rotation = pose[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-3):
        return f"rotation not orthonormal (R R^T off the identity by up to {np.abs(rotation @ rotation.T - np.eye(3)).max():.3g})"
    if not np.linalg.det(rotation) > 0:  # a mirror image (det -1) is not a pose
        return "rotation with det -1 (a mirror image)"
    return None


def check_frame(frame: SyncFrame, intrinsics: Mapping[int, Intrinsics]) -> None:
    """A frame the mapper can use, or a one-line UsageError naming the field and what was expected."""
    if not isinstance(frame, SyncFrame):
        raise UsageError(f"Mapper.add_frame frame: got a {type(frame).__name__}; expected a SyncFrame")
    sid = frame.stack_id
    if isinstance(sid, bool) or not isinstance(sid, numbers.Integral):
        raise UsageError(f"SyncFrame.stack_id {sid!r}: a {type(sid).__name__}; expected an int (a key of the "
                         "Mapper's intrinsics)")
    if sid not in intrinsics:
        raise UsageError(f"SyncFrame.stack_id {sid!r}: unknown stack; expected one of {sorted(intrinsics)} "
                         "(the stacks whose intrinsics the Mapper was given; Mapper.add_stack adds one)")
    intr = intrinsics[sid]
    t = frame.time
    if isinstance(t, bool) or not isinstance(t, numbers.Real) or not math.isfinite(t):
        raise UsageError(f"SyncFrame.time {t!r}: expected a finite number of seconds")
    if abs(t) > MAX_TIME_S:
        raise UsageError(f"SyncFrame.time {t!r}: beyond {MAX_TIME_S:g} s (the year 5138); expected seconds, "
                         "not milli-, micro- or nanoseconds")
    if isinstance(t, np.floating) and abs(np.spacing(t)) > TIME_RESOLUTION_S:  # a float32 epoch time: 128 s steps
        raise UsageError(f"SyncFrame.time {float(t)!r}: a {t.dtype} holds a time this large only to {float(np.spacing(t)):g} s; "
                         "expected seconds as a Python float or float64")
    rgb = frame.rgb
    want = (intr.height, intr.width, 3)
    if not isinstance(rgb, np.ndarray) or rgb.shape != want or rgb.dtype != np.uint8:
        got = f"{rgb.dtype} array of shape {rgb.shape}" if isinstance(rgb, np.ndarray) else type(rgb).__name__
        raise UsageError(f"SyncFrame.rgb (stack {sid}): got a {got}; expected uint8 of shape {want} "
                         "(RGB at the intrinsics' height x width)")
    if frame.depth is not None:
        if np.shape(frame.depth) != want[:2]:
            raise UsageError(f"SyncFrame.depth (stack {sid}): shape {np.shape(frame.depth)}; expected {want[:2]} "
                             "metres (NaN = invalid) or None")
        if not np.issubdtype(np.asarray(frame.depth).dtype, np.floating):
            raise UsageError(f"SyncFrame.depth (stack {sid}): {np.asarray(frame.depth).dtype} values; expected "
                             "floating-point metres (NaN = invalid): a 16UC1 image in millimetres divided by 1000")
        depth = np.asarray(frame.depth, dtype=np.float64)
        _check_ranges(f"SyncFrame.depth (stack {sid})", depth, "z-depths")
        if (far := np.nanmax(depth, initial=0.0)) > MAX_DEPTH_M:
            raise UsageError(f"SyncFrame.depth (stack {sid}): {far:g} m is beyond {MAX_DEPTH_M} m, the most the "
                             "frame store's millimetres hold; expected metres (NaN = invalid)")
    if (problem := _pose_problem(frame.cam_to_world)) is not None:
        raise UsageError(f"SyncFrame.cam_to_world (stack {sid}, time {frame.time}): {problem}; expected a finite "
                         "(4, 4) rigid transform (rotation with det +1, translation in metres, last row 0 0 0 1)")
    axis_z = float(np.asarray(frame.cam_to_world, dtype=np.float64)[2, 2])  # the optical axis' world z
    if looks_vertical(axis_z):
        raise UsageError(f"SyncFrame.cam_to_world (stack {sid}, time {frame.time}): the camera looks straight "
                         f"{'up' if axis_z > 0 else 'down'} ({math.degrees(math.acos(min(1.0, abs(axis_z)))):.1f} deg "
                         "from vertical); expected OpenCV camera axes (z forward, y down), not a ROS body frame "
                         "(x forward, z up), of a camera that sees the room, in a world whose z is up")
    if np.shape(frame.irs_range) != (8, 8):
        raise UsageError(f"SyncFrame.irs_range (stack {sid}): shape {np.shape(frame.irs_range)}; expected (8, 8) "
                         "zone depths in metres in image zone order (NaN = invalid)")
    kind = np.asarray(frame.irs_range).dtype.kind
    if kind in "bc":  # a bool mask would read as 1 m, complex values lose their imaginary part
        raise UsageError(f"SyncFrame.irs_range (stack {sid}): {np.asarray(frame.irs_range).dtype} values; expected "
                         "real (8, 8) zone depths in metres (NaN = invalid)")
    try:
        irs = np.asarray(frame.irs_range, dtype=np.float64)
    except (TypeError, ValueError):
        raise UsageError(f"SyncFrame.irs_range (stack {sid}): not numbers; expected (8, 8) zone depths in "
                         "metres (NaN = invalid)") from None
    _check_ranges(f"SyncFrame.irs_range (stack {sid})", irs, "ranges")
    uss = frame.uss_range
    if isinstance(uss, bool) or not isinstance(uss, numbers.Real) or np.isinf(uss) or uss < 0:
        raise UsageError(f"SyncFrame.uss_range (stack {sid}) {uss!r}: expected a range >= 0 m or NaN (no echo)")
    if uss > MAX_RANGE_M:
        raise UsageError(f"SyncFrame.uss_range (stack {sid}) {uss!r}: beyond {MAX_RANGE_M:g} m; expected metres")


def valid_ranges(uss_range: float, irs_range) -> tuple[float, np.ndarray]:
    """A checked frame's USS range and IRS zones (8, 8) in metres as the mapper keeps them: NaN
    where invalid, as the TOF and USS files are read (sensors/irs.py, sensors/uss.py): an IRS zone
    at or below IRS_MIN_VALID_M (0 is the sensor's "no target", which many drivers publish) and a
    USS range of 0 (no echo) are no readings, not obstacles at the lens."""
    irs = np.array(irs_range, dtype=np.float64)  # a copy: the caller's array is not changed
    irs[irs <= IRS_MIN_VALID_M] = np.nan
    uss = float(uss_range)
    return (math.nan if uss <= 0.0 else uss), irs


def _check_ranges(what: str, values: np.ndarray, kind: str) -> None:
    """Ranges in metres: >= 0, NaN where invalid, none beyond MAX_RANGE_M (millimetres given)."""
    finite = values[np.isfinite(values)]
    if (finite < 0).any() or np.isinf(values).any():
        low = float(np.nanmin(values)) if not np.isnan(values).all() else math.nan
        raise UsageError(f"{what}: holds negative or infinite values (min {low:g}); expected {kind} >= 0 m, "
                         "NaN where invalid")
    if finite.size and finite.max() > MAX_RANGE_M:
        raise UsageError(f"{what}: {finite.max():g} is beyond {MAX_RANGE_M:g} m; expected metres, not millimetres")


def looks_vertical(axis_z):
    """True (per pose) where the optical axis' world z (cam_to_world[..., 2, 2]) is within
    MIN_AXIS_TILT_DEG of vertical: a ROS body frame (x forward, z up) or a world that is not z-up,
    not an OpenCV camera that sees the room."""
    return np.abs(axis_z) > math.cos(math.radians(MIN_AXIS_TILT_DEG))


def check_intrinsics(intrinsics: Mapping[int, Intrinsics], what: str = "Mapper intrinsics") -> None:
    """Stacks' intrinsics the mapper can use (as the readers check a file's), all of one image size
    (one training batch holds every camera's pixels), or a one-line UsageError naming the field
    (`what`: the argument, as the caller's user knows it)."""
    if not isinstance(intrinsics, Mapping):
        raise UsageError(f"{what}: got a {type(intrinsics).__name__}; expected a dict stack id -> "
                         "virus_nerf.sensors.camera.Intrinsics")
    for sid, intr in intrinsics.items():
        where = f"{what}[{sid!r}]"
        if isinstance(sid, bool) or not isinstance(sid, numbers.Integral):
            raise UsageError(f"{where}: the key {sid!r} is a {type(sid).__name__}; expected the stack id as an int "
                             "(SyncFrame.stack_id)")
        if not isinstance(intr, Intrinsics):
            raise UsageError(f"{where}: got a {type(intr).__name__}; expected a virus_nerf.sensors.camera.Intrinsics")
        for name in ("fx", "fy", "cx", "cy", "width", "height"):
            v = getattr(intr, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v):
                raise UsageError(f"{where}.{name} {v!r}: expected a finite number of pixels")
        for name in ("width", "height"):
            problem = image_side_problem(getattr(intr, name), name)
            if problem:
                raise UsageError(f"{where}.{name}: {problem}")
        bad = intrinsics_problem(intr.fx, intr.fy, intr.cx, intr.cy, int(intr.width), int(intr.height))
        if bad:
            raise UsageError(f"{where}.{bad[0]}: {bad[1]}")
    sizes = {(int(i.width), int(i.height)) for i in intrinsics.values()}
    if len(sizes) > 1:
        shown = ", ".join(f"stack {s} {int(i.width)}x{int(i.height)}" for s, i in intrinsics.items())
        raise UsageError(f"{what}: the stacks' images differ in size ({shown}); expected one size for "
                         "every camera (resize the images and scale the intrinsics alike)")
