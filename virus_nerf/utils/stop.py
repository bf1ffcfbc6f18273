"""Stopping a long-running command cleanly on SIGINT or SIGTERM (issue 39).

A robot's launch system stops a process with SIGINT (Ctrl-C, ROS launch), then SIGTERM
(`systemctl stop`, `docker stop`), then SIGKILL. Inside `stop_on_signals()` the first SIGINT or
SIGTERM raises `Stopped` in the main thread (a KeyboardInterrupt, so every `except
KeyboardInterrupt` that keeps the map treats both alike); the command writes its final outputs,
prints one line saying where they are, marks the exception `reported` and lets it rise to the CLI,
which exits 128 + the signal number (130, 143) without a traceback. A second signal while the
outputs are being written stops the process at once (exit 128 + signal; every file is written
atomically, so what was written before is whole). A Ctrl-C outside such a block is a plain
KeyboardInterrupt: one line and exit 130 (cli.py).

Once a stop signal came, "Exception ignored in ..." reports are dropped (`quiet_after_stop`): a
signal that lands inside a C callback (llvmlite's, while numba loads a kernel) is reported so,
and an object it cut half-built reports its `__del__` at exit. Both are the stop's echo, not
errors, and would follow the command's one line.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

SIGNALS = tuple(s for s in (getattr(signal, "SIGINT", None), getattr(signal, "SIGTERM", None)) if s is not None)


class Stopped(KeyboardInterrupt):
    """The process was asked to stop (SIGINT or SIGTERM): end with the outputs written so far."""

    def __init__(self, signum: int = signal.SIGINT) -> None:
        self.signum = int(signum)
        self.reported = False  # the command printed its one line: the CLI adds nothing
        super().__init__(self.name)

    @property
    def name(self) -> str:
        try:
            return signal.Signals(self.signum).name
        except ValueError:  # pragma: no cover - not a known signal number
            return f"signal {self.signum}"

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


def exit_code_of(exc: KeyboardInterrupt) -> int:
    """130 for a plain Ctrl-C, 128 + the signal for `Stopped`."""
    return exc.exit_code if isinstance(exc, Stopped) else 128 + signal.SIGINT


def _at_once(signum, frame) -> None:  # noqa: ARG001 - a signal handler's signature
    """The second signal: no more clean-up (the first one's outputs are being written)."""
    name = signal.Signals(signum).name
    os.write(2, f"virus-nerf: {name} again: stopped at once (files written so far are whole)\n".encode())
    os._exit(128 + signum)


# `stops_deferred`: how deep inside such blocks, the signal they deferred; `stop_on_signals`: the first signal
_STEP = {"depth": 0, "pending": None, "signalled": None}


def _ignore_unraisable(unraisable) -> None:  # noqa: ARG001 - sys.unraisablehook's signature
    """`sys.unraisablehook` after a stop: the reports are the stop's echo (see the module docstring)."""


def quiet_after_stop() -> None:
    """Drop "Exception ignored in ..." reports from now on: the process was stopped by a signal."""
    sys.unraisablehook = _ignore_unraisable


def _first(signum, frame) -> None:  # noqa: ARG001
    for s in SIGNALS:
        signal.signal(s, _at_once)
    quiet_after_stop()
    _STEP["signalled"] = signum  # a Stopped raised where a C callback swallows it still ends the block
    # inside a deferring block (a training step, a TensorBoard write) that ends first
    # (`stops_deferred`); outside one the Stopped rises here, and is also kept for the next such
    # block's end: where a C callback swallowed it, the work would go on to the end of
    # `stop_on_signals` (a whole budget of training) before the stop stands
    _STEP["pending"] = signum
    if _STEP["depth"]:
        return
    raise Stopped(signum)


@contextmanager
def stops_deferred() -> Iterator[None]:
    """Work a first signal must not cut in half; its `Stopped` rises when the block is done:
    - a training step (the optimiser stepped, the grid not yet updated: a checkpoint of that would
      not continue as the run would have);
    - a call into a library that hands work to its own thread (TensorBoard's event writer, tqdm's
      bar): a `Stopped` raised inside `threading.Condition.notify`, between waking the thread and
      taking it off the waiters, leaves a stale waiter that swallows the next wake-up (CPython
      gh-92530). The thread then sleeps until its own timer (TensorBoard's: 120 s) and the close at
      the stop waits for it (seen: a stopped `train` wrote its map two minutes late).
    A signal whose `Stopped` a C callback swallowed rises at the end of the next such block. A
    block that ends while a stop already rises (in a `finally`) adds no second one."""
    _STEP["depth"] += 1
    try:
        yield
    finally:
        _STEP["depth"] -= 1
    pending = _STEP["pending"]
    if pending is not None and not _STEP["depth"]:
        _STEP["pending"] = None
        if not isinstance(sys.exc_info()[1], KeyboardInterrupt):
            raise Stopped(pending)


@contextmanager
def stop_on_signals() -> Iterator[None]:
    """SIGINT and SIGTERM raise `Stopped` inside the block (main thread only; elsewhere a no-op);
    the final outputs are written inside it (a second signal there stops at once). The old
    handlers are back when the block ends, however it ends; a block that ends without the
    `Stopped` of a signal it got raises it then."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.getsignal(s) for s in SIGNALS}
    for s in SIGNALS:
        signal.signal(s, _first)
    try:
        yield
    finally:
        signalled, _STEP["signalled"], _STEP["pending"] = _STEP["signalled"], None, None
        for s, handler in old.items():
            signal.signal(s, handler if handler is not None else signal.SIG_DFL)
    if signalled is not None:
        # the handler's Stopped was swallowed (raised inside llvmlite's ctypes callback while numba
        # loaded a kernel: "Exception ignored"): the work went on to its end; the stop stands
        raise Stopped(signalled)
