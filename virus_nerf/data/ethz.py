"""Reader for recordings in the ETHZ format (docs/method.md 4).

Layout under DATA/: camera_intrinsics.CSV and per room ROOM/measurements, ROOM/poses,
ROOM/lidars/filtered, ROOM/maps, ROOM/split. Everything returned is in metres, seconds and
RGB order; invalid readings are NaN. Images and depth maps are read lazily, one at a time.
Nothing under DATA/ is ever written unless `write_split=True` is asked for.
"""

from __future__ import annotations

import dataclasses
import os
import re
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Literal

import numpy as np

from virus_nerf.data.csvtable import (
    check_sorted_times,
    read_csv_rows,
    read_numeric_csv,
    refuse_bad_header,
)
from virus_nerf.data.frame import SyncFrame
from virus_nerf.data.images import check_depth_header, image_size, read_depth, read_rgb
from virus_nerf.data.pcd import read_pcd_xyz
from virus_nerf.data.split import make_split, read_split, read_split_ratios
from virus_nerf.data.split import write_split as write_split_file
from virus_nerf.errors import DataFormatError, UsageError
from virus_nerf.sensors import irs, uss
from virus_nerf.sensors.camera import Intrinsics, image_side_problem, intrinsics_problem
from virus_nerf.sensors.geometry import QUATERNION_NORM_TOLERANCE, pose_matrix
from virus_nerf.sensors.irs import IRS_MAX_PLAUSIBLE_MM  # noqa: F401 - re-exported (its old home)
from virus_nerf.utils.textfile import not_a_number, quoted

PoseSource = Literal["optimised", "odometry"]
POSE_COLUMNS = ("time", "x", "y", "z", "qx", "qy", "qz", "qw")
TOF_COLUMNS = ("time",) + tuple(f"meas_{k}" for k in range(irs.IRS_ZONE_COUNT))
# QUATERNION_NORM_TOLERANCE (sensors/geometry.py) and IRS_MAX_PLAUSIBLE_MM (sensors/irs.py) are the
# checks a pose or an IRS reading meets wherever it enters: here, in a bag and in a stream
# (data/bags/messages.py). Re-exported under their old home.


