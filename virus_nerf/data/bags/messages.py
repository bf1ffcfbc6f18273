"""The ETHZ robot's message types (names, which role accepts which, a rosbags typestore that knows
them) and one decoder per message kind: a deserialised ROS message -> typed values (docs/method.md 4).

`import-bag` (stages.py, stack_writer.py), the stream (live.py) and a ROS 2 node call these
decoders and nothing else, so a message refused on one path is refused on every path, in the same
words. The rules a reading shares with the ETHZ layout's files (the IRS plausibility bound and zone
order, a depth map's invalid values, the USS echo code, the unit quaternion) live once beside the
sensor (sensors/irs.py, sensors/uss.py, data/images.py, sensors/geometry.py), called from here and
from data/ethz.py.

The decoders are pure: they read the message's fields as rosbags or rclpy deserialise them (no ROS
install needed; the two custom messages are registered from their `.msg` text), return metres and
seconds (where the layout stores another unit, the reading keeps that raw value too, so an import
writes exactly what the message held), and raise `MessageError` naming the source, topic, message
and field, and what was expected.
"""

from __future__ import annotations

import io
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from virus_nerf.data.bags.odometry import Transform
from virus_nerf.data.images import depth_from_mm, depth_to_mm
from virus_nerf.errors import DataFormatError
from virus_nerf.sensors import irs, uss
from virus_nerf.sensors.camera import Intrinsics, intrinsics_problem
from virus_nerf.sensors.geometry import QUATERNION_NORM_TOLERANCE, pose_matrix

# Custom messages of the ETHZ robot (ROS package `sensors`). USS: the echo time of the first
# echo in microseconds (metres = meas / 5000, >= 50000 = no echo). TOF: the 64 zones of the
# 8x8 infrared ToF in mm in sensor order (0 = invalid) and their standard deviations.
USS_TYPE = "sensors/msg/USS"
TOF_TYPE = "sensors/msg/TOF"
USS_MSG = "std_msgs/Header header\nuint32 meas\n"
TOF_MSG = "std_msgs/Header header\nuint16[] meas\nuint16[] stds\n"

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
RANGE = "sensor_msgs/msg/Range"
CLOUD = "sensor_msgs/msg/PointCloud2"
TF = "tf2_msgs/msg/TFMessage"
ODOMETRY = "nav_msgs/msg/Odometry"

# Which message types each role accepts (the importer refuses a topic of any other type).
ACCEPTED: dict[str, tuple[str, ...]] = {
    "color": (IMAGE, COMPRESSED),
    "depth": (IMAGE, COMPRESSED),
    "camera_info": (CAMERA_INFO,),
    "uss": (USS_TYPE, RANGE),
    "tof": (TOF_TYPE,),
    "lidar": (CLOUD,),
    "tf": (TF,),
    "odometry": (ODOMETRY,),  # wheel (or any) odometry: map-bag --poses odometry
}


def custom_types() -> dict:
    """rosbags type definitions of the two custom messages."""
    from rosbags.typesys import get_types_from_msg

    return {**get_types_from_msg(USS_MSG, USS_TYPE), **get_types_from_msg(TOF_MSG, TOF_TYPE)}


