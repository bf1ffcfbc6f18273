"""A ROS 1 or ROS 2 bag played onto DDS at its recorded pace, as `ros2 bag play` would.

Every message of the chosen topics is published on its topic, in the bag's receive order, when a
wall clock scaled by `rate` passes its receive time; its header stamps are left as recorded (a
node reads them as the robot's clock). A ROS 1 message is converted to the ROS 2 shape of the
chosen distro (ros2/types.py `to_ros2`: `seq` dropped, CameraInfo's `D, K, R, P` as `d, k, r,
p`). QoS: what the bag recorded its publishers offering (a ROS 2 bag's offered QoS profiles, a
ROS 1 topic's latching), as `ros2 bag play` offers it: a latched /map (map-bag --out-bag) reaches
readers that ask for transient local. Where the bag records none: `/tf_static` reliable and
transient local (a node that joins later still gets the static transforms), every other topic
reliable and volatile, depth 10 (ROS 2's default profile).

With `clock_hz` it also publishes `/clock` (rosgraph_msgs/Clock), as `ros2 bag play --clock`: the
bag's time (its receive times, from the first message's, advancing at `rate`) that many times a
wall-clock second, best effort and depth 1 as rclcpp's clock subscription asks, so nodes run
with use_sim_time follow the bag; a /clock recorded in the bag (a simulator's) is then not played,
as rosbag2 does, so there is one clock.

With `loops` 0 (`--loop`) it plays the bag again and again until stopped, each pass from the
bag's start, its stamps and /clock as recorded (`ros2 bag play --loop`): a node sees its clock go
back (the virus-nerf node takes it as a restart and keeps mapping, data/bags/live.py `restart`).

So the node can be tried on a machine without ROS and without a robot, and tested here.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from virus_nerf.ros2 import dds, types


@dataclass
class PlayReport:
    messages: int = 0
    topics: int = 0
    wall_s: float = 0.0
    behind_s: float = 0.0  # the most a message was published after it was due (wall seconds)
    clock_ticks: int = 0  # /clock messages published
    passes: int = 0  # plays of the bag begun


CLOCK_TOPIC, CLOCK_TYPE = "/clock", "rosgraph_msgs/msg/Clock"
CLOCK_QOS = dds.QosKind(reliable=False, transient_local=False, depth=1)  # rclcpp's ClockQoS


class _Clock:
    """/clock at `hz` wall-clock ticks a second: the bag's time at wall second w of the play is
    t0 + w * rate."""

    def __init__(self, participant: dds.Participant, store, hz: float, rate: float) -> None:
        self.writer = participant.writer(CLOCK_TOPIC, CLOCK_TYPE, CLOCK_QOS)
        self.store, self.period, self.rate = store, 1.0 / hz, rate
        self.t0: float | None = None
        self.next_s = 0.0  # the next tick (wall seconds of the play)
        self.ticks = 0

    def tick(self, now_s: float) -> float:
        """Publish the bag's time if a tick is due at wall second `now_s`; the next tick's second."""
        if self.t0 is not None and now_s >= self.next_s:
            ns = round((self.t0 + now_s * self.rate) * 1e9)
            stamp = self.store.types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
            self.writer.write(types.serialize(self.store.types[CLOCK_TYPE](clock=stamp), CLOCK_TYPE, self.store))
            self.ticks += 1
            self.next_s += self.period
            if self.next_s <= now_s:  # late: the next a period on, no burst of ticks to catch up
                self.next_s = now_s + self.period
        return self.next_s


def play_qos(topic: str, recorded) -> dds.QosKind:
    """The QoS a topic is played with: as recorded (data.bags.reader.RecordedQos; a keep-all or
    unrecorded depth as ROS 2's default, 10), else the module doc's defaults."""
    if recorded is None:
        return dds.STATIC if dds.is_tf_static(topic) else dds.RELIABLE
    return dds.QosKind(reliable=recorded.reliable, transient_local=recorded.transient_local,
                       depth=recorded.depth or dds.RELIABLE.depth)


def play(bag: Path, participant: dds.Participant, *, rate: float = 1.0, topics: list[str] | None = None,
         delay_s: float = 1.0, clock_hz: float = 0.0, loops: int = 1,
         log: Callable[[str], None] = print, report: PlayReport | None = None) -> PlayReport:
    """Publish `bag`'s messages (of `topics`, default all) on the participant's domain; returns
    after the last one. delay_s: wall seconds between the publishers' creation and the first
    message, for discovery (`ros2 bag play --delay`); clock_hz: /clock ticks a wall-clock second
    (0: no /clock); loops: plays of the bag (0: until stopped). `report`: filled as it plays, so
    that a caller stopped part-way (a signal) can say what was played."""
    from virus_nerf.data.bags.reader import BagReader
    from virus_nerf.errors import UsageError

    store = types.typestore(participant.distro)
    report = report if report is not None else PlayReport()
    with BagReader(bag) as reader:
        known = reader.topics
        names = list(known) if topics is None else topics
        for t in names:
            if t not in known:
                raise UsageError(f"--topic {t}: not in the bag {bag}; it has {', '.join(sorted(known))}")
        if clock_hz > 0 and CLOCK_TOPIC in names:  # one clock: ours (rosbag2 does the same)
            names = [t for t in names if t != CLOCK_TOPIC]
            log(f"ros2-play: the bag's own {CLOCK_TOPIC} is not played: --clock publishes the bag's time")
        writers = {}
        for t in names:
            writers[t] = participant.writer(t, known[t].msgtype, play_qos(t, reader.recorded_qos(t)))
        report.topics = len(writers)
        clock = _Clock(participant, store, clock_hz, rate) if clock_hz > 0 else None
        log(f"ros2-play: {bag}: {len(writers)} topics on ROS 2 domain {participant.domain_id} "
            f"({participant.distro}), rate {rate:g}" + (f", /clock at {clock_hz:g} Hz" if clock else ""))
        time.sleep(delay_s)
        first = time.monotonic()
        try:
            while loops == 0 or report.passes < loops:
                report.passes += 1
                if not _play_once(reader, names, writers, store, rate, clock, report):
                    break  # nothing to play
        finally:  # a stop too: the report says what was played
            report.wall_s = time.monotonic() - first
            report.clock_ticks = clock.ticks if clock is not None else 0
    return report


def _play_once(reader, names: list[str], writers: dict, store, rate: float, clock: _Clock | None,
               report: PlayReport) -> bool:
    """One pass over the bag's messages at their pace (the clock from the bag's start); False when
    there were none."""
    start = time.monotonic()
    r0 = None
    for topic, msg in reader.iter_topics(names):
        received = msg.received_s if msg.received_s is not None else msg.time_s
        if r0 is None:
            r0 = received
            if clock is not None:
                clock.t0, clock.next_s = r0, 0.0
        due = (received - r0) / rate
        wait = _wait_until(start, due, clock)
        if wait < 0:
            report.behind_s = max(report.behind_s, -wait)
        msgtype = msg.msgtype
        writers[topic].write(types.serialize(types.to_ros2(msg.msg, msgtype, store), msgtype, store))
        report.messages += 1
    return r0 is not None


def _wait_until(start: float, due_s: float, clock: _Clock | None) -> float:
    """Sleep until `due_s` wall seconds after `start` (monotonic), ticking the clock meanwhile;
    how long it waited (negative: how late it already was)."""
    now = time.monotonic() - start
    first = due_s - now
    while True:
        next_tick = clock.tick(now) if clock is not None else float("inf")
        if now >= due_s:
            return first
        time.sleep(min(due_s, next_tick) - now)
        now = time.monotonic() - start