@dataclass
class SensorStack:
    """All samples of one sensor stack (camera, aligned depth, USS, IRS); row i = sample i."""

    stack_id: int
    intrinsics: Intrinsics
    times: np.ndarray  # (N,) s, camera timestamps
    cam_to_world: np.ndarray  # (N, 4, 4) OpenCV camera axes, metres
    lidar_to_world: np.ndarray  # (N, 4, 4) LiDAR pose at the same timestamps
    uss_range: np.ndarray  # (N,) m radial, NaN = no echo
    irs_range: np.ndarray  # (N, 8, 8) m z-depth, image zone order, NaN = invalid
    image_paths: list[Path]
    depth_paths: list[Path]
    split: np.ndarray  # (N,) 'train' | 'val' | 'test' | 'skip'

    def __len__(self) -> int:
        return len(self.times)

    def indices(self, label: str) -> np.ndarray:
        """Sample indices with split label `label` ('train', 'val', 'test')."""
        return np.flatnonzero(self.split == label)

    def image(self, i: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB."""
        return read_rgb(self.image_paths[i], self.intrinsics)

    def require_depth(self) -> None:
        """Refuse in one line (DataFormatError naming the folder) when the stack has no depth images."""
        if not self.depth_paths:
            raise DataFormatError(self.image_paths[0].parent.with_name(f"CAM{self.stack_id}_aligned_depth_to_color_image_raw"),
                                  "missing: this recording has no depth images; the rgbd sensor needs them "
                                  "(train without rgbd in --sensors)")

    def depth(self, i: int) -> np.ndarray:
        """(H, W) float32 z-depth in metres, NaN where invalid."""
        self.require_depth()
        return read_depth(self.depth_paths[i], self.intrinsics)

    def frame(self, i: int, with_depth: bool = False) -> SyncFrame:
        """Sample i as a SyncFrame (the image read now; the depth image only if asked)."""
        return SyncFrame(
            time=float(self.times[i]), stack_id=self.stack_id, rgb=self.image(i),
            cam_to_world=self.cam_to_world[i].copy(), uss_range=float(self.uss_range[i]),
            irs_range=self.irs_range[i].copy(), depth=self.depth(i) if with_depth else None,
        )


@dataclass
class Recording:
    """One room of an ETHZ-format dataset."""

    root: Path
    room: str
    stacks: dict[int, SensorStack]
    lidar_times: np.ndarray  # (K,) s
    lidar_paths: list[Path]
    map_path: Path | None
    pose_source: PoseSource = "optimised"
    _map_cache: np.ndarray | None = field(default=None, repr=False)

    @property
    def room_dir(self) -> Path:
        return self.root / self.room

    def lidar_scan(self, k: int) -> np.ndarray:
        """(M, 3) float32 points of LiDAR scan k in the sensor frame."""
        return read_pcd_xyz(self.lidar_paths[k])

    def lidar_map(self) -> np.ndarray:
        """(P, 3) float32 global map points, world frame (cached after the first read)."""
        if self.map_path is None:
            raise DataFormatError(self.room_dir / "maps", "no map_*.pcd found; ground truth needs the LiDAR map")
        if self._map_cache is None:
            self._map_cache = read_pcd_xyz(self.map_path, nonempty="the LiDAR map")
        return self._map_cache

    @cached_property
    def _lidar_pose_track(self) -> tuple[np.ndarray, np.ndarray]:
        times = np.concatenate([s.times for s in self.stacks.values()])
        poses = np.concatenate([s.lidar_to_world for s in self.stacks.values()])
        known = np.isfinite(poses).all(axis=(1, 2))  # a stack without poses_lidar_* holds NaN: left out
        times, poses = times[known], poses[known]
        order = np.argsort(times, kind="stable")
        return times[order], poses[order]

    def lidar_pose_at(self, t: float) -> np.ndarray:
        """LiDAR-to-world (4, 4) at time t, interpolated (slerp) between the stacks' samples."""
        from virus_nerf.sensors.geometry import interpolate_poses

        return interpolate_poses(*self._lidar_pose_track, np.array([t]))[0]

    def camera_poses(self, label: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Camera-to-world (N, 4, 4) and stack id (N,) of every sample (or of those with split
        label `label`), stack by stack in the recording's stack order."""
        stacks = list(self.stacks.values())
        rows = [np.arange(len(st.times)) if label is None else st.indices(label) for st in stacks]
        return (np.concatenate([st.cam_to_world[r] for st, r in zip(stacks, rows, strict=True)]),
                np.concatenate([np.full(len(r), st.stack_id) for st, r in zip(stacks, rows, strict=True)]))

    @property
    def duration(self) -> float:
        t = np.concatenate([s.times for s in self.stacks.values()])
        return float(t.max() - t.min())

    def frame_order(self, labels: tuple[str, ...] | None = None) -> list[tuple[int, int]]:
        """(stack id, sample index) of every sample with a split label in `labels` (None: all),
        in time order (ties: lower stack id first): the order a drive delivers them."""
        entries = [(float(st.times[i]), s, int(i)) for s, st in sorted(self.stacks.items())
                   for i in (range(len(st)) if labels is None else np.flatnonzero(np.isin(st.split, labels)))]
        return [(s, i) for _, s, i in sorted(entries)]


def common_image_size(intrinsics: dict[int, Intrinsics], *, source: Path | None = None,
                      shown: dict[int, Intrinsics] | None = None) -> tuple[int, int]:
    """The one (width, height) of every stack's `intrinsics`; stacks of different sizes are refused in
    one line listing each stack's size (`shown`: the sizes to list, e.g. the recording's own where
    `intrinsics` are scaled), a DataFormatError naming `source` if given, else a UsageError."""
    sizes = {(i.width, i.height) for i in intrinsics.values()}
    if len(sizes) == 1:
        return sizes.pop()
    listed = ", ".join(f"CAM{s} {i.width}x{i.height}" for s, i in sorted((shown or intrinsics).items()))
    problem = (f"the stacks' images differ in size ({listed}); expected one image size for all stacks"
               if sizes else "no sensor stacks; expected at least one")
    if source is not None:
        raise DataFormatError(source, problem)
    raise UsageError(problem)


def read_intrinsics(path: Path, default_size: tuple[int, int] | None = (640, 480)) -> dict[int, Intrinsics]:
    """camera_intrinsics.CSV (cam_id,fx,fy,cx,cy[,width,height]) -> {stack id: Intrinsics}.

    The real recordings have no size columns and are 640x480; simulated ones at another
    resolution add width,height. default_size None: without the columns the size is the images'
    (a bag's topics file), given as 0 x 0 and checked with the principal point once known
    (`sized_by_image`).
    """
    if not path.is_file():
        raise DataFormatError(path, "camera intrinsics file not found (expected cam_id,fx,fy,cx,cy)")
    rows = read_csv_rows(path, "camera intrinsics file")
    expected = ["cam_id", "fx", "fy", "cx", "cy"]
    header = [h.strip() for h in rows[0]] if rows else []
    if header not in (expected, expected + ["width", "height"]):
        refuse_bad_header(path, header)
        raise DataFormatError(path, f"header must be {','.join(expected)} (optionally ,width,height)", row=1)
    out: dict[int, Intrinsics] = {}
    for row_no, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) != len(header):
            raise DataFormatError(path, f"has {len(row)} values; expected {len(header)}", row=row_no)
        m = re.fullmatch(r"CAM([0-9]+)", row[0].strip())
        if not m:
            raise DataFormatError(path, f"cam_id {quoted(row[0])} is not CAM<number>", row=row_no, field="cam_id")
        if int(m.group(1)) in out:  # two calibrations of one camera: which one is meant is not for us to guess
            raise DataFormatError(path, f"cam_id {row[0].strip()} again (an earlier row has it); expected one row "
                                        "per camera", row=row_no, field="cam_id")
        values = []
        for name, text in zip(header[1:], row[1:], strict=True):
            try:
                v = float(text)
            except ValueError:
                raise DataFormatError(path, not_a_number(text), row=row_no, field=name) from None
            if not np.isfinite(v) or (name in ("fx", "fy", "width", "height") and v <= 0):
                raise DataFormatError(path, f"value {v} must be finite (and positive for focal lengths and sizes)",
                                      row=row_no, field=name)
            if name in ("width", "height") and (problem := image_side_problem(v, name)):
                raise DataFormatError(path, problem, row=row_no, field=name)
            values.append(v)
        fx, fy, cx, cy = values[:4]
        size = (int(values[4]), int(values[5])) if len(values) == 6 else (default_size or (0, 0))
        bad = intrinsics_problem(fx, fy, cx, cy, *size) if size != (0, 0) else None
        if bad:
            raise DataFormatError(path, bad[1], row=row_no, field=bad[0])
        out[int(m.group(1))] = Intrinsics(fx, fy, cx, cy, width=size[0], height=size[1])
    return out


def sized_by_image(intr: Intrinsics, rgb_shape: tuple[int, ...], source: str | Path) -> Intrinsics:
    """Intrinsics of unknown size (read_intrinsics with default_size None) given the size of the
    camera's first image (H, W, ...), and checked with it; known ones as they are."""
    if (intr.width, intr.height) != (0, 0):
        return intr
    sized = dataclasses.replace(intr, width=int(rgb_shape[1]), height=int(rgb_shape[0]))
    bad = intrinsics_problem(sized.fx, sized.fy, sized.cx, sized.cy, sized.width, sized.height)
    if bad:
        raise DataFormatError(source, f"{bad[1]} (the size of the camera's images, {sized.width}x{sized.height}: the "
                                      "file gives none)", field=bad[0])
    return sized


def read_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Pose CSV (time,x,y,z,qx,qy,qz,qw) -> times (N,), poses (N, 4, 4)."""
    table = read_numeric_csv(path, POSE_COLUMNS)
    times = table["time"]
    check_sorted_times(path, times)
    xyz = np.stack([table[c] for c in ("x", "y", "z")], axis=1)
    quat = np.stack([table[c] for c in ("qx", "qy", "qz", "qw")], axis=1)
    for name, arr in (("x/y/z", xyz), ("qx/qy/qz/qw", quat)):
        bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
        if bad.size:
            raise DataFormatError(path, "pose is not finite", row=int(bad[0]) + 2, field=name)
    norms = np.linalg.norm(quat, axis=1)
    bad = np.flatnonzero(norms < 1e-6)
    if bad.size:
        raise DataFormatError(
            path, "quaternion has (near) zero norm and cannot be normalised", row=int(bad[0]) + 2, field="qx/qy/qz/qw"
        )
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUATERNION_NORM_TOLERANCE)
    if bad.size:
        i = int(bad[0])
        raise DataFormatError(
            path,
            f"quaternion ({', '.join(f'{v:g}' for v in quat[i])}) has norm {norms[i]:.6g}; expected a unit "
            f"quaternion (| |q| - 1 | <= {QUATERNION_NORM_TOLERANCE:g})",
            row=i + 2,
            field="qx/qy/qz/qw",
        )
    return times, pose_matrix(xyz, quat / norms[:, None])


def read_uss(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """USS<id>.csv (time,meas: echo time in us) -> times (N,), ranges (N,) m, NaN = no echo."""
    table = read_numeric_csv(path, ("time", "meas"))
    check_sorted_times(path, table["time"])
    if (problem := uss.raw_unit_problem(table["meas"])) is not None:
        row, text = problem
        raise DataFormatError(path, text, row=None if row is None else row + 2, field=None if row is None else "meas")
    return table["time"], uss.range_from_raw(table["meas"])


def read_tof(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """TOF<id>.csv (time, meas_0..63 in mm) -> times (N,), (N, 8, 8) m in image zone order."""
    table = read_numeric_csv(path, TOF_COLUMNS)
    check_sorted_times(path, table["time"])
    mm = np.stack([table[f"meas_{k}"] for k in range(irs.IRS_ZONE_COUNT)], axis=1)
    far = irs.implausible_zones(mm)  # (row, zone), row-major: the first row first
    if far.size:
        i, k = (int(v) for v in far[0])
        raise DataFormatError(path, irs.implausible_problem(float(mm[i, k])), row=i + 2, field=f"meas_{k}")
    if (problem := irs.metres_problem(mm)) is not None:
        raise DataFormatError(path, problem)
    return table["time"], irs.grid_from_mm(mm)


def _numbered_files(folder: Path, suffix: str) -> list[Path]:
    """img0.png, img1.png, ... in numeric order; the numbers must run 0..N-1 without gaps."""
    if not folder.is_dir():
        raise DataFormatError(folder, "folder not found")
    found: dict[int, Path] = {}
    for p in folder.iterdir():
        m = re.fullmatch(rf"img(\d+){re.escape(suffix)}", p.name)
        if m:
            found[int(m.group(1))] = p
    if not found:  # img0.jpg, frame_000.png: the folder holds images under names the layout does not read
        others = sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))
        if others:
            raise DataFormatError(folder, f"no img<i>{suffix} among its {len(others)} files (e.g. {others[0]}); "
                                          f"expected them named img0{suffix}, img1{suffix}, ...")
    missing = sorted(set(range(len(found))) - set(found))
    if missing:
        raise DataFormatError(folder / f"img{missing[0]}{suffix}", "file missing (images must be numbered img0..imgN-1)")
    return [found[i] for i in range(len(found))]


def _pose_file(poses_dir: Path, kind: str, stack: int, source: PoseSource) -> Path:
    name = f"poses_{kind}_balm_sync{stack}.csv" if source == "optimised" else f"poses_{kind}_sync{stack}.csv"
    return poses_dir / name


# One sample's readings agree in time within this: row i of a stack's files, and a test point's
# stack-3 frame and LiDAR scan (evaluation/testpoints.py). import-bag pairs a camera frame with its
# USS and IRS readings within the same 0.15 s (topics file). At the office drive's 0.5 m/s the
# robot moves 7.5 cm in it; the real recording's files agree to 0.3 us, its stacks by 27 ms.
SYNC_TOLERANCE_S = 0.15
MAX_JUMP_M, MAX_SPEED_M_S = 1.0, 5.0  # a camera moving farther and faster between two rows is a glitch


def check_same_times(path: Path, times: np.ndarray, camera_times: np.ndarray, camera_file: str) -> None:
    """Rows of a stack's sensor file are matched to the camera's by index (the ETHZ layout): refuse,
    naming the first row, a file whose times are not the camera's within SYNC_TOLERANCE_S (e.g.
    another clock), and say how many rows are off."""
    n = min(len(times), len(camera_times))
    off = np.flatnonzero(~(np.abs(np.asarray(times[:n]) - np.asarray(camera_times[:n])) <= SYNC_TOLERANCE_S))
    if len(off):
        k = int(off[0])
        raise DataFormatError(path, f"time {times[k]:.3f} s is {times[k] - camera_times[k]:+.3f} s from the camera's "
                                    f"{camera_times[k]:.3f} s in {camera_file} ({len(off)} of {n} rows are more than "
                                    f"{SYNC_TOLERANCE_S} s off); expected row i of every file of a stack to be the same "
                                    "sample (clocks that do not agree?)", row=k + 2, field="time")


def check_pose_jumps(path: Path, times: np.ndarray, poses: np.ndarray) -> None:
    """Refuse a camera pose that jumps more than MAX_JUMP_M at more than MAX_SPEED_M_S from the
    previous row (a GPS glitch, an odometry reset), naming its row: a map from it would be wrong."""
    if len(times) < 2:
        return
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)  # (N-1,) m
    dt = np.abs(np.diff(times))
    bad = np.flatnonzero(~((step <= MAX_JUMP_M) | (step <= MAX_SPEED_M_S * dt)))
    if len(bad):
        k = int(bad[0]) + 1
        raise DataFormatError(path, f"the camera jumps {step[k - 1]:.2f} m in {dt[k - 1]:.3f} s (time {times[k]:.3f} s); "
                                    f"expected a continuous drive (at most {MAX_JUMP_M:g} m or {MAX_SPEED_M_S:g} m/s "
                                    "between rows: a pose glitch or an odometry reset?)", row=k + 2, field="x")


def resolve_pose_source(room_dir: Path, wanted: PoseSource) -> tuple[PoseSource, str | None]:
    """The pose source to read: `wanted`, or odometry when `wanted` is "optimised" and the room
    has only odometry pose files (a robot without a LiDAR has no LiDAR-optimised poses); the
    second value is a one-line note when the source was changed, else None."""
    poses_dir = Path(room_dir) / "poses"
    if wanted == "optimised" and not any(poses_dir.glob("poses_cam_balm_sync*.csv")) \
            and any(poses_dir.glob("poses_cam_sync*.csv")):
        return "odometry", (f"{poses_dir}: no optimised poses (poses_cam_balm_sync*.csv); using the odometry "
                            "poses (poses_cam_sync*.csv)")
    return wanted, None


# the files of one sensor stack <id> in ROOM/measurements: any of them names a stack, so a stack
# whose USS, IRS table or image folder is missing fails on that file, not silently left out
STACK_FILE_PATTERNS = (r"USS(\d+)\.csv", r"TOF(\d+)\.csv", r"CAM(\d+)_color_image_raw")


def available_stacks(room_dir: Path) -> list[int]:
    """The sensor stack ids of a room: every <id> that one of its stack files (STACK_FILE_PATTERNS)
    carries in ROOM/measurements."""
    meas = room_dir / "measurements"
    if not meas.is_dir():
        raise DataFormatError(meas, "measurements folder not found")
    ids = sorted({int(m.group(1)) for p in meas.iterdir() for pattern in STACK_FILE_PATTERNS
                  if (m := re.fullmatch(pattern, p.name))})
    if not ids:
        raise DataFormatError(meas, "no sensor stack found; expected USS<id>.csv, TOF<id>.csv and "
                                    "CAM<id>_color_image_raw/ for each stack (USS1.csv, TOF1.csv, ...)")
    return ids


def load_recording(
    data_dir: str | Path,
    room: str,
    *,
    poses: PoseSource = "optimised",
    stacks: list[int] | None = None,
    write_split: bool = False,
    check_images: bool = True,
) -> Recording:
    """Open one room of an ETHZ dataset; reads the tables now, images later on demand.

    If ROOM/split/split.csv is missing, a split is made from split_description.csv (or
    60/0/40) with the same labels for all stacks; it is written only if `write_split`.
    """
    root = Path(data_dir)
    room_dir = root / room
    if not root.is_dir():  # the dataset folder itself (--data), named as such, not as a missing room
        raise DataFormatError(root, ("is a file" if root.exists() else "no such folder")
                              + "; expected the dataset folder that holds the room folders (--data)")
    if not room_dir.is_dir():
        raise DataFormatError(room_dir, f"room folder not found under {root}")
    intrinsics = read_intrinsics(root / "camera_intrinsics.CSV")
    read = {}
    for s in stacks or available_stacks(room_dir):
        if s not in intrinsics:
            raise DataFormatError(root / "camera_intrinsics.CSV", f"no row for CAM{s}", field="cam_id")
        read[s] = _read_stack(room_dir, s, intrinsics[s], poses, check_images)
    splits = _splits(room_dir, {s: len(st) for s, st in read.items()}, write_split)
    lidar_entries = _lidar_scans(room_dir)
    if lidar_entries and not any(np.isfinite(st.lidar_to_world).all() for st in read.values()):
        raise DataFormatError(room_dir / "poses", f"no LiDAR poses (poses_lidar_*sync<id>.csv) for the {len(lidar_entries)} "
                              "LiDAR scans in lidars/filtered; expected them to place the scans (a robot without a LiDAR: "
                              "a recording without lidars/)")
    return Recording(
        root=root,
        room=room,
        stacks={s: dataclasses.replace(st, split=splits[s]) for s, st in read.items()},
        lidar_times=np.array([t for t, _ in lidar_entries]),
        lidar_paths=[p for _, p in lidar_entries],
        map_path=_map_path(room_dir),
        pose_source=poses,
    )


def _read_stack(room_dir: Path, s: int, intr: Intrinsics, poses: PoseSource, check_images: bool) -> SensorStack:
    """Stack `s`'s poses, USS, TOF and image lists, checked against each other (one sample per
    row, the same times, no pose jumps, images of the intrinsics' size); its split comes later."""
    meas = room_dir / "measurements"
    cam_path = _pose_file(room_dir / "poses", "cam", s, poses)
    lidar_path = _pose_file(room_dir / "poses", "lidar", s, poses)
    t_cam, cam_to_world = read_poses(cam_path)
    has_lidar_poses = _present(lidar_path)
    if has_lidar_poses:
        t_lidar, lidar_to_world = read_poses(lidar_path)
    else:  # a robot without a LiDAR: its LiDAR poses are unknown (NaN), never used for mapping
        t_lidar, lidar_to_world = t_cam, np.full_like(cam_to_world, np.nan)
    t_uss, uss_range = read_uss(meas / f"USS{s}.csv")
    t_tof, irs_range = read_tof(meas / f"TOF{s}.csv")
    images = _numbered_files(meas / f"CAM{s}_color_image_raw", ".png")
    depth_dir = meas / f"CAM{s}_aligned_depth_to_color_image_raw"
    depths = _numbered_files(depth_dir, ".npy") if _present(depth_dir, "folder") else []  # no depth camera: none
    counts = {
        cam_path.name: len(t_cam),
        lidar_path.name: len(t_lidar),
        f"USS{s}.csv": len(uss_range),
        f"TOF{s}.csv": len(irs_range),
        f"CAM{s}_color_image_raw/": len(images),
    }
    if depths:  # a robot without a depth camera has none
        counts[f"CAM{s}_aligned_depth_to_color_image_raw/"] = len(depths)
    if len(set(counts.values())) != 1:
        raise DataFormatError(
            room_dir, f"stack {s} files disagree in sample count (row i of each is one sample): {counts}"
        )
    check_same_times(meas / f"USS{s}.csv", t_uss, t_cam, cam_path.name)
    check_same_times(meas / f"TOF{s}.csv", t_tof, t_cam, cam_path.name)
    if has_lidar_poses:
        check_same_times(lidar_path, t_lidar, t_cam, cam_path.name)
    check_pose_jumps(cam_path, t_cam, cam_to_world)
    if check_images and images:
        for p in images:
            size = image_size(p)
            if size != (intr.width, intr.height):
                raise DataFormatError(
                    p, f"image is {size[0]}x{size[1]}; the intrinsics of CAM{s} expect {intr.width}x{intr.height}"
                )
        for p in depths:
            check_depth_header(p, intr)
    return SensorStack(stack_id=s, intrinsics=intr, times=t_cam, cam_to_world=cam_to_world,
                       lidar_to_world=lidar_to_world, uss_range=uss_range, irs_range=irs_range,
                       image_paths=images, depth_paths=depths, split=np.empty(0, dtype=object))


