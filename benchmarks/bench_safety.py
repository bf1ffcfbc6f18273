"""Can a planner drive on the map? (issue 42): per simulated room, the 2D map's obstacles marked
free (within 1 m / 2 m of the path / all), its free recall and a planner's crossings, with the
range sensors' evidence (maps/planner.py, the default) and without it (the NeRF's scans alone),
beside the anchors (the USS + IRS inverse-sensor map, a LiDAR's 2D map), all from
evaluation/safety.py on the same raster against the `map` ground truth.

Each room is simulated (simulation seeds 81, 82, 83 by default: no test uses them), trained with
the defaults by `virus-nerf train` (offline: bounded by steps, so bit-reproducible and
independent of the machine's load; --online: `train --online --playback 1` with
{"extent": {"mode": "grow"}}, the driving map), then judged twice from its checkpoint:

    .venv/bin/python benchmarks/bench_safety.py --out benchmarks/results/safety_d47.json
    .venv/bin/python benchmarks/bench_safety.py --online --scenes office,common --out online.json

Runs are kept under --runs (a run folder that exists is judged again, not retrained). Training
runs one at a time: two trainings on 2 cores run ~20x slower each (measured).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_time_to_map import ensure_data  # noqa: E402

STEPS = {"office": 1500, "common": 4000, "warehouse": 3000}  # ~ the 55 s / 175 s budgets of issue 42


def train(data: Path, scene: str, run: Path, online: bool, seed: int) -> None:
    if run.exists():
        return
    cmd = [sys.executable, "-m", "virus_nerf.cli", "train", "--data", str(data), "--room", scene, "--out", str(run),
           "--seed", str(seed), "--quiet"]
    if online:
        cfg = run.parent / "grow.json"
        cfg.write_text(json.dumps({"extent": {"mode": "grow"}}))
        cmd += ["--online", "--playback", "1", "--config", str(cfg)]
    else:
        cmd += ["--max-steps", str(STEPS[scene])]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"training failed ({run}):\n{proc.stderr[-3000:]}")


def judge(run: Path) -> dict:
    """The run's safety with and without the range evidence, and its anchors."""
    from virus_nerf.engine import views
    from virus_nerf.evaluation.safety import MAP_POSES, mapper_safety
    from virus_nerf.maps.planner import RangeEvidence
    from virus_nerf.trainer.run import load_trained

    trainer, cfg, _ = load_trained(run, "--run")
    trainer._sync_frames()  # the training frames, as `train` had them at its end
    mapper = trainer.mapper
    if "stereo" in cfg.sensors:  # online too: the tracks the drive ended, as offline
        from virus_nerf.stereo.build import stereo_depth

        mapper.set_stereo(stereo_depth(trainer.recording, trainer.store.frame_list(), cfg.stereo))  # cached

    def figures(block: dict, planner: dict | None = None) -> dict:
        out = {z: block["zones"][z]["free_share"] for z in ("1m", "2m", "all")}
        out["free_recall"] = block["free_recall"]
        if planner is not None:
            out["planner_crossing"], out["planner_paths"] = planner["crossing"], planner["paths"]
        return out

    after = mapper_safety(mapper, trainer.recording, cfg.evaluation.height_band_m).document
    evidence = views.MapViews.range_evidence
    views.MapViews.range_evidence = lambda self: RangeEvidence.empty()
    try:
        mapper.update_map(0.05, max_poses=MAP_POSES)  # the scans alone, for the query that follows
        before = mapper_safety(mapper, trainer.recording, cfg.evaluation.height_band_m).document
    finally:
        views.MapViews.range_evidence = evidence
    return {"run": str(run), "frames": mapper.frames, "steps": mapper.step,
            "map": figures(after, after["planner"]), "nerf_scans_alone": figures(before, before["planner"]),
            "sensors_alone": figures(after["anchors"]["sensors"]), "lidar": figures(after["anchors"]["lidar"])}


def mean(rows: list[dict]) -> dict:
    keys = rows[0].keys()
    return {k: round(sum(r[k] for r in rows if r[k] is not None) / max(1, sum(r[k] is not None for r in rows)), 4)
            for k in keys}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="office,common,warehouse")
    ap.add_argument("--seeds", default="81,82,83")
    ap.add_argument("--online", action="store_true", help="train while driving (playback 1, grown box)")
    ap.add_argument("--data", type=Path, default=HERE / ".data")
    ap.add_argument("--runs", type=Path, default=HERE / ".runs")
    ap.add_argument("--train-seed", type=int, default=0)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    if args.out.exists():
        sys.exit(f"--out {args.out}: exists; choose a new file (nothing is overwritten)")
    doc: dict = {"online": args.online, "steps": None if args.online else STEPS, "gt": "map", "rooms": {},
                 "mean": {}}
    for scene in args.scenes.split(","):
        rows = []
        for seed in (int(s) for s in args.seeds.split(",")):
            data = ensure_data(args.data, scene, seed)
            run = args.runs / ("online" if args.online else "offline") / f"{scene}{seed}"
            run.parent.mkdir(parents=True, exist_ok=True)
            train(data, scene, run, args.online, args.train_seed)
            rows.append(judge(run))
            doc["rooms"][f"{scene}{seed}"] = rows[-1]
            print(json.dumps({f"{scene}{seed}": rows[-1]}), file=sys.stderr)
        doc["mean"][scene] = {k: mean([r[k] for r in rows])
                              for k in ("map", "nerf_scans_alone", "sensors_alone", "lidar")}
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    print(json.dumps(doc["mean"], indent=1))


if __name__ == "__main__":
    main()
