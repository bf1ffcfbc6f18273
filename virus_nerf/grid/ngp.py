"""The Instant-NGP occupancy grid, the baseline of the ablation (docs/method.md 3.3).

A density value per cell over the scene box. Every update (the trainer calls it every
`update_interval` steps) evaluates the field at one jittered point inside some cells: all cells
during the first `warmup_steps` training steps, afterwards n/4 cells drawn uniformly plus n/4
drawn among the currently occupied cells (with replacement, as in Instant-NGP). Then, as in
Instant-NGP's EMA kernel, every cell decays and takes the new density where it has one:
    value <- max(decay * value, sigma)     (sigma = 0 for cells not evaluated this time),
and a cell is occupied where value > min(mean of all values, sigma_max), sigma_max being the
density at which one step of the ray marcher (`march.step_size`) has alpha = min_alpha (0.01).
Before the first update every cell is occupied, so the untrained field is marched everywhere.
"""

from __future__ import annotations

import math

import torch

from virus_nerf.grid.base import DensityFn, GridSpec, GridUpdateBatch, OccupancyGrid, pad_cells
from virus_nerf.grid.ngp_config import NgpGridConfig
from virus_nerf.scene_box import SceneBox


class NgpGrid(OccupancyGrid):
    """Instant-NGP density grid; `occupied` (rx, ry, rz) bool feeds the ray marcher."""

    def __init__(
        self,
        box: SceneBox | GridSpec,
        config: NgpGridConfig | None = None,
        step_size: float = 0.01,
        device: torch.device | str = "cpu",
    ) -> None:
        """Cells over `box` (GridSpec.from_box with config.max_resolution), or over a given spec.

        step_size (metres): the ray marcher's step (the Mapper passes march.step_size), so that
        sigma_max matches what is actually marched.
        """
        self.config = config or NgpGridConfig()
        if not step_size > 0 or not 0 < self.config.min_alpha < 1:
            raise ValueError(
                f"NgpGrid needs step_size > 0 m and 0 < min_alpha < 1, got {step_size} and {self.config.min_alpha}"
            )
        self.step_size = float(step_size)
        # 1/m: the density whose alpha over one marching step is min_alpha (-ln(1 - 0.01) / step)
        self.sigma_max = -math.log(1.0 - self.config.min_alpha) / self.step_size
        if isinstance(box, GridSpec):
            self.spec = box
        else:
            self.spec = GridSpec.from_box(box, self.config.max_resolution)
        self.device = torch.device(device)
        self.values = torch.zeros(self.spec.resolution, dtype=torch.float32, device=self.device)
        self._occupied = torch.ones(self.spec.resolution, dtype=torch.bool, device=self.device)
        self.n_updates = 0
        self.last_n_evaluated = 0  # points evaluated in the last update (diagnostics, tests)

    @property
    def occupied(self) -> torch.Tensor:
        return self._occupied

    @property
    def threshold(self) -> float:
        """1/m: min(mean value, sigma_max), the occupancy threshold of the current values."""
        return min(float(self.values.mean()), self.sigma_max)

    def cells_to_update(self, step: int, generator: torch.Generator) -> torch.Tensor:
        """Flat cell indices (K,) int64 to evaluate at training step `step`."""
        n = self.spec.n_cells
        if step < self.config.warmup_steps:
            return torch.arange(n, device=self.device)
        q = n // 4
        uniform = torch.randint(n, (q,), generator=generator, device=generator.device)
        occ = torch.nonzero(self._occupied.reshape(-1).to(generator.device)).squeeze(1)
        if occ.numel() == 0:  # nothing occupied: Instant-NGP draws nothing from it either
            return uniform.to(self.device)
        pick = torch.randint(occ.numel(), (q,), generator=generator, device=generator.device)
        return torch.cat([uniform, occ[pick]]).to(self.device)

    def cell_points(self, cells: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """World points (K, 3) float32, one uniform random point inside each flat cell index."""
        _, ry, rz = self.spec.resolution
        ijk = torch.stack([cells // (ry * rz), (cells // rz) % ry, cells % rz], dim=-1)
        u = torch.rand(
            cells.shape[0], 3, generator=generator, dtype=torch.float64, device=generator.device
        ).to(self.device)
        lo = torch.tensor(self.spec.box.lo, dtype=torch.float64, device=self.device)
        cell = torch.from_numpy(self.spec.cell_size).to(self.device)
        return (lo + (ijk.to(torch.float64) + u) * cell).to(torch.float32)

    def update(
        self,
        step: int,
        density_fn: DensityFn,
        batch: GridUpdateBatch | None,
        generator: torch.Generator,
        *,
        driving: bool = False,
    ) -> None:
        """One Instant-NGP update at training step `step`; `batch` and the schedule are not used
        by this grid."""
        cells = self.cells_to_update(step, generator)
        points = self.cell_points(cells, generator)
        sigma = torch.empty(cells.shape[0], dtype=torch.float32, device=self.device)
        with torch.no_grad():
            for a in range(0, cells.shape[0], self.config.chunk_size):
                b = min(a + self.config.chunk_size, cells.shape[0])
                out = density_fn(points[a:b]).reshape(-1)
                if out.shape[0] != b - a:
                    raise ValueError(
                        f"density_fn returned {out.shape[0]} values for {b - a} points"
                    )
                sigma[a:b] = out.to(torch.float32)
        sigma = torch.nan_to_num(sigma, nan=0.0).clamp(min=0.0)  # a NaN must not mark a cell
        fresh = torch.zeros(self.spec.n_cells, dtype=torch.float32, device=self.device)
        fresh.scatter_reduce_(0, cells, sigma, reduce="amax")  # a cell drawn twice keeps the max
        values = torch.maximum(self.values.reshape(-1) * self.config.decay, fresh)
        self.values = values.reshape(self.spec.resolution)
        self._occupied = self.values > self.threshold
        self.n_updates += 1
        self.last_n_evaluated = int(cells.shape[0])

    def grow(self, box: SceneBox) -> None:
        """Cover the larger `box` (grid/extent.py): cells keep their values; new cells start as
        at construction (density 0, occupied until an update evaluates them)."""
        spec, offset = self.spec.grown(box)
        self.values = pad_cells(self.values, spec.resolution, offset, 0.0)
        self._occupied = pad_cells(self._occupied, spec.resolution, offset, True)
        self.spec = spec

    def state_dict(self) -> dict[str, torch.Tensor | int | float]:
        return {
            "values": self.values.clone(),
            "occupied": self._occupied.clone(),
            "n_updates": self.n_updates,
            "resolution": torch.tensor(self.spec.resolution),
        }

    def load_state_dict(self, state: dict) -> None:
        res = tuple(int(v) for v in state["resolution"])
        if res != tuple(self.spec.resolution):
            raise ValueError(
                f"grid state has resolution {res}, this grid has {self.spec.resolution}"
            )
        self.values = state["values"].to(self.device, torch.float32).clone()
        self._occupied = state["occupied"].to(self.device, torch.bool).clone()
        self.n_updates = int(state["n_updates"])
