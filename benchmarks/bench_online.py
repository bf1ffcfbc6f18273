"""Mapping while driving against offline training on drives no test uses (issue 29, item 7).

For each simulated drive (one simulation seed each), two runs of the same wall budget, one at a
time, each in its own process: offline (`--max-time` = the drive's length, every frame from the
first step) and online (`--online --playback 1`: frames appear as the training clock passes
their time, the whole drive in the same seconds). Both are scored at the end on all test points
against the LiDAR map at camera height (zone 3, `map` ground truth). Online runs follow the
training clock, so a busy machine changes their numbers: run this on an idle one.

    python benchmarks/bench_online.py --scene office --sim-seeds 71,72,73,74,75 --out benchmarks/results/online_drives.json

--variant NAME=JSON adds an online run per drive with that config merged over --config (e.g.
'view={"virus_grid": {"warmup_restart": "view"}}'), scored against the same offline run.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from bench_out import new_out, write_out

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_time_to_map import DEFAULT_DATA, ensure_data  # noqa: E402


def run(data: Path, room: str, out: Path, online: bool, seconds: float, seed: int, config: str) -> dict:
    cfg = out.parent / f"{out.name}.json"
    cfg.write_text(config)
    cmd = [sys.executable, "-m", "virus_nerf.cli", "train", "--data", str(data), "--room", room, "--out", str(out),
           "--gt", "map", "--seed", str(seed), "--config", str(cfg), "--quiet"]
    cmd += ["--online", "--playback", "1"] if online else ["--max-time", str(seconds)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed: {proc.stderr.strip()[-500:]}")
    doc = json.loads((out / "metrics.json").read_text())
    z3 = doc["sensors"]["NeRF"]["zone3"]
    return {"acc_mean": z3["acc_mean"], "cov_mean": z3["cov_mean"], "steps": doc["train"]["steps"]}


def _merge(base: dict, patch: dict) -> dict:
    """`patch` merged into `base`, section by section."""
    out = dict(base)
    for k, v in patch.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="office")
    ap.add_argument("--sim-seeds", default="71,72,73,74,75")
    ap.add_argument("--train-seed", type=int, default=0)
    ap.add_argument("--config", default="{}", help="partial TrainConfig JSON for both runs")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME=JSON",
                    help="a further online run per drive with this config merged over --config (repeatable); "
                         "its ratios are against the same offline run")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    new_out(args.out)  # before the run: a result is never overwritten
    variants = {}
    for spec in args.variant:
        name, _, patch = spec.partition("=")
        variants[name] = json.dumps(_merge(json.loads(args.config), json.loads(patch)))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for sim_seed in (int(s) for s in args.sim_seeds.split(",")):
            data = ensure_data(args.data, args.scene, sim_seed)
            from virus_nerf.data.ethz import load_recording

            drive_s = load_recording(data, args.scene).duration
            row = {"sim_seed": sim_seed, "drive_s": round(drive_s, 1)}
            for mode in ("offline", "online"):
                r = run(data, args.scene, Path(tmp) / f"{mode}{sim_seed}", mode == "online", drive_s, args.train_seed,
                        args.config)
                row[mode] = r
            row["acc_ratio"] = round(row["online"]["acc_mean"] / row["offline"]["acc_mean"], 3)
            row["cov_ratio"] = round(row["online"]["cov_mean"] / row["offline"]["cov_mean"], 3)
            for name, config in variants.items():
                r = run(data, args.scene, Path(tmp) / f"{name}{sim_seed}", True, drive_s, args.train_seed, config)
                r["acc_ratio"] = round(r["acc_mean"] / row["offline"]["acc_mean"], 3)
                r["cov_ratio"] = round(r["cov_mean"] / row["offline"]["cov_mean"], 3)
                row.setdefault("variants", {})[name] = r
            rows.append(row)
            print(json.dumps(row), flush=True)
    mean = {f"{m}_{k}": round(sum(r[m][k] for r in rows) / len(rows), 4)
            for m in ("offline", "online") for k in ("acc_mean", "cov_mean")}
    mean["acc_online_over_offline"] = round(mean["online_acc_mean"] / mean["offline_acc_mean"], 3)
    mean["cov_online_over_offline"] = round(mean["online_cov_mean"] / mean["offline_cov_mean"], 3)
    mean["worst_acc_ratio"] = max(r["acc_ratio"] for r in rows)
    mean["worst_cov_ratio"] = max(r["cov_ratio"] for r in rows)
    for name in variants:
        runs = [r["variants"][name] for r in rows]
        for k in ("acc_mean", "cov_mean"):
            mean[f"{name}_{k}"] = round(sum(v[k] for v in runs) / len(runs), 4)
        mean[f"{name}_acc_over_offline"] = round(mean[f"{name}_acc_mean"] / mean["offline_acc_mean"], 3)
        mean[f"{name}_cov_over_offline"] = round(mean[f"{name}_cov_mean"] / mean["offline_cov_mean"], 3)
        mean[f"{name}_worst_acc_ratio"] = max(v["acc_ratio"] for v in runs)
        mean[f"{name}_worst_cov_ratio"] = max(v["cov_ratio"] for v in runs)
    doc = {"command": " ".join(sys.argv), "scene": args.scene, "gt": "map, zone3", "config": json.loads(args.config),
           "variants": {k: json.loads(v) for k, v in variants.items()}, "drives": rows, "mean": mean}
    print(json.dumps(mean, indent=1))
    if args.out:
        write_out(args.out, json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
