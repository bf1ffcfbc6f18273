"""The live ROS 2 node over DDS on the loopback interface only (no multicast, nothing leaves the
machine): `ros2-play` publishes a simulated office bag, `virus-nerf ros2` maps it, and a reader
that joins late gets `/map` and decodes it (issue 40). Every participant stops by itself."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cyclonedds")
pytest.importorskip("rosbags")

from helpers import run_cli  # noqa: E402

from virus_nerf.ros2 import dds, types  # noqa: E402

GRID = "nav_msgs/msg/OccupancyGrid"


def _domain() -> int:
    """A domain of this test process alone: the test run's pid picks a block of 16 domains, the
    pytest-xdist worker (gw0, gw1, ...) its own in the block, so two workers never meet."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    run_pid = os.getppid() if worker else os.getpid()  # xdist's workers are children of the run
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    return 150 + (run_pid % 5) * 16 + index % 16  # 150-229: valid ROS 2 domain ids


@pytest.fixture(scope="module")
def office_bag(tiny_office, tmp_path_factory) -> Path:
    from virus_nerf.data.bags.writer import write_bag

    return write_bag(tiny_office, tmp_path_factory.mktemp("ros2") / "drive_tf", ros_version=2, tf=True)


def _node(out: Path, domain: int, *extra: str) -> subprocess.Popen:
    argv = ["ros2", "--out", str(out), "--tf-child", "rslidar", "--localhost-only", "--domain-id", str(domain),
            "--publish-every", "1", "--n-rays", "90", "--max-poses", "5", *extra]
    return subprocess.Popen([sys.executable, "-c", "from virus_nerf.cli import main; main()", *argv],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(proc: subprocess.Popen, text: str, timeout_s: float = 60.0) -> list[str]:
    """Lines of the node's stdout up to (and with) the first that contains `text`."""
    lines, start = [], time.monotonic()
    while time.monotonic() - start < timeout_s:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line.rstrip())
        if text in line:
            return lines
    raise AssertionError(f"no {text!r} from the node: {lines} {proc.stderr.read() if proc.poll() is not None else ''}")


def _grid_values(path: Path) -> np.ndarray:
    """OccupancyGrid.data of a map.pgm (mapping/ros_maps.py grid_data: the bag's and the node's)."""
    from PIL import Image

    from virus_nerf.mapping.ros_maps import grid_data
    from virus_nerf.maps.occupancy import OccupancyMap2D

    return grid_data(OccupancyMap2D(np.asarray(Image.open(path)), 0.05, (0.0, 0.0)))


