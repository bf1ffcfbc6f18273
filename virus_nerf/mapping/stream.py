"""Streaming `map-bag`: the bag read message by message in recording order and mapped as it goes.

A wall clock, scaled by the playback speed, releases each message when it passes the message's
receive time in the bag (the order a robot gets them). Each released message goes to a
`data.bags.live.LiveSync`, which hands back the frames it completes (colour image + depth, USS,
IRS within their sync tolerances + pose); they go to the `Mapper` at once. The mapper trains while
the next message is not yet due; every `snapshot_every` seconds of wall time (the first after
`first_snapshot` s, delayed by no training step: a step can take seconds on a CPU, and the first
map shows that mapping runs) the map goes to OUT/snapshots/NNNN_<s>s/ with a progress line that
reports the lag: the scaled wall clock minus the recording time of the newest frame. Snapshots take
at most half the wall time (`next_snapshot_time`: one slower than its period puts the next further
off). A colour image released more than `max_lag` recording seconds after it was due is dropped
without being decoded (a robot cannot pause its sensors); the count is reported. The mapper is
made at the first frames, its scene box around the first frame, grown as the robot drives
(`initial_box`, docs/extent.md).

Bad data (`live.StreamError` and any `DataFormatError` of a message) stops the stream: the map made
so far is written to OUT/map/ as the final map, OUT/stream.json says where it stopped, and the
error is raised again (map-bag: exit code 2 with the one-line error). SIGINT and SIGTERM
(utils/stop.py `Stopped`) stop it the same way and the command exits 130 / 143.

What a kill (SIGKILL, a power cut) leaves is consistent: every snapshot folder appears whole (built
under a temporary name), and after each one OUT/snapshots/mapper.pt (the mapper's state, naming its
snapshot) and OUT/stream.json (the report so far, `running` true) are replaced atomically.
`finish_killed` (map-bag --resume) makes the final map of such a run from its last snapshot. The
final outputs are written small first (OUT/map/'s maps, stream.json, then mapper.pt), so a full
disk costs the least (utils/io.py `Outputs`).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from virus_nerf.data.bags.live import LiveSync, StreamFrame
from virus_nerf.data.playback import Playback
from virus_nerf.errors import DataFormatError
from virus_nerf.mapping.replay import FINAL, SNAPSHOTS, _progress_line, _publish, next_snapshot_time
from virus_nerf.maps.occupancy import MAP_POSES, MAP_RAYS
from virus_nerf.scene_box import SceneBox
from virus_nerf.utils.stop import Stopped

REPORT = "stream.json"
STATE = "mapper.pt"  # the mapper's state: OUT/snapshots/mapper.pt during the run, OUT/map/mapper.pt at the end
STARTUP_WAIT_S = 1.0  # bag seconds the first frames wait for every stack's camera_info
IDLE_SLEEP_S = 0.01  # a live source with nothing new and nothing to train: the pause


def initial_box(positions: np.ndarray, extent, sensors=()) -> SceneBox:
    """The scene box of a stream: the room is not known in advance, so the box starts around the
    first frame's camera (grid/extent.py first_box) and the mapper grows it as the robot drives
    (`extent.mode` grow, docs/extent.md)."""
    from virus_nerf.grid.extent import first_box

    return first_box(np.asarray(positions, dtype=np.float64).reshape(-1, 3)[0], extent, sensors)


@dataclass
class StreamReport:
    """What a streaming run did (also OUT/stream.json)."""

    snapshots: list[str] = field(default_factory=list)  # those on disk (--keep-snapshots removes older ones)
    snapshots_removed: int = 0  # --keep-snapshots: the older snapshot folders removed
    final: str | None = None
    frames: int = 0
    steps: int = 0
    train_s: float = 0.0
    wall_s: float = 0.0  # from the first message to the final map
    first_snapshot_s: float | None = None  # wall seconds from the first message to the first snapshot
    dropped: dict[str, int] = field(default_factory=dict)  # reason -> colour frames
    without: dict[str, int] = field(default_factory=dict)  # live: silent sensor (uss, tof, depth) -> frames made without it
    lag_s: list[float] = field(default_factory=list)  # at each snapshot
    # over every frame as it reached the mapper (a snapshot's lag is taken before it, while the
    # stream falls behind after one): median, max; and at the final map
    frame_lag_median_s: float | None = None
    frame_lag_max_s: float | None = None
    final_lag_s: float | None = None
    # --poses lidar-odometry: LiDAR scans KISS-ICP did not register, to keep up with the LiDAR
    scans_skipped: int = 0
    # --poses lidar-odometry: the floor of the first scan registered (odometry.ScanRegistration.describe)
    lidar_floor: dict | None = None
    stopped: str | None = None  # the error (or signal) that stopped the stream
    stopped_at_s: float | None = None  # bag seconds since the first message
    running: bool = False  # true in the report written at each snapshot while the stream runs
    # --out-bag: {"path", "map_frame", "base_frame"}, so `map-bag --resume` of a killed run can
    # rebuild the bag the kill left unfinished
    out_bag: dict | None = None

    def as_dict(self, out: Path) -> dict:
        """The stream.json document of the run in OUT: its folders named relative to OUT (where
        stream.json lies), so they hold wherever OUT is read from or moved to."""
        doc = dataclasses.asdict(self)
        doc["snapshots"] = [_relative(p, out) for p in self.snapshots]
        doc["final"] = None if self.final is None else _relative(self.final, out)
        return doc


def _relative(path: str, out: Path) -> str:
    """`path` relative to OUT (as is when it lies elsewhere)."""
    try:
        return Path(path).relative_to(out).as_posix()
    except ValueError:
        return str(path)


def warm_up(config) -> float:
    """`engine.mapper.warm_up`, imported when called (the stream's module loads no torch)."""
    from virus_nerf.engine.mapper import warm_up as load_kernels

    return load_kernels(config)


class StreamRun:
    """One streaming run into OUT (see module doc); `run(messages)` returns the report."""

    def __init__(self, sync: LiveSync, out: Path, config, *, playback: float = 1.0, snapshot_every: float = 10.0,
                 first_snapshot: float = 1.0, max_lag: float = 2.0, drive_s: float = 0.0, resolution: float = 0.05,
                 n_rays: int = MAP_RAYS, max_poses: int = MAP_POSES, train_slice: float = 0.25, train_share: float = 0.5,
                 box: Callable[..., SceneBox] = initial_box, log: Callable[[str], None] = print,
                 live=None, ros_bag=None, warm_step_s: float = 0.1, keep_snapshots: int | None = None) -> None:
        self.sync, self.out, self.config = sync, Path(out), config
        self.keep_snapshots = keep_snapshots  # None: every snapshot stays; N: the newest N (a long drive's disk)
        self.playback, self.snapshot_every, self.max_lag = playback, snapshot_every, max_lag
        self.drive_s, self.resolution, self.n_rays, self.max_poses = drive_s, resolution, n_rays, max_poses
        self.train_slice, self.box, self.log, self.live, self.ros_bag = train_slice, box, log, live, ros_bag
        self.train_share, self.train_next, self.warm_step_s = train_share, 0.0, warm_step_s
        self.next_snapshot = min(first_snapshot, snapshot_every)
        self.mapper = None
        self.held: list[StreamFrame] = []  # the first frames, until the mapper can be made
        self.newest: float | None = None  # recording time of the newest frame given to the mapper
        self.start: float | None = None  # monotonic time of the first message
        self.r0 = self.t0 = 0.0  # receive time and stamp of the first message
        # the frame feeder on the receive clock (releases messages) and on the stamps (the lag)
        self.released = self.stamped = Playback(0.0, playback)  # from 0 until the first message
        self.behind = 0.0  # recording seconds the newest message was released after it was due
        self.latest = -math.inf  # the stamp of the newest message (not a static transform's)
        self.anchored, self.restarts = False, 0  # the lag's clock (`_anchor`)
        # a live source (ros2/node.py): messages arrive stamped with the wall clock (time.time)
        self.live_source = getattr(sync, "on_problem", None) is not None
        self.report = StreamReport()
        from virus_nerf.mapping.ros_maps import RosMapBag

        if isinstance(ros_bag, RosMapBag):  # (the ROS 2 node's sink is its /map publisher)
            self.report.out_bag = {"path": str(ros_bag.path.absolute()), "map_frame": ros_bag.map_frame,
                                   "base_frame": ros_bag.base_frame}
        self._warned: set[str] = set()
        self.frame_lags: list[float] = []  # the lag as each frame reached the mapper (s)
        self.snapshot_tried = False  # the first snapshot was attempted (written or not: a full disk)

    # ------------------------------------------------------------------ clock
    def now(self) -> float:
        return time.monotonic() - self.start

    def map_time(self) -> float:
        """The recording time the maps carry: the newest mapped frame's; the stream's first stamp
        before the first frame and after a clock restart until a frame of the new clock is mapped."""
        return self.newest if self.newest is not None else self.t0

    def lag(self, now: float) -> float:
        """Recording seconds between the robot's present and the newest frame (the first message
        stands in before the first frame). From a bag, the present is the scaled wall clock. Live,
        the input's rate is not ours to know (a bag played at --rate 2 runs twice as fast as the
        wall clock): the present is the newest message's stamp plus how late it was read."""
        newest = self.map_time()
        if self.live_source:
            return max(self.latest - newest, 0.0) + max(self.behind, 0.0)
        return self.stamped.recording_time(now) - newest

    # ------------------------------------------------------------------ the loop
    def run(self, messages) -> StreamReport:
        """messages: (topic, Message) in bag order (BagReader.iter_topics), or from a live source
        (ros2/node.py) that yields None when nothing new has come: then the mapper trains a step."""
        try:
            for item in messages:
                if item is None:
                    self._idle()
                    continue
                topic, msg = item
                due = self._due(msg)
                if "static" not in topic:
                    self.latest = msg.time_s
                    if not self.anchored:
                        self._anchor(msg)
                self._wait(due)
                self._train_owed(due)
                self.behind = (self.now() - due) * self.playback
                late = self.sync.is_color(topic) and self.behind > self.max_lag
                frames = self.sync.push(topic, msg, late=late)
                if self.sync.restarts != self.restarts:
                    self._restarted()
                self._add(frames)
                self._maybe_snapshot()
            self._add(self.sync.finish())
        except DataFormatError as exc:
            self.report.stopped = str(exc)
            self.report.stopped_at_s = getattr(exc, "at_s", None)
            self._close()
            raise
        except KeyboardInterrupt as exc:  # the operator (Ctrl-C) or the robot (SIGTERM) stops it: keep the map
            self.report.stopped = f"interrupted ({exc.name if isinstance(exc, Stopped) else 'Ctrl-C'})"
            # at the end of the bag (`LiveSync.finish`: the clock past every message) the stop came
            # after the newest message; stream.json holds only finite numbers
            at = None if self.sync.t0 is None else self.sync.rel(self.sync.clock)
            if at is not None and not math.isfinite(at):
                at = self.sync.rel(self.latest) if math.isfinite(self.latest) else None
            self.report.stopped_at_s = at
            self._close()
            raise
        self._close()
        return self.report

    def _anchor(self, msg) -> None:
        """The lag's first message: not a static transform (a late joiner's are old); from a bag
        the lag's clock starts at its stamp."""
        self.anchored = True
        if msg.time_s == self.t0 and not self.live_source:  # the first message: `_due` anchored it
            return
        self.t0 = msg.time_s
        self.stamped = Playback(msg.time_s - self.now() * self.playback, self.playback)

    def _restarted(self) -> None:
        """Live, the clock went back (LiveSync.restart): the frames from here on are the newest,
        stamped before those mapped; the mapper keeps its frames in time order (`restart_clock`).
        Frames held for a mapper not made yet belong to the old clock: dropped (counted)."""
        self.restarts, self.newest = self.sync.restarts, None
        if self.mapper is not None:
            self.mapper.restart_clock()
        for f in self.held:
            self.sync.dropped[f.frame.stack_id]["before a clock restart"] += 1
        self.held = []

    def _due(self, msg) -> float:
        """Wall seconds (from the first message) at which `msg` is released."""
        received = msg.received_s if msg.received_s is not None else msg.time_s
        if self.start is None:
            # live, arrival times are the wall clock (time.time): the clock starts now, so a message
            # that waited in the queue is as late as it is (a colour image beyond max_lag is dropped)
            r0 = time.time() if self.live_source else received
            self.start, self.r0, self.t0 = time.monotonic(), r0, msg.time_s
            self.released, self.stamped = Playback(r0, self.playback), Playback(msg.time_s, self.playback)
        return self.released.elapsed_at(received)

    def _wait(self, due: float) -> None:
        """Train (or sleep, before the first frame) until `due`; snapshots on the way."""
        while (now := self.now()) < due:
            if self._maybe_snapshot():
                continue
            # a snapshot overdue before the mapper exists (live: no pose yet) waits for it
            budget = max(min(self.train_slice, due - now, self.next_snapshot - now), 0.0)
            if self._may_train(now):
                self._train(budget)
            else:
                time.sleep(budget if budget > 0 else min(due - now, IDLE_SLEEP_S))

    def _idle(self) -> None:
        """A live source has nothing new: a snapshot when due, else a training step (a short
        pause before the mapper exists)."""
        if self.start is None or self._maybe_snapshot():
            if self.start is None:
                time.sleep(IDLE_SLEEP_S)
            return
        now = self.now()
        if self._may_train(now):
            # one step, then look for messages again: the next one may come any moment (a bag's
            # stream likewise trains only until its next message is due)
            self._train(IDLE_SLEEP_S)
        else:
            time.sleep(IDLE_SLEEP_S)

    def _may_train(self, now: float) -> bool:
        """A mapper, and no step that could delay the first snapshot (on a CPU one step can take
        seconds): before it, a step starts only if it should end in time (2 x the warm-up's step,
        or the mean of the steps so far)."""
        if self.mapper is None:
            return False
        if self.snapshot_tried:  # not only a written one: on a full disk the map must still train
            return True
        m = self.mapper
        step_s = m.seconds / m.step if m.step else 2.0 * self.warm_step_s
        return self.next_snapshot - now > step_s

    def _train(self, budget: float) -> None:
        t = time.monotonic()
        self.mapper.train(budget)
        took = time.monotonic() - t
        # the earliest next slice forced while behind: train_share of the wall time, over the last slice
        self.train_next = self.now() + took * (1.0 - self.train_share) / self.train_share

    def _train_owed(self, due: float) -> None:
        """Behind the clock, the messages would take all the time and the map would never train:
        a slice is forced once the messages since the last one took as long as it (train_share
        0.5), as a robot's mapper thread runs beside its sensor callbacks. Not while the stream is
        more than max_lag behind: then its colour images are dropped anyway and catching up on the
        other messages comes first (the lag stays bounded). Snapshots count for neither."""
        now = self.now()
        if not self._may_train(now):
            return
        if now >= self.train_next and (now - due) * self.playback <= self.max_lag:
            self._train(self.train_slice)

    def _add(self, frames: list[StreamFrame]) -> None:
        if self.mapper is None:
            self.held.extend(frames)
            if not self.held:
                return
            stacks_known = set(self.sync.cfg.stacks) <= set(self.sync.intrinsics)
            if not stacks_known and self.sync.clock <= self.held[0].frame.time + STARTUP_WAIT_S:
                return
            frames, self.held = self.held, []
            self._make_mapper(frames)  # adds them
            return
        for f in frames:
            sid = f.frame.stack_id
            if sid not in self.mapper.intrinsics and not self._join(sid):
                continue
            self.mapper.add_frame(f.frame)
            self.newest = f.frame.time if self.newest is None else max(self.newest, f.frame.time)
            self.frame_lags.append(self.lag(self.now()))
            if self.live is not None:
                self.live.log_frame(f.frame, self.mapper.intrinsics)
            if self.ros_bag is not None:
                self.ros_bag.write_pose(f.frame.time, f.frame.cam_to_world, f.frame.stack_id)

    def _join(self, sid: int) -> bool:
        """A stack whose camera_info came after the mapper was made (a camera driver that started
        late) joins the map now, said once; False (its frame dropped, counted) while its
        camera_info has not come, or when its images differ in size from the mapped stacks'."""
        from virus_nerf.errors import UsageError

        if sid not in self.sync.intrinsics:
            self.sync.dropped[sid]["no camera_info"] += 1
            return False
        try:
            self.mapper.add_stack(sid, self.sync.intrinsics[sid])
        except UsageError as exc:
            self.sync.dropped[sid]["camera_info after the map started"] += 1
            self._warn(f"late camera_info {sid}", f"stack {sid}'s camera_info came after the map was started "
                       f"with stacks {sorted(self.mapper.intrinsics)}, and it cannot join: {exc}; its frames are "
                       "not mapped in this run")
            return False
        self.log(f"stack {sid}'s camera_info came after the map was started: its frames are mapped from now on "
                 f"(bag time {self.sync.rel(self.sync.clock):.3f} s)")
        return True

    def _make_mapper(self, first: list[StreamFrame]) -> None:
        """The mapper for the stacks whose intrinsics are known, its box from the first frames; the
        first frame's prior and the kernels loaded (start-up, on the clock: the robot is driving)."""
        from virus_nerf.config_io import to_dict
        from virus_nerf.engine.mapper import Mapper
        from virus_nerf.engine.schedule import Horizon, Schedules
        from virus_nerf.utils.io import write_json_atomic

        # the extent is unknown: the box grows from the first frame (grid/extent.py); the learning
        # rate decays over the drive (config.json records it as the budget)
        horizon = Horizon.drive(self.drive_s, self.playback)
        cfg = dataclasses.replace(self.config, max_steps=horizon.max_steps, max_time=horizon.max_time,
                                  extent=dataclasses.replace(self.config.extent, mode="grow"))
        box = self.box(np.stack([f.frame.cam_to_world[:3, 3] for f in first]), cfg.extent, cfg.sensors)
        self.mapper = Mapper(cfg, dict(self.sync.intrinsics), box, Schedules.of(cfg, horizon))
        (self.out / SNAPSHOTS).mkdir(parents=True)
        self.mapper.spill_frames(self.out)  # a long drive's frames beyond the budget go to disk
        write_json_atomic(self.out / SNAPSHOTS / "config.json", to_dict(cfg))
        if self.live is not None:
            self.live.start_time = first[0].frame.time
        self._add(first[:1])
        self.mapper.prepare()
        self._add(first[1:])

    # ------------------------------------------------------------------ maps
    def _maybe_snapshot(self) -> bool:
        """A snapshot when due; postponed while the stream is more than max_lag behind (catching
        up on the messages first: a snapshot can take seconds on a CPU, and taken while behind it
        would put the stream further behind every time), by at most one snapshot period."""
        now = self.now()
        if self.mapper is None or now < self.next_snapshot:
            return False
        if self.behind > self.max_lag and now < self.next_snapshot + self.snapshot_every:
            return False
        k = len(self.report.snapshots) + self.report.snapshots_removed + 1  # written so far, and the next
        folder = self.out / SNAPSHOTS / f"{k:04d}_{now:.1f}s"
        lag = self.lag(now)
        self.snapshot_tried = True
        try:
            info = self._snapshot(folder, self.map_time())
        except OSError as exc:  # a full disk: the map is still in memory, the final map comes first
            self._warn("snapshot", f"snapshot {k}: {exc.filename or folder}: could not be written "
                       f"({exc.strerror or exc}); mapping goes on")
        else:
            self.report.snapshots.append(str(folder))
            self.report.lag_s.append(round(lag, 3))
            if self.report.first_snapshot_s is None:
                self.report.first_snapshot_s = round(self.now(), 3)
            self.log(self._line(f"snapshot {k}", now, info, folder, lag))
            self._save_progress(folder)
            self._remove_old_snapshots()
        after = self.train_next = self.now()  # the snapshot's time is not the messages'
        self.next_snapshot = next_snapshot_time(self.next_snapshot, self.snapshot_every, after, after - now)
        return True

    def _remove_old_snapshots(self) -> None:
        """--keep-snapshots N: the oldest snapshot folders this run wrote go, the newest N stay;
        after the mapper's state names the newest (a kill in between leaves what `--resume` reads)."""
        keep, r = self.keep_snapshots, self.report
        while keep is not None and len(r.snapshots) > keep:
            shutil.rmtree(r.snapshots.pop(0), ignore_errors=True)
            r.snapshots_removed += 1

    def _snapshot(self, folder: Path, recording_time: float, with_state: bool = False):
        from virus_nerf.errors import require_folder

        require_folder(self.out)  # removed under the stream: not rebuilt by the next snapshot
        maps = _publish(self.mapper, recording_time, self.resolution, self.n_rays, self.max_poses, self.live,
                        self.ros_bag)
        return self.mapper.snapshot(folder, self.resolution, self.n_rays, self.max_poses, with_state=with_state,
                                    maps=maps)

    def _line(self, what: str, now: float, info, folder: Path, lag: float) -> str:
        """replay's progress line with the lag and the frames dropped so far."""
        drive_t = self.map_time() - self.t0
        head, _, tail = _progress_line(what, now, drive_t, self.drive_s, info, folder).rpartition(" -> ")
        dropped = sum(self.sync.dropped_total().values())
        return f"{head}, lag {lag:.2f} s, {dropped} dropped -> {tail}"

    def _warn(self, kind: str, line: str) -> None:
        """One warning per kind of failure (a full disk would repeat it at every snapshot)."""
        if kind not in self._warned:
            self._warned.add(kind)
            self.log(f"warning: {line} (said once)")

    def _save_progress(self, folder: Path) -> None:
        """After snapshot `folder`: the mapper's state (naming the snapshot) and the report so far,
        each replaced atomically, so a kill leaves a consistent pair (finish_killed reads them)."""
        from virus_nerf.utils.io import save_torch_atomic, write_json_atomic

        r = self.report
        self._count_inputs()
        r.frames, r.steps, r.train_s, r.wall_s = self.mapper.frames, self.mapper.step, self.mapper.seconds, self.now()
        r.running = True
        try:
            write_json_atomic(self.out / REPORT, r.as_dict(self.out))
            save_torch_atomic({"snapshot": folder.name, "mapper": self.mapper.state()}, self.out / SNAPSHOTS / STATE)
        except OSError as exc:
            self._warn("state", f"{exc.filename}: could not be written ({exc.strerror or exc}); mapping goes on")
        finally:
            r.running = False

    def _count_inputs(self) -> None:
        """The report's counts of what did not become a frame or a pose."""
        r = self.report
        r.dropped, r.without = dict(self.sync.dropped_total()), dict(self.sync.without_total())
        if self.frame_lags:
            r.frame_lag_median_s = round(statistics.median(self.frame_lags), 3)
            r.frame_lag_max_s = round(max(self.frame_lags), 3)
        r.scans_skipped = getattr(self.sync.poses, "skipped", 0)
        r.lidar_floor = getattr(self.sync.poses, "floor", None)
        if r.lidar_floor and "note" in r.lidar_floor:
            self._warn("floor", r.lidar_floor["note"])

    def _close(self) -> None:
        """The final map of what was made (none when no frame reached the mapper) and the report,
        small files first: OUT/map/'s maps, OUT/stream.json, then OUT/map/mapper.pt. What does not
        fit is named in one NotWrittenError after the rest was written."""
        from virus_nerf.utils.io import Outputs, save_torch_atomic, write_json_atomic

        r = self.report
        if self.mapper is None and self.held:  # the bag ended (or stopped) during the start-up wait
            frames, self.held = self.held, []
            self._make_mapper(frames)
        self._count_inputs()
        outputs = Outputs()
        if self.mapper is not None:
            now = self.now()
            lag = self.lag(now)
            final = self.out / FINAL
            made = {}
            r.final_lag_s = round(lag, 3)
            if outputs.write(final, lambda: made.update(info=self._snapshot(
                    final, self.map_time()))):
                r.final = str(final)
                self.log(self._line("final map", now, made["info"], final, lag))
            r.frames, r.steps, r.train_s, r.wall_s = self.mapper.frames, self.mapper.step, self.mapper.seconds, now
        if self.out.is_dir():
            outputs.write(self.out / REPORT, lambda: write_json_atomic(self.out / REPORT, r.as_dict(self.out)))
        if self.mapper is not None and r.final is not None:  # beside a map that did not fit: no map/ at all
            state = self.out / FINAL / STATE
            outputs.write(state, lambda: save_torch_atomic(self.mapper.state(), state))
        outputs.check("free some space; the snapshots in " + str(self.out / SNAPSHOTS) + " are whole")


BEHIND_SHARE = 0.05  # a stream that dropped this share of its frames as late is said to have fallen behind


def behind_note(report: StreamReport, playback: float) -> str | None:
    """The line a stream that could not keep up with the bag ends with (the counts alone in the
    summary are easily missed): a share of BEHIND_SHARE or more of its frames dropped as late."""
    from virus_nerf.data.bags.live import LATE

    late = report.dropped.get(LATE, 0)
    if late == 0 or late < BEHIND_SHARE * (report.frames + late):
        return None
    return (f"the mapper fell behind the bag: {late} of {report.frames + late} frames were dropped as late; "
            f"a lower --playback (now {playback:g}) keeps up on this machine")


def summary(report: StreamReport) -> str:
    """One line: frames, dropped frames by reason, lag at the snapshots."""
    dropped = sum(report.dropped.values())
    reasons = ", ".join(f"{n} {why}" for why, n in sorted(report.dropped.items(), key=lambda kv: -kv[1]))
    lag = (f"; lag at snapshots median {statistics.median(report.lag_s):.2f} s, max {max(report.lag_s):.2f} s"
           if report.lag_s else "")
    if report.frame_lag_max_s is not None:
        lag += f"; lag at frames median {report.frame_lag_median_s:.2f} s, max {report.frame_lag_max_s:.2f} s"
    without = "".join(f", {n} without {role}" for role, n in sorted(report.without.items()))
    skipped = f"; {report.scans_skipped} LiDAR scans skipped to keep up" if report.scans_skipped else ""
    return f"{report.frames} frames{without}, {dropped} dropped{f' ({reasons})' if reasons else ''}{lag}{skipped}"


def snapshot_number(folder: Path) -> int:
    """k of a snapshot folder `kkkk_T.Ts`: the order they were made in (past 9999 the names have
    five digits and no longer sort as text)."""
    return int(folder.name.split("_")[0])


def finish_killed(out: Path, log: Callable[[str], None] = print) -> StreamReport:
    """The final map of a streaming run that was killed (SIGKILL, a power cut) from what it saved:
    OUT/map/ is a copy of its newest snapshot (map.*, prob.*, snapshot.json) with OUT/snapshots/
    mapper.pt when that state belongs to this snapshot; OUT/stream.json (the report of that
    snapshot) is marked stopped. Small files first, as at a normal end (utils/io.py `Outputs`).
    The caller holds OUT's lock; a run that ended or never made a snapshot is refused."""
    import json
    import shutil

    import torch

    from virus_nerf.engine.views import SnapshotInfo
    from virus_nerf.errors import UsageError
    from virus_nerf.utils.io import (
        Outputs,
        new_output_dir,
        remove_stale_partials,
        remove_stale_temps,
        save_torch_atomic,
        write_json_atomic,
    )

    out = Path(out)
    report_path = out / REPORT
    try:
        doc = json.loads(report_path.read_text()) if report_path.is_file() else None
    except (OSError, ValueError):
        doc = None  # cannot be: written atomically; then the snapshots alone say what was made
    half = {name: remove_stale_temps(out / name)  # left by the killed process (the lock proves it is gone)
            for name in (REPORT, f"{SNAPSHOTS}/{STATE}", f"{FINAL}/{STATE}")}
    remove_stale_partials(out / FINAL, owned=True)
    if (out / SNAPSHOTS).is_dir():  # a snapshot the kill cut short (`.NAME.partial-*`), never finished
        for p in (out / SNAPSHOTS).glob(".*.partial-*"):
            remove_stale_partials(out / SNAPSHOTS / p.name[1:].split(".partial-")[0], owned=True)
    final = out / FINAL
    written = (final / "snapshot.json").is_file()  # the process wrote its final map whole (not its report)
    if final.is_dir() and not written:  # a map/ the process could not finish (a full disk): set aside
        if any(final.iterdir()):
            final.rename(final.with_name(f"{FINAL}.incomplete-{time.time_ns()}"))
        else:
            final.rmdir()
    if doc is not None and not doc.get("running", False) and written:
        lost = f"; its mapper state was not saved (stopped while writing {out / FINAL / STATE})" \
            if half[f"{FINAL}/{STATE}"] and not (out / FINAL / STATE).is_file() else ""
        raise UsageError(f"--resume --out {out}: the stream ended (final map in {out / FINAL}, {report_path}); "
                         f"nothing to finish{lost}")
    snaps = sorted((p for p in (out / SNAPSHOTS).glob("[0-9]*_*") if p.is_dir() and p.name.split("_")[0].isdigit()),
                   key=snapshot_number) if (out / SNAPSHOTS).is_dir() else []
    if not snaps:
        raise UsageError(f"--resume --out {out}: the stream was stopped before its first snapshot; there is no map "
                         "to finish (run map-bag again into a new --out)")
    last = snaps[-1]
    report = StreamReport()
    if doc is not None:
        known = {f.name for f in dataclasses.fields(StreamReport)}
        report = StreamReport(**{k: v for k, v in doc.items() if k in known})
    report.snapshots = [str(p) for p in snaps]  # every whole snapshot (the report may predate the last)
    report.running = False
    report.stopped = report.stopped or f"killed after snapshot {snapshot_number(last)} ({last.name})"
    state_path, state = out / SNAPSHOTS / STATE, None
    if state_path.is_file():
        try:
            saved = torch.load(state_path, map_location="cpu", weights_only=False)
            state = saved["mapper"] if saved.get("snapshot") == last.name else None
        except Exception:  # noqa: BLE001 - written atomically; a foreign or damaged file is left alone
            state = None
    info = SnapshotInfo.read(final if written else last)
    report.frames, report.steps, report.train_s = info.frames, info.steps, info.seconds
    outputs = Outputs()

    def copy_map() -> None:
        if written:
            return
        with new_output_dir(final) as tmp:
            for p in sorted(last.iterdir()):
                if p.is_file():
                    shutil.copyfile(p, tmp / p.name)

    if outputs.write(final, copy_map):
        report.final = str(final)
    outputs.write(report_path, lambda: write_json_atomic(report_path, report.as_dict(out)))
    if state is not None and not written:
        outputs.write(final / STATE, lambda: save_torch_atomic(state, final / STATE))
    outputs.check("free some space and run map-bag --resume again")
    note = "" if (final / STATE).is_file() else f" (no mapper state of {last.name} was saved)"
    log(f"map-bag: the stream in {out} was stopped after snapshot {snapshot_number(last)}; final map (that snapshot's) in "
        f"{final}{note}, report in {report_path}{rebuild_out_bag(report.out_bag, snaps)}")
    return report


def rebuild_out_bag(out_bag: dict | None, snaps: list[Path]) -> str:
    """The --out-bag of a killed run, which a kill leaves without its metadata.yaml and most of its
    messages (an MCAP is finished on close): the unfinished folder is kept aside as
    PATH.incomplete-<ns>, and PATH rebuilt with /map and /map_probability of every snapshot at
    its newest frame's stamp, as the run wrote them. The /tf poses were in the run's memory
    only. Returns what the resume line adds ("" when there is nothing to rebuild)."""
    from virus_nerf.engine.views import SnapshotInfo
    from virus_nerf.mapping.ros_maps import RosMapBag
    from virus_nerf.maps.occupancy import read_map_server

    if not out_bag or (Path(out_bag["path"]) / "metadata.yaml").is_file():
        return ""
    path = Path(out_bag["path"])
    aside = ""
    if path.exists():
        kept = path.with_name(f"{path.name}.incomplete-{time.time_ns()}")
        path.rename(kept)
        aside = f"; the unfinished bag kept as {kept}"
    written = 0
    with RosMapBag(path, map_frame=out_bag["map_frame"], base_frame=out_bag["base_frame"]) as bag:
        for snap in snaps:
            stamp = SnapshotInfo.read(snap).last_frame_time
            if stamp is None:
                continue
            prob = read_map_server(snap / "prob.yaml") if (snap / "prob.yaml").is_file() else None
            bag.write_maps(float(stamp), read_map_server(snap / "map.yaml"), prob)
            written += 1
    return (f"; --out-bag {path} rebuilt from the {written} snapshots' maps (the /tf poses were lost with the "
            f"killed process{aside})")
