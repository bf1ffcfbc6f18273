"""Robot-to-world poses as their messages arrive, for the stream's frame pairing (live.py).

One class a kind of source: /tf and /tf_static (`TfPoses`), nav_msgs/Odometry (`OdometryPoses`),
KISS-ICP over each LiDAR scan in its worker process (`KissPoses`), a CSV or TUM file
(`CsvPoses`). Each takes its messages one by one (`add`) and answers the pose at a time (`at`),
interpolated as the importer interpolates (odometry.PoseTrack); `make_pose_source` makes the one
`--poses` names.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from virus_nerf.data.bags import messages as m
from virus_nerf.data.bags.odometry import (
    KissIcpSettings,
    PoseTrack,
    ScanRegistration,
    Transform,
    tf_track,
)
from virus_nerf.data.bags.reader import Message
from virus_nerf.data.bags.topics import LidarConfig, TopicsConfig
from virus_nerf.errors import DataFormatError, UsageError


class PoseSource:
    """Robot-to-world poses as their messages arrive. Subclasses feed `add`; `at` interpolates."""

    describe = "poses"
    role = "tf"  # the messages.ACCEPTED role of its topics (what a live subscriber accepts on them)
    topics: tuple[str, ...] = ()

    def add(self, topic: str, msg: Message) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def newest_s(self) -> float:
        """Stamp of the newest pose known (-inf: none yet)."""
        raise NotImplementedError

    def decided(self, t: float, tolerance_s: float, clock_s: float) -> bool:
        return self.newest_s() >= t or clock_s > t + tolerance_s

    def at(self, t: float, tolerance_s: float) -> np.ndarray | None:
        raise NotImplementedError

    def prune(self, before_s: float) -> None:
        """Forget poses no waiting or future frame can use (keeps one before `before_s`)."""

    def problem(self) -> str:
        """Why there is no pose yet, for the error when none comes (empty: no known reason)."""
        return ""

    def restart(self) -> None:
        """Forget the poses received (live: the clock went back, a bag played again)."""

    def close(self) -> None:
        """Release what the source holds (a worker process); the stream calls it at its end."""


class TrackPoses(PoseSource):
    """A pose track that grows message by message (KISS-ICP, odometry); interpolated as PoseTrack."""

    def __init__(self) -> None:
        self.times: list[float] = []
        self.poses: list[np.ndarray] = []

    def append(self, t: float, pose: np.ndarray) -> None:
        if self.times and t <= self.times[-1]:
            return  # a repeated stamp: the first pose stands (times must increase for the slerp)
        self.times.append(t)
        self.poses.append(pose)

    def newest_s(self) -> float:
        return self.times[-1] if self.times else -math.inf

    def at(self, t: float, tolerance_s: float) -> np.ndarray | None:
        if not self.times:
            return None
        pose, ok = PoseTrack(np.array(self.times), np.stack(self.poses)).at(np.array([t]), tolerance_s)
        return pose[0] if ok[0] else None

    def prune(self, before_s: float) -> None:
        k = int(np.searchsorted(self.times, before_s)) - 1  # the last pose before: an interpolation end
        if k > 0:
            del self.times[:k], self.poses[:k]

    def restart(self) -> None:
        self.times.clear()
        self.poses.clear()


class CsvPoses(PoseSource):
    """A whole pose file (read before the drive): every pose is known at once."""

    def __init__(self, track: PoseTrack, path: Path) -> None:
        self.track, self.describe = track, f"--poses-file {path}"

    def newest_s(self) -> float:
        return float(self.track.times_s[-1])

    def decided(self, t: float, tolerance_s: float, clock_s: float) -> bool:
        return True

    def at(self, t: float, tolerance_s: float) -> np.ndarray | None:
        pose, ok = self.track.at(np.array([t]), tolerance_s)
        return pose[0] if ok[0] else None


class OdometryPoses(TrackPoses):
    """nav_msgs/Odometry on one topic (a robot without LiDAR: its wheel odometry)."""

    role = "odometry"

    def __init__(self, topic: str, bag: Path) -> None:
        super().__init__()
        self.topics, self.describe, self.bag = (topic,), f"odometry {topic}", bag

    def add(self, topic: str, msg: Message) -> None:
        self.append(msg.time_s, m.decode_odometry(msg.msg, m.Where(self.bag, topic, msg.index)))


class KissPoses(TrackPoses):
    """KISS-ICP registering each LiDAR scan as it arrives (kiss_icp.KissICP.register_frame), with
    the importer's range filter and float32 points, so the poses are those of its first pass.

    With `worker` (default) the registration runs in a process of its own (kiss_worker.py): the
    scan is decoded and filtered here, sent, and its pose collected when a frame needs it, so
    the mapper trains while the scan registers. A frame waits for a pose whose scan is still being
    registered; at the end of the bag every pending pose is collected.

    keep_up (a stream in real time: map-bag, the ROS 2 node): the worker registers the newest scan
    it has and skips the older ones waiting (kiss_worker.py), so the poses keep up with the LiDAR
    on a machine too slow to register every scan; `skipped` counts them. A frame still waits for
    the first pose at or after its stamp. Without it every scan is registered (the importer's poses)."""

    role = "lidar"

    def __init__(self, topic: str, lidar: LidarConfig, settings: KissIcpSettings | None, bag: Path,
                 worker: bool = True, keep_up: bool = False) -> None:
        from virus_nerf.data.bags.kiss_worker import KissWorker

        super().__init__()
        self.topics, self.describe, self.bag = (topic,), f"KISS-ICP on {topic}", bag
        self.lidar, self.settings = lidar, lidar.kiss_settings(settings)
        if keep_up and not worker:
            raise ValueError("keep_up needs the worker process (the scans must queue somewhere)")
        self.worker = KissWorker(self.settings, keep_up) if worker else None
        self.registration = None if self.worker is not None else ScanRegistration(self.settings)
        self.last_sent = -math.inf
        self._skipped = 0  # by workers closed
        self._floor: dict | None = None  # kept from a worker closed

    def add(self, topic: str, msg: Message) -> None:
        where = m.Where(self.bag, topic, msg.index)  # the importer's scan (float32, as its PCD holds it)
        pts = m.decode_scan(msg.msg, where, self.lidar.min_range_m, self.lidar.max_range_m).astype(np.float64)
        if msg.time_s <= self.last_sent:
            return  # a repeated stamp (the importer keeps one scan per stamp)
        self.last_sent = msg.time_s
        if self.worker is None:
            self.append(msg.time_s, self.registration.register(msg.time_s, pts))
            return
        self.worker.send(msg.time_s, pts)  # float32-exact values: the worker casts back to float64
        self._collect()

    def _collect(self, block: bool = False) -> None:
        if self.worker is None:
            return
        try:
            done = self.worker.poll(block)
        except RuntimeError as exc:  # the stream stops with its map of the frames so far (StreamRun)
            raise DataFormatError(self.bag, f"{self.describe}: {exc}") from None
        for t, pose in done:
            self.append(t, pose)

    @property
    def floor(self) -> dict | None:
        """The first registered scan's floor (odometry.ScanRegistration.describe); None before it."""
        if self.worker is not None:
            return self.worker.floor
        if self.registration is not None and self.registration.started:
            return self.registration.describe()
        return self._floor

    @property
    def skipped(self) -> int:
        """Scans not registered to keep up (keep_up)."""
        return self._skipped + (self.worker.skipped if self.worker is not None else 0)

    def newest_s(self) -> float:
        """Stamp of the newest scan received (its pose may still be registering): the source has
        not stopped while scans come."""
        return max(super().newest_s(), self.last_sent)

    def decided(self, t: float, tolerance_s: float, clock_s: float) -> bool:
        self._collect()
        if TrackPoses.newest_s(self) >= t:
            return True
        if self.worker is not None and self.worker.pending:
            if self.worker.pending[-1] >= t and clock_s != math.inf:
                return False  # the pose at or after `t` is being registered: the frame waits for it
            if clock_s > t + tolerance_s:
                self._collect(block=True)  # every pose up to the clock, then decide as without a worker
                return True
            return False
        return clock_s > t + tolerance_s

    def at(self, t: float, tolerance_s: float) -> np.ndarray | None:
        self._collect()
        return super().at(t, tolerance_s)

    def restart(self) -> None:
        super().restart()
        self.last_sent = -math.inf  # scans registered from here on continue KISS-ICP's map

    def close(self) -> None:
        if self.worker is not None:
            self.worker.close()
            self._skipped += self.worker.skipped
            self._floor = self.worker.floor
            self.worker = None


class TfPoses(PoseSource):
    """Frame `child` in frame `parent` from /tf and /tf_static as they arrive (odometry.tf_track
    over the transforms kept: the importer's composition and interpolation)."""

    def __init__(self, topics: tuple[str, ...], parent: str, child: str, bag: Path) -> None:
        self.topics, self.parent, self.child, self.bag = topics, parent, child, bag
        self.describe = f"tf {parent} -> {child} ({', '.join(topics)})"
        self.static: dict[str, Transform] = {}
        self.dynamic: dict[str, list[Transform]] = {}  # child frame -> its transforms, stamp order
        self._track: PoseTrack | None = None
        self._problem = f"no transform from {parent} to {child} yet"
        self._dirty = False

    def add(self, topic: str, msg: Message) -> None:
        static = "static" in topic
        for item in m.decode_tf(msg.msg, m.Where(self.bag, topic, msg.index), static):
            if static:
                self.static[item.child] = item
            else:
                links = self.dynamic.setdefault(item.child, [])
                if not links or item.time_s > links[-1].time_s:
                    links.append(item)
        self._dirty = True

    def track(self) -> PoseTrack | None:
        if self._dirty:
            self._dirty = False
            items = list(self.static.values()) + [tr for links in self.dynamic.values() for tr in links]
            try:
                self._track = tf_track(items, self.parent, self.child, str(self.bag))
            except DataFormatError as exc:  # the chain is not complete yet (or never will be)
                self._track, self._problem = None, exc.problem
        return self._track

    def _chain_newest(self) -> float:
        """The newest stamp at which every dynamic link of the chain is known."""
        newest, f = math.inf, self.child
        while f != self.parent:
            if f in self.dynamic:
                newest = min(newest, self.dynamic[f][-1].time_s)
                f = self.dynamic[f][-1].parent
            elif f in self.static:
                f = self.static[f].parent
            else:
                return -math.inf
        return newest

    def newest_s(self) -> float:
        return -math.inf if self.track() is None else self._chain_newest()

    def at(self, t: float, tolerance_s: float) -> np.ndarray | None:
        track = self.track()
        if track is None:
            return None
        pose, ok = track.at(np.array([t]), tolerance_s)
        return pose[0] if ok[0] else None

    def prune(self, before_s: float) -> None:
        for links in self.dynamic.values():
            k = next((i for i, tr in enumerate(links) if tr.time_s >= before_s), len(links)) - 1
            if k > 0:
                del links[:k]
                self._dirty = True

    def problem(self) -> str:
        return "" if self.track() is not None else self._problem

    def restart(self) -> None:
        self.dynamic.clear()  # the static transforms hold
        self._dirty = True


# ------------------------------------------------------------------------------- the frames


def check_pose_flags(poses: str, poses_file: str | Path | None) -> None:
    """--poses csv and --poses-file go together: one without the other is refused in one line (a
    pose file given with another --poses was ignored, silently)."""
    if poses == "csv" and poses_file is None:
        raise UsageError("--poses csv needs --poses-file FILE (time,x,y,z,qx,qy,qz,qw or TUM)")
    if poses != "csv" and poses_file is not None:
        raise UsageError(f"--poses-file {poses_file}: read only with --poses csv (given --poses {poses}); add "
                         "--poses csv, or leave --poses-file out")


def make_pose_source(poses: str, cfg: TopicsConfig, bag: Path, *, present: Callable[[str], bool],
                     poses_file: Path | None = None, tf_parent: str = "odom", tf_child: str | None = None,
                     odometry_topic: str = "/odom", kiss: KissIcpSettings | None = None,
                     keep_up: bool = False) -> PoseSource:
    """The pose source of `--poses` (lidar-odometry, tf, csv, odometry); present(topic): is it in the
    bag; keep_up: a stream in real time (KissPoses)."""
    if poses == "lidar-odometry":
        return KissPoses(cfg.lidar.topic, cfg.lidar, kiss, bag, keep_up=keep_up)
    if poses == "odometry":
        return OdometryPoses(odometry_topic, bag)
    if poses == "csv":
        from virus_nerf.data.bags.odometry import csv_track

        return CsvPoses(csv_track(poses_file), Path(poses_file))
    topics = tuple(t for t in cfg.tf_topics if present(t))
    return TfPoses(topics, tf_parent, tf_child, bag)
