"""ROS 2 topics over DDS with cyclonedds, no ROS install: what rmw_cyclonedds_cpp puts on the wire.

A ROS 2 node (rmw_cyclonedds_cpp) is a DDS participant; its topic `/map` is the DDS topic `rt/map`
of type `nav_msgs::msg::dds_::OccupancyGrid_` (ros2/rmw_cyclonedds, namespace_prefix.hpp and
serdata.cpp), final structs in plain CDR (XCDR1). Matching is by topic and type name, so a ROS 2
node and this one see each other as long as both name the same type. Payloads are (de)serialised
by rosbags (ros2/types.py) and go to and from cyclonedds as raw CDR bytes: the decoders of
data/bags/messages.py then read exactly what they read from a bag, and an image is not turned into
a Python list on the way. The IdlStruct of each type (ros2/types.py) only registers the topic.

Quality of service, as ROS 2 names it (REP-2003, rmw's profiles):
- sensors: best effort, volatile; a best-effort reader also matches a reliable writer, so one
  reader serves every driver; its history is deeper than the drivers' (SENSOR_DEPTH): the mapper
  takes messages between training slices;
- `/tf_static`: reliable, transient local (a late joiner gets the static transforms);
- maps (`/map`): reliable, transient local, keep last 1: a planner or `map_saver_cli` started
  later still gets the newest map.

`loopback=True` configures the domain to use the loopback interface only, without multicast
(discovery by unicast to 127.0.0.1): tests never leave the machine.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

from virus_nerf.errors import UsageError, install_extra

ROS_TOPIC_PREFIX = "rt"  # rmw_cyclonedds: topics; "rq"/"rr" are services
DISCOVERY_TOPIC = "ros_discovery_info"  # rmw_dds_common's graph topic (a DDS name, no prefix)
ENTITIES_INFO = "rmw_dds_common/msg/ParticipantEntitiesInfo"
SENSOR_DEPTH = 200  # samples a sensor reader keeps between two takes (a few seconds of every sensor)
MAX_QUEUED_S = 30.0  # a writer's source time further back than this (or ahead) is another clock, not a wait
MAX_DOMAIN_ID = 232  # the DDS port mapping's limit (ROS 2 documents 0-101 / 215-232 as safe)
LOOPBACK_CONFIG = (
    "<CycloneDDS><Domain id=\"any\"><General><Interfaces><NetworkInterface address=\"127.0.0.1\"/></Interfaces>"
    "<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
    "<MaxAutoParticipantIndex>40</MaxAutoParticipantIndex><Peers><Peer address=\"127.0.0.1\"/></Peers>"
    "</Discovery></Domain></CycloneDDS>"
)


def require_dds():
    """The cyclonedds module, or the one-line message naming the extra."""
    try:
        import cyclonedds  # noqa: F401
        import rosbags  # noqa: F401
    except ImportError as exc:
        raise UsageError(f"the ROS 2 node needs the ros2 extra ({exc.name} is missing): "
                         f"{install_extra('ros2')}") from None


def domain_id(value: int | None = None) -> int:
    """The ROS domain: `value`, else $ROS_DOMAIN_ID, else 0 (as ROS 2)."""
    raw = value if value is not None else os.environ.get("ROS_DOMAIN_ID", "0") or "0"
    try:
        d = int(raw)
    except ValueError:
        raise UsageError(f"ROS_DOMAIN_ID={raw!r}: expected an integer 0-{MAX_DOMAIN_ID}") from None
    if not 0 <= d <= MAX_DOMAIN_ID:
        raise UsageError(f"domain id {d}: expected 0-{MAX_DOMAIN_ID}")
    return d


def is_tf_static(topic: str) -> bool:
    """The static transforms' topic (tf2's /tf_static, namespaced or not): reliable, transient local."""
    return topic == "/tf_static" or topic.endswith("/tf_static")


def dds_topic(name: str) -> str:
    """'/map' -> 'rt/map' (a fully qualified ROS name); rmw's graph topic keeps its own name."""
    if name == DISCOVERY_TOPIC:
        return name
    if not name.startswith("/"):
        raise UsageError(f"topic {name!r}: expected a fully qualified name starting with '/'")
    return ROS_TOPIC_PREFIX + name


MAX_TOPIC_CHARS = 247  # rmw: a DDS name is at most 255 characters, 8 kept for the prefixes


