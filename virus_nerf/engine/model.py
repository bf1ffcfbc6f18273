"""The scene model: field + occupancy grid + marcher, rendering rays end to end.

`SceneModel.ranges` makes a trained model a RangeModel for the 2D scan evaluation (docs/method.md 6.3):
depth / opacity along each ray, NaN where opacity < min_opacity (docs/method.md 3.1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from virus_nerf.data.ethz import Recording
from virus_nerf.data.room_box import fit_scene_box
from virus_nerf.engine.config import MapperConfig
from virus_nerf.field.field import NerfField
from virus_nerf.grid.base import GridSpec, OccupancyGrid
from virus_nerf.grid.ngp import NgpGrid
from virus_nerf.grid.virus import VirusGrid
from virus_nerf.render.compositing import (
    RenderOutput,
    composite,
    opacity_front,
    scan_depth,
    transmittance,
)
from virus_nerf.render.marching import march_rays
from virus_nerf.render.samples import PackedSamples
from virus_nerf.scene_box import SceneBox

# Visible share of the marched samples under which a training step first finds the hidden ones
# with a density-only pass (then trains the rest); above it one pass trains every density and
# skips only the hidden samples' colour. Cost model from the step profile (hash encoding forward
# ~15 %, backward ~22 %, density MLP ~21 %, colour MLP ~42 % of the field's time): the pre-pass
# costs ~22 % of a full pass and pays off below a ~0.6 visible share.
TWO_PASS_BELOW = 0.6


@dataclass
class RenderStats:
    n_rays: int
    n_samples: int  # marched samples (each at least through the density pass)
    positions: torch.Tensor | None = None  # (S, 3) sample points (for a forward-pass NeRF-Update)
    sigma: torch.Tensor | None = None  # (S,) 1/m at those points, detached
    samples: PackedSamples | None = None  # the rendered intervals (for losses on the weights)
    n_trained: int = 0  # samples rendered with gradients (below n_samples when hidden ones are skipped)
    # share of the marched samples still visible (T >= min_transmittance), measured by a training
    # render that skips hidden samples; None when not measured. The caller keeps it and hands it to
    # the next render, where it picks the path (TWO_PASS_BELOW)
    visible_share: float | None = None


class SceneModel:
    """Renders colour, depth and opacity of rays through the field, marching in occupied cells."""

    def __init__(self, field: NerfField, grid: OccupancyGrid, step_size: float, near: float, max_samples: int,
                 min_opacity: float = 0.5, backend: str = "auto", min_transmittance: float = 0.0):
        self.field = field
        self.grid = grid
        self.step_size = step_size
        self.near = near
        self.max_samples = max_samples
        self.min_opacity = min_opacity
        self.backend = backend  # marching and compositing kernels (render.marching.resolve_backend)
        # training: samples behind transmittance < this skip the gradient pass (0 = render all)
        self.min_transmittance = min_transmittance

    @property
    def device(self) -> torch.device:
        return next(self.field.parameters()).device

    def render(
        self,
        origins: torch.Tensor,
        directions: torch.Tensor,
        generator: torch.Generator | None = None,
        rgb_rays: torch.Tensor | None = None,
        visible_share: float = 1.0,
        occupied: torch.Tensor | None = None,
    ) -> tuple[RenderOutput, RenderStats]:
        """origins, directions (R, 3) -> RenderOutput (rgb (R,3), depth (R,), opacity (R,)).

        rgb_rays (R,) bool, optional: rays whose colour is needed; the others are rendered for
        depth only (their rgb is 0 and carries no gradient). visible_share: the previous training
        render's `RenderStats.visible_share`, which picks this one's path when hidden samples are
        skipped (below TWO_PASS_BELOW: a density pre-pass). occupied (rx, ry, rz) bool, optional:
        the cells to march instead of the grid's own (the map's low scans, maps/extract.py). The
        model keeps no state of its own.
        """
        samples = march_rays(
            origins,
            directions,
            self.grid.occupied if occupied is None else occupied,
            self.grid.spec,
            near=self.near,
            far=1e4,
            step_size=self.step_size,
            max_samples_per_ray=self.max_samples,
            jitter=generator,
            backend=self.backend,
        )
        positions = samples.positions(origins, directions)  # (S, 3)
        dirs = directions[samples.ray_indices]  # (S, 3)
        rgb_mask = None if rgb_rays is None else rgb_rays[samples.ray_indices]  # (S,)
        if self.min_transmittance > 0 and torch.is_grad_enabled():
            if visible_share < TWO_PASS_BELOW:
                return self._render_visible(origins.shape[0], samples, positions, dirs, rgb_mask)
            return self._render_colour_visible(origins.shape[0], samples, positions, dirs, rgb_mask)
        sigma, rgb = self.field(positions, dirs, rgb_mask)
        out = composite(sigma, rgb, samples, n_rays=origins.shape[0], background=None, backend=self.backend)
        stats = RenderStats(
            n_rays=origins.shape[0], n_samples=samples.n_samples, positions=positions.detach(),
            sigma=sigma.detach(), samples=samples, n_trained=samples.n_samples,
        )
        return out, stats

    def _render_visible(self, n_rays: int, samples: PackedSamples, positions: torch.Tensor, dirs: torch.Tensor,
                        rgb_mask: torch.Tensor | None) -> tuple[RenderOutput, RenderStats]:
        """Two passes: densities of all S samples without gradients, then the full field with
        gradients only on the samples still visible (T_j >= min_transmittance; a prefix of each
        ray). Behind a surface nothing reaches a loss (compositing.transmittance), so the
        colour MLP and both backward passes skip those samples (docs/method.md 10)."""
        with torch.no_grad():
            sigma_all = self.field.density(positions)  # (S,)
        keep = transmittance(sigma_all, samples) >= self.min_transmittance  # (S,) bool
        visible = samples.select(keep)
        sub_mask = None if rgb_mask is None else rgb_mask[keep]
        sigma, rgb = self.field(positions[keep], dirs[keep], sub_mask)  # (V,), (V, 3)
        out = composite(sigma, rgb, visible, n_rays=n_rays, background=None, backend=self.backend)
        stats = RenderStats(
            n_rays=n_rays, n_samples=samples.n_samples, positions=positions.detach(), sigma=sigma_all,
            samples=visible, n_trained=visible.n_samples, visible_share=_share(keep),
        )
        return out, stats

    def _render_colour_visible(self, n_rays: int, samples: PackedSamples, positions: torch.Tensor,
                               dirs: torch.Tensor, rgb_mask: torch.Tensor | None) -> tuple[RenderOutput, RenderStats]:
        """One pass: densities of all S samples with gradients, the colour MLP only on the visible
        ones (T_j >= min_transmittance; hidden samples get rgb 0, which moves the render by less
        than their weights, < eps). Cheaper than `_render_visible` when most samples are visible
        (a hazy early field), where a density pre-pass would find little to skip."""
        sigma, h, idx = self.field.geometry(positions)  # (S,), (M, G), (M,)
        keep = transmittance(sigma, samples) >= self.min_transmittance  # (S,) bool
        rgb = self.field.colour_at(h, idx, dirs, keep if rgb_mask is None else keep & rgb_mask)  # (S, 3)
        out = composite(sigma, rgb, samples, n_rays=n_rays, background=None, backend=self.backend)
        stats = RenderStats(
            n_rays=n_rays, n_samples=samples.n_samples, positions=positions.detach(), sigma=sigma.detach(),
            samples=samples, n_trained=samples.n_samples, visible_share=_share(keep),
        )
        return out, stats

    @torch.no_grad()
    def ranges(self, origins: np.ndarray, directions: np.ndarray, chunk: int = 8192,
               occupied: torch.Tensor | None = None, front: float | None = None) -> np.ndarray:
        """Scan depth (N,) metres along unit rays; NaN where the model sees nothing (docs/method.md 3.1).
        occupied: the cells to march instead of the grid's own (`render`). front: give the depth
        where a ray's opacity first reaches this level instead of D / A (`opacity_front`)."""
        out = np.full(len(origins), np.nan)
        o_all = torch.as_tensor(np.asarray(origins, dtype=np.float32), device=self.device)
        d_all = torch.as_tensor(np.asarray(directions, dtype=np.float32), device=self.device)
        for start in range(0, len(origins), chunk):
            o, d = o_all[start : start + chunk], d_all[start : start + chunk]
            no_colour = torch.zeros(o.shape[0], dtype=torch.bool, device=self.device)  # scans need depth only
            r, stats = self.render(o, d, generator=None, rgb_rays=no_colour, occupied=occupied)
            depth = scan_depth(r, self.min_opacity) if front is None else \
                opacity_front(r, stats.samples, front, self.min_opacity)  # (n,)
            out[start : start + len(o)] = depth.double().cpu().numpy()
        return out