def test_play_map_and_a_late_reader_get_the_map_over_loopback_dds(office_bag, tiny_office, tmp_path):
    domain, out = _domain(), tmp_path / "node"
    node = _node(out, domain, "--exit-when-idle", "4")  # the default config: the map a user gets
    try:
        up = _wait_for(node, "node up on ROS 2 domain")
        assert f"domain {domain} (jazzy, localhost only)" in up[-1]
        player = dds.Participant("jazzy", domain, loopback=True)
        try:
            from virus_nerf.ros2.play import play

            report = play(office_bag, player, delay_s=1.5, log=lambda line: None)
        finally:
            player.close()
        assert report.messages > 100 and report.topics == 13
        # a reader that joins after the drive: /map is latched (reliable, transient local, depth 1)
        reader = dds.Participant("jazzy", domain, loopback=True)
        try:
            sub = reader.reader("/map", GRID, dds.LATCHED)
            graph = reader.reader(dds.DISCOVERY_TOPIC, dds.ENTITIES_INFO, dds.LATCHED)  # `ros2 node list`'s source
            t0, got, first_s = time.monotonic(), [], None
            while time.monotonic() - t0 < 60:  # until the node ends (its final map is the last one)
                ended = node.poll() is not None
                got += sub.take()
                if got and first_s is None:
                    first_s = time.monotonic() - t0
                    publishers = reader.discover()  # the node's writers, while it is on the graph
                    qos = str(reader.offered.get("/map"))
                    time.sleep(0.5)  # the graph info is latched too
                    nodes = [types.deserialize(s.payload, dds.ENTITIES_INFO, types.typestore("jazzy"))
                             for s in graph.take()]
                    map_writers = set(reader.discover().get("/map") and reader.writer_gids["/map"])
                if ended:
                    break
                time.sleep(0.05)
        finally:
            reader.close()
        stdout, stderr = node.communicate(timeout=60)
    finally:
        if node.poll() is None:
            node.kill()
    assert node.returncode == 0, stderr
    assert got and first_s < 5.0, "the late reader got no /map (the latched one at once)"
    assert publishers.get("/map") == {GRID}  # topic rt/map, type nav_msgs::msg::dds_::OccupancyGrid_
    assert "TransientLocal" in qos and "Reliable" in qos and "KeepLast(depth=1)" in qos, qos
    # the node is on the ROS graph as /virus_nerf, its /map writer among its writers (rmw's GIDs)
    named = [n for info in nodes for n in info.node_entities_info_seq if n.node_name == "virus_nerf"]
    assert len(named) == 1 and named[0].node_namespace == "/", nodes
    gids = {bytes(np.asarray(g.data, dtype=np.uint8)) for g in named[0].writer_gid_seq}
    assert map_writers and map_writers <= gids and len(named[0].reader_gid_seq) >= 10
    store = types.typestore("jazzy")
    msg = types.deserialize(got[-1].payload, GRID, store)
    data = np.asarray(msg.data)
    assert msg.header.frame_id == "odom" and abs(msg.info.resolution - 0.05) < 1e-6
    assert data.size == msg.info.width * msg.info.height
    # the newest map received is the node's final map, cell for cell
    np.testing.assert_array_equal(data, _grid_values(out / "map" / "map.pgm"))
    report = json.loads((out / "stream.json").read_text())
    assert report["frames"] >= 10 and report["stopped"] is None  # of ~30 (late images dropped on a busy machine)
    # free where the robot drove, occupied near the room's surfaces at camera height
    from virus_nerf.data.ethz import load_recording

    rec = load_recording(tiny_office, sorted(p.name for p in tiny_office.iterdir() if (p / "measurements").is_dir())[0])
    grid = data.reshape(msg.info.height, msg.info.width)
    origin = np.array([msg.info.origin.position.x, msg.info.origin.position.y])

    def cells(xy):
        ij = np.floor((xy - origin) / msg.info.resolution).astype(int)
        ok = (ij >= 0).all(1) & (ij[:, 0] < msg.info.width) & (ij[:, 1] < msg.info.height)
        return grid[ij[ok, 1], ij[ok, 0]]

    path = np.concatenate([st.cam_to_world[:, :2, 3] for st in rec.stacks.values()])
    on_path = cells(path)
    # never occupied: a pixel where a camera of the node's frames stood is free where a sensor looked
    # (D92), whatever a half-trained field's scans say. A busy machine drops frames (late), and the
    # positions of dropped frames are not the node's: measured on 2 cores shared with other jobs, 2-5
    # of the 30 positions then lay in pixels the half-trained scans marked occupied; so only a node
    # that kept every frame must have none. Free on most of it: the drive's first positions lie
    # behind every frame's view (forward cameras, D36) and stay unknown, 3 of 15 a stack offline and
    # more when a busy machine drops the first frames
    shown = (np.unique(on_path, return_counts=True), report["dropped"])
    assert (on_path == 100).mean() <= (0.0 if not report["dropped"] else 0.2), shown
    assert (on_path == 0).mean() >= 0.5, shown
    height = float(np.mean([st.cam_to_world[:, 2, 3].mean() for st in rec.stacks.values()]))
    walls = rec.lidar_map()
    walls = walls[np.abs(walls[:, 2] - height) < 0.35][:, :2]  # the planner map's obstacle band (maps/planner.py)
    from scipy.spatial import cKDTree

    def to_walls(value):  # (N,) metres from each cell of `value` to the nearest surface point
        xy = np.argwhere(grid == value)[:, ::-1] * msg.info.resolution + origin + msg.info.resolution / 2
        return cKDTree(walls).query(xy)[0]

    # a 3 s drive trains for seconds, so only this holds of a trained map whatever the machine: its
    # obstacles lie nearer the room's surfaces than its free space does (medians measured: 0.24-0.40
    # m against 0.74-1.03 m unloaded, 44 steps; 0.78 against 1.03 m with a training beside it). On 2
    # cores shared with two busy processes (another test worker) the node trains 7 steps on 11 of
    # the 30 frames (19 late): a haze, 1.45 against 1.33 m. That is the machine, not the node
    occupied, free = to_walls(100), to_walls(0)
    if report["steps"] >= 20:
        assert len(occupied) > 10 and len(free) > 500 and np.median(occupied) < np.median(free), \
            (np.median(occupied), np.median(free), report["steps"])
    assert "ros2: subscribed to /tf_static (tf2_msgs/msg/TFMessage)" in stdout
    assert f"maps published on /map; final map in {out / 'map'}" in stdout


