"""The live ROS 2 node: the robot's topics in over DDS, `/map` and `/map_probability` out.

The same engine and frame pairing as `map-bag`'s stream (mapping/stream.py `StreamRun`,
data/bags/live.py `LiveSync`): `LiveMessages` is the stream's message source. It finds the
robot's publishers on the graph (DDS discovery: a topic's type is the one its writers announce,
so the node may start before or after the drivers), subscribes to each wanted topic with an
accepted type, and hands the messages to the stream as they come, deserialised by rosbags into
the objects a bag gives (`Message`), in stamp order within each take; when nothing is new it
yields None and the stream trains. The stream runs live (`LiveSync(on_problem=...)`): a sensor
that stops, a clock that goes back, a malformed message or a pose jump is one line in the log and
the node keeps mapping.

`MapPublisher` takes the stream's maps (the `ros_bag` sink of StreamRun: `write_maps` at every
snapshot and at the final map) and publishes them as nav_msgs/OccupancyGrid, reliable and
transient local, keep last 1 (ros2/dds.py), stamped with the newest frame's time, in the map
frame the user names (the pose source's world frame: `--tf-parent`, e.g. odom, unless a map ->
odom transform is published by someone else).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from virus_nerf.data.bags import messages as m
from virus_nerf.data.bags.live import RESTART_BACK_S
from virus_nerf.data.bags.reader import Message
from virus_nerf.mapping.ros_maps import OCCUPANCY_GRID, grid_message, stamp_ns
from virus_nerf.ros2 import dds, types

DISCOVER_EVERY_S = 0.5  # wall seconds between looks at the graph's publishers


def live_stamp(msg, fallback_s: float) -> float:
    """The message's time on the robot's clock: its header stamp; a TFMessage's newest transform
    stamp (it has no header); else `fallback_s` (the writer's source time)."""
    t = m.stamp_s(msg)  # a TFMessage's newest transform
    if t > 0:
        return t
    return fallback_s


def order_take(take: list[tuple[str, Message]], newest: dict[str, float]) -> list[tuple[str, Message]]:
    """One poll's messages (each topic's in arrival order) in stamp order, a clock restart kept
    whole: a topic whose stamp goes back more than RESTART_BACK_S (a bag played again, a clock
    reset) starts its next pass there, and every pass comes after the one before it, each in
    stamp order. Sorting a take that spans the jump by stamp alone put the old pass's tail after
    the new pass's head: two restarts, and every topic said stopped and back. `newest`: each
    topic's newest stamp so far (updated)."""
    keyed = []
    passes: dict[str, int] = {}
    for arrival, (topic, msg) in enumerate(take):
        prev = newest.get(topic)
        if prev is not None and msg.time_s < prev - RESTART_BACK_S:
            passes[topic] = passes.get(topic, 0) + 1
        newest[topic] = msg.time_s
        keyed.append((passes.get(topic, 0), msg.time_s, arrival, topic, msg))
    keyed.sort(key=lambda k: k[:3])
    return [(topic, msg) for *_, topic, msg in keyed]


class LiveMessages:
    """(topic, Message) as they arrive from DDS, None when nothing is new (module doc).

    wanted: topic -> the message types accepted on it; stop(): ends the iteration when true
    (checked at every poll); log: one line per event (a subscription made, a type refused);
    published: the topics this node writes (its maps): another publisher of one is said once."""

    def __init__(self, participant: dds.Participant, wanted: dict[str, tuple[str, ...]],
                 log: Callable[[str], None] = print, stop: Callable[[], bool] = lambda: False,
                 published: tuple[str, ...] = ()) -> None:
        self.participant, self.wanted, self.log, self.stop = participant, wanted, log, stop
        self.published, self.rivals = published, set()  # rivals: published topics another node writes too
        self.store = types.typestore(participant.distro)
        self.readers: dict[str, dds.Reader] = {}
        self.counts: dict[str, int] = dict.fromkeys(wanted, 0)
        self.refused: set[tuple[str, str]] = set()
        self.bad: dict[str, int] = {}  # topic -> payloads that did not deserialise
        self.last_message_s: float | None = None  # wall time (monotonic) of the newest message (not /tf_static)
        self.newest: dict[str, float] = {}  # topic -> its newest stamp (`order_take`)
        self._next_discovery = 0.0

    def discover(self) -> None:
        """Subscribe to each wanted topic once a publisher of an accepted type is on the graph; say
        once when another node publishes one of this node's topics (two mapping nodes on one
        domain: a planner would read both their maps on one topic)."""
        publishers = self.participant.discover()
        for topic in self.published:
            if topic in publishers and topic not in self.rivals:
                self.rivals.add(topic)
                self.log(f"ros2: warning: another node also publishes {topic} "
                         f"({', '.join(sorted(publishers[topic]))}): its readers get both nodes' maps; give this "
                         "node another topic (--map-topic, --probability-topic, --namespace) or --domain-id")
        for topic, msgtypes in publishers.items():
            if topic not in self.wanted or topic in self.readers:
                continue
            accepted = [t for t in msgtypes if t in self.wanted[topic]]
            if not accepted:
                for t in sorted(msgtypes):
                    if (topic, t) not in self.refused:
                        self.refused.add((topic, t))
                        self.log(f"ros2: topic {topic} is published as {t}; expected "
                                 f"{' or '.join(self.wanted[topic])}: not subscribed")
                continue
            kind = dds.STATIC if dds.is_tf_static(topic) else dds.SENSOR
            self.readers[topic] = self.participant.reader(topic, accepted[0], kind)
            self.log(f"ros2: subscribed to {topic} ({accepted[0]})")

    def poll(self) -> list[tuple[str, Message]]:
        """Every message received since the last poll, in stamp order."""
        now = time.monotonic()
        if now >= self._next_discovery:
            self.discover()
            self._next_discovery = now + DISCOVER_EVERY_S
        batch = []
        for topic, reader in self.readers.items():
            for sample in reader.take():
                try:
                    msg = types.deserialize(sample.payload, reader.msgtype, self.store)
                except Exception as exc:  # noqa: BLE001 - a malformed payload from the wire: said, skipped
                    self.bad[topic] = self.bad.get(topic, 0) + 1
                    if self.bad[topic] == 1:
                        self.log(f"ros2: topic {topic}: a message did not deserialise as {reader.msgtype} "
                                 f"({type(exc).__name__}); skipped (said once per topic)")
                    continue
                k = self.counts[topic]
                self.counts[topic] = k + 1
                t = live_stamp(msg, sample.source_s)
                batch.append((topic, Message(k, t, msg, reader.msgtype, sample.received_s)))
        if any(not dds.is_tf_static(topic) for topic, _ in batch):  # latched, sent before the robot moves
            self.last_message_s = time.monotonic()
        return order_take(batch, self.newest)

    def __iter__(self) -> Iterator[tuple[str, Message] | None]:
        """Ends when stop() is true and nothing is waiting (what came during a long step counts)."""
        while True:
            batch = self.poll()
            if batch:
                yield from batch
            elif self.stop():
                return
            else:
                yield None


class MapPublisher:
    """/map (the planner's map) and /map_probability (the VIRUS grid's) on DDS, latched."""

    def __init__(self, participant: dds.Participant, map_topic: str = "/map",
                 probability_topic: str = "/map_probability", frame_id: str = "map",
                 log: Callable[[str], None] = print) -> None:
        self.store, self.frame_id, self.log = types.typestore(participant.distro), frame_id, log
        self.writers = {"map": participant.writer(map_topic, OCCUPANCY_GRID, dds.LATCHED),
                        "probability": participant.writer(probability_topic, OCCUPANCY_GRID, dds.LATCHED)}
        self.published = 0
        self.first_s: float | None = None  # wall time (monotonic) of the first /map

    def write_pose(self, time_s: float, cam_to_world, stack_id: int | None = None) -> None:
        """The robot's pose is the pose source's (tf, odometry): the node publishes no transform."""

    def write_maps(self, time_s: float, map2d=None, prob=None) -> None:
        ns = stamp_ns(max(float(time_s), 0.0)) if math.isfinite(time_s) else 0
        for name, grid in (("map", map2d), ("probability", prob)):
            if grid is not None:
                msg = grid_message(self.store, ns, grid, self.frame_id)
                self.writers[name].write(types.serialize(msg, OCCUPANCY_GRID, self.store))
        self.published += 1
        if self.first_s is None:
            self.first_s = time.monotonic()

    def flush(self, timeout_s: float = 2.0) -> None:
        """Wait (at most `timeout_s`) until the matched readers have the newest maps: the final map
        reaches them before the node leaves the graph."""
        for w in self.writers.values():
            w.wait_for_acks(timeout_s)


def wanted_topics(sync, source) -> dict[str, tuple[str, ...]]:
    """Topic -> accepted message types of every topic the stream reads (the topics file's roles,
    the pose source's topics)."""
    wanted: dict[str, tuple[str, ...]] = {}
    for topic, keys in sync.roles.items():
        wanted[topic] = tuple(dict.fromkeys(t for _, role in keys for t in m.ACCEPTED[role]))
    for topic in source.topics:
        wanted.setdefault(topic, m.ACCEPTED[source.role])
    return wanted


def label(participant: dds.Participant) -> Path:
    """What errors name as the data source (a bag's path elsewhere)."""
    return Path(f"ROS 2 domain {participant.domain_id}")
