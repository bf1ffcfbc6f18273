"""Reading ROS 1 (.bag) and ROS 2 (folder with metadata.yaml + .db3/.mcap, or a bare .mcap/.db3
file) bags with rosbags.

`BagReader` opens either kind, checks that a topic exists and carries an accepted message type,
and iterates one topic's messages deserialised, with their stamps. Every failure of rosbags
(truncated file, corrupt index or database, undecodable message) becomes one `DataFormatError`
naming the bag, so a broken bag never ends in a traceback.
"""

from __future__ import annotations

import sqlite3
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from virus_nerf.data.bags import messages as m
from virus_nerf.errors import DataFormatError


def _bag_errors() -> tuple[type[BaseException], ...]:
    """Exception types rosbags (and its storage backends) raise on a damaged bag."""
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error
    from rosbags.serde import SerdeError
    from rosbags.typesys import TypesysError

    return (AnyReaderError, Reader1Error, Reader2Error, SerdeError, TypesysError, sqlite3.Error,
            struct.error, EOFError, UnicodeDecodeError, IndexError, KeyError, ValueError, AssertionError,
            MemoryError, OverflowError)  # a corrupt record length: rosbags asks for exabytes at once


@dataclass(frozen=True)
class TopicInfo:
    topic: str
    msgtype: str  # normalised ('sensors/msg/USS', 'sensor_msgs/msg/Image', ...)
    count: int


@dataclass(frozen=True)
class Message:
    """One deserialised message: its position in the topic, stamp (s) and content."""

    index: int
    time_s: float  # header stamp; the bag's receive time where the header stamp is unset
    msg: object
    msgtype: str
    received_s: float | None = None  # the bag's receive (record) time: the order messages arrive in


@dataclass(frozen=True)
class RecordedQos:
    """How a topic's publishers offered it when the bag was recorded (a player offers the same, as
    `ros2 bag play` does: a latched /map stays latched for the readers that ask for that)."""

    reliable: bool
    transient_local: bool
    depth: int  # KEEP_LAST depth; 0 = keep all or not recorded


