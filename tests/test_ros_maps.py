"""The rosbag2 (MCAP) of maps and poses, read back with the independent `mcap` + `mcap_ros2`
reader (not rosbags, which wrote it): grids cell by cell against map_server's map.pgm, origin,
resolution, topics, counts, timestamps and the tf of hand-computed poses."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

pytest.importorskip("rosbags")
make_reader = pytest.importorskip("mcap.reader").make_reader
DecoderFactory = pytest.importorskip("mcap_ros2.decoder").DecoderFactory

from virus_nerf.errors import OutputExistsError, UsageError  # noqa: E402
from virus_nerf.mapping.ros_maps import RosMapBag, base_pose  # noqa: E402
from virus_nerf.maps.occupancy import FREE, OCCUPIED, UNKNOWN, OccupancyMap2D, write_map_server  # noqa: E402

RES, ORIGIN = 0.25, (-1.5, 2.0)


def _pattern_map() -> OccupancyMap2D:
    """A 5 x 7 trinary map whose rows and columns all differ, so a flip or a transpose shows."""
    img = np.full((5, 7), UNKNOWN, dtype=np.uint8)  # row 0 = largest y
    img[4, :] = FREE  # bottom row (smallest y) free
    img[:, 0] = OCCUPIED  # left column (smallest x) occupied
    img[0, 6] = OCCUPIED  # top-right corner
    img[2, 3] = FREE
    return OccupancyMap2D(img, RES, ORIGIN, "trinary")


def _prob_map() -> OccupancyMap2D:
    """Raw map, as Mapper.probability_map makes it: p = 0 .. 1 in 35 steps as round(100 p), and
    the top-left pixel (row 0 = largest y) unknown: no sensor looked there (255)."""
    p = np.linspace(0.0, 1.0, 35).reshape(5, 7)
    value = np.rint(100 * p).astype(np.uint8)
    value[0, 0] = 255
    return OccupancyMap2D(value, RES, ORIGIN, "raw")


def _read_pgm(path) -> np.ndarray:
    """A binary P5 PGM as written by write_map_server (header 'P5\\nW H\\n255\\n')."""
    raw = path.read_bytes()
    magic, size, maxval, body = raw.split(b"\n", 3)
    w, h = map(int, size.split())
    assert magic == b"P5" and maxval == b"255"
    return np.frombuffer(body, dtype=np.uint8).reshape(h, w)


def _upright_camera(position, yaw: float) -> np.ndarray:
    """An upright, level OpenCV camera at `position` looking along world yaw `yaw` (rad)."""
    fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([np.cross(down, fwd), down, fwd])  # camera x right, y down, z forward
    pose[:3, 3] = position
    return pose


def _messages(bag: RosMapBag) -> list[tuple[str, int, object]]:
    with open(bag.mcap_path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(ch.topic, msg.log_time, dec) for _, ch, msg, dec in reader.iter_decoded_messages()]


@pytest.fixture
def bag(tmp_path):
    """Two poses at 10.0 and 10.5 s, the maps at 11.25 s, the map alone again at 12 s."""
    with RosMapBag(tmp_path / "maps_bag") as b:
        b.write_pose(10.0, _upright_camera((1.0, 2.0, 0.5), math.pi / 2))
        b.write_pose(10.5, _upright_camera((1.5, 2.0, 0.5), 0.0))
        b.write_maps(11.25, _pattern_map(), _prob_map())
        b.write_maps(12.0, _pattern_map(), None)
    return b


def test_topics_counts_and_timestamps(bag):
    msgs = _messages(bag)
    assert [(t, ns) for t, ns, _ in msgs] == [
        ("/tf", 10_000_000_000), ("/tf", 10_500_000_000),
        ("/map", 11_250_000_000), ("/map_probability", 11_250_000_000), ("/map", 12_000_000_000)]
    assert bag.counts == {"/map": 2, "/map_probability": 1, "/tf": 2}
    with open(bag.mcap_path, "rb") as f:
        summary = make_reader(f).get_summary()
    schemas = {ch.topic: summary.schemas[ch.schema_id].name for ch in summary.channels.values()}
    assert schemas == {"/map": "nav_msgs/msg/OccupancyGrid", "/map_probability": "nav_msgs/msg/OccupancyGrid",
                       "/tf": "tf2_msgs/msg/TFMessage"}
    assert (bag.path / "metadata.yaml").is_file()
    # header stamps = bag time
    _, _, grid = msgs[2]
    assert (grid.header.stamp.sec, grid.header.stamp.nanosec) == (11, 250_000_000)
    assert grid.header.frame_id == "map"


def test_map_matches_map_server_pgm_cell_by_cell(bag, tmp_path):
    m = _pattern_map()
    pgm, _ = write_map_server(m, tmp_path, "map")
    image = _read_pgm(pgm)  # row 0 = largest y
    grid = next(dec for t, _, dec in _messages(bag) if t == "/map")
    info = grid.info
    assert (info.width, info.height) == (7, 5)
    assert info.resolution == pytest.approx(RES)
    assert (info.origin.position.x, info.origin.position.y, info.origin.position.z) == (ORIGIN[0], ORIGIN[1], 0.0)
    o = info.origin.orientation
    assert (o.x, o.y, o.z, o.w) == (0.0, 0.0, 0.0, 1.0)
    data = np.asarray(grid.data, dtype=np.int8).reshape(info.height, info.width)  # row 0 = smallest y
    expected = {OCCUPIED: 100, FREE: 0, UNKNOWN: -1}
    for r in range(5):
        for c in range(7):
            assert data[r, c] == expected[int(image[4 - r, c])], (r, c)
    # spot checks in world terms: the cell at the origin (lower-left) is the occupied left column,
    # the bottom row above it is free, the top-right cell occupied, (3, 2) free
    assert data[0, 0] == 100 and (data[0, 1:] == 0).all() and data[4, 6] == 100 and data[2, 3] == 0


def test_probability_map_is_round_100p_and_unknown_where_no_sensor_looked(bag):
    """/map_probability = round(100 p), -1 where no sensor looked (a costmap's unknown, where a
    50 would read as free): the values map_server's raw mode serves from the same prob.pgm."""
    grid = next(dec for t, _, dec in _messages(bag) if t == "/map_probability")
    data = np.flipud(np.asarray(grid.data, dtype=np.int8).reshape(5, 7))  # row 0 = largest y, as the image
    want = np.rint(100 * np.linspace(0.0, 1.0, 35).reshape(5, 7)).astype(np.int8)
    want[0, 0] = -1
    np.testing.assert_array_equal(data, want)
    assert data[0, 1] == 3 and data[4, 6] == 100  # p = 1/34 -> 2.94 %, p = 1


