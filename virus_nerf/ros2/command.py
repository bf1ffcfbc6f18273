"""`virus-nerf ros2` (the live node) and `virus-nerf ros2-play` (a bag onto DDS); docs/ros2.md."""

from __future__ import annotations

import os
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Annotated

import tyro

from virus_nerf.errors import UsageError, require_input_file, require_int, require_number
from virus_nerf.mapping.command import Sinks
from virus_nerf.mapping.options import (
    DEFAULT_RASTER,
    NO_VIEW,
    MapRaster,
    RerunSinks,
    load_stream_config,
)
from virus_nerf.utils.io import require_new_folder

NODE_POSES = ("tf", "odometry", "lidar-odometry")
NODE_NAME = "virus_nerf"  # the name `ros2 node list` shows (in --namespace)


def _localhost_only(flag: bool) -> bool:
    """--localhost-only, or ROS 2's own switches: ROS_LOCALHOST_ONLY=1 (Humble),
    ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (Jazzy)."""
    return (flag or os.environ.get("ROS_LOCALHOST_ONLY", "") == "1"
            or os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").upper() == "LOCALHOST")


def ros2(
    out: Path | None = None,
    topics: Path | None = None,
    poses: str = "tf",
    tf_parent: str = "odom",
    tf_child: str | None = None,
    odometry_topic: str = "/odom",
    distro: str = "jazzy",
    domain_id: int | None = None,
    localhost_only: bool = False,
    namespace: str = "/",
    map_topic: str = "map",
    probability_topic: str = "map_probability",
    map_frame: str | None = None,
    publish_every: float = 5.0,
    first_map: float = 1.0,
    drive: float = 600.0,
    max_lag: float = 2.0,
    max_silence: float = 2.0,
    config: Path | None = None,
    maps: Annotated[MapRaster, tyro.conf.arg(name="")] = DEFAULT_RASTER,
    duration: float | None = None,
    exit_when_idle: float | None = None,
    keep_snapshots: int | None = None,
    view: Annotated[RerunSinks, tyro.conf.arg(name="")] = NO_VIEW,
) -> None:
    """Map live from a ROS 2 robot over DDS and publish /map (no ROS install: the ros2 extra).

    Joins the ROS 2 graph (domain $ROS_DOMAIN_ID), subscribes to the robot's topics as the topics
    file names them (colour or compressed image + camera_info, USS, ToF, depth if named; poses from
    /tf and /tf_static, nav_msgs/Odometry or KISS-ICP on the LiDAR), maps while the robot drives
    with map-bag's engine and frame pairing, and publishes the planner's map on /map and the VIRUS
    grid's probability on /map_probability (nav_msgs/OccupancyGrid, reliable, transient local) every
    --publish-every seconds. OUT/ gets map-bag's snapshots, final map and stream.json. A sensor
    that stops, a clock that jumps back, a malformed message or missing TF is one line in the log
    and the node keeps mapping; Ctrl-C or SIGTERM writes and publishes the final map (exit 130/143).

    Args:
        out: New output folder (snapshots, final map, stream.json).
        topics: Topic mapping file (default: the ETHZ robot's topic names; docs/usage.md).
        poses: Pose source: tf (/tf, /tf_static), odometry (nav_msgs/Odometry on --odometry-topic)
            or lidar-odometry (KISS-ICP on the topics file's LiDAR).
        tf_parent: --poses tf: the world frame.
        tf_child: --poses tf: the frame the topics file's camera mounting is given in (the LiDAR's).
        odometry_topic: --poses odometry: the topic.
        distro: ROS 2 message definitions: humble or jazzy (jazzy adds the type hash to the QoS user data).
        domain_id: ROS domain (default $ROS_DOMAIN_ID, else 0).
        localhost_only: Use the loopback interface only, no multicast (also ROS_LOCALHOST_ONLY=1 or
            ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST).
        namespace: The node's namespace: relative topic names resolve in it.
        map_topic: The planner's map (nav_msgs/OccupancyGrid; relative: in --namespace; ~/x: the node's).
        probability_topic: The VIRUS grid's occupancy probability, 0-100.
        map_frame: The maps' frame_id (default: --tf-parent, the frame the poses are in).
        publish_every: Wall-clock seconds between maps (each also a snapshot in OUT/snapshots;
            further apart when one takes longer: they take at most half the wall time).
        first_map: Wall-clock seconds from the first message to the first map.
        drive: Expected drive in seconds (the progress lines' and config.json's budget); the learning
            rate decays over it only with a config's optim.lr_decay_driving below 1.
        max_lag: A colour image that waited this many wall-clock seconds since it arrived is dropped
            (counted).
        max_silence: A sensor topic (or the pose source) silent this long is said in the log.
        config: JSON training config (default: the defaults).
        maps: The maps (--resolution, --n-rays, --max-poses; mapping/options.py, as map-bag's).
        duration: Stop after this many wall-clock seconds (default: run until Ctrl-C or SIGTERM).
        exit_when_idle: Stop when no message came for this many seconds after the first one.
        keep_snapshots: Keep only the newest N snapshot folders (the older ones this run wrote are removed;
            default: all of them): a node left running for hours writes one every --publish-every seconds.
        view: The live view (--rerun, --rerun-connect, --rerun-save; as map-bag's).
    """
    from virus_nerf.mapping.ros_maps import require_frame
    from virus_nerf.ros2.dds import require_dds, require_name, resolve

    if out is None:
        raise UsageError("--out is required: give --out DIR (a new folder for the snapshots and the final map)")
    if poses not in NODE_POSES:
        raise UsageError(f"--poses {poses!r}: expected {', '.join(NODE_POSES[:-1])} or {NODE_POSES[-1]}")
    if poses == "tf" and tf_child is None:
        raise UsageError("--poses tf needs --tf-child FRAME: the frame the topics file's camera mounting is "
                         "given in (the LiDAR's, e.g. rslidar)")
    namespace = require_name("--namespace", namespace, "/" + namespace.strip("/"), "namespace")
    names = {}
    for key, flag, value, example in (("map", "--map-topic", map_topic, "map"),
                                      ("probability", "--probability-topic", probability_topic, "map_probability")):
        if not value:
            raise UsageError(f"{flag} '': expected a topic name, e.g. {example}")
        names[key] = require_name(flag, value, resolve(value, namespace, NODE_NAME))
    require_name("--odometry-topic", odometry_topic, odometry_topic)  # an input, as the topics file's: absolute
    for flag, value in (("--tf-parent", tf_parent), ("--tf-child", tf_child), ("--map-frame", map_frame)):
        if value is not None:
            require_frame(flag, value)
    for flag, value, low in (("--publish-every", publish_every, 0.0), ("--first-map", first_map, 0.0),
                             ("--drive", drive, 0.0), ("--max-lag", max_lag, 0.0),
                             ("--max-silence", max_silence, 0.0)):
        require_number(flag, value, low, lo_open=flag != "--first-map")
    if keep_snapshots is not None:
        require_int("--keep-snapshots", keep_snapshots, 1)
    maps.check()
    for flag, value in (("--duration", duration), ("--exit-when-idle", exit_when_idle)):
        if value is not None:
            require_number(flag, value, 0.0)
    if topics is not None:
        require_input_file("--topics", topics, "the importer's topic mapping file (TOML)")
    out = Path(out)
    require_new_folder("--out", out)
    view.check()
    require_dds()
    from virus_nerf.ros2.types import typestore

    typestore(distro)  # the one-line refusal of an unknown distro
    cfg = load_stream_config(config)
    from virus_nerf.utils.stop import stop_on_signals

    with stop_on_signals():
        run_node(out, topics, poses, tf_parent, tf_child, odometry_topic, cfg, distro=distro, domain=domain_id,
                 loopback=_localhost_only(localhost_only), names=names, map_frame=map_frame or tf_parent,
                 namespace=namespace,
                 publish_every=publish_every, first_map=first_map, drive=drive, max_lag=max_lag,
                 max_silence=max_silence, maps=maps, sinks=Sinks(view),
                 duration=duration, exit_when_idle=exit_when_idle, keep_snapshots=keep_snapshots)


def require_topic_names(tcfg) -> None:
    """Every topic the topics file names is a ROS 2 topic name, else one line naming the file and
    key: a name no publisher can have would be waited for in silence."""
    from virus_nerf.errors import ConfigError
    from virus_nerf.ros2.dds import name_problem

    named = [(f"stacks.{s}.{role}", topic) for s, st in sorted(tcfg.stacks.items()) for role, topic in st.roles().items()]
    named += [("lidar.topic", tcfg.lidar.topic)] if tcfg.lidar.topic else []
    named += [(f"tf_topics[{i}]", t) for i, t in enumerate(tcfg.tf_topics)]
    for key, topic in named:
        problem = name_problem(topic)
        if problem is not None:
            raise ConfigError(f"{topic!r}: not a ROS 2 topic name; {problem}", file=tcfg.source, key=key)


def run_node(out: Path, topics: Path | None, poses: str, tf_parent: str, tf_child: str | None, odometry_topic: str,
             cfg, *, distro: str, domain: int | None, loopback: bool, names: dict, map_frame: str, namespace: str,
             publish_every: float, first_map: float, drive: float, max_lag: float, max_silence: float,
             maps: MapRaster, sinks: Sinks, duration: float | None, exit_when_idle: float | None,
             keep_snapshots: int | None = None, log=print) -> None:
    """The node (ros2/node.py) until a stop: --duration, --exit-when-idle, SIGINT or SIGTERM."""
    from virus_nerf.data.bags.live import LiveSync
    from virus_nerf.data.bags.poses import make_pose_source
    from virus_nerf.data.bags.topics import default_topics, read_topics
    from virus_nerf.mapping.command import make_out, run_made_nothing
    from virus_nerf.mapping.stream import StreamRun, summary, warm_up
    from virus_nerf.ros2.dds import Participant
    from virus_nerf.ros2.node import LiveMessages, MapPublisher, label, wanted_topics
    from virus_nerf.trainer.config import TrainConfig
    from virus_nerf.trainer.run_folder import RunLock
    from virus_nerf.utils.stop import Stopped

    tcfg = read_topics(topics) if topics else default_topics()
    require_topic_names(tcfg)
    for note in tcfg.notes:  # e.g. no [stacks]: the ETHZ robot's topics are waited for
        log(f"ros2: note: {note}")
    cfg = cfg if cfg is not None else TrainConfig()
    tcfg = tcfg.for_sensors(cfg.sensors)  # a depth image the mapper does not use is neither read nor waited for
    participant = Participant(distro, domain, loopback=loopback)
    participant.announce_node(NODE_NAME, namespace)
    where = label(participant)
    with Leaving(log) as leaving, ExitStack() as owned:
        owned.callback(participant.close)
        source = make_pose_source(poses, tcfg, where, present=lambda t: True, tf_parent=tf_parent, tf_child=tf_child,
                                  odometry_topic=odometry_topic, keep_up=True)
        owned.callback(source.close)  # KISS-ICP's worker process ends with the node
        sync = LiveSync(tcfg, source, where, with_depth="rgbd" in cfg.sensors, max_silence_s=max_silence,
                        on_problem=lambda line: log(f"ros2: {line}"))
        publisher = MapPublisher(participant, names["map"], names["probability"], map_frame, log=log)
        owned.callback(publisher.flush)  # the final map reaches the readers before the node leaves
        warm_step_s = warm_up(cfg)
        made = make_out(out)
        owned.enter_context(RunLock(out, "--out"))
        started = time.monotonic()

        def stop() -> bool:
            now = time.monotonic()
            if duration is not None and now - started >= duration:
                return True
            last = messages.last_message_s
            return exit_when_idle is not None and last is not None and now - last >= exit_when_idle

        messages = LiveMessages(participant, wanted_topics(sync, source), log=log, stop=stop,
                                published=(names["map"], names["probability"]))
        messages.discover()
        log(f"ros2: node up on ROS 2 domain {participant.domain_id} ({distro}{', localhost only' if loopback else ''}); "
            f"waiting for {', '.join(sorted(messages.wanted))}; maps on {names['map']} and {names['probability']} "
            f"(frame {map_frame}) every {publish_every:g} s")
        run = None
        try:
            with ExitStack() as stack:
                live, _ = sinks.open(stack)
                run = StreamRun(sync, out, cfg, playback=1.0, snapshot_every=publish_every, first_snapshot=first_map,
                                max_lag=max_lag, drive_s=drive, live=live, ros_bag=publisher,
                                warm_step_s=warm_step_s, keep_snapshots=keep_snapshots, **maps.kwargs())
                report = run.run(messages)
        except BaseException as exc:
            nothing = run_made_nothing(out)
            if nothing:
                made.remove()  # made by this run, and nothing in it
                sinks.discard()
            if isinstance(exc, Stopped):
                exc.reported = True
                if nothing or run is None or run.report.final is None:
                    log(f"ros2: stopped by {exc.name} before the first frame was mapped; nothing was kept")
                else:
                    log(f"ros2: stopped by {exc.name}; {summary(run.report)}; final map in {run.report.final} "
                        f"(published on {names['map']}), report in {out / 'stream.json'}")
            raise
        # said before the node leaves the graph (its readers get up to 2 s to take the final map)
        if report.final is None:
            made.remove()  # made by this run, and nothing in it
            sinks.discard()
            log(f"ros2: no frame was mapped ({summary(report)}); nothing was kept")
        else:
            leaving.published = True  # before the line: a stop while it is printed is said after it
            log(f"ros2: {summary(report)}, {report.steps} steps in {report.wall_s:.1f} s; {publisher.published} maps "
                f"published on {names['map']}; final map in {report.final}")


class Leaving:
    """The node leaving the graph after its final map and last line: a stop signal then (a hung
    reader holds the final map's hand-over, 2 s per topic) adds one line after it, not the CLI's
    bare "interrupted" (a review: the summary was lost)."""

    def __init__(self, log) -> None:
        self.log, self.published = log, False

    def __enter__(self) -> Leaving:
        return self

    def __exit__(self, kind, exc, tb) -> None:
        from virus_nerf.utils.stop import Stopped

        if self.published and isinstance(exc, Stopped) and not exc.reported:
            exc.reported = True
            self.log(f"ros2: stopped by {exc.name} while leaving the ROS 2 graph; the final map was published, a "
                     "reader that had not taken it yet gets none")


def ros2_play(
    bag: Annotated[Path, tyro.conf.Positional],
    rate: float = 1.0,
    topic: list[str] | None = None,
    distro: str = "jazzy",
    domain_id: int | None = None,
    localhost_only: bool = False,
    delay: float = 1.0,
    clock: bool = False,
    clock_hz: float = 40.0,
    loop: bool = False,
) -> None:
    """Play a ROS 1 or ROS 2 bag onto a ROS 2 graph over DDS, as `ros2 bag play` (no ROS install).

    Each message goes out on its topic at its recorded pace (scaled by --rate), header stamps as
    recorded; ROS 1 messages converted to ROS 2's. Try the node without a robot: `virus-nerf ros2
    --out OUT ...` in one terminal, `virus-nerf ros2-play BAG` in another (docs/ros2.md).

    Args:
        bag: ROS bag (ROS 1 .bag, a ROS 2 bag folder, or a bare ROS 2 .mcap/.db3 file).
        rate: Recording seconds per wall-clock second.
        topic: Play only these topics (--topic /a /b; default: all).
        distro: ROS 2 message definitions: humble or jazzy.
        domain_id: ROS domain (default $ROS_DOMAIN_ID, else 0).
        localhost_only: Use the loopback interface only, no multicast (also ROS_LOCALHOST_ONLY=1 or
            ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST).
        delay: Seconds between joining the graph and the first message (discovery).
        clock: Also publish /clock (rosgraph_msgs/Clock) with the bag's time, as the --clock of
            `ros2 bag play`, for nodes run with use_sim_time (a /clock recorded in the bag is then
            not played).
        clock_hz: /clock messages a second with --clock (`ros2 bag play --clock 40`).
        loop: Play the bag again and again until Ctrl-C or SIGTERM, each pass from its start
            with its recorded stamps (`ros2 bag play --loop`; the node takes the jump back as a
            restart and keeps mapping).
    """
    from virus_nerf.ros2.dds import Participant, require_dds
    from virus_nerf.ros2.play import PlayReport, play
    from virus_nerf.utils.stop import Stopped, stop_on_signals

    require_number("--rate", rate, 0.0)
    if topic is not None and not topic:
        raise UsageError("--topic: expected one or more topic names (--topic /tf /CAM1/color/image_raw); "
                         "leave --topic out to play every topic")
    require_number("--delay", delay, 0.0, lo_open=False)
    require_number("--clock-hz", clock_hz, 0.0)
    if not Path(bag).exists():
        raise UsageError(f"BAG {bag}: no such file or folder; expected a ROS bag")
    require_dds()
    participant = Participant(distro, domain_id, loopback=_localhost_only(localhost_only))
    report = PlayReport()
    try:
        with stop_on_signals():
            play(Path(bag), participant, rate=rate, topics=topic, delay_s=delay, clock_hz=clock_hz if clock else 0.0,
                 loops=0 if loop else 1, report=report)
    except Stopped as exc:  # Ctrl-C ends a --loop: what was played, as a finished play says it
        exc.reported = True
        print(f"ros2-play: stopped by {exc.name}; {_played(report, clock)}")
        raise
    finally:
        participant.close()
    print(f"ros2-play: {_played(report, clock)}")


def _played(report, clock: bool) -> str:
    """ros2-play's summary: messages, topics, passes of the bag, wall time, lateness, /clock ticks."""
    passes = f" ({report.passes} passes of the bag)" if report.passes > 1 else ""
    return (f"{report.messages} messages on {report.topics} topics{passes} in {report.wall_s:.1f} s "
            f"(at most {report.behind_s:.2f} s late)" + (f", {report.clock_ticks} /clock ticks" if clock else ""))