def name_problem(name: str, what: str = "topic") -> str | None:
    """Why `name` (a fully qualified ROS 2 name, '/a/b') is not one, or None: ROS 2's rules (rmw's
    validate_full_topic_name): '/'-separated tokens of letters, digits and '_', none empty and none
    starting with a digit, no '/' at the end (a namespace may be '/' alone)."""
    if not name.startswith("/"):
        return "expected a name starting with '/'"
    if name == "/":
        return None if what == "namespace" else "expected a name after '/'"
    if name.endswith("/"):
        return "expected no '/' at the end"
    if len(name) > MAX_TOPIC_CHARS:
        return f"expected at most {MAX_TOPIC_CHARS} characters"
    for token in name[1:].split("/"):
        if not token:
            return "expected no repeated '/'"
        bad = sorted({c for c in token if not (c.isascii() and (c.isalnum() or c == "_"))})
        if bad:
            return f"{''.join(bad)!r} is not allowed: expected letters, digits, '_' and '/'"
        if token[0].isdigit():
            return f"token {token!r} starts with a digit"
    return None


def require_name(flag: str, value: str, resolved: str, what: str = "topic") -> str:
    """`resolved` (the fully qualified form of `value`), or the one-line refusal naming `flag`."""
    problem = name_problem(resolved, what)
    if problem is not None:
        shown = f"{value!r}" if value == resolved else f"{value!r} ({resolved!r})"
        raise UsageError(f"{flag} {shown}: not a ROS 2 {what} name; {problem}")
    return resolved


def resolve(name: str, namespace: str = "/", node: str | None = None) -> str:
    """A ROS name resolved as rcl resolves it for node `node` in `namespace`: '/x' stays,
    'x' -> '<namespace>/x', '~' and '~/x' -> the node's private '<namespace>/<node>[/x]'."""
    if name.startswith("/"):
        return name
    ns = "/" + namespace.strip("/")
    if name == "~" or name.startswith("~/"):
        if node is None:
            raise ValueError(f"{name!r}: a private name needs the node's name")
        ns, name = ns.rstrip("/") + "/" + node, name[2:]
    return (ns.rstrip("/") + "/" + name) if name else ns


_LOOPBACK_DOMAINS: dict[int, object] = {}  # domain id -> its cyclonedds Domain, configured loopback-only


@dataclass(frozen=True)
class QosKind:
    """One of the QoS profiles of the module doc."""

    reliable: bool
    transient_local: bool
    depth: int


SENSOR = QosKind(reliable=False, transient_local=False, depth=SENSOR_DEPTH)
STATIC = QosKind(reliable=True, transient_local=True, depth=SENSOR_DEPTH)  # /tf_static
LATCHED = QosKind(reliable=True, transient_local=True, depth=1)  # /map
RELIABLE = QosKind(reliable=True, transient_local=False, depth=10)  # ROS 2's default profile


def _qos(kind: QosKind, user_data: bytes = b""):
    from cyclonedds.core import Policy, Qos
    from cyclonedds.util import duration

    policies = [Policy.Reliability.Reliable(max_blocking_time=duration(milliseconds=100)) if kind.reliable
                else Policy.Reliability.BestEffort,
                Policy.Durability.TransientLocal if kind.transient_local else Policy.Durability.Volatile,
                Policy.History.KeepLast(kind.depth),
                Policy.DataRepresentation(use_cdrv0_representation=True)]
    if user_data:
        policies.append(Policy.Userdata(data=user_data))
    return Qos(*policies)


@dataclass
class Sample:
    """One received message: raw CDR (with its 4-byte encapsulation header) and when it came."""

    payload: bytes
    received_s: float  # when it arrived (wall clock, time.time): `arrival`
    source_s: float  # the writer's source timestamp (s since the epoch)


def arrival(taken_s: float, source_s: float) -> float:
    """When a sample arrived: the writer's source time, when it lies at most MAX_QUEUED_S before
    the take (the same clock: one host, or hosts in time sync), else the take. A sample that waited
    in the reader's queue while the mapper was busy then counts as late as it is, and the stream
    drops a colour image more than --max-lag behind, as map-bag does."""
    return source_s if 0.0 <= taken_s - source_s <= MAX_QUEUED_S else taken_s


