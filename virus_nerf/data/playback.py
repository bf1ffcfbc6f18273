"""The one frame feeder of mapping while driving: a recording's clock run at a playback speed.

`train --online` runs it on the training clock (frames appear as the training seconds times the
speed pass their timestamps: evaluations and start-up do not advance the drive), `map-bag` on
the wall clock (a robot's drive does not wait for the mapper). Both release a frame once
`elapsed * speed` seconds of recording have passed since the first frame's time `t0`.
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
