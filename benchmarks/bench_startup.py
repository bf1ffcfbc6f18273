"""How long the command line takes before it does the work: wall seconds, each command in a fresh
process (the median of --repeats), for the help pages, a mistyped flag (the one-line error, exit
2) and `evaluate` / `export --what map` of a 5-step run on a 3 s simulated office that the
benchmark trains first (their work is small: what is left is the start-up). Run it on an idle
machine; `--source` times another checkout with this environment's packages (a `git worktree` of
an older commit), so two commits compare on one machine:

    .venv/bin/python benchmarks/bench_startup.py --out startup.json
    git worktree add /tmp/old c7cc9ca && .venv/bin/python benchmarks/bench_startup.py --source /tmp/old
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

from bench_out import new_out, write_out

TINY_CONFIG = {  # a 5-step training of 128 rays on a coarse grid (the tests' tiny run)
    "max_steps": 5, "max_time": None, "batch_size": 128, "log_every": 2, "plots": False,
    "march": {"step_size": 0.06, "max_samples": 32},
    "virus_grid": {"warmup_steps": 16, "update_interval": 4, "rays_per_update": 64},
    "evaluation": {"n_rays": 64},
}


def cli(source: Path, args: list[str], expect: int = 0) -> float:
    """Wall seconds of `python -m virus_nerf.cli ARGS` run from `source` (its package first on
    the path); a different exit code than `expect` stops the benchmark."""
    env = {**os.environ, "PYTHONPATH": str(source)}
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "virus_nerf.cli", *map(str, args)], cwd=source, env=env,
                          capture_output=True, text=True)
    seconds = time.perf_counter() - t
    if proc.returncode != expect:
        sys.exit(f"virus-nerf {' '.join(map(str, args))}: exit {proc.returncode} (expected {expect}): "
                 f"{proc.stderr.strip()[-500:]}")
    return seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--source", type=Path, default=Path(__file__).resolve().parents[1],
                    help="the checkout to time (default: this one)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    new_out(args.out)  # before the run: a result is never overwritten
    source = args.source.resolve()
    if not (source / "virus_nerf" / "__init__.py").is_file():
        ap.error(f"--source {args.source}: no virus_nerf checkout there (expected SOURCE/virus_nerf/__init__.py)")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        cli(source, ["simulate", "--scene", "office", "--seed", "3", "--duration", "3", "--resolution-scale", "0.25",
                     "--out", tmp / "office"])
        (tmp / "tiny.json").write_text(json.dumps(TINY_CONFIG))
        cli(source, ["train", "--data", tmp / "office", "--room", "office", "--out", tmp / "run", "--config",
                     tmp / "tiny.json", "--quiet"])
        commands = {  # name -> (its arguments given a new output path, its exit code)
            "--help": (lambda new: ["--help"], 0),
            "simulate --help": (lambda new: ["simulate", "--help"], 0),
            "train --help": (lambda new: ["train", "--help"], 0),
            "train, a mistyped flag": (lambda new: ["train", "--data", tmp / "office", "--room", "office", "--out",
                                                    new, "--batch-size", "many"], 2),
            "evaluate (tiny run)": (lambda new: ["evaluate", "--run", tmp / "run", "--out", new / "metrics.json"], 0),
            "export --what map (tiny run)": (lambda new: ["export", "--run", tmp / "run", "--what", "map", "--out",
                                                          new], 0),
        }
        rows = {}
        for name, (argv, expect) in commands.items():
            times = [cli(source, argv(tmp / f"out_{len(rows)}_{k}"), expect) for k in range(args.repeats)]
            rows[name] = round(statistics.median(times), 2)
            print(f"{name:32s} {rows[name]:6.2f} s")
    doc = {"source": str(source), "commit": _commit(source), "repeats": args.repeats, "seconds": rows,
           "cpu_count": os.cpu_count()}
    if args.out is not None:
        write_out(args.out, json.dumps(doc, indent=1) + "\n")


def _commit(source: Path) -> str | None:
    proc = subprocess.run(["git", "-C", str(source), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    return proc.stdout.strip() or None


if __name__ == "__main__":
    main()