class Writer:
    """A ROS 2 publisher: `write(payload)` sends serialised CDR as is."""

    def __init__(self, participant: Participant, topic: str, msgtype: str, kind: QosKind) -> None:
        from cyclonedds.pub import DataWriter

        self.topic, self.msgtype, self.kind = topic, msgtype, kind
        t, qos = participant.endpoint(topic, msgtype, kind)
        self._writer = DataWriter(participant.dp, t, qos=qos)

    def write(self, payload: bytes) -> None:
        from cyclonedds._clayer import ddspy_write
        from cyclonedds.core import DDSException

        data = bytes(payload)
        data = data.ljust((len(data) + 3) & ~3, b"\0")  # samples are 4-byte padded, as cyclonedds' own write
        ret = ddspy_write(self._writer._ref, data)
        if ret < 0:
            raise DDSException(ret, f"writing {self.topic}")

    def wait_for_acks(self, timeout_s: float) -> bool:
        """True when every matched reliable reader acknowledged what was written (within timeout_s)."""
        from cyclonedds.core import DDSException

        # dds_wait_for_acks itself: cyclonedds 11.0.1's DataWriter.wait_for_acks raises AttributeError
        # on a timeout (it compares against a constant its base Exception does not have)
        ret = self._writer._wait_for_acks(self._writer._ref, int(timeout_s * 1e9))
        if ret == DDSException.DDS_RETCODE_TIMEOUT:  # a reader that left or lags; the map stays latched
            return False
        if ret < 0:
            raise DDSException(ret, f"waiting for the readers of {self.topic}")
        return True


class Reader:
    """A ROS 2 subscription: `take()` returns the samples received since the last take."""

    def __init__(self, participant: Participant, topic: str, msgtype: str, kind: QosKind) -> None:
        from cyclonedds.sub import DataReader

        self.topic, self.msgtype, self.kind = topic, msgtype, kind
        t, qos = participant.endpoint(topic, msgtype, kind)
        self._reader = DataReader(participant.dp, t, qos=qos)

    def take(self, n: int = 1000) -> list[Sample]:
        from cyclonedds._clayer import ddspy_take
        from cyclonedds.core import DDSException, InstanceState, SampleState, ViewState

        got = ddspy_take(self._reader._ref, SampleState.Any | ViewState.Any | InstanceState.Any, n)
        if isinstance(got, int):
            raise DDSException(got, f"taking {self.topic}")
        now = time.time()
        return [Sample(data, arrival(now, info.source_timestamp * 1e-9), info.source_timestamp * 1e-9)
                for data, info in got if info.valid_data]


