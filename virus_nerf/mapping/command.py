"""`virus-nerf map-bag`: a ROS bag mapped in real time, with map snapshots.

By default the bag is streamed (mapping/stream.py, data/bags/live.py): read message by message in
recording order as the playback clock passes them, synchronised into frames as they complete, the
map trained in between. With --import-first the old path runs instead: the whole bag is imported
into OUT/recording (an ETHZ folder, by `virus_nerf.data.bags`), then that folder is replayed
(mapping/replay.py). Either way a snapshot is written every --snapshot-every seconds and the final
map at the end.
"""

from __future__ import annotations

import shutil
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from virus_nerf.errors import (
    DataFormatError,
    OutputExistsError,
    UsageError,
    require_input_file,
    require_int,
    require_number,
)
from virus_nerf.mapping.options import (
    DEFAULT_RASTER,
    NO_VIEW,
    MapRaster,
    RerunSinks,
    load_stream_config,
)
from virus_nerf.utils.io import require_new_folder


def _importer(poses: str):
    """`import_bag`, after the one-line check that the optional ROS dependencies `--poses` needs
    are installed."""
    from virus_nerf.data.bags.importer import import_bag, require_ros_extra

    require_ros_extra(poses, "map-bag")
    return import_bag


POSES = ("lidar-odometry", "tf", "csv", "odometry")


