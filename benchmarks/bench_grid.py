"""VIRUS grid update cost on its own: Depth-Update, NeRF-Update (analytic density, no network)
and a whole update() call, in milliseconds (median over repeats), at the default resolution.

    .venv/bin/python benchmarks/bench_grid.py
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from virus_nerf.grid.base import GridUpdateBatch
from virus_nerf.grid.virus import VirusGrid, VirusGridConfig
from virus_nerf.scene_box import SceneBox


@dataclass(frozen=True)
class UpdateTiming:
    """Milliseconds per call (median over repeats) of the grid's parts, density cost excluded-ish."""

    depth_ms: float  # Depth-Update of n_depth rays
    nerf_ms: float  # NeRF-Update of n_nerf rays with an analytic density (no network)
    update_ms: float  # a whole update() call, warm-up decay included
    n_depth: int
    n_nerf: int
    resolution: tuple[int, int, int]


def benchmark_update(
    n_rays: int = 1024, repeats: int = 20, seed: int = 0, config: VirusGridConfig | None = None
) -> UpdateTiming:
    """Time one update in a 9 x 8 x 2.6 m room at the configured resolution (128 by default).

    IRS-like rays from 0.4-1.2 m height with ranges 0.3-4 m; NeRF rays with far = 6 m and a
    cheap analytic density (walls dense, inside empty), so the number measures the grid itself.
    """
    cfg = config or VirusGridConfig(rays_per_update=n_rays)
    box = SceneBox((0.0, 0.0, 0.0), (9.0, 8.0, 2.6))
    g = torch.Generator().manual_seed(seed)
    k = n_rays

    def rays(n: int) -> tuple[torch.Tensor, torch.Tensor]:
        o = torch.rand(n, 3, generator=g) * torch.tensor([7.0, 6.0, 0.8]) + torch.tensor([1.0, 1.0, 0.4])
        d = torch.randn(n, 3, generator=g)
        d[:, 2] *= 0.3
        return o, d / d.norm(dim=-1, keepdim=True)

    do, dd = rays(k)
    no, nd = rays(k)
    batch = GridUpdateBatch(
        depth_origins=do, depth_directions=dd, depth_ranges=0.3 + 3.7 * torch.rand(k, generator=g),
        nerf_origins=no, nerf_directions=nd, nerf_far=torch.full((k,), 6.0),
    )

    def density(p: torch.Tensor) -> torch.Tensor:  # walls 0.2 m thick are dense
        lo = torch.tensor([0.2, 0.2, 0.2])
        hi = torch.tensor([8.8, 7.8, 2.4])
        wall = ((p < lo) | (p > hi)).any(dim=-1)
        return torch.where(wall, torch.tensor(500.0), torch.tensor(0.05))

    grid = VirusGrid(box, cfg)
    n_depth = min(k, round(cfg.depth_share * cfg.rays_per_update))
    n_nerf = min(k, cfg.rays_per_update - n_depth)
    grid.depth_update(do[:n_depth], dd[:n_depth], batch.depth_ranges[:n_depth])  # compile/warm
    grid.update(0, density, batch, g)

    def timed(fn) -> float:
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
        return 1e3 * float(np.median(ts))

    depth_ms = timed(lambda: grid.depth_update(do[:n_depth], dd[:n_depth], batch.depth_ranges[:n_depth]))
    nerf_ms = timed(lambda: grid.nerf_update(density, no[:n_nerf], nd[:n_nerf], batch.nerf_far[:n_nerf], g))
    steps = iter(range(1, 10**9))
    update_ms = timed(lambda: grid.update(next(steps) * cfg.update_interval, density, batch, g))
    return UpdateTiming(depth_ms, nerf_ms, update_ms, n_depth, n_nerf, grid.spec.resolution)


def main() -> None:
    import argparse
    import dataclasses
    import json

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rays", default="256,1024,4096", help="rays per update to time, comma-separated")
    ap.add_argument("--repeats", type=int, default=20, help="calls per figure (the median is reported)")
    args = ap.parse_args()
    rows = [dataclasses.asdict(benchmark_update(n_rays=int(n), repeats=args.repeats)) for n in args.rays.split(",")]
    print(json.dumps({"benchmark": "virus_grid_update", "torch_threads": torch.get_num_threads(), "runs": rows},
                     indent=1))


if __name__ == "__main__":
    main()