def make_typestore(ros_version: int):
    """ROS 1 Noetic or ROS 2 Humble standard types plus the custom ones."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros_version == 1 else Stores.ROS2_HUMBLE)
    store.register(custom_types())
    if TF not in store.fielddefs:  # rosbags' Noetic store lacks tf2_msgs, which ROS 1's /tf carries
        from rosbags.typesys import get_types_from_msg

        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF))
    return store


def normalise_type(name: str) -> str:
    """'sensors/USS' (ROS 1) -> 'sensors/msg/USS'; the custom names are matched case-insensitively."""
    parts = name.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    full = "/".join(parts)
    for custom in (USS_TYPE, TOF_TYPE):
        if full.lower() == custom.lower():
            return custom
    return full


# ------------------------------------------------------------------------------- decoding
class MessageError(DataFormatError):
    """A message that cannot be decoded or fails a check: `topic`, `index` (0-based) and `field`
    name it; the text is "SOURCE, field 'F': topic T, message N: what is wrong; what was expected"."""

    def __init__(self, source: str | Path, topic: str, index: int | None, problem: str,
                 field: str | None = None) -> None:
        self.topic, self.index = topic, index
        at = f"topic {topic}" if index is None else f"topic {topic}, message {index + 1}"
        super().__init__(source, f"{at}: {problem}", field=field)


@dataclass(frozen=True)
class Where:
    """Where a message came from, for its errors: a bag (or a node's name), topic and index."""

    source: str | Path
    topic: str
    index: int | None = None

    def error(self, problem: str, field: str | None = None) -> MessageError:
        return MessageError(self.source, self.topic, self.index, problem, field=field)


def stamp_s(msg) -> float:
    """Header stamp in seconds (0.0 when the message has no header or an unset stamp). A
    TFMessage, which has no header, is stamped by its newest transform: the robot's clock, as every
    other topic (its receive time may be another clock: a bag of sim time, a replayed bag)."""
    header = getattr(msg, "header", None)
    if header is None:
        transforms = getattr(msg, "transforms", None)
        return max((stamp_s(tr) for tr in transforms), default=0.0) if transforms is not None else 0.0
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def frame_id(msg) -> str:
    """The header's frame, without the leading '/' ROS 1 allowed (tf names frames without it)."""
    return msg.header.frame_id.lstrip("/")


# ----------------------------------------------------------------------------------- images
def decode_color(msg, msgtype: str, where: Where, size: tuple[int, int] | None = None) -> np.ndarray:
    """Image or CompressedImage -> (H, W, 3) uint8 RGB; size (width, height): the camera info's,
    refused when the image differs."""
    if msgtype == COMPRESSED:
        rgb = _decompress(msg, where)
        if rgb.dtype == np.uint16:  # a 16-bit PNG (mono16 through image_transport): its top byte, as PIL's RGB
            rgb = (rgb >> 8).astype(np.uint8)
        if rgb.ndim == 2:
            rgb = np.repeat(rgb[..., None], 3, axis=2)
        rgb = np.ascontiguousarray(rgb[..., :3].astype(np.uint8))
    else:
        enc = msg.encoding.lower()
        channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}
        if enc not in channels:
            raise where.error(f"colour encoding {msg.encoding!r}; expected rgb8, bgr8, rgba8, bgra8 or mono8",
                              field="encoding")
        px = _pixels(msg, np.uint8, channels[enc], where)
        if enc == "mono8":
            rgb = np.repeat(px, 3, axis=2)
        else:
            rgb = np.ascontiguousarray((px[..., 2::-1] if enc.startswith("bgr") else px)[..., :3])
    if size is not None and (rgb.shape[1], rgb.shape[0]) != tuple(size):
        raise where.error(f"image is {rgb.shape[1]}x{rgb.shape[0]}; the camera info says {size[0]}x{size[1]}")
    return rgb


@dataclass(frozen=True, eq=False)
class DepthImage:
    """An aligned depth image as the layout stores it (uint16 z-depth in mm, 0 and 65535 invalid)."""

    mm: np.ndarray  # (H, W) uint16

    def metres(self) -> np.ndarray:
        """(H, W) float32 z-depth in metres, NaN invalid: data/images.py's rule for a .npy map."""
        return depth_from_mm(self.mm)


def decode_depth(msg, msgtype: str, where: Where, size: tuple[int, int] | None = None) -> DepthImage:
    """Aligned depth: 16UC1/mono16 (mm) as is, 32FC1 from metres (non-finite or <= 0 -> 0), a
    16-bit PNG CompressedImage, or image_transport's compressedDepth (16UC1 or 32FC1 inside); size
    (width, height): the colour image's, refused when it differs."""
    if msgtype == COMPRESSED and "compresseddepth" in msg.format.lower().replace(" ", ""):
        mm = _compressed_depth_mm(msg, where)
    elif msgtype == COMPRESSED:
        mm = _decompress(msg, where)
        if mm.ndim != 2 or mm.dtype != np.uint16:
            raise where.error("compressed depth must be a 16-bit single-channel PNG (mm) or image_transport's "
                              "compressedDepth", field="format")
    else:
        enc = msg.encoding.lower()
        if enc in ("16uc1", "mono16"):
            mm = _pixels(msg, np.uint16, 1, where)[..., 0]
        elif enc == "32fc1":
            mm = depth_to_mm(_pixels(msg, np.float32, 1, where)[..., 0])
        else:
            raise where.error(f"depth encoding {msg.encoding!r}; expected 16UC1 (mm) or 32FC1 (m)", field="encoding")
    if size is not None and (mm.shape[1], mm.shape[0]) != tuple(size):
        raise where.error(f"depth map is {mm.shape[1]}x{mm.shape[0]}; the colour image is {size[0]}x{size[1]} "
                          "(expected depth aligned to colour)")
    return DepthImage(mm)