def map_bag(
    bag: Annotated[Path | None, tyro.conf.Positional] = None,
    out: Path | None = None,
    playback: float = 1.0,
    snapshot_every: float = 10.0,
    topics: Path | None = None,
    poses: str = "lidar-odometry",
    poses_file: Path | None = None,
    tf_parent: str = "odom",
    tf_child: str | None = None,
    odometry_topic: str = "/odom",
    import_first: bool = False,
    first_snapshot: float = 1.0,
    max_lag: float = 2.0,
    max_silence: float = 2.0,
    keep_snapshots: int | None = None,
    config: Path | None = None,
    maps: Annotated[MapRaster, tyro.conf.arg(name="")] = DEFAULT_RASTER,
    view: Annotated[RerunSinks, tyro.conf.arg(name="")] = NO_VIEW,
    out_bag: Path | None = None,
    map_frame: str = "map",
    base_frame: str = "base_link",
    resume: bool = False,
) -> None:
    """Map a ROS bag while playing it in real time: snapshots every few seconds, a final map.

    Streams the bag (docs/live-view.md, "Streaming"): messages are read in recording order as the
    playback clock passes them, each colour image becomes a frame once its depth, USS, IRS and pose
    are in (within the topics file's sync tolerances) and goes to the mapper at once. Writes OUT/
    (refused if it exists): snapshots/NNNN_<s>s/ (map.pgm/.yaml/.png, prob.* for the VIRUS grid,
    snapshot.json; one progress line each, with the lag), map/ (the final map and mapper.pt) and
    stream.json (frames, dropped frames by reason, lag, where a stream stopped). Bad data (a topic
    that stops, a clock that goes backwards, a pose jump over 1 m) stops the stream: the final map
    of what was made is written, then the one-line error and exit code 2. SIGINT or SIGTERM stops
    it the same way (exit 130 / 143; a second signal stops at once); after SIGKILL or a power cut,
    --resume writes the final map from the last snapshot. A full disk: the maps and stream.json
    are written before mapper.pt, what did not fit is named in one line, exit 2.

    Args:
        bag: ROS bag (ROS 1 .bag, a ROS 2 bag folder, or a bare ROS 2 .mcap/.db3 file).
        out: New output folder.
        playback: Recording seconds per wall-clock second (below 1 on a slow machine).
        snapshot_every: Wall-clock seconds between map snapshots (streaming: further apart when a
            snapshot takes longer than this; they take at most half the wall time).
        topics: Topic mapping file (default: the ETHZ robot's topic names).
        poses: Pose source: lidar-odometry (KISS-ICP scan by scan), tf (/tf, /tf_static), csv
            (--poses-file) or odometry (nav_msgs/Odometry on --odometry-topic; streaming only).
        poses_file: LiDAR (or robot) poses for --poses csv: time,x,y,z,qx,qy,qz,qw CSV or TUM.
        tf_parent: --poses tf: the world frame.
        tf_child: --poses tf: the LiDAR's frame (default: the frame of the LiDAR topic's messages).
        odometry_topic: --poses odometry: the topic; its child frame takes the LiDAR's place for
            the topics file's camera_in_lidar mounting.
        import_first: Import the whole bag into OUT/recording first, then replay it (the old path;
            --poses odometry is streaming only).
        first_snapshot: Wall-clock seconds from the first message to the first snapshot (at most
            --snapshot-every; no training step that might delay it starts); streaming only.
        max_lag: A colour image released more than this many recording seconds late (the mapper
            was busy) is dropped, and counted; streaming only.
        max_silence: A sensor topic (or the pose source) silent this many recording seconds has
            stopped: the stream ends there (bad data); streaming only.
        keep_snapshots: Keep only the newest N snapshot folders (the older ones this run wrote are
            removed; default: all of them), for a long drive's disk; streaming only.
        config: JSON training config (a run's config.json works; default: the defaults).
        maps: The maps (--resolution, --n-rays, --max-poses; mapping/options.py).
        view: The live view (--rerun, --rerun-connect, --rerun-save; mapping/options.py).
        out_bag: New folder for a rosbag2 (MCAP) of the maps as they grow (/map, /map_probability,
            nav_msgs/OccupancyGrid) and the robot's /tf, for RViz 2 and Foxglove.
        map_frame: --out-bag: the maps' frame_id and the parent frame of the /tf poses.
        base_frame: --out-bag: the robot's frame, the child frame of the /tf poses.
        resume: Finish the map-bag in --out that was killed (SIGKILL, a power cut): its final map
            (OUT/map/) from its last snapshot and the mapper state saved with it, and stream.json
            marked stopped; the stream is not continued (BAG and the other flags are not needed).
    """
    if out is None:
        raise UsageError("--out is required: give --out DIR (a new folder; with --resume the killed run's folder)")
    frames_given = (map_frame, base_frame) != ("map", "base_link")
    if resume:
        # the final map is the last snapshot as it was made: a flag that asks for more is refused, not ignored
        unused = [flag for flag, given in (("--out-bag", out_bag is not None), ("--rerun*", view.wanted),
                                           ("--map-frame/--base-frame", frames_given),
                                           ("--resolution/--n-rays/--max-poses", maps != DEFAULT_RASTER),
                                           ("--keep-snapshots", keep_snapshots is not None)) if given]
        if unused:
            raise UsageError(f"--resume writes the final map from the last snapshot as it was made; {unused[0]} "
                             "cannot apply to it: drop it")
        _finish(Path(out))
        return
    if bag is None:
        raise UsageError("BAG is required: give the ROS bag to map (or --resume --out DIR to finish a killed run)")
    require_number("--playback", playback, 0.0)
    require_number("--snapshot-every", snapshot_every, 0.0)
    maps.check()
    require_number("--first-snapshot", first_snapshot, 0.0)
    require_number("--max-lag", max_lag, 0.0)
    require_number("--max-silence", max_silence, 0.0)
    if keep_snapshots is not None:
        require_int("--keep-snapshots", keep_snapshots, 1)
        if import_first:
            raise UsageError("--keep-snapshots streams only: drop --import-first")
    if poses not in POSES:
        raise UsageError(f"--poses {poses!r}: expected {', '.join(POSES[:-1])} or {POSES[-1]}")
    if import_first and poses == "odometry":
        raise UsageError("--poses odometry streams only: drop --import-first")
    from virus_nerf.data.bags.poses import check_pose_flags

    check_pose_flags(poses, poses_file)
    bag, out = Path(bag), Path(out)
    if not bag.exists():
        raise UsageError(f"BAG {bag}: no such file or folder; expected a ROS bag")
    if topics is not None:
        require_input_file("--topics", topics, "the importer's topic mapping file")
    cfg = load_stream_config(config)
    require_new_folder("--out", out)
    if out_bag is not None:
        if Path(out_bag).absolute() == out.absolute():
            raise UsageError(f"--out-bag {out_bag}: the same folder as --out; give the maps' bag a folder of its own")
        require_new_folder("--out-bag", out_bag)
    from virus_nerf.mapping.ros_maps import require_tf_pair

    require_tf_pair(("--map-frame", map_frame), ("--base-frame", base_frame))
    if out_bag is None and frames_given:
        raise UsageError("--map-frame and --base-frame name the frames of --out-bag's maps and /tf: give --out-bag DIR")
    view.check()
    from virus_nerf.data.bags.topics import default_topics, read_topics

    tcfg = read_topics(topics) if topics else default_topics()  # read once: the stream and the sinks agree
    mounts = {s: st.camera_in_lidar() for s, st in tcfg.stacks.items()}
    sinks = Sinks(view, out_bag, map_frame, base_frame, mounts)  # base_link: the frame the poses are in
    pose_args = dict(poses=poses, poses_file=poses_file, tf_parent=tf_parent, tf_child=tf_child)
    from virus_nerf.utils.stop import stop_on_signals

    with stop_on_signals():  # SIGINT/SIGTERM: the final map, stream.json, one line, exit 130/143
        if import_first:
            _import_then_replay(bag, out, playback, snapshot_every, tcfg, cfg, pose_args, maps, sinks)
            return
        stream_map_bag(bag, out, playback, snapshot_every, tcfg, cfg, pose_args, maps, sinks,
                       odometry_topic=odometry_topic, first_snapshot=first_snapshot, max_lag=max_lag,
                       max_silence=max_silence, keep_snapshots=keep_snapshots)


