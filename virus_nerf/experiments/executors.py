"""Where runs execute: local processes (threads each waiting on a `virus-nerf train` process) or
a Dask cluster (`--scheduler ADDRESS`, or `--scheduler local` for a LocalCluster on this machine).

Both run `runs.execute_run` on a RunSpec, so a run folder is the same whichever executor ran
it, and an ablation or a study started with one executor can be continued with the other. With a
remote cluster the data and output folders must be reachable at the same paths on every worker
(a shared file system); the RunSpecs carry absolute paths.
"""

from __future__ import annotations

import concurrent.futures
import os
import threading
from collections.abc import Iterable, Iterator
from contextlib import closing
from typing import Any

from virus_nerf.experiments.runs import (
    STOPPED_WITH_CALLER,
    RunResult,
    RunSpec,
    clear_caller_stop,
    execute_run,
    log_file,
    request_stop,
    run_done,
)


def require_extra(module: str, extra: str, what: str) -> Any:
    """Import an optional dependency, or a one-line UsageError naming the extra to install."""
    import importlib

    from virus_nerf.errors import UsageError, install_extra

    try:
        return importlib.import_module(module)
    except ImportError:
        raise UsageError(f"{what} needs the optional package '{module}', which is not installed: "
                         f"{install_extra(extra)}") from None