def _pixels(msg, dtype, channels: int, where: Where) -> np.ndarray:
    """Image.data with its row step -> (H, W, C) array of `dtype`."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    item = np.dtype(dtype).itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if h <= 0 or w <= 0:
        raise where.error(f"image of {w}x{h}; expected a width and height of at least 1 pixel", field="width")
    if step < w * channels * item:
        raise where.error(f"step {step} bytes is shorter than a row of {w} pixels of {channels * item} bytes "
                          f"({w * channels * item})", field="step")
    if data.size < h * step:
        raise where.error(f"image of {w}x{h}, step {step} holds {data.size} bytes; expected {h * step}", field="data")
    rows = data[: h * step].reshape(h, step)[:, : w * channels * item]
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    return np.ascontiguousarray(rows).view(dt).reshape(h, w, channels).astype(dtype)


def _decompress(msg, where: Where, skip: int = 0) -> np.ndarray:
    """A CompressedImage's data (after `skip` header bytes) decoded by PIL: (H, W) uint16 for a
    16-bit image, (H, W) or (H, W, 3) uint8 otherwise."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(bytes(np.asarray(msg.data, dtype=np.uint8))[skip:])) as im:
            if im.mode in ("I;16", "I;16B", "I"):
                return np.asarray(im, dtype=np.uint16)
            return np.asarray(im.convert("RGB") if im.mode not in ("L", "RGB") else im)
    except UnidentifiedImageError:
        raise where.error(f"compressed image ({msg.format!r}) cannot be decoded: not an image format PIL reads "
                          "(PNG, JPEG, ...)", field="data") from None
    except OSError as exc:
        raise where.error(f"compressed image ({msg.format!r}) cannot be decoded: {exc}", field="data") from None


# image_transport's compressedDepth: a 12-byte header (int32 format, float32 depthQuantA, depthQuantB)
# before the PNG; 16UC1 keeps millimetres, 32FC1 stores quantised inverse depth (0 = invalid)
COMPRESSED_DEPTH_HEADER = struct.Struct("<iff")


def _compressed_depth_mm(msg, where: Where) -> np.ndarray:
    """(H, W) uint16 mm of an image_transport compressedDepth message ('16UC1; compressedDepth png'
    or '32FC1; compressedDepth png')."""
    fmt = msg.format.lower()
    if "rvl" in fmt:
        raise where.error(f"compressed depth {msg.format!r}: the RVL codec is not read; expected compressedDepth png "
                          "(image_transport's default) or a 16-bit PNG", field="format")
    data = bytes(np.asarray(msg.data, dtype=np.uint8))
    if len(data) <= COMPRESSED_DEPTH_HEADER.size:
        raise where.error(f"compressed depth holds {len(data)} bytes; expected a 12-byte header and a PNG", field="data")
    _, quant_a, quant_b = COMPRESSED_DEPTH_HEADER.unpack_from(data)
    raw = _decompress(msg, where, skip=COMPRESSED_DEPTH_HEADER.size)
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise where.error(f"compressed depth {msg.format!r} holds no 16-bit single-channel PNG", field="data")
    if not fmt.startswith("32fc1"):
        return raw  # 16UC1: millimetres as they were
    v = raw.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        metres = np.where(v > 0, quant_a / (v - quant_b), np.nan)
    return depth_to_mm(metres)


@dataclass(frozen=True)
class CameraInfo:
    """A pinhole camera and the distortion coefficients its message held (not modelled: the layout
    is pinhole; `distorted` says whether an import should note them)."""

    intrinsics: Intrinsics
    distortion: tuple[float, ...] = ()

    @property
    def distorted(self) -> bool:
        return bool(self.distortion) and max(abs(d) for d in self.distortion) > 1e-6