def _finish(out: Path) -> None:
    """map-bag --resume: the final map of a killed stream in OUT (mapping/stream.py finish_killed)."""
    from virus_nerf.mapping.stream import finish_killed
    from virus_nerf.trainer.run_folder import RunLock

    if not out.is_dir():
        raise UsageError(f"--resume --out {out}: no such folder; expected the --out of a map-bag that was killed")
    if not (out / "snapshots").is_dir() and not (out / "stream.json").is_file():
        raise UsageError(f"--resume --out {out}: not a map-bag output folder (no snapshots/, no stream.json)")
    with RunLock(out, "--out"):  # not while the map-bag that writes it still runs
        finish_killed(out)


@dataclass(frozen=True)
class MadeOut:
    """OUT and the parent folders this process made for it (deepest first): a run that keeps
    nothing removes them all, so "nothing was kept" leaves nothing behind."""

    out: Path
    parents: tuple[Path, ...] = ()

    def remove(self) -> None:
        shutil.rmtree(self.out, ignore_errors=True)
        for folder in self.parents:
            try:
                folder.rmdir()  # empty unless something else wrote there meanwhile: then it stays
            except OSError:
                break


def make_out(out: Path) -> MadeOut:
    """OUT, made by this process alone: another map-bag that made it meanwhile (both passed the
    check before their start-up) is a one-line refusal naming --out, not the OS's "File exists"."""
    missing = tuple(p for p in Path(out).absolute().parents if not p.exists())
    try:
        out.mkdir(parents=True)
    except FileExistsError:
        raise OutputExistsError(out) from None
    return MadeOut(out, missing)


@dataclass(frozen=True)
class Sinks:
    """Where a stream's frames and maps go besides OUT: the live view and a bag of the maps."""

    view: RerunSinks = NO_VIEW
    out_bag: Path | None = None  # a rosbag2 (MCAP) of /map, /map_probability and /tf
    map_frame: str = "map"  # out_bag's maps' frame_id and its /tf parent
    base_frame: str = "base_link"  # out_bag's /tf child
    camera_in_base: dict = field(default_factory=dict)  # out_bag: stack id -> (4, 4) camera mount on base_link
    made: list = field(default_factory=list)  # the files and folders `open` made (`discard` removes them)

    def open(self, stack: ExitStack) -> tuple:
        """(LiveView or None, RosMapBag or None), closed with `stack`."""
        live = ros_bag = None
        if self.view.wanted:
            from virus_nerf.mapping.live_view import LiveView

            v = self.view
            live = stack.enter_context(LiveView(spawn=v.rerun, connect=v.rerun_connect, save=v.rerun_save))
            if v.rerun_save is not None:
                self.made.append(Path(v.rerun_save))
        if self.out_bag is not None:
            from virus_nerf.mapping.ros_maps import RosMapBag

            ros_bag = stack.enter_context(RosMapBag(self.out_bag, map_frame=self.map_frame, base_frame=self.base_frame,
                                                    camera_in_base=self.camera_in_base))
            self.made.append(Path(self.out_bag))
        return live, ros_bag

    def discard(self) -> None:
        """A run that kept nothing: the live view's recording and the maps' bag it made go too, so
        the same command can run again (both were refused had they existed)."""
        for path in self.made:
            if path.is_dir():
                shutil.rmtree(path, ignore_errors=True)
            else:
                path.unlink(missing_ok=True)
        self.made.clear()

    def note(self) -> str:
        """"; live view in X; ROS maps in Y" for the files written, "" for none."""
        return "".join(f"; {what} {p}" for what, p in (("live view in", self.view.rerun_save),
                                                        ("ROS maps in", self.out_bag)) if p)