def test_the_node_stopped_by_sigterm_keeps_its_final_map_in_one_line(office_bag, tiny_office, tmp_path):
    """Issue 39: `systemctl stop` / `docker stop` (SIGTERM) while the node maps: the final map and
    stream.json on disk, one line saying where, exit 143, no traceback. The input runs at twice the
    wall clock's rate (`ros2-play --rate 2`): the lag stays the robot's."""
    import signal

    domain, out = _domain(), tmp_path / "node"
    node = _node(out, domain)  # runs until stopped
    try:
        _wait_for(node, "node up on ROS 2 domain")
        player = dds.Participant("jazzy", domain, loopback=True)
        try:
            from virus_nerf.ros2.play import play

            play(office_bag, player, rate=2.0, delay_s=1.5, log=lambda line: None)  # the robot's clock runs fast
        finally:
            player.close()
        start = time.monotonic()
        while not list((out / "snapshots").glob("[0-9]*")) and time.monotonic() - start < 60:
            time.sleep(0.2)  # a first map, so there is one to keep
        node.send_signal(signal.SIGTERM)
        stdout, stderr = node.communicate(timeout=60)
    finally:
        if node.poll() is None:
            node.kill()
    assert node.returncode == 143 and "Traceback" not in stderr, stderr
    last = stdout.splitlines()[-1]
    assert last.startswith("ros2: stopped by SIGTERM; ") and f"final map in {out / 'map'}" in last, last
    assert (out / "map" / "map.pgm").is_file() and (out / "map" / "map.yaml").is_file()
    report = json.loads((out / "stream.json").read_text())
    assert report["stopped"] == "interrupted (SIGTERM)" and report["final"] == "map"
    # the lag is the robot's clock's, whatever its rate: never ahead of the newest message
    assert report["lag_s"] and min(report["lag_s"]) >= 0.0, report["lag_s"]


@pytest.mark.skipif(not hasattr(__import__("signal"), "SIGSTOP"), reason="needs SIGSTOP (POSIX)")
def test_a_stop_while_a_hung_reader_holds_the_final_map_keeps_the_summary(office_bag, tmp_path):
    """The node's last act waits for its /map readers (2 s per topic); SIGTERM then (a hung reader:
    SIGSTOP here) ends the wait with one line after the run's summary, exit 143 (a review: the
    summary was lost and the CLI said only "interrupted"; a stop landing just before or after the
    wait is said alike)."""
    import signal

    domain, out = _domain(), tmp_path / "node"
    script = (f"import time\nfrom virus_nerf.ros2 import dds\np = dds.Participant('jazzy', {domain}, loopback=True)\n"
              f"r = p.reader('/map', {GRID!r}, dds.LATCHED)\nt0 = time.monotonic()\n"
              "while not r.take() and time.monotonic() - t0 < 90:\n    time.sleep(0.02)\n"
              "print('got', flush=True)\ntime.sleep(90)\n")
    node = _node(out, domain, "--exit-when-idle", "3")
    reader = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        _wait_for(node, "node up on ROS 2 domain")
        player = dds.Participant("jazzy", domain, loopback=True)
        try:
            from virus_nerf.ros2.play import play

            play(office_bag, player, rate=1.0, delay_s=1.5, log=lambda line: None)
        finally:
            player.close()
        assert reader.stdout.readline().strip() == "got"  # a first map reached it
        os.kill(reader.pid, signal.SIGSTOP)  # matched, and no longer acknowledging
        lines = _wait_for(node, "maps published on /map")  # the run's summary: the node now waits for readers
        node.send_signal(signal.SIGTERM)
        stdout, stderr = node.communicate(timeout=60)
    finally:
        for proc in (node, reader):
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=30)
    assert node.returncode == 143 and "Traceback" not in stderr and "interrupted" not in stderr, stderr
    assert "final map in" in lines[-1] and (out / "map" / "map.pgm").is_file()
    assert stdout.splitlines() == ["ros2: stopped by SIGTERM while leaving the ROS 2 graph; the final map was "
                                   "published, a reader that had not taken it yet gets none"], stdout
    assert json.loads((out / "stream.json").read_text())["stopped"] is None  # the drive itself ended (idle)


