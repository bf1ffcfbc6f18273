"""One decoder per message kind (issue 38, item 2): hand-built messages decode to known metres and
seconds, the checks are the layout files' (a ToF zone beyond 100 m, a depth map's invalid values, a
unit quaternion), and import-bag and the stream refuse the same bad message in the same words."""

from __future__ import annotations

import re
from pathlib import Path
from types import SimpleNamespace as NS

import numpy as np
import pytest

from virus_nerf.data.bags import messages as m
from virus_nerf.errors import DataFormatError

WHERE = m.Where(Path("robot.bag"), "/TOF1", 4)


def _header(sec: int, nanosec: int, frame: str = "") -> NS:
    return NS(stamp=NS(sec=sec, nanosec=nanosec), frame_id=frame)


def test_tof_zones_become_an_image_ordered_grid_in_metres():
    """Zone k of the sensor lands at grid[k % 8, 7 - k // 8] (sensors/irs.py); 0 and <= 100 mm are
    invalid; stds default to 65535 when the message has none."""
    meas = np.full(64, 1000, dtype=np.uint16)
    meas[0], meas[9], meas[63] = 2345, 0, 100  # zone 0: 2.345 m; zone 9 no target; zone 63 at the 0.1 m floor
    r = m.decode_tof(NS(meas=meas), WHERE)
    grid = r.grid_m()
    assert grid.shape == (8, 8) and grid[0, 7] == pytest.approx(2.345)
    assert np.isnan(grid[1, 6]) and np.isnan(grid[7, 0])
    assert np.count_nonzero(grid == 1.0) == 61
    assert r.stds_mm.tolist() == [65535.0] * 64
    with pytest.raises(DataFormatError, match=r"field 'meas'.*has 63 zones; expected 64"):
        m.decode_tof(NS(meas=meas[:63]), WHERE)


def test_a_tof_zone_beyond_100_m_is_refused_as_from_a_tof_file(tmp_path):
    """150 m in zone 10: the message is refused naming topic, message and zone, in the words the
    TOF file's reader uses for the same reading (one rule: sensors/irs.py)."""
    from virus_nerf.data.ethz import read_tof

    meas = np.full(64, 500.0)
    meas[10] = 150_000.0
    with pytest.raises(m.MessageError) as err:
        m.decode_tof(NS(meas=meas), WHERE)
    problem = "150000 mm (150 m) is beyond any IRS reading (> 100000 mm = 100 m); expected millimetres"
    assert str(err.value) == f"robot.bag, field 'meas[10]': topic /TOF1, message 5: {problem}"
    assert err.value.topic == "/TOF1" and err.value.index == 4 and err.value.field == "meas[10]"
    csv = tmp_path / "TOF1.csv"
    csv.write_text("time," + ",".join(f"meas_{k}" for k in range(64)) + "\n1.0," + ",".join(f"{v:g}" for v in meas) + "\n")
    with pytest.raises(DataFormatError) as file_err:
        read_tof(csv)
    assert file_err.value.problem == problem and file_err.value.field == "meas_10"


def test_a_tof_message_in_metres_is_refused_as_a_tof_file_is(tmp_path):
    """Readings 0.3-3.9 (metres, not millimetres): no VL53L5CX reads below 20 mm, so a message whose
    eight or more target zones all read below 10 mm is refused naming its field, in the TOF file's
    words; fewer target zones (a stray reading) or readings from 20 mm up decode."""
    from virus_nerf.data.ethz import read_tof

    meas = np.linspace(0.3, 3.9, 64)
    meas[::2] = 0.0  # 32 zones with a target, the others the sensor's "no target"
    with pytest.raises(m.MessageError) as err:
        m.decode_tof(NS(meas=meas), WHERE)
    problem = "every reading is below 10 mm (the largest 3.9); expected millimetres (the {} holds metres?)"
    assert str(err.value) == f"robot.bag, field 'meas': topic /TOF1, message 5: {problem.format('message')}"
    csv = tmp_path / "TOF1.csv"
    csv.write_text("time," + ",".join(f"meas_{k}" for k in range(64)) + "\n1.0," + ",".join(f"{v:g}" for v in meas) + "\n")
    with pytest.raises(DataFormatError, match=re.escape(problem.format("file"))):
        read_tof(csv)
    few = np.zeros(64)
    few[:7] = 5.0  # seven stray readings: no evidence of the unit
    assert np.isnan(m.decode_tof(NS(meas=few), WHERE).grid_m()).all()  # 5 mm is below the 0.1 m floor: invalid
    near = np.full(64, 20.0)  # every zone at the sensor's nearest reading, in millimetres
    assert m.decode_tof(NS(meas=near), WHERE).meas_mm.tolist() == [20.0] * 64


