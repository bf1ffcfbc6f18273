"""One training run as a separate `virus-nerf train` process, resumable and retried once.

`execute_run` is what every executor runs (`executors.py`: local threads, or a Dask worker on
another machine), so a run folder looks the same whichever executor ran it. It never reruns or
overwrites a finished run (finished = metrics.json exists); a run that died is retried once
(resumed from its checkpoint, or started again with the dead folder kept aside); a run whose
stop file (`RUN.stop`, beside the folder) appears is terminated and not retried (tune's pruning,
or the command that started it stopped: a training on a Dask worker is no child of that command).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from virus_nerf.trainer.run_folder import CHECKPOINT, METRICS

USAGE_EXIT = 2  # `virus-nerf` exits 2 on a user mistake: the same command would fail again
# `train` stopped by SIGINT / SIGTERM (kept its checkpoint; 130 / 143), or ended by either before it
# could say so: a stop asked for, never retried
STOP_EXITS = (130, 143, -2, -15)


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


@dataclass(frozen=True)
class RunResult:
    """What became of a RunSpec: exit code of the last attempt, attempts made (0: it was finished
    already), whether it was stopped on request, the host it ran on and its wall seconds."""

    spec: RunSpec
    returncode: int
    attempts: int
    stopped: bool = False
    host: str = ""
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return run_done(self.spec.out)


def run_done(out: Path) -> bool:
    return (Path(out) / METRICS).is_file()


def log_file(out: Path) -> Path:
    """RUN.log beside the run folder: the train process's output, every attempt appended."""
    out = Path(out)
    return out.with_name(f"{out.name}.log")


def stop_file(out: Path) -> Path:
    """RUN.stop beside the run folder: while it exists the run is terminated / not started."""
    out = Path(out)
    return out.with_name(f"{out.name}.stop")


# the reason a command's own stop (Ctrl-C, SIGTERM) writes: the same command run again clears it
STOPPED_WITH_CALLER = "stopped with the command that started it"


def request_stop(out: Path, reason: str = "stop requested") -> None:
    path = stop_file(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(reason + "\n")


def clear_caller_stop(out: Path) -> None:
    """Remove RUN.stop if the command's own stop wrote it (not a study's pruning): the command run
    again continues the run from its checkpoint."""
    path = stop_file(out)
    try:
        if path.read_text().strip() == STOPPED_WITH_CALLER:
            path.unlink()
    except FileNotFoundError:
        pass


def _worker_env(threads: int, shared_cpu: bool = False) -> dict[str, str]:
    """The child's environment: `threads` for every thread pool; on a CPU shared with other runs,
    OpenMP threads that sleep instead of spinning while they wait (OMP_WAIT_POLICY=PASSIVE, unless
    the user set a policy): two 2-thread trainings on 2 cores ran 1.7x faster each with it,
    while one alone runs 1.4x slower with it (docs/method.md 10)."""
    from virus_nerf.utils.parent import PARENT_ENV

    env = dict(os.environ)
    env.update({"OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads),
                "NUMBA_NUM_THREADS": str(threads), "PYTHONUNBUFFERED": "1",
                # the child dies with this process (utils.parent.watch_parent): a killed local
                # ablation, tune, online or demo (or Dask worker) leaves no training running
                PARENT_ENV: str(os.getpid())})
    if shared_cpu:
        env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    return env


HOLDER_WAIT_S = 600.0  # how long an attempt waits for a training still stopping in its folder
# how long a training asked to stop (SIGTERM) may take to end its step and write its map and
# checkpoint before it is killed, which costs the run everything since its last checkpoint: a
# warehouse run took 5.6 s on an idle 2-core machine; several trainings sharing the cores (an
# ablation, tune, the tests in parallel) take a multiple of that
STOP_GRACE_S = 300.0


def _wait_for_the_holder(spec: RunSpec, wait_s: float = HOLDER_WAIT_S) -> bool:
    """Wait until no process holds the run's lock: a training stopped a moment ago (its parent
    killed, a Dask worker lost, the same command run again at once) first ends its step and keeps
    its map and checkpoint; deciding before would set a live folder aside. False (said in the
    run's log) when it is still held after `wait_s`."""
    from virus_nerf.trainer.run_folder import RunLock

    if not spec.out.is_dir():
        return True
    lock, t0 = RunLock(spec.out, "--out"), time.monotonic()
    while lock.held_by_another():
        if time.monotonic() - t0 > wait_s:
            with log_file(spec.out).open("a") as fh:
                fh.write(f"# {socket.gethostname()} pid {os.getpid()}: {spec.out} is still locked by another "
                         f"training after {wait_s:g} s; not started\n")
            return False
        time.sleep(0.25)
    return True


def _attempt(spec: RunSpec, threads: int, poll_s: float, shared_cpu: bool) -> tuple[int, bool]:
    """One train process for `spec`; returns (exit code, stopped on request)."""
    cmd = spec.command()
    if not _wait_for_the_holder(spec):
        return USAGE_EXIT, False
    if spec.out.exists() and (spec.out / CHECKPOINT).is_file():
        cmd = cmd + ["--resume"]  # an interrupted run continues from its checkpoint
    elif spec.out.exists():
        # died before its first checkpoint: keep it aside, never delete
        spec.out.rename(spec.out.with_name(f"{spec.out.name}.incomplete-{time.time_ns()}"))
    spec.out.parent.mkdir(parents=True, exist_ok=True)
    with log_file(spec.out).open("a") as fh:
        fh.write(f"# {socket.gethostname()} pid {os.getpid()}: {' '.join(cmd)}\n")
        fh.flush()
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, env=_worker_env(threads, shared_cpu))
        while True:
            try:
                return proc.wait(timeout=poll_s), False
            except subprocess.TimeoutExpired:
                if not stop_file(spec.out).exists():
                    continue
            proc.terminate()  # SIGTERM: the run ends its step and keeps its map and checkpoint
            try:
                proc.wait(timeout=STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
                fh.write(f"# {socket.gethostname()} pid {os.getpid()}: the training did not stop within "
                         f"{STOP_GRACE_S:g} s of SIGTERM; killed\n")
            return proc.returncode, True


def execute_run(spec: RunSpec, threads: int = 1, retries: int = 1, poll_s: float = 0.5,
                shared_cpu: bool = False) -> RunResult:
    """Run `spec` to its end: nothing if finished, else up to 1 + `retries` attempts (a run that
    died is retried; a usage error, exit 2, a stop request or a stop by SIGINT / SIGTERM is not).
    `shared_cpu`: other runs use the same cores at the same time (see `_worker_env`)."""
    t0 = time.perf_counter()
    host = socket.gethostname()
    if run_done(spec.out):
        return RunResult(spec, 0, 0, host=host)
    attempts, rc, stopped = 0, 0, False
    while attempts <= retries:
        if stop_file(spec.out).exists():  # also after an attempt that died of the same stop (Ctrl-C)
            stopped = True
            break
        rc, stopped = _attempt(spec, threads, poll_s, shared_cpu)
        attempts += 1
        stopped = stopped or rc in STOP_EXITS  # stopped by a signal (a Ctrl-C to the group), not dead
        if stopped or run_done(spec.out) or rc == USAGE_EXIT:
            break
    return RunResult(spec, rc, attempts, stopped=stopped, host=host, seconds=time.perf_counter() - t0)
