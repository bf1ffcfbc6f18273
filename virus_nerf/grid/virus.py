"""The Bayesian VIRUS occupancy grid (paper III-B, docs/method.md 3.4).

Cells hold clamped log-odds l = ln p/(1-p) (float32); the marcher samples where l > 0 (p > 0.5).
Every update step (every `update_interval` training steps) the grid:
1. moves every cell along the warm-up schedule (counted in training steps, docs/method.md 9.6),
2. runs the Depth-Update on a share of the batch's IRS rays (sensor_model.depth_log_odds,
   every crossed cell visited, docs/method.md 9.4),
3. runs the NeRF-Update (eq. 9) on points along the rest of the rays.
Writes use the shared cell-index formula (docs/method.md 9.5): both updates name cells with
`cell_index_scalar`, the numba twin of the marcher's `cell_index`.

Warm-up: l = l_init (p_init = 0.55, so everything is marched at first) plus an offset that goes
linearly from 0 at step 0 to l_prior - l_init at `warmup_steps` (p_prior = 0.49). The offset is
applied to all cells as a difference at each update, so after step `warmup_steps` a cell no
sensor or NeRF-Update ever supported sits at l_prior < 0 (empty) however many updates ran, and a
cell with evidence keeps it (the offset is small, 0.24 in log-odds).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from virus_nerf.grid.base import (
    DensityFn,
    GridSpec,
    GridUpdateBatch,
    OccupancyGrid,
    SensorPriorRequest,
    SensorRays,
    pad_cells,
)
from virus_nerf.grid.sensor_model import (
    depth_update_kernel,
    nerf_log_odds,
    points_to_cells,
    spec_arrays,
)
from virus_nerf.grid.virus_config import VirusGridConfig
from virus_nerf.scene_box import SceneBox


@dataclass(frozen=True)
class NerfUpdateInfo:
    """What the last NeRF-Update did (for logging): points drawn / inside the box, sigma_T (1/m),
    cells touched."""

    n_drawn: int
    n_points: int
    sigma_threshold: float
    n_cells: int


class VirusGrid(OccupancyGrid):
    """Bayesian occupancy grid over the scene box, updated from IRS ranges and the NeRF's density."""

    optional_state_keys = ("viewed", "restart_step", "column_applied")  # a column's warm-up restarted

    def __init__(
        self,
        box: SceneBox | GridSpec,
        config: VirusGridConfig | None = None,
        device: torch.device | str = "cpu",
    ) -> None:
        """Cells over `box` (GridSpec.from_box with config.max_resolution), or over a given spec.

        The log-odds live on the CPU (numba kernels write them); `occupied` is handed out on
        `device`, where the ray marcher runs.
        """
        self.config = config or VirusGridConfig()
        self.spec = box if isinstance(box, GridSpec) else GridSpec.from_box(box, self.config.max_resolution)
        self.device = torch.device(device)
        self._lo, self._size, self._res = spec_arrays(self.spec)
        # (rx, ry, rz) float32 log-odds; flat index = (ix * ry + iy) * rz + iz (base.cell_index)
        self._logodds = torch.full(self.spec.resolution, self.config.logodds_init, dtype=torch.float32)
        self._decay_applied = 0.0  # warm-up offset of the run's clock (every cell follows it ...)
        # ... but columns a camera first looked at after the start (restart_warmup_in_view): per
        # column (rx, ry) the step its own warm-up started (-1: the run's clock) and the offset
        # added to it; None until the first such column
        self._restart_step: np.ndarray | None = None
        self._column_applied: np.ndarray | None = None
        self._viewed: np.ndarray | None = None  # (rx, ry) bool: in some training frame's view
        self._last_step = -1
        self._n_updates = 0
        self.last_nerf_update: NerfUpdateInfo | None = None
        self._occupied: torch.Tensor | None = None  # cache of logodds > 0, reset on every write

    # ------------------------------------------------------------------ reads
    @property
    def prior_request(self) -> SensorPriorRequest | None:
        c = self.config
        if c.init != "sensors":
            return None
        return SensorPriorRequest(c.init_zone_samples)

    @property
    def warmup_done(self) -> bool:
        """True once the run's warm-up clock has applied its whole offset (p_init moved to p_prior):
        until then cells nothing has updated are still occupied. Columns whose warm-up restarted
        while driving (restart_warmup_in_view) run their own, local clocks; they do not count."""
        c = self.config
        return abs(self._decay_applied - (c.logodds_prior - c.logodds_init)) < 1e-6

    @property
    def logodds(self) -> torch.Tensor:
        """(rx, ry, rz) float32 log-odds (a view: do not write)."""
        return self._logodds

    @property
    def probability(self) -> torch.Tensor:
        """(rx, ry, rz) occupancy probability in [0, 1]."""
        return torch.sigmoid(self._logodds)

    @property
    def occupied(self) -> torch.Tensor:
        """(rx, ry, rz) bool, p > 0.5 <=> l > 0. Cached between writes: the marcher reads it
        every step, the grid changes every `update_interval` steps. Do not write into it."""
        if self._occupied is None:
            self._occupied = torch.from_numpy(self._logodds.numpy() > 0.0).to(self.device)
        return self._occupied

    # ----------------------------------------------------------------- update
    def update(
        self,
        step: int,
        density_fn: DensityFn | None,
        batch: GridUpdateBatch | None,
        generator: torch.Generator,
        *,
        driving: bool = False,
    ) -> None:
        """Warm-up decay (scheduled by `driving`), then Depth-Update and
        NeRF-Update on their shares of `batch`.

        Depth rays get round(depth_share * rays_per_update) (fewer if the batch has fewer); the
        NeRF-Update gets the rest of rays_per_update, so a camera-only run (no depth rays) spends
        the whole budget on the NeRF-Update and every sensor combination runs (docs/method.md 9.10).
        All randomness comes from `generator`.
        """
        if step < 0:
            raise ValueError(f"VirusGrid.update: step must be >= 0, got {step}")
        self._occupied = None
        self._apply_warmup(step, driving)
        if batch is not None:
            n_depth_avail = int(batch.depth_ranges.shape[0])
            n_nerf_avail = int(batch.nerf_origins.shape[0])
            n_depth = min(n_depth_avail, round(self.config.depth_share * self.config.rays_per_update))
            n_nerf = min(n_nerf_avail, self.config.rays_per_update - n_depth)
            if n_depth > 0:
                pick = torch.randperm(n_depth_avail, generator=generator, device=generator.device)[:n_depth]
                pick = pick.to(batch.depth_origins.device)
                self.depth_update(
                    batch.depth_origins[pick], batch.depth_directions[pick], batch.depth_ranges[pick]
                )
            forward = self.config.nerf_update_source == "forward" and batch.forward_sigma is not None
            if forward and n_nerf > 0:
                self.nerf_update_from_samples(batch.forward_points, batch.forward_sigma)
            elif n_nerf > 0 and density_fn is not None:
                pick = torch.randperm(n_nerf_avail, generator=generator, device=generator.device)[:n_nerf]
                pick = pick.to(batch.nerf_origins.device)
                self.nerf_update(
                    density_fn,
                    batch.nerf_origins[pick],
                    batch.nerf_directions[pick],
                    batch.nerf_far[pick],
                    generator,
                )
        self._last_step = step
        self._n_updates += 1

    def _apply_warmup(self, step: int, driving: bool = False) -> None:
        """Move every cell to the warm-up offset of `step` (a function of steps, not updates);
        over `warmup_steps_driving` steps instead while `driving` (the offset is applied as a
        difference, so a switch moves every cell by the same amount and keeps its evidence). A
        column whose warm-up restarted (restart_warmup_in_view) follows its own clock from then."""
        c = self.config
        length = c.warmup_steps_driving if driving else c.warmup_steps
        done = min(step, length) / length
        full = c.logodds_prior - c.logodds_init
        target = full * done
        if self._restart_step is None:
            delta = target - self._decay_applied
            if delta != 0.0:
                # numpy in place (single-threaded): torch's intra-op threads cost ~30 ms here on a
                # busy 2-core machine against ~0.5 ms for one thread
                flat = self._logodds.view(-1).numpy()
                np.add(flat, np.float32(delta), out=flat)
                np.clip(flat, c.logodds_min, c.logodds_max, out=flat)
        else:
            own = self._restart_step >= 0
            column_done = np.minimum(np.maximum(step - self._restart_step, 0), length) / length
            column_target = np.where(own, full * column_done, target).astype(np.float32)  # (rx, ry)
            delta = column_target - self._column_applied
            if np.any(delta != 0.0):
                cells = self._logodds.numpy()  # (rx, ry, rz), shares memory
                np.add(cells, delta[:, :, None], out=cells)
                np.clip(cells, c.logodds_min, c.logodds_max, out=cells)
                self._column_applied = column_target
        self._decay_applied = target

    def restart_warmup_in_view(self, viewed: np.ndarray, step: int) -> int:
        """Columns (rx, ry) bool `viewed` that a training frame's camera now looks at: each one
        seen for the first time after step 0 starts its warm-up again, from p_init (its evidence
        kept), so a part of the room the robot reaches late is marched, and learnt by the field,
        as the first part was (virus_grid.warmup_restart; docs/method.md 3.4). Columns in view at
        step 0 follow the run's clock. Returns the number of columns restarted."""
        viewed = np.asarray(viewed, dtype=bool)
        rx, ry, _ = self.spec.resolution
        if viewed.shape != (rx, ry):
            raise ValueError(f"VirusGrid.restart_warmup_in_view: viewed {viewed.shape}, expected ({rx}, {ry})")
        if self._viewed is None:
            self._viewed = np.zeros((rx, ry), dtype=bool)
        new = viewed & ~self._viewed
        self._viewed |= viewed
        if step <= 0 or not new.any():
            return 0
        if self._restart_step is None:
            self._restart_step = np.full((rx, ry), -1, dtype=np.int32)
            self._column_applied = np.full((rx, ry), self._decay_applied, dtype=np.float32)
        self._restart_step[new] = step
        self._occupied = None
        return int(new.sum())

    def initialise(self, depth: SensorRays | None) -> int:
        """Prior knowledge before the first training step (config.init == "sensors").

        A Depth-Update along every `depth` ray (the training IRS zones: free space up to each
        return, occupied at it). Cells no sensor saw keep p_init and go through the warm-up as
        before. Returns the number of (cell, ray) increments applied.
        """
        if self.config.init == "none" or depth is None or not len(depth):
            return 0
        return self.depth_update(depth.origins, depth.directions, depth.ranges)

    def surface_points(self, points: np.ndarray) -> int:
        """Each cell holding one of the world `points` (N, 3) m gets `stereo_point_increment` in
        log-odds, once per call however many points it holds (one measurement, as a NeRF-Update
        cell); points outside the box and non-finite ones count nowhere. Returns the cells raised."""
        inc = self.config.stereo_point_increment
        pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        pts = np.ascontiguousarray(pts[np.isfinite(pts).all(axis=1)])
        if inc <= 0.0 or not len(pts):
            return 0
        cells = points_to_cells(pts, self._lo, self._size, self._res)
        cells = np.unique(cells[cells >= 0])
        self._occupied = None
        flat = self._logodds.view(-1).numpy()  # shares memory
        flat[cells] = np.clip(flat[cells] + np.float32(inc), self.config.logodds_min, self.config.logodds_max)
        return int(len(cells))

    def depth_update(self, origins: torch.Tensor, directions: torch.Tensor, ranges: torch.Tensor) -> int:
        """Depth-Update: origins (K, 3), directions (K, 3), ranges (K,) metres along the ray.

        Directions are normalised here; rays with a non-finite or non-positive range are skipped.
        Returns the number of (cell, ray) increments applied.
        """
        o, d, m = _check_rays(origins, directions, ranges, "depth")
        if o.shape[0] == 0:
            return 0
        c = self.config
        self._occupied = None
        flat = self._logodds.view(-1).numpy()  # shares memory: the kernel writes in place
        return int(
            depth_update_kernel(
                o, d, m, self._lo, self._size, self._res, flat,
                c.std_per_m, c.std_floor, c.false_rate, c.hit_probability, c.stop_length,
                c.max_increment, c.logodds_min, c.logodds_max,
            )
        )

    @torch.no_grad()
    def nerf_update(
        self,
        density_fn: DensityFn,
        origins: torch.Tensor,
        directions: torch.Tensor,
        far: torch.Tensor,
        generator: torch.Generator,
    ) -> NerfUpdateInfo:
        """NeRF-Update (eq. 9) along rays: origins (M, 3), directions (M, 3) unit, far (M,) metres.

        P points per ray at t ~ U(0, far), jittered by N(0, (pos_noise_per_m t)^2) per axis;
        points outside the box are dropped, the rest evaluated by `density_fn` without gradient.
        sigma_T = min(sigma_T_max, mean sigma of these points). Several points in one cell count
        as one measurement: the cell gets the mean of their increments, so a cell's evidence does
        not depend on how many rays happen to cross it (cells near the cameras would otherwise
        get most of it).
        """
        c = self.config
        o, d, f = _check_rays(origins, directions, far, "nerf")  # float64, unit directions
        n_rays, p = o.shape[0], c.nerf_points_per_ray
        # draws from the torch generator (reproducible), arithmetic in numpy/numba: single-threaded,
        # immune to torch's intra-op thread wake-ups on a busy 2-core machine
        u = torch.rand(n_rays, p, generator=generator, device=generator.device).cpu().numpy()
        noise = torch.randn(n_rays, p, 3, generator=generator, device=generator.device).cpu().numpy()
        t = u.astype(np.float64) * f[:, None]  # (M, P) metres
        pts = o[:, None, :] + d[:, None, :] * t[..., None] + noise * (c.pos_noise_per_m * t)[..., None]
        pts = np.ascontiguousarray(pts.reshape(-1, 3), dtype=np.float32)  # (M*P, 3)
        cells = points_to_cells(pts, self._lo, self._size, self._res)  # cell_index_scalar
        inside = cells >= 0
        pts, cells = pts[inside], cells[inside]
        if cells.shape[0] == 0:
            return self._apply_nerf_evidence(cells, np.zeros(0), n_rays * p)
        sigma = density_fn(torch.from_numpy(pts).to(origins.device)).detach().reshape(-1)
        if sigma.shape[0] != pts.shape[0]:
            raise ValueError(
                f"density_fn returned {sigma.shape[0]} densities for {pts.shape[0]} points"
            )
        return self._apply_nerf_evidence(cells, sigma.to("cpu", torch.float64).numpy(), n_rays * p)

    @torch.no_grad()
    def nerf_update_from_samples(self, points: torch.Tensor, sigma: torch.Tensor) -> NerfUpdateInfo:
        """NeRF-Update (eq. 9) from densities already computed: points (S, 3) m, sigma (S,) 1/m."""
        pts = np.ascontiguousarray(points.detach().to("cpu", torch.float32).numpy())
        cells = points_to_cells(pts, self._lo, self._size, self._res)
        sig = sigma.detach().to("cpu", torch.float64).numpy().reshape(-1)
        inside = cells >= 0
        return self._apply_nerf_evidence(cells[inside], sig[inside], int(pts.shape[0]))

    def _apply_nerf_evidence(self, cells: np.ndarray, sigma: np.ndarray, n_drawn: int) -> NerfUpdateInfo:
        """Per-cell mean of the eq. 9 increments of densities `sigma` (N,) at points in `cells` (N,).

        Non-finite densities (a diverged network) are dropped, so they cannot poison a cell:
        numpy's maximum/clip and Python's min pass NaN through silently.
        """
        c = self.config
        finite = np.isfinite(sigma)
        cells, sigma = cells[finite], sigma[finite]
        if cells.shape[0] == 0:
            info = NerfUpdateInfo(n_drawn=n_drawn, n_points=0, sigma_threshold=float("nan"), n_cells=0)
            self.last_nerf_update = info
            return info
        sigma_t = min(c.sigma_threshold_max, float(sigma.mean()))
        inc = nerf_log_odds(sigma, sigma_t, c.zeta, c.max_increment, c.sigma_floor)
        # per-cell mean increment; bincount sums sequentially, so this is deterministic
        uniq, inv = np.unique(cells, return_inverse=True)
        sums = np.bincount(inv, weights=inc, minlength=uniq.shape[0])
        counts = np.bincount(inv, minlength=uniq.shape[0])
        self._occupied = None
        flat = self._logodds.view(-1).numpy()
        new = flat[uniq].astype(np.float64) + sums / counts
        flat[uniq] = np.clip(new, c.logodds_min, c.logodds_max).astype(np.float32)
        info = NerfUpdateInfo(
            n_drawn=n_drawn, n_points=int(cells.shape[0]), sigma_threshold=sigma_t, n_cells=int(uniq.shape[0])
        )
        self.last_nerf_update = info
        return info

    def grow(self, box: SceneBox) -> None:
        """Cover the larger `box` (grid/extent.py): cells keep their values; new cells get the
        value of a cell nothing updated (p_init moved by the warm-up so far)."""
        spec, offset = self.spec.grown(box)
        c = self.config
        fill = float(np.clip(np.float32(c.logodds_init) + np.float32(self._decay_applied), c.logodds_min,
                             c.logodds_max))
        self._logodds = pad_cells(self._logodds, spec.resolution, offset, fill)

        def pad_columns(values: np.ndarray, column_fill) -> np.ndarray:  # (rx, ry) -> (RX, RY)
            out = np.full(spec.resolution[:2], column_fill, dtype=values.dtype)
            out[offset[0] : offset[0] + values.shape[0], offset[1] : offset[1] + values.shape[1]] = values
            return out

        if self._viewed is not None:
            self._viewed = pad_columns(self._viewed, False)
        if self._restart_step is not None:
            self._restart_step = pad_columns(self._restart_step, -1)
            self._column_applied = pad_columns(self._column_applied, self._decay_applied)
        self.spec = spec
        self._lo, self._size, self._res = spec_arrays(spec)
        self._occupied = None

    # ------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, torch.Tensor | int | float]:
        state = {
            "logodds": self._logodds.clone(),
            "decay_applied": float(self._decay_applied),
            "last_step": int(self._last_step),
            "n_updates": int(self._n_updates),
        }
        if self._viewed is not None:
            state["viewed"] = torch.from_numpy(self._viewed.copy())
        if self._restart_step is not None:
            state["restart_step"] = torch.from_numpy(self._restart_step.copy())
            state["column_applied"] = torch.from_numpy(self._column_applied.copy())
        return state

    def load_state_dict(self, state: dict) -> None:
        for key in ("logodds", "decay_applied", "last_step", "n_updates"):
            if key not in state:
                raise ValueError(f"VirusGrid.load_state_dict: missing field {key!r}")
        lo = state["logodds"]
        if tuple(lo.shape) != tuple(self.spec.resolution):
            raise ValueError(
                f"VirusGrid.load_state_dict: field 'logodds' has shape {tuple(lo.shape)}, "
                f"grid resolution is {self.spec.resolution}"
            )
        self._logodds = lo.detach().to("cpu", torch.float32).clone()
        self._occupied = None
        self._decay_applied = float(state["decay_applied"])
        self._last_step = int(state["last_step"])
        self._n_updates = int(state["n_updates"])
        # absent in checkpoints of runs without a restarted column (and before the option)
        self._viewed = state["viewed"].numpy().astype(bool).copy() if "viewed" in state else None
        if "restart_step" in state:
            self._restart_step = state["restart_step"].numpy().astype(np.int32).copy()
            self._column_applied = state["column_applied"].numpy().astype(np.float32).copy()
        else:
            self._restart_step = self._column_applied = None


def _check_rays(origins, directions, ranges, what: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K, 3), (K, 3), (K,) tensors -> contiguous float64 numpy with unit directions."""
    o = torch.as_tensor(origins).detach().to("cpu", torch.float64)
    d = torch.as_tensor(directions).detach().to("cpu", torch.float64)
    m = torch.as_tensor(ranges).detach().to("cpu", torch.float64).reshape(-1)
    k = m.shape[0]
    if o.shape != (k, 3) or d.shape != (k, 3):
        raise ValueError(
            f"{what} rays: origins {tuple(o.shape)} and directions {tuple(d.shape)} must be ({k}, 3) "
            f"to match ranges ({k},)"
        )
    norm = d.norm(dim=-1, keepdim=True)
    if k and not bool((norm > 0).all()):
        raise ValueError(f"{what} rays: directions contain a zero vector")
    d = d / norm.clamp_min(1e-300)
    return o.contiguous().numpy(), d.contiguous().numpy(), m.contiguous().numpy()