def _import_then_replay(bag: Path, out: Path, playback: float, snapshot_every: float, tcfg, cfg,
                        pose_args: dict, maps: MapRaster, sinks: Sinks) -> None:
    """The whole bag imported into OUT/recording with the topic mapping `tcfg` (the command's
    TopicsConfig), then replayed (--import-first)."""
    from virus_nerf.mapping.replay import replay
    from virus_nerf.trainer.run_folder import RunLock
    from virus_nerf.utils.stop import Stopped

    import_bag = _importer(pose_args["poses"])
    made = make_out(out)
    with RunLock(out, "--out"):  # one process writes into OUT: map-bag --resume waits for this one to end
        try:
            imported = import_bag(bag, out / "recording", topics=tcfg, **pose_args)
        except BaseException:
            made.remove()  # nothing written yet but the partial import
            raise
        try:
            with ExitStack() as stack:
                live, ros_bag = sinks.open(stack)
                report = replay(out / "recording", out, playback, snapshot_every, cfg, room=imported.room,
                                **maps.kwargs(), live=live, ros_bag=ros_bag)
        except Stopped as exc:
            exc.reported = True
            final = f"final map in {out / 'map'}" if (out / "map").is_dir() else "no map was made yet"
            print(f"map-bag: stopped by {exc.name}; {final}; the recording imported in {out / 'recording'}")
            raise
    print(f"map-bag: {report.frames} frames, {report.steps} steps in {report.wall_s:.1f} s of wall time; "
          f"{len(report.snapshots)} snapshot(s) in {out / 'snapshots'}, final map in {report.final}{sinks.note()}")


