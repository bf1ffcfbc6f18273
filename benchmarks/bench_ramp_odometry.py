"""KISS-ICP's LiDAR poses on a ramp: `flat_floor` true (planar, the default) against false (D119).

The simulated room (its preset and furniture, seeded as `virus-nerf simulate` seeds it) gets a
ramp across its whole width: from x = --ramp-start m (the drive starts at x = 0) it rises at
--ramp-deg over --ramp-length m to a plateau that fills the rest of the room, built of boxes 5 cm
deep (5.3 mm steps at 6 deg, within the LiDAR's noise). The robot drives the room's usual path;
its LiDAR is pitched with the floor under the robot (the mean slope over 0.5 m, a wheelbase) and
lifted with it. Only LiDAR scans are simulated; each variant registers them as import-bag does
(kiss_icp_track, the start re-registered). Reported: the LiDAR's position error against the
simulator's poses (3D and along the floor, median and max, m), its height (min and max, m, in the
first floor's frame) and the tilt it registers (median, 90th percentile and max, deg).

    python benchmarks/bench_ramp_odometry.py --scene common --seed 71 --ramp-deg 6 --duration 30
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from virus_nerf.data.bags.odometry import KissIcpSettings, find_floor, kiss_icp_track

VARIANTS = {"flat_floor_true": KissIcpSettings(), "flat_floor_false": KissIcpSettings(planar=False)}
WHEELBASE_M = 0.5
STEP_M = 0.05  # the ramp's boxes, deep


def ramp_drive(scene: str, seed: int, ramp_deg: float, ramp_start_m: float, ramp_length_m: float,
               duration_s: float, rate_hz: float = 10.0):
    """(times (K,) s, LiDAR-to-world poses (K, 4, 4), scans: K arrays (M, 3) in the sensor frame)."""
    from scipy.spatial.transform import Rotation

    from virus_nerf.sensors.rig import LIDAR_HEIGHT_M
    from virus_nerf.sim.command import _rng
    from virus_nerf.sim.rooms import build_room
    from virus_nerf.sim.scene import Box, Scene, SceneObject
    from virus_nerf.sim.sensors import LidarModel
    from virus_nerf.sim.trajectory import DrivePath, Trajectory

    room = build_room(scene, _rng(seed, "room"))
    lo, hi = np.asarray(room.scene.extent_lo), np.asarray(room.scene.extent_hi)
    floor_z = -LIDAR_HEIGHT_M  # the world frame is the LiDAR's at the start
    tan = np.tan(np.radians(ramp_deg))
    boxes = []
    for i in range(int(round(ramp_length_m / STEP_M))):  # each box from its step to the room's end
        x, rise = ramp_start_m + i * STEP_M, (i + 1) * STEP_M * tan
        boxes.append(Box(((x + hi[0]) / 2, (lo[1] + hi[1]) / 2, floor_z + rise / 2), (hi[0] - x, hi[1] - lo[1], rise)))
    floor = next(o for o in room.scene.objects if o.kind == "floor")
    world = Scene([*room.scene.objects, SceneObject("ramp", "floor", tuple(boxes), floor.material)],
                  room.scene.name, room.scene.extent_lo, room.scene.extent_hi, room.scene.meta)

    def rise(x: float) -> float:
        return float(np.clip((x - ramp_start_m) * tan, 0.0, ramp_length_m * tan))

    traj = Trajectory(DrivePath(room.drive), duration_s + 0.5)
    lidar = LidarModel()
    times = np.arange(0.0, duration_s + 1e-9, 1.0 / rate_hz)
    poses, scans = np.empty((len(times), 4, 4)), []
    for k, t in enumerate(times):
        flat = np.asarray(traj.lidar_to_world(t))  # on the flat floor
        x, y = flat[0, 3], flat[1, 3]
        front, back = rise(x + WHEELBASE_M / 2), rise(x - WHEELBASE_M / 2)
        tilt = np.eye(4)  # about the floor point under the LiDAR, then up the ramp
        tilt[:3, :3] = Rotation.from_euler("y", -np.arctan2(front - back, WHEELBASE_M)).as_matrix()
        foot = np.eye(4)
        foot[:3, 3] = [x, y, floor_z]
        up = np.eye(4)
        up[2, 3] = (front + back) / 2
        poses[k] = up @ foot @ tilt @ np.linalg.inv(foot) @ flat
        scans.append(lidar.scan(world, poses[k], _rng(seed, "lidar", k)))
    return times, poses, scans


def evaluate(times, poses, scans, settings: KissIcpSettings) -> dict:
    t0 = time.perf_counter()
    est = kiss_icp_track(times, lambda k: scans[k], settings).poses
    seconds = time.perf_counter() - t0
    truth = np.linalg.inv(poses[0]) @ poses  # in the first scan's frame, as KISS-ICP's
    level = np.eye(4)
    level[:3, :3] = find_floor(scans[0]).level()
    flat = level @ est @ level.T  # z along the first floor's normal
    err = np.linalg.norm(est[:, :3, 3] - truth[:, :3, 3], axis=1)
    along = np.linalg.norm((level @ truth @ level.T)[:, :2, 3] - flat[:, :2, 3], axis=1)
    tilt = np.degrees(np.arccos(np.clip(flat[:, 2, 2], -1.0, 1.0)))
    r = lambda v: round(float(v), 4)  # noqa: E731
    return {"error_median_m": r(np.median(err)), "error_max_m": r(err.max()),
            "along_floor_median_m": r(np.median(along)), "along_floor_max_m": r(along.max()),
            "height_min_m": r(flat[:, 2, 3].min()), "height_max_m": r(flat[:, 2, 3].max()),
            "tilt_median_deg": r(np.median(tilt)), "tilt_p90_deg": r(np.percentile(tilt, 90)), "tilt_max_deg": r(tilt.max()),
            "seconds": round(seconds, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="common")
    ap.add_argument("--seed", type=int, default=71)
    ap.add_argument("--ramp-deg", type=float, default=6.0)
    ap.add_argument("--ramp-start", type=float, default=4.0, help="m along the drive's first leg")
    ap.add_argument("--ramp-length", type=float, default=3.0, help="m")
    ap.add_argument("--duration", type=float, default=30.0, help="s")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    args = ap.parse_args()
    times, poses, scans = ramp_drive(args.scene, args.seed, args.ramp_deg, args.ramp_start, args.ramp_length,
                                     args.duration)
    truth = np.linalg.inv(poses[0]) @ poses
    out = {"scene": args.scene, "seed": args.seed, "ramp_deg": args.ramp_deg, "ramp_start_m": args.ramp_start,
           "ramp_length_m": args.ramp_length, "duration_s": args.duration,
           "true_height_max_m": round(float(truth[:, 2, 3].max()), 4), "variants": {}}
    for name in args.variants.split(","):
        out["variants"][name] = evaluate(times, poses, scans, VARIANTS[name])
        print(name, json.dumps(out["variants"][name]), flush=True)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
