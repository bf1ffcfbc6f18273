"""Replay of a recording through a `Mapper` in real time (mapping while driving, issue 12).

A wall clock, scaled by the playback speed, runs through the recording: every frame is added to
the mapper once the clock passes its timestamp (read and decoded then, as a robot receives it),
and the mapper trains continuously in between. Every `snapshot_every` seconds of wall time the
current map is written to OUT/snapshots/NNNN_<seconds>s/ (map.pgm/.yaml/.png, prob.* for the
VIRUS grid, snapshot.json) with one progress line (snapshots take at most half the wall time:
`next_snapshot_time`); when the last frame has arrived, the final map goes to OUT/map/ with the mapper's state (mapper.pt). Every folder appears complete (built
under a temporary name and renamed) and none is ever overwritten.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from virus_nerf.data.playback import FrameFeeder
from virus_nerf.errors import (
    DataFormatError,
    OutputExistsError,
    UsageError,
    require_folder,
    require_number,
)
from virus_nerf.maps.occupancy import MAP_POSES, MAP_RAYS

SNAPSHOTS = "snapshots"
REMOVAL_GRACE_S = 0.5  # s a vanished frame file waits for its folder's removal to show (replay's `add`)
FINAL = "map"
SNAPSHOT_SHARE = 0.5  # snapshots take at most this share of the wall time (`next_snapshot_time`)


@dataclass(frozen=True)
class ReplayReport:
    """What a replay did; `snapshots` in the order written."""

    snapshots: tuple[Path, ...]
    final: Path
    frames: int
    steps: int
    train_s: float  # training clock
    wall_s: float  # wall time from the first frame to the final map


def find_room(recording_dir: Path, room: str | None = None) -> tuple[Path, str]:
    """An ETHZ folder -> (data folder, room): DATA (holding camera_intrinsics.CSV and one room, or
    `room`) or DATA/ROOM itself."""
    d = Path(recording_dir)
    if not d.is_dir():
        raise UsageError(f"recording {d}: no such folder; expected an ETHZ recording (camera_intrinsics.CSV, ROOM/)")
    if room is None and (d / "measurements").is_dir():
        return d.parent, d.name
    if not (d / "camera_intrinsics.CSV").is_file():
        raise DataFormatError(d / "camera_intrinsics.CSV", "missing; expected an ETHZ recording folder")
    if room is not None:
        return d, room
    rooms = sorted(p.name for p in d.iterdir() if (p / "measurements").is_dir())
    if len(rooms) != 1:
        raise UsageError(f"recording {d}: holds {len(rooms)} rooms {rooms}; expected exactly one (or name the room)")
    return d, rooms[0]


def replay(
    recording_dir: Path,
    out: Path,
    playback: float = 1.0,
    snapshot_every: float = 10.0,
    config=None,
    *,
    room: str | None = None,
    poses: Literal["auto", "optimised", "odometry"] = "auto",
    frames: Literal["all", "train"] = "all",
    resolution: float = 0.05,
    n_rays: int = MAP_RAYS,
    max_poses: int = MAP_POSES,
    train_slice: float = 0.25,
    log: Callable[[str], None] = print,
    live=None,
    ros_bag=None,
) -> ReplayReport:
    """Replay an ETHZ recording through a Mapper in real time; snapshots into OUT (see module doc).

    OUT may exist (map-bag imports the bag into OUT/recording first) but OUT/snapshots and
    OUT/map must not. config: a TrainConfig (default TrainConfig()); its learning rate decays
    over the drive's wall duration. poses: the recording's pose files, "auto" = the optimised
    ones where present, else odometry. frames: every frame, or only the split's 'train' ones.
    live: a mapping.live_view.LiveView that gets every frame as it arrives and every snapshot's
    maps; ros_bag: a mapping.ros_maps.RosMapBag that gets the robot's pose per frame (/tf) and
    every snapshot's maps (/map, /map_probability), stamped with the recording's time.
    """
    from virus_nerf.data.ethz import load_recording
    from virus_nerf.engine.mapper import Mapper
    from virus_nerf.engine.schedule import Horizon, Schedules
    from virus_nerf.trainer.config import TrainConfig
    from virus_nerf.utils.io import write_json_atomic

    require_number("--playback", playback, 0.0)
    require_number("--snapshot-every", snapshot_every, 0.0)
    require_number("--resolution", resolution, 0.0)
    if poses not in ("auto", "optimised", "odometry"):
        raise UsageError(f"--poses {poses!r}: expected auto, optimised or odometry")
    if frames not in ("all", "train"):
        raise UsageError(f"--frames {frames!r}: expected all or train")
    out = Path(out)
    for p in (out / SNAPSHOTS, out / FINAL):
        if p.exists():
            raise OutputExistsError(p)
    data, room = find_room(recording_dir, room)
    if poses == "auto":
        poses = "optimised" if any((data / room / "poses").glob("poses_cam_balm_sync*.csv")) else "odometry"
    recording = load_recording(data, room, poses=poses)
    order = recording.frame_order(None if frames == "all" else ("train",))
    if not order:
        raise DataFormatError(data / room / "split", f"no frames to replay (frames={frames})")
    times = [float(recording.stacks[s].times[i]) for s, i in order]
    drive_s = times[-1] - times[0]
    cfg = config if config is not None else TrainConfig()
    # the extent is unknown to a robot: the box grows from the first frame (docs/extent.md); the
    # learning rate decays over the drive (config.json records it as the budget)
    horizon = Horizon.drive(drive_s, playback)
    cfg = dataclasses.replace(cfg, max_steps=horizon.max_steps, max_time=horizon.max_time,
                              extent=dataclasses.replace(cfg.extent, mode="grow"))
    mapper = Mapper.for_recording(recording, cfg, Schedules.of(cfg, horizon))
    with_depth = "rgbd" in cfg.sensors

    (out / SNAPSHOTS).mkdir(parents=True)
    from virus_nerf.config_io import to_dict

    write_json_atomic(out / SNAPSHOTS / "config.json", to_dict(cfg))
    written: list[Path] = []
    # start-up (kernels loaded, the first frame's prior) before the drive's clock starts, as a
    # robot starts its mapper before it drives off
    intrinsics = {sid: st.intrinsics for sid, st in recording.stacks.items()}
    if live is not None:
        live.start_time = times[0]  # the live view's drive_time 0 is the first frame

    mapper.spill_frames(out)  # a long drive's frames beyond the budget go to disk, as when streaming

    def add(k: int) -> None:
        s, i = order[k]
        require_folder(out)  # removed under the run: its frames (OUT/recording) are gone with it
        try:
            frame = recording.stacks[s].frame(i, with_depth=with_depth)
        except DataFormatError:
            # a frame's file vanished: `rm -rf OUT` empties the folders before it removes OUT, so
            # give it a moment; OUT gone is one line saying so, else the recording is damaged
            time.sleep(REMOVAL_GRACE_S)
            require_folder(out)
            raise
        mapper.add_frame(frame)
        if live is not None:
            live.log_frame(frame, intrinsics)
        if ros_bag is not None:
            ros_bag.write_pose(frame.time, frame.cam_to_world, frame.stack_id)

    def snapshot(folder: Path, recording_time: float, with_state: bool = False):
        require_folder(out)
        maps = _publish(mapper, recording_time, resolution, n_rays, max_poses, live, ros_bag)
        return mapper.snapshot(folder, resolution, n_rays, max_poses, with_state=with_state, maps=maps)

    feeder = FrameFeeder(times, playback)  # on the wall clock
    for k in feeder.release(0.0):  # the first frame (and any at its time) before the clock starts
        add(int(k))
    mapper.prepare()
    mapper.build_optimizer()  # before the drive's clock
    start = time.monotonic()
    next_snapshot = snapshot_every

    def final() -> None:
        """The final map, small files first: OUT/map/'s maps, then mapper.pt (utils/io.py Outputs)."""
        from virus_nerf.utils.io import Outputs, save_torch_atomic

        wall_s = time.monotonic() - start
        outputs, made = Outputs(), {}
        if outputs.write(out / FINAL, lambda: made.update(info=snapshot(out / FINAL, feeder.last_time))):
            log(_progress_line("final map", wall_s, feeder.last_time - times[0], drive_s, made["info"], out / FINAL))
            # only beside a whole map: a map/ made for it alone would read as a finished final map
            outputs.write(out / FINAL / "mapper.pt", lambda: save_torch_atomic(mapper.state(), out / FINAL / "mapper.pt"))
        outputs.check("free some space; the snapshots in " + str(out / SNAPSHOTS) + " are whole")

    try:
        while True:
            now = time.monotonic() - start
            for k in feeder.release(now):
                add(int(k))
            if feeder.done:
                break
            if now >= next_snapshot:
                folder = out / SNAPSHOTS / f"{len(written) + 1:04d}_{now:.1f}s"
                info = snapshot(folder, feeder.last_time)
                written.append(folder)
                log(_progress_line(f"snapshot {len(written)}", now, feeder.last_time - times[0], drive_s, info, folder))
                after = time.monotonic() - start
                next_snapshot = next_snapshot_time(next_snapshot, snapshot_every, after, after - now)
            budget = min(train_slice, feeder.wait(now), next_snapshot - now)
            if budget > 0:
                mapper.train(budget)
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM (utils/stop.py): the map of the frames so far
        final()
        raise
    wall_s = time.monotonic() - start
    final()
    return ReplayReport(tuple(written), out / FINAL, mapper.frames, mapper.step, mapper.seconds, wall_s)