def test_another_node_publishing_the_nodes_map_is_said_once():
    """Two mapping nodes on one domain (a review: both published /map unwarned, and a planner
    reads both maps on one topic): the node says once that another writer of its topic is on the
    graph, over real DDS on the loopback interface."""
    from virus_nerf.ros2.node import LiveMessages

    domain, lines = _domain(), []
    other, node = dds.Participant("jazzy", domain, loopback=True), dds.Participant("jazzy", domain, loopback=True)
    try:
        other.writer("/map", GRID, dds.LATCHED)
        messages = LiveMessages(node, {}, log=lines.append, published=("/map", "/map_probability"))
        start = time.monotonic()
        while not lines and time.monotonic() - start < 20:
            messages.discover()
            time.sleep(0.1)
        for _ in range(3):
            messages.discover()  # said once, not at every discovery
    finally:
        other.close()
        node.close()
    assert lines == ["ros2: warning: another node also publishes /map (nav_msgs/msg/OccupancyGrid): its readers get "
                     "both nodes' maps; give this node another topic (--map-topic, --probability-topic, --namespace) "
                     "or --domain-id"]


def test_ros2_flags_are_refused_in_one_line(tmp_path):
    code, _, err = run_cli(["ros2", "--out", tmp_path / "o"])
    assert code == 2 and "--poses tf needs --tf-child FRAME" in err and "Traceback" not in err
    code, _, err = run_cli(["ros2", "--out", tmp_path / "o", "--tf-child", "x", "--distro", "iron"])
    assert code == 2 and "iron" in err and "humble" in err and len(err.strip().splitlines()) == 1
    code, _, err = run_cli(["ros2-play", tmp_path / "none.bag"])
    assert code == 2 and "no such file" in err
    code, _, err = run_cli(["ros2", "--out", tmp_path / "o", "--tf-child", "x", "--keep-snapshots", "0"])
    assert code == 2 and "--keep-snapshots 0" in err and len(err.strip().splitlines()) == 1
    os.environ["ROS_DOMAIN_ID"], old = "999", os.environ.get("ROS_DOMAIN_ID")
    try:
        code, _, err = run_cli(["ros2", "--out", tmp_path / "o", "--tf-child", "x"])
    finally:
        os.environ.pop("ROS_DOMAIN_ID") if old is None else os.environ.__setitem__("ROS_DOMAIN_ID", old)
    assert code == 2 and "domain id 999" in err
    assert not (tmp_path / "o").exists()


def test_a_sample_arrives_at_its_source_time_when_that_is_the_same_clock():
    """A sample that waited 3 s in the queue while the mapper was busy counts 3 s late (the stream
    then drops a colour image beyond --max-lag); a source clock that is not ours is not trusted."""
    assert dds.arrival(1000.0, 997.0) == 997.0
    assert dds.arrival(1000.0, 1000.0) == 1000.0
    assert dds.arrival(1000.0, 1000.5) == 1000.0  # the writer's clock ahead of ours: another clock
    assert dds.arrival(1000.0, 1000.0 - dds.MAX_QUEUED_S - 1) == 1000.0  # far behind: another clock


