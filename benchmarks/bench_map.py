"""How long the planner's map and a snapshot take (issue 42, item 4: a snapshot may not get slower
by more than a quarter): for trained run folders, the median wall time of `Mapper.update_map`
(the NeRF's scans, the observed mask, the range evidence: `map.pgm`) and of `Mapper.snapshot`
(map.pgm, prob.pgm, their PNGs and snapshot.json) over --repeats, with torch's default threads
(--threads to set them). Run it on an idle machine; compare commits on the same runs:

    .venv/bin/python benchmarks/bench_map.py --runs RUN [RUN ...] --out map_time.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from bench_out import new_out, write_out


def time_run(run: Path, repeats: int) -> dict:
    from virus_nerf.maps.occupancy import MAP_POSES
    from virus_nerf.trainer.run import load_trained

    trainer, cfg, _ = load_trained(run, "--run")
    trainer._sync_frames()  # the training frames, as `train` had them at its end
    mapper = trainer.mapper
    if "stereo" in cfg.sensors:  # the stereo points the map's rules ask about, as while driving (cached pass)
        from virus_nerf.stereo.build import stereo_depth

        mapper.set_stereo(stereo_depth(trainer.recording, trainer.store.frame_list(), trainer.stereo_config()))
    mapper.update_map(0.05, max_poses=MAP_POSES)  # warm: the observed mask is cached as while driving
    maps, snaps = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(repeats):
            t = time.perf_counter()
            mapper.update_map(0.05, max_poses=MAP_POSES)
            maps.append(time.perf_counter() - t)
            mapper._map_cache = None  # a snapshot after a training step renders the map again
            t = time.perf_counter()
            mapper.snapshot(Path(tmp) / f"s{k}", max_poses=MAP_POSES)
            snaps.append(time.perf_counter() - t)
    return {"run": str(run), "frames": mapper.frames, "map_s": round(statistics.median(maps), 3),
            "snapshot_s": round(statistics.median(snaps), 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=Path, nargs="+", required=True)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, help="torch threads (default: torch's own)")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    new_out(args.out)  # before the run: a result is never overwritten
    if (missing := [r for r in args.runs if not (r / "checkpoint.pt").is_file()]):
        ap.error(f"--runs: {missing[0]} is no trained run (no checkpoint.pt there)")
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    rows = [time_run(r, args.repeats) for r in args.runs]
    for r in rows:
        print(json.dumps(r))
    if args.out is not None:
        write_out(args.out, json.dumps({"threads": torch.get_num_threads(), "repeats": args.repeats, "runs": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
