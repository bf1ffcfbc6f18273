"""Training-step throughput on a simulated office: steps/s and samples/s (docs/method.md 10, issue 5/6).

For each (field profile, batch size, grid) the trainer first runs past the grid warm-up
(untimed), then times `--steps` steps. Both grids run in the same process on the same data,
so their steps/s compare directly. Prints one JSON document.

    .venv/bin/python benchmarks/bench_train.py [--steps 20] [--quick]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

from virus_nerf.cli import _keep_large_allocations


def measure(recording, field_name: str, batch: int, grid: str, steps: int, warm: int) -> dict:
    import torch

    from virus_nerf.field.field import FieldConfig
    from virus_nerf.grid.ngp import NgpGridConfig
    from virus_nerf.grid.virus import VirusGridConfig
    from virus_nerf.trainer.config import TrainConfig
    from virus_nerf.trainer.loop import Trainer

    field = FieldConfig.paper() if field_name == "paper" else FieldConfig.cpu_default()
    cfg = dataclasses.replace(
        TrainConfig(), grid=grid, batch_size=batch, max_steps=10**9, max_time=None, image_scale=1.0, field=field,
        # the warm-up is shortened so the timed steps see each grid in its steady state
        virus_grid=VirusGridConfig(warmup_steps=warm // 2), ngp_grid=NgpGridConfig(warmup_steps=warm // 2),
    )
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(recording, cfg, Path(tmp), quiet=True)
        _ = trainer.sampler  # decode frames before timing
        for _ in range(warm):
            trainer.train_step()
        sync = torch.cuda.synchronize if trainer.mapper.device.type == "cuda" else (lambda: None)
        sync()  # on a GPU, time finished work, not queued kernels
        s0, n0 = trainer.mapper.step, trainer.mapper.samples
        t0 = time.perf_counter()
        for _ in range(steps):
            trainer.train_step()
        sync()
        dt = time.perf_counter() - t0
        n = trainer.mapper.samples - n0
        return {
            "steps_per_s": round((trainer.mapper.step - s0) / dt, 3),
            "samples_per_s": round(n / dt),
            "samples_per_ray": round(n / (steps * batch), 1),
            "occupied_share": round(trainer.mapper.grid.occupancy_share(), 4),
            "torch_threads": torch.get_num_threads(),
            "device": str(trainer.mapper.device),
        }


def _only_room(ap: argparse.ArgumentParser, data: Path) -> str:
    """The one room folder of an ETHZ recording (a folder holding measurements/); several or none: refused."""
    rooms = sorted(p.name for p in Path(data).iterdir() if (p / "measurements").is_dir()) if Path(data).is_dir() else []
    if len(rooms) != 1:
        ap.error(f"--data {data}: {'holds the rooms ' + ', '.join(rooms) if rooms else 'holds no room folder'}; "
                 "expected one room (name it with --room)")
    return rooms[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20, help="timed steps per configuration")
    ap.add_argument("--warm", type=int, default=48, help="untimed steps first (grid warm-up is warm/2)")
    ap.add_argument("--quick", action="store_true", help="CPU-default field and 1024 rays only")
    ap.add_argument("--batches", default=None, help="comma-separated rays per step (default 1024,4096)")
    ap.add_argument("--fields", default=None, help="comma-separated field profiles: cpu_default,paper")
    ap.add_argument("--data", type=Path, default=None, help="an ETHZ recording (default: simulate an office)")
    ap.add_argument("--room", default=None, help="the room folder in --data (default: its only room)")
    args = ap.parse_args()
    # the flags checked before anything is simulated or trained, each in one line
    fields = tuple(args.fields.split(",")) if args.fields else None
    if fields is not None and (bad := [f for f in fields if f not in ("cpu_default", "paper")]):
        ap.error(f"--fields {args.fields!r}: unknown profile {bad[0]!r}; expected cpu_default and/or paper")
    try:
        batches = tuple(int(b) for b in args.batches.split(",")) if args.batches else None
    except ValueError:
        ap.error(f"--batches {args.batches!r}: expected comma-separated whole numbers of rays (e.g. 1024,4096)")
    if batches is not None and min(batches) < 1:
        ap.error(f"--batches {args.batches!r}: expected rays per step >= 1")
    if args.steps < 1 or args.warm < 2:
        ap.error(f"--steps {args.steps} --warm {args.warm}: expected --steps >= 1 and --warm >= 2 (the grid warms "
                 "up for warm/2 steps)")
    _keep_large_allocations()
    from virus_nerf.data.ethz import load_recording
    from virus_nerf.sim.command import simulate

    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            data = Path(tmp) / "office"
            simulate(scene="office", out=data, seed=0, duration=20.0, resolution_scale=0.5)
        recording = load_recording(data, args.room or _only_room(ap, data))
        fields = fields or (("cpu_default",) if args.quick else ("cpu_default", "paper"))
        batches = batches or ((1024,) if args.quick else (1024, 4096))
        results = {}
        for field in fields:
            for batch in batches:
                key = f"{field}/batch{batch}"
                results[key] = {g: measure(recording, field, batch, g, args.steps, args.warm) for g in ("virus", "ngp")}
                v, n = results[key]["virus"]["steps_per_s"], results[key]["ngp"]["steps_per_s"]
                results[key]["virus_over_ngp"] = round(v / n, 3) if n else None
                print(key, json.dumps(results[key]), file=sys.stderr, flush=True)
    from bench_time_to_map import gpu_name  # this folder is the script's sys.path[0]

    print(json.dumps({"benchmark": "train_step", "machine": platform.machine(), "cpus": os.cpu_count(), "gpu": gpu_name(),
                      "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"), "results": results}, indent=2))


if __name__ == "__main__":
    main()