def test_names_resolve_as_ros_2_resolves_them():
    assert dds.resolve("map", "/") == "/map"
    assert dds.resolve("map", "/robot1") == "/robot1/map"
    assert dds.resolve("/map", "/robot1") == "/map"
    assert dds.resolve("~/map", "/robot1", "virus_nerf") == "/robot1/virus_nerf/map"  # the node's private name
    assert dds.resolve("~", "/", "virus_nerf") == "/virus_nerf"
    assert dds.dds_topic("/robot1/map") == "rt/robot1/map"
    assert dds.is_tf_static("/tf_static") and dds.is_tf_static("/robot1/tf_static") and not dds.is_tf_static("/tf")
    assert types.dds_type_name(GRID) == "nav_msgs::msg::dds_::OccupancyGrid_"
    # ROS 2's rules for a fully qualified name (rmw's validate_full_topic_name)
    for good in ("/map", "/robot_1/map", "/a/B9_c"):
        assert dds.name_problem(good) is None
    assert dds.name_problem("/", "namespace") is None and dds.name_problem("/") == "expected a name after '/'"
    assert dds.name_problem("map") == "expected a name starting with '/'"
    assert dds.name_problem("/a//b") == "expected no repeated '/'"
    assert dds.name_problem("/a/") == "expected no '/' at the end"
    assert dds.name_problem("/robot1/2d_map") == "token '2d_map' starts with a digit"
    assert dds.name_problem("/bad topic!") == "' !' is not allowed: expected letters, digits, '_' and '/'"
    assert dds.name_problem("/a" * 124) == "expected at most 247 characters"


def test_ros_names_and_frames_are_refused_before_anything_is_made(tmp_path):
    """What rmw or tf2 would refuse later (a DDS error, a frame RViz drops) is one line now, naming
    the flag; an input topic is absolute, as the topics file's."""
    for argv, says in (
            (["--map-topic", "bad topic!"], "--map-topic 'bad topic!' ('/bad topic!'): not a ROS 2 topic name; ' !' is not"),
            (["--namespace", "robot 1"], "--namespace 'robot 1' ('/robot 1'): not a ROS 2 namespace name"),
            (["--map-topic", ""], "--map-topic '': expected a topic name, e.g. map"),
            (["--probability-topic", "2d"], "--probability-topic '2d' ('/2d'): not a ROS 2 topic name; token '2d'"),
            (["--map-frame", ""], "--map-frame '': not a tf2 frame id"),
            (["--tf-parent", "/odom"], "--tf-parent '/odom': not a tf2 frame id"),
            (["--poses", "odometry", "--odometry-topic", "odom"],
             "--odometry-topic 'odom': not a ROS 2 topic name; expected a name starting with '/'")):
        code, _, err = run_cli(["ros2", "--out", tmp_path / "o", "--tf-child", "rslidar", *argv])
        assert code == 2 and says in err and len(err.strip().splitlines()) == 1, (argv, err)
    assert not (tmp_path / "o").exists()
    code, _, err = run_cli(["ros2-play", tmp_path / "drive.bag", "--topic"])
    assert code == 2 and "--topic: expected one or more topic names" in err and "Traceback" not in err


def test_a_topics_file_is_checked_as_ros_2_names_and_its_notes_are_said(tmp_path):
    """A topic in the topics file that no ROS 2 publisher can have ('/a b') is one line naming the
    file and key, not a node waiting in silence; a folder given as --topics is called a folder; a
    file without [stacks] says the ETHZ robot's topics are waited for. Nothing is made."""
    bad = tmp_path / "robot.toml"
    bad.write_text('[stacks.1]\ncolor = "/a b"\ncamera_in_lidar = { translation = [0, 0, 0], rotation_xyzw = [0, 0, 0, 1] }\n')
    code, _, err = run_cli(["ros2", "--out", tmp_path / "o", "--tf-child", "rslidar", "--topics", bad])
    assert code == 2 and err == (f"virus-nerf: error: {bad}, key 'stacks.1.color': '/a b': not a ROS 2 topic name; "
                                 "' ' is not allowed: expected letters, digits, '_' and '/'\n")
    code, _, err = run_cli(["ros2", "--out", tmp_path / "o", "--tf-child", "rslidar", "--topics", tmp_path])
    assert code == 2 and f"--topics {tmp_path}: a folder; expected the importer's topic mapping file" in err
    assert not (tmp_path / "o").exists()
    from virus_nerf.data.bags.topics import read_topics
    from virus_nerf.ros2.command import require_topic_names

    empty = tmp_path / "empty.toml"
    empty.write_text("")
    tcfg = read_topics(empty)
    require_topic_names(tcfg)  # the ETHZ topics are ROS 2 names
    from virus_nerf.errors import UsageError
    from virus_nerf.ros2.command import run_node

    lines = []
    with pytest.raises(UsageError, match="domain id 300: expected 0-232"):  # the note comes before the graph is joined
        run_node(tmp_path / "n", empty, "tf", "odom", "rslidar", "/odom", None, distro="jazzy", domain=300,
                 loopback=True, names={}, map_frame="odom", namespace="/", publish_every=1.0, first_map=1.0,
                 drive=1.0, max_lag=1.0, max_silence=1.0, maps=None, sinks=None, duration=None,
                 exit_when_idle=None, log=lines.append)
    assert lines[0].startswith(f"ros2: note: {empty}: no [stacks] section: the ETHZ robot's stacks 1 and 3 are used")


