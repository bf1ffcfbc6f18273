"""`virus-nerf map-bag`: a ROS bag replayed through the Mapper in real time, with map snapshots.

The bag is first imported into OUT/recording (an ETHZ folder, by `virus_nerf.data.bags`), then
that folder is replayed (mapping/replay.py): frames are added as the playback clock passes
their timestamps, the map trains in between, a snapshot is written every --snapshot-every
seconds and the final map at the end.
"""

from __future__ import annotations

import shutil
from contextlib import ExitStack
from pathlib import Path
from typing import Annotated

import tyro

from virus_nerf.errors import OutputExistsError, UsageError, require_int, require_number


def _importer():
    """`import_bag`, after the one-line check that the optional ROS dependencies are installed."""
    from virus_nerf.data.bags.importer import import_bag, require_ros_extra

    require_ros_extra()
    return import_bag


def map_bag(
    bag: Annotated[Path, tyro.conf.Positional],
    out: Path,
    playback: float = 1.0,
    snapshot_every: float = 10.0,
    topics: Path | None = None,
    poses: str = "lidar-odometry",
    config: Path | None = None,
    resolution: float = 0.05,
    n_rays: int = 360,
    max_poses: int = 30,
    rerun: bool = False,
    rerun_connect: str | None = None,
    rerun_save: Path | None = None,
    out_bag: Path | None = None,
) -> None:
    """Map a ROS bag while replaying it in real time: snapshots every few seconds, a final map.

    Writes OUT/ (refused if it exists): recording/ (the bag as an ETHZ folder), snapshots/NNNN_<s>s/
    (map.pgm/.yaml/.png, prob.* for the VIRUS grid, snapshot.json; one progress line each) and
    map/ (the final map and mapper.pt). Each snapshot folder appears complete or not at all.

    Args:
        bag: ROS bag (ROS 1 .bag or a ROS 2 bag folder).
        out: New output folder.
        playback: Recording seconds per wall-clock second (below 1 on a slow machine).
        snapshot_every: Wall-clock seconds between map snapshots.
        topics: Topic mapping file for the importer (default: its built-in topic names).
        poses: Pose source for the importer (default lidar-odometry).
        config: JSON training config (a run's config.json works; default: the defaults).
        resolution: Metres per map pixel.
        n_rays: Rays per 360 deg scan of the maps.
        max_poses: Camera positions scanned for each map (evenly over the frames so far).
        rerun: Spawn a Rerun viewer and watch the mapping live (the live extra; docs/live-view.md).
        rerun_connect: Send the live view to a running Rerun viewer at this URL instead
            (e.g. rerun+http://192.168.1.7:9876/proxy).
        rerun_save: Record the live view into this new .rrd file (play it later with `rerun FILE`).
        out_bag: New folder for a rosbag2 (MCAP) of the maps as they grow (/map, /map_probability,
            nav_msgs/OccupancyGrid) and the robot's /tf, for RViz 2 and Foxglove.
    """
    from virus_nerf.mapping.replay import replay

    require_number("--playback", playback, 0.0)
    require_number("--snapshot-every", snapshot_every, 0.0)
    require_number("--resolution", resolution, 0.0)
    require_int("--n-rays", n_rays, 1, 1_000_000)
    require_int("--max-poses", max_poses, 1)
    bag, out = Path(bag), Path(out)
    if not bag.exists():
        raise UsageError(f"BAG {bag}: no such file or folder; expected a ROS bag")
    if topics is not None and not Path(topics).is_file():
        raise UsageError(f"--topics {topics}: no such file; expected the importer's topic mapping file")
    cfg = None
    if config is not None:
        from virus_nerf.config_io import load_json_config
        from virus_nerf.trainer.config import TrainConfig

        cfg = load_json_config(TrainConfig, config)
    if out.exists():
        raise OutputExistsError(out)
    if rerun_save is not None and Path(rerun_save).suffix != ".rrd":
        raise UsageError(f"--rerun-save {rerun_save}: expected a .rrd file name")
    for path in (rerun_save, out_bag):
        if path is not None and Path(path).exists():
            raise OutputExistsError(path)
    if rerun or rerun_connect or rerun_save:
        from virus_nerf.mapping.live_view import _rerun

        _rerun()  # the live extra's one-line message now, not after the import
    import_bag = _importer()
    out.mkdir(parents=True)
    try:
        imported = import_bag(bag, out / "recording", topics=topics, poses=poses)
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)  # nothing written yet but the partial import
        raise
    with ExitStack() as sinks:
        live = ros_bag = None
        if rerun or rerun_connect or rerun_save:
            from virus_nerf.mapping.live_view import LiveView

            live = sinks.enter_context(LiveView(spawn=rerun, connect=rerun_connect, save=rerun_save))
        if out_bag is not None:
            from virus_nerf.mapping.ros_maps import RosMapBag

            ros_bag = sinks.enter_context(RosMapBag(out_bag))
        report = replay(out / "recording", out, playback, snapshot_every, cfg, room=imported.room,
                        resolution=resolution, n_rays=n_rays, max_poses=max_poses, live=live, ros_bag=ros_bag)
    extra = "".join(f"; {what} {p}" for what, p in (("live view in", rerun_save), ("ROS maps in", out_bag)) if p)
    print(f"map-bag: {report.frames} frames, {report.steps} steps in {report.wall_s:.1f} s; "
          f"{len(report.snapshots)} snapshot(s) in {out / 'snapshots'}, final map in {report.final}{extra}")
