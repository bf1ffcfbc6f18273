"""The 3D Bayesian (VIRUS) grid as `.npy` + a JSON sidecar.

The array is the occupancy *probability* p = sigmoid(log-odds) as float32, shape (rx, ry, rz),
axis order (x, y, z): a user needs no knowledge of the clamp or the log-odds to threshold it
(the ray marcher samples where p > 0.5). It is NaN in the columns no sensor looked at (no
camera's view wedge, maps/observed.py, and no camera standing there), as prob.pgm is unknown: there the
grid holds its warm-up and prior (p 0.49 after the warm-up, below the threshold), which a
planner reading the array must not take for free space. The log-odds are written beside it
(`grid_logodds.npy`, the grid's state everywhere) for those who fuse further evidence. The
sidecar says where each cell is and which share of the columns was observed.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

INDEX_RULE = ("cell (ix, iy, iz) of world point p: i = floor((p - lo) / (hi - lo) * shape) per axis, "
              "inside when 0 <= i < shape (virus_nerf.grid.base.cell_index); "
              "with shape = (nx, ny, nz): flat index = (ix * ny + iy) * nz + iz; cell centre = lo + (i + 0.5) * "
              "cell_size")


@dataclass(frozen=True)
class Grid3DInfo:
    """What the sidecar holds; metres throughout."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    resolution: tuple[int, int, int]  # cells along x, y, z
    cell_size: tuple[float, float, float]  # metres per cell along x, y, z
    occupied_threshold: float = 0.5  # the marcher samples cells with p above this
    observed: float | None = None  # share of the (x, y) columns some sensor looked at (the rest NaN)

    def to_dict(self) -> dict:
        return {
            "data": "grid_probability.npy",
            "logodds": "grid_logodds.npy",
            "value": "occupancy probability in [0, 1] (float32); log-odds in grid_logodds.npy",
            "axis_order": ["x", "y", "z"],
            "shape": list(self.resolution),
            "lo": list(self.lo),
            "hi": list(self.hi),
            "cell_size": list(self.cell_size),
            "units": "metres",
            "index": INDEX_RULE,
            "occupied_threshold": self.occupied_threshold,
            "unknown": "NaN in grid_probability.npy: the columns (ix, iy) no camera's view wedge covered "
                       "(12 m) and no camera stood in; the log-odds there are the grid's prior, not evidence",
            "observed": self.observed,
        }


def write_grid3d(probability: np.ndarray, logodds: np.ndarray, observed: np.ndarray, info: Grid3DInfo,
                 folder: Path) -> None:
    """grid_probability.npy (NaN in the columns outside `observed`, (rx, ry) bool [ix, iy]),
    grid_logodds.npy and grid.json into `folder`, each atomically."""
    from virus_nerf.utils.io import atomic_path, write_json_atomic

    observed = np.asarray(observed, dtype=bool)
    if observed.shape != tuple(info.resolution[:2]):
        raise ValueError(f"write_grid3d: observed {observed.shape}, expected the grid's columns {info.resolution[:2]}")
    probability = np.where(observed[:, :, None], probability, np.nan)  # (rx, ry, rz)
    info = dataclasses.replace(info, observed=round(float(observed.mean()), 4) if observed.size else 0.0)
    for name, arr in (("grid_probability.npy", probability), ("grid_logodds.npy", logodds)):
        with atomic_path(folder / name) as tmp, tmp.open("wb") as fh:
            np.save(fh, np.ascontiguousarray(arr, dtype=np.float32))
    write_json_atomic(folder / "grid.json", info.to_dict())
