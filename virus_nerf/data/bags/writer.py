"""`write_bag`: an ETHZ-layout recording -> a ROS 1 or ROS 2 bag with the ETHZ robot's topics.

The inverse of `import_bag` up to the message quantisation (USS echo time whole microseconds,
TOF whole millimetres): colour (rgb8) and aligned depth (16UC1 mm) images, camera info, the
custom USS and TOF messages (or sensor_msgs/Range for the USS), and the LiDAR scans as
PointCloud2; no poses (they are what an import has to recover). Used by the tests, and by anyone
who wants to replay a simulated recording in a ROS tool.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np

from virus_nerf.data.bags import messages as m
from virus_nerf.data.bags.topics import ethz_stack
from virus_nerf.errors import OutputExistsError
from virus_nerf.sensors import irs


def write_bag(recording_dir: str | Path, bag_path: str | Path, ros_version: Literal[1, 2] = 1,
              room: str | None = None, uss_as_range: bool = False, lidar_topic: str | None = "/rslidar_points",
              storage: Literal["sqlite3", "mcap"] = "sqlite3", compressed_color: bool = False,
              tf: bool = False) -> Path:
    """Write the recording `recording_dir` (an ETHZ data folder; `room` default: its first room)
    to `bag_path` (ROS 1: a .bag file; ROS 2: a new folder). Bag times = header stamps.

    uss_as_range: USS as sensor_msgs/Range (m) instead of the custom message; compressed_color:
    colour as PNG CompressedImage; tf: the recording's LiDAR poses at the camera stamps on /tf
    (odom -> base_link) with base_link -> rslidar on /tf_static (for `import-bag --poses tf`).
    Holds all messages in memory before writing: meant for short recordings."""
    from virus_nerf.data.ethz import load_recording

    data = Path(recording_dir)
    bag_path = Path(bag_path)
    if bag_path.exists():
        raise OutputExistsError(bag_path)
    if room is None:
        rooms = sorted(p.name for p in data.iterdir() if (p / "measurements").is_dir())
        room = rooms[0]
    rec = load_recording(data, room)
    store = m.make_typestore(ros_version)
    messages: list[tuple[int, str, str, object]] = []  # (ns, topic, type, message)
    t = store.types

    def header(stamp_s: float, frame: str):
        ns = int(round(stamp_s * 1e9))
        stamp = t["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        if ros_version == 1:
            return t["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
        return t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def add(stamp_s: float, topic: str, typename: str, msg) -> None:
        messages.append((int(round(stamp_s * 1e9)), topic, typename, msg))

    meas_dir = rec.room_dir / "measurements"
    for s, st in rec.stacks.items():
        names = ethz_stack(s) if s in (1, 3) else None
        color = names.color if names else f"/CAM{s}/color/image_raw"
        depth = names.depth if names else f"/CAM{s}/aligned_depth_to_color/image_raw"
        info = names.camera_info if names else f"/CAM{s}/color/camera_info"
        frame = f"CAM{s}_color_optical_frame"
        uss_raw = np.loadtxt(meas_dir / f"USS{s}.csv", delimiter=",", skiprows=1, ndmin=2)[:, 1]
        tof_rows = np.loadtxt(meas_dir / f"TOF{s}.csv", delimiter=",", skiprows=1, ndmin=2)
        it = st.intrinsics
        k = [it.fx, 0.0, it.cx, 0.0, it.fy, it.cy, 0.0, 0.0, 1.0]
        p = [it.fx, 0.0, it.cx, 0.0, 0.0, it.fy, it.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
        for i, ts in enumerate(st.times):
            h = header(float(ts), frame)
            rgb = st.image(i)
            if compressed_color:
                add(ts, color, m.COMPRESSED, t[m.COMPRESSED](header=h, format="rgb8; png compressed rgb8",
                                                             data=np.frombuffer(st.image_paths[i].read_bytes(), np.uint8)))
            else:
                add(ts, color, m.IMAGE, t[m.IMAGE](header=h, height=rgb.shape[0], width=rgb.shape[1],
                                                   encoding="rgb8", is_bigendian=0, step=3 * rgb.shape[1],
                                                   data=rgb.reshape(-1)))
            d = np.load(st.depth_paths[i]).astype("<u2")
            add(ts, depth, m.IMAGE, t[m.IMAGE](header=h, height=d.shape[0], width=d.shape[1], encoding="16UC1",
                                               is_bigendian=0, step=2 * d.shape[1], data=d.view(np.uint8).reshape(-1)))
            add(ts, info, m.CAMERA_INFO, _camera_info(t, ros_version, h, it.width, it.height, k, p))
            add(ts, f"/USS{s}", *_uss(t, h, float(uss_raw[i]), uss_as_range))
            mm = np.clip(np.round(tof_rows[i, 1:1 + irs.IRS_ZONE_COUNT]), 0, 65535).astype(np.uint16)
            sd = np.clip(np.round(tof_rows[i, 1 + irs.IRS_ZONE_COUNT:]), 0, 65535).astype(np.uint16)
            add(ts, f"/TOF{s}", m.TOF_TYPE, t[m.TOF_TYPE](header=h, meas=mm, stds=sd))
    if tf:
        _add_tf(t, rec, header, add)
    if lidar_topic:
        for kk, ts in enumerate(rec.lidar_times):
            add(ts, lidar_topic, m.CLOUD, _cloud(t, header(float(ts), "rslidar"), rec.lidar_scan(kk)))
    messages.sort(key=lambda x: x[0])
    _write(bag_path, ros_version, store, messages, storage)
    return bag_path


# base_link -> rslidar of the written /tf_static: any fixed mounting, to exercise the chain
BASE_TO_LIDAR = ((0.1, 0.0, 0.5), (0.0, 0.0, 0.0, 1.0))


def _add_tf(t, rec, header, add) -> None:
    """/tf odom -> base_link at the union of camera stamps and /tf_static base_link -> rslidar."""
    from virus_nerf.sensors.geometry import invert_pose, matrix_to_quat, pose_matrix

    base_to_lidar = pose_matrix(np.array(BASE_TO_LIDAR[0]), np.array(BASE_TO_LIDAR[1]))

    def stamped(ts: float, parent: str, child: str, pose: np.ndarray):
        q = matrix_to_quat(pose[:3, :3])
        tr = t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](x=pose[0, 3], y=pose[1, 3], z=pose[2, 3]),
            rotation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
        return t["geometry_msgs/msg/TransformStamped"](header=header(ts, parent), child_frame_id=child, transform=tr)

    times = np.concatenate([st.times for st in rec.stacks.values()])
    poses = np.concatenate([st.lidar_to_world for st in rec.stacks.values()])
    order = np.argsort(times, kind="stable")
    first = float(times[order[0]])
    add(first, "/tf_static", m.TF, t[m.TF](transforms=[stamped(first, "base_link", "rslidar", base_to_lidar)]))
    for j in order:
        odom_base = poses[j] @ invert_pose(base_to_lidar)
        add(float(times[j]), "/tf", m.TF, t[m.TF](transforms=[stamped(float(times[j]), "odom", "base_link", odom_base)]))


def _camera_info(t, ros_version: int, h, width: int, height: int, k: list, p: list):
    roi = t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    mats = {"D": np.zeros(5), "K": np.array(k), "R": np.eye(3).reshape(-1), "P": np.array(p)}
    if ros_version == 2:
        mats = {key.lower(): v for key, v in mats.items()}
    return t[m.CAMERA_INFO](header=h, height=height, width=width, distortion_model="plumb_bob", **mats,
                            binning_x=0, binning_y=0, roi=roi)


def _uss(t, h, raw_us: float, as_range: bool) -> tuple[str, object]:
    if not as_range:
        return m.USS_TYPE, t[m.USS_TYPE](header=h, meas=int(round(raw_us)))
    r = raw_us / 5000.0 if raw_us < 50000 else float("inf")
    return m.RANGE, t[m.RANGE](header=h, radiation_type=0, field_of_view=float(np.radians(55.0)), min_range=0.0,
                               max_range=10.0, range=r)


def _cloud(t, h, xyz: np.ndarray):
    pts = np.ascontiguousarray(xyz, dtype="<f4")
    fields = [t["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
    return t[m.CLOUD](header=h, height=1, width=len(pts), fields=fields, is_bigendian=False, point_step=12,
                      row_step=12 * len(pts), data=pts.view(np.uint8).reshape(-1), is_dense=True)


def _write(path: Path, ros_version: int, store, messages: list, storage: str) -> None:
    topics = {}
    for _, topic, typename, _ in messages:
        topics.setdefault(topic, typename)
    if ros_version == 1:
        from rosbags.rosbag1 import Writer

        with Writer(path) as w:
            conns = {tp: w.add_connection(tp, ty, typestore=store) for tp, ty in topics.items()}
            for ns, tp, ty, msg in messages:
                w.write(conns[tp], ns, store.serialize_ros1(msg, ty))
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        with Writer(path, version=Writer.VERSION_LATEST, storage_plugin=plugin) as w:
            conns = {tp: w.add_connection(tp, ty, typestore=store) for tp, ty in topics.items()}
            for ns, tp, ty, msg in messages:
                w.write(conns[tp], ns, store.serialize_cdr(msg, ty))