def test_ros2_play_offers_a_latched_map_latched(tmp_path):
    """ros2-play offers each topic as the bag recorded it (`ros2 bag play`): map-bag --out-bag's
    /map was offered reliable and transient local, depth 1, so a reader asking for that (RViz's Map
    display set to Transient Local, nav2's static layer, map_saver) gets it; /tf as recorded
    (reliable, volatile, 100); a bag without recorded QoS keeps the defaults."""
    import threading

    from virus_nerf.data.bags.reader import BagReader, RecordedQos
    from virus_nerf.mapping.ros_maps import RosMapBag
    from virus_nerf.maps.occupancy import OccupancyMap2D
    from virus_nerf.ros2.play import play, play_qos

    grid = OccupancyMap2D(np.full((4, 5), 254, np.uint8), 0.05, (0.0, 0.0))
    with RosMapBag(tmp_path / "maps") as bag:
        pose = np.eye(4)
        pose[:3, :3] = [[0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0]]
        bag.write_pose(1.0, pose)
        bag.write_maps(1.0, grid, None)
    with BagReader(tmp_path / "maps") as reader:
        assert reader.recorded_qos("/map") == RecordedQos(reliable=True, transient_local=True, depth=1)
        assert reader.recorded_qos("/tf") == RecordedQos(reliable=True, transient_local=False, depth=100)
    assert play_qos("/map", RecordedQos(True, True, 1)) == dds.LATCHED
    assert play_qos("/tf_static", None) == dds.STATIC and play_qos("/x", None) == dds.RELIABLE
    domain = _domain()
    listener = dds.Participant("jazzy", domain, loopback=True)
    player = dds.Participant("jazzy", domain, loopback=True)
    try:
        reader = listener.reader("/map", GRID, dds.LATCHED)
        done = threading.Thread(target=play, args=(tmp_path / "maps", player), kwargs={"log": lambda _: None})
        done.start()
        t0, got = time.monotonic(), []
        while not got and time.monotonic() - t0 < 20:
            got = reader.take()
            time.sleep(0.05)
        done.join(timeout=30)
        assert len(got) == 1
        msg = types.deserialize(got[0].payload, GRID, types.typestore("jazzy"))
        assert (msg.info.width, msg.info.height) == (5, 4) and msg.header.stamp.sec == 1
    finally:
        listener.close()
        player.close()


def _play_reading_clock(bag: Path, **play_args) -> tuple[dict, np.ndarray]:
    """ros2.play.play(bag, **play_args) on a loopback domain while a best-effort reader takes
    /clock: ({"r": the PlayReport}, the times it read (s))."""
    import threading

    from virus_nerf.ros2.play import CLOCK_TOPIC, CLOCK_TYPE, play

    play_args.setdefault("log", lambda _: None)
    play_args.setdefault("delay_s", 0.3)
    domain = _domain()
    listener, player = dds.Participant("jazzy", domain, loopback=True), dds.Participant("jazzy", domain, loopback=True)
    report, got = {}, []
    try:
        reader = listener.reader(CLOCK_TOPIC, CLOCK_TYPE, dds.QosKind(reliable=False, transient_local=False, depth=1000))
        done = threading.Thread(target=lambda: report.update(r=play(bag, player, **play_args)))
        done.start()
        while done.is_alive():
            got += reader.take()
            time.sleep(0.05)
        done.join()
        got += reader.take()
    finally:
        listener.close()
        player.close()
    store = types.typestore("jazzy")
    msgs = (types.deserialize(s.payload, CLOCK_TYPE, store) for s in got)
    return report, np.array([m.clock.sec + m.clock.nanosec * 1e-9 for m in msgs])