def decode_camera_info(msg, where: Where) -> CameraInfo:
    """CameraInfo K (ROS 1 'K', ROS 2 'k') and D -> the intrinsics of the images published with
    it, refused as an implausible intrinsics file is (sensors/camera.py `intrinsics_problem`).
    REP 104: K, width and height are the full sensor's; a region of interest crops the image and
    binning divides it (0 and 1: none), as image_geometry's camera model applies them."""
    k = np.asarray(msg.K if hasattr(msg, "K") else msg.k, dtype=np.float64).ravel()
    if k.size != 9 or not np.isfinite(k).all() or k[0] <= 0 or k[4] <= 0 or msg.width <= 0 or msg.height <= 0:
        raise where.error(f"camera matrix {k.tolist()} at {msg.width}x{msg.height} is not a valid pinhole camera",
                          field="K")
    fx, fy, cx, cy = float(k[0]), float(k[4]), float(k[2]), float(k[5])
    width, height = int(msg.width), int(msg.height)
    roi = getattr(msg, "roi", None)
    if roi is not None and int(roi.width) > 0 and int(roi.height) > 0:
        x0, y0 = int(roi.x_offset), int(roi.y_offset)
        if x0 + int(roi.width) > width or y0 + int(roi.height) > height:
            raise where.error(f"region of interest {roi.width}x{roi.height} at ({x0}, {y0}) reaches outside the "
                              f"{width}x{height} sensor", field="roi")
        cx, cy, width, height = cx - x0, cy - y0, int(roi.width), int(roi.height)
    bx, by = max(1, int(getattr(msg, "binning_x", 0))), max(1, int(getattr(msg, "binning_y", 0)))
    fx, fy, cx, cy, width, height = fx / bx, fy / by, cx / bx, cy / by, width // bx, height // by
    problem = intrinsics_problem(fx, fy, cx, cy, width, height)
    if problem is not None:  # e.g. a camera driver that publishes K of another resolution, or zeros
        name, what = problem
        raise where.error(f"camera matrix {name}: {what}", field="K")
    d = np.asarray(getattr(msg, "D", getattr(msg, "d", ())), dtype=np.float64).ravel()
    return CameraInfo(Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=width, height=height), tuple(float(v) for v in d))


# ------------------------------------------------------------------------- range sensors
def _field(msg, name: str, where: Where):
    """msg.name, or a named error when a custom message of the bag lacks the field."""
    if not hasattr(msg, name):
        raise where.error(f"message has no field {name!r}; expected the ETHZ layout "
                          f"({USS_MSG.strip()!r} / {TOF_MSG.strip()!r})", field=name)
    return getattr(msg, name)


@dataclass(frozen=True)
class UssReading:
    """One ultrasonic reading; `echo_us` is what the layout's USS file stores (>= 50000: no echo)."""

    echo_us: float

    @property
    def range_m(self) -> float:
        """Radial range in metres, NaN = no echo (sensors/uss.py `range_from_raw`, as a USS file)."""
        return float(uss.range_from_raw(np.array([self.echo_us]))[0])


def decode_uss(msg, msgtype: str, where: Where) -> UssReading:
    """sensors/msg/USS (echo time in us, as is) or sensor_msgs/Range (m * 5000). REP 117: -Inf is
    something nearer than min_range, an echo there (the datasheet's 2 cm without a min_range);
    +Inf (nothing within max_range), NaN and <= 0 are no echo. A finite range outside
    [min_range, max_range) is no echo too: Range.msg discards it, and drivers publish max_range
    itself when nothing answered (no echo claims nothing: `maps/evidence.py`). A finite range or
    max_range beyond uss.USS_MAX_PLAUSIBLE_M is refused (centimetres)."""
    if msgtype == USS_TYPE:
        return UssReading(float(_field(msg, "meas", where)))
    r = float(msg.range)
    for name, value in (("max_range", float(msg.max_range)), ("range", r)):
        if np.isfinite(value) and value > uss.USS_MAX_PLAUSIBLE_M:
            raise where.error(f"{value:g} m is beyond any ultrasonic {'reading' if name == 'range' else 'range'} "
                              f"(> {uss.USS_MAX_PLAUSIBLE_M:g} m); expected metres (centimetres?)", field=name)
    if r == -np.inf:
        near = float(msg.min_range)
        return UssReading((near if np.isfinite(near) and near > 0 else uss.USS_MIN_RANGE_M) * uss.USS_RAW_PER_M)
    far, near = float(msg.max_range), float(getattr(msg, "min_range", 0.0))
    if not np.isfinite(r) or r <= 0 or (far > 0 and r >= far) or (near > 0 and r < near):
        return UssReading(uss.USS_NO_ECHO_RAW)
    return UssReading(r * uss.USS_RAW_PER_M)


