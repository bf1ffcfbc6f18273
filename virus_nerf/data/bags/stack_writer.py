"""Second pass of `import_bag`: write one stack's samples in the ETHZ layout (docs/method.md 4).

Only the colour and depth frames chosen by the matching are decoded; the small sensors were
read in the first pass. Units stay those of the layout: PNG RGB, uint16 mm depth, USS echo time
in microseconds, TOF mm in sensor order, camera-to-world and LiDAR-to-world poses.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from virus_nerf.data.bags import messages as m
from virus_nerf.data.bags.odometry import PoseTrack
from virus_nerf.data.bags.sync import StackMatch, TopicReport
from virus_nerf.errors import DataFormatError
from virus_nerf.sensors import uss
from virus_nerf.sensors.camera import Intrinsics
from virus_nerf.sensors.irs import IRS_ZONE_COUNT
from virus_nerf.sim import writer


def write_stack(imp, mt: StackMatch, track: PoseTrack) -> Intrinsics:
    """Write images, depth maps, USS, TOF and poses of stack `mt.stack`; returns its intrinsics.

    imp: the running importer (its reader, plan, topics config, room folder and first-pass values)."""
    s, reader = mt.stack, imp.reader
    st = imp.cfg.stacks[s]
    roles = st.roles()
    meas = imp.room_dir / "measurements"
    cdir, ddir = meas / f"CAM{s}_color_image_raw", meas / f"CAM{s}_aligned_depth_to_color_image_raw"
    cdir.mkdir()
    ddir.mkdir()
    intr = _intrinsics(imp, s) if "camera_info" in roles else imp.plan.intrinsics[s]

    topic = roles["color"]
    want = {int(k): i for i, k in enumerate(mt.color_index)}
    for msg in reader.iter_topic(topic):
        i = want.get(msg.index)
        if i is None:
            continue
        where = m.Where(reader.path, topic, msg.index)
        rgb = m.decode_color(msg.msg, msg.msgtype, where)
        if rgb.shape[:2] != (intr.height, intr.width):
            raise where.error(f"image is {rgb.shape[1]}x{rgb.shape[0]}; the camera info says "
                              f"{intr.width}x{intr.height}")
        writer.write_png(cdir / f"img{i}.png", rgb)

    n = len(mt.times_s)
    if "depth" in roles:
        topic = roles["depth"]
        targets: dict[int, list[int]] = defaultdict(list)
        for i, k in enumerate(mt.partner["depth"]):
            targets[int(k)].append(i)
        for msg in reader.iter_topic(topic):
            if msg.index not in targets:
                continue
            where = m.Where(reader.path, topic, msg.index)
            depth = m.decode_depth(msg.msg, msg.msgtype, where)
            if depth.shape != (intr.height, intr.width):
                raise where.error(f"depth map is {depth.shape[1]}x{depth.shape[0]}; the colour image is "
                                  f"{intr.width}x{intr.height} (expected depth aligned to colour)")
            for i in targets[msg.index]:
                writer.write_depth(ddir / f"img{i}.npy", depth)
    else:
        imp.notes.append(f"stack {s} has no depth topic: depth maps written all invalid (0)")
        for i in range(n):
            writer.write_depth(ddir / f"img{i}.npy", np.zeros((intr.height, intr.width), dtype=np.uint16))

    if "uss" in roles:
        raw = np.array([imp._small[(s, "uss")][k] for k in mt.partner["uss"]], dtype=np.float64)
    else:
        imp.notes.append(f"stack {s} has no USS topic: written as no echo")
        raw = np.full(n, 50000.0)
    writer.write_uss(meas / f"USS{s}.csv", mt.times_s, uss.range_from_raw(raw))

    if "tof" in roles:
        pairs = [imp._small[(s, "tof")][k] for k in mt.partner["tof"]]
        tof = np.array([p[0] for p in pairs]).reshape(n, IRS_ZONE_COUNT)
        std = np.array([p[1] for p in pairs]).reshape(n, IRS_ZONE_COUNT)
    else:
        imp.notes.append(f"stack {s} has no TOF topic: written as invalid zones")
        tof, std = np.zeros((n, IRS_ZONE_COUNT)), np.full((n, IRS_ZONE_COUNT), 65535.0)
    writer.write_tof(meas / f"TOF{s}.csv", mt.times_s, tof, std)

    lidar, _ = track.at(mt.times_s, np.inf)
    cam = lidar @ st.camera_in_lidar()
    for prefix in ("balm_sync", "sync"):
        writer.write_poses(imp.room_dir / "poses" / f"poses_cam_{prefix}{s}.csv", mt.times_s, cam)
        writer.write_poses(imp.room_dir / "poses" / f"poses_lidar_{prefix}{s}.csv", mt.times_s, lidar)
    return intr


def _intrinsics(imp, s: int) -> Intrinsics:
    """The first camera_info message of stack s (the report counts it as the one used)."""
    topic = imp.plan.roles[(s, "camera_info")]
    for msg in imp.reader.iter_topic(topic):
        intr = m.decode_camera_info(msg.msg, m.Where(imp.reader.path, topic, msg.index))
        d = np.asarray(msg.msg.D if hasattr(msg.msg, "D") else msg.msg.d, dtype=np.float64)
        if d.size and np.abs(d).max() > 1e-6:
            imp.notes.append(f"{topic}: distortion {d.round(4).tolist()} ignored (the layout is pinhole)")
        count = imp.reader.topics[topic].count
        imp.reports[topic] = TopicReport(topic, "camera_info", s, count, count, msg.time_s, msg.time_s)
        return intr
    raise DataFormatError(imp.reader.path, f"topic {topic} has no messages")