def stream_map_bag(bag: Path, out: Path, playback: float, snapshot_every: float, tcfg, cfg,
                   pose_args: dict, maps: MapRaster, sinks: Sinks, *, odometry_topic: str = "/odom",
                   first_snapshot: float = 1.0, max_lag: float = 2.0, max_silence: float = 2.0,
                   keep_snapshots: int | None = None) -> None:
    """The streaming path (mapping/stream.py) with the topic mapping `tcfg` (data.bags.topics
    TopicsConfig, read once by the command): topics checked against the bag before OUT is made;
    OUT removed again when the stream stops before its first frame (nothing was mapped)."""
    from virus_nerf.data.bags.importer import plan_topics, require_ros_extra
    from virus_nerf.data.bags.live import LiveSync
    from virus_nerf.data.bags.poses import make_pose_source
    from virus_nerf.data.bags.reader import BagReader
    from virus_nerf.mapping.stream import StreamRun, behind_note, summary, warm_up
    from virus_nerf.trainer.config import TrainConfig
    from virus_nerf.trainer.run_folder import RunLock
    from virus_nerf.utils.stop import Stopped

    require_ros_extra(pose_args["poses"], "map-bag")
    poses = pose_args["poses"]
    for note in tcfg.notes:  # e.g. no [stacks]: the ETHZ robot's topics are read
        print(f"map-bag: note: {note}")
    cfg = cfg if cfg is not None else TrainConfig()
    tcfg = tcfg.for_sensors(cfg.sensors)  # no depth topic required, read or waited for without rgbd
    with BagReader(bag) as reader, ExitStack() as owned:
        plan = plan_topics(reader, tcfg, "csv" if poses == "odometry" else poses)
        if poses == "odometry":
            reader.require(odometry_topic, "odometry", "--odometry-topic")
        child = pose_args["tf_child"]
        if poses == "tf" and child is None:
            child = _lidar_frame(reader, tcfg.lidar.topic)
        source = make_pose_source(poses, tcfg, bag, present=lambda t: t in reader.topics,
                                  poses_file=pose_args["poses_file"], tf_parent=pose_args["tf_parent"],
                                  tf_child=child, odometry_topic=odometry_topic, keep_up=True)
        owned.callback(source.close)  # KISS-ICP's worker process ends with the stream
        sync = LiveSync(tcfg, source, bag, intrinsics=plan.intrinsics, with_depth="rgbd" in cfg.sensors,
                        max_silence_s=max_silence)
        first, last = reader.span_s
        warm_step_s = warm_up(cfg)
        made = make_out(out)
        owned.enter_context(RunLock(out, "--out"))  # map-bag --resume waits for this process to end
        run = None
        try:
            with ExitStack() as stack:
                live, ros_bag = sinks.open(stack)
                run = StreamRun(sync, out, cfg, playback=playback, snapshot_every=snapshot_every,
                                first_snapshot=first_snapshot, max_lag=max_lag, drive_s=max(last - first, 0.0),
                                live=live, ros_bag=ros_bag, warm_step_s=warm_step_s, keep_snapshots=keep_snapshots,
                                **maps.kwargs())
                report = run.run(reader.iter_topics(sync.topics()))
        except BaseException as exc:
            nothing = run_made_nothing(out)
            if nothing:
                made.remove()
                sinks.discard()
            if isinstance(exc, Stopped):
                exc.reported = True
                if nothing or run is None or run.report.final is None:
                    print(f"map-bag: stopped by {exc.name} before the first frame was mapped; nothing was kept")
                else:
                    print(f"map-bag: stopped by {exc.name} at {run.report.stopped_at_s or 0.0:.2f} s of "
                          f"{max(last - first, 0.0):.1f} s of the bag; {summary(run.report)}; final map in "
                          f"{run.report.final}, report in {out / 'stream.json'}")
            elif not nothing and isinstance(exc, DataFormatError | KeyboardInterrupt) and run is not None:
                at = _at(exc) if isinstance(exc, DataFormatError) else f"{run.report.stopped_at_s or 0.0:.2f} s"
                print(f"map-bag: stopped at {at} of {max(last - first, 0.0):.1f} s of the bag; "
                      f"{summary(run.report)}; final map of what was made in {out / 'map'}")
            raise
    if report.final is None:
        made.remove()
        sinks.discard()
        raise DataFormatError(bag, f"no frame could be made ({summary(report)}); check the topics file's sync "
                              "tolerances and the pose source")
    removed = f" (and {report.snapshots_removed} older ones removed)" if report.snapshots_removed else ""
    print(f"map-bag: {summary(report)}, {report.steps} steps in {report.wall_s:.1f} s of wall time; "
          f"{len(report.snapshots)} snapshot(s){removed} in {out / 'snapshots'}, final map in {report.final}"
          f"{sinks.note()}")
    if (behind := behind_note(report, playback)) is not None:
        print(f"map-bag: warning: {behind}")


def run_made_nothing(out: Path) -> bool:
    """Nothing was written into OUT (the stream stopped before its first frame made the mapper)."""
    return not (out / "snapshots").exists() and not (out / "map").exists()


def _at(exc: Exception) -> str:
    at = getattr(exc, "at_s", None)
    return "an unknown time" if at is None else f"{at:.2f} s"


def _lidar_frame(reader, topic: str | None) -> str:
    """--poses tf without --tf-child: the frame of the LiDAR's first message."""
    from virus_nerf.errors import UsageError

    if not topic or topic not in reader.topics:
        raise UsageError("--poses tf needs --tf-child FRAME (the bag has no LiDAR whose frame could be used)")
    from virus_nerf.data.bags.messages import frame_id

    for msg in reader.iter_topic(topic):
        return frame_id(msg.msg)
    raise UsageError("--poses tf needs --tf-child FRAME (the LiDAR topic has no messages)")