@dataclass(frozen=True, eq=False)
class TofReading:
    """One IRS (ToF) reading; meas_mm/stds_mm are what the layout's TOF file stores."""

    meas_mm: np.ndarray  # (64,) float64 mm, sensor order, 0 = invalid
    stds_mm: np.ndarray  # (64,) float64 mm, 65535 = none

    def grid_m(self) -> np.ndarray:
        """(8, 8) z-depth in metres in image zone order, NaN invalid (sensors/irs.py, as a TOF file)."""
        return irs.grid_from_mm(self.meas_mm)


TOF_UNIT_MIN_TARGETS = 8  # zones with a target before a message whose readings are all below 10 mm is refused


def decode_tof(msg, where: Where) -> TofReading:
    """sensors/msg/TOF -> 64 zones in mm; a zone beyond 100 m is refused (irs.IRS_MAX_PLAUSIBLE_MM:
    the TOF file's check), and so is a message whose TOF_UNIT_MIN_TARGETS or more target zones all
    read below 10 mm (metres: irs.metres_problem, the TOF file's check); stds 65535 where the
    message has none."""
    meas = np.asarray(_field(msg, "meas", where), dtype=np.float64)
    if meas.size != irs.IRS_ZONE_COUNT:
        raise where.error(f"has {meas.size} zones; expected 64 (8x8)", field="meas")
    far = irs.implausible_zones(meas)
    if far.size:
        k = int(far[0, 0])
        raise where.error(irs.implausible_problem(float(meas[k])), field=f"meas[{k}]")
    if (problem := irs.metres_problem(meas, min_targets=TOF_UNIT_MIN_TARGETS)) is not None:
        raise where.error(problem.replace("the file holds", "the message holds"), field="meas")
    stds = np.asarray(getattr(msg, "stds", ()), dtype=np.float64)
    if stds.size != irs.IRS_ZONE_COUNT:
        stds = np.full(irs.IRS_ZONE_COUNT, 65535.0)
    return TofReading(meas, stds)


class TofUnitCheck:
    """The metres check over each ToF topic's messages so far, as the TOF file's check takes the
    whole file: one message of a room seen from its middle holds 0-11 targets (a simulated office),
    too few for `decode_tof`'s check alone. A topic is millimetres from its first target reading
    of 10 mm up; it is refused (this message and every later one) once TOF_UNIT_MIN_TARGETS target
    readings came, all below 10 mm."""

    def __init__(self) -> None:
        self._seen: dict[str, tuple[int, float]] = {}  # topic -> (target readings, the largest) mm

    def add(self, reading: TofReading, where: Where) -> None:
        count, largest = self._seen.get(where.topic, (0, 0.0))
        if largest >= irs.METRES_BELOW_MM:
            return
        mm = reading.meas_mm
        targets = mm[np.isfinite(mm) & (mm > 0)]
        if targets.size:
            count, largest = count + int(targets.size), max(largest, float(targets.max()))
            self._seen[where.topic] = (count, largest)
        if count >= TOF_UNIT_MIN_TARGETS and largest < irs.METRES_BELOW_MM:
            raise where.error(f"every reading of the topic up to here is below 10 mm ({count} readings, the largest "
                              f"{largest:g}); expected millimetres (the topic holds metres?)", field="meas")


