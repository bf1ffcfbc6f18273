"""What every occupancy grid shares: its cells over the scene box and one cell-index function.

Design 9.5: grid writes (updates) and ray-marching reads use the SAME cell-index formula.
`cell_index` (torch) is that formula; the numba kernels call `cell_index_scalar`, which does the
identical arithmetic, and a parity test pins them together.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np
import torch

from virus_nerf.scene_box import SceneBox


@dataclass(frozen=True)
class GridSpec:
    """Cells over the scene box: resolution (rx, ry, rz), cubic-ish cells of `cell_size` metres."""

    box: SceneBox
    resolution: tuple[int, int, int]

    @staticmethod
    def from_box(box: SceneBox, max_resolution: int = 128) -> GridSpec:
        """Near-cubic cells: the longest box axis gets `max_resolution` cells, others in proportion."""
        size = box.size
        cell = float(size.max()) / max_resolution
        res = tuple(max(1, math.ceil(float(s) / cell - 1e-9)) for s in size)
        return GridSpec(box=box, resolution=res)  # type: ignore[arg-type]

    @staticmethod
    def from_cell(box: SceneBox, cell: float) -> GridSpec:
        """Cells of `cell` metres (the box spans whole cells: grid/extent.py makes it so)."""
        res = tuple(max(1, round(float(s) / cell)) for s in box.size)
        return GridSpec(box=box, resolution=res)  # type: ignore[arg-type]

    def grown(self, box: SceneBox) -> tuple[GridSpec, tuple[int, int, int]]:
        """This grid's cells over a larger `box` whose sides lie whole cells further out: the new
        spec and the offset (3,) in cells of the old cell (0, 0, 0) in the new grid."""
        cell = self.cell_size
        offset = np.rint((np.asarray(self.box.lo) - np.asarray(box.lo)) / cell).astype(int)
        res = np.rint(np.asarray(box.size) / cell).astype(int)
        if (offset < 0).any() or (offset + np.asarray(self.resolution) > res).any():
            raise ValueError(f"GridSpec.grown: box {box} does not contain {self.box}")
        return GridSpec(box=box, resolution=tuple(int(r) for r in res)), tuple(int(o) for o in offset)  # type: ignore[arg-type]

    @property
    def n_cells(self) -> int:
        rx, ry, rz = self.resolution
        return rx * ry * rz

    @property
    def cell_size(self) -> np.ndarray:
        """(3,) metres per cell along x, y, z."""
        return self.box.size / np.asarray(self.resolution)

    def cell_centers(self) -> torch.Tensor:
        """(n_cells, 3) world coordinates of all cell centres, in flat-index order."""
        rx, ry, rz = self.resolution
        ix, iy, iz = torch.meshgrid(
            torch.arange(rx), torch.arange(ry), torch.arange(rz), indexing="ij"
        )
        ijk = torch.stack([ix, iy, iz], dim=-1).reshape(-1, 3).to(torch.float64)
        lo = torch.tensor(self.box.lo, dtype=torch.float64)
        return (lo + (ijk + 0.5) * torch.from_numpy(self.cell_size)).to(torch.float32)


def cell_index(points: torch.Tensor, spec: GridSpec) -> torch.Tensor:
    """World points (N, 3) -> flat cell index (N,) int64, -1 outside the box.

    Flat index = (ix * ry + iy) * rz + iz with i = floor((p - lo) / size * res), computed in
    float64 like the numba twin, so both agree on points exactly on cell borders.
    """
    points = points.to(torch.float64)
    lo = points.new_tensor(spec.box.lo)
    size = points.new_tensor(spec.box.size.tolist())
    res = torch.tensor(spec.resolution, device=points.device)
    u = (points - lo) / size * res.to(points.dtype)  # (N, 3) cell coordinates
    ijk = torch.floor(u).to(torch.int64)
    inside = ((ijk >= 0) & (ijk < res)).all(dim=-1)
    flat = (ijk[:, 0] * res[1] + ijk[:, 1]) * res[2] + ijk[:, 2]
    return torch.where(inside, flat, torch.full_like(flat, -1))


@numba.njit(cache=True, inline="always")
def cell_index_scalar(x, y, z, lo, size, res):  # pragma: no cover - compiled
    """Numba twin of `cell_index` for one point; lo, size (3,) float, res (3,) int64."""
    ux = (x - lo[0]) / size[0] * res[0]
    uy = (y - lo[1]) / size[1] * res[1]
    uz = (z - lo[2]) / size[2] * res[2]
    ix = int(math.floor(ux))
    iy = int(math.floor(uy))
    iz = int(math.floor(uz))
    if ix < 0 or iy < 0 or iz < 0 or ix >= res[0] or iy >= res[1] or iz >= res[2]:
        return -1
    return (ix * res[1] + iy) * res[2] + iz


DensityFn = Callable[[torch.Tensor], torch.Tensor]  # world points (N, 3) -> sigma (N,), no grad


@dataclass
class SensorRays:
    """Rays of a range sensor in the world frame (metres): one reading per ray."""

    origins: torch.Tensor  # (K, 3)
    directions: torch.Tensor  # (K, 3) unit
    ranges: torch.Tensor  # (K,) metres along the ray; NaN = no reading

    def __len__(self) -> int:
        return int(self.ranges.shape[0])

    def concat(self, other: SensorRays) -> SensorRays:
        """These rays, then `other`'s."""
        return SensorRays(torch.cat([self.origins, other.origins]), torch.cat([self.directions, other.directions]),
                          torch.cat([self.ranges, other.ranges]))

    def valid(self) -> SensorRays:
        """Only the rays with a finite, positive range."""
        keep = torch.isfinite(self.ranges) & (self.ranges > 0)
        return SensorRays(self.origins[keep], self.directions[keep], self.ranges[keep])


