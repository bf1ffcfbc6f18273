"""Pose error of KISS-ICP LiDAR odometry (import-bag's default poses) on a simulated drive.

Simulates an office drive (or reads an existing simulated recording with --data), registers its
LiDAR scans with each settings variant and prints JSON: the camera-1 pose error against the
simulator's exact poses (median ATE after a rigid best fit, translation m and rotation deg) over
the whole drive and over the first second. Camera poses are derived as import-bag derives them
(LiDAR pose interpolated at the camera stamp x camera-in-LiDAR).

    python benchmarks/bench_bag_odometry.py --duration 20 [--data DIR --room office]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

from virus_nerf.data.bags.odometry import KissIcpSettings, kiss_icp_track
from virus_nerf.data.ethz import load_recording
from virus_nerf.evaluation.trajectory import frame_points, rigid_fit, trajectory_error
from virus_nerf.sensors.rig import camera_in_lidar

VARIANTS = {
    "kiss_defaults": KissIcpSettings.library_defaults(),
    "range30_voxel0.3_no_refine": KissIcpSettings(voxel_size_m=0.3, refine_start_s=0.0),
    "range30_voxel0.2_no_refine": KissIcpSettings(refine_start_s=0.0),
    "range30_voxel0.2_drop_floor_no_refine": KissIcpSettings(refine_start_s=0.0, drop_floor_ceiling_m=0.2),
    "range30_voxel0.2_drop_floor_refine": KissIcpSettings(drop_floor_ceiling_m=0.2),
    "chosen": KissIcpSettings(),
}


def evaluate(rec, settings: KissIcpSettings) -> dict:
    t0 = time.perf_counter()
    track = kiss_icp_track(rec.lidar_times, rec.lidar_scan, settings)
    seconds = time.perf_counter() - t0
    st = rec.stacks[1]
    lidar, ok = track.at(st.times, 0.1)
    est = lidar @ camera_in_lidar(1)
    ref = st.cam_to_world
    align = rigid_fit(frame_points(est[ok]), frame_points(ref[ok]))
    full = trajectory_error(est[ok], ref[ok], align=align)
    first = (st.times[ok] - rec.lidar_times[0]) <= 1.0
    start = trajectory_error(est[ok], ref[ok], mask=first, align=align)
    return {"settings": dataclasses.asdict(settings), "seconds": round(seconds, 2),
            "full": full.as_dict(), "first_second": start.as_dict()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--room", default="office")
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of {','.join(VARIANTS)}")
    args = ap.parse_args()
    if (bad := [v for v in args.variants.split(",") if v not in VARIANTS]):
        ap.error(f"--variants {args.variants!r}: unknown variant {bad[0]!r}; expected some of {','.join(VARIANTS)}")
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            from virus_nerf.sim.command import simulate_dataset

            data = Path(tmp) / "sim"
            simulate_dataset("office", data, seed=args.seed, duration=args.duration, resolution_scale=0.1,
                             progress=False)
        rec = load_recording(data, args.room)
        out = {"data": str(args.data or f"simulated office seed {args.seed}, {args.duration} s"),
               "scans": len(rec.lidar_times), "variants": {}}
        for name in args.variants.split(","):
            out["variants"][name] = evaluate(rec, VARIANTS[name])
            print(name, json.dumps(out["variants"][name]["full"]), json.dumps(out["variants"][name]["first_second"]),
                  flush=True)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