# ---------------------------------------------------------------------------------- LiDAR
_PCL_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def decode_cloud(msg, where: Where) -> np.ndarray:
    """PointCloud2 -> (M, 3) float64 x y z in the sensor frame, non-finite points removed."""
    fields = {f.name: f for f in msg.fields}
    missing = [n for n in ("x", "y", "z") if n not in fields]
    if missing:
        raise where.error(f"point fields {sorted(fields)}; expected x, y, z", field="fields")
    order = ">" if msg.is_bigendian else "<"
    width, height, step = int(msg.width), int(msg.height), int(msg.point_step)
    formats = [order + _PCL_TYPES.get(int(fields[c].datatype), "f4") for c in "xyz"]
    offsets = [int(fields[c].offset) for c in "xyz"]
    end = max(o + np.dtype(f).itemsize for o, f in zip(offsets, formats, strict=True))
    if step < end:
        raise where.error(f"point_step {step} bytes; the fields x, y, z end at byte {end} of a point",
                          field="point_step")
    row_step = int(msg.row_step) if height > 1 and int(msg.row_step) else width * step  # one row, or unset
    if row_step < width * step:
        raise where.error(f"row_step {row_step} bytes; a row of {width} points of {step} bytes needs "
                          f"{width * step}", field="row_step")
    data = np.asarray(msg.data, dtype=np.uint8)
    need = (height - 1) * row_step + width * step if width and height else 0
    if data.size < need:
        raise where.error(f"{height} rows of {width} points ({step} bytes a point, {row_step} a row) need {need} "
                          f"bytes; the message has {data.size}", field="data")
    dtype = np.dtype({"names": ["x", "y", "z"], "formats": formats, "offsets": offsets, "itemsize": step})
    if not need:
        return np.zeros((0, 3))
    # (height, row_step) bytes, each row's points the first width * point_step of its bytes (padding after)
    rows = np.frombuffer(data[:need].tobytes() + bytes(height * row_step - need), np.uint8).reshape(height, row_step)
    pts = np.ascontiguousarray(rows[:, : width * step]).view(dtype).ravel()
    xyz = np.stack([pts["x"], pts["y"], pts["z"]], axis=1).astype(np.float64)
    return xyz[np.isfinite(xyz).all(axis=1)]


def decode_scan(msg, where: Where, min_range_m: float, max_range_m: float) -> np.ndarray:
    """PointCloud2 -> (M, 3) float32: the points within [min_range_m, max_range_m] of the sensor,
    at the precision the layout's PCD files hold (what the importer writes and KISS-ICP registers)."""
    pts = decode_cloud(msg, where)
    r = np.linalg.norm(pts, axis=1)
    return pts[(r >= min_range_m) & (r <= max_range_m)].astype(np.float32)


# ---------------------------------------------------------------------------------- poses
def _check_pose(xyz: np.ndarray, quat: np.ndarray, where: Where, field: str) -> float:
    """The quaternion's norm; a non-finite pose or a quaternion off unit norm by more than
    QUATERNION_NORM_TOLERANCE (the pose files' check; zeros: an uninitialised publisher) is refused."""
    norm = float(np.linalg.norm(quat))
    if not (np.isfinite(xyz).all() and np.isfinite(quat).all()) or abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise where.error(f"pose {xyz.round(4).tolist()} / quaternion {quat.round(4).tolist()} is not finite or "
                          f"not of unit norm (| |q| - 1 | <= {QUATERNION_NORM_TOLERANCE:g})", field=field)
    return norm


def decode_odometry(msg, where: Where) -> np.ndarray:
    """nav_msgs/Odometry -> (4, 4) pose of its child frame (the robot) in its header's frame;
    the covariance and twist are not used."""
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    xyz = np.array([p.x, p.y, p.z], dtype=np.float64)
    quat = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    return pose_matrix(xyz, quat / _check_pose(xyz, quat, where, "pose.pose"))


def decode_tf(msg, where: Where, static: bool) -> list[Transform]:
    """tf2_msgs/TFMessage -> one Transform (child in parent at its own stamp) per entry, frames
    without a leading '/'; static: the message came on /tf_static."""
    out = []
    for k, tr in enumerate(msg.transforms):
        tt, q = tr.transform.translation, tr.transform.rotation
        xyz, quat = np.array([tt.x, tt.y, tt.z], dtype=np.float64), np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
        _check_pose(xyz, quat, where, f"transforms[{k}].transform")
        pose = pose_matrix(xyz, quat)  # normalised inside, as before the check existed
        out.append(Transform(stamp_s(tr), frame_id(tr), tr.child_frame_id.lstrip("/"), pose, static))
    return out
