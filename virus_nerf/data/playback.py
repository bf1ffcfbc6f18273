"""The one frame feeder of mapping while driving: a recording's clock run at a playback speed.

`train --online` runs it on the training clock (frames appear as the training seconds times the
speed pass their timestamps: evaluations and start-up do not advance the drive), `map-bag` on
the wall clock (a robot's drive does not wait for the mapper). Both release a frame once
`elapsed * speed` seconds of recording have passed since the first frame's time `t0`
(`FrameFeeder` over a `Playback`); the ROS 2 stream releases its messages by the same `Playback`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Playback:
    """A recording replayed from its time `t0` (s) at `speed` recording seconds per second."""

    t0: float
    speed: float = 1.0

    def __post_init__(self) -> None:
        if not (self.speed > 0.0 and np.isfinite(self.speed)):
            raise ValueError(f"playback speed {self.speed!r}: expected a finite number > 0")

    def recording_time(self, elapsed: float) -> float:
        """Recording time (s) reached after `elapsed` seconds of the feeder's clock."""
        return self.t0 + elapsed * self.speed

    def elapsed_at(self, time: float) -> float:
        """Seconds of the feeder's clock until the recording time `time` (s) is reached."""
        return (time - self.t0) / self.speed

    def due(self, times: np.ndarray, elapsed: float) -> np.ndarray:
        """(N,) bool: which of the recording times `times` (s) have been reached after `elapsed` s."""
        return np.asarray(times) <= self.recording_time(elapsed)


class FrameFeeder:
    """A drive's frames released in time order (ties: in the given order) as a clock passes them.

    times (N,): recording time (s) of each frame row; speed: recording seconds per second of the
    feeder's clock, which starts at the first frame's time (so the first frame is due at once).
    """

    def __init__(self, times, speed: float = 1.0):
        self.times = np.asarray(times, dtype=np.float64)  # (N,)
        if self.times.ndim != 1 or not len(self.times):
            raise ValueError(f"frame times of shape {self.times.shape}: expected at least one frame")
        self.order = np.lexsort((np.arange(len(self.times)), self.times))  # (N,) rows in time order
        self._sorted = self.times[self.order]
        self.playback = Playback(float(self._sorted[0]), speed)
        self.released = 0  # frames released so far (the first `released` of `order`)

    def due(self, elapsed: float) -> np.ndarray:
        """Rows (time order) whose time the clock has reached after `elapsed` s (at least the first)."""
        return self.order[:self._due_count(elapsed)]

    def release(self, elapsed: float) -> np.ndarray:
        """Rows due after `elapsed` s and not released before, in time order."""
        return self.release_first(self._due_count(elapsed))

    def release_first(self, n: int) -> np.ndarray:
        """The first `n` rows in time order not released before (a checkpoint's frames, whatever
        is due at its clock)."""
        n = min(max(int(n), 0), len(self.order))
        new = self.order[self.released:n]
        self.released = max(self.released, n)
        return new

    def wait(self, elapsed: float) -> float:
        """Seconds of the clock from `elapsed` until the next frame is due (inf: all released)."""
        if self.done:
            return float("inf")
        return self.playback.elapsed_at(float(self._sorted[self.released])) - elapsed

    @property
    def done(self) -> bool:
        return self.released == len(self.order)

    @property
    def last_time(self) -> float:
        """Recording time (s) of the newest frame released (the first frame's before any)."""
        return float(self._sorted[max(0, self.released - 1)])

    def _due_count(self, elapsed: float) -> int:
        reached = self.playback.recording_time(elapsed)
        return max(1, int(np.searchsorted(self._sorted, reached, side="right")))