def test_ros2_play_publishes_the_bags_time_on_clock_and_loops(office_bag):
    """`ros2-play --clock 20 --rate 2` (as `ros2 bag play --clock`): /clock carries the bag's time,
    from its first message's receive time, rising 2 bag seconds a wall second: 20 ticks a second
    are 0.1 s of bag time apart, each within the bag's span (the last may be a sleep's overshoot
    past the last message's time). Played twice (`loops`, as --loop until stopped): every message
    twice, and the clock goes back to the bag's start once."""
    from virus_nerf.data.bags.reader import BagReader

    with BagReader(office_bag) as bag:
        received = [m.received_s if m.received_s is not None else m.time_s for _, m in bag.iter_topics(list(bag.topics))]
    report, clocks = _play_reading_clock(office_bag, rate=2.0, clock_hz=20.0, loops=2)
    assert report["r"].passes == 2 and report["r"].messages == 2 * len(received)
    back = np.flatnonzero(np.diff(clocks) <= 0)
    assert len(back) == 1  # the second pass
    for part in (clocks[:back[0] + 1], clocks[back[0] + 1:]):
        assert len(part) >= 0.5 * (received[-1] - received[0]) / 2.0 * 20
        assert np.all(np.diff(part) > 0)
        assert received[0] - 1e-6 <= part[0] <= received[0] + 0.3 and part[-1] <= received[-1] + 0.2
        assert np.median(np.diff(part)) == pytest.approx(0.1, rel=0.15)
    assert report["r"].clock_ticks >= len(clocks)


