"""`import_bag`: a ROS 1/2 bag -> a recording in the ETHZ layout (docs/method.md 4) that
`virus_nerf.data.ethz.load_recording` reads.

Two passes over the bag keep memory bounded: the first reads every stamp, the small sensors
(USS, IRS, camera info, tf) and the LiDAR scans (written at once as filtered PCDs); poses and the
per-stack matching follow; the second pass decodes and writes only the colour and depth frames
that became samples. Everything is built in a temporary folder renamed into place at the end,
so a failure leaves nothing behind and an existing folder is never touched.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path
from typing import Literal

from virus_nerf.data.bags.odometry import KissIcpSettings, csv_track
from virus_nerf.data.bags.poses import check_pose_flags
from virus_nerf.data.bags.reader import BagReader
from virus_nerf.data.bags.report import REPORT_NAME, ImportReport
from virus_nerf.data.bags.stages import ImportRun, Plan
from virus_nerf.data.bags.topics import TopicsConfig, default_topics, read_topics
from virus_nerf.errors import DataFormatError, OutputExistsError, UsageError, install_extra
from virus_nerf.sensors.camera import Intrinsics
from virus_nerf.utils.io import new_output_dir, write_json_atomic

__all__ = ["ImportReport", "import_bag", "require_ros_extra", "room_name"]

PoseMode = Literal["lidar-odometry", "tf", "csv", "odometry"]
ROS_EXTRA = install_extra("ros")


def require_ros_extra(poses: str = "lidar-odometry", command: str = "import-bag") -> None:
    """One-line error naming `command` when the optional ROS dependencies are missing (KISS-ICP
    only for --poses lidar-odometry)."""
    needed = ["rosbags"] + (["kiss_icp"] if poses == "lidar-odometry" else [])
    missing = [n for n in needed if importlib.util.find_spec(n) is None]
    if missing:
        raise UsageError(f"{command} needs {' and '.join(missing)} (not installed): {ROS_EXTRA}")


def room_name(bag: Path) -> str:
    stem = bag.stem if bag.is_file() else bag.name  # office.bag, office.mcap (a bare ROS 2 file) -> office
    return re.sub(r"[^A-Za-z0-9_-]", "_", stem) or "room"


def import_bag(bag: str | Path, out: str | Path, topics: str | Path | TopicsConfig | None = None,
               poses: PoseMode = "lidar-odometry", poses_file: str | Path | None = None,
               tf_parent: str = "odom", tf_child: str | None = None, room: str | None = None,
               kiss: KissIcpSettings | None = None, odometry_topic: str = "/odom") -> ImportReport:
    """Import `bag` into the new ETHZ data folder `out` (room `room`, default the bag's name).

    poses: 'lidar-odometry' (KISS-ICP on the LiDAR topic), 'tf' (frame `tf_child`, default the
    LiDAR's frame, in `tf_parent` from /tf and /tf_static) or 'csv' (`poses_file`: LiDAR poses
    as time,x,y,z,qx,qy,qz,qw or TUM) or 'odometry' (nav_msgs/Odometry on `odometry_topic`, e.g. a
    robot's wheel odometry: no LiDAR needed; the robot frame's pose with the topics file's
    camera mounting). Raises DataFormatError / UsageError / OutputExistsError
    (one line) before or while reading; `out` then does not exist.
    """
    if poses not in ("lidar-odometry", "tf", "csv", "odometry"):
        raise UsageError(f"--poses {poses!r}: expected lidar-odometry, tf, csv or odometry")
    require_ros_extra(poses)
    bag, out = Path(bag), Path(out)
    if out.exists():
        raise OutputExistsError(out)
    cfg = topics if isinstance(topics, TopicsConfig) else read_topics(topics) if topics else default_topics()
    check_pose_flags(poses, poses_file)
    csv_poses = csv_track(poses_file) if poses == "csv" else None
    room = room_name(bag) if room is None else room
    if not re.fullmatch(r"[A-Za-z0-9_-]+", room):
        raise UsageError(f"--room {room!r}: expected letters, digits, '_' or '-'")
    with BagReader(bag) as reader:
        plan = plan_topics(reader, cfg, poses, odometry_topic)
        with new_output_dir(out) as root:
            report = ImportRun(reader, cfg, plan, root, room).run(poses, csv_poses, tf_parent, tf_child, kiss)
            report.data_dir = str(out)
            write_json_atomic(root / REPORT_NAME, report.as_dict())
    return report


def plan_topics(reader: BagReader, cfg: TopicsConfig, poses: str, odometry_topic: str = "/odom") -> Plan:
    """Check every named topic against the bag before anything is written."""
    roles: dict[tuple[int | None, str], str] = {}
    where = f"topics file {cfg.source}" if cfg.source else "default ETHZ topics"
    for s, st in cfg.stacks.items():
        for role, topic in st.roles().items():
            reader.require(topic, role, f"stacks.{s}.{role} of the {where}")
            roles[(s, role)] = topic
    bag_topics = reader.topics
    if cfg.lidar.topic and (cfg.lidar.topic in bag_topics or cfg.lidar_named):  # a topic named must be there
        reader.require(cfg.lidar.topic, "lidar", f"lidar.topic of the {where}")
        roles[(None, "lidar")] = cfg.lidar.topic
    elif poses == "lidar-odometry":
        raise DataFormatError(reader.path, f"--poses lidar-odometry needs a LiDAR: no topic {cfg.lidar.topic} "
                              f"(lidar.topic of the {where}); name it in a topics file or use --poses tf, odometry or csv")
    if poses == "odometry":
        if odometry_topic not in bag_topics:
            raise DataFormatError(reader.path, f"--poses odometry: no topic {odometry_topic} in the bag; name the "
                                  "nav_msgs/Odometry topic with --odometry-topic")
        reader.require(odometry_topic, "odometry", "--odometry-topic")
        roles[(None, "odometry")] = odometry_topic
    if poses == "tf":
        found = [t for t in cfg.tf_topics if t in bag_topics]
        if not found:
            raise DataFormatError(reader.path, f"--poses tf: none of the tf topics {list(cfg.tf_topics)} is in the bag")
        for k, t in enumerate(found):
            reader.require(t, "tf", "tf_topics")
            roles[(None, f"tf{k}")] = t
    intrinsics: dict[int, Intrinsics] = {}
    need_csv = [s for s, st in cfg.stacks.items() if not st.camera_info]
    if need_csv:
        if cfg.intrinsics_csv is None:
            raise DataFormatError(cfg.source or reader.path, f"stack {need_csv[0]} has no camera_info topic; "
                                  "name one or give intrinsics_csv (cam_id,fx,fy,cx,cy[,width,height])")
        from virus_nerf.data.ethz import read_intrinsics

        table = read_intrinsics(cfg.intrinsics_csv, default_size=None)  # no size columns: the images' size
        for s in need_csv:
            if s not in table:
                raise DataFormatError(cfg.intrinsics_csv, f"no row for CAM{s}", field="cam_id")
            intrinsics[s] = table[s]
    return Plan(roles, intrinsics)