def _present(path: Path, kind: str = "file") -> bool:
    """Whether an optional file (kind "file") or folder ("folder") of the layout is there: False
    when nothing is at `path`; a link that leads nowhere, or a folder where a file belongs (and
    the reverse), is refused in one line, not taken for "absent" (a split file behind a broken
    link would silently give another split)."""
    if kind == "file" and path.is_file() or kind == "folder" and path.is_dir():
        return True
    if path.is_symlink() and not path.exists():
        raise DataFormatError(path, f"a link to {os.readlink(path)}, which does not exist; expected the {kind} "
                                    "itself (or nothing here)")
    if path.exists():
        what = "a folder" if path.is_dir() else "a file" if path.is_file() else "not a regular file"
        raise DataFormatError(path, f"is {what}; expected a {kind} (or nothing here)")
    return False


def _splits(room_dir: Path, lengths: dict[int, int], write_split: bool) -> dict[int, np.ndarray]:
    """Each stack's split labels: split/split.csv, else made from split_description.csv (or
    60/0/40), written only if `write_split`."""
    split_path = room_dir / "split" / "split.csv"
    if _present(split_path):
        return read_split(split_path, lengths)
    ratios = read_split_ratios(room_dir / "split" / "split_description.csv")
    splits = {s: make_split(n, ratios) for s, n in lengths.items()}
    if write_split:
        write_split_file(split_path, splits)
    return splits


def _lidar_scans(room_dir: Path) -> list[tuple[float, Path]]:
    """(time s, path) of lidars/filtered/<seconds>.<nanoseconds>.pcd, in time order."""
    lidar_dir = room_dir / "lidars" / "filtered"
    entries: list[tuple[float, Path]] = []
    if _present(lidar_dir, "folder"):
        for p in lidar_dir.glob("*.pcd"):
            m = re.fullmatch(r"(\d+)\.(\d{9})\.pcd", p.name)
            if not m:  # "1700000000.5.pcd" would read as 5 ns: refused, not guessed
                raise DataFormatError(p, "LiDAR scan name: expected <seconds>.<nanoseconds, 9 digits>.pcd "
                                         "(e.g. 1702374040.067347336.pcd), the scan's time")
            entries.append((int(m.group(1)) + int(m.group(2)) * 1e-9, p))
    return sorted(entries)


def _map_path(room_dir: Path) -> Path | None:
    """The room's LiDAR map: maps/map_balm.pcd, else the first maps/map*.pcd; None without one."""
    maps = sorted((room_dir / "maps").glob("map*.pcd")) if (room_dir / "maps").is_dir() else []
    return next((p for p in maps if p.name == "map_balm.pcd"), maps[0] if maps else None)