@dataclass
class GridUpdateBatch:
    """Sensor and training rays a grid may use in one update (world frame, metres).

    depth_*: rays with a measured range (IRS zones) for the VIRUS Depth-Update;
    nerf_*: training rays along which the VIRUS NeRF-Update samples points.
    The Instant-NGP grid ignores this and evaluates cells instead.
    """

    depth_origins: torch.Tensor  # (K, 3)
    depth_directions: torch.Tensor  # (K, 3) unit
    depth_ranges: torch.Tensor  # (K,) metres along the ray, finite
    nerf_origins: torch.Tensor  # (M, 3)
    nerf_directions: torch.Tensor  # (M, 3) unit
    nerf_far: torch.Tensor  # (M,) metres: how far along each ray points may be drawn
    # densities the training forward pass already computed (optional NeRF-Update source):
    forward_points: torch.Tensor | None = None  # (S, 3) sample positions
    forward_sigma: torch.Tensor | None = None  # (S,) 1/m, detached


@dataclass(frozen=True)
class SensorPriorRequest:
    """What a grid wants before the first step: every training IRS zone as `zone_samples`^2
    Depth-Update rays."""

    zone_samples: int


class OccupancyGrid(ABC):
    """A grid of cells over the scene box; `occupied` is what the ray marcher reads.

    The grid owns its update: how often (`update_interval`, training steps), how many rays and
    which kinds (its config), and whether it wants a sensor prior before step 0."""

    # state_dict entries a grid holds only once something set them (a state without them loads)
    optional_state_keys: tuple[str, ...] = ()

    spec: GridSpec
    config: object  # the grid's own config dataclass
    @property
    def update_interval(self) -> int:
        """Training steps between two calls of `update`."""
        return int(self.config.update_interval)

    @property
    def prior_request(self) -> SensorPriorRequest | None:
        """Sensor rays wanted by `initialise` before the first step; None = no prior."""
        return None

    def initialise(self, depth: SensorRays | None) -> int:
        """Prior evidence before the first step (see `prior_request`); returns cell increments."""
        return 0

    def surface_points(self, points: np.ndarray) -> int:
        """Evidence that surfaces lie at world `points` (N, 3) m (the stereo's triangulated points);
        returns the number of cells raised (a grid without evidence: none)."""
        return 0

    @property
    @abstractmethod
    def occupied(self) -> torch.Tensor:
        """(rx, ry, rz) bool: cells the marcher samples in."""

    @abstractmethod
    def update(
        self,
        step: int,
        density_fn: DensityFn,
        batch: GridUpdateBatch | None,
        generator: torch.Generator,
        *,
        driving: bool = False,
    ) -> None:
        """One grid update at training step `step` (called every `update_interval` steps).

        driving: frames keep arriving (mapping while driving); a grid may schedule by it."""

    @abstractmethod
    def state_dict(self) -> dict[str, torch.Tensor | int | float]:
        ...

    @abstractmethod
    def load_state_dict(self, state: dict) -> None:
        ...

    def occupancy_share(self) -> float:
        return float(self.occupied.float().mean())

    def grow(self, box: SceneBox) -> None:
        """Cover the larger `box` (grid/extent.py): every existing cell keeps its place and value,
        the new cells start as cells nothing has updated yet."""
        raise NotImplementedError(f"{type(self).__name__} cannot grow")


def pad_cells(values: torch.Tensor, resolution: tuple[int, int, int], offset: tuple[int, int, int],
              fill: float | bool) -> torch.Tensor:
    """(rx, ry, rz) `values` placed at `offset` inside a new (RX, RY, RZ) tensor of `fill`."""
    out = torch.full(resolution, fill, dtype=values.dtype, device=values.device)
    ox, oy, oz = offset
    rx, ry, rz = values.shape
    out[ox : ox + rx, oy : oy + ry, oz : oz + rz] = values
    return out
