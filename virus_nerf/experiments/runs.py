"""Running many trainings as separate processes, resumably (finished runs are never redone)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class RunSpec:
    """One `virus-nerf train` invocation."""

    name: str
    data: Path
    room: str
    out: Path
    args: tuple[str, ...] = field(default_factory=tuple)  # extra CLI flags

    def command(self) -> list[str]:
        return [sys.executable, "-m", "virus_nerf.cli", "train", "--data", str(self.data), "--room", self.room,
                "--out", str(self.out), "--quiet", *self.args]


def run_done(out: Path) -> bool:
    return (out / "metrics.json").is_file()


def _worker_env(threads: int) -> dict[str, str]:
    env = dict(os.environ)
    env.update({"OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads),
                "NUMBA_NUM_THREADS": str(threads), "PYTHONUNBUFFERED": "1"})
    return env


def _run_one(spec: RunSpec, threads: int) -> tuple[RunSpec, int, float]:
    t0 = time.perf_counter()
    cmd = spec.command()
    if spec.out.exists() and (spec.out / "checkpoint.pt").is_file():
        cmd = cmd + ["--resume"]  # an interrupted run continues from its checkpoint
    elif spec.out.exists():
        # interrupted before its first checkpoint: keep it aside, never delete
        spec.out.rename(spec.out.with_name(f"{spec.out.name}.incomplete-{int(time.time())}"))
    spec.out.parent.mkdir(parents=True, exist_ok=True)
    log = spec.out.parent / f"{spec.out.name}.log"
    with log.open("a") as fh:
        proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, env=_worker_env(threads))
    return spec, proc.returncode, time.perf_counter() - t0


def run_all(specs: list[RunSpec], workers: int = 2, threads_per_worker: int | None = None) -> list[RunSpec]:
    """Run every unfinished spec, `workers` at a time; returns the specs that failed."""
    todo = [s for s in specs if not run_done(s.out)]
    done = len(specs) - len(todo)
    print(f"{len(specs)} runs: {done} already finished, {len(todo)} to run with {workers} worker(s)")
    threads = threads_per_worker or max(1, (os.cpu_count() or 2) // max(1, workers))
    failed: list[RunSpec] = []
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        for k, (spec, rc, secs) in enumerate(pool.map(lambda s: _run_one(s, threads), todo), start=1):
            status = "ok" if rc == 0 and run_done(spec.out) else f"FAILED (exit {rc}, see {spec.out}.log)"
            print(f"  [{k}/{len(todo)}] {spec.name}: {status} in {secs:.0f} s", flush=True)
            if status != "ok":
                failed.append(spec)
    return failed