def test_ros2_play_clock_leaves_out_the_bags_own_clock(tmp_path):
    """A simulator's bag records /clock (1000.0 s on) beside its data (receive times 50-51 s): with
    --clock the bag's /clock is not played (rosbag2 does the same), so /clock carries one time,
    the bag's (50-51 s), never 1000 s."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    from virus_nerf.ros2.play import CLOCK_TOPIC, CLOCK_TYPE

    store = get_typestore(Stores.ROS2_JAZZY)
    stamp = store.types["builtin_interfaces/msg/Time"]
    with Writer(tmp_path / "sim_bag", version=Writer.VERSION_LATEST) as w:
        clock, chatter = w.add_connection(CLOCK_TOPIC, CLOCK_TYPE, typestore=store), \
            w.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        for k in range(11):  # 50.0 ... 51.0 s received, the simulator's clock at 1000.0 ...
            t_ns = 50_000_000_000 + k * 100_000_000
            w.write(clock, t_ns, store.serialize_cdr(store.types[CLOCK_TYPE](clock=stamp(sec=1000, nanosec=k * 100_000_000)),
                                                     CLOCK_TYPE))
            w.write(chatter, t_ns, store.serialize_cdr(store.types["std_msgs/msg/String"](data=str(k)), "std_msgs/msg/String"))
    lines = []
    _, clocks = _play_reading_clock(tmp_path / "sim_bag", clock_hz=20.0, log=lines.append)
    assert len(clocks) >= 5 and np.all((clocks >= 50.0 - 1e-6) & (clocks <= 51.2)) and np.all(np.diff(clocks) > 0)
    assert any("/clock is not played" in line for line in lines)


def test_ros2_play_loop_plays_until_a_stop(office_bag):
    """`ros2-play --loop` plays on until SIGINT (the 3 s bag at rate 4: 0.75 s a pass, still
    playing after 2 s), then exits 130 with one line, no traceback, and says what it played (it
    said nothing of that before)."""
    import signal

    argv = ["ros2-play", str(office_bag), "--loop", "--rate", "4", "--delay", "0", "--localhost-only",
            "--domain-id", str(_domain())]
    proc = subprocess.Popen([sys.executable, "-c", "from virus_nerf.cli import main; main()", *argv],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stdout.readline()
        assert first.startswith("ros2-play: ") and "topics on ROS 2 domain" in first
        time.sleep(2.0)
        assert proc.poll() is None  # still playing
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130 and "Traceback" not in err and len(err.strip().splitlines()) <= 1, err
    said = re.search(r"^ros2-play: stopped by SIGINT; (\d+) messages on (\d+) topics \((\d+) passes of the bag\) "
                     r"in [\d.]+ s \(at most [\d.]+ s late\)$", out, flags=re.M)
    assert said is not None and int(said[1]) > 0 and int(said[3]) >= 2, out


def test_a_publisher_that_left_is_forgotten():
    """A writer gone from the graph (a ros2-play that ended) is no longer a publisher: the node
    neither subscribes to its topic nor says it did; a second writer of the topic keeps it."""
    domain = _domain()
    seen, gone = dds.Participant("jazzy", domain, loopback=True), dds.Participant("jazzy", domain, loopback=True)
    stays = dds.Participant("jazzy", domain, loopback=True)
    try:
        def wait_for(check):
            t0 = time.monotonic()
            while not check(seen.discover()) and time.monotonic() - t0 < 20:
                time.sleep(0.05)
            return check(seen.discover())

        gone.writer("/left", GRID, dds.LATCHED)
        gone.writer("/shared", GRID, dds.LATCHED)
        stays.writer("/shared", GRID, dds.LATCHED)
        assert wait_for(lambda p: "/left" in p and len(seen.writer_gids.get("/shared", ())) == 2)
        gone.close()
        assert wait_for(lambda p: "/left" not in p and len(seen.writer_gids.get("/shared", ())) == 1)
        assert seen.publishers["/shared"] == {GRID} and "/left" not in seen.writer_gids
    finally:
        for p in (seen, gone, stays):
            p.close()


@pytest.mark.skipif(not hasattr(__import__("signal"), "SIGSTOP"), reason="needs SIGSTOP (POSIX)")
def test_a_reader_that_stops_acknowledging_is_a_timeout_not_a_crash():
    """The node's last act waits for its /map readers' acknowledgements; a reader that left (or
    hangs: SIGSTOP here, a killed `ros2 topic echo --once` before its lease ends) makes the wait
    time out, which is False (the map stays latched), not a traceback (cyclonedds 11.0.1's own
    DataWriter.wait_for_acks raises AttributeError then)."""
    import signal

    from virus_nerf.mapping.ros_maps import grid_message
    from virus_nerf.maps.occupancy import OccupancyMap2D

    domain, store = _domain(), types.typestore("jazzy")
    payload = types.serialize(grid_message(store, 0, OccupancyMap2D(np.full((4, 5), 254, np.uint8), 0.05, (0.0, 0.0))),
                              GRID, store)
    script = (f"import time\nfrom virus_nerf.ros2 import dds\np = dds.Participant('jazzy', {domain}, loopback=True)\n"
              f"r = p.reader('/acks', {GRID!r}, dds.LATCHED)\nt0 = time.monotonic()\n"
              "while not r.take() and time.monotonic() - t0 < 60:\n    time.sleep(0.02)\n"
              "print('got', flush=True)\ntime.sleep(60)\n")
    participant = dds.Participant("jazzy", domain, loopback=True)
    reader = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        writer = participant.writer("/acks", GRID, dds.LATCHED)
        writer.write(payload)  # latched: the reader gets it whenever it matches
        assert reader.stdout.readline().strip() == "got"
        assert writer.wait_for_acks(10.0) is True
        os.kill(reader.pid, signal.SIGSTOP)  # matched, and no longer acknowledging
        stat, t0 = Path(f"/proc/{reader.pid}/stat"), time.monotonic()
        while stat.exists() and stat.read_text().rsplit(")", 1)[-1].split()[0] != "T" and time.monotonic() - t0 < 10:
            time.sleep(0.01)  # stopped for sure: a receive thread still running might acknowledge the next sample
        writer.write(payload)
        start = time.monotonic()
        assert writer.wait_for_acks(0.5) is False
        assert time.monotonic() - start < 5.0
    finally:
        reader.kill()
        reader.wait(timeout=30)
        participant.close()
