"""The stages of one import (`ImportRun.run`), in the temporary output folder:

1. first pass over the bag: every stamp, the small sensors (USS, TOF, camera info, tf) decoded,
   the LiDAR scans written at once as filtered PCDs (memory stays bounded by one scan);
2. LiDAR poses (KISS-ICP, tf or CSV);
3. per stack, colour frames matched to their partners (sync.py);
4. second pass (stack_writer.py): only the colour and depth frames that became samples are
   decoded and written, then the per-stack tables and poses;
5. the global map and the split.
"""

from __future__ import annotations

import dataclasses
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from virus_nerf.data import writer
from virus_nerf.data.bags import messages as m
from virus_nerf.data.bags.odometry import (
    KissIcpSettings,
    PoseTrack,
    ScanRegistration,
    Transform,
    kiss_icp_track,
    tf_track,
)
from virus_nerf.data.bags.reader import BagReader
from virus_nerf.data.bags.report import ImportReport
from virus_nerf.data.bags.stack_writer import write_frames, write_tables
from virus_nerf.data.bags.sync import StackMatch, TopicReport, match_nearest, match_stack
from virus_nerf.data.bags.topics import TopicsConfig
from virus_nerf.data.pcd import read_pcd_xyz, write_pcd_xyz
from virus_nerf.data.split import DEFAULT_RATIOS, make_split, write_split
from virus_nerf.data.voxel_map import VoxelMap
from virus_nerf.errors import DataFormatError, UsageError
from virus_nerf.sensors.camera import Intrinsics
from virus_nerf.sensors.geometry import upside_down_words
from virus_nerf.sensors.rig import MAIN_STACK

Key = tuple[int | None, str]  # (stack, role); stack None for the LiDAR and tf topics


@dataclass
class Plan:
    """Topics checked against the bag before anything is written."""

    roles: dict[Key, str]  # (stack, role) -> topic
    intrinsics: dict[int, Intrinsics]  # from the topics file's CSV, for stacks without camera_info (0 x 0: the images')


