"""KISS-ICP in a process of its own, for the streaming pose source (data/bags/poses.py KissPoses).

KISS-ICP's registration holds Python's GIL (measured: a registration loop and a Python loop in two
threads take the sum of their times), so in the mapping process it takes a third of one core
from training at a 10 Hz LiDAR. In a worker process it runs on the other core while the mapper
trains. The worker gets the scans in order and answers each with its pose; the same scans in the
same order give the same poses as an in-process KissICP (it is deterministic).

A robot's LiDAR does not wait for the registration: where a scan takes longer to register than
the LiDAR's period (a large room on a shared 2-core CPU), the scans queue and every pose comes
later than the one before (measured: 10 s median and 24 s max behind a 60 s common-area drive at
playback 1). With `keep_up` the worker registers the newest scan it has and answers each older
waiting one as skipped (no pose), so a pose is never more than about two registrations behind
its scan; KISS-ICP's constant-velocity prediction is then stretched to the interval actually
registered (odometry.ScanRegistration). Without it (the default) every scan is registered, as the
importer does.

The worker never outlives the mapping process, whatever ends it (issue 39): it is a plain
subprocess (`python -m virus_nerf.data.bags.kiss_worker PARENT_PID`, no multiprocessing, so no
resource-tracker process either) that talks over two pipes; on Linux the kernel sends it SIGKILL
when its parent dies (prctl PR_SET_PDEATHSIG), elsewhere a thread polls its parent pid; a closed
scan pipe (the parent gone) ends it too. It ignores SIGINT and SIGTERM (a Ctrl-C or a
`systemctl stop` reaches the whole process group): the mapping process stops it when it has
written its map.
"""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
from multiprocessing.connection import Connection

import numpy as np

from virus_nerf.data.bags.odometry import KissIcpSettings

PR_SET_PDEATHSIG = 1  # linux/prctl.h


def die_with_parent(parent: int, poll_s: float = 1.0) -> None:
    """End this process when `parent` ends: PR_SET_PDEATHSIG on Linux, and a polling thread."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):  # not Linux: the thread below does it within poll_s
        pass
    if os.getppid() != parent:  # the parent died before the line above
        os._exit(1)

    def poll() -> None:
        import time

        while os.getppid() == parent:
            time.sleep(poll_s)
        os._exit(1)

    threading.Thread(target=poll, name="watch-parent", daemon=True).start()


def _serve(scans: Connection, poses: Connection) -> None:
    """Worker loop: (KissIcpSettings, keep_up), then (time, float32 points (N, 3)) from `scans` ->
    (time, pose (4, 4) or None when skipped, error, the floor found: ScanRegistration.describe()
    with the first pose, else None) to `poses`, until None or the end of the pipe."""
    t = None
    try:
        settings, keep_up = scans.recv()
        from virus_nerf.data.bags.odometry import ScanRegistration

        registration = ScanRegistration(settings, stretch=keep_up)
        while True:
            item = scans.recv()
            if keep_up and registration.started:  # (the first scan is the world frame: never skipped)
                while item is not None and scans.poll(0):  # a newer scan waits: this one is skipped
                    poses.send((item[0], None, None, None))
                    item = scans.recv()
            if item is None:
                return
            t, pts = item
            first = not registration.started
            pose = registration.register(t, pts)
            poses.send((t, pose, None, registration.describe() if first else None))
    except (EOFError, BrokenPipeError):  # the mapping process is gone
        return
    except Exception as exc:  # noqa: BLE001 - sent to the mapping process, raised there
        try:
            poses.send((t, None, f"{type(exc).__name__}: {exc}", None))
        except OSError:
            pass


def main(argv: list[str]) -> None:
    """python -m virus_nerf.data.bags.kiss_worker PARENT_PID SCANS_FD POSES_FD"""
    parent, scans_fd, poses_fd = (int(a) for a in argv)
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, signal.SIG_IGN)
    die_with_parent(parent)
    _serve(Connection(scans_fd, writable=False), Connection(poses_fd, readable=False))


class KissWorker:
    """A KISS-ICP registration process: `send` a scan (returns at once), `poll` the poses done.
    keep_up: register the newest scan waiting and skip the older ones (module doc); `skipped`
    counts them."""

    def __init__(self, settings: KissIcpSettings, keep_up: bool = False) -> None:
        scans_r, scans_w = os.pipe()
        poses_r, poses_w = os.pipe()
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-m", "virus_nerf.data.bags.kiss_worker", str(os.getpid()), str(scans_r),
                 str(poses_w)], pass_fds=(scans_r, poses_w), stdin=subprocess.DEVNULL)
        except BaseException:
            for fd in (scans_r, scans_w, poses_r, poses_w):
                os.close(fd)
            raise
        os.close(scans_r)
        os.close(poses_w)
        self._scans = Connection(scans_w, readable=False)
        self._poses = Connection(poses_r, writable=False)
        # a scan is larger than a pipe's buffer: a thread writes them, so `send` never waits on a
        # registration in progress
        self._outbox: queue.SimpleQueue = queue.SimpleQueue()
        self._outbox.put((settings, keep_up))
        self._writer = threading.Thread(target=self._write, name="kiss-icp-send", daemon=True)
        self._writer.start()
        self.pending: list[float] = []  # stamps sent, pose not yet received
        self.skipped = 0  # scans answered without a pose (keep_up)
        self.floor: dict | None = None  # the first registered scan's floor (ScanRegistration.describe)

    def _write(self) -> None:
        while True:
            item = self._outbox.get()
            try:
                self._scans.send(item)
            except OSError:  # the worker died: poll() says so
                return
            if item is None:
                return

    def send(self, t: float, pts: np.ndarray) -> None:
        self._outbox.put((t, np.ascontiguousarray(pts, dtype=np.float32)))
        self.pending.append(t)

    def poll(self, block: bool = False) -> list[tuple[float, np.ndarray]]:
        """The poses done so far, in scan order (skipped scans left out); with `block`, waits for
        every pending scan. Raises RuntimeError (one line) when the worker failed or died."""
        out = []
        while self.pending:
            try:
                ready = self._poses.poll(0.5 if block else 0)
                item = self._poses.recv() if ready else None
            except (EOFError, OSError):
                item, ready = None, False
            if item is None:
                if self._proc.poll() is not None or ready:
                    raise RuntimeError(f"the KISS-ICP worker process stopped (exit code {self._proc.poll()}) "
                                       f"with {len(self.pending)} scan(s) unregistered")
                if block:
                    continue
                break
            t, pose, error, floor = item
            if floor is not None:
                self.floor = floor
            if error is not None:
                raise RuntimeError(f"KISS-ICP failed: {error}")
            self.pending.pop(0)
            if pose is None:
                self.skipped += 1
            else:
                out.append((t, pose))
        return out

    def close(self) -> None:
        """Stop the worker; never waits on a scan it will not read (a dead worker's full pipe)."""
        if self._proc.poll() is None:
            self._outbox.put(None)
            try:
                self._proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait(timeout=5.0)
        self._writer.join(timeout=1.0)  # done: it sent None or met the closed pipe
        for conn in (self._scans, self._poses):
            try:
                conn.close()
            except OSError:
                pass


if __name__ == "__main__":
    main(sys.argv[1:])
