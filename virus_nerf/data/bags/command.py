"""`virus-nerf import-bag`: a ROS 1 or ROS 2 bag -> an ETHZ-layout recording (README "Your own robot")."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Literal

import tyro


def import_bag(
    bag: Annotated[Path, tyro.conf.Positional],
    out: Path,
    topics: Path | None = None,
    poses: Literal["lidar-odometry", "tf", "csv", "odometry"] = "lidar-odometry",
    poses_file: Path | None = None,
    tf_parent: str = "odom",
    tf_child: str | None = None,
    room: str | None = None,
    json_summary: bool = False,
    odometry_topic: str = "/odom",
) -> None:
    """Import a ROS bag (ROS 1 .bag file or ROS 2 folder) into the ETHZ layout for train/sensors.

    Args:
        bag: ROS 1 .bag file, ROS 2 bag folder (metadata.yaml + .db3/.mcap) or a single ROS 2 .mcap/.db3 file.
        out: New data folder (refused if it exists); train with --data OUT --room ROOM.
        topics: TOML topics file naming your robot's topics, mounting and sync tolerances (default: the ETHZ robot's).
        poses: lidar-odometry (KISS-ICP on the LiDAR scans), tf (--tf-parent/--tf-child from /tf, /tf_static), csv (--poses-file) or odometry (nav_msgs/Odometry on --odometry-topic, e.g. wheel odometry; no LiDAR needed).
        poses_file: LiDAR poses for --poses csv: time,x,y,z,qx,qy,qz,qw with header, or a TUM trajectory.
        tf_parent: World frame for --poses tf.
        tf_child: LiDAR frame for --poses tf (default: the LiDAR messages' frame_id).
        room: Room folder name inside OUT (default: the bag's name).
        json_summary: Print the import report as JSON instead of the table.
        odometry_topic: nav_msgs/Odometry topic for --poses odometry.
    """
    from virus_nerf.data.bags.importer import import_bag as run_import

    report = run_import(bag, out, topics=topics, poses=poses, poses_file=poses_file, tf_parent=tf_parent,
                        tf_child=tf_child, room=room, odometry_topic=odometry_topic)
    print(json.dumps(report.as_dict(), indent=1) if json_summary else report.summary())
