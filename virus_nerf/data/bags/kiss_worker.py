"""KISS-ICP in a process of its own, for the streaming pose source (data/bags/live.py KissPoses).

KISS-ICP's registration holds Python's GIL (measured: a registration loop and a Python loop in two
threads take the sum of their times), so in the mapping process it takes a third of one core
from training at a 10 Hz LiDAR. In a worker process it runs on the other core while the mapper
trains. The worker gets the scans in order and answers each with its pose; the same scans in the
same order give the same poses as an in-process KissICP (it is deterministic).
"""

from __future__ import annotations

import multiprocessing as mp
import queue

import numpy as np

from virus_nerf.data.bags.odometry import KissIcpSettings


def _serve(scans, poses, settings: KissIcpSettings) -> None:
    """Worker loop: (time, float32 points (N, 3)) from `scans` -> (time, pose (4, 4), error) to
    `poses`, until None arrives. Ctrl-C is the mapping process's to handle (it closes the worker)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    t = None
    try:
        from kiss_icp.kiss_icp import KissICP

        from virus_nerf.data.bags.odometry import _kiss_config

        icp = KissICP(_kiss_config(settings))
        while True:
            item = scans.get()
            if item is None:
                return
            t, pts = item
            icp.register_frame(pts.astype(np.float64), np.empty(0))
            poses.put((t, np.array(icp.last_pose, dtype=np.float64), None))
    except Exception as exc:  # noqa: BLE001 - sent to the mapping process, raised there
        poses.put((t, None, f"{type(exc).__name__}: {exc}"))


class KissWorker:
    """A KISS-ICP registration process: `send` a scan (returns at once), `poll` the poses done."""

    def __init__(self, settings: KissIcpSettings) -> None:
        ctx = mp.get_context("spawn")  # no fork of a process that holds torch's threads
        self._scans, self._poses = ctx.Queue(), ctx.Queue()
        self._proc = ctx.Process(target=_serve, args=(self._scans, self._poses, settings), daemon=True,
                                 name="virus-nerf-kiss-icp")
        self._proc.start()
        self.pending: list[float] = []  # stamps sent, pose not yet received

    def send(self, t: float, pts: np.ndarray) -> None:
        self._scans.put((t, np.ascontiguousarray(pts, dtype=np.float32)))
        self.pending.append(t)

    def poll(self, block: bool = False) -> list[tuple[float, np.ndarray]]:
        """The poses done so far, in scan order; with `block`, waits for every pending scan.
        Raises RuntimeError (one line) when the worker failed or died."""
        out = []
        while self.pending:
            try:
                t, pose, error = self._poses.get(block=block, timeout=0.5 if block else None)
            except queue.Empty:
                if not self._proc.is_alive():
                    raise RuntimeError(f"the KISS-ICP worker process stopped (exit code {self._proc.exitcode}) "
                                       f"with {len(self.pending)} scan(s) unregistered") from None
                if block:
                    continue
                break
            if error is not None:
                raise RuntimeError(f"KISS-ICP failed: {error}")
            self.pending.pop(0)
            out.append((t, pose))
        return out

    def close(self) -> None:
        """Stop the worker; never waits on a scan it will not read (a dead worker's full pipe)."""
        self._scans.cancel_join_thread()
        if self._proc.is_alive():
            self._scans.put(None)
            self._proc.join(timeout=5.0)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(timeout=5.0)
        self._scans.close()
        self._poses.close()
