"""ROS message types of the ETHZ robot and decoding of messages into numpy (docs/method.md 4).

The two custom messages of the ETHZ recording are registered from their `.msg` text, so no ROS
install is needed. Decoders take a message deserialised by `rosbags` (a dataclass) and return
plain numpy values in the units the bag holds; the conversion to the layout's units happens
in the importer. Every decoder raises `DataFormatError` naming the bag, topic and field.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from virus_nerf.errors import DataFormatError
from virus_nerf.sensors.camera import Intrinsics, intrinsics_problem

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


def stamp_s(msg) -> float:
    """Header stamp in seconds (0.0 when the message has no header or an unset stamp)."""
    header = getattr(msg, "header", None)
    if header is None:
        return 0.0
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


class Where:
    """Bag + topic (+ message index) for error messages."""

    def __init__(self, bag: Path, topic: str, index: int) -> None:
        self.bag, self.topic, self.index = bag, topic, index

    def error(self, problem: str, field: str | None = None) -> DataFormatError:
        return DataFormatError(self.bag, f"topic {self.topic}, message {self.index + 1}: {problem}", field=field)


def decode_color(msg, msgtype: str, where: Where) -> np.ndarray:
    """Colour image -> (H, W, 3) uint8 RGB."""
    if msgtype == COMPRESSED:
        rgb = _decompress(msg, where)
        if rgb.ndim == 2:
            rgb = np.repeat(rgb[..., None], 3, axis=2)
        return np.ascontiguousarray(rgb[..., :3].astype(np.uint8))
    enc = msg.encoding.lower()
    channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}
    if enc not in channels:
        raise where.error(f"colour encoding {msg.encoding!r}; expected rgb8, bgr8, rgba8, bgra8 or mono8",
                          field="encoding")
    px = _pixels(msg, np.uint8, channels[enc], where)
    if enc == "mono8":
        return np.repeat(px, 3, axis=2)
    if enc.startswith("bgr"):
        px = px[..., 2::-1]
    return np.ascontiguousarray(px[..., :3])


def decode_depth(msg, msgtype: str, where: Where) -> np.ndarray:
    """Aligned depth -> (H, W) uint16 z-depth in mm, 0 = invalid (16UC1/mono16 as is, 32FC1 from m)."""
    if msgtype == COMPRESSED:
        px = _decompress(msg, where)
        if px.ndim != 2 or px.dtype != np.uint16:
            raise where.error("compressed depth must be a 16-bit single-channel PNG (mm)", field="format")
        return px
    enc = msg.encoding.lower()
    if enc in ("16uc1", "mono16"):
        return _pixels(msg, np.uint16, 1, where)[..., 0]
    if enc == "32fc1":
        m = _pixels(msg, np.float32, 1, where)[..., 0].astype(np.float64)
        mm = np.where(np.isfinite(m) & (m > 0), np.round(m * 1000.0), 0.0)
        return np.clip(mm, 0, 65534).astype(np.uint16)
    raise where.error(f"depth encoding {msg.encoding!r}; expected 16UC1 (mm) or 32FC1 (m)", field="encoding")


def _pixels(msg, dtype, channels: int, where: Where) -> np.ndarray:
    """Image.data with its row step -> (H, W, C) array of `dtype`."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    item = np.dtype(dtype).itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if h <= 0 or w <= 0 or step < w * channels * item or data.size < h * step:
        raise where.error(f"image of {w}x{h}, step {step} holds {data.size} bytes; expected {h * step}", field="data")
    rows = data[: h * step].reshape(h, step)[:, : w * channels * item]
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    return np.ascontiguousarray(rows).view(dt).reshape(h, w, channels).astype(dtype)


def _decompress(msg, where: Where) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(bytes(np.asarray(msg.data, dtype=np.uint8)))) as im:
            if im.mode in ("I;16", "I;16B", "I"):
                return np.asarray(im, dtype=np.uint16)
            return np.asarray(im.convert("RGB") if im.mode not in ("L", "RGB") else im)
    except (UnidentifiedImageError, OSError) as exc:
        raise where.error(f"compressed image ({msg.format!r}) cannot be decoded: {exc}", field="data") from None


