"""A bag's messages -> synchronised frames, one message at a time (streaming `map-bag`, issue 29).

The importer (importer.py, stages.py) matches every colour frame against the whole bag; a robot
cannot wait for the whole drive. `LiveSync` gets the messages in the order they were recorded and
keeps only what the next frames can still use:

- the newest USS, IRS (TOF) and depth messages of each stack (`Recent`), back to the oldest
  colour image still waiting minus the sync tolerance of that sensor;
- the colour images still waiting for their partners (a few per stack);
- the poses of the pose source (poses.py `PoseSource`: /tf, KISS-ICP over each LiDAR scan,
  nav_msgs Odometry, or a CSV/TUM file), back to the oldest waiting image.

A colour image becomes a frame as soon as each partner is *decided*: the partner topic has sent a
message stamped at or after the image (no later message can be nearer), or the stream's clock (the
newest stamp seen) has passed the image by that sensor's tolerance (nothing within the tolerance
can still come). Its pose likewise: a pose at or after the image exists (then it is interpolated as
the importer interpolates), or the clock passed the image by sync.pose_tolerance_s (then the newest
pose serves if it lies within the tolerance). With the same tolerances and the same nearest-stamp
rule (ties to the earlier stamp) the frames are the importer's; the differences are the ends of a
pose track (a pose that arrives later than the tolerance does not count) and KISS-ICP's start,
which the importer re-registers against the following seconds (odometry.py `refine_start_s`) and a
stream cannot.

Bad data stops the stream with a `StreamError` (one line naming the topic and the bag time): a
stamp older than its topic's previous one, a watched topic silent for `max_silence_s`, a gap of
`max_silence_s` in every topic (the bag's clock jumps forward: said as such), or the robot
moving more than `max_jump_m` between consecutive frames (at most JUMP_WINDOW_S apart).

Live (the ROS 2 node, `on_problem` given) a robot's data cannot be refused and the map must go on:
each of these is one line to `on_problem` (repeats of a kind within PROBLEM_REPEAT_S counted, not
said) and the stream goes on: a malformed message is skipped; a message older than its topic's
previous one is skipped, or, more than RESTART_BACK_S back (a bag played again, a robot's clock
reset), starts the synchronisation again (the sensor buffers and poses are forgotten, the images
waiting for them dropped and counted; the map keeps every frame made); a silent topic or pose
source is said once and said again when it is back. Meanwhile a silent USS, ToF or depth topic's frames are made without it
(NaN: no measurement, as for a stack without that sensor; counted in `without`), while a silent
pose source drops the frames (no pose); a frame whose pose jumps is dropped and the next frames
are compared with it.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from virus_nerf.data.bags import messages as m
from virus_nerf.data.bags.poses import PoseSource
from virus_nerf.data.bags.reader import Message
from virus_nerf.data.bags.sync import match_nearest
from virus_nerf.data.bags.topics import TopicsConfig
from virus_nerf.data.ethz import MAX_JUMP_M
from virus_nerf.data.frame import SyncFrame
from virus_nerf.errors import DataFormatError
from virus_nerf.sensors.camera import Intrinsics

LATE = "late (the mapper was behind)"  # the drop reason of a colour image released past max_lag
# MAX_JUMP_M (data/ethz.py): the robot moving further between two consecutive frames is a broken pose source
JUMP_WINDOW_S = 1.0  # ... when they are at most this far apart in time
MAX_SILENCE_S = 2.0  # a watched topic silent this long (bag time) has stopped
PARTNERS = ("depth", "uss", "tof")
RESTART_BACK_S = 1.0  # live: a topic's clock this far back is a restart, not a message out of order
PROBLEM_REPEAT_S = 10.0  # live: the same problem said at most once per this many wall seconds  # the importer's order: a dropped frame counts its first missing partner


class StreamError(DataFormatError):
    """Bad data met while streaming; `at_s`: where (seconds since the bag's first message)."""

    def __init__(self, bag: Path, problem: str, at_s: float, field: str | None = None) -> None:
        super().__init__(bag, problem, field=field)
        self.at_s = at_s


@dataclass(frozen=True)
class StreamFrame:
    """A frame for the mapper and the robot's (LiDAR / odometry frame) pose it came from."""

    frame: SyncFrame
    robot_to_world: np.ndarray  # (4, 4)


class Recent:
    """Stamped values of one topic, oldest first, within the window the waiting frames need."""

    def __init__(self) -> None:
        self.items: deque[tuple[float, object]] = deque()

    @property
    def newest_s(self) -> float:
        return self.items[-1][0] if self.items else -math.inf

    def add(self, t: float, value) -> None:
        self.items.append((t, value))

    def decided(self, t: float, tolerance_s: float, clock_s: float) -> bool:
        """No message still to come can be nearer to `t` within the tolerance than those here."""
        return self.newest_s >= t or clock_s > t + tolerance_s

    def nearest(self, t: float, tolerance_s: float):
        """The value stamped nearest to `t` within the tolerance, or None: the importer's rule
        (sync.match_nearest; ties to the earlier stamp)."""
        if not self.items:
            return None
        k = int(match_nearest(np.array([t]), np.array([ti for ti, _ in self.items]), tolerance_s)[0])
        return None if k < 0 else self.items[k][1]

    def prune(self, before_s: float) -> None:
        while self.items and self.items[0][0] < before_s:
            self.items.popleft()


class LiveSync:
    """Messages in, frames out (module doc). `push` each message in bag order, `finish` at the end.

    cfg: the topics file (stacks, sync tolerances, camera mounting); intrinsics: stacks whose
    intrinsics come from the topics file's CSV (the others from their first camera_info);
    with_depth: decode the depth image of each frame (the rgbd sensor)."""

    def __init__(self, cfg: TopicsConfig, poses: PoseSource, bag: Path, *, intrinsics: dict[int, Intrinsics] | None = None,
                 with_depth: bool = False, max_silence_s: float = MAX_SILENCE_S, max_jump_m: float = MAX_JUMP_M,
                 on_problem: Callable[[str], None] | None = None) -> None:
        self.cfg, self.poses, self.bag, self.with_depth = cfg, poses, Path(bag), with_depth
        self.on_problem = on_problem  # live: problems are said and the stream goes on (module doc)
        self.problems: Counter = Counter()  # live: kind -> times met
        self._said: dict[str, tuple[float, int]] = {}  # kind -> (wall time said, repeats since)
        self.silent: dict[str, float] = {}  # live: topic (or "poses") -> its last stamp when found silent
        self.restarts = 0  # live: times the clock went back (restart)
        self.max_silence_s, self.max_jump_m = max_silence_s, max_jump_m
        self.intrinsics: dict[int, Intrinsics] = dict(intrinsics or {})
        self.mount = {s: st.camera_in_lidar() for s, st in cfg.stacks.items()}
        sync = cfg.sync
        self.tolerance = {"depth": sync.depth_tolerance_s, "uss": sync.uss_tolerance_s, "tof": sync.tof_tolerance_s}
        self.roles: dict[str, list[tuple[int, str]]] = {}
        for s, st in cfg.stacks.items():
            for role, topic in st.roles().items():
                self.roles.setdefault(topic, []).append((s, role))
        self.buffers = {(s, r): Recent() for s, st in cfg.stacks.items() for r in PARTNERS if r in st.roles()}
        self.tof_units = m.TofUnitCheck()  # a ToF topic in metres, over its messages
        self.waiting: dict[int, deque[Message]] = {s: deque() for s in cfg.stacks}
        self.watched = {t for t, keys in self.roles.items() if any(r != "camera_info" for _, r in keys)}
        self.last_kept = dict.fromkeys(cfg.stacks, -math.inf)  # camera_rate_hz thinning
        self.last_color = dict.fromkeys(cfg.stacks, -math.inf)
        self.first_color: dict[int, float] = {}  # the first colour stamp (since a restart), for the intrinsics' wait
        self.last_stamp: dict[str, float] = {}
        self.t0: float | None = None  # the first stamp: bag times in messages count from here
        self.clock = -math.inf  # the newest stamp seen
        self.resumed_at = -math.inf  # live: where the clock went on after every topic was quiet (`_check_gap`)
        self.dropped: dict[int, Counter] = {s: Counter() for s in cfg.stacks}
        self.without: dict[int, Counter] = {s: Counter() for s in cfg.stacks}  # live: role -> frames made without it
        self.made = 0
        self.last_frame: tuple[float, np.ndarray] | None = None  # (time, robot pose) for the jump check
        self.error: StreamError | None = None  # met while releasing frames: raised at the next message

    # ------------------------------------------------------------------ input
    def topics(self) -> list[str]:
        """Every topic to read, stacks first, then the pose source's."""
        return list(self.roles) + [t for t in self.poses.topics if t not in self.roles]

    def is_color(self, topic: str) -> bool:
        return any(r == "color" for _, r in self.roles.get(topic, ()))

    def rel(self, t: float) -> float:
        """Seconds since the bag's first message."""
        return t - (self.t0 if self.t0 is not None else t)

    def push(self, topic: str, msg: Message, late: bool = False) -> list[StreamFrame]:
        """One message; the frames it completes, in time order. late: a colour image the mapper
        is too far behind to use (counted as dropped, never decoded)."""
        if self.error is not None:
            raise self.error
        t = msg.time_s
        if "static" in topic:
            # timeless: static transforms start no clock and move none. A late joiner gets old ones
            # (transient local); a bag's are often stamped 0, or on the recorder's clock where the
            # robot's is sim time
            with self._at(msg, topic):
                self.poses.add(topic, msg)
            return self._release() if self.t0 is not None else []
        if self.t0 is None:
            self.t0 = t
        if not self._check_clock(topic, msg):
            return []  # live: skipped
        self._check_gap(topic, msg)
        self.clock = max(self.clock, t)
        with self._at(msg, topic):
            if topic in self.poses.topics:
                self.poses.add(topic, msg)
            for s, role in self.roles.get(topic, ()):
                where = m.Where(self.bag, topic, msg.index)
                if role == "color":
                    self._color(s, msg, late)
                elif role == "camera_info":
                    if s not in self.intrinsics:
                        self.intrinsics[s] = m.decode_camera_info(msg.msg, where).intrinsics
                elif role == "uss":
                    self.buffers[(s, role)].add(t, m.decode_uss(msg.msg, msg.msgtype, where).range_m)
                elif role == "tof":
                    reading = m.decode_tof(msg.msg, where)
                    self.tof_units.add(reading, where)
                    self.buffers[(s, role)].add(t, reading.grid_m())
                else:  # depth: decoded only if the frame is made and wants it
                    self.buffers[(s, role)].add(t, msg)
        if self.silent:
            self._back()
        self._check_silence()
        return self._release()

    def finish(self) -> list[StreamFrame]:
        """The bag has ended: every waiting image is decided with what came."""
        if self.error is not None:
            raise self.error
        self.clock = math.inf
        return self._release()

    @contextmanager
    def _at(self, msg: Message, topic: str = ""):
        """A message the decoders refuse (data/bags/messages.py: the importer's checks and words) stops
        the stream as a StreamError at that message's bag time; live it is skipped, said once."""
        try:
            yield
        except m.MessageError as exc:
            error = StreamError(self.bag, exc.problem, self.rel(msg.time_s), field=exc.field)
            if self.on_problem is None:
                raise error from None
            self._problem(f"malformed {topic}", f"{error}; the message is skipped")

    # ------------------------------------------------------------------ live problems
    def _problem(self, kind: str, line: str) -> None:
        """Live: say `line` unless `kind` was said in the last PROBLEM_REPEAT_S (then count it)."""
        import time

        self.problems[kind] += 1
        now = time.monotonic()
        said, repeats = self._said.get(kind, (-math.inf, 0))
        if now - said < PROBLEM_REPEAT_S:
            self._said[kind] = (said, repeats + 1)
            return
        more = f" ({repeats} more like it since it was last said)" if repeats else ""
        self._said[kind] = (now, 0)
        self.on_problem(line + more)

    def _back(self) -> None:
        """Live: a topic (or the pose source) found silent has spoken again."""
        for key, last in list(self.silent.items()):
            newest = self.poses.newest_s() if key == "poses" else self.last_stamp.get(key, -math.inf)
            if newest > last:
                del self.silent[key]
                gap = f" after {newest - last:.1f} s" if last > -math.inf else ""
                self.on_problem(f"{'the pose source' if key == 'poses' else 'topic ' + key} is back at bag time "
                                f"{self.rel(newest):.3f} s{gap}")

    def restart(self, t: float) -> None:
        """Live: the clock went back to `t` (a bag played again, a clock reset): the synchronisation
        starts again; the frames already made stay in the map. `restarts` counts them (the stream
        re-anchors its lag clock)."""
        self.restarts += 1
        for s, q in self.waiting.items():  # images of the old clock, never to be completed: counted
            self.dropped[s]["before a clock restart"] += len(q)
            q.clear()
        for buf in self.buffers.values():
            buf.items.clear()
        self.poses.restart()
        self.last_stamp.clear()
        self.silent.clear()
        self.last_kept = dict.fromkeys(self.cfg.stacks, -math.inf)
        self.last_color = dict.fromkeys(self.cfg.stacks, -math.inf)
        self.first_color.clear()
        self.clock, self.last_frame, self.resumed_at = t, None, -math.inf

    def _color(self, s: int, msg: Message, late: bool) -> None:
        t = msg.time_s
        self.last_color[s] = t
        self.first_color.setdefault(s, t)
        if t == self.last_kept[s]:  # a driver that publishes a frame twice: the first is the sample
            self.dropped[s]["repeated stamp"] += 1
            return
        rate = self.cfg.sync.camera_rate_hz
        if rate > 0 and t - self.last_kept[s] < 1.0 / rate - 1e-6:
            self.dropped[s]["thinned to camera_rate_hz"] += 1
            return
        self.last_kept[s] = t
        if late:
            self.dropped[s][LATE] += 1
        else:
            self.waiting[s].append(msg)

    # ------------------------------------------------------------------ checks
    def _check_clock(self, topic: str, msg: Message) -> bool:
        """False: live, the message is skipped (out of order)."""
        prev = self.last_stamp.get(topic)
        if prev is not None and msg.time_s < prev and "static" not in topic:
            error = StreamError(self.bag, f"topic {topic}: the clock went backwards: message {msg.index + 1} is "
                                f"stamped at {self.rel(msg.time_s):.3f} s, {prev - msg.time_s:.3f} s before the "
                                f"previous one at {self.rel(prev):.3f} s (seconds since the bag's first message)",
                                self.rel(prev))
            if self.on_problem is None:
                raise error
            if prev - msg.time_s <= RESTART_BACK_S:
                self._problem(f"order {topic}", f"{error}; the message is skipped")
                return False
            self._problem("restart", f"{error}; taken as a restart (a bag played again, a clock reset): "
                          "the synchronisation starts again, the map keeps its frames")
            self.restart(msg.time_s)
        self.last_stamp[topic] = msg.time_s
        return True

    def _check_gap(self, topic: str, msg: Message) -> None:
        """A bag: no topic sent anything for more than max_silence_s of bag time (a clock jump, a
        recording paused) stops the stream, named as such rather than as every topic stopping.
        Live, the whole robot went quiet and goes on: its topics' silence counts from here (each
        gets max_silence_s to speak again), not from before the pause."""
        gap = msg.time_s - self.clock
        if self.clock == -math.inf or gap <= self.max_silence_s:
            return
        if self.on_problem is not None:
            self.resumed_at = msg.time_s
        else:
            raise StreamError(self.bag, f"the bag's clock jumps {gap:.3f} s forward: no topic sent anything between "
                              f"{self.rel(self.clock):.3f} s and {self.rel(msg.time_s):.3f} s (message "
                              f"{msg.index + 1} of {topic}; seconds since the bag's first message); a gap over "
                              f"{self.max_silence_s:g} s in every topic stops the stream", self.rel(self.clock))

    def _check_silence(self) -> None:
        """A watched topic (or the pose source) silent for max_silence_s of bag time has stopped."""
        limit = self.max_silence_s
        for topic in self.watched:
            last = self.last_stamp.get(topic)
            since = max(self.t0 if last is None else last, self.resumed_at)
            if self.clock - since > limit and topic not in self.silent:
                if last is not None and last < self.t0 - limit:  # its messages come, stamped long before the stream
                    problem = (f"topic {topic} is stamped on another clock: its newest message at {self.rel(last):.3f} s, "
                               f"the stream at {self.rel(self.clock):.3f} s (seconds since the bag's first message); "
                               "check the clocks")
                else:
                    what = "sent nothing" if last is None else f"stopped: its last message is at {self.rel(last):.3f} s"
                    problem = f"topic {topic} {what} and none came for {limit:g} s (bag time {self.rel(self.clock):.3f} s)"
                self._silent(topic, -math.inf if last is None else last,
                             StreamError(self.bag, problem, self.rel(self.clock)))
        for s, first in self.first_color.items():  # a camera's images came, its intrinsics did not
            topic = self.cfg.stacks[s].camera_info
            if (s not in self.intrinsics and topic and self.clock - max(first, self.resumed_at) > limit
                    and topic not in self.silent):
                last = self.last_stamp.get(topic)
                what = "sent nothing" if last is None else f"sent nothing usable since {self.rel(last):.3f} s"
                self._silent(topic, -math.inf if last is None else last, StreamError(
                    self.bag, f"topic {topic} {what} while stack {s}'s colour images came for {limit:g} s (bag "
                    f"time {self.rel(self.clock):.3f} s): its frames cannot be made without the camera's intrinsics",
                    self.rel(self.clock)), live="they are dropped until it comes")
        newest = self.poses.newest_s()
        if self.clock - max(newest, self.t0, self.resumed_at) > limit and "poses" not in self.silent:
            why = self.poses.problem()
            what = "no pose yet" if newest == -math.inf else f"the last pose is at {self.rel(newest):.3f} s"
            self._silent("poses", newest, StreamError(self.bag, f"{self.poses.describe}: {what} and none came for {limit:g} s "
                                              f"(bag time {self.rel(self.clock):.3f} s){': ' + why if why else ''}",
                                              self.rel(self.clock)))

    def _silent(self, key: str, last: float, error: StreamError,
                live: str = "mapping goes on without it") -> None:
        """A topic (or "poses") silent since stamp `last`: the stream stops, or live goes on (said,
        with what becomes of the frames)."""
        if self.on_problem is None:
            raise error
        self.silent[key] = last
        self.problems[f"silent {key}"] += 1
        self.on_problem(f"{error}; {live}")

    def _check_jump(self, f: StreamFrame) -> bool:
        """Consecutive frames at most JUMP_WINDOW_S apart (frames dropped while the mapper was
        behind leave gaps the robot may legitimately have driven a metre in)."""
        if self.last_frame is not None:
            t_prev, prev = self.last_frame
            d = float(np.linalg.norm(f.robot_to_world[:3, 3] - prev[:3, 3]))
            if d > self.max_jump_m and f.frame.time - t_prev <= JUMP_WINDOW_S:
                error = StreamError(self.bag, f"{self.poses.describe}: the pose jumps {d:.2f} m between the frames "
                                    f"at {self.rel(t_prev):.3f} s and {self.rel(f.frame.time):.3f} s; expected at most "
                                    f"{self.max_jump_m:g} m", self.rel(f.frame.time))
                self.last_frame = (f.frame.time, f.robot_to_world)  # live: the next frames are compared with it
                if self.on_problem is None:
                    raise error
                self._problem("jump", f"{error}; the frame is dropped")
                return False
        self.last_frame = (f.frame.time, f.robot_to_world)
        return True

    # ------------------------------------------------------------------ output
    def _release(self) -> list[StreamFrame]:
        out = []
        for s, queue in self.waiting.items():
            while queue and self._decided(s, queue[0].time_s):
                frame = self._make(s, queue.popleft())
                if frame is not None:
                    out.append(frame)
        out.sort(key=lambda f: (f.frame.time, f.frame.stack_id))
        kept = []
        for f in out:
            try:
                if self._check_jump(f):
                    kept.append(f)
                else:
                    self.dropped[f.frame.stack_id]["pose jump"] += 1
            except StreamError as exc:  # the frames before the jump still reach the map
                self.error = exc
                break
        out = kept
        self.made += len(out)
        self._prune()
        return out

    def _decided(self, s: int, t: float) -> bool:
        roles = self.cfg.stacks[s].roles()
        tol = self.cfg.sync.pose_tolerance_s
        if s not in self.intrinsics and self.clock <= t + max([tol, *self.tolerance.values()]):
            return False  # its camera_info follows the image: wait as long as for any partner
        return (all(self.buffers[(s, r)].decided(t, self.tolerance[r], self.clock) for r in PARTNERS if r in roles)
                and self.poses.decided(t, tol, self.clock))

    def _make(self, s: int, msg: Message) -> StreamFrame | None:
        """The frame of colour image `msg`, or None (counted) when a partner or its pose is missing."""
        t, roles = msg.time_s, self.cfg.stacks[s].roles()
        partner = {}
        for r in PARTNERS:
            if r in roles:
                near = self.buffers[(s, r)].nearest(t, self.tolerance[r])
                if near is not None:
                    partner[r] = near
                elif roles[r] in self.silent:  # live: the sensor stopped; the frame goes on without it (NaN)
                    self.without[s][r] += 1
                else:
                    self.dropped[s][f"no {r} within {self.tolerance[r]:g} s"] += 1
                    return None
        robot = self.poses.at(t, self.cfg.sync.pose_tolerance_s)
        if robot is None:
            self.dropped[s]["no pose"] += 1
            return None
        if s not in self.intrinsics:
            self.dropped[s]["no camera_info"] += 1
            return None
        intr = self.intrinsics[s]
        rgb = depth = None
        with self._at(msg, self.cfg.stacks[s].color):
            where = m.Where(self.bag, self.cfg.stacks[s].color, msg.index)
            if (intr.width, intr.height) == (0, 0):  # the topics file's CSV gives no size: the images'
                from virus_nerf.data.ethz import sized_by_image

                rgb = m.decode_color(msg.msg, msg.msgtype, where)
                intr = self.intrinsics[s] = sized_by_image(intr, rgb.shape, self.cfg.intrinsics_csv or self.bag)
            else:
                rgb = m.decode_color(msg.msg, msg.msgtype, where, (intr.width, intr.height))
        if self.with_depth:
            depth = self._depth(s, partner.get("depth"), intr)
        if rgb is None or (self.with_depth and depth is None):  # live: a malformed image (said)
            self.dropped[s]["malformed"] += 1
            return None
        frame = SyncFrame(time=t, stack_id=s, rgb=rgb, cam_to_world=robot @ self.mount[s],
                          uss_range=partner.get("uss", math.nan),
                          irs_range=partner["tof"] if "tof" in partner else np.full((8, 8), np.nan), depth=depth)
        return StreamFrame(frame, robot)

    def _depth(self, s: int, msg: Message | None, intr: Intrinsics) -> np.ndarray | None:
        """(H, W) metres, NaN invalid (the importer's uint16 mm read back; all NaN without a depth topic);
        None: live, a malformed depth image (said)."""
        if msg is None:
            return np.full((intr.height, intr.width), np.nan, dtype=np.float32)
        with self._at(msg, self.cfg.stacks[s].depth):
            where = m.Where(self.bag, self.cfg.stacks[s].depth, msg.index)
            return m.decode_depth(msg.msg, msg.msgtype, where, (intr.width, intr.height)).metres()
        return None

    def _prune(self) -> None:
        """Keep what the waiting images and the next ones (stamped after the last seen) can use."""
        horizon = {s: q[0].time_s if q else self.last_color[s] for s, q in self.waiting.items()}
        for (s, r), buf in self.buffers.items():
            buf.prune(horizon[s] - self.tolerance[r] - 1e-9)
        self.poses.prune(min(horizon.values()) - self.cfg.sync.pose_tolerance_s)

    # ------------------------------------------------------------------ report
    def dropped_total(self) -> Counter:
        return sum(self.dropped.values(), Counter())

    def without_total(self) -> Counter:
        """Live: sensor role -> frames made without it while its topic was silent."""
        return sum(self.without.values(), Counter())
