"""Memory a training step takes per marched sample (issue 39 item 3): the constant behind
`engine.memory.SAMPLE_BYTES`, the batch check's bound.

For each of --batches, a fresh process builds the trainer on a simulated office (the default
config, the CPU-default field), decodes its frames, notes its peak RSS, then runs --steps steps
from the start (the grid's warm-up: the most samples per ray a run sees) and notes its peak RSS
again. The step's working memory over its samples is the slope between batch sizes (what does not
grow with the batch, the frames and the network, cancels out). Prints one JSON document.

    .venv/bin/python benchmarks/bench_step_memory.py [--batches 1024,4096,16384] [--data DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
from pathlib import Path


def peak_rss() -> int:
    """Bytes: this process's peak resident set so far (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def child(data: Path, batch: int, steps: int) -> dict:
    from virus_nerf.cli import _keep_large_allocations

    _keep_large_allocations()
    from virus_nerf.data.ethz import load_recording
    from virus_nerf.trainer.config import TrainConfig
    from virus_nerf.trainer.loop import Trainer

    recording = load_recording(data, "office")
    cfg = dataclasses.replace(TrainConfig(), batch_size=batch, max_steps=10**9, max_time=None)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(recording, cfg, Path(tmp), quiet=True)
        _ = trainer.sampler  # the frames decoded: not the step's memory
        trainer.train_step()  # one step so that the network's and the optimiser's state exist
        before = peak_rss()
        first = trainer.mapper.samples
        most = 0
        for _ in range(steps):
            s0 = trainer.mapper.samples
            trainer.train_step()
            most = max(most, trainer.mapper.samples - s0)
        return {"batch": batch, "peak_before_steps": before, "peak_after_steps": peak_rss(),
                "most_samples_in_a_step": most, "samples": trainer.mapper.samples - first,
                "max_samples_per_ray": cfg.march.max_samples}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batches", default="1024,4096,16384")
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument("--data", type=Path, default=None,
                    help="an ETHZ dataset holding an office room (default: simulate one)")
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        print(json.dumps(child(args.data, args.child, args.steps)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            from virus_nerf.sim.command import simulate

            data = Path(tmp) / "office"
            simulate(scene="office", out=data, seed=0, duration=20.0, resolution_scale=0.5)
        rows = []
        for batch in (int(b) for b in args.batches.split(",")):
            cmd = [sys.executable, __file__, "--child", str(batch), "--data", str(data), "--steps", str(args.steps)]
            out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
            rows.append(json.loads(out.strip().splitlines()[-1]))
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    # the step's own memory: peak after the steps minus the peak before them, over the step's samples
    for r in rows:
        r["step_bytes"] = r["peak_after_steps"] - r["peak_before_steps"]
        r["bytes_per_sample"] = round(r["step_bytes"] / max(1, r["most_samples_in_a_step"]))
    first, last = rows[0], rows[-1]
    slope = (last["peak_after_steps"] - first["peak_after_steps"]) / max(
        1, last["most_samples_in_a_step"] - first["most_samples_in_a_step"])
    print(json.dumps({"benchmark": "step_memory", "machine": platform.machine(), "cpus": os.cpu_count(),
                      "rows": rows, "bytes_per_sample_slope": round(slope)}, indent=2))


if __name__ == "__main__":
    main()
