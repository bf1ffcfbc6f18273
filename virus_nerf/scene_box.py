"""The axis-aligned scene box in metres (docs/method.md 3.5, 9.2): anisotropic, fitted to the room.

The field normalises world points to [0, 1]^3 inside this box; the occupancy grids cover the
same box. A flat room gets a flat box, so no grid layer is wasted on empty height.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SceneBox:
    lo: tuple[float, float, float]  # metres, world frame
    hi: tuple[float, float, float]

    def __post_init__(self) -> None:
        # plain floats: numpy scalars would print as np.float64(...) in messages and configs
        object.__setattr__(self, "lo", tuple(float(v) for v in self.lo))
        object.__setattr__(self, "hi", tuple(float(v) for v in self.hi))
        if not all(np.isfinite(self.lo + self.hi)):  # one line naming the fields, as other inputs are
            raise ValueError(f"SceneBox lo={self.lo} hi={self.hi}: expected finite metres")
        if not all(hi > lo for lo, hi in zip(self.lo, self.hi, strict=True)):
            raise ValueError(f"scene box needs hi > lo on every axis, got lo={self.lo} hi={self.hi}")

    @property
    def size(self) -> np.ndarray:
        return np.asarray(self.hi) - np.asarray(self.lo)

    @property
    def center(self) -> np.ndarray:
        return (np.asarray(self.hi) + np.asarray(self.lo)) / 2

    def contains(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points)
        return np.all((p >= np.asarray(self.lo)) & (p <= np.asarray(self.hi)), axis=-1)

    def normalise(self, points):
        """World points (N, 3) -> [0, 1]^3 box coordinates; works for numpy and torch."""
        lo = points.new_tensor(self.lo) if hasattr(points, "new_tensor") else np.asarray(self.lo)
        size = points.new_tensor(self.size) if hasattr(points, "new_tensor") else self.size
        return (points - lo) / size

    def padded(self, margin: float) -> SceneBox:
        return SceneBox(tuple(float(v - margin) for v in self.lo), tuple(float(v + margin) for v in self.hi))

    @staticmethod
    def around(points: np.ndarray, margin: float = 0.1) -> SceneBox:
        """The tightest box around points (N, 3), grown by `margin` metres on every side."""
        p = np.asarray(points, dtype=np.float64)
        return SceneBox(tuple(p.min(axis=0) - margin), tuple(p.max(axis=0) + margin))

    def to_dict(self) -> dict:
        return {"lo": list(self.lo), "hi": list(self.hi)}

    @staticmethod
    def from_dict(d: dict) -> SceneBox:
        return SceneBox(tuple(map(float, d["lo"])), tuple(map(float, d["hi"])))