def next_snapshot_time(scheduled: float, every: float, finished: float, took: float,
                       share: float = SNAPSHOT_SHARE) -> float:
    """When the snapshot after the one scheduled at `scheduled` (wall seconds) is due: the next on
    the grid scheduled + k * every after the one just written (`finished`, `took` seconds to
    write), missed ones skipped, and no sooner than `took` * (1 - share) / share after it. A
    snapshot slower than its period (a large map on a slow or busy computer) would otherwise leave
    the stream nothing but snapshots, its lag growing without end."""
    earliest = finished + took * (1.0 - share) / share
    return scheduled + every * max(1, math.floor((earliest - scheduled) / every) + 1)


def _publish(mapper, recording_time: float, resolution: float, n_rays: int, max_poses: int, live, ros_bag):
    """The current maps, computed once, sent to the live view and the ROS bag; None when there is
    neither (the snapshot computes them itself)."""
    if live is None and ros_bag is None:
        return None
    if live is not None:
        from virus_nerf.mapping.live_view import log_mapper

        m, prob, _ = log_mapper(live, mapper, recording_time, resolution, n_rays, max_poses)
    else:
        m, prob = mapper.map2d(resolution, n_rays, max_poses), mapper.probability_map(resolution)
    if ros_bag is not None:
        ros_bag.write_maps(recording_time, m, prob)
    return m, prob


def _progress_line(what: str, now: float, drive_t: float, drive_s: float, info, folder: Path) -> str:
    loss = "-" if info.loss is None else f"{info.loss:.4f}"
    return (f"{what} at {now:.1f} s (drive {drive_t:.1f}/{drive_s:.1f} s): {info.frames} frames, {info.steps} steps, "
            f"loss {loss}, map {info.map_known:.1%} known, {info.map_occupied:.1%} of it occupied, "
            f"grid {info.grid_occupied:.1%} occupied -> {folder}")
