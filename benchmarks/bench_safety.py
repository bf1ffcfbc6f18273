"""Can a planner drive on the map? (issue 42): per simulated room, the 2D map's obstacles marked
free (within 1 m / 2 m of the path / all), its free recall, what the body meets below the band
that it marks free (`below_*`, D113) and a planner's crossings (of the band's obstacles, and
`planner_crossing_below`, of those alone the body meets below the band: D114), with the
range sensors' evidence (maps/planner.py, the default) and without it (the NeRF's scans alone),
beside the anchors (the USS + IRS inverse-sensor map, a LiDAR's 2D map), all from
evaluation/safety.py on the same raster against the `map` ground truth.

Each room is simulated (simulation seeds 81, 82, 83 by default: no test uses them), trained with
the defaults by `virus-nerf train` (offline: bounded by steps, so bit-reproducible and
independent of the machine's load; --online: `train --online --playback 1` with
{"extent": {"mode": "grow"}}, the driving map), then judged twice from its checkpoint (the
Mapper's map, as its snapshots and the run's metrics.json make it: 360 rays from 30 training
positions), and once more as `virus-nerf export` writes map.pgm to disk (the same map since
D85, read from the file and judged along every frame's path: `export`):

    .venv/bin/python benchmarks/bench_safety.py --out benchmarks/results/safety_d47.json
    .venv/bin/python benchmarks/bench_safety.py --online --scenes office,common --out online.json

--bag judges what `map-bag` writes instead: each room's recording is written to a ROS 2 bag
(MCAP, the poses on /tf), streamed by `virus-nerf map-bag BAG --playback 1 --poses tf` in its
own process (real time: run it on an idle machine), and the final map's map.pgm / map.yaml, the
file a planner reads, is judged as it lies on disk against the recording's LiDAR map:

    .venv/bin/python benchmarks/bench_safety.py --bag --out bag.json

--config FILE trains every room with that `train --config` over the defaults (its runs kept under
RUNS/MODE/FILE-STEM/), and --steps 0.63 gives each kind 63 % of its protocol steps: a config whose
steps cost longer is judged at the defaults' wall time (D124):

    .venv/bin/python benchmarks/bench_safety.py --scenes warehouse --config pre.json --steps 0.63 --out pre.json

Runs are kept under --runs (a run folder that exists is judged again, not retrained). Training
runs one at a time: two trainings on 2 cores run ~20x slower each (measured). The JSON holds each
room's figures, their means by room kind (`mean`) and the planner's paths summed over the rooms
(`total`: "N of M paths").
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from bench_out import new_out, write_out

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_time_to_map import ensure_data  # noqa: E402

STEPS = {"office": 1500, "common": 4000, "warehouse": 3000}  # ~ the 55 s / 175 s budgets of issue 42


def train(data: Path, scene: str, run: Path, online: bool, seed: int, config: dict, steps: int) -> None:
    """`virus-nerf train` of one room into `run` (kept: a run folder that exists is not trained
    again), with `config` over the defaults (online: with the grown box as well)."""
    if run.exists():
        return
    cmd = [sys.executable, "-m", "virus_nerf.cli", "train", "--data", str(data), "--room", scene, "--out", str(run),
           "--seed", str(seed), "--quiet"]
    if online:
        config = {**config, "extent": {**config.get("extent", {}), "mode": "grow"}}
        cmd += ["--online", "--playback", "1"]
    else:
        cmd += ["--max-steps", str(steps)]
    if config:
        cfg = run.parent / f"{run.name}.config.json"
        cfg.write_text(json.dumps(config))
        cmd += ["--config", str(cfg)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"training failed ({run}):\n{proc.stderr[-3000:]}")


def judge(run: Path, data: Path, scene: str) -> dict:
    """The run's safety with and without the range evidence, its anchors, and the figures of
    the map.pgm that `virus-nerf export` writes (`exported`)."""
    from virus_nerf.engine import views
    from virus_nerf.evaluation.safety import mapper_safety
    from virus_nerf.maps.occupancy import MAP_POSES
    from virus_nerf.maps.planner import RangeEvidence
    from virus_nerf.trainer.run import load_trained

    trainer, cfg, _ = load_trained(run, "--run")
    trainer._sync_frames()  # the training frames, as `train` had them at its end
    mapper = trainer.mapper
    if "stereo" in cfg.sensors:  # online too: the tracks the drive ended, as offline
        from virus_nerf.stereo.build import stereo_depth

        mapper.set_stereo(stereo_depth(trainer.recording, trainer.store.frame_list(), trainer.stereo_config()))  # cached

    def figures(block: dict, planner: dict | None = None) -> dict:
        out = {z: block["zones"][z]["free_share"] for z in ("1m", "2m", "all")}
        out["free_recall"], out["free_recall_drivable"] = block["free_recall"], block.get("free_recall_drivable")
        out["planner_reach"] = block.get("planner_reach")
        out.update(below_figures(block))
        if planner is not None:
            out["planner_crossing"], out["planner_paths"] = planner["crossing"], planner["paths"]
            out["planner_unsafe_m2"] = planner["unsafe_m2"]
            out["planner_unsafe_2m_m2"] = planner["unsafe_near_m2"]["2m"]
            out.update(planner_below(planner))
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
            "map": figures(after, after["planner"]), "export": judge_files(exported(run), data, scene),
            "nerf_scans_alone": figures(before, before["planner"]),
            "sensors_alone": figures(after["anchors"]["sensors"]), "lidar": figures(after["anchors"]["lidar"])}


def exported(run: Path) -> Path:
    """RUN/export_map/: `virus-nerf export --what map` of the run with its defaults (made once)."""
    out = run / "export_map"
    if not out.exists():
        cmd = [sys.executable, "-m", "virus_nerf.cli", "export", "--run", str(run), "--out", str(out), "--what", "map"]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"export failed ({run}):\n{proc.stderr[-3000:]}")
    return out


def stream(data: Path, scene: str, bags: Path, run: Path) -> None:
    """The room's recording as a ROS 2 bag (made once under `bags`), mapped by `map-bag` at
    playback 1 into `run` (kept: a run folder that exists is judged again, not streamed again)."""
    from virus_nerf.data.bags.writer import write_bag

    bag = bags / data.name
    if bag.exists() and not (bag / "metadata.yaml").is_file():  # the writer puts it last
        sys.exit(f"{bag}: a bag whose writing was stopped (no metadata.yaml); remove it to write it again")
    if not bag.exists():
        bags.mkdir(parents=True, exist_ok=True)
        write_bag(data, bag, ros_version=2, room=scene, storage="mcap", tf=True)
    if run.exists():
        if not (run / "map" / "map.pgm").is_file():  # a stream that was stopped before its final map
            sys.exit(f"{run}: a map-bag run without its final map (stopped?); run `virus-nerf map-bag --resume "
                     f"--out {run}` or choose another --runs")
        return
    cmd = [sys.executable, "-m", "virus_nerf.cli", "map-bag", str(bag), "--out", str(run), "--playback", "1",
           "--poses", "tf"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"map-bag failed ({run}):\n{proc.stderr[-3000:]}")


def read_map_files(folder: Path):
    """(image (H, W) uint8, origin (x, y) m, resolution m) of folder/map.pgm and map.yaml (read as
    bench_ros2_node.py reads it: PyYAML, which the dev extra brings)."""
    import yaml
    from PIL import Image

    meta = yaml.safe_load((folder / "map.yaml").read_text())
    image = np.asarray(Image.open(folder / meta["image"]))
    return image, (float(meta["origin"][0]), float(meta["origin"][1])), float(meta["resolution"])


def judge_files(folder: Path, data: Path, scene: str) -> dict:
    """map.pgm / map.yaml in `folder` against the recording's LiDAR map at the cameras' height
    (+-the evaluation's band), the path being every camera position of the recording."""
    from virus_nerf.data.ethz import load_recording
    from virus_nerf.data.room_box import fit_scene_box
    from virus_nerf.evaluation.evaluate import EvaluationConfig
    from virus_nerf.evaluation.gt import body_slice, height_slice
    from virus_nerf.evaluation.safety import judge_map, planner_check
    from virus_nerf.maps.extract import camera_height

    rec = load_recording(data, scene)
    poses, stack_ids = rec.camera_poses()  # (N, 4, 4), (N,): every frame
    image, origin, resolution = read_map_files(folder)
    height, band = camera_height(poses, stack_ids), EvaluationConfig().height_band_m
    obstacles = height_slice(rec.lidar_map(), height, band)
    box = fit_scene_box(rec)
    body = body_slice(rec.lidar_map(), height, band)  # (B, 2) what the body meets below the band
    block = judge_map(image, origin, resolution, obstacles, poses[:, :2, 3], extent=(box.lo[:2], box.hi[:2]),
                      body_xy=body).block()
    planner = planner_check(image, origin, resolution, obstacles, path_xy=poses[:, :2, 3], body_xy=body).block()
    out = {z: block["zones"][z]["free_share"] for z in ("1m", "2m", "all")}
    out.update(free_recall=block["free_recall"], free_recall_drivable=block["free_recall_drivable"],
               planner_reach=block["planner_reach"], planner_crossing=planner["crossing"], planner_paths=planner["paths"],
               planner_unsafe_m2=planner["unsafe_m2"], planner_unsafe_2m_m2=planner["unsafe_near_m2"]["2m"])
    out.update(below_figures(block))
    out.update(planner_below(planner))
    return out


def below_figures(block: dict) -> dict:
    """What the body meets below the band marked free, by zone ("below_1m", ...; none without the
    body's ground truth)."""
    return {f"below_{z}": b["free_share"] for z, b in (block.get("below_band") or {}).items()}


def planner_below(planner: dict) -> dict:
    """The planner's paths that pass only what the body meets below the band, and where its centre
    may touch that (m^2); none for a block written without the body's ground truth."""
    if planner.get("crossing_below") is None:
        return {}
    return {"planner_crossing_below": planner["crossing_below"], "planner_unsafe_below_m2": planner["unsafe_below_m2"]}


def judge_bag(run: Path, data: Path, scene: str) -> dict:
    report = json.loads((run / "stream.json").read_text())
    return {"run": str(run), "frames": report["frames"], "dropped": int(sum(report["dropped"].values())),
            "steps": report["steps"], "map": judge_files(run / "map", data, scene)}


COUNTS = ("planner_paths", "planner_crossing", "planner_crossing_below")  # summed over rooms as well


def totals(rows: list[dict]) -> dict:
    """The planner's counts summed over rooms ("N of M paths"): each count that every row holds
    (a room without a floor has no `planner_crossing_below`, and then no room's is summed)."""
    return {k: sum(r[k] for r in rows) for k in COUNTS if all(r.get(k) is not None for r in rows)}


def mean(rows: list[dict]) -> dict:
    """Each figure's mean over the rooms that have it (a room without a floor has no `below_*`)."""
    keys = dict.fromkeys(k for r in rows for k in r)  # every row's keys, in order
    return {k: round(sum(v) / len(v), 4) if (v := [r[k] for r in rows if r.get(k) is not None]) else None
            for k in keys}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="office,common,warehouse")
    ap.add_argument("--seeds", default="81,82,83")
    ap.add_argument("--online", action="store_true", help="train while driving (playback 1, grown box)")
    ap.add_argument("--bag", action="store_true", help="map-bag at playback 1 on each room's bag, its map.pgm judged")
    ap.add_argument("--data", type=Path, default=HERE / ".data")
    ap.add_argument("--runs", type=Path, default=HERE / ".runs")
    ap.add_argument("--train-seed", type=int, default=0)
    ap.add_argument("--config", type=Path, help="a `train --config` JSON over the defaults (runs kept under "
                    "RUNS/MODE/CONFIG-NAME/)")
    ap.add_argument("--steps", type=float, default=1.0, help="offline: this share of each kind's protocol steps "
                    "(e.g. 0.63 for a config whose steps cost 1/0.63 as long: the same wall time)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    config = json.loads(args.config.read_text()) if args.config else {}
    if args.bag and config:
        ap.error("--config: map-bag runs take the defaults")
    if args.steps <= 0 or (args.steps != 1.0 and (args.online or args.bag)):
        ap.error(f"--steps {args.steps}: expected a share > 0 of the offline protocol's steps (a drive has no budget)")
    new_out(args.out)  # before the run: a result is never overwritten
    budget = {scene: round(n * args.steps) for scene, n in STEPS.items()}
    mode = "bag" if args.bag else "online" if args.online else "offline"
    # steps: what each kind's rooms trained, in seed order (one number where they agree); a run
    # kept under --runs from another budget is judged as it is and labelled with its own steps
    doc: dict = {"mode": mode, "online": args.online, "protocol_steps": budget if mode == "offline" else None,
                 "config": config, "steps": {}, "gt": "map", "rooms": {}, "mean": {}, "total": {}}
    for scene in args.scenes.split(","):
        rows = []
        for seed in (int(s) for s in args.seeds.split(",")):
            data = ensure_data(args.data, scene, seed)
            run = args.runs / mode / (args.config.stem if args.config else "") / f"{scene}{seed}"
            run.parent.mkdir(parents=True, exist_ok=True)
            if args.bag:
                stream(data, scene, args.data / "bags", run)
                rows.append(judge_bag(run, data, scene))
            else:
                train(data, scene, run, args.online, args.train_seed, config, budget[scene])
                rows.append(judge(run, data, scene))
            doc["rooms"][f"{scene}{seed}"] = rows[-1]
            print(json.dumps({f"{scene}{seed}": rows[-1]}), file=sys.stderr)
        steps = [r["steps"] for r in rows]
        doc["steps"][scene] = steps[0] if len(set(steps)) == 1 else steps
        if mode == "offline" and set(steps) != {budget[scene]}:
            print(f"note: {scene}: rooms trained {steps} steps, not the protocol's {budget[scene]} (runs kept under "
                  f"{args.runs})", file=sys.stderr)
        kinds = ("map",) if args.bag else ("map", "export", "nerf_scans_alone", "sensors_alone", "lidar")
        doc["mean"][scene] = {k: mean([r[k] for r in rows]) for k in kinds}
        doc["total"][scene] = {k: t for k in kinds if (t := totals([r[k] for r in rows]))}
    write_out(args.out, json.dumps(doc, indent=1) + "\n")
    print(json.dumps({"mean": doc["mean"], "total": doc["total"]}, indent=1))


if __name__ == "__main__":
    main()
