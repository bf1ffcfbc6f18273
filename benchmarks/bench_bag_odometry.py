"""Pose error of KISS-ICP LiDAR odometry (import-bag's default poses) on a simulated drive.

Simulates an office drive (or reads an existing simulated recording with --data), registers its
LiDAR scans with each settings variant and prints JSON: the camera-1 pose error against the
simulator's exact poses (median ATE after a rigid best fit, translation m and rotation deg) over
the whole drive and over the first second, and without the fit (`unaligned`: the simulator's world
frame is the first scan's, as KISS-ICP's; a map is judged in it). Camera poses are derived as
import-bag derives them (LiDAR pose interpolated at the camera stamp x camera-in-LiDAR).

The `skip*` variants register only some scans, as a stream keeping up with a LiDAR faster than
the registration does (map-bag, the ROS 2 node: kiss_worker.py keep_up): every 2nd, or with
gaps of 1, 2 and 3 scans in turn (a busy worker's irregular skipping), with the stream's
settings (no re-registration of the start) and with or without the predicted motion stretched
to the interval registered; compare them with `range30_voxel0.2_no_refine`, the stream's poses
when it registers every scan. `seconds`: reading and registering the scans (one thread).

    python benchmarks/bench_bag_odometry.py --duration 20 [--data DIR --room office]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from virus_nerf.data.bags.odometry import (
    KissIcpSettings,
    PoseTrack,
    ScanRegistration,
    kiss_icp_track,
)
from virus_nerf.data.ethz import load_recording
from virus_nerf.evaluation.trajectory import frame_points, rigid_fit, trajectory_error
from virus_nerf.sensors.rig import camera_in_lidar

SIX_DOF = KissIcpSettings(drop_floor_ceiling_m=0.0, planar=False, refine_start_s=2.0)  # the settings before D118
VARIANTS = {
    "kiss_defaults": KissIcpSettings.library_defaults(),
    "range30_voxel0.3_no_refine": dataclasses.replace(SIX_DOF, voxel_size_m=0.3, refine_start_s=0.0),
    "range30_voxel0.2_no_refine": dataclasses.replace(SIX_DOF, refine_start_s=0.0),
    "range30_voxel0.2_drop_floor_no_refine": dataclasses.replace(SIX_DOF, refine_start_s=0.0, drop_floor_ceiling_m=0.2),
    "range30_voxel0.2_drop_floor_refine": dataclasses.replace(SIX_DOF, drop_floor_ceiling_m=0.2),
    "range30_voxel0.2_refine": SIX_DOF,  # import-bag before D118
    "planar_no_refine": KissIcpSettings(refine_start_s=0.0, drop_floor_ceiling_m=0.0),
    "drop_floor_planar_no_refine": KissIcpSettings(refine_start_s=0.0),  # a stream's (D118)
    "drop_floor_planar_refine": KissIcpSettings(refine_start_s=2.0),  # import-bag's, D118
    "chosen": KissIcpSettings(),
    "refine_start5": KissIcpSettings(refine_start_s=5.0),
    "refine_start8": KissIcpSettings(refine_start_s=8.0),  # import-bag's, D120
    "refine_start12": KissIcpSettings(refine_start_s=12.0),
    "refine_start16": KissIcpSettings(refine_start_s=16.0),
}
STREAM = KissIcpSettings(refine_start_s=0.0)  # a stream cannot re-register its start
SKIPPING = {  # name -> (scans from one registered to the next, in turn; stretch the predicted motion)
    "skip1of2_stretch": ((2,), True),
    "skip_gaps123_stretch": ((1, 2, 3), True),
    "skip_gaps123_no_stretch": ((1, 2, 3), False),
}


def skipping_track(rec, gaps: tuple[int, ...], stretch: bool) -> PoseTrack:
    """The stream's registration of the scans `gaps` apart in turn (the first and the last always)."""
    keep, k = [], 0
    while k < len(rec.lidar_times):
        keep.append(k)
        k += gaps[len(keep) % len(gaps)]
    if keep[-1] != len(rec.lidar_times) - 1:
        keep.append(len(rec.lidar_times) - 1)
    registration = ScanRegistration(STREAM, stretch=stretch)
    poses = np.stack([registration.register(float(rec.lidar_times[k]), rec.lidar_scan(k)) for k in keep])
    return PoseTrack(np.asarray(rec.lidar_times, dtype=np.float64)[keep], poses)


def evaluate(rec, settings: KissIcpSettings | None, skipping: tuple[tuple[int, ...], bool] | None = None) -> dict:
    t0 = time.perf_counter()
    if skipping is None:
        track = kiss_icp_track(rec.lidar_times, rec.lidar_scan, settings)
    else:
        settings = STREAM
        track = skipping_track(rec, *skipping)
    seconds = time.perf_counter() - t0
    st = rec.stacks[1]
    lidar, ok = track.at(st.times, 0.1)
    est = lidar @ camera_in_lidar(1)
    ref = st.cam_to_world
    align = rigid_fit(frame_points(est[ok]), frame_points(ref[ok]))
    full = trajectory_error(est[ok], ref[ok], align=align)
    first = (st.times[ok] - rec.lidar_times[0]) <= 1.0
    start = trajectory_error(est[ok], ref[ok], mask=first, align=align)
    unaligned = trajectory_error(est[ok], ref[ok], align=np.eye(4))  # both frames are the first scan's
    return {"settings": dataclasses.asdict(settings), "seconds": round(seconds, 2),
            "scans_registered": len(track.times_s),
            **({"gaps": list(skipping[0]), "stretch": skipping[1]} if skipping else {}),
            "full": full.as_dict(), "first_second": start.as_dict(), "unaligned": unaligned.as_dict()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--room", default="office")
    names = [*VARIANTS, *SKIPPING]
    ap.add_argument("--variants", default=",".join(names), help=f"comma-separated, of {','.join(names)}")
    ap.add_argument("--scene", default="office", help="the room simulated (without --data)")
    args = ap.parse_args()
    if (bad := [v for v in args.variants.split(",") if v not in names]):
        ap.error(f"--variants {args.variants!r}: unknown variant {bad[0]!r}; expected some of {','.join(names)}")
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            from virus_nerf.sim.command import simulate_dataset

            data = Path(tmp) / "sim"
            simulate_dataset(args.scene, data, seed=args.seed, duration=args.duration, resolution_scale=0.1,
                             progress=False)
        rec = load_recording(data, args.room if args.data else args.scene)
        out = {"data": str(args.data or f"simulated {args.scene} seed {args.seed}, {args.duration} s"),
               "scans": len(rec.lidar_times), "variants": {}}
        for name in args.variants.split(","):
            out["variants"][name] = evaluate(rec, VARIANTS.get(name), SKIPPING.get(name))
            print(name, json.dumps(out["variants"][name]["full"]), json.dumps(out["variants"][name]["first_second"]),
                  json.dumps(out["variants"][name]["unaligned"]), flush=True)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
