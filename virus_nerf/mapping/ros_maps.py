"""ROS-native maps out of the mapper: a rosbag2 in MCAP storage (issue 29, item 5).

`RosMapBag(path)` writes, without ROS installed (rosbags, the `ros` extra), a rosbag2 folder
PATH/ holding metadata.yaml and PATH/<folder name>.mcap (`RosMapBag.mcap_path`) that RViz 2
(`ros2 bag play PATH`) or Foxglove (open the .mcap) shows as it is:

- `/map` (nav_msgs/msg/OccupancyGrid): the trinary map (`Mapper.map2d`): 100 occupied, 0 free,
  -1 unknown, the values map_server would publish from the same map.pgm (its thresholds,
  maps.occupancy.OCCUPIED_THRESH / FREE_THRESH);
- `/map_probability` (nav_msgs/msg/OccupancyGrid): the VIRUS grid's occupancy probability
  (`Mapper.probability_map`) as round(100 p), 0..100, and -1 where no sensor looked (the value
  map_server serves from the same prob.pgm, `mode: raw`);
- `/tf` (tf2_msgs/msg/TFMessage): map -> base_link, one per frame of the stack(s) that give the
  robot's pose (`RobotStacks`: the mounted ones, else the first seen).

Both grids are in frame "map" (`map_frame`; the /tf child is `base_frame`); info.origin is the world (x, y, 0) of the lower-left corner of
the lower-left cell with identity orientation, info.resolution metres per cell. Cell data is
row-major from the lower-left (OccupancyGrid row 0 = smallest y), whereas the map images
(maps.occupancy, PGM) have row 0 = largest y: the rows are flipped on the way out.

Robot pose (map -> base_link), ROS body axes x forward, y left, z up. The mapper knows camera
poses in OpenCV axes (x right, y down, z forward). Two ways to a robot pose:
- with the camera's mount on the robot (`camera_in_base[stack_id]`, a (4, 4) camera-to-base
  transform, e.g. `sensors.rig.camera_in_lidar(stack)` with the LiDAR as base_link):
  base_to_map = cam_to_world @ inv(camera_in_base), the full 3D pose;
- without it, the camera levelled: base_link sits at the camera's position, x = the optical
  axis (camera z) projected onto the floor plane, z = world up, y = z cross x. For an upright,
  level camera this is the fixed axis change body (x, y, z) = camera (z, -x, -y); unlike that
  constant it keeps z up for cameras mounted pitched or upside down (the real rig's are both,
  sensors/rig.py).

Timestamps: `time_s` (the frames' recording time, seconds >= 0) becomes the header stamp and
the bag's receive time (nanoseconds).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from virus_nerf.errors import OutputExistsError, UsageError, install_extra
from virus_nerf.maps.occupancy import FREE_THRESH, OCCUPIED_THRESH, OccupancyMap2D
from virus_nerf.sensors.geometry import invert_pose, matrix_to_quat

MAP_TOPIC = "/map"
PROB_TOPIC = "/map_probability"
TF_TOPIC = "/tf"
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
DISTROS = ("humble", "jazzy")


class RobotStacks:
    """Which stacks' cameras give the robot's pose (base_link): with mounts, every mounted stack
    (each mount puts its camera on the same body); without, the first stack seen alone. The rig's
    two cameras stand 0.28 m apart and look 15 deg to either side, so their levelled poses taken
    in turn would make base_link jump back and forth between them at the camera rate."""

    def __init__(self, mounted: Mapping[int, np.ndarray] | None = None) -> None:
        self.mounted = frozenset(int(k) for k in (mounted or {}))
        self.first: int | None = None

    def drives(self, stack_id: int | None) -> bool:
        """Whether a frame of `stack_id` gives the robot pose (None: a caller of one camera, yes)."""
        if stack_id is None:
            return True
        if self.mounted:
            return int(stack_id) in self.mounted
        if self.first is None:
            self.first = int(stack_id)
        return int(stack_id) == self.first


def base_pose(cam_to_world: np.ndarray, camera_in_base: np.ndarray | None = None) -> np.ndarray:
    """(4, 4) base_link-to-map pose in ROS body axes (x forward, y left, z up) from a camera pose
    in OpenCV axes; with `camera_in_base` (the camera's (4, 4) mount on the robot) the full pose,
    without it the camera levelled (module docstring). Why levelled: a 2D map's robot turns about
    world z, and its base_link must keep z up whichever way the camera is mounted."""
    pose = np.asarray(cam_to_world, dtype=np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise UsageError(f"cam_to_world of shape {pose.shape}: expected a finite (4, 4) camera-to-world pose")
    if camera_in_base is not None:
        return pose @ invert_pose(np.asarray(camera_in_base, dtype=np.float64))
    forward = pose[:3, 2].copy()  # the optical axis in the world
    forward[2] = 0.0
    n = np.linalg.norm(forward)
    if n < 1e-6:
        raise UsageError("cam_to_world: the camera looks straight up or down; a levelled robot heading needs "
                         "an optical axis off the vertical (or give the camera's mount, camera_in_base)")
    x = forward / n
    z = np.array([0.0, 0.0, 1.0])
    out = np.eye(4)
    out[:3, :3] = np.column_stack([x, np.cross(z, x), z])  # columns: body x, y, z in the world
    out[:3, 3] = pose[:3, 3]
    return out


def occupancy_values(m: OccupancyMap2D) -> np.ndarray:
    """(H, W) int8 OccupancyGrid values of a map image, rows still image order (row 0 = top).

    raw: the value itself where it is 0..100, else -1, as map_server's raw mode (the probability
    map, round(100 p)). trinary and scale go through p = (255 - value) / 255, the occupancy
    probability map_server reads from the PGM (negate 0). trinary: 100 where p > OCCUPIED_THRESH,
    0 where p < FREE_THRESH, -1 in between (0 -> 100, 254 -> 0, 205 -> -1), as map_server's
    trinary mode; scale: round(100 p) in 0..100 (the probability itself, not map_server's
    rescaling between the thresholds, so that a reader gets p back to 1 %)."""
    img = np.asarray(m.image)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise UsageError(f"OccupancyMap2D.image {img.dtype} of shape {img.shape}: expected (H, W) uint8")
    if m.mode == "raw":
        return np.where(img <= 100, img, -1).astype(np.int8)
    p = (255.0 - img) / 255.0  # (H, W)
    if m.mode == "trinary":
        out = np.full(img.shape, -1, dtype=np.int8)
        out[p > OCCUPIED_THRESH] = 100
        out[p < FREE_THRESH] = 0
        return out
    if m.mode == "scale":
        return np.rint(100.0 * p).astype(np.int8)
    raise UsageError(f"OccupancyMap2D.mode {m.mode!r}: expected 'trinary', 'scale' or 'raw'")


def grid_data(m: OccupancyMap2D) -> np.ndarray:
    """(H * W,) int8 OccupancyGrid.data: rows flipped so that row 0 = smallest y, row-major."""
    return np.ascontiguousarray(np.flipud(occupancy_values(m))).reshape(-1)


ROS_MAX_STAMP_S = 2**31 - 1  # builtin_interfaces/Time's sec is an int32


def stamp_ns(time_s: float) -> int:
    """Seconds -> nanoseconds (refused below 0): the bag's receive time and the header stamp."""
    if isinstance(time_s, bool) or not isinstance(time_s, int | float | np.floating) or not np.isfinite(time_s) \
            or time_s < 0:
        raise UsageError(f"time_s {time_s!r}: expected a finite time in seconds >= 0")
    if time_s > ROS_MAX_STAMP_S:  # builtin_interfaces/Time's sec is an int32
        raise UsageError(f"time_s {time_s!r}: beyond a ROS stamp's {ROS_MAX_STAMP_S} s (the year 2038); expected "
                         "seconds, not milli-, micro- or nanoseconds")
    return int(round(float(time_s) * 1e9))