def test_a_message_and_the_layouts_file_give_the_same_tof_and_uss_numbers(tmp_path):
    """What the importer writes from a message reads back (data/ethz.py) as the stream's values."""
    from virus_nerf.data import writer
    from virus_nerf.data.ethz import read_tof, read_uss
    from virus_nerf.sensors import uss

    rng = np.random.default_rng(4)
    meas = rng.integers(0, 4500, 64).astype(np.uint16)
    meas[:3] = (0, 50, 101)
    tof = m.decode_tof(NS(meas=meas, stds=np.full(64, 7, dtype=np.uint16)), WHERE)
    writer.write_tof(tmp_path / "TOF1.csv", np.array([1.0]), tof.meas_mm[None], tof.stds_mm[None])
    np.testing.assert_array_equal(read_tof(tmp_path / "TOF1.csv")[1][0], tof.grid_m())
    readings = [m.decode_uss(NS(meas=v), m.USS_TYPE, WHERE) for v in (3752, 50000, 0)]
    raw = np.array([r.echo_us for r in readings])
    writer.write_uss(tmp_path / "USS1.csv", np.arange(3.0), uss.range_from_raw(raw))
    np.testing.assert_array_equal(read_uss(tmp_path / "USS1.csv")[1], [r.range_m for r in readings])
    assert readings[0].range_m == pytest.approx(0.7504) and np.isnan(readings[1].range_m) and np.isnan(readings[2].range_m)


def test_depth_in_metres_follows_the_npy_maps_invalid_rule(tmp_path):
    """16UC1 [0, 1500, 65535] mm -> [NaN, 1.5, NaN] m, as a .npy depth map of the same values reads."""
    from virus_nerf.data import writer
    from virus_nerf.data.images import read_depth
    from virus_nerf.sensors.camera import Intrinsics

    mm = np.array([[0, 1500, 65535]], dtype="<u2")
    msg = NS(encoding="16UC1", height=1, width=3, step=6, is_bigendian=0, data=mm.view(np.uint8).reshape(-1))
    depth = m.decode_depth(msg, m.IMAGE, WHERE, size=(3, 1))
    assert depth.mm.dtype == np.uint16 and depth.mm.tolist() == [[0, 1500, 65535]]
    got = depth.metres()
    assert got.dtype == np.float32 and np.isnan(got[0, [0, 2]]).all() and got[0, 1] == pytest.approx(1.5)
    writer.write_depth(tmp_path / "img0.npy", depth.mm)
    np.testing.assert_array_equal(read_depth(tmp_path / "img0.npy", Intrinsics(2.0, 2.0, 1.5, 0.5, 3, 1)), got)
    with pytest.raises(m.MessageError, match=r"depth map is 3x1; the colour image is 4x1 \(expected depth aligned"):
        m.decode_depth(msg, m.IMAGE, WHERE, size=(4, 1))


def test_one_rule_from_metres_to_the_depth_maps_millimetres():
    """data/images.depth_to_mm, used by the frame store, the exports and depth messages: by hand,
    1.2344 m -> 1234 mm; 0.6 mm -> 1; 65.534 m -> 65534; NaN, inf, <= 0, under 0.5 mm and beyond
    65.534 m -> 0 (invalid); and back through depth_from_mm (1234 mm -> 1.234 m, 0 -> NaN)."""
    from virus_nerf.data.images import depth_from_mm, depth_to_mm
    from virus_nerf.sampler.frames import resize_depth_mm

    metres = np.array([1.2344, 0.0006, 65.534, np.nan, np.inf, -1.0, 0.0, 0.0004, 65.5346, 70.0])
    assert depth_to_mm(metres).tolist() == [1234, 1, 65534, 0, 0, 0, 0, 0, 0, 0]
    assert depth_from_mm(depth_to_mm(metres))[0] == pytest.approx(1.234) and np.isnan(depth_from_mm(depth_to_mm(metres))[3])
    assert resize_depth_mm(metres[None, :], (10, 1)).tolist() == [depth_to_mm(metres).tolist()]


