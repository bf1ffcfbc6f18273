"""Unknown extent (issue 29, item 2): mapping while driving with the box grown from the first frame
(`extent.mode` grow) against the box fitted in advance from the LiDAR map and the whole drive.

Each run is `virus-nerf train --online` (frames released by the training clock at
--playback), or with --steps an offline run of that many steps (bit-reproducible: the
representation's cost alone, whatever else the machine runs), in its own process, one at a time; the NeRF scans are scored at the end against
the LiDAR map at camera height (zone 3, `map` ground truth). The peak resident memory of each run
(its process's ru_maxrss) is reported beside the drive's length.

    python benchmarks/bench_extent.py --scenes common,warehouse --sim-seeds 61,62,63 --out benchmarks/results/extent.json

Modes (--modes, default fitted,grow): fitted, grow (the default of `extent.mode` grow: the box
grown to hold what the robot sensed, D44), grow_sensed (the same, spelt out) and grow_reach (the
first design: the reach around every camera). --grow-config merges a JSON object into the grow
runs' config (a variant, e.g. '{"extent": {"margin_m": 0.2}}'); --keep keeps each run's output
folder (metrics, maps, checkpoint) under a folder for a look afterwards.

Rooms: the simulated rooms under benchmarks/.data (made by bench_time_to_map.py's `ensure_data`).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_out import new_out, write_out

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_time_to_map import DEFAULT_DATA, ensure_data  # noqa: E402

# grow: the default of extent.mode grow (the box grown to hold what the robot sensed, D44);
# grow_sensed: the same, spelt out; grow_reach: the reach around every camera (D38, an option)
MODES = {"fitted": {}, "grow": {"extent": {"mode": "grow"}},
         "grow_reach": {"extent": {"mode": "grow", "grow_from": "reach", "grow_step_m": 2.0}},
         "grow_sensed": {"extent": {"mode": "grow", "grow_from": "sensed"}}}


def merged(base: dict, extra: dict) -> dict:
    """`base` with `extra` merged in, nested objects key by key."""
    out = dict(base)
    for k, v in extra.items():
        out[k] = merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def run_once(data: Path, room: str, mode: str, playback: float, seed: int, work: Path,
             steps: int | None = None, extra: dict | None = None) -> dict:
    """One online training (or, with `steps`, an offline one of that many steps: bit-reproducible,
    so a busy machine changes its wall time only); its zone-3 metrics, wall time and peak memory.
    `extra`: merged into the mode's config (--grow-config)."""
    cfg = work / f"{mode}.json"
    doc = merged(MODES[mode], extra or {})
    cfg.write_text(json.dumps({**doc, **({} if steps is None else {"max_time": None, "max_steps": steps})}))
    out = work / f"run_{data.name}_{mode}_{seed}"
    cmd = [sys.executable, "-m", "virus_nerf.cli", "train", "--data", str(data), "--room", room, "--out", str(out),
           "--gt", "map", "--seed", str(seed), "--config", str(cfg), "--quiet"]
    cmd += ["--online", "--playback", str(playback)] if steps is None else ["--max-steps", str(steps)]
    start = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.monotonic() - start
    err = proc.stderr.read()
    if status != 0:
        raise SystemExit(f"{' '.join(cmd)} failed: {err.strip()[-500:]}")
    doc = json.loads((out / "metrics.json").read_text())
    z3 = doc["sensors"]["NeRF"]["zone3"]
    return {"acc_mean": z3["acc_mean"], "cov_mean": z3["cov_mean"], "wall_s": round(wall, 1),
            "peak_rss_mb": round(usage.ru_maxrss / 1024, 1), "steps": doc["train"]["steps"],
            "safety_all_free": doc.get("safety", {}).get("zones", {}).get("all", {}).get("free_share")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="common,warehouse")
    ap.add_argument("--sim-seeds", default="61,62,63")
    ap.add_argument("--playback", type=float, default=1.0, help="recording seconds per training second")
    ap.add_argument("--steps", type=int, help="offline runs of this many steps instead of online ones")
    ap.add_argument("--train-seed", type=int, default=0)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--modes", default="fitted,grow", help="comma-separated subset of " + ",".join(MODES))
    ap.add_argument("--grow-config", type=json.loads, default={},
                    help='JSON object merged into the grow runs\' config, e.g. \'{"extent": {"margin_m": 0.2}}\'')
    ap.add_argument("--keep", type=Path, help="keep each run's output folder under this folder")
    args = ap.parse_args()
    new_out(args.out)  # before the run: a result is never overwritten
    modes = args.modes.split(",")
    if set(modes) - set(MODES):
        raise SystemExit(f"--modes {args.modes!r}: expected a subset of {','.join(MODES)}")
    if not isinstance(args.grow_config, dict):
        raise SystemExit(f"--grow-config {args.grow_config!r}: expected a JSON object")
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp) if args.keep is None else args.keep
        work.mkdir(parents=True, exist_ok=True)
        for scene in args.scenes.split(","):
            for sim_seed in (int(s) for s in args.sim_seeds.split(",")):
                data = ensure_data(args.data, scene, sim_seed)
                from virus_nerf.data.ethz import load_recording

                drive_s = load_recording(data, scene).duration
                for mode in modes:
                    extra = args.grow_config if mode.startswith("grow") else None
                    r = run_once(data, scene, mode, args.playback, args.train_seed, work, args.steps, extra)
                    r.update(scene=scene, sim_seed=sim_seed, mode=mode, drive_s=round(drive_s, 1))
                    results.append(r)
                    print(json.dumps(r), flush=True)
    summary = {}
    for scene in args.scenes.split(","):
        for mode in modes:
            rows = [r for r in results if r["scene"] == scene and r["mode"] == mode]
            summary[f"{scene}/{mode}"] = {k: round(sum(r[k] for r in rows) / len(rows), 3)
                                          for k in ("acc_mean", "cov_mean", "peak_rss_mb", "steps")}
    doc = {"command": " ".join(sys.argv), "playback": None if args.steps else args.playback, "steps": args.steps, "gt": "map, zone3",
           "grow_config": args.grow_config, "threads": os.environ.get("OMP_NUM_THREADS"), "runs": results,
           "mean": summary}
    print(json.dumps(summary, indent=1))
    if args.out:
        write_out(args.out, json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