def require_frame(flag: str, value: str) -> str:
    """A tf2 frame id: not empty, no whitespace, no leading '/' (tf2 refuses or strips it)."""
    if not value or any(c.isspace() for c in value) or value.startswith("/"):
        raise UsageError(f"{flag} {value!r}: not a tf2 frame id; expected a name without spaces or a "
                         "leading '/', e.g. map or odom")
    return value


def require_tf_pair(parent: tuple[str, str], child: tuple[str, str]) -> None:
    """A transform's (flag, frame) parent and child: two tf2 frame ids, not the same one."""
    for flag, value in (parent, child):
        require_frame(flag, value)
    if parent[1] == child[1]:
        raise UsageError(f"{parent[0]} and {child[0]} are both {parent[1]!r}: a transform needs two frames")


def grid_message(typestore, ns: int, m: OccupancyMap2D, frame_id: str = "map"):
    """nav_msgs/OccupancyGrid (of `typestore`'s distro) of map `m` at `ns` nanoseconds in frame
    `frame_id`: its origin the lower-left corner, yaw 0 (the bag's /map and the ROS 2 node's)."""
    t = typestore.types
    h, w = np.shape(m.image)
    stamp = t["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    origin = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=float(m.origin[0]), y=float(m.origin[1]), z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    info = t["nav_msgs/msg/MapMetaData"](map_load_time=stamp, resolution=float(m.resolution), width=int(w),
                                         height=int(h), origin=origin)
    return t[OCCUPANCY_GRID](header=t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id), info=info,
                             data=grid_data(m))