class BagReader:
    """A ROS 1 or ROS 2 bag open for reading (use as a context manager)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if self.path.is_dir():
            if not (self.path / "metadata.yaml").is_file():
                raise DataFormatError(self.path, "folder has no metadata.yaml; expected a ROS 2 bag folder "
                                      "(metadata.yaml + .db3/.mcap) or a ROS 1 .bag file")
            self.ros_version = 2
        elif self.path.is_file():
            if self.path.suffix not in (".bag", ".mcap", ".db3"):
                raise DataFormatError(self.path, "expected a ROS 1 .bag file, a ROS 2 bag folder (metadata.yaml + "
                                      ".db3/.mcap) or a single ROS 2 .mcap/.db3 file")
            # rosbags reads a ROS 2 storage file without its folder's metadata.yaml (rosbag2.Reader picks
            # its McapReader / Sqlite3Reader by the suffix): rosbag2 may write single .mcap files.
            self.ros_version = 1 if self.path.suffix == ".bag" else 2
        else:
            raise DataFormatError(self.path, "bag not found")
        self._reader = None
        self._errors = _bag_errors()

    def __enter__(self) -> BagReader:
        from rosbags.highlevel import AnyReader

        try:
            reader = AnyReader([self.path], default_typestore=m.make_typestore(self.ros_version))
            reader.open()
        except self._errors as exc:
            raise self.corrupt(exc) from None
        self._reader = reader
        return self

    def __exit__(self, *exc) -> None:
        if self._reader is not None:
            try:
                self._reader.close()
            except self._errors:
                pass
            self._reader = None

    def corrupt(self, exc: BaseException) -> DataFormatError:
        what = " ".join(str(exc).split()) or type(exc).__name__
        if isinstance(exc, MemoryError):
            what = "a record's length asks for more memory than there is (MemoryError)"
        return DataFormatError(self.path, f"cannot be read (truncated or corrupt bag?): {what}")

    @property
    def topics(self) -> dict[str, TopicInfo]:
        out = {}
        for name, info in self._reader.topics.items():
            out[name] = TopicInfo(name, m.normalise_type(info.msgtype or "?"), int(info.msgcount))
        return out

    def recorded_qos(self, topic: str) -> RecordedQos | None:
        """The QoS `topic` was offered with when recorded: a ROS 2 bag's offered_qos_profiles (when
        its publishers agreed), a ROS 1 connection's latching (latched: reliable, transient local,
        depth 1, as ROS 1 replays it); None when the bag records none."""
        from rosbags.interfaces import (
            ConnectionExtRosbag1,
            ConnectionExtRosbag2,
            QosDurability,
            QosHistory,
            QosReliability,
        )

        exts = [c.ext for c in self._reader.connections if c.topic == topic]
        if any(isinstance(e, ConnectionExtRosbag1) and e.latching for e in exts):
            return RecordedQos(reliable=True, transient_local=True, depth=1)
        profiles = {p for e in exts if isinstance(e, ConnectionExtRosbag2) for p in (e.offered_qos_profiles or [])
                    if not isinstance(p, str)}  # rosbags keeps an unparsed profile list as its YAML text
        if len({(p.reliability, p.durability) for p in profiles}) != 1:
            return None
        first = next(iter(profiles))
        depths = [p.depth for p in profiles if p.history == QosHistory.KEEP_LAST]
        return RecordedQos(reliable=first.reliability != QosReliability.BEST_EFFORT,
                           transient_local=first.durability == QosDurability.TRANSIENT_LOCAL,
                           depth=max(depths, default=0))

    @property
    def span_s(self) -> tuple[float, float]:
        """(first, last) receive time of the bag's messages in seconds (from the bag's index)."""
        return self._reader.start_time * 1e-9, self._reader.end_time * 1e-9

    def require(self, topic: str, role: str, key: str) -> TopicInfo:
        """The topic's info; refuses a topic missing from the bag or of a type `role` cannot read.

        key: where the topic was named (a topics-file key such as 'stacks.1.uss', or a flag)."""
        topics = self.topics
        if topic not in topics:
            listed = ", ".join(sorted(topics)) or "none"
            raise DataFormatError(self.path, f"no topic {topic} ({key}); the bag has: {listed}. "
                                  "Name your robot's topics in a topics file (--topics FILE)")
        info = topics[topic]
        accepted = m.ACCEPTED[role]
        if info.msgtype not in accepted:
            raise DataFormatError(self.path, f"topic {topic} ({key}) has message type {info.msgtype}; "
                                  f"expected {' or '.join(accepted)}")
        self._ensure_type(topic)
        if info.count == 0:
            raise DataFormatError(self.path, f"topic {topic} ({key}) has no messages")
        return info

    def _ensure_type(self, topic: str) -> None:
        """Register a known type the bag carries no definition of (older ROS 2 bags); refuse an unknown one."""
        store = self._reader.typestore
        raw = {c.msgtype for c in self._reader.connections if c.topic == topic}
        missing = {t for t in raw if t not in store.fielddefs}
        if not missing:
            return
        known = m.make_typestore(self.ros_version)
        for t in missing:
            name = m.normalise_type(t)
            if name not in known.fielddefs:
                raise DataFormatError(self.path, f"topic {topic}: message type {t} has no definition in the bag "
                                      "and is not a standard or ETHZ type")
            defs = {k: v for k, v in known.fielddefs.items() if k not in store.fielddefs}
            store.register(defs)
            if t != name:  # a differently cased custom name: same layout under the bag's name
                store.register({t: known.fielddefs[name]})

    def iter_topic(self, topic: str) -> Iterator[Message]:
        """Messages of `topic` in bag order, deserialised."""
        for _, msg in self.iter_topics([topic]):
            yield msg

    def iter_topics(self, topics: list[str]) -> Iterator[tuple[str, Message]]:
        """(topic, message) of several topics in one pass over the bag, in bag time order;
        Message.index counts within each topic (the same in every pass)."""
        conns = [c for c in self._reader.connections if c.topic in set(topics)]
        counts = dict.fromkeys(topics, 0)
        try:
            for conn, t_ns, raw in self._reader.messages(connections=conns):
                msg = self._reader.deserialize(raw, conn.msgtype)
                stamp = m.stamp_s(msg)
                k = counts[conn.topic]
                counts[conn.topic] = k + 1
                yield conn.topic, Message(k, stamp if stamp > 0 else t_ns * 1e-9, msg, m.normalise_type(conn.msgtype),
                                          t_ns * 1e-9)
        except self._errors as exc:
            raise self.corrupt(exc) from None
