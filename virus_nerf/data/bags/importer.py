"""`import_bag`: a ROS 1/2 bag -> a recording in the ETHZ layout (docs/method.md 4) that
`virus_nerf.data.ethz.load_recording` reads.

Two passes over the bag keep memory bounded: the first reads every stamp, the small sensors
(USS, IRS, camera info, tf) and the LiDAR scans (written at once as filtered PCDs); poses and the
per-stack matching follow; the second pass decodes and writes only the colour and depth frames
that became samples. Everything is built in a temporary folder renamed into place at the end,
so a failure leaves nothing behind and an existing folder is never touched.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from virus_nerf.data.bags import messages as m
from virus_nerf.data.bags.odometry import (
    KissIcpSettings,
    PoseTrack,
    Transform,
    csv_track,
    kiss_icp_track,
    tf_track,
)
from virus_nerf.data.bags.reader import BagReader
from virus_nerf.data.bags.sync import StackMatch, TopicReport, match_stack
from virus_nerf.data.bags.topics import TopicsConfig, default_topics, read_topics
from virus_nerf.data.pcd import read_pcd_xyz, write_pcd_xyz
from virus_nerf.data.split import DEFAULT_RATIOS, make_split, write_split
from virus_nerf.errors import DataFormatError, OutputExistsError, UsageError
from virus_nerf.sensors.camera import Intrinsics
from virus_nerf.sim import writer
from virus_nerf.sim.sensors import VoxelMap
from virus_nerf.utils.io import new_output_dir, write_json_atomic

PoseMode = Literal["lidar-odometry", "tf", "csv"]
REPORT_NAME = "import_report.json"
ROS_EXTRA = "pip install 'virus-nerf[ros]'"


@dataclass
class ImportReport:
    """What an import wrote and dropped (also saved as DATA/import_report.json)."""

    bag: str
    data_dir: str  # the ETHZ data folder: pass it as --data, with --room `room`
    room: str
    ros_version: int
    poses: str
    samples: dict[int, int]  # stack -> samples written
    lidar_scans: int
    map_points: int
    topics: list[TopicReport]
    dropped_frames: dict[int, dict[str, int]]  # stack -> reason -> colour frames dropped
    pose_settings: dict | None = None
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        for t, rep in zip(d["topics"], self.topics, strict=True):
            t["dropped"] = rep.dropped
        return d

    def summary(self) -> str:
        lines = [f"imported {self.bag} (ROS {self.ros_version}) -> {self.data_dir}, room {self.room!r}",
                 f"  poses: {self.poses}; samples per stack: "
                 + ", ".join(f"{s}: {n}" for s, n in self.samples.items())
                 + f"; LiDAR scans: {self.lidar_scans}; map points: {self.map_points}"]
        for t in self.topics:
            lines.append(f"  {t.topic:<45} {t.role:<11} {t.messages:>6} messages, {t.used:>6} used, "
                         f"{t.dropped:>6} dropped")
        for s, reasons in self.dropped_frames.items():
            for why, n in reasons.items():
                lines.append(f"  stack {s}: {n} colour frames dropped ({why})")
        lines += [f"  note: {n}" for n in self.notes]
        return "\n".join(lines)


def require_ros_extra(poses: str = "lidar-odometry") -> None:
    """One-line error when the optional ROS dependencies are missing."""
    needed = ["rosbags"] + (["kiss_icp"] if poses == "lidar-odometry" else [])
    missing = [n for n in needed if importlib.util.find_spec(n) is None]
    if missing:
        raise UsageError(f"import-bag needs {' and '.join(missing)} (not installed): {ROS_EXTRA}")


def room_name(bag: Path) -> str:
    stem = bag.name.removesuffix(".bag") if bag.is_file() else bag.name
    return re.sub(r"[^A-Za-z0-9_-]", "_", stem) or "room"


def import_bag(bag: str | Path, out: str | Path, topics: str | Path | TopicsConfig | None = None,
               poses: PoseMode = "lidar-odometry", poses_file: str | Path | None = None,
               tf_parent: str = "odom", tf_child: str | None = None, room: str | None = None,
               kiss: KissIcpSettings | None = None) -> ImportReport:
    """Import `bag` into the new ETHZ data folder `out` (room `room`, default the bag's name).

    poses: 'lidar-odometry' (KISS-ICP on the LiDAR topic), 'tf' (frame `tf_child`, default the
    LiDAR's frame, in `tf_parent` from /tf and /tf_static) or 'csv' (`poses_file`: LiDAR poses
    as time,x,y,z,qx,qy,qz,qw or TUM). Raises DataFormatError / UsageError / OutputExistsError
    (one line) before or while reading; `out` then does not exist.
    """
    if poses not in ("lidar-odometry", "tf", "csv"):
        raise UsageError(f"--poses {poses!r}: expected lidar-odometry, tf or csv")
    require_ros_extra(poses)
    bag, out = Path(bag), Path(out)
    if out.exists():
        raise OutputExistsError(out)
    cfg = topics if isinstance(topics, TopicsConfig) else read_topics(topics) if topics else default_topics()
    if poses == "csv" and poses_file is None:
        raise UsageError("--poses csv needs --poses-file FILE (time,x,y,z,qx,qy,qz,qw or TUM)")
    csv_poses = csv_track(poses_file) if poses == "csv" else None
    room = room or room_name(bag)
    if not re.fullmatch(r"[A-Za-z0-9_-]+", room):
        raise UsageError(f"--room {room!r}: expected letters, digits, '_' or '-'")
    with BagReader(bag) as reader:
        plan = _plan(reader, cfg, poses)
        with new_output_dir(out) as root:
            report = _Importer(reader, cfg, plan, root, room).run(poses, csv_poses, tf_parent, tf_child, kiss)
            report.data_dir = str(out)
            write_json_atomic(root / REPORT_NAME, report.as_dict())
    return report


@dataclass
class _Plan:
    roles: dict[tuple[int | None, str], str]  # (stack, role) -> topic (stack None: lidar, tf)
    intrinsics: dict[int, Intrinsics]  # from the topics file's CSV, for stacks without camera_info


def _plan(reader: BagReader, cfg: TopicsConfig, poses: str) -> _Plan:
    """Check every named topic against the bag before anything is written."""
    roles: dict[tuple[int | None, str], str] = {}
    where = f"topics file {cfg.source}" if cfg.source else "default ETHZ topics"
    for s, st in cfg.stacks.items():
        for role, topic in st.roles().items():
            reader.require(topic, role, f"stacks.{s}.{role} of the {where}")
            roles[(s, role)] = topic
    bag_topics = reader.topics
    if cfg.lidar.topic and cfg.lidar.topic in bag_topics:
        reader.require(cfg.lidar.topic, "lidar", f"lidar.topic of the {where}")
        roles[(None, "lidar")] = cfg.lidar.topic
    elif poses == "lidar-odometry":
        raise DataFormatError(reader.path, f"--poses lidar-odometry needs a LiDAR: no topic {cfg.lidar.topic} "
                              f"(lidar.topic of the {where}); name it in a topics file or use --poses tf or csv")
    if poses == "tf":
        found = [t for t in cfg.tf_topics if t in bag_topics]
        if not found:
            raise DataFormatError(reader.path, f"--poses tf: none of the tf topics {list(cfg.tf_topics)} is in the bag")
        for k, t in enumerate(found):
            reader.require(t, "tf", "tf_topics")
            roles[(None, f"tf{k}")] = t
    intrinsics: dict[int, Intrinsics] = {}
    need_csv = [s for s, st in cfg.stacks.items() if not st.camera_info]
    if need_csv:
        if cfg.intrinsics_csv is None:
            raise DataFormatError(cfg.source or reader.path, f"stack {need_csv[0]} has no camera_info topic; "
                                  "name one or give intrinsics_csv (cam_id,fx,fy,cx,cy[,width,height])")
        from virus_nerf.data.ethz import read_intrinsics

        table = read_intrinsics(cfg.intrinsics_csv)
        for s in need_csv:
            if s not in table:
                raise DataFormatError(cfg.intrinsics_csv, f"no row for CAM{s}", field="cam_id")
            intrinsics[s] = table[s]
    return _Plan(roles, intrinsics)


class _Importer:
    """One import into the temporary folder `root` (the passes of the module docstring)."""

    def __init__(self, reader: BagReader, cfg: TopicsConfig, plan: _Plan, root: Path, room: str) -> None:
        self.reader, self.cfg, self.plan, self.root, self.room = reader, cfg, plan, root, room
        self.room_dir = root / room
        self.reports: dict[str, TopicReport] = {}
        self.notes: list[str] = []

    def _report(self, stack: int | None, role: str, times: np.ndarray, used: int) -> None:
        topic = self.plan.roles[(stack, role)]
        t = np.asarray(times)
        self.reports[topic] = TopicReport(topic, role.rstrip("0123456789"), stack, len(t), used,
                                          float(t.min()) if len(t) else None, float(t.max()) if len(t) else None)

    def _stamps(self, stack: int, role: str) -> np.ndarray:
        return np.array([msg.time_s for msg in self.reader.iter_topic(self.plan.roles[(stack, role)])])

    def run(self, poses: str, csv_poses: PoseTrack | None, tf_parent: str, tf_child: str | None,
            kiss: KissIcpSettings | None) -> ImportReport:
        for sub in ("measurements", "poses", "lidars/filtered", "maps", "split"):
            (self.room_dir / sub).mkdir(parents=True)
        lidar_times, lidar_paths, lidar_frame = self._lidar()
        if poses == "lidar-odometry":
            if len(lidar_times) < 2:
                raise DataFormatError(self.reader.path, f"--poses lidar-odometry: topic {self.plan.roles[(None, 'lidar')]}"
                                      f" has {len(lidar_times)} usable scans; expected at least 2")
            settings = kiss or KissIcpSettings()
            track = kiss_icp_track(lidar_times, lambda k: read_pcd_xyz(lidar_paths[k]), settings)
            pose_settings: dict | None = {"kiss_icp": dataclasses.asdict(settings)}
        elif poses == "tf":
            child = tf_child or lidar_frame
            if not child:
                raise UsageError("--poses tf needs --tf-child FRAME (the bag has no LiDAR whose frame could be used)")
            track = tf_track(self._transforms(), tf_parent, child, str(self.reader.path))
            pose_settings = {"tf_parent": tf_parent, "tf_child": child}
        else:
            track, pose_settings = csv_poses, None
        assert track is not None
        matches = {s: self._match(s, track) for s in self.cfg.stacks}
        intrinsics = {s: self._write_stack(matches[s], track) for s in self.cfg.stacks}
        writer.write_intrinsics(self.root / "camera_intrinsics.CSV", intrinsics)
        n_map = self._write_map(lidar_times, lidar_paths, track)
        n_max = max(len(mt.times_s) for mt in matches.values())
        labels = make_split(n_max, DEFAULT_RATIOS)
        write_split(self.room_dir / "split" / "split.csv", {s: labels[: len(mt.times_s)] for s, mt in matches.items()})
        writer.write_split_description(self.room_dir / "split" / "split_description.csv", DEFAULT_RATIOS)
        if poses != "csv":
            self.notes.append("poses_*_balm_sync*.csv hold the same odometry poses as poses_*_sync*.csv "
                              "(no bundle adjustment was run)")
        order = [t for t in self.plan.roles.values() if t in self.reports]
        return ImportReport(
            bag=str(self.reader.path), data_dir=str(self.root), room=self.room, ros_version=self.reader.ros_version,
            poses=poses, samples={s: len(mt.times_s) for s, mt in matches.items()}, lidar_scans=len(lidar_times),
            map_points=n_map, topics=[self.reports[t] for t in order],
            dropped_frames={s: mt.dropped_frames for s, mt in matches.items()}, pose_settings=pose_settings,
            notes=self.notes)

    def _lidar(self) -> tuple[np.ndarray, list[Path], str | None]:
        """Write every LiDAR scan as a filtered PCD (range limits of the topics file)."""
        if (None, "lidar") not in self.plan.roles:
            self.notes.append("no LiDAR in the bag: no scans and no map (evaluation against a map is impossible)")
            return np.zeros(0), [], None
        topic = self.plan.roles[(None, "lidar")]
        lo, hi = self.cfg.lidar.min_range_m, self.cfg.lidar.max_range_m
        times, paths, seen, frame, stamps = [], [], set(), None, []
        for msg in self.reader.iter_topic(topic):
            stamps.append(msg.time_s)
            pts = m.decode_cloud(msg.msg, m.Where(self.reader.path, topic, msg.index))
            frame = frame or msg.msg.header.frame_id
            r = np.linalg.norm(pts, axis=1)
            name = writer.lidar_file_name(msg.time_s)
            if name in seen:
                continue
            seen.add(name)
            path = self.room_dir / "lidars" / "filtered" / name
            write_pcd_xyz(path, pts[(r >= lo) & (r <= hi)])
            times.append(msg.time_s)
            paths.append(path)
        order = np.argsort(times, kind="stable")
        self._report(None, "lidar", np.array(stamps), len(times))
        return np.asarray(times)[order], [paths[i] for i in order], frame

    def _transforms(self) -> list[Transform]:
        from virus_nerf.sensors.geometry import pose_matrix

        out = []
        for (_, role), topic in self.plan.roles.items():
            if not role.startswith("tf"):
                continue
            stamps = []
            for msg in self.reader.iter_topic(topic):
                stamps.append(msg.time_s)
                for tr in msg.msg.transforms:
                    tt, q = tr.transform.translation, tr.transform.rotation
                    pose = pose_matrix(np.array([tt.x, tt.y, tt.z]), np.array([q.x, q.y, q.z, q.w]))
                    out.append(Transform(m.stamp_s(tr), tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/"),
                                         pose, "static" in topic))
            self._report(None, role, np.array(stamps), len(stamps))
        return out

    def _match(self, s: int, track: PoseTrack) -> StackMatch:
        sync, roles = self.cfg.sync, self.cfg.stacks[s].roles()
        color = self._stamps(s, "color")
        tol = {"depth": sync.depth_tolerance_s, "uss": sync.uss_tolerance_s, "tof": sync.tof_tolerance_s}
        self._small = getattr(self, "_small", {})
        streams = {}
        for role in ("depth", "uss", "tof"):
            if role in roles:
                times = self._stamps(s, role) if role == "depth" else self._read_small(s, role)
                streams[role] = (times, tol[role])
        _, pose_ok = track.at(color, sync.pose_tolerance_s)
        match = match_stack(s, color, streams, pose_ok, sync.camera_rate_hz)
        if len(match.times_s) == 0:
            self._unsynchronised(s, color, streams, pose_ok)
        self._report(s, "color", color, len(match.times_s))
        for role, (times, _) in streams.items():
            self._report(s, role, times, len(np.unique(match.partner[role])))
        return match

    def _read_small(self, s: int, role: str) -> np.ndarray:
        topic = self.plan.roles[(s, role)]
        times, values = [], []
        for msg in self.reader.iter_topic(topic):
            times.append(msg.time_s)
            if role == "uss":
                values.append(m.decode_uss_us(msg.msg, msg.msgtype))
            else:
                values.append(m.decode_tof(msg.msg, m.Where(self.reader.path, topic, msg.index)))
        self._small[(s, role)] = values
        return np.array(times)

    def _unsynchronised(self, s: int, color: np.ndarray, streams: dict, pose_ok: np.ndarray) -> None:
        """Name the stream that no colour frame could be matched with."""
        from virus_nerf.data.bags.sync import match_nearest

        ctopic = self.plan.roles[(s, "color")]
        span = f"{color.min():.3f}..{color.max():.3f} s" if len(color) else "no frames"
        for role, (times, tol) in streams.items():
            if (match_nearest(color, times, tol) < 0).all():
                raise DataFormatError(self.reader.path, f"cannot synchronise topic {self.plan.roles[(s, role)]} with "
                                      f"{ctopic}: no message within {tol:g} s of any colour frame (stamps "
                                      f"{times.min():.3f}..{times.max():.3f} s, colour {span}); check the clocks or "
                                      f"raise sync.{role}_tolerance_s in the topics file")
        if not pose_ok.any():
            raise DataFormatError(self.reader.path, f"cannot synchronise {ctopic} with the poses: no pose within the "
                                  f"pose tolerance of any colour frame (colour {span})")
        raise DataFormatError(self.reader.path, f"stack {s}: no colour frame of {ctopic} has every partner within "
                              "its tolerance (sync section of the topics file)")

    def _write_stack(self, mt: StackMatch, track: PoseTrack) -> Intrinsics:
        from virus_nerf.data.bags.stack_writer import write_stack

        return write_stack(self, mt, track)

    def _write_map(self, times: np.ndarray, paths: list[Path], track: PoseTrack) -> int:
        """The global map as the ETHZ one: 3 cm voxels hit at least twice (docs/method.md 4)."""
        vmap = VoxelMap()
        poses, ok = track.at(times, self.cfg.sync.pose_tolerance_s)
        for k in np.flatnonzero(ok):
            pts = read_pcd_xyz(paths[k]).astype(np.float64)
            vmap.add(pts @ poses[k, :3, :3].T + poses[k, :3, 3])
        pts = vmap.points()
        if len(times):
            write_pcd_xyz(self.room_dir / "maps" / "map_balm.pcd", pts)
        return len(pts)