def test_a_probability_preview_is_dark_where_occupied_and_grey_where_unknown():
    from virus_nerf.maps.occupancy import preview

    m = OccupancyMap2D(np.array([[0, 50, 100, 255]], dtype=np.uint8), RES, ORIGIN, "raw")
    assert preview(m).tolist() == [[255, 128, 0, 128]]  # 255 (1 - p); unknown mid grey


def test_tf_of_hand_computed_poses(bag):
    tfs = [dec.transforms for t, _, dec in _messages(bag) if t == "/tf"]
    assert [len(t) for t in tfs] == [1, 1]
    a, b = tfs[0][0], tfs[1][0]
    assert (a.header.frame_id, a.child_frame_id) == ("map", "base_link")
    assert (a.header.stamp.sec, a.header.stamp.nanosec) == (10, 0)
    # camera at (1, 2, 0.5) looking along world +y: base_link yaw +90 deg about z
    tr = a.transform.translation
    assert (tr.x, tr.y, tr.z) == pytest.approx((1.0, 2.0, 0.5))
    q = a.transform.rotation
    s = math.sqrt(0.5)
    assert (q.x, q.y, q.z, q.w) == pytest.approx((0.0, 0.0, s, s), abs=1e-12)
    # looking along world +x: identity rotation
    q = b.transform.rotation
    assert (b.transform.translation.x, q.x, q.y, q.z, q.w) == pytest.approx((1.5, 0, 0, 0, 1), abs=1e-12)


def test_base_pose_levels_pitched_and_upside_down_cameras():
    """The real rig's cameras are upside down and pitched ~5 deg (sensors/rig.py): base_link keeps
    z up, x along the optical axis' heading, at the camera's position."""
    yaw = math.radians(30)
    cam = _upright_camera((0.2, -0.3, 0.6), yaw)
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])  # roll 180 deg about the optical axis: upside down
    pitch = np.eye(4)
    c, s = math.cos(math.radians(5)), math.sin(math.radians(5))
    pitch[1:3, 1:3] = [[c, -s], [s, c]]  # about camera x
    for pose in (cam, cam @ flip, cam @ pitch, cam @ flip @ pitch):
        base = base_pose(pose)
        np.testing.assert_allclose(base[:3, 2], (0, 0, 1), atol=1e-12)
        np.testing.assert_allclose(base[:3, 0], (math.cos(yaw), math.sin(yaw), 0), atol=1e-12)
        np.testing.assert_allclose(base[:3, 3], (0.2, -0.3, 0.6))
    # with the camera's mount the full pose: base = cam @ inv(mount)
    mount = _upright_camera((0.3, 0.1, -0.1), 0.0)
    np.testing.assert_allclose(base_pose(cam, mount) @ mount, cam, atol=1e-12)