def test_colour_size_and_camera_info_distortion():
    px = np.arange(6, dtype=np.uint8)
    msg = NS(encoding="rgb8", height=1, width=2, step=6, is_bigendian=0, data=px)
    assert m.decode_color(msg, m.IMAGE, WHERE, size=(2, 1)).tolist() == [[[0, 1, 2], [3, 4, 5]]]
    with pytest.raises(m.MessageError, match=r"topic /TOF1, message 5: image is 2x1; the camera info says 640x480"):
        m.decode_color(msg, m.IMAGE, WHERE, size=(640, 480))
    k = [386.0, 0, 320.0, 0, 387.0, 240.0, 0, 0, 1]
    info = m.decode_camera_info(NS(k=k, d=[0.1, 0, 0, 0, 0], width=640, height=480), WHERE)
    assert (info.intrinsics.fx, info.intrinsics.fy, info.intrinsics.cx, info.intrinsics.cy) == (386.0, 387.0, 320.0, 240.0)
    assert info.distorted and info.distortion == (0.1, 0.0, 0.0, 0.0, 0.0)
    assert not m.decode_camera_info(NS(K=k, D=[], width=640, height=480), WHERE).distorted  # ROS 1 names


def test_scan_is_range_filtered_at_the_layouts_float32():
    rec = np.zeros(3, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
    rec["x"] = [0.1, 2.000000001, 40.0]
    fields = [NS(name=n, offset=8 * i, datatype=8) for i, n in enumerate("xyz")]
    msg = NS(fields=fields, is_bigendian=False, width=3, height=1, point_step=24, data=rec.view(np.uint8).reshape(-1),
             header=_header(1, 0, "/rslidar"))
    pts = m.decode_scan(msg, WHERE, 0.3, 30.0)
    assert pts.dtype == np.float32 and pts.tolist() == [[2.0, 0.0, 0.0]]
    assert m.frame_id(msg) == "rslidar"


def _tf_entry(stamp: tuple[int, int], parent: str, child: str, xyz, q) -> NS:
    return NS(header=_header(*stamp, parent), child_frame_id=child,
              transform=NS(translation=NS(x=xyz[0], y=xyz[1], z=xyz[2]), rotation=NS(x=q[0], y=q[1], z=q[2], w=q[3])))


def test_tf_and_odometry_decode_to_poses_and_refuse_a_broken_quaternion():
    s = np.sin(np.pi / 4)
    msg = NS(transforms=[_tf_entry((2, 500_000_000), "/odom", "base_link", (1.0, 2.0, 0.5), (0, 0, s, s))])
    (tr,) = m.decode_tf(msg, WHERE, static=False)
    assert (tr.time_s, tr.parent, tr.child, tr.static) == (2.5, "odom", "base_link", False)
    np.testing.assert_allclose(tr.pose, [[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 0.5], [0, 0, 0, 1]], atol=1e-12)
    bad = NS(transforms=[msg.transforms[0], _tf_entry((2, 0), "odom", "x", (0, 0, 0), (0, 0, 0, 0))])
    with pytest.raises(m.MessageError, match=r"field 'transforms\[1\].transform'.*quaternion \[0.0, 0.0, 0.0, 0.0\] "
                                             r"is not finite or not of unit norm"):
        m.decode_tf(bad, WHERE, static=True)
    odom = NS(pose=NS(pose=NS(position=NS(x=3.0, y=0.0, z=0.0), orientation=NS(x=0.0, y=0.0, z=s, w=s))))
    np.testing.assert_allclose(m.decode_odometry(odom, WHERE)[:3, 3], [3, 0, 0])
    odom.pose.pose.orientation.w = 2.0
    with pytest.raises(m.MessageError, match=r"field 'pose.pose'.*not of unit norm"):
        m.decode_odometry(odom, WHERE)


def test_stamp_and_a_node_source_without_an_index():
    assert m.stamp_s(NS(header=_header(3, 250_000_000))) == 3.25 and m.stamp_s(NS()) == 0.0
    # a TFMessage has no header: it is stamped by its newest transform
    tf = NS(transforms=[NS(header=_header(7, 0)), NS(header=_header(5, 500_000_000))])
    assert m.stamp_s(tf) == 7.0 and m.stamp_s(NS(transforms=[])) == 0.0
    err = m.Where("ros2 node virus_nerf", "/TOF1").error("has 3 zones; expected 64 (8x8)", field="meas")
    assert str(err) == "ros2 node virus_nerf, field 'meas': topic /TOF1: has 3 zones; expected 64 (8x8)"


def test_the_streams_nearest_partner_is_the_importers():
    """live.Recent.nearest and sync.match_nearest: one rule, duplicate stamps and ties included."""
    from virus_nerf.data.bags.live import Recent
    from virus_nerf.data.bags.sync import match_nearest

    rng = np.random.default_rng(7)
    for _ in range(200):
        stamps = np.sort(rng.integers(0, 12, rng.integers(1, 7))) * 0.25  # quarter seconds: exact ties
        buf = Recent()
        for k, t in enumerate(stamps):
            buf.add(float(t), k)
        for t in np.arange(-0.5, 3.5, 0.125):
            k = int(match_nearest(np.array([t]), stamps, 0.3)[0])
            assert buf.nearest(float(t), 0.3) == (None if k < 0 else k), (stamps, t)


# ----------------------------------------------------------------- one bad message, both paths
def _tof_rewritten(tiny_office, folder: Path, change) -> tuple[Path, Path]:
    """The tiny office as a ROS 1 bag whose /TOF1 carries uint32 zones (a robot's own TOF
    definition), `change(n, meas)` applied to its n-th message (from 1); and its LiDAR poses as CSV."""
    pytest.importorskip("rosbags")
    from rosbags.rosbag1 import Reader, Writer
    from rosbags.typesys import get_types_from_msg

    from virus_nerf.data.bags.writer import write_bag
    from virus_nerf.data.ethz import load_recording
    from virus_nerf.data.writer import write_poses

    rec = load_recording(tiny_office, "office")
    write_poses(folder / "lidar.csv", *rec._lidar_pose_track)
    good = write_bag(tiny_office, folder / "good.bag", ros_version=1)
    wide = "sensors/msg/tof"  # matched to the ETHZ TOF case-insensitively; the bag's own definition is read
    store = m.make_typestore(1)
    store.register(get_types_from_msg("std_msgs/Header header\nuint32[] meas\nuint16[] stds\n", wide))
    n_tof = 0
    with Reader(good) as r, Writer(folder / "bad.bag") as w:
        conns = {}
        for c, t_ns, raw in r.messages():
            msg, msgtype = store.deserialize_ros1(raw, c.msgtype), c.msgtype
            if c.topic == "/TOF1":
                meas = np.asarray(msg.meas, dtype=np.uint32)
                n_tof += 1
                change(n_tof, meas)
                msg, msgtype = store.types[wide](header=msg.header, meas=meas, stds=msg.stds), wide
            if c.topic not in conns:
                conns[c.topic] = w.add_connection(c.topic, msgtype, typestore=store)
            w.write(conns[c.topic], t_ns, store.serialize_ros1(msg, msgtype))
    return folder / "bad.bag", folder / "lidar.csv"


@pytest.fixture(scope="module")
def tof_bag(tiny_office, tmp_path_factory) -> tuple[Path, Path]:
    """The 5th /TOF1 message with 150 m in zone 10."""

    def far(n: int, meas: np.ndarray) -> None:
        if n == 5:
            meas[10] = 150_000

    return _tof_rewritten(tiny_office, tmp_path_factory.mktemp("tof_bag"), far)


def _import_and_stream(bag: Path, poses: Path, out: Path):
    """import-bag's error and the stream's (at which message, and the frames before it)."""
    from virus_nerf.data.bags.importer import import_bag
    from virus_nerf.data.bags.live import LiveSync, StreamError
    from virus_nerf.data.bags.poses import make_pose_source
    from virus_nerf.data.bags.reader import BagReader
    from virus_nerf.data.bags.topics import default_topics

    with pytest.raises(DataFormatError) as imported:
        import_bag(bag, out, poses="csv", poses_file=poses)
    assert not out.exists()
    cfg = default_topics()
    frames, last = [], None
    with pytest.raises(StreamError) as streamed, BagReader(bag) as reader:
        sync = LiveSync(cfg, make_pose_source("csv", cfg, bag, present=lambda t: True, poses_file=poses), bag)
        for topic, msg in reader.iter_topics(sync.topics()):
            last = (topic, msg)
            frames += sync.push(topic, msg)
    assert str(streamed.value) == str(imported.value)
    return imported.value, streamed.value, last, frames, sync


def test_a_tof_topic_in_metres_is_refused_over_its_messages(tiny_office, tmp_path):
    """Three target zones a message, in metres (1, 2 and 3): no message alone holds the eight
    target readings `decode_tof` wants as evidence of the unit, the topic does by its third
    message (9 readings), where import-bag and the stream both stop, in the same line. Seen in a
    user's review: one message in 39 of an office held eight targets, so map-bag mapped 76 frames
    of metres first and import-bag wrote a recording the TOF file's reader refused."""

    def metres(n: int, meas: np.ndarray) -> None:
        meas[:] = 0
        meas[[3, 30, 60]] = (1, 2, 3)

    bag, poses = _tof_rewritten(tiny_office, tmp_path, metres)
    imported, streamed, last, _, _ = _import_and_stream(bag, poses, tmp_path / "rec")
    assert str(imported) == (f"{bag}, field 'meas': topic /TOF1, message 3: every reading of the topic up to here is "
                             "below 10 mm (9 readings, the largest 3); expected millimetres (the topic holds metres?)")
    assert last[0] == "/TOF1" and last[1].index == 2


def test_the_tof_unit_check_settles_on_millimetres_and_counts_each_topic_apart():
    """A reading of 10 mm or more settles a topic as millimetres (later small readings pass); the
    readings of two topics never add up; a message without targets counts nothing."""
    check = m.TofUnitCheck()
    small = np.zeros(64)
    small[:5] = 4.0  # five targets below 10 mm: under eight, no evidence alone
    tof1, tof3 = m.Where("b", "/TOF1", 0), m.Where("b", "/TOF3", 0)
    check.add(m.decode_tof(NS(meas=np.zeros(64)), tof1), tof1)
    check.add(m.decode_tof(NS(meas=small), tof1), tof1)
    check.add(m.decode_tof(NS(meas=small), tof3), tof3)  # 5 + 5, but apart
    settled = small.copy()
    settled[10] = 25.0
    check.add(m.decode_tof(NS(meas=settled), tof3), tof3)  # 10 readings, one of 25 mm: millimetres
    for _ in range(3):
        check.add(m.decode_tof(NS(meas=small), tof3), tof3)
    with pytest.raises(m.MessageError, match=r"\(10 readings, the largest 4\)"):
        check.add(m.decode_tof(NS(meas=small), tof1), tof1)


def test_import_bag_and_the_stream_refuse_a_150_m_tof_reading_alike(tof_bag, tmp_path):
    """The same bad ToF message: import-bag refuses it (before: imported, then refused by the TOF
    file's reader), the stream stops at it (before: mapped as a 150 m free ray), in the same line."""
    bag, poses = tof_bag
    imported, streamed, last, frames, sync = _import_and_stream(bag, poses, tmp_path / "rec")
    assert str(imported) == (f"{bag}, field 'meas[10]': topic /TOF1, message 5: 150000 mm (150 m) is beyond "
                             "any IRS reading (> 100000 mm = 100 m); expected millimetres")
    assert last[0] == "/TOF1" and last[1].index == 4  # stopped at that message, at its bag time
    assert streamed.at_s == sync.rel(last[1].time_s) > 0.5 and frames  # the frames before it reach the map
