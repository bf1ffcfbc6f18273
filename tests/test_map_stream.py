"""Streaming map-bag (issue 29, item 3): the bag synchronised message by message (data/bags/live.py)
gives the importer's frames and poses, the real-time loop (mapping/stream.py) writes snapshots with
the lag, and bad data stops the stream with one line after writing the map made so far."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli, tiny_train_config

pytest.importorskip("rosbags")

from virus_nerf.data.bags import messages as m  # noqa: E402
from virus_nerf.data.bags.live import LiveSync, StreamError  # noqa: E402
from virus_nerf.data.bags.poses import make_pose_source  # noqa: E402
from virus_nerf.data.bags.reader import BagReader  # noqa: E402
from virus_nerf.data.bags.topics import default_topics  # noqa: E402
from virus_nerf.data.ethz import load_recording  # noqa: E402
from virus_nerf.errors import DataFormatError  # noqa: E402


@pytest.fixture(scope="module")
def bags(tiny_office, tmp_path_factory) -> dict[str, Path]:
    """The tiny office as a ROS 1 bag (LiDAR, no tf), a ROS 2 bag with /tf, and its LiDAR poses as CSV."""
    from virus_nerf.data.bags.writer import write_bag
    from virus_nerf.data.writer import write_poses

    d = tmp_path_factory.mktemp("stream_bags")
    rec = load_recording(tiny_office, "office")
    times, poses = rec._lidar_pose_track
    write_poses(d / "lidar.csv", times, poses)
    return {"ros1": write_bag(tiny_office, d / "drive.bag", ros_version=1),
            "tf": write_bag(tiny_office, d / "drive_tf", ros_version=2, tf=True), "csv": d / "lidar.csv"}


@pytest.fixture(scope="module")
def tiny_cfg(tmp_path_factory) -> Path:
    from virus_nerf.config_io import to_dict

    path = tmp_path_factory.mktemp("stream_cfg") / "cfg.json"  # no stereo: its tracking costs per frame
    path.write_text(json.dumps(to_dict(tiny_train_config(sensors=("camera", "uss", "irs")))))
    return path


def _stream(bag: Path, poses: str, cfg=None, source=None, **kw):
    """Every message of `bag` through a LiveSync (no mapper, no clock) -> (frames, sync)."""
    cfg = cfg or default_topics()
    with BagReader(bag) as reader:
        source = source or make_pose_source(poses, cfg, bag, present=lambda t: t in reader.topics, **kw)
        try:
            sync = LiveSync(cfg, source, bag)
            frames = []
            for topic, msg in reader.iter_topics(sync.topics()):
                frames += sync.push(topic, msg)
            frames += sync.finish()
        finally:
            source.close()
    return frames, sync


def _by_stack(frames) -> dict[int, list]:
    out: dict[int, list] = {}
    for f in frames:
        out.setdefault(f.frame.stack_id, []).append(f.frame)
    return out


def _rewrite(src: Path, dst: Path, edit) -> Path:
    """Copy a ROS 1 bag; edit(topic, t_ns, msg) -> [(topic, msgtype, t_ns, msg), ...] replaces each message."""
    from rosbags.rosbag1 import Reader, Writer

    store = m.make_typestore(1)
    with Reader(src) as r, Writer(dst) as w:
        conns = {}
        for c, t, raw in r.messages():
            for topic, msgtype, t_ns, msg in edit(c.topic, t, store.deserialize_ros1(raw, c.msgtype), c.msgtype):
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, msgtype, typestore=store)
                w.write(conns[topic], t_ns, store.serialize_ros1(msg, msgtype))
    return dst


@pytest.mark.parametrize("poses", ["tf", "csv"])
def test_streamed_frames_are_the_importers(bags, tmp_path, poses):
    """--poses tf (ROS 2 bag) and csv (ROS 1 bag): the same frames as import-bag, stamp for stamp,
    with the same poses (to the 1e-9 of the importer's CSV), USS, IRS and pixels."""
    from virus_nerf.data.bags.importer import import_bag

    bag = bags["tf"] if poses == "tf" else bags["ros1"]
    kw = {"tf_child": "rslidar"} if poses == "tf" else {"poses_file": bags["csv"]}
    import_bag(bag, tmp_path / "rec", poses=poses, room="drive", **kw)
    rec = load_recording(tmp_path / "rec", "drive")
    frames, sync = _stream(bag, poses, **kw)
    assert not sync.dropped_total() and len(frames) == sum(len(st) for st in rec.stacks.values())
    by = _by_stack(frames)
    for s, st in rec.stacks.items():
        got = by[s]
        assert len(got) == len(st)
        np.testing.assert_allclose([f.time for f in got], st.times, atol=1e-6)
        np.testing.assert_allclose(np.stack([f.cam_to_world for f in got]), st.cam_to_world, atol=1e-8)
        np.testing.assert_array_equal([f.uss_range for f in got], st.uss_range)
        np.testing.assert_array_equal(np.stack([f.irs_range for f in got]), st.irs_range)
        for i in (0, len(st) // 2, len(st) - 1):
            assert np.array_equal(got[i].rgb, st.image(i))


def test_a_colour_frame_published_twice_is_one_frame_imported_and_streamed(bags, tmp_path):
    """A camera driver that publishes each frame twice (one stamp): import-bag and the stream make
    one frame of each, the bag's first, and count the others as repeated stamps. Before, the import
    wrote two rows of one time (which load_recording refuses) and map-bag stopped at the second."""
    from virus_nerf.data.bags.importer import import_bag

    topic = default_topics().stacks[1].color
    twice = _rewrite(bags["ros1"], tmp_path / "twice.bag",
                     lambda t, t_ns, msg, typ: [(t, typ, t_ns, msg)] + ([(t, typ, t_ns + 1, msg)] if t == topic else []))
    import_bag(bags["ros1"], tmp_path / "once", poses="csv", room="drive", poses_file=bags["csv"])
    report = import_bag(twice, tmp_path / "twice", poses="csv", room="drive", poses_file=bags["csv"])
    once, rec = load_recording(tmp_path / "once", "drive"), load_recording(tmp_path / "twice", "drive")
    n = len(once.stacks[1])
    assert f"stack 1: {n} colour frames dropped (repeated stamp)" in report.summary()
    for s, st in once.stacks.items():
        np.testing.assert_array_equal(rec.stacks[s].times, st.times)
        np.testing.assert_array_equal(rec.stacks[s].uss_range, st.uss_range)
    frames, sync = _stream(twice, "csv", poses_file=bags["csv"])
    assert len(frames) == sum(len(st) for st in once.stacks.values())
    assert dict(sync.dropped[1]) == {"repeated stamp": n} and not sync.dropped[3]
    np.testing.assert_allclose([f.frame.time for f in frames if f.frame.stack_id == 1], once.stacks[1].times, atol=1e-6)


def test_a_ros1_bag_with_tf_gives_the_ros2_bags_frames(bags, tiny_office, tmp_path):
    """write_bag(ros_version=1, tf=True): rosbags' Noetic types lack tf2_msgs, registered for /tf;
    its frames and poses streamed from /tf are the ROS 2 bag's."""
    from virus_nerf.data.bags.writer import write_bag

    ros1 = write_bag(tiny_office, tmp_path / "drive_tf.bag", ros_version=1, tf=True)
    got, _ = _stream(ros1, "tf", tf_child="rslidar")
    want, _ = _stream(bags["tf"], "tf", tf_child="rslidar")
    assert len(got) == len(want) > 10
    np.testing.assert_allclose([f.frame.time for f in got], [f.frame.time for f in want], atol=1e-6)
    np.testing.assert_allclose(np.stack([f.frame.cam_to_world for f in got]),
                               np.stack([f.frame.cam_to_world for f in want]), atol=1e-8)


def test_a_bag_on_sim_time_streams_from_tf_on_its_stamps(tiny_office, tmp_path):
    """Every header stamp (the transforms' too) on the robot's clock, starting at 100 s, 1699999900 s
    behind the bag's receive times (a bag of sim time, a replayed bag): the stream runs on the
    stamps, /tf's as every topic's, and gives the bag's frames at their stamps. Before, /tf took its
    receive time and the stream stopped at once: "the bag's clock jumps 1699999900.000 s forward"
    (a user's review)."""
    import dataclasses

    from virus_nerf.data.bags.writer import write_bag

    behind = 1_699_999_900
    ros1 = write_bag(tiny_office, tmp_path / "drive_tf.bag", ros_version=1, tf=True)

    def earlier(stamped):
        stamp = stamped.header.stamp
        return dataclasses.replace(stamped, header=dataclasses.replace(
            stamped.header, stamp=dataclasses.replace(stamp, sec=stamp.sec - behind)))

    def edit(topic, t_ns, msg, msgtype):
        if hasattr(msg, "transforms"):
            msg = dataclasses.replace(msg, transforms=[earlier(tr) for tr in msg.transforms])
        elif hasattr(msg, "header"):
            msg = earlier(msg)
        return [(topic, msgtype, t_ns, msg)]

    sim_time = _rewrite(ros1, tmp_path / "sim_time.bag", edit)
    got, sync = _stream(sim_time, "tf", tf_child="rslidar")
    want, _ = _stream(ros1, "tf", tf_child="rslidar")
    assert not sync.dropped_total() and len(got) == len(want) > 10
    assert min(f.frame.time for f in want) > behind  # the simulator's stamps: 2023 on the recorder's clock
    np.testing.assert_allclose([f.frame.time + behind for f in got], [f.frame.time for f in want], atol=1e-6)
    np.testing.assert_allclose(np.stack([f.frame.cam_to_world for f in got]),
                               np.stack([f.frame.cam_to_world for f in want]), atol=1e-8)


def test_a_poses_file_on_another_clock_is_named_with_both_time_ranges(bags, tmp_path):
    """A poses file with times from the drive's start (a user's export), a bag on the robot's clock:
    import-bag names both ranges, as it does for a sensor topic on another clock."""
    from virus_nerf.data.bags.importer import import_bag
    from virus_nerf.data.ethz import read_poses
    from virus_nerf.data.writer import write_poses

    times, poses = read_poses(bags["csv"])
    relative = tmp_path / "relative.csv"
    write_poses(relative, times - times[0], poses)
    with pytest.raises(DataFormatError) as err:
        import_bag(bags["ros1"], tmp_path / "rec", poses="csv", poses_file=relative)
    got = str(err.value)
    want = (f"cannot synchronise /CAM1/color/image_raw with the poses: no pose within sync.pose_tolerance_s of any "
            f"colour frame (poses 0.000..{times[-1] - times[0]:.3f} s of --poses csv, colour 1700000000.000..")
    assert want in got and got.endswith("s); check the clocks"), got
    assert not (tmp_path / "rec").exists()


def test_a_topic_on_another_clock_is_named_so_not_as_stopped(bags, tmp_path):
    """/TOF1 stamped in kiloseconds (a driver's clock): its messages keep coming, stamped 1.7e6 s
    where the others are at 1.7e9. The stream names the clock; before, "topic /TOF1 stopped: its
    last message is at -1698300000.000 s" (a user's review). import-bag already said "check the clocks"."""
    import dataclasses

    def edit(topic, t_ns, msg, msgtype):
        if topic == "/TOF1":
            stamp = msg.header.stamp
            msg = dataclasses.replace(msg, header=dataclasses.replace(
                msg.header, stamp=dataclasses.replace(stamp, sec=stamp.sec // 1000)))
        return [(topic, msgtype, t_ns, msg)]

    bag = _rewrite(bags["ros1"], tmp_path / "kilo.bag", edit)
    with pytest.raises(StreamError) as err:
        _stream(bag, "csv", poses_file=bags["csv"])
    got = str(err.value)
    assert "topic /TOF1 is stamped on another clock: its newest message at -1698300000.000 s, the stream at " in got, got
    assert got.endswith("s (seconds since the bag's first message); check the clocks"), got


def test_poses_with_the_quaternion_in_w_x_y_z_order_are_noted(bags, tmp_path):
    """The LiDAR poses written w,x,y,z in the qx,qy,qz,qw columns: each reads as a half turn, the
    robot upside down. import-bag says so in a note (a LiDAR may hang upside down, so it is no
    refusal); the right order gives no such note."""
    from virus_nerf.data.bags.importer import import_bag
    from virus_nerf.data.ethz import read_poses
    from virus_nerf.sensors.geometry import matrix_to_quat

    times, poses = read_poses(bags["csv"])
    q = np.stack([matrix_to_quat(p[:3, :3]) for p in poses])  # (N, 4) x, y, z, w
    assert (poses[:, 2, 2] > 0.9).all()  # the simulated LiDAR stands upright
    swapped = tmp_path / "wxyz.csv"
    rows = [",".join(repr(float(v)) for v in (t, *p[:3, 3], w, x, y, z))
            for t, p, (x, y, z, w) in zip(times, poses, q, strict=True)]
    swapped.write_text("time,x,y,z,qx,qy,qz,qw\n" + "\n".join(rows) + "\n")
    note = "points below the horizon: an upside-down LiDAR, or quaternions in w,x,y,z order?"
    report = import_bag(bags["ros1"], tmp_path / "wrong", poses="csv", poses_file=swapped)
    assert any(note in n and n.startswith("the up axis of 100% of the poses (--poses csv)") for n in report.notes), \
        report.notes
    report = import_bag(bags["ros1"], tmp_path / "right", poses="csv", poses_file=bags["csv"])
    assert not any(note in n for n in report.notes)


def test_kiss_icp_in_its_worker_process_gives_the_in_process_poses(bags):
    """The registration moved to a worker process (it holds the GIL): the same frames, the same
    poses to the last bit, and the worker ends with the stream."""
    from virus_nerf.data.bags.poses import KissPoses

    cfg = default_topics()
    in_process = KissPoses(cfg.lidar.topic, cfg.lidar, None, bags["ros1"], worker=False)
    local, _ = _stream(bags["ros1"], "lidar-odometry", source=in_process)
    worker = KissPoses(cfg.lidar.topic, cfg.lidar, None, bags["ros1"])
    proc = worker.worker._proc
    remote, _ = _stream(bags["ros1"], "lidar-odometry", source=worker)
    assert len(remote) == len(local) > 0
    for a, b in zip(local, remote, strict=True):
        assert a.frame.time == b.frame.time and a.frame.stack_id == b.frame.stack_id
        np.testing.assert_array_equal(a.frame.cam_to_world, b.frame.cam_to_world)
    assert proc.poll() is not None
    # the floor the worker found, kept after it ended (stream.json's lidar_floor): the simulator's
    # LiDAR is level, 0.72 m above the floor
    assert worker.floor == in_process.floor and worker.floor["motion"] == "along the floor"
    assert worker.floor["floor_m"] == pytest.approx(-0.72, abs=0.02)


def test_a_dead_kiss_icp_worker_is_one_line_not_a_hang():
    """The worker process killed (out of memory, a crash in KISS-ICP): the next wait for a pose
    raises at once, naming the worker, and closing does not wait on the scans it will not read."""
    from virus_nerf.data.bags.kiss_worker import KissWorker
    from virus_nerf.data.bags.odometry import KissIcpSettings

    worker = KissWorker(KissIcpSettings())
    worker._proc.kill()  # (it ignores SIGTERM: the mapping process stops it once its map is written)
    worker._proc.wait(timeout=10.0)
    for k in range(3):  # ~1 MB of scans into a pipe nobody reads
        worker.send(float(k), np.zeros((30000, 3), dtype=np.float32))
    with pytest.raises(RuntimeError, match="KISS-ICP worker process stopped .* 3 scan"):
        worker.poll(block=True)
    worker.close()
    assert worker._proc.poll() is not None


def _box_room_scan(position: np.ndarray, spacing: float = 0.4) -> np.ndarray:
    """Points (N, 3) float32 of an 8 x 6 x 3 m room (walls, floor, ceiling on a fixed `spacing`
    grid, a 0.4 m pillar) seen from a sensor at `position` (no rotation): about 1100 points, so
    three scans fit in a pipe's 64 KB."""
    u = np.arange(0.0, 8.0 + 1e-9, spacing)
    v = np.arange(0.0, 6.0 + 1e-9, spacing)
    w = np.arange(0.0, 3.0 + 1e-9, spacing)
    parts = []
    for x in (0.0, 8.0):
        yy, zz = np.meshgrid(v, w)
        parts.append(np.c_[np.full(yy.size, x), yy.ravel(), zz.ravel()])
    for y in (0.0, 6.0):
        xx, zz = np.meshgrid(u, w)
        parts.append(np.c_[xx.ravel(), np.full(xx.size, y), zz.ravel()])
    for z in (0.0, 3.0):
        xx, yy = np.meshgrid(u[::2], v[::2])
        parts.append(np.c_[xx.ravel(), yy.ravel(), np.full(xx.size, z)])
    zz = np.repeat(w, 4)
    parts.append(np.c_[np.tile([5.0, 5.4, 5.4, 5.0], len(w)), np.tile([2.0, 2.0, 2.4, 2.4], len(w)), zz])
    return (np.concatenate(parts) - position).astype(np.float32)


def test_kiss_icp_keeping_up_registers_the_newest_scan_and_skips_the_waiting_ones():
    """A robot at 0.5 m/s in a box room, a scan every 0.1 s. The worker is held (SIGSTOP) while
    scans 2-5 come: it then skips 2, 3 and 4 and registers 5, whose pose (and the next one's) is
    the true one: the motion predicted over 1 interval is stretched to the 4 registered."""
    import os
    import signal
    import time

    from virus_nerf.data.bags.kiss_worker import KissWorker
    from virus_nerf.data.bags.odometry import KissIcpSettings

    truth = {k: np.array([1.5 + 0.05 * k, 2.5 + 0.01 * k, 1.0]) for k in range(7)}
    worker = KissWorker(KissIcpSettings(), keep_up=True)
    try:
        got = []
        for k in (0, 1):
            worker.send(0.1 * k, _box_room_scan(truth[k]))
            got += worker.poll(block=True)
        os.kill(worker._proc.pid, signal.SIGSTOP)
        try:
            for k in (2, 3, 4, 5):
                worker.send(0.1 * k, _box_room_scan(truth[k]))
            deadline = time.monotonic() + 10.0
            while not worker._outbox.empty() and time.monotonic() < deadline:
                time.sleep(0.01)
            time.sleep(0.2)  # the last scan's write into the pipe
        finally:
            os.kill(worker._proc.pid, signal.SIGCONT)
        got += worker.poll(block=True)
        worker.send(0.6, _box_room_scan(truth[6]))
        got += worker.poll(block=True)
    finally:
        worker.close()
    assert [round(t, 3) for t, _ in got] == [0.0, 0.1, 0.5, 0.6]
    assert worker.skipped == 3 and not worker.pending
    for t, pose in got:  # the first scan is the world frame
        k = round(t * 10)
        np.testing.assert_allclose(pose[:3, 3], truth[k] - truth[0], atol=0.01)
        np.testing.assert_allclose(pose[:3, :3], np.eye(3), atol=1e-3)


def test_kiss_icp_keeping_up_never_skips_the_first_scan():
    """The world frame is the first scan's: scans 0-3 wait while the worker starts (held by
    SIGSTOP); it registers 0, skips 1 and 2, registers 3."""
    import os
    import signal
    import time

    from virus_nerf.data.bags.kiss_worker import KissWorker
    from virus_nerf.data.bags.odometry import KissIcpSettings

    truth = {k: np.array([1.5 + 0.05 * k, 2.5, 1.0]) for k in range(4)}
    worker = KissWorker(KissIcpSettings(), keep_up=True)
    try:
        os.kill(worker._proc.pid, signal.SIGSTOP)
        try:
            for k in range(4):
                worker.send(0.1 * k, _box_room_scan(truth[k]))
            deadline = time.monotonic() + 10.0
            while not worker._outbox.empty() and time.monotonic() < deadline:
                time.sleep(0.01)
            time.sleep(0.2)
        finally:
            os.kill(worker._proc.pid, signal.SIGCONT)
        got = worker.poll(block=True)
    finally:
        worker.close()
    assert [round(t, 3) for t, _ in got] == [0.0, 0.3] and worker.skipped == 2
    np.testing.assert_allclose(got[1][1][:3, 3], truth[3] - truth[0], atol=0.01)


def test_the_registration_says_what_it_did_with_the_floor():
    """The box room seen 1 m above its floor: floor at -1.0 m, ceiling at +2.0 m, level, the motion
    kept along the floor. Walls seen only above the sensor (a LiDAR tilted up): no floor, 6 degrees
    of freedom, and a note."""
    from virus_nerf.data.bags.odometry import KissIcpSettings, ScanRegistration

    scan = _box_room_scan(np.array([1.5, 2.5, 1.0]))
    registration = ScanRegistration(KissIcpSettings())
    registration.register(0.0, scan)
    got = registration.describe()
    assert got["floor_found"] and got["motion"] == "along the floor" and "note" not in got
    assert got["floor_m"] == pytest.approx(-1.0, abs=0.01) and got["ceiling_m"] == pytest.approx(2.0, abs=0.01)
    assert got["tilt_deg"] < 0.05
    rng = np.random.default_rng(0)
    side = rng.uniform(-4.0, 4.0, 2000)
    walls = np.c_[np.where(np.arange(2000) % 2, side, 4.0), np.where(np.arange(2000) % 2, 4.0, side),
                  rng.uniform(0.0, 2.0, 2000)]
    no_floor = ScanRegistration(KissIcpSettings())
    no_floor.register(0.0, walls)
    got = no_floor.describe()
    assert not got["floor_found"] and got["motion"] == "6 degrees of freedom" and "no floor" in got["note"]
    assert ScanRegistration(KissIcpSettings(drop_floor_ceiling_m=0.0, planar=False)).describe() == {"floor_searched": False}


def test_a_stream_keeping_up_gives_every_frame_its_pose_from_the_scans_registered(bags, tiny_office):
    """map-bag and the ROS 2 node register the newest LiDAR scan and skip those that waited
    (keep_up). Each scan registered before the next comes (a LiDAR the worker keeps up with),
    except while the worker is held (SIGSTOP) for 5 scans: those are skipped but the newest, the
    frames wait for a pose at or after their stamp, and every frame is placed within 4 cm of the truth."""
    import os
    import signal
    import time

    from virus_nerf.data.bags.poses import KissPoses

    truth = load_recording(tiny_office, "office")
    n = sum(len(st) for st in truth.stacks.values())
    cfg = default_topics()
    source = KissPoses(cfg.lidar.topic, cfg.lidar, None, bags["ros1"], keep_up=True)
    pid, scans, frames = source.worker._proc.pid, 0, []
    try:
        with BagReader(bags["ros1"]) as reader:
            sync = LiveSync(cfg, source, bags["ros1"])
            for topic, msg in reader.iter_topics(sync.topics()):
                if topic == cfg.lidar.topic:
                    scans += 1
                    if scans == 10:  # the held scans written into the pipe first (a loaded machine's
                        # writer thread may lag): the worker then finds them waiting and skips all but the newest
                        deadline = time.monotonic() + 10.0
                        while not source.worker._outbox.empty() and time.monotonic() < deadline:
                            time.sleep(0.01)
                        time.sleep(0.2)
                    if scans in (5, 10):
                        os.kill(pid, signal.SIGSTOP if scans == 5 else signal.SIGCONT)
                frames += sync.push(topic, msg)
                if topic == cfg.lidar.topic and not 5 <= scans < 10:
                    source._collect(block=True)  # the LiDAR's period is longer than a registration
            frames += sync.finish()
    finally:
        os.kill(pid, signal.SIGCONT)
        source.close()
    assert scans > 10 and source.skipped > 0  # (4: the newest of the 5 registered)
    assert len(frames) == n and not sync.dropped_total()
    for f in frames:  # measured 1.7 cm at most (1.0 cm registering every scan)
        st = truth.stacks[f.frame.stack_id]
        k = int(np.argmin(np.abs(st.times - f.frame.time)))
        assert np.linalg.norm(f.frame.cam_to_world[:3, 3] - st.cam_to_world[k, :3, 3]) < 0.04


def test_lidar_odometry_and_wheel_odometry_streams(bags, tiny_office, tmp_path):
    """KISS-ICP registering scan by scan gives every frame a pose near the simulator's; a robot
    without LiDAR: nav_msgs/Odometry on /odom (here the LiDAR's true pose at each scan)."""
    truth = load_recording(tiny_office, "office")
    n = sum(len(st) for st in truth.stacks.values())
    frames, sync = _stream(bags["ros1"], "lidar-odometry")
    assert len(frames) == n and not sync.dropped_total()
    for f in frames:  # the stream cannot re-register the start against later scans (importer's refine_start_s)
        st = truth.stacks[f.frame.stack_id]
        k = int(np.argmin(np.abs(st.times - f.frame.time)))  # the world frame of both: the first scan
        # measured 1.0 cm at most (8 cm before the floor was left out and the motion kept on it, D118)
        assert np.linalg.norm(f.frame.cam_to_world[:3, 3] - st.cam_to_world[k, :3, 3]) < 0.03

    bag = _rewrite(bags["ros1"], tmp_path / "odom.bag", _odometry_edit(truth))
    frames, sync = _stream(bag, "odometry", odometry_topic="/odom")
    assert len(frames) == n and not sync.dropped_total()
    for f in frames:
        st = truth.stacks[f.frame.stack_id]
        k = int(np.argmin(np.abs(st.times - f.frame.time)))
        assert np.linalg.norm(f.frame.cam_to_world[:3, 3] - st.cam_to_world[k, :3, 3]) < 0.02  # 10 Hz interpolated


def _bad(bags, tmp_path, name, edit, **kw) -> tuple[list, StreamError]:
    bag = _rewrite(bags["ros1"], tmp_path / f"{name}.bag", edit)
    frames = []
    with pytest.raises(StreamError) as err:
        cfg = default_topics()
        with BagReader(bag) as reader:
            sync = LiveSync(cfg, make_pose_source("csv", cfg, bag, present=lambda t: True, poses_file=bags["csv"]),
                            bag, **kw)
            for topic, msg in reader.iter_topics(sync.topics()):
                frames += sync.push(topic, msg)
            frames += sync.finish()
    assert "\n" not in str(err.value)
    return frames, err.value


def test_a_depth_topic_that_stops_ends_no_stream_that_does_not_use_depth(bags, tiny_cfg, tmp_path):
    """map-bag without the rgbd sensor neither requires, reads nor waits for the depth images: a
    depth driver that stops half-way ends no stream and drops no frame (a review: the stream
    stopped with "topic ... stopped"), and a bag recorded without depth maps (it was refused for
    the missing topic); with rgbd the stream still stops."""
    depth = default_topics().stacks[1].depth

    def stops(topic, t, msg, ty):
        return [] if topic == depth and t * 1e-9 > 1700000001.0 else [(topic, ty, t, msg)]

    bag = _rewrite(bags["ros1"], tmp_path / "depth_stops.bag", stops)
    cfg = default_topics().for_sensors(("camera", "uss", "irs"))  # as map-bag and the node take them
    frames = []
    with BagReader(bag) as reader:
        sync = LiveSync(cfg, make_pose_source("csv", cfg, bag, present=lambda t: True, poses_file=bags["csv"]), bag,
                        max_silence_s=1.0)
        for topic, msg in reader.iter_topics(sync.topics()):
            frames += sync.push(topic, msg)
        frames += sync.finish()
    whole, _ = _stream(bags["ros1"], "csv", poses_file=bags["csv"])
    assert depth not in sync.topics() and len(frames) == len(whole) and not sync.dropped_total()
    frames, err = _bad(bags, tmp_path, "depth_stops_rgbd", stops, max_silence_s=1.0, with_depth=True)
    assert f"topic {depth} stopped" in str(err) and frames
    no_depth = _rewrite(bags["ros1"], tmp_path / "no_depth.bag",
                        lambda topic, t, msg, ty: [] if "depth" in topic else [(topic, ty, t, msg)])
    out = tmp_path / "out"
    code, _, stderr = run_cli(["map-bag", no_depth, "--out", out, "--playback", "20", "--config", tiny_cfg,
                               "--n-rays", "32", "--max-poses", "3", "--poses", "csv", "--poses-file", bags["csv"]])
    assert code == 0 and (out / "map" / "map.pgm").is_file(), stderr


def test_bad_input_while_streaming_names_the_topic_and_time(bags, tmp_path):
    """A clock that goes backwards, a topic that stops half-way, a pose that jumps: one line naming
    the topic (or pose source) and the bag time, after the frames made until then."""
    def keep(topic, t, msg, ty):
        return [(topic, ty, t, msg)]

    def backwards(topic, t, msg, ty):
        if topic == "/USS1" and abs(t * 1e-9 - 1700000001.458) < 0.01:  # the 8th USS1 message 1 s early
            msg.header.stamp.sec -= 1
        return keep(topic, t, msg, ty)

    frames, err = _bad(bags, tmp_path, "backwards", backwards)
    assert "topic /USS1: the clock went backwards: message 8 is stamped at 0.458 s" in str(err), err
    assert err.at_s == pytest.approx(1.25, abs=0.01) and frames

    def stops(topic, t, msg, ty):
        return [] if topic == "/TOF3" and t * 1e-9 > 1700000001.0 else keep(topic, t, msg, ty)

    frames, err = _bad(bags, tmp_path, "stops", stops, max_silence_s=1.0)
    assert "topic /TOF3 stopped: its last message is at 0.860 s" in str(err) and "none came for 1 s" in str(err)
    assert frames and err.at_s > 1.86

    def blind(topic, t, msg, ty):  # stack 1's camera never says its intrinsics
        return [] if topic == "/CAM1/color/camera_info" else keep(topic, t, msg, ty)

    frames, err = _bad(bags, tmp_path, "blind", blind, max_silence_s=1.0)
    assert re.search(r"topic /CAM1/color/camera_info sent nothing while stack 1's colour images came for 1 s \(bag "
                     r"time 1\.\d{3} s\): its frames cannot be made without the camera's intrinsics$", str(err)), err
    assert 1.0 < err.at_s < 1.4

    def jumps(topic, t, msg, ty):  # every stamp after 1.5 s 20 s later: a clock jump, not 8 topics stopping
        if t * 1e-9 > 1700000001.5:
            if hasattr(msg, "header"):
                msg.header.stamp.sec += 20
            t += 20 * 10**9
        return keep(topic, t, msg, ty)

    frames, err = _bad(bags, tmp_path, "jumps", jumps)
    assert re.search(r"the bag's clock jumps 20\.\d{3} s forward: no topic sent anything between 1\.[45]\d\d s and "
                     r"21\.\d{3} s \(message \d+ of /\S+; .* a gap over 2 s in every topic stops the stream$", str(err)), err
    assert frames and 1.4 < err.at_s <= 1.5

    # a pose file whose poses jump 2 m after 1.5 s
    rec_csv = bags["csv"].read_text().splitlines()
    jumped = [rec_csv[0]] + [_shift(row, 2.0) if float(row.split(",")[0]) > 1700000001.5 else row for row in rec_csv[1:]]
    bad_csv = tmp_path / "jump.csv"
    bad_csv.write_text("\n".join(jumped) + "\n")
    cfg = default_topics()
    frames = []
    with pytest.raises(StreamError) as err, BagReader(bags["ros1"]) as reader:
        sync = LiveSync(cfg, make_pose_source("csv", cfg, bags["ros1"], present=lambda t: True, poses_file=bad_csv),
                        bags["ros1"])
        for topic, msg in reader.iter_topics(sync.topics()):
            frames += sync.push(topic, msg)
    assert re.search(r"the pose jumps [12]\.\d\d m between the frames at 1\.\d+ s and 1\.\d+ s; expected at most 1 m",
                     str(err.value)), err.value
    assert f"--poses-file {bad_csv}" in str(err.value) and frames


def _shift(row: str, dx: float) -> str:
    v = row.split(",")
    v[1] = f"{float(v[1]) + dx:.9f}"
    return ",".join(v)


def test_map_bag_streams_with_snapshots_lag_and_final_map(bags, tiny_cfg, tmp_path):
    """The default map-bag path: snapshots every 0.6 s, each line with the lag, a final map with
    every frame the importer makes (nothing dropped at --max-lag 100), stream.json; no recording/."""
    out = tmp_path / "out"
    have_sinks = importlib.util.find_spec("rerun") and importlib.util.find_spec("mcap_ros2")
    sinks = ["--rerun-save", tmp_path / "live.rrd", "--out-bag", tmp_path / "maps_bag", "--map-frame", "odom",
             "--base-frame", "robot"] if have_sinks else []
    code, stdout, stderr = run_cli(["map-bag", bags["ros1"], "--out", out, "--playback", "2", "--snapshot-every",
                                    "0.6", "--config", tiny_cfg, "--n-rays", "32", "--max-poses", "3", "--poses", "csv",
                                    "--poses-file", bags["csv"], "--max-lag", "100", *sinks])
    assert code == 0, stderr
    lines = [ln for ln in stdout.splitlines() if ln.startswith(("snapshot", "final map"))]
    snaps = sorted(p for p in (out / "snapshots").iterdir() if p.is_dir())
    assert len(snaps) >= 1 and len(lines) == len(snaps) + 1
    for k, (line, folder) in enumerate(zip(lines, snaps, strict=False), start=1):
        assert line.startswith(f"snapshot {k} at ") and ", lag " in line and str(folder) in line
        assert {"map.pgm", "map.yaml", "map.png", "snapshot.json"} <= {p.name for p in folder.iterdir()}
    assert lines[-1].startswith("final map") and ", lag " in lines[-1]
    report = json.loads((out / "stream.json").read_text())
    final = json.loads((out / "map" / "snapshot.json").read_text())
    assert final["frames"] == report["frames"] == 30 and report["dropped"] == {} and report["stopped"] is None
    assert len(report["lag_s"]) == len(snaps) and report["first_snapshot_s"] < 5
    assert (out / "map" / "mapper.pt").is_file() and not (out / "recording").exists()
    assert "map-bag: 30 frames, 0 dropped; lag at snapshots median" in stdout and "; lag at frames median" in stdout
    # the lag as each frame reached the mapper, and at the final map (a snapshot's is taken before it)
    assert 0.0 <= report["frame_lag_median_s"] <= report["frame_lag_max_s"] and report["final_lag_s"] is not None
    if have_sinks:  # the live view and the ROS maps get every frame and every snapshot's maps, as in replay
        from test_mapper import _check_map_bag_sinks

        _check_map_bag_sinks(tmp_path / "live.rrd", tmp_path / "maps_bag", out, len(snaps), 30, ("odom", "robot"))
        _check_base_is_the_lidar(tmp_path / "maps_bag", bags["csv"])


def _check_base_is_the_lidar(bag_dir: Path, poses_csv: Path) -> None:
    """Every /tf of the maps' bag is the LiDAR's pose of --poses-file at its stamp (the cameras
    mounted by the topics file's camera_in_lidar), whichever stack's frame wrote it."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    rows = np.loadtxt(poses_csv, delimiter=",", skiprows=1)  # time, x, y, z, qx, qy, qz, qw
    with open(bag_dir / f"{bag_dir.name}.mcap", "rb") as f:
        tfs = [msg.transforms[0] for _, ch, _, msg in make_reader(f, decoder_factories=[DecoderFactory()])
               .iter_decoded_messages() if ch.topic == "/tf"]
    assert len(tfs) == 30
    for tf in tfs:
        t = tf.header.stamp.sec + 1e-9 * tf.header.stamp.nanosec
        expected = [np.interp(t, rows[:, 0], rows[:, k]) for k in (1, 2, 3)]
        v = tf.transform.translation
        np.testing.assert_allclose([v.x, v.y, v.z], expected, atol=0.01)


def test_map_bag_drops_late_frames_and_keeps_the_map_on_bad_data(bags, tiny_cfg, tmp_path):
    """Too fast a playback for the mapper: late colour images are dropped and counted. A pose jump,
    a topic that stops: exit 2, one line naming the pose source or topic and the time, the final
    map of the frames before it."""
    out = tmp_path / "late"
    code, stdout, stderr = run_cli(["map-bag", bags["ros1"], "--out", out, "--playback", "20", "--config", tiny_cfg,
                                    "--n-rays", "32", "--max-poses", "3", "--poses", "csv", "--poses-file", bags["csv"],
                                    "--max-lag", "0.05"])
    assert code == 0, stderr
    report = json.loads((out / "stream.json").read_text())
    # how many are late depends on the machine's speed (8-12 of 30 on 2 cores): some are, and every
    # colour image is a frame or a dropped one
    late = report["dropped"]["late (the mapper was behind)"]
    assert late >= 1 and report["frames"] >= 1 and report["frames"] + sum(report["dropped"].values()) == 30
    assert f"{late} late (the mapper was behind)" in stdout
    if late >= 0.05 * (report["frames"] + late):  # fell behind: said in a line of its own
        assert (f"map-bag: warning: the mapper fell behind the bag: {late} of {report['frames'] + late} frames were "
                "dropped as late; a lower --playback (now 20) keeps up on this machine") in stdout

    rows = bags["csv"].read_text().splitlines()
    bad_csv = tmp_path / "jump.csv"
    bad_csv.write_text("\n".join([rows[0]] + [_shift(r, 3.0) if float(r.split(",")[0]) > 1700000001.5 else r
                                              for r in rows[1:]]) + "\n")
    out = tmp_path / "jump"
    code, stdout, stderr = run_cli(["map-bag", bags["ros1"], "--out", out, "--playback", "4", "--config", tiny_cfg,
                                    "--n-rays", "32", "--max-poses", "3", "--poses", "csv", "--poses-file", bad_csv,
                                    "--max-lag", "100"])
    assert code == 2 and stderr.count("\n") == 1 and re.search(r"the pose jumps [23]\.\d\d m", stderr), stderr
    report = json.loads((out / "stream.json").read_text())
    final = json.loads((out / "map" / "snapshot.json").read_text())
    assert 10 <= final["frames"] == report["frames"] < 30 and 1.5 < report["stopped_at_s"] < 1.75
    assert "map-bag: stopped at 1.6" in stdout and (out / "map" / "map.pgm").is_file()

    bag = _rewrite(bags["ros1"], tmp_path / "stops.bag",  # /USS3 stops after 1 s
                   lambda topic, t, msg, ty: [] if topic == "/USS3" and t * 1e-9 > 1700000001.0 else [(topic, ty, t, msg)])
    out = tmp_path / "stops"
    code, stdout, stderr = run_cli(["map-bag", bag, "--out", out, "--playback", "4", "--config", tiny_cfg,
                                    "--n-rays", "32", "--max-poses", "3", "--poses", "csv", "--poses-file", bags["csv"],
                                    "--max-lag", "100", "--max-silence", "1"])
    assert code == 2 and stderr.count("\n") == 1, stderr
    assert "topic /USS3 stopped: its last message is at 0.860 s and none came for 1 s" in stderr
    assert json.loads((out / "map" / "snapshot.json").read_text())["frames"] >= 10


def test_map_bag_refuses_a_bag_without_images_or_odometry(bags, tmp_path):
    """No colour image messages, or no odometry topic for --poses odometry: one line naming the
    topic, nothing written; --poses odometry cannot --import-first."""
    bag = _rewrite(bags["ros1"], tmp_path / "blind.bag",
                   lambda topic, t, msg, ty: [] if topic == "/CAM1/color/image_raw" else [(topic, ty, t, msg)])
    for argv, message in (([bag, "--poses", "csv", "--poses-file", bags["csv"]], "no topic /CAM1/color/image_raw"),
                          ([bags["ros1"], "--poses", "odometry"], "no topic /odom (--odometry-topic)"),
                          ([bags["ros1"], "--poses", "odometry", "--import-first"], "--poses odometry streams only"),
                          ([bags["ros1"], "--poses", "csv"], "--poses csv needs --poses-file")):
        code, _, stderr = run_cli(["map-bag", *argv, "--out", tmp_path / "out"])
        assert code == 2 and stderr.count("\n") == 1 and message in stderr, stderr
        assert not (tmp_path / "out").exists()
    # a stream that maps nothing (no transform to the world frame asked for) keeps nothing: not
    # OUT, not the maps' bag it had begun, so the same command can run again
    code, _, stderr = run_cli(["map-bag", bags["tf"], "--out", tmp_path / "out", "--poses", "tf", "--tf-parent",
                               "nowhere", "--out-bag", tmp_path / "maps_bag", "--playback", "4"])
    assert code == 2 and stderr.count("\n") == 1 and "nowhere" in stderr, stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blind.bag"]
    for argv, message in (([tmp_path / "out"], f"--out-bag {tmp_path / 'out'}: the same folder as --out"),
                          ([tmp_path / "blind.bag" / "maps"], f"--out-bag {tmp_path / 'blind.bag' / 'maps'}: cannot "
                                                              f"be made: {tmp_path / 'blind.bag'} is a file, not a folder")):
        code, _, stderr = run_cli(["map-bag", bags["ros1"], "--poses", "csv", "--poses-file", bags["csv"], "--out",
                                   tmp_path / "out", "--out-bag", *argv])
        assert code == 2 and stderr.count("\n") == 1 and message in stderr, stderr
    code, _, stderr = run_cli(["map-bag", bags["ros1"], "--poses", "csv", "--poses-file", bags["csv"], "--out",
                               tmp_path / "blind.bag" / "out"])
    assert code == 2 and f"--out {tmp_path / 'blind.bag' / 'out'}: cannot be made: {tmp_path / 'blind.bag'} is a " \
                         "file, not a folder" in stderr, stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blind.bag"]
    # a config whose step could not fit in memory (issue 39): the marcher's worst case, before any work
    big = tmp_path / "big.json"
    big.write_text(json.dumps({"batch_size": 10**9}))
    code, _, stderr = run_cli(["map-bag", bags["ros1"], "--poses", "csv", "--poses-file", bags["csv"], "--config", big,
                               "--out", tmp_path / "out"])
    assert code == 2 and stderr.count("\n") == 1, stderr
    assert f"--config {big}: batch_size 1000000000: a step may march up to 256 samples a ray" in stderr, stderr
    assert not (tmp_path / "out").exists()


def _odometry_edit(truth, drop_lidar: bool = False):
    """A `_rewrite` edit adding nav_msgs/Odometry on /odom (the LiDAR's true pose) at every LiDAR
    stamp, and with `drop_lidar` leaving the LiDAR out: a robot with wheel odometry and no LiDAR."""
    from virus_nerf.sensors.geometry import matrix_to_quat

    T = m.make_typestore(1).types

    def edit(topic, t_ns, msg, msgtype):
        out = [] if drop_lidar and topic == "/rslidar_points" else [(topic, msgtype, t_ns, msg)]
        if topic == "/rslidar_points":
            pose = truth.lidar_pose_at(t_ns * 1e-9)
            q = matrix_to_quat(pose[:3, :3])
            cov = np.zeros(36)
            odom = T["nav_msgs/msg/Odometry"](
                header=T["std_msgs/msg/Header"](seq=0, stamp=msg.header.stamp, frame_id="odom"), child_frame_id="rslidar",
                pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=pose[0, 3], y=pose[1, 3], z=pose[2, 3]),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])), covariance=cov),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](
                    linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                    angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)), covariance=cov))
            out.append(("/odom", "nav_msgs/msg/Odometry", t_ns, odom))
        return out

    return edit


def test_import_bag_with_wheel_odometry_and_no_lidar_trains_without_ground_truth(bags, tiny_office, tiny_cfg,
                                                                                 tmp_path):
    """Issue 29 item 1: a bag with cameras, USS, IRS and nav_msgs/Odometry only imports (camera =
    odometry pose x mounting, exactly the LiDAR-pose import's), and `train` on it maps and scores
    nothing."""
    truth = load_recording(tiny_office, "office")
    bag = _rewrite(bags["ros1"], tmp_path / "odom.bag", _odometry_edit(truth, drop_lidar=True))
    code, out, err = run_cli(["import-bag", bag, "--out", tmp_path / "data", "--poses", "odometry"])
    assert code == 0, err
    rec = load_recording(tmp_path / "data", "odom")
    assert rec.map_path is None and len(rec.lidar_times) == 0
    for s, st in rec.stacks.items():  # the poses at the camera stamps: the simulator's, to the 10 Hz interpolation
        ref = truth.stacks[s]
        k = np.searchsorted(ref.times, st.times)
        np.testing.assert_allclose(st.times, ref.times[k], atol=1e-6)
        assert np.abs(st.cam_to_world[:, :3, 3] - ref.cam_to_world[k, :3, 3]).max() < 0.02
    code, out, err = run_cli(["train", "--data", tmp_path / "data", "--room", "odom", "--out", tmp_path / "run",
                              "--config", tiny_cfg, "--quiet"])
    assert code == 0, err
    assert "no LiDAR map" in out and (tmp_path / "run" / "map" / "map.pgm").is_file()


def test_live_mode_says_each_problem_once_and_goes_on(bags, tmp_path):
    """The ROS 2 node's stream (LiveSync with on_problem): a topic that stops and comes back, a
    malformed message, a message out of order, a pose that jumps and a clock that goes back to the
    bag's start (played again) are each one line, and frames keep coming after every one."""
    import dataclasses

    cfg = default_topics()
    rec_csv = bags["csv"].read_text().splitlines()
    jumped = [rec_csv[0]] + [_shift(row, 2.0) if 1700000001.5 < float(row.split(",")[0]) < 1700000001.8 else row
                             for row in rec_csv[1:]]
    csv = tmp_path / "jump.csv"
    csv.write_text("\n".join(jumped) + "\n")
    with BagReader(bags["ros1"]) as reader:
        lines: list[str] = []
        sync = LiveSync(cfg, make_pose_source("csv", cfg, bags["ros1"], present=lambda t: True, poses_file=csv),
                        bags["ros1"], max_silence_s=0.5, on_problem=lines.append)
        messages = list(reader.iter_topics(sync.topics()))
    t0 = messages[0][1].time_s
    edited = []
    for topic, msg in messages:
        rel = msg.time_s - t0
        if topic == "/USS1" and 0.8 < rel < 1.6:
            continue  # silent for 0.8 s
        if topic == "/TOF3" and msg.index == 5:
            msg = dataclasses.replace(msg, msg=dataclasses.replace(msg.msg, meas=np.zeros(10, dtype=np.uint16)))
        edited.append((topic, msg))
        if topic == "/USS3" and msg.index == 12:  # an older message again: out of order
            edited.append((topic, dataclasses.replace(messages_by(messages, "/USS3", 11), index=13)))
    made = [sync.push(topic, msg) for topic, msg in edited]
    first_pass = sum(len(f) for f in made)
    again = [sync.push(topic, dataclasses.replace(msg)) for topic, msg in messages]  # the bag played again
    again.append(sync.finish())
    said = "\n".join(lines)
    assert "topic /USS1 stopped: its last message is at 0.625 s and none came for 0.5 s" in said
    assert "mapping goes on without it" in said and "topic /USS1 is back at bag time 1.667 s after 1.0 s" in said
    assert "/TOF3" in said and "the message is skipped" in said
    assert "topic /USS3: the clock went backwards" in said
    assert re.search(r"the pose jumps [12]\.\d\d m .*; the frame is dropped", said), said
    assert "taken as a restart (a bag played again, a clock reset)" in said
    assert len(lines) == len(set(lines)) and all("\n" not in ln for ln in lines)
    assert first_pass >= 20 and sum(len(f) for f in again) >= 20  # frames keep coming after each problem
    assert sync.dropped_total()["pose jump"] >= 1 and sync.problems["restart"] >= 1


def messages_by(messages, topic: str, index: int):
    return next(msg for t, msg in messages if t == topic and msg.index == index)


def _live(bags, keep) -> tuple[list, LiveSync, list[str]]:
    """The ROS 1 bag streamed live (the node's LiveSync, max_silence_s 0.5) with the messages
    keep(topic, msg, sync) passes: (frames, sync, the lines it said)."""
    cfg = default_topics()
    lines: list[str] = []
    with BagReader(bags["ros1"]) as reader:
        source = make_pose_source("csv", cfg, bags["ros1"], present=lambda t: True, poses_file=bags["csv"])
        sync = LiveSync(cfg, source, bags["ros1"], max_silence_s=0.5, on_problem=lines.append)
        frames = []
        for topic, msg in reader.iter_topics(sync.topics()):
            if keep(topic, msg, sync):
                frames += sync.push(topic, msg)
        frames += sync.finish()
    return frames, sync, lines


def test_live_a_silent_tof_leaves_its_camera_mapping(bags):
    """Live, a ToF topic that never sends is said once and its stack's frames go on without it
    (IRS all NaN: no measurement, as for a stack without a ToF), counted in `without`; only the
    frames before its silence was noticed wait in vain. The other stack keeps its ToF."""
    frames, sync, lines = _live(bags, lambda topic, msg, sync: topic != "/TOF3")
    by_stack = _by_stack(frames)
    assert any("topic /TOF3 sent nothing" in ln and "mapping goes on without it" in ln for ln in lines), lines
    waited = sum(n for why, n in sync.dropped[3].items() if why.startswith("no tof"))
    assert len(by_stack[3]) >= 10 and all(np.isnan(f.irs_range).all() for f in by_stack[3])
    assert sync.without_total() == {"tof": len(by_stack[3])} and 1 <= waited <= len(by_stack[3])
    assert not any("camera_info" in ln for ln in lines)
    whole = _by_stack(_stream(bags["ros1"], "csv", poses_file=bags["csv"])[0])[1]  # every topic, not live
    assert [f.time for f in by_stack[1]] == [f.time for f in whole]
    assert all(np.array_equal(a.irs_range, b.irs_range, equal_nan=True) for a, b in zip(by_stack[1], whole, strict=True))
    assert any(np.isfinite(f.irs_range).any() for f in by_stack[1])


def test_live_a_camera_without_camera_info_is_said_and_said_back(bags):
    """Live, colour images whose camera_info does not come (a typo in the topics file, a driver
    that does not publish it): said once after max_silence_s, the stack's frames dropped and counted
    meanwhile; when it comes, said back, and that stack's frames are made again."""
    frames, sync, lines = _live(bags, lambda topic, msg, sync: topic != "/CAM3/color/camera_info"
                               or msg.time_s - sync.t0 > 1.5)
    said = [ln for ln in lines if "camera_info" in ln]
    assert len(said) == 2, lines
    assert re.search(r"topic /CAM3/color/camera_info sent nothing while stack 3's colour images came for 0\.5 s "
                     r"\(bag time 0\.\d{3} s\): its frames cannot be made without the camera's intrinsics; they are "
                     r"dropped until it comes$", said[0]), said[0]
    assert re.search(r"topic /CAM3/color/camera_info is back at bag time 1\.[5-7]\d\d s$", said[1]), said[1]
    by_stack = _by_stack(frames)
    assert sync.dropped[3]["no camera_info"] >= 5 and by_stack[3] and min(f.time for f in by_stack[3]) > sync.t0 + 1.4
    assert len(by_stack[1]) >= 10  # the other camera never waited


def test_an_out_that_keeps_nothing_leaves_no_parent_behind(tmp_path):
    """map-bag and the ROS 2 node make --out with its missing parents; a run that keeps nothing
    removes what it made, and only that."""
    from virus_nerf.mapping.command import make_out

    made = make_out(tmp_path / "a" / "b" / "out")
    (made.out / "stream.json").write_text("{}")
    made.remove()
    assert not (tmp_path / "a").exists() and tmp_path.is_dir()
    made = make_out(tmp_path / "a" / "b" / "out")
    (tmp_path / "a" / "notes.txt").write_text("another's")  # written beside it meanwhile: stays
    made.remove()
    assert not (tmp_path / "a" / "b").exists() and (tmp_path / "a" / "notes.txt").read_text() == "another's"


def _csv_sync(bags, on_problem=None) -> tuple[LiveSync, list]:
    """A LiveSync of the default topics on the bag's CSV poses (live when `on_problem` is given) and
    the bag's messages in order."""
    cfg = default_topics()
    with BagReader(bags["ros1"]) as reader:
        sync = LiveSync(cfg, make_pose_source("csv", cfg, bags["ros1"], present=lambda t: True, poses_file=bags["csv"]),
                        bags["ros1"], on_problem=on_problem)
        return sync, list(reader.iter_topics(sync.topics()))


def test_live_stream_played_twice_keeps_the_mapper_in_time_order(bags, tiny_cfg, tmp_path):
    """Live, a bag played again (a clock reset) restarts the synchronisation; its frames reach the
    mapper after `restart_clock`, so they continue after the newest frame in the mapper's store
    (which refuses a frame older than its stack's previous one) and the map takes both passes."""
    import math

    from virus_nerf.mapping.options import load_stream_config
    from virus_nerf.mapping.stream import StreamRun

    lines: list[str] = []
    sync, messages = _csv_sync(bags, lines.append)
    once = sum(1 for t, _ in messages if t in ("/CAM1/color/image_raw", "/CAM3/color/image_raw"))
    (tmp_path / "out").mkdir()
    run = StreamRun(sync, tmp_path / "out", load_stream_config(tiny_cfg), snapshot_every=1e9, first_snapshot=1e9,
                    max_lag=math.inf, drive_s=10.0, n_rays=16, max_poses=2, log=lambda line: None)
    report = run.run(messages + messages)
    assert any("taken as a restart" in ln for ln in lines) and sync.restarts == 1
    store = run.mapper.store
    assert report.frames == len(store) > once  # frames of both passes (a few wait for partners at each start)
    for s in (1, 3):
        times = store.times[store.stack_ids == s]
        assert (np.diff(times) > 0).all()  # in time order, the second pass after the first
    first_pass_end = max(f.time_s for t, f in messages)
    assert store.times.max() > first_pass_end + 1.0 and report.final is not None
    if importlib.util.find_spec("mcap_ros2") is None:
        return
    # a snapshot due after a restart, before a frame of the new clock is mapped (the ROS 2 node's
    # /map publisher, here the bag's writer): the maps carry the stream's first stamp, no crash
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from virus_nerf.mapping.ros_maps import RosMapBag

    with RosMapBag(tmp_path / "maps") as run.ros_bag:
        sync.restarts += 1
        run._restarted()
        run.next_snapshot = 0.0  # due
        assert run._maybe_snapshot() and run.newest is None
    with open(run.ros_bag.mcap_path, "rb") as f:
        grid = next(msg for _, ch, _, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()
                    if ch.topic == "/map")
    t0 = messages[0][1].time_s
    assert grid.header.stamp.sec + 1e-9 * grid.header.stamp.nanosec == pytest.approx(t0, abs=1e-6)


def test_resume_finishes_from_the_newest_snapshot_past_9999(tmp_path):
    """Snapshot folders are numbered 0001, 0002, ...; the 10000th (14 h at a snapshot every 5 s)
    has five digits and sorts before 9999 as text: `map-bag --resume` of a killed run takes the
    newest by its number."""
    from virus_nerf.mapping.stream import finish_killed

    out = tmp_path / "run"
    for k, t in ((9998, 49990.0), (9999, 49995.0), (10000, 50000.0)):
        snap = out / "snapshots" / f"{k:04d}_{t:.1f}s"
        snap.mkdir(parents=True)
        (snap / "map.pgm").write_text(f"map of snapshot {k}")
        (snap / "snapshot.json").write_text(json.dumps({"frames": k, "steps": 2 * k, "seconds": t}))
    (out / "stream.json").write_text(json.dumps({"running": True}))
    lines = []
    report = finish_killed(out, log=lines.append)
    assert (out / "map" / "map.pgm").read_text() == "map of snapshot 10000"
    assert report.frames == 10000 and report.steps == 20000
    assert report.stopped == "killed after snapshot 10000 (10000_50000.0s)"
    assert lines[0].startswith(f"map-bag: the stream in {out} was stopped after snapshot 10000; final map")
    assert [Path(p).name for p in report.snapshots] == ["9998_49990.0s", "9999_49995.0s", "10000_50000.0s"]


def test_a_stop_at_the_end_of_the_bag_keeps_a_finite_stop_time(bags, tiny_cfg, tmp_path):
    """SIGTERM while the stream decides its last frames (`LiveSync.finish` puts its clock past every
    message): stream.json says it stopped at the newest message, a number (before: inf, which JSON
    refuses, so a traceback, `running: true` and no mapper.pt)."""
    import math
    import signal

    from virus_nerf.mapping.options import load_stream_config
    from virus_nerf.mapping.stream import StreamRun
    from virus_nerf.utils.stop import Stopped

    sync, messages = _csv_sync(bags)
    finish = sync.finish

    def finish_then_stop():
        finish()
        raise Stopped(signal.SIGTERM)

    sync.finish = finish_then_stop
    (tmp_path / "out").mkdir()
    run = StreamRun(sync, tmp_path / "out", load_stream_config(tiny_cfg), snapshot_every=1e9, first_snapshot=1e9,
                    max_lag=math.inf, drive_s=10.0, n_rays=16, max_poses=2, log=lambda line: None)
    with pytest.raises(Stopped):
        run.run(messages)
    doc = json.loads((tmp_path / "out" / "stream.json").read_text())
    newest = max(m.time_s for t, m in messages if t not in ("/tf_static",))
    assert doc["stopped"] == "interrupted (SIGTERM)" and doc["running"] is False
    assert doc["stopped_at_s"] == pytest.approx(newest - messages[0][1].time_s, abs=1e-6)
    assert (tmp_path / "out" / "map" / "mapper.pt").is_file()


def test_resume_sets_aside_a_final_map_a_full_disk_cut_and_clears_cut_snapshots(tmp_path):
    """A full disk at the end left map/ without its maps (before: with mapper.pt alone, or empty):
    `--resume` no longer takes it for a finished map; an empty one goes, one with files is kept
    aside. A snapshot a kill cut short (`.NAME.partial-*`) is cleared."""
    from virus_nerf.mapping.stream import finish_killed

    for case in ("empty", "with files"):
        out = tmp_path / case.replace(" ", "_")
        snap = out / "snapshots" / "0001_10.0s"
        snap.mkdir(parents=True)
        (snap / "map.pgm").write_text("map of snapshot 1")
        (snap / "snapshot.json").write_text(json.dumps({"frames": 5, "steps": 9, "seconds": 3.0}))
        (out / "snapshots" / ".0002_20.0s.partial-99999999-x").mkdir()
        (out / "stream.json").write_text(json.dumps({"running": True}))
        (out / "map").mkdir()
        if case == "with files":
            (out / "map" / "mapper.pt").write_text("a state beside no map")
        finish_killed(out, log=lambda line: None)
        assert (out / "map" / "map.pgm").read_text() == "map of snapshot 1"
        assert not list((out / "snapshots").glob(".*partial*"))
        kept = list(out.glob("map.incomplete-*"))
        assert len(kept) == (case == "with files")
        if kept:
            assert (kept[0] / "mapper.pt").read_text() == "a state beside no map"


def test_a_snapshot_slower_than_its_period_puts_the_next_further_off():
    """Snapshots take at most half the wall time: the next is on the --snapshot-every grid, after
    the one just written, and no sooner than it took to write (hand-computed grid points). Before,
    a 4 s snapshot every 0.6 s left the stream only snapshots and its lag grew to 100 s."""
    from virus_nerf.mapping.replay import next_snapshot_time

    # a fast snapshot: the next grid point (10 s scheduled, written by 10.5 s in 0.5 s -> 20 s)
    assert next_snapshot_time(10.0, 10.0, 10.5, 0.5) == 20.0
    # missed grid points are skipped: written by 31 s (took 1 s) -> 40 s, not 20 s or 30 s
    assert next_snapshot_time(10.0, 10.0, 31.0, 1.0) == 40.0
    # slower than its period: scheduled at 1.0 s every 0.5 s, 4.1 s to write (done at 5.1 s):
    # not before 9.2 s -> grid point 1.0 + 17 * 0.5 = 9.5 s (before: 5.5 s)
    assert next_snapshot_time(1.0, 0.5, 5.1, 4.1) == pytest.approx(9.5)
    # at most a quarter of the wall time: 3 x as long as it took after it
    assert next_snapshot_time(1.0, 0.5, 5.1, 4.1, share=0.25) == pytest.approx(17.5)


def test_live_every_colour_image_is_a_frame_or_counted_across_a_restart(bags):
    """Live, a bag cut short just after a colour image, then played whole: every colour image
    pushed is a frame or a dropped one with its reason. The image that was waiting for its depth,
    USS and IRS when the clock went back is "before a clock restart" (before, it vanished from
    the counts)."""

    sync, messages = _csv_sync(bags, lambda line: None)
    colours = [k for k, (t, _) in enumerate(messages) if sync.is_color(t)]
    cut = colours[len(colours) // 2]  # a colour image mid-bag; its partners come after it
    first = messages[:cut + 1]
    made = sum(len(sync.push(t, msg)) for t, msg in first + messages) + len(sync.finish())
    dropped = sync.dropped_total()
    assert sync.restarts == 1 and dropped == {"before a clock restart": 1}
    assert made + 1 == len(colours) // 2 + 1 + len(colours)


def test_a_take_spanning_a_clock_restart_keeps_each_pass_whole(bags):
    """The ROS 2 node takes each topic's messages in arrival order and feeds them in stamp order;
    a take that spans a restart (a bag played again) keeps the old pass's tail before the new
    pass's head (hand-made take: A 2.9, 0.0, 0.1 and B 2.95, 0.05). Fed so, the stream restarts
    once and says no topic stopped (before: stamp order alone gave two restarts and 13 lines)."""
    pytest.importorskip("cyclonedds")
    from virus_nerf.data.bags.reader import Message
    from virus_nerf.ros2.node import order_take

    def msg(t):
        return Message(0, t, None, "x", None)

    take = [("A", msg(2.9)), ("A", msg(0.0)), ("A", msg(0.1)), ("B", msg(2.95)), ("B", msg(0.05))]
    newest = {"A": 2.8}
    got = [(topic, m_.time_s) for topic, m_ in order_take(take, newest)]
    assert got == [("A", 2.9), ("B", 2.95), ("A", 0.0), ("B", 0.05), ("A", 0.1)]
    assert newest == {"A": 0.1, "B": 0.05}
    # a take within one pass: plain stamp order
    assert [m_.time_s for _, m_ in order_take([("A", msg(0.3)), ("B", msg(0.2))], newest)] == [0.2, 0.3]
    # the whole bag twice in one take, each topic in arrival order: one restart
    lines: list[str] = []
    sync, messages = _csv_sync(bags, lines.append)
    by_topic = sorted(messages + messages, key=lambda item: item[0])  # stable: each topic's in arrival order
    for topic, m_ in order_take(by_topic, {}):
        sync.push(topic, m_)
    assert sync.restarts == 1 and not any("stopped" in ln for ln in lines), lines


def test_a_snapshot_the_disk_refused_still_lets_the_map_train(tmp_path):
    """Before the first snapshot no step starts that might delay it; after it, the map trains
    freely. A snapshot a full disk refused counts as the first: before, a node on a full disk
    mapped 97 frames with 0 steps (a review: every map it published came from an untrained field)."""
    import errno
    import time as time_mod
    from types import SimpleNamespace

    from virus_nerf.mapping.stream import StreamRun

    lines: list[str] = []
    run = StreamRun(SimpleNamespace(), tmp_path, None, snapshot_every=1.0, first_snapshot=1.0, log=lines.append,
                    warm_step_s=5.0)  # a slow machine: a step may take 10 s
    run.mapper = SimpleNamespace(step=0, seconds=0.0)
    run.start = time_mod.monotonic() - 0.5
    assert not run._may_train(run.now())  # 10 s to the step, 0.5 s to the first snapshot

    def full(folder, recording_time, with_state=False):
        raise OSError(errno.ENOSPC, "No space left on device", str(folder / "map.png"))

    run._snapshot = full
    run.start = time_mod.monotonic() - 1.2  # the first snapshot is due
    assert run._maybe_snapshot() and run.report.snapshots == []
    assert lines and "could not be written (No space left on device); mapping goes on" in lines[0]
    assert run._may_train(run.now())


def test_live_a_robot_that_pauses_and_goes_on_is_not_said_stopped(bags):
    """Live, every topic quiet for 5 s (the robot paused), then all of them again: nothing is said
    (docs: "if every topic stops, the clock stops with them"; before, each topic was said stopped
    and back at once) and the frames after the pause are mapped. A topic that does not come back
    after the pause is still said stopped."""
    import dataclasses

    cfg = default_topics()
    with BagReader(bags["ros1"]) as reader:
        messages = list(reader.iter_topics(LiveSync(cfg, make_pose_source(
            "csv", cfg, bags["ros1"], present=lambda t: True, poses_file=bags["csv"]), bags["ros1"]).topics()))
    t0 = messages[0][1].time_s

    def shifted(m_):  # the pause at 0.5 s of the bag (2.4 s after it); the poses file is on the bag's clock, shifted too
        return m_ if m_.time_s < t0 + 0.5 else dataclasses.replace(m_, time_s=m_.time_s + 5.0)

    csv = np.loadtxt(bags["csv"], delimiter=",", skiprows=1)
    csv[csv[:, 0] >= t0 + 0.5, 0] += 5.0
    moved = bags["csv"].with_name("paused.csv")
    np.savetxt(moved, csv, delimiter=",", header="time,x,y,z,qx,qy,qz,qw", comments="", fmt="%.9f")
    for drop in (None, "/TOF1"):
        lines: list[str] = []
        sync = LiveSync(cfg, make_pose_source("csv", cfg, bags["ros1"], present=lambda t: True, poses_file=moved),
                        bags["ros1"], on_problem=lines.append)
        made = [f for t, m_ in messages if not (drop and t == drop and m_.time_s >= t0 + 0.5)
                for f in sync.push(t, shifted(m_))] + sync.finish()
        if drop is None:
            assert lines == [] and any(f.frame.time > t0 + 5.5 for f in made)
        else:
            assert [ln for ln in lines if "stopped" in ln and drop in ln], lines


def test_a_camera_whose_camera_info_comes_after_the_map_started_joins_it(bags, tiny_cfg, tmp_path):
    """Live, a camera driver that starts late: stack 3's camera_info comes 2 s into the drive, past
    the first second's wait, so the map starts with stack 1 alone; stack 3 joins when its
    camera_info comes, said once, and its frames are mapped from then on (before: never, in the
    whole run)."""
    import math

    from virus_nerf.mapping.options import load_stream_config
    from virus_nerf.mapping.stream import StreamRun

    problems, lines = [], []
    sync, messages = _csv_sync(bags, problems.append)
    t0 = messages[0][1].time_s
    late = [(t, m_) for t, m_ in messages if t != "/CAM3/color/camera_info" or m_.time_s - t0 > 2.0]
    (tmp_path / "out").mkdir()
    run = StreamRun(sync, tmp_path / "out", load_stream_config(tiny_cfg), snapshot_every=1e9, first_snapshot=1e9,
                    max_lag=math.inf, drive_s=10.0, n_rays=16, max_poses=2, log=lines.append)
    report = run.run(late)
    joined = [ln for ln in lines if "camera_info came after the map was started" in ln]
    assert len(joined) == 1 and re.fullmatch(r"stack 3's camera_info came after the map was started: its frames are "
                                             r"mapped from now on \(bag time 2\.\d{3} s\)", joined[0]), lines
    store = run.mapper.store
    mine = store.times[store.stack_ids == 3]
    assert len(mine) >= 3 and mine.min() > 2.0 and (store.stack_ids == 1).sum() >= 10, (len(mine), store.stack_ids)
    assert sync.dropped[3]["no camera_info"] > 0 and "camera_info after the map started" not in sync.dropped[3]
    assert report.frames == len(store)


def test_a_late_camera_that_cannot_join_is_said_once(tmp_path):
    """A late camera whose images differ in size from the mapped ones cannot join (one batch
    holds every camera's pixels): said once with the reason, its frames counted under their own
    reason (a review saw such a stack said "back" and then never mapped, with no word why)."""
    from collections import Counter
    from types import SimpleNamespace

    from virus_nerf.errors import UsageError
    from virus_nerf.mapping.stream import StreamRun

    def add_stack(sid, intrinsics):
        raise UsageError("Mapper.add_stack intrinsics: the stacks' images differ in size (stack 1 640x480, stack 3 848x480)")

    lines: list[str] = []
    sync = SimpleNamespace(dropped={1: Counter(), 3: Counter()}, intrinsics={1: "cam1", 3: "cam3"})
    run = StreamRun(sync, tmp_path, None, log=lines.append)
    run.mapper = SimpleNamespace(intrinsics={1: "cam1"}, add_stack=add_stack)
    late = SimpleNamespace(frame=SimpleNamespace(stack_id=3))
    run._add([late, late])
    assert sync.dropped[3] == {"camera_info after the map started": 2}
    assert lines == ["warning: stack 3's camera_info came after the map was started with stacks [1], and it cannot "
                     "join: Mapper.add_stack intrinsics: the stacks' images differ in size (stack 1 640x480, stack 3 848x480); "
                     "its frames are not mapped in this run (said once)"]


def test_a_stream_that_dropped_a_twentieth_of_its_frames_as_late_says_it_fell_behind():
    from virus_nerf.data.bags.live import LATE
    from virus_nerf.mapping.stream import StreamReport, behind_note

    assert behind_note(StreamReport(frames=83, dropped={LATE: 33, "no pose": 2}), 4.0) == (
        "the mapper fell behind the bag: 33 of 116 frames were dropped as late; a lower --playback (now 4) keeps up "
        "on this machine")
    assert behind_note(StreamReport(frames=96, dropped={LATE: 4}), 1.0) is None  # 4 of 100: below a twentieth
    assert behind_note(StreamReport(frames=95, dropped={LATE: 5}), 1.0) is not None
    assert behind_note(StreamReport(frames=10, dropped={"no pose": 9}), 1.0) is None


def test_keep_snapshots_leaves_the_newest_on_disk_and_the_numbering_goes_on(bags, tiny_cfg, tmp_path):
    """--keep-snapshots 1: a long drive's disk holds the newest snapshot folder only; every one is
    still made and numbered, stream.json lists what is on disk and counts the removed; the final
    map and mapper.pt as always. Refused at 0, with --import-first and with --resume."""
    out = tmp_path / "keep"
    code, stdout, stderr = run_cli(["map-bag", bags["ros1"], "--out", out, "--playback", "1", "--snapshot-every", "0.3",
                                    "--first-snapshot", "0.2", "--keep-snapshots", "1", "--config", tiny_cfg,
                                    "--n-rays", "32", "--max-poses", "3", "--poses", "csv", "--poses-file", bags["csv"],
                                    "--max-lag", "100"])
    assert code == 0, stderr
    made = [ln.split(" -> ")[-1] for ln in stdout.splitlines() if ln.startswith("snapshot ")]
    assert len(made) >= 2, stdout
    on_disk = sorted(p.name for p in (out / "snapshots").iterdir() if p.is_dir())
    assert on_disk == [Path(made[-1]).name] and Path(made[-1]).name.startswith(f"{len(made):04d}_")
    report = json.loads((out / "stream.json").read_text())
    assert report["snapshots"] == [f"snapshots/{on_disk[0]}"] and report["snapshots_removed"] == len(made) - 1
    assert f"1 snapshot(s) (and {len(made) - 1} older ones removed) in" in stdout
    assert (out / "map" / "map.pgm").is_file() and (out / "map" / "mapper.pt").is_file()
    for extra, said in ((["--keep-snapshots", "0"], "--keep-snapshots 0"),
                        (["--keep-snapshots", "2", "--import-first"], "--keep-snapshots streams only")):
        code, _, err = run_cli(["map-bag", bags["ros1"], "--out", tmp_path / "no", *extra])
        assert code == 2 and said in err and not (tmp_path / "no").exists(), err
    code, _, err = run_cli(["map-bag", "--resume", "--out", out, "--keep-snapshots", "2"])
    assert code == 2 and "--keep-snapshots cannot apply to it" in err, err
