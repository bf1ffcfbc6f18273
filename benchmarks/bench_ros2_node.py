"""The live ROS 2 node against map-bag on the same bag (issue 40's targets), over loopback DDS.

For each simulated drive (bench_stream.py's bags: a room no test uses, half resolution, poses on
/tf) two runs, one after the other:
- `virus-nerf map-bag BAG --playback 1 --poses tf` (the reference);
- `virus-nerf ros2 --poses tf` and `virus-nerf ros2-play BAG --topic ...` (the topics the node
  reads: no depth, no LiDAR; as `ros2 bag play --topics`) started at once (a robot already
  driving when its mapper starts), with a third process, a plain cyclonedds reader, that records
  when each `/map` arrives and decodes the last one.
Reported per drive and run: frames mapped and dropped, the lag at the snapshots taken while the
drive goes on (the node keeps running `--exit-when-idle` seconds after it, when the lag only grows),
steps; for the node the wall seconds from its start to the first `/map` received and the last
`/map`'s size and free / occupied / unknown counts; for both the final map's quality against the
room (obstacles: the simulated LiDAR map within 0.35 m of camera height): occupied cells within
0.3 m of an obstacle, obstacle points within 2 m of the path marked free. Real time: run this on
an idle machine (the player takes ~0.25 of a core).

    python benchmarks/bench_ros2_node.py --sim-seeds 61,62,63 --seconds 30 --out benchmarks/results/ros2_node_d51.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_out import new_out, write_out

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_stream import ensure_bag  # noqa: E402
from bench_time_to_map import DEFAULT_DATA  # noqa: E402

CLI = [sys.executable, "-m", "virus_nerf.cli"]
READER = """
import json, sys, time
import numpy as np
from virus_nerf.ros2 import types
from virus_nerf.ros2.dds import LATCHED, Participant
t0, until = float(sys.argv[1]), float(sys.argv[2])
p = Participant("jazzy", int(sys.argv[3]), loopback=True)
r = p.reader("/map", "nav_msgs/msg/OccupancyGrid", LATCHED)
arrivals, last = [], None
while time.time() < until and not (arrivals and time.time() - t0 - arrivals[-1] > float(sys.argv[4])):
    for s in r.take():
        arrivals.append(round(time.time() - t0, 2))
        last = s
    time.sleep(0.02)
out = {"arrivals_s": arrivals}
if last is not None:
    m = types.deserialize(last.payload, "nav_msgs/msg/OccupancyGrid", types.typestore("jazzy"))
    d = np.asarray(m.data)
    out.update(width=int(m.info.width), height=int(m.info.height), resolution=round(float(m.info.resolution), 4),
               free=int((d == 0).sum()), occupied=int((d == 100).sum()), unknown=int((d == -1).sum()),
               frame_id=m.header.frame_id)