class RosMapBag:
    """A rosbag2 (MCAP storage) of /map, /map_probability and /tf, written as the mapper runs.

    path: the bag folder to create (refused if it exists). distro: "humble" or "jazzy", whose
    message definitions go into the bag (the three types are the same in both; jazzy adds their
    type hashes). camera_in_base: stack id -> (4, 4) camera-to-base_link mount (module
    docstring); stacks without one use the levelled camera. map_frame: the maps' frame_id and
    the /tf parent; base_frame: the /tf child (tf2 frame ids). Use as a context manager, or call
    `close()`: the bag's metadata.yaml is written on close.
    """

    def __init__(self, path: str | Path, *, distro: str = "jazzy",
                 camera_in_base: Mapping[int, np.ndarray] | None = None,
                 map_frame: str = "map", base_frame: str = "base_link") -> None:
        try:
            from rosbags.interfaces import (
                Qos,
                QosDurability,
                QosHistory,
                QosLiveliness,
                QosReliability,
                QosTime,
            )
            from rosbags.rosbag2 import StoragePlugin, Writer
            from rosbags.typesys import Stores, get_typestore
        except ImportError:
            raise UsageError(f"--out-bag needs the ros extra: {install_extra('ros')}") from None
        if distro not in DISTROS:
            raise UsageError(f"distro {distro!r}: expected one of {DISTROS}")
        require_tf_pair(("map_frame", map_frame), ("base_frame", base_frame))
        self.path = Path(path)
        if self.path.exists():
            raise OutputExistsError(self.path, "--out-bag")
        self.map_frame, self.base_frame = map_frame, base_frame
        self.camera_in_base = {int(k): np.asarray(v, dtype=np.float64) for k, v in (camera_in_base or {}).items()}
        self.robot_stacks = RobotStacks(self.camera_in_base)
        self.typestore = get_typestore(Stores.ROS2_HUMBLE if distro == "humble" else Stores.ROS2_JAZZY)
        self.counts = {MAP_TOPIC: 0, PROB_TOPIC: 0, TF_TOPIC: 0}
        zero = QosTime(0, 0)
        # A map is latched in ROS (map_server publishes reliable + transient local, depth 1), so
        # that RViz's Map display, which subscribes that way, gets the map it asks for.
        latched = Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
                      zero, zero, QosLiveliness.AUTOMATIC, zero, False)
        tf_qos = Qos(QosHistory.KEEP_LAST, 100, QosReliability.RELIABLE, QosDurability.VOLATILE,
                     zero, zero, QosLiveliness.AUTOMATIC, zero, False)
        self._writer = Writer(self.path, version=8, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._conn = {
            MAP_TOPIC: self._writer.add_connection(MAP_TOPIC, OCCUPANCY_GRID, typestore=self.typestore,
                                                   offered_qos_profiles=[latched]),
            PROB_TOPIC: self._writer.add_connection(PROB_TOPIC, OCCUPANCY_GRID, typestore=self.typestore,
                                                    offered_qos_profiles=[latched]),
            TF_TOPIC: self._writer.add_connection(TF_TOPIC, TF_MESSAGE, typestore=self.typestore,
                                                  offered_qos_profiles=[tf_qos]),
        }
        self._closed = False

    # ------------------------------------------------------------------ messages
    def _header(self, ns: int, frame_id: str):
        t = self.typestore.types
        return t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=ns // 10**9,
                                                                                 nanosec=ns % 10**9),
                                         frame_id=frame_id)

    def _grid_message(self, ns: int, m: OccupancyMap2D):
        return grid_message(self.typestore, ns, m, self.map_frame)

    def _write(self, topic: str, ns: int, msg, msgtype: str) -> None:
        if self._closed:
            raise UsageError(f"RosMapBag {self.path}: already closed")
        self._writer.write(self._conn[topic], ns, self.typestore.serialize_cdr(msg, msgtype))
        self.counts[topic] += 1

    # ------------------------------------------------------------------ public
    def write_pose(self, time_s: float, cam_to_world: np.ndarray, stack_id: int | None = None) -> np.ndarray | None:
        """One /tf message map -> base_link at `time_s` from a camera pose (OpenCV axes, (4, 4))
        of a stack that gives the robot's pose (`RobotStacks`; the others write nothing); the
        camera's mount is camera_in_base[stack_id] where given. Returns the (4, 4)
        base_link-to-map pose written, None for a stack that does not give it."""
        ns = stamp_ns(time_s)
        if not self.robot_stacks.drives(stack_id):
            return None
        pose = base_pose(cam_to_world, self.camera_in_base.get(stack_id) if stack_id is not None else None)
        t = self.typestore.types
        q = matrix_to_quat(pose[:3, :3])  # (x, y, z, w)
        tf = t["geometry_msgs/msg/TransformStamped"](
            header=self._header(ns, self.map_frame), child_frame_id=self.base_frame,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=float(pose[0, 3]), y=float(pose[1, 3]),
                                                           z=float(pose[2, 3])),
                rotation=t["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                           w=float(q[3]))))
        self._write(TF_TOPIC, ns, t[TF_MESSAGE](transforms=[tf]), TF_MESSAGE)
        return pose

    def write_maps(self, time_s: float, map2d: OccupancyMap2D | None = None,
                   prob: OccupancyMap2D | None = None) -> None:
        """/map from `map2d` (trinary) and /map_probability from `prob` (scale) at `time_s`;
        either may be None (e.g. the Instant-NGP grid has no probability map)."""
        ns = stamp_ns(time_s)
        for topic, m in ((MAP_TOPIC, map2d), (PROB_TOPIC, prob)):
            if m is not None:
                self._write(topic, ns, self._grid_message(ns, m), OCCUPANCY_GRID)

    @property
    def mcap_path(self) -> Path:
        """The bag's one MCAP file (rosbags names it after the folder)."""
        return self.path / f"{self.path.name}.mcap"

    def close(self) -> None:
        """Finish the bag (metadata.yaml, the MCAP's summary); a second call does nothing."""
        if not self._closed:
            self._closed = True
            self._writer.close()

    def __enter__(self) -> RosMapBag:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