class ImportRun:
    """One import into the temporary folder `root`; `run` returns the report."""

    def __init__(self, reader: BagReader, cfg: TopicsConfig, plan: Plan, root: Path, room: str) -> None:
        self.reader, self.cfg, self.plan, self.root, self.room = reader, cfg, plan, root, room
        self.room_dir = root / room
        self.reports: dict[str, TopicReport] = {}
        self.notes: list[str] = list(cfg.notes)  # e.g. that the topics file named no stacks
        self.stamps: dict[Key, list[float]] = defaultdict(list)
        self.small: dict[Key, list] = defaultdict(list)  # uss: UssReading; tof: TofReading
        self.tof_units = m.TofUnitCheck()  # a ToF topic in metres, over its messages
        self.camera_info: dict[int, Intrinsics] = {}
        self.transforms: list[Transform] = []
        self.odometry: list[tuple[float, np.ndarray]] = []  # (time s, (4, 4) robot pose) of --poses odometry
        self.lidar_times: list[float] = []
        self.lidar_paths: list[Path] = []
        self.lidar_frame: str | None = None

    def run(self, poses: str, csv_poses: PoseTrack | None, tf_parent: str, tf_child: str | None,
            kiss: KissIcpSettings | None) -> ImportReport:
        for sub in ("measurements", "poses", "lidars/filtered", "maps", "split"):
            (self.room_dir / sub).mkdir(parents=True)
        self._first_pass()
        track, pose_settings = self._poses(poses, csv_poses, tf_parent, tf_child, kiss)
        if (note := upside_down_words(track.poses, f"the poses (--poses {poses})")) is not None:
            self.notes.append(note)
        matches = {s: self._match(s, track, poses) for s in self.cfg.stacks}
        if MAIN_STACK not in matches:
            self.notes.append(f"no stack {MAIN_STACK}: the scores' test points stand at stack {MAIN_STACK}'s frames, so "
                              "train can only map this recording (--gt none); to score it, number the main camera "
                              f"[stacks.{MAIN_STACK}] in the topics file")
        intrinsics = {s: self.camera_info.get(s) or self.plan.intrinsics[s] for s in self.cfg.stacks}
        write_frames(self, matches, intrinsics)
        for mt in matches.values():
            write_tables(self, mt, track)
        writer.write_intrinsics(self.root / "camera_intrinsics.CSV", intrinsics)
        n_map = self._write_map(track)
        n_max = max(len(mt.times_s) for mt in matches.values())
        labels = make_split(n_max, DEFAULT_RATIOS)
        write_split(self.room_dir / "split" / "split.csv", {s: labels[: len(mt.times_s)] for s, mt in matches.items()})
        writer.write_split_description(self.room_dir / "split" / "split_description.csv", DEFAULT_RATIOS)
        self.notes.append("poses_*_balm_sync*.csv hold the same poses as poses_*_sync*.csv (no bundle adjustment)")
        order = [t for t in dict.fromkeys(self.plan.roles.values()) if t in self.reports]
        return ImportReport(
            bag=str(self.reader.path), data_dir=str(self.root), room=self.room, ros_version=self.reader.ros_version,
            poses=poses, samples={s: len(mt.times_s) for s, mt in matches.items()},
            lidar_scans=len(self.lidar_times), map_points=n_map, topics=[self.reports[t] for t in order],
            dropped_frames={s: mt.dropped_frames for s, mt in matches.items()}, pose_settings=pose_settings,
            notes=self.notes)

    # ---------------------------------------------------------------------------- first pass
    def _first_pass(self) -> None:
        by_topic: dict[str, list[Key]] = defaultdict(list)
        for key, topic in self.plan.roles.items():
            by_topic[topic].append(key)
        seen_files: set[str] = set()
        for topic, msg in self.reader.iter_topics(list(by_topic)):
            for stack, role in by_topic[topic]:
                self.stamps[(stack, role)].append(msg.time_s)
                where = m.Where(self.reader.path, topic, msg.index)
                if role == "uss":
                    self.small[(stack, role)].append(m.decode_uss(msg.msg, msg.msgtype, where))
                elif role == "tof":
                    reading = m.decode_tof(msg.msg, where)
                    self.tof_units.add(reading, where)
                    self.small[(stack, role)].append(reading)
                elif role == "camera_info" and stack not in self.camera_info:
                    self.camera_info[stack] = self._camera_info(msg, where)
                elif role == "color" and stack in self.plan.intrinsics and self.plan.intrinsics[stack].width == 0:
                    self.plan.intrinsics[stack] = self._sized(stack, msg, where)
                elif role == "lidar":
                    self._lidar_scan(msg, where, seen_files)
                elif role.startswith("tf"):
                    self.transforms += m.decode_tf(msg.msg, where, static="static" in topic)
                elif role == "odometry":
                    self.odometry.append((msg.time_s, m.decode_odometry(msg.msg, where)))
        if (None, "lidar") not in self.plan.roles:
            self.notes.append(f"no LiDAR topic {self.cfg.lidar.topic} in the bag: no scans and no map (evaluation "
                              "against a map is impossible; a LiDAR on another topic: lidar.topic in a topics file)"
                              if self.cfg.lidar.topic else "no LiDAR (lidar.topic empty): no scans and no map "
                              "(evaluation against a map is impossible)")
        for key in self.plan.roles:
            if key[1] in ("lidar", "camera_info", "odometry") or key[1].startswith("tf"):
                times = self.stamps[key]
                used = len(self.lidar_times) if key[1] == "lidar" else len(times)
                self._report(key, np.array(times), used)
        order = np.argsort(self.lidar_times, kind="stable")
        self.lidar_times = [self.lidar_times[i] for i in order]
        self.lidar_paths = [self.lidar_paths[i] for i in order]

    def _camera_info(self, msg, where: m.Where) -> Intrinsics:
        info = m.decode_camera_info(msg.msg, where)
        if info.distorted:
            self.notes.append(f"{where.topic}: distortion {np.round(info.distortion, 4).tolist()} ignored "
                              "(the layout is pinhole)")
        return info.intrinsics

    def _lidar_scan(self, msg, where: m.Where, seen: set[str]) -> None:
        """Write one scan as a filtered PCD (range limits of the topics file); duplicates skipped."""
        pts = m.decode_scan(msg.msg, where, self.cfg.lidar.min_range_m, self.cfg.lidar.max_range_m)
        self.lidar_frame = self.lidar_frame or m.frame_id(msg.msg)
        name = writer.lidar_file_name(msg.time_s)
        if name in seen:
            return
        seen.add(name)
        path = self.room_dir / "lidars" / "filtered" / name
        write_pcd_xyz(path, pts)
        self.lidar_times.append(msg.time_s)
        self.lidar_paths.append(path)

    def _sized(self, stack: int, msg, where: m.Where) -> Intrinsics:
        """The topics file's intrinsics without a size take the camera's first image's."""
        from virus_nerf.data.ethz import sized_by_image

        rgb = m.decode_color(msg.msg, msg.msgtype, where)
        return sized_by_image(self.plan.intrinsics[stack], rgb.shape, self.cfg.intrinsics_csv or self.reader.path)

    def _report(self, key: Key, times: np.ndarray, used: int) -> None:
        topic = self.plan.roles[key]
        self.reports[topic] = TopicReport(topic, key[1].rstrip("0123456789"), key[0], len(times), used,
                                          float(times.min()) if len(times) else None,
                                          float(times.max()) if len(times) else None)

    # --------------------------------------------------------------------------------- poses
    def _poses(self, poses: str, csv_poses: PoseTrack | None, tf_parent: str, tf_child: str | None,
               kiss: KissIcpSettings | None) -> tuple[PoseTrack, dict | None]:
        if poses == "lidar-odometry":
            if len(self.lidar_times) < 2:
                raise DataFormatError(self.reader.path, f"--poses lidar-odometry: topic "
                                      f"{self.plan.roles[(None, 'lidar')]} has {len(self.lidar_times)} "
                                      "usable scans; expected at least 2")
            settings = self.cfg.lidar.kiss_settings(kiss)
            paths = self.lidar_paths
            registration = ScanRegistration(settings)
            track = kiss_icp_track(np.array(self.lidar_times), lambda k: read_pcd_xyz(paths[k]),
                                   registration=registration)
            floor = registration.describe()
            if "note" in floor:
                self.notes.append(floor["note"])
            return track, {"kiss_icp": dataclasses.asdict(settings), "floor": floor}
        if poses == "tf":
            child = tf_child or self.lidar_frame
            if not child:
                raise UsageError("--poses tf needs --tf-child FRAME (the bag has no LiDAR whose frame could be used)")
            track = tf_track(self.transforms, tf_parent, child, str(self.reader.path))
            return track, {"tf_parent": tf_parent, "tf_child": child}
        if poses == "odometry":
            if len(self.odometry) < 2:
                raise DataFormatError(self.reader.path, f"--poses odometry: topic {self.plan.roles[(None, 'odometry')]}"
                                      f" has {len(self.odometry)} messages; expected at least 2")
            self.odometry.sort(key=lambda tp: tp[0])
            times = np.array([t for t, _ in self.odometry])
            return PoseTrack(times, np.stack([p for _, p in self.odometry])), {
                "odometry_topic": self.plan.roles[(None, "odometry")]}
        assert csv_poses is not None
        return csv_poses, None

    # ------------------------------------------------------------------------------ matching
    def _match(self, s: int, track: PoseTrack, poses: str) -> StackMatch:
        sync, roles = self.cfg.sync, self.cfg.stacks[s].roles()
        color = np.array(self.stamps[(s, "color")])
        tol = {"depth": sync.depth_tolerance_s, "uss": sync.uss_tolerance_s, "tof": sync.tof_tolerance_s}
        streams = {role: (np.array(self.stamps[(s, role)]), tol[role]) for role in tol if role in roles}
        _, pose_ok = track.at(color, sync.pose_tolerance_s)
        match = match_stack(s, color, streams, pose_ok, sync.camera_rate_hz)
        if len(match.times_s) == 0:
            self._unsynchronised(s, color, streams, pose_ok, track, poses)
        self._report((s, "color"), color, len(match.times_s))
        for role, (times, _) in streams.items():
            self._report((s, role), times, len(np.unique(match.partner[role])))
        return match

    def _unsynchronised(self, s: int, color: np.ndarray, streams: dict, pose_ok: np.ndarray, track: PoseTrack,
                        poses: str) -> None:
        """Name the stream that no colour frame could be matched with."""
        ctopic = self.plan.roles[(s, "color")]
        span = f"{color.min():.3f}..{color.max():.3f} s" if len(color) else "no frames"
        for role, (times, tol) in streams.items():
            if (match_nearest(color, times, tol) < 0).all():
                raise DataFormatError(self.reader.path, f"cannot synchronise topic {self.plan.roles[(s, role)]} with "
                                      f"{ctopic}: no message within {tol:g} s of any colour frame (stamps "
                                      f"{times.min():.3f}..{times.max():.3f} s, colour {span}); check the clocks or "
                                      f"raise sync.{role}_tolerance_s in the topics file")
        if not pose_ok.any():
            t = track.times_s
            span_poses = f"poses {t.min():.3f}..{t.max():.3f} s" if len(t) else "no poses"
            raise DataFormatError(self.reader.path, f"cannot synchronise {ctopic} with the poses: no pose within "
                                  f"sync.pose_tolerance_s of any colour frame ({span_poses} of --poses {poses}, "
                                  f"colour {span}); check the clocks")
        raise DataFormatError(self.reader.path, f"stack {s}: no colour frame of {ctopic} has every partner within "
                              "its tolerance (sync section of the topics file)")

    # ----------------------------------------------------------------------------------- map
    def _write_map(self, track: PoseTrack) -> int:
        """The global map as the ETHZ one: 3 cm voxels hit at least twice (docs/method.md 4)."""
        if not self.lidar_times:
            return 0
        vmap = VoxelMap()
        poses, ok = track.at(np.array(self.lidar_times), self.cfg.sync.pose_tolerance_s)
        for k in np.flatnonzero(ok):
            pts = read_pcd_xyz(self.lidar_paths[k]).astype(np.float64)
            vmap.add(pts @ poses[k, :3, :3].T + poses[k, :3, 3])
        pts = vmap.points()
        write_pcd_xyz(self.room_dir / "maps" / "map_balm.pcd", pts)
        return len(pts)