class Participant:
    """A ROS 2 participant on a domain; its topics, readers, writers and the graph's publishers."""

    def __init__(self, distro: str, domain: int | None = None, loopback: bool = False) -> None:
        require_dds()
        from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication
        from cyclonedds.domain import Domain, DomainParticipant

        from virus_nerf.ros2 import types

        types.typestore(distro)  # the one-line refusal of an unknown distro, before joining
        self.distro, self.domain_id = distro, domain_id(domain)
        # a Domain made with a configuration is the one the participants of this process join (made once)
        if loopback and self.domain_id not in _LOOPBACK_DOMAINS:
            _LOOPBACK_DOMAINS[self.domain_id] = Domain(self.domain_id, LOOPBACK_CONFIG)
        self.dp = DomainParticipant(self.domain_id)
        self._topics: dict[str, object] = {}
        self._entities: list = []  # readers and writers, deleted before the participant
        self._readers: list = []  # the node's (announce_node)
        self._writers: list = []
        self.node: tuple[str, str] | None = None  # (name, namespace) once announced
        self._publications = BuiltinDataReader(self.dp, BuiltinTopicDcpsPublication)
        self._own = {self.dp.guid}
        self.offered: dict[str, object] = {}  # ROS topic -> the QoS its newest remote writer offers
        self._remote: dict[bytes, tuple[str, str]] = {}  # a remote writer's 16-byte GUID -> (ROS topic, type)

    def endpoint(self, name: str, msgtype: str, kind: QosKind):
        """(the DDS topic of ROS topic `name`, made once, and the QoS of profile `kind` with the
        type's user data) for a reader or a writer."""
        from cyclonedds.topic import Topic

        from virus_nerf.ros2 import types

        qos = _qos(kind, types.user_data(self.distro, msgtype))
        key = f"{name} {msgtype}"
        if key not in self._topics:
            self._topics[key] = Topic(self.dp, dds_topic(name), types.idl_struct(self.distro, msgtype), qos=qos)
        return self._topics[key], qos

    def writer(self, topic: str, msgtype: str, kind: QosKind) -> Writer:
        w = Writer(self, topic, msgtype, kind)
        self._entities.append(w._writer)
        self._writers.append(w._writer)
        self._announce()
        return w

    def reader(self, topic: str, msgtype: str, kind: QosKind) -> Reader:
        r = Reader(self, topic, msgtype, kind)
        self._entities.append(r._reader)
        self._readers.append(r._reader)
        self._announce()
        return r

    # ------------------------------------------------------------------ the ROS graph
    def gid(self, entity) -> bytes:
        """The rmw GID of a DDS entity: its 16-byte GUID (zero-padded to Humble's 24 bytes)."""
        size = 24 if self.distro == "humble" else 16
        return entity.guid.bytes.ljust(size, b"\0")

    def announce_node(self, name: str, namespace: str = "/") -> None:
        """Be a ROS node on the graph: rmw_dds_common's ParticipantEntitiesInfo on
        `ros_discovery_info` (reliable, transient local, keep last 1), naming this participant's
        readers and writers under node `name` in `namespace`, as rmw_cyclonedds does; `ros2 node
        list` and `ros2 topic info -v` read it. Sent again whenever a reader or writer is made."""
        self.node = (name, "/" + namespace.strip("/"))
        self._discovery_writer = Writer(self, DISCOVERY_TOPIC, ENTITIES_INFO, LATCHED)
        self._entities.append(self._discovery_writer._writer)
        self._announce()

    def _announce(self) -> None:
        if self.node is None:
            return
        import numpy as np

        from virus_nerf.ros2 import types

        store = types.typestore(self.distro)
        t = store.types

        def gid(entity):
            return t["rmw_dds_common/msg/Gid"](data=np.frombuffer(self.gid(entity), dtype=np.uint8).copy())

        node = t["rmw_dds_common/msg/NodeEntitiesInfo"](
            node_namespace=self.node[1], node_name=self.node[0], reader_gid_seq=[gid(r) for r in self._readers],
            writer_gid_seq=[gid(w) for w in self._writers])
        info = t[ENTITIES_INFO](gid=gid(self.dp), node_entities_info_seq=[node])
        self._discovery_writer.write(types.serialize(info, ENTITIES_INFO, store))

    def discover(self) -> dict[str, set[str]]:
        """The publishers on the graph now (other participants'), ROS topic -> message types. A
        writer that has left (its discovery sample no longer alive: a `ros2-play` that ended, a
        node that stopped) is forgotten, and its topic with it when it was the last one: nothing
        is subscribed to, or said to be, on the word of a publisher that is gone."""
        from cyclonedds.core import InstanceState

        from virus_nerf.ros2 import types

        for ep in self._publications.take(256):
            info = getattr(ep, "sample_info", None)
            if info is not None and info.instance_state != InstanceState.Alive:
                self._forget(ep.key.bytes)  # the key alone (no topic) once the writer was seen alive
                continue
            if not getattr(ep, "topic_name", None) or ep.participant_key in self._own:
                continue
            if not ep.topic_name.startswith(ROS_TOPIC_PREFIX + "/"):
                continue
            msgtype = types.ros_type_name(ep.type_name)
            if msgtype is None:
                continue
            topic = ep.topic_name[len(ROS_TOPIC_PREFIX):]
            self.offered[topic] = ep.qos
            self._remote[ep.key.bytes] = (topic, msgtype)
        return self.publishers

    @property
    def publishers(self) -> dict[str, set[str]]:
        """ROS topic -> the ROS message types of its remote writers on the graph."""
        out: dict[str, set[str]] = {}
        for topic, msgtype in self._remote.values():
            out.setdefault(topic, set()).add(msgtype)
        return out

    @property
    def writer_gids(self) -> dict[str, set[bytes]]:
        """ROS topic -> its remote writers' 16-byte GUIDs."""
        out: dict[str, set[bytes]] = {}
        for gid, (topic, _) in self._remote.items():
            out.setdefault(topic, set()).add(gid)
        return out

    def _forget(self, gid: bytes) -> None:
        """A remote writer that left; its topic's offered QoS goes with the topic's last writer."""
        topic, _ = self._remote.pop(gid, (None, None))
        if topic is not None and topic not in self.publishers:
            self.offered.pop(topic, None)

    def close(self) -> None:
        """Leave the graph now: readers and writers, topics, then the participant deleted (cyclonedds
        deletes an entity when its Python object is collected; a node's peers should not wait)."""
        if self.dp is None:
            return
        for entity in [*reversed(self._entities), self._publications, *self._topics.values(), self.dp]:
            entity.__del__()  # dds_delete, once (cyclonedds forgets the entity)
        self._entities.clear()
        self._topics.clear()
        self.dp = None