class LocalExecutor:
    """`workers` runs at a time on this machine, each a subprocess with `threads` threads."""

    def __init__(self, workers: int, threads: int | None = None) -> None:
        cores = os.cpu_count() or 2
        self.workers = max(1, workers)
        self.threads = threads or max(1, cores // self.workers)
        # more threads than cores in all: the runs' OpenMP threads must sleep, not spin, while waiting
        self.shared_cpu = self.workers * self.threads > cores
        self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=self.workers)

    def describe(self) -> str:
        return f"{self.workers} local worker(s), {self.threads} thread(s) per run"

    def submit(self, spec: RunSpec):
        """A future (done(), result() -> RunResult)."""
        return self._pool.submit(execute_run, spec, self.threads, shared_cpu=self.shared_cpu)

    def as_completed(self, futures: list) -> Iterator:
        return concurrent.futures.as_completed(futures)

    def close(self) -> None:
        self._pool.shutdown(wait=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class DaskExecutor:
    """Runs sent to a dask.distributed scheduler; each task occupies one worker thread for the
    length of its training (start workers with `--nthreads 1`, one per training at a time)."""

    def __init__(self, scheduler: str, workers: int = 2, threads: int | None = None) -> None:

        self._distributed = require_extra("distributed", "dask", f"--scheduler {scheduler}")
        self.threads = threads or 1
        self._cluster = None
        if scheduler == "local":
            # the dashboard on a free loopback port: 8787 may be another scheduler's (no warning then)
            self._cluster = self._distributed.LocalCluster(n_workers=max(1, workers), threads_per_worker=1,
                                                           processes=True, dashboard_address="127.0.0.1:0")
            self.client = self._distributed.Client(self._cluster)
        else:
            self.client = _connect(self._distributed, scheduler)
        self.scheduler = scheduler

    @property
    def n_workers(self) -> int:
        return len(self.client.scheduler_info().get("workers", {}))

    def describe(self) -> str:
        return f"Dask scheduler {self.scheduler} ({self.n_workers} worker(s)), {self.threads} thread(s) per run"

    def submit(self, spec: RunSpec):
        return self.client.submit(execute_run, spec, self.threads, pure=False)

    def as_completed(self, futures: list) -> Iterator:
        return iter(self._distributed.as_completed(futures))

    def close(self) -> None:
        import logging

        # a stop cancels tasks and ends a LocalCluster's busy workers: distributed's warnings about
        # that (a CancelledError, "still alive after 4 s, killing") would follow the command's one line
        logging.getLogger("distributed").setLevel(logging.ERROR)
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


CONNECT_TIMEOUT_S = 30.0  # a scheduler address that does not answer as a scheduler (a dashboard port)


def _connect(distributed, scheduler: str):
    """A Client of the scheduler at `scheduler`, or the one-line UsageError naming --scheduler.
    distributed's own timeout does not cover a port that accepts and never answers (a dashboard,
    any other service): the connection runs in a daemon thread with its own deadline."""
    from virus_nerf.errors import UsageError

    box: dict = {}

    def connect() -> None:
        try:
            box["client"] = distributed.Client(scheduler, timeout="20s")
        except Exception as exc:  # noqa: BLE001 - reported below, in one line
            box["error"] = exc

    thread = threading.Thread(target=connect, daemon=True)
    thread.start()
    thread.join(CONNECT_TIMEOUT_S)
    expected = "expected e.g. tcp://HOST:8786 (the scheduler's port, not its dashboard's) or 'local'"
    if thread.is_alive():
        raise UsageError(f"--scheduler {scheduler}: nothing answered as a Dask scheduler within "
                         f"{CONNECT_TIMEOUT_S:g} s; {expected}")
    if "error" in box:
        raise UsageError(f"--scheduler {scheduler}: cannot connect to a Dask scheduler there "
                         f"({type(box['error']).__name__}); {expected}")
    return box["client"]


def check_scheduler(scheduler: str | None) -> None:
    """Before a command writes anything: the dask extra for --scheduler, and a scheduler that
    answers at its address (connected once and closed; 'local' starts nothing yet)."""
    if scheduler is None:
        return
    distributed = require_extra("distributed", "dask", f"--scheduler {scheduler}")
    if scheduler != "local":
        _connect(distributed, scheduler).close()


def make_executor(scheduler: str | None, workers: int, threads: int | None = None):
    """LocalExecutor without a scheduler, DaskExecutor with one ('local': a LocalCluster of
    `workers` single-thread workers)."""
    if scheduler is None:
        return LocalExecutor(workers, threads)
    return DaskExecutor(scheduler, workers, threads)


def stop_unfinished(futures: dict) -> int:
    """The caller stops (Ctrl-C, SIGTERM, an error): every run not finished gets its stop file
    (runs.STOPPED_WITH_CALLER), which the attempt waiting on its training polls: the training
    ends its step and keeps its checkpoint. Needed beyond the local children dying with their
    parent: a training on a Dask worker is the worker's child and would run on. Runs not started
    yet are cancelled. Returns how many runs were unfinished."""
    unfinished = {fut: spec for fut, spec in futures.items() if not fut.done()}
    for fut, spec in unfinished.items():
        request_stop(spec.out, STOPPED_WITH_CALLER)
        fut.cancel()  # a queued run never starts; a running one ends through its stop file
    return len(unfinished)


def run_many(executor, specs: Iterable[RunSpec]) -> Iterator[tuple[RunSpec, RunResult | None, str]]:
    """Submit every spec; yield (spec, result or None, error text) as each completes. Closed or
    interrupted before the end (use contextlib.closing), the unfinished runs are stopped."""
    futures = {}
    try:
        for spec in specs:
            clear_caller_stop(spec.out)  # left by this command's earlier stop: continue the run
            futures[executor.submit(spec)] = spec
        for fut in executor.as_completed(list(futures)):
            spec = futures[fut]
            try:
                result = fut.result()
            except Exception as exc:  # the task itself broke (e.g. a worker lost the shared folder)
                yield spec, None, f"{type(exc).__name__}: {exc}"
            else:
                yield spec, result, ""
    finally:
        if n := stop_unfinished(futures):
            print(f"stopping {n} unfinished run(s): each ends its step and keeps its checkpoint; the same "
                  "command continues them", flush=True)


def run_all(specs: list[RunSpec], workers: int = 2, threads_per_worker: int | None = None,
            scheduler: str | None = None) -> list[RunSpec]:
    """Run every unfinished spec, `workers` at a time locally or on the Dask `scheduler`; a run
    that dies is retried once. Returns the specs that failed (no metrics.json in the end)."""
    todo = [s for s in specs if not run_done(s.out)]
    failed: list[RunSpec] = []
    with make_executor(scheduler, workers, threads_per_worker) as executor:
        print(f"{len(specs)} runs: {len(specs) - len(todo)} already finished, {len(todo)} to run on "
              f"{executor.describe()}", flush=True)
        with closing(run_many(executor, todo)) as results:  # stopped early: the unfinished runs are stopped
            for k, (spec, res, error) in enumerate(results, start=1):
                if res is not None and res.ok:
                    status = f"ok in {res.seconds:.0f} s" + (f" ({res.attempts} attempts)" if res.attempts > 1 else "")
                elif res is not None:
                    status = f"FAILED after {res.attempts} attempt(s) (exit {res.returncode}, see {log_file(spec.out)})"
                else:
                    status = f"FAILED ({error})"
                print(f"  [{k}/{len(todo)}] {spec.name}: {status}", flush=True)
                if res is None or not res.ok:
                    failed.append(spec)
    return failed