def test_base_link_follows_one_camera_without_mounts_and_both_with_them(tmp_path):
    """The rig's two stacks 0.28 m apart, looking 15 deg to either side: without their mounts
    base_link is the first stack's levelled camera alone (taken in turn, the two would make it jump
    between them at the camera rate); with both mounts both frames give the same body pose."""
    yaw = math.radians(15)
    body = np.eye(4)
    body[:3, 3] = (2.0, 1.0, 0.0)  # the robot at (2, 1), heading along world x
    mounts = {1: _upright_camera((0.35, -0.14, 0.57), -yaw), 3: _upright_camera((0.35, 0.14, 0.57), yaw)}
    cams = {s: body @ m for s, m in mounts.items()}  # camera-to-world = body @ camera-to-body
    with RosMapBag(tmp_path / "levelled") as b:
        written = [b.write_pose(0.1 * k, cams[s], stack_id=s) for k, s in enumerate((1, 3, 1, 3))]
    assert [w is None for w in written] == [False, True, False, True] and b.counts["/tf"] == 2
    tfs = [dec.transforms[0].transform.translation for t, _, dec in _messages(b) if t == "/tf"]
    assert [(round(v.x, 9), round(v.y, 9)) for v in tfs] == [(2.35, 0.86), (2.35, 0.86)]  # stack 1's camera
    with RosMapBag(tmp_path / "mounted", camera_in_base=mounts) as b:
        written = [b.write_pose(0.1 * k, cams[s], stack_id=s) for k, s in enumerate((1, 3, 1, 3))]
    assert b.counts["/tf"] == 4
    for pose in written:
        np.testing.assert_allclose(pose, body, atol=1e-12)


def test_mount_per_stack_and_refusals(tmp_path):
    mount = _upright_camera((0.3, 0.0, 0.0), 0.0)  # camera 0.3 m ahead of base_link, looking forward
    with RosMapBag(tmp_path / "b", camera_in_base={3: mount}) as b:
        pose = b.write_pose(0.0, _upright_camera((1.3, 0.0, 0.0), 0.0), stack_id=3)
        np.testing.assert_allclose(pose, [[1, 0, 0, 1.0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], atol=1e-12)
        with pytest.raises(UsageError, match="time_s"):
            b.write_pose(-1.0, np.eye(4))
    with pytest.raises(OutputExistsError):
        RosMapBag(tmp_path / "b")
    with pytest.raises(UsageError, match="distro"):
        RosMapBag(tmp_path / "c", distro="noetic")
    with pytest.raises(UsageError, match="already closed"):
        b.write_maps(1.0, _pattern_map())


def test_frames_are_named_by_the_caller_and_checked(tmp_path):
    """map_frame names the maps' frame and the /tf parent, base_frame the /tf child; a name tf2
    refuses (leading '/', spaces, empty) or the same name twice is refused before the bag is made."""
    with RosMapBag(tmp_path / "odom_bag", map_frame="odom", base_frame="robot") as b:
        b.write_pose(1.0, _upright_camera((1.0, 2.0, 0.5), 0.0))
        b.write_maps(1.5, _pattern_map(), _prob_map())
    msgs = _messages(b)
    tf = next(dec for t, _, dec in msgs if t == "/tf").transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("odom", "robot")
    assert [dec.header.frame_id for t, _, dec in msgs if t != "/tf"] == ["odom", "odom"]
    for kwargs, message in (({"map_frame": "/map"}, "map_frame '/map': not a tf2 frame id"),
                            ({"base_frame": "base link"}, "base_frame 'base link': not a tf2 frame id"),
                            ({"map_frame": ""}, "map_frame '': not a tf2 frame id"),
                            ({"map_frame": "odom", "base_frame": "odom"},
                             "map_frame and base_frame are both 'odom': a transform needs two frames")):
        with pytest.raises(UsageError, match=re.escape(message)):
            RosMapBag(tmp_path / "refused", **kwargs)
        assert not (tmp_path / "refused").exists()
