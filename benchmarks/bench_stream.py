"""Streaming at playback x1 (issue 29, item 3): does `virus-nerf map-bag` keep up with the bag?

For each simulated drive (one simulation seed each, a room no test uses) the recording is written
to a ROS 2 bag (MCAP) once, then `virus-nerf map-bag BAG --playback 1` streams it in its own
process, one run at a time. Reported per drive: the wall seconds from the command's start to the
first snapshot folder, the colour frames mapped and dropped (by reason), the lag at the snapshots
(scaled wall clock minus the newest frame's recording time: median and max), the training steps,
the LiDAR scans KISS-ICP skipped to keep up, and the final map's time. Real time: run this on an idle machine.

    python benchmarks/bench_stream.py --scene office --sim-seeds 61,62,63 --out benchmarks/results/stream.json

--judge also judges each final map (map.pgm / map.yaml as a planner reads them) against the
recording's LiDAR map, as `bench_safety.py --bag` does: the obstacles it marks free within 1 m /
2 m of the path / all, and its free recall (the map ground truth; with --poses lidar-odometry the
map is drawn on KISS-ICP's poses, whose world frame is the first scan's, the simulator's too).

--poses picks the pose source (lidar-odometry: KISS-ICP scan by scan, the default of map-bag;
tf: the recording's poses on /tf, a robot without LiDAR); --args passes further map-bag flags
(a variant, e.g. '--max-poses 10').
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_out import new_out, write_out

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_time_to_map import DEFAULT_DATA  # noqa: E402


def ensure_bag(root: Path, scene: str, seed: int, seconds: float) -> Path:
    """A `seconds` drive through room `seed` (simulated at half resolution, as the time-to-map
    rooms) as a ROS 2 bag in MCAP with the poses also on /tf, made once under `root`."""
    bag = root / "bags" / f"{scene}{seed}_{seconds:.0f}s"
    if not bag.exists():
        from virus_nerf.data.bags.writer import write_bag
        from virus_nerf.sim.command import simulate

        data = root / f"{scene}{seed}_{seconds:.0f}s"
        if not data.exists():
            print(f"simulating {scene} (seed {seed}, {seconds:.0f} s) -> {data}", file=sys.stderr)
            simulate(scene=scene, out=data, seed=seed, duration=seconds, resolution_scale=0.5)
        print(f"writing {bag}", file=sys.stderr)
        bag.parent.mkdir(parents=True, exist_ok=True)
        write_bag(data, bag, ros_version=2, room=scene, storage="mcap", tf=True)
    return bag


def judged(out: Path, data: Path, scene: str) -> dict:
    """The final map's safety figures (bench_safety.judge_files)."""
    from bench_safety import judge_files

    fig = judge_files(out / "map", data, scene)
    return {"map_free_1m": fig["1m"], "map_free_2m": fig["2m"], "map_free_all": fig["all"],
            "map_free_recall": fig["free_recall"]}


def run(bag: Path, out: Path, poses: str, extra: list[str]) -> dict:
    cmd = [sys.executable, "-m", "virus_nerf.cli", "map-bag", str(bag), "--out", str(out), "--playback", "1",
           "--poses", poses] + extra
    start = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    first = None
    while proc.poll() is None:
        if first is None and any((out / "snapshots").glob("0001_*")):
            first = time.monotonic() - start
        time.sleep(0.05)
    stdout, stderr = proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed: {stderr.strip()[-800:]}")
    report = json.loads((out / "stream.json").read_text())
    lags = report["lag_s"]
    dropped = report["dropped"]
    return {
        "first_snapshot_from_start_s": None if first is None else round(first, 2),
        "first_snapshot_from_first_message_s": report["first_snapshot_s"],
        "frames": report["frames"],
        "dropped": dropped,
        "dropped_total": int(sum(dropped.values())),
        "steps": report["steps"],
        "scans_skipped": report.get("scans_skipped"),  # KISS-ICP keeping up (absent before it did)
        "train_s": report["train_s"],
        "wall_s": report["wall_s"],
        "snapshots": len(report["snapshots"]),
        "lag_median_s": round(statistics.median(lags), 3) if lags else None,
        "lag_max_s": round(max(lags), 3) if lags else None,
        "command_s": round(time.monotonic() - start, 2),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="office")
    ap.add_argument("--sim-seeds", default="61,62,63")
    ap.add_argument("--seconds", type=float, default=30.0, help="recording seconds streamed per drive")
    ap.add_argument("--poses", default="lidar-odometry", choices=("lidar-odometry", "tf"))
    ap.add_argument("--args", default="", help="further map-bag flags, one string")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--judge", action="store_true", help="judge each final map against the map ground truth")
    args = ap.parse_args()
    new_out(args.out)  # before the run: a result is never overwritten
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for sim_seed in (int(s) for s in args.sim_seeds.split(",")):
            bag = ensure_bag(args.data, args.scene, sim_seed, args.seconds)
            out = Path(tmp) / f"s{sim_seed}"
            row = {"sim_seed": sim_seed, **run(bag, out, args.poses, shlex.split(args.args))}
            if args.judge:
                row.update(judged(out, args.data / f"{args.scene}{sim_seed}_{args.seconds:.0f}s", args.scene))
            rows.append(row)
            print(json.dumps(row), flush=True)
    frames = sum(r["frames"] for r in rows)
    dropped = sum(r["dropped_total"] for r in rows)
    mean = {
        "frames_mapped_share": round(frames / max(1, frames + dropped), 3),
        "lag_median_s": round(statistics.mean(r["lag_median_s"] for r in rows if r["lag_median_s"] is not None), 3),
        "lag_max_s": max(r["lag_max_s"] for r in rows if r["lag_max_s"] is not None),
        "first_snapshot_from_start_s_max": max(r["first_snapshot_from_start_s"] or 0.0 for r in rows),
        "steps_mean": round(statistics.mean(r["steps"] for r in rows), 1),
    }
    if args.judge:
        mean.update({k: round(statistics.mean(r[k] for r in rows), 4)
                     for k in ("map_free_1m", "map_free_2m", "map_free_all", "map_free_recall")})
    print(json.dumps(mean, indent=1))
    if args.out:
        doc = {"command": "benchmarks/bench_stream.py " + " ".join(sys.argv[1:]), "scene": args.scene,
               "seconds": args.seconds, "poses": args.poses, "args": args.args, "drives": rows, "mean": mean}
        write_out(args.out, json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