print(json.dumps(out))
p.close()
"""


def map_quality(data: Path, scene: str, folder: Path) -> dict:
    """The final map against the simulated room (module doc)."""
    import yaml
    from PIL import Image
    from scipy.spatial import cKDTree

    from virus_nerf.data.ethz import load_recording

    rec = load_recording(data, scene)
    height = float(np.mean([st.cam_to_world[:, 2, 3].mean() for st in rec.stacks.values()]))
    walls = rec.lidar_map()
    walls = walls[np.abs(walls[:, 2] - height) < 0.35][:, :2]  # (N, 2) the planner map's obstacle band
    path = np.concatenate([st.cam_to_world[:, :2, 3] for st in rec.stacks.values()])
    img = np.asarray(Image.open(folder / "map.pgm"))  # (H, W) row 0 = largest y
    meta = yaml.safe_load((folder / "map.yaml").read_text())
    res, (ox, oy) = meta["resolution"], meta["origin"][:2]
    rows, cols = np.argwhere(img == 0).T
    occupied = np.c_[cols * res + ox, (img.shape[0] - 1 - rows) * res + oy] + res / 2
    near = walls[cKDTree(path).query(walls)[0] < 2.0]
    c = np.floor((near[:, 0] - ox) / res).astype(int)
    r = img.shape[0] - 1 - np.floor((near[:, 1] - oy) / res).astype(int)
    inside = (r >= 0) & (r < img.shape[0]) & (c >= 0) & (c < img.shape[1])
    values = img[r[inside], c[inside]]
    return {"occupied_cells": int(len(occupied)),
            "occupied_within_0.3m": round(float(np.mean(cKDTree(walls).query(occupied)[0] < 0.3)), 3),
            "free_cells": int((img == 254).sum()),
            "obstacles_near_path_marked_free": round(float(np.mean(values == 254)), 3)}


def stream_figures(out: Path, drive_s: float) -> dict:
    report = json.loads((out / "stream.json").read_text())
    times = [float(Path(s).name.split("_")[1].rstrip("s")) for s in report["snapshots"]]
    during = [lag for lag, t in zip(report["lag_s"], times, strict=False) if t <= drive_s + 1.0]
    return {"frames": report["frames"], "dropped": report["dropped"],
            "dropped_total": int(sum(report["dropped"].values())), "steps": report["steps"],
            "lag_during_drive_s": during,
            "lag_median_s": round(statistics.median(during), 3) if during else None,
            "lag_max_s": round(max(during), 3) if during else None}


def run_map_bag(bag: Path, out: Path, snapshot_every: float) -> None:
    proc = subprocess.run([*CLI, "map-bag", str(bag), "--out", str(out), "--playback", "1", "--poses", "tf",
                           "--tf-child", "rslidar", "--snapshot-every", str(snapshot_every)],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"map-bag failed: {proc.stderr.strip()[-800:]}")


def run_node(bag: Path, out: Path, snapshot_every: float, domain: int, drive_s: float) -> dict:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    t0 = time.time()
    reader = subprocess.Popen([sys.executable, "-c", READER, str(t0), str(t0 + drive_s + 90), str(domain), "8"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    node = subprocess.Popen([*CLI, "ros2", "--out", str(out), "--tf-child", "rslidar", "--localhost-only",
                             "--publish-every", str(snapshot_every), "--exit-when-idle", "4"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    # the topics the node reads (as `ros2 bag play --topics`): colour, camera_info, USS, ToF, /tf, /tf_static
    topics = [f"/{kind}{s}" for s in (1, 3) for kind in ("USS", "TOF")] + ["/tf", "/tf_static"] + [
        f"/CAM{s}/color/{name}" for s in (1, 3) for name in ("image_raw", "camera_info")]
    play = subprocess.run([*CLI, "ros2-play", str(bag), "--localhost-only", "--topic", *topics], capture_output=True,
                          text=True, env=env)
    node_out, node_err = node.communicate()
    got = json.loads(reader.communicate()[0] or "{}")
    if play.returncode or node.returncode:
        raise SystemExit(f"ros2 failed: {play.stderr.strip()[-400:]} {node_err.strip()[-800:]}")
    arrivals = got.pop("arrivals_s", [])
    return {"first_map_s": arrivals[0] if arrivals else None, "maps_received": len(arrivals), "last_map": got}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="office")
    ap.add_argument("--sim-seeds", default="61,62,63")
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--snapshot-every", type=float, default=5.0)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    new_out(args.out)  # before the run: a result is never overwritten
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in (int(s) for s in args.sim_seeds.split(",")):
            bag = ensure_bag(args.data, args.scene, seed, args.seconds)
            data = args.data / f"{args.scene}{seed}_{args.seconds:.0f}s"
            ref, live = Path(tmp) / f"mb{seed}", Path(tmp) / f"node{seed}"
            run_map_bag(bag, ref, args.snapshot_every)
            node = run_node(bag, live, args.snapshot_every, 150 + seed % 80, args.seconds)
            row = {"sim_seed": seed,
                   "map_bag": {**stream_figures(ref, args.seconds), "map": map_quality(data, args.scene, ref / "map")},
                   "node": {**stream_figures(live, args.seconds), **node,
                            "map": map_quality(data, args.scene, live / "map")}}
            rows.append(row)
            print(json.dumps(row), flush=True)
    if args.out:
        doc = {"command": "benchmarks/bench_ros2_node.py " + " ".join(sys.argv[1:]), "scene": args.scene,
               "seconds": args.seconds, "drives": rows}
        write_out(args.out, json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
