"""Second pass of `import_bag`: write the stacks' samples in the ETHZ layout (docs/method.md 4).

Only the colour and depth frames chosen by the matching are decoded (one pass over the image
topics of all stacks); the small sensors were read in the first pass. Units stay those of the
layout: PNG RGB, uint16 mm depth, USS echo time in microseconds, TOF mm in sensor order,
camera-to-world and LiDAR-to-world poses.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from virus_nerf.data import writer
from virus_nerf.data.bags import messages as m
from virus_nerf.data.bags.odometry import PoseTrack
from virus_nerf.data.bags.sync import StackMatch
from virus_nerf.sensors import uss
from virus_nerf.sensors.camera import Intrinsics
from virus_nerf.sensors.irs import IRS_ZONE_COUNT


def write_frames(run, matches: dict[int, StackMatch], intrinsics: dict[int, Intrinsics]) -> None:
    """Decode and write the sample frames: img{i}.png and img{i}.npy of every stack.

    run: the ImportRun (its reader, plan, room folder and notes)."""
    meas = run.room_dir / "measurements"
    targets: dict[tuple[str, int], list[tuple[int, str, int]]] = defaultdict(list)  # (topic, msg) -> (stack, role, i)
    for s, mt in matches.items():
        (meas / f"CAM{s}_color_image_raw").mkdir()
        (meas / f"CAM{s}_aligned_depth_to_color_image_raw").mkdir()
        for i, k in enumerate(mt.color_index):
            targets[(run.plan.roles[(s, "color")], int(k))].append((s, "color", i))
        if "depth" in mt.partner:
            for i, k in enumerate(mt.partner["depth"]):
                targets[(run.plan.roles[(s, "depth")], int(k))].append((s, "depth", i))
        else:
            run.notes.append(f"stack {s} has no depth topic: depth maps written all invalid (0)")
            intr = intrinsics[s]
            for i in range(len(mt.times_s)):
                writer.write_depth(meas / f"CAM{s}_aligned_depth_to_color_image_raw" / f"img{i}.npy",
                                   np.zeros((intr.height, intr.width), dtype=np.uint16))
    topics = sorted({topic for topic, _ in targets})
    for topic, msg in run.reader.iter_topics(topics):
        for s, role, i in targets.get((topic, msg.index), ()):
            size, where = (intrinsics[s].width, intrinsics[s].height), m.Where(run.reader.path, topic, msg.index)
            if role == "color":
                rgb = m.decode_color(msg.msg, msg.msgtype, where, size)
                writer.write_png(meas / f"CAM{s}_color_image_raw" / f"img{i}.png", rgb)
            else:
                depth = m.decode_depth(msg.msg, msg.msgtype, where, size)
                writer.write_depth(meas / f"CAM{s}_aligned_depth_to_color_image_raw" / f"img{i}.npy", depth.mm)


def write_tables(run, mt: StackMatch, track: PoseTrack) -> None:
    """USS{s}.csv, TOF{s}.csv and the four pose files of stack `mt.stack`."""
    s, n = mt.stack, len(mt.times_s)
    st = run.cfg.stacks[s]
    meas = run.room_dir / "measurements"
    if "uss" in mt.partner:
        raw = np.array([run.small[(s, "uss")][k].echo_us for k in mt.partner["uss"]], dtype=np.float64).reshape(n)
    else:
        run.notes.append(f"stack {s} has no USS topic: written as no echo")
        raw = np.full(n, 50000.0)
    writer.write_uss(meas / f"USS{s}.csv", mt.times_s, uss.range_from_raw(raw))

    if "tof" in mt.partner:
        readings = [run.small[(s, "tof")][k] for k in mt.partner["tof"]]
        tof = np.array([r.meas_mm for r in readings]).reshape(n, IRS_ZONE_COUNT)
        std = np.array([r.stds_mm for r in readings]).reshape(n, IRS_ZONE_COUNT)
    else:
        run.notes.append(f"stack {s} has no TOF topic: written as invalid zones")
        tof, std = np.zeros((n, IRS_ZONE_COUNT)), np.full((n, IRS_ZONE_COUNT), 65535.0)
    writer.write_tof(meas / f"TOF{s}.csv", mt.times_s, tof, std)

    lidar, _ = track.at(mt.times_s, np.inf)
    cam = lidar @ st.camera_in_lidar()
    for prefix in ("balm_sync", "sync"):
        writer.write_poses(run.room_dir / "poses" / f"poses_cam_{prefix}{s}.csv", mt.times_s, cam)
        writer.write_poses(run.room_dir / "poses" / f"poses_lidar_{prefix}{s}.csv", mt.times_s, lidar)