def _share(keep: torch.Tensor) -> float:
    """Share of True in (S,) bool `keep`; 1.0 for no sample."""
    return float(keep.float().mean()) if keep.numel() else 1.0


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def start_box(recording: Recording, config: MapperConfig) -> SceneBox:
    """The mapper's box before its first frame: fitted to the room (`extent.mode` fitted), or the
    box around the recording's first training frame (grow: grid/extent.py)."""
    if config.extent.mode != "grow":
        return fit_scene_box(recording)
    from virus_nerf.grid.extent import first_box

    first = min(((float(st.times[i]), st.cam_to_world[i, :3, 3]) for st in recording.stacks.values()
                 for i in st.indices("train")[:1]), key=lambda tp: tp[0])
    return first_box(first[1], config.extent, config.sensors)


def build_grid(config: MapperConfig, box: SceneBox, device: torch.device, spec: GridSpec | None = None) -> OccupancyGrid:
    """The configured occupancy grid over `spec` (default: `box` with the grid's max_resolution);
    a grid that cannot fit in memory is refused before it is allocated."""
    from virus_nerf.utils.memory import require_memory

    cfg = config.ngp_grid if config.grid == "ngp" else config.virus_grid
    spec = spec or GridSpec.from_box(box, cfg.max_resolution)
    key = "extent.grid_cell_m" if config.extent.mode == "grow" else f"{config.grid}_grid.max_resolution"
    # per cell: float32 value, bool occupied, float32 probability or density on reading
    require_memory(f"{key}: a {'x'.join(map(str, spec.resolution))} cell grid", spec.n_cells * 9.0,
                   "a coarser grid")
    if config.grid == "ngp":
        cfg = config.ngp_grid
        return NgpGrid(spec, cfg, step_size=config.march.step_size, device=device)
    return VirusGrid(spec, cfg, device=device)
