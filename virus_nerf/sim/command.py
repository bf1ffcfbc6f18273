"""`virus-nerf simulate`: write a simulated recording in the ETHZ format (docs/method.md 5, 7)."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from virus_nerf.data import writer
from virus_nerf.data.pcd import write_pcd_xyz
from virus_nerf.data.split import DEFAULT_RATIOS, make_split, write_split
from virus_nerf.data.voxel_map import VoxelMap
from virus_nerf.sensors.irs import IRS_ZONE_COUNT
from virus_nerf.sensors.rig import (
    CAMERA_INTRINSICS,
    STACK_IDS,
    STACK_TIME_OFFSET_S,
    camera_in_lidar,
)
from virus_nerf.sim.rooms import ROOM_NAMES, Room, build_room
from virus_nerf.sim.sensors import (
    CameraModel,
    DepthModel,
    IrsModel,
    LidarModel,
    UssModel,
    irs_row_mm,
    render_camera,
)
from virus_nerf.sim.trajectory import DrivePath, OdometryDrift, Trajectory, odometry_poses
from virus_nerf.utils.io import new_output_dir

# Timestamps start at a fixed epoch so a seed gives identical files.
TIME_ORIGIN_S = 1_700_000_000.0

# Random streams (one Generator per stream and frame, so changing one sensor does not shift
# the others' noise).
_STREAM = {"room": 0, "depth": 1, "irs": 2, "uss": 3, "lidar": 4, "odometry": 5, "camera": 6}


@dataclass(frozen=True)
class SimConfig:
    """Rates (Hz), sensor models and the odometry drift of one simulated drive."""

    camera_rate: float = 4.8  # per stack; the real recording samples every ~0.208 s
    lidar_rate: float = 10.0
    camera: CameraModel = field(default_factory=CameraModel)
    depth: DepthModel = field(default_factory=DepthModel)
    irs: IrsModel = field(default_factory=IrsModel)
    uss: UssModel = field(default_factory=UssModel)
    lidar: LidarModel = field(default_factory=LidarModel)
    drift: OdometryDrift = field(default_factory=OdometryDrift)


def _rng(seed: int, stream: str, index: int = 0) -> np.random.Generator:
    return np.random.default_rng([seed, _STREAM[stream], index])


def simulate(
    scene: Literal["office", "common", "warehouse"],
    out: Path,
    seed: int = 0,
    duration: float = 60.0,
    resolution_scale: float = 1.0,
) -> None:
    """Simulate a robot drive through a room and write it as an ETHZ-format dataset.

    Writes OUT/camera_intrinsics.CSV and OUT/<scene>/ (measurements, poses, lidars/filtered,
    maps/map_balm.pcd, split, scene.json with the exact geometry). Deterministic for a seed;
    OUT must not exist (it is built under a temporary name and renamed when complete).

    Args:
        scene: room preset, 'office' (~72 m^2), 'common' (common area, ~216 m^2) or 'warehouse'
            (32 x 16 m hall with rows of shelving racks, ~512 m^2; one drive loop takes ~135 s).
        out: output folder (must not exist).
        seed: random seed of the furniture placement and all sensor noise.
        duration: length of the drive in seconds, in (0, 3600].
        resolution_scale: camera image scale in (0, 1] (1.0 = 640x480; intrinsics are scaled to match).
    """
    from virus_nerf.errors import OutputExistsError, UsageError, require_int, require_number

    require_int("--seed", seed, 0, 2**32 - 1)
    require_number("--duration", duration, 0.0, 3600.0)
    require_number("--resolution-scale", resolution_scale, 0.0, 1.0)
    if scene not in ROOM_NAMES:
        raise UsageError(f"--scene {scene!r}: expected one of " + ", ".join(repr(n) for n in ROOM_NAMES))
    if Path(out).exists():
        raise OutputExistsError(out)
    simulate_dataset(scene, Path(out), seed=seed, duration=duration, resolution_scale=resolution_scale)


def simulate_dataset(
    scene: str, out: Path, *, seed: int = 0, duration: float = 60.0, resolution_scale: float = 1.0,
    config: SimConfig | None = None, progress: bool | None = None,
) -> Room:
    """`simulate` with a configurable `SimConfig`; returns the generated room."""
    from tqdm import tqdm

    if duration <= 0:
        raise ValueError(f"duration must be positive seconds, got {duration}")
    if not 0 < resolution_scale <= 1.0:
        raise ValueError(f"resolution_scale must be in (0, 1], got {resolution_scale}")
    cfg = config or SimConfig()
    room = build_room(scene, _rng(seed, "room"))
    traj = Trajectory(DrivePath(room.drive), duration + 0.5)
    intr = {s: CAMERA_INTRINSICS[s].scaled(resolution_scale) if resolution_scale != 1.0 else CAMERA_INTRINSICS[s]
            for s in STACK_IDS}
    if progress is None:
        progress = sys.stderr.isatty()

    with new_output_dir(out) as root:
        room_dir = root / scene
        meas = room_dir / "measurements"
        for sub in ("measurements", "poses", "lidars/filtered", "maps", "split"):
            (room_dir / sub).mkdir(parents=True, exist_ok=True)
        writer.write_intrinsics(root / "camera_intrinsics.CSV", intr)
        room.scene.save(room_dir / "scene.json")

        stack_times = {s: np.arange(0.0, duration - STACK_TIME_OFFSET_S[s] + 1e-9, 1.0 / cfg.camera_rate)
                       + STACK_TIME_OFFSET_S[s] for s in STACK_IDS}
        lidar_times = np.arange(0.0, duration + 1e-9, 1.0 / cfg.lidar_rate)
        n_frames = sum(len(v) for v in stack_times.values())
        bar = tqdm(total=n_frames + len(lidar_times), desc=f"simulate {scene}", unit="frame", disable=not progress)

        for s in STACK_IDS:
            times = stack_times[s]
            (meas / f"CAM{s}_color_image_raw").mkdir()
            (meas / f"CAM{s}_aligned_depth_to_color_image_raw").mkdir()
            lidar_pose = traj.lidar_to_world(times)  # (N, 4, 4)
            cam_pose = lidar_pose @ camera_in_lidar(s)
            uss_r = np.empty(len(times))
            tof_mm = np.empty((len(times), IRS_ZONE_COUNT))
            tof_std = np.empty((len(times), IRS_ZONE_COUNT))
            for i in range(len(times)):
                frame_id = s * 1_000_000 + i
                f = render_camera(room.scene, intr[s], cam_pose[i], cfg.camera, frame_seed=seed * 7919 + frame_id)
                writer.write_png(meas / f"CAM{s}_color_image_raw" / f"img{i}.png", f.rgb)
                depth = cfg.depth.apply(f.z, f.cos_incidence, _rng(seed, "depth", frame_id))
                writer.write_depth(meas / f"CAM{s}_aligned_depth_to_color_image_raw" / f"img{i}.npy", depth)
                grid, std = cfg.irs.measure(room.scene, cam_pose[i], _rng(seed, "irs", frame_id))
                tof_mm[i], tof_std[i] = irs_row_mm(grid, std)
                uss_r[i] = cfg.uss.measure(room.scene, cam_pose[i], _rng(seed, "uss", frame_id))
                bar.update()
            abs_t = TIME_ORIGIN_S + times
            writer.write_uss(meas / f"USS{s}.csv", abs_t, uss_r)
            writer.write_tof(meas / f"TOF{s}.csv", abs_t, tof_mm, tof_std)
            writer.write_poses(room_dir / "poses" / f"poses_cam_balm_sync{s}.csv", abs_t, cam_pose)
            writer.write_poses(room_dir / "poses" / f"poses_lidar_balm_sync{s}.csv", abs_t, lidar_pose)
            odo = odometry_poses(traj, times, cfg.drift, _rng(seed, "odometry"))
            writer.write_poses(room_dir / "poses" / f"poses_cam_sync{s}.csv", abs_t, odo @ camera_in_lidar(s))
            writer.write_poses(room_dir / "poses" / f"poses_lidar_sync{s}.csv", abs_t, odo)

        vmap = VoxelMap()
        for k, t in enumerate(lidar_times):
            pose = traj.lidar_to_world(t)
            pts = cfg.lidar.scan(room.scene, pose, _rng(seed, "lidar", k))
            write_pcd_xyz(room_dir / "lidars" / "filtered" / writer.lidar_file_name(TIME_ORIGIN_S + t), pts)
            vmap.add(pts.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3])
            bar.update()
        write_pcd_xyz(room_dir / "maps" / "map_balm.pcd", vmap.points())
        n_max = max(len(v) for v in stack_times.values())
        labels = make_split(n_max, DEFAULT_RATIOS)
        write_split(room_dir / "split" / "split.csv", {s: labels[: len(stack_times[s])] for s in STACK_IDS})
        writer.write_split_description(room_dir / "split" / "split_description.csv", DEFAULT_RATIOS)
        bar.close()
    return room