def decode_camera_info(msg, where: Where) -> Intrinsics:
    """CameraInfo K (ROS 1 'K', ROS 2 'k') -> pinhole Intrinsics (distortion is not modelled)."""
    k = np.asarray(msg.K if hasattr(msg, "K") else msg.k, dtype=np.float64).ravel()
    if k.size != 9 or not np.isfinite(k).all() or k[0] <= 0 or k[4] <= 0 or msg.width <= 0 or msg.height <= 0:
        raise where.error(f"camera matrix {k.tolist()} at {msg.width}x{msg.height} is not a valid pinhole camera",
                          field="K")
    problem = intrinsics_problem(float(k[0]), float(k[4]), float(k[2]), float(k[5]), int(msg.width), int(msg.height))
    if problem is not None:  # e.g. a camera driver that publishes K of another resolution, or zeros
        name, what = problem
        raise where.error(f"camera matrix {name}: {what}", field="K")
    return Intrinsics(fx=float(k[0]), fy=float(k[4]), cx=float(k[2]), cy=float(k[5]),
                      width=int(msg.width), height=int(msg.height))


def _field(msg, name: str, where: Where):
    """msg.name, or a named error when a custom message of the bag lacks the field."""
    if not hasattr(msg, name):
        raise where.error(f"message has no field {name!r}; expected the ETHZ layout "
                          f"({USS_MSG.strip()!r} / {TOF_MSG.strip()!r})", field=name)
    return getattr(msg, name)


def decode_uss_us(msg, msgtype: str, where: Where) -> float:
    """USS reading -> echo time in microseconds (sensors/msg/USS as is; Range m * 5000, no echo 50000)."""
    if msgtype == USS_TYPE:
        return float(_field(msg, "meas", where))
    r = float(msg.range)
    if not np.isfinite(r) or r <= 0 or (msg.max_range > 0 and r > float(msg.max_range)):
        return 50000.0
    return r * 5000.0


def decode_tof(msg, where: Where) -> tuple[np.ndarray, np.ndarray]:
    """TOF -> meas (64,) mm in sensor order and stds (64,) mm (65535 where the message has none)."""
    meas = np.asarray(_field(msg, "meas", where), dtype=np.float64)
    if meas.size != 64:
        raise where.error(f"has {meas.size} zones; expected 64 (8x8)", field="meas")
    stds = np.asarray(getattr(msg, "stds", ()), dtype=np.float64)
    if stds.size != 64:
        stds = np.full(64, 65535.0)
    return meas, stds


_PCL_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def decode_cloud(msg, where: Where) -> np.ndarray:
    """PointCloud2 -> (M, 3) float64 x y z in the sensor frame, non-finite points removed."""
    fields = {f.name: f for f in msg.fields}
    missing = [n for n in ("x", "y", "z") if n not in fields]
    if missing:
        raise where.error(f"point fields {sorted(fields)}; expected x, y, z", field="fields")
    order = ">" if msg.is_bigendian else "<"
    n = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if n and data.size < n * step:
        raise where.error(f"{n} points of {step} bytes need {n * step} bytes; the message has {data.size}",
                          field="data")
    dtype = np.dtype({
        "names": ["x", "y", "z"],
        "formats": [order + _PCL_TYPES.get(int(fields[c].datatype), "f4") for c in "xyz"],
        "offsets": [int(fields[c].offset) for c in "xyz"],
        "itemsize": step,
    })
    pts = np.frombuffer(data[: n * step].tobytes(), dtype=dtype, count=n)
    xyz = np.stack([pts["x"], pts["y"], pts["z"]], axis=1).astype(np.float64)
    return xyz[np.isfinite(xyz).all(axis=1)]


def decode_odometry(msg, where: Where) -> np.ndarray:
    """nav_msgs/Odometry -> (4, 4) pose of its child frame (the robot) in its header's frame;
    the covariance and twist are not used. A non-finite pose or a quaternion far from unit norm
    is refused (a zero quaternion is what an uninitialised odometry publishes)."""
    from virus_nerf.sensors.geometry import pose_matrix

    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    xyz = np.array([p.x, p.y, p.z], dtype=np.float64)
    quat = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    norm = float(np.linalg.norm(quat))
    if not (np.isfinite(xyz).all() and np.isfinite(quat).all()) or abs(norm - 1.0) > 1e-3:
        raise where.error(f"pose {xyz.round(4).tolist()} / quaternion {quat.round(4).tolist()} is not finite or "
                          "not of unit norm", field="pose.pose")
    return pose_matrix(xyz, quat / norm)
