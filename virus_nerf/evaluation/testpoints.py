"""Test points of the evaluation (docs/method.md 6.1): the test frames of stack 1 and the stack-3 frame
taken at (nearly) the same time. One test point = one scan origin shared by every scan."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from virus_nerf.data.ethz import Recording
from virus_nerf.errors import DataFormatError
from virus_nerf.sensors.rig import MAIN_STACK

PARTNER_STACK = 3


@dataclass(frozen=True, eq=False)
class TestPoint:
    """Where and when a 2D scan is taken; the scan origin is the camera-1 position (docs/method.md 9.9)."""

    __test__ = False  # not a pytest test class

    index1: int  # frame index in stack 1
    index3: int | None  # synchronous frame index in stack 3 (None if the recording has no stack 3)
    time: float  # s, stack-1 camera timestamp
    time3: float | None  # s, stack-3 camera timestamp
    pose1: np.ndarray  # (4, 4) camera-1 to world
    pose3: np.ndarray | None  # (4, 4) camera-3 to world

    @property
    def origin(self) -> np.ndarray:
        """(3,) scan origin in the world frame, metres (camera-1 position)."""
        return self.pose1[:3, 3].copy()

    @property
    def origin_xy(self) -> np.ndarray:
        """(2,) scan origin in the horizontal plane."""
        return self.pose1[:2, 3].copy()

    @property
    def height(self) -> float:
        """Camera-1 height z (m), the height of the 2D slice."""
        return float(self.pose1[2, 3])

    def camera_poses(self) -> dict[int, tuple[int, np.ndarray]]:
        """Stack id -> (frame index, camera-to-world pose) for the stacks present."""
        out = {MAIN_STACK: (self.index1, self.pose1)}
        if self.index3 is not None and self.pose3 is not None:
            out[PARTNER_STACK] = (self.index3, self.pose3)
        return out


def nearest_index(times: np.ndarray, t: float) -> int:
    """Index of the entry of sorted `times` nearest to t."""
    j = int(np.searchsorted(times, t))
    if j <= 0:
        return 0
    if j >= len(times):
        return len(times) - 1
    return j - 1 if (t - times[j - 1]) <= (times[j] - t) else j


def make_test_points(recording: Recording, split: str = "test") -> list[TestPoint]:
    """One TestPoint per stack-1 frame labelled `split`, paired with the nearest stack-3 frame."""
    if MAIN_STACK not in recording.stacks:
        raise DataFormatError(recording.room_dir / "measurements", "stack 1 (USS1.csv, CAM1) is needed for the test points")
    s1 = recording.stacks[MAIN_STACK]
    s3 = recording.stacks.get(PARTNER_STACK)
    points = []
    for i in s1.indices(split):
        t = float(s1.times[i])
        j = nearest_index(s3.times, t) if s3 is not None and len(s3) else None
        points.append(
            TestPoint(
                index1=int(i),
                index3=j,
                time=t,
                time3=float(s3.times[j]) if j is not None else None,
                pose1=np.array(s1.cam_to_world[i], dtype=np.float64),
                pose3=np.array(s3.cam_to_world[j], dtype=np.float64) if j is not None else None,
            )
        )
    return points


def split_file(recording: Recording) -> str:
    """The split file a refusal names (the default split when the recording has none)."""
    path = recording.room_dir / "split" / "split.csv"
    return str(path) if path.is_file() else f"{path} (absent: the default split made in memory)"


def require_test_points(recording: Recording) -> None:
    """A one-line DataFormatError naming the split file when the recording has no test frame of
    the main stack: there is nothing to score (`train` and `sensors` refuse it before any work)."""
    if not make_test_points(recording):
        raise DataFormatError(split_file(recording), f"no CAM{MAIN_STACK} rows labelled 'test'; the evaluation "
                              f"scores the test frames of stack {MAIN_STACK}", field=f"CAM{MAIN_STACK}")
