"""Speed of the ray marcher, the compositor and the Instant-NGP grid update (docs/method.md 10).

Prints one JSON object. Marching: 4096 rays in a 9 x 8 x 2.6 m room whose 128-cell grid is ~20 %
occupied (walls, floor, ceiling, furniture blocks), numba vs torch. Compositing: 4096 x 64
samples, forward + backward. NgpGrid: one full-grid (warm-up) update and one post-warm-up update
with a cheap density_fn at max_resolution 64 and 128. Times are medians of a few repeats after a
warm-up call (numba compile excluded, reported separately). Run:
    .venv/bin/python benchmarks/bench_render.py
"""

from __future__ import annotations

import os

# Spinning OpenMP workers (the default) lose whole scheduler slices per parallel op when the CPU is
# shared (measured here: torch compositing 176 ms active vs 18 ms passive). Set before torch loads;
# export OMP_WAIT_POLICY=ACTIVE to measure the other way.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numba  # noqa: E402
import torch  # noqa: E402

from virus_nerf.grid.base import GridSpec  # noqa: E402
from virus_nerf.grid.ngp import NgpGrid, NgpGridConfig  # noqa: E402
from virus_nerf.render import PackedSamples, composite, march_rays  # noqa: E402
from virus_nerf.scene_box import SceneBox  # noqa: E402

BOX = SceneBox((-4.5, -4.0, 0.0), (4.5, 4.0, 2.6))


CPU_MS: dict[str, float] = {}  # label -> median process CPU ms (all threads), steadier when shared


def timed(fn, repeats: int = 5, label: str | None = None) -> float:
    """Median wall seconds of fn(); with a label, also records the median CPU ms in CPU_MS."""
    times, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn()
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    if label:
        CPU_MS[label] = round(statistics.median(cpu) * 1e3, 2)
    return statistics.median(times)


def room_occupancy(spec: GridSpec, seed: int = 0) -> torch.Tensor:
    """Walls/floor/ceiling 0.15 m thick and random furniture blocks up to ~20 % of the cells."""
    g = torch.Generator().manual_seed(seed)
    centres = spec.cell_centers().reshape(*spec.resolution, 3)
    x, y, z = centres.unbind(-1)
    lo, hi = BOX.lo, BOX.hi
    occ = (x < lo[0] + 0.15) | (x > hi[0] - 0.15) | (y < lo[1] + 0.15) | (y > hi[1] - 0.15)
    occ |= (z < 0.15) | (z > hi[2] - 0.15)
    while float(occ.float().mean()) < 0.2:
        sx, sy = (torch.rand(2, generator=g) * torch.tensor([1.5, 1.2]) + 0.4).tolist()
        sz = float(torch.rand(1, generator=g)) * 1.8 + 0.4  # tables to cupboards
        cx, cy = (
            torch.rand(2, generator=g) * torch.tensor([8.0, 7.0]) - torch.tensor([4.0, 3.5])
        ).tolist()
        occ |= (abs(x - cx) < sx / 2) & (abs(y - cy) < sy / 2) & (z < sz)
    return occ


def camera_rays(n: int, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    o = torch.rand(n, 3, generator=g) * torch.tensor([7.0, 6.0, 0.6]) + torch.tensor(
        [-3.5, -3.0, 0.7]
    )
    yaw = torch.rand(n, generator=g) * 2 * torch.pi
    pitch = (torch.rand(n, generator=g) - 0.5) * torch.pi / 3  # +-30 deg
    d = torch.stack(
        [torch.cos(yaw) * torch.cos(pitch), torch.sin(yaw) * torch.cos(pitch), torch.sin(pitch)],
        dim=-1,
    )
    return o, d


def bench_marching(n_rays: int = 4096) -> dict:
    spec = GridSpec.from_box(BOX, 128)
    occ = room_occupancy(spec)
    o, d = camera_rays(n_rays)
    out: dict = {
        "resolution": list(spec.resolution),
        "occupied_share": round(float(occ.float().mean()), 3),
    }
    cases = {
        "const_0.01m": dict(step_size=0.01, cone_angle=0.0),
        "cone_1/256": dict(step_size=0.01, cone_angle=1 / 256),
    }
    for name, kw in cases.items():
        res = {}
        t = time.perf_counter()
        s = march_rays(o, d, occ, spec, 0.05, 15.0, max_samples_per_ray=1024, backend="numba", **kw)
        res["numba_first_call_s"] = round(time.perf_counter() - t, 3)
        res["samples_per_ray"] = round(s.n_samples / n_rays, 1)
        variants = [
            ("numba_skip", dict(backend="numba", skip_empty=True), 9),
            ("numba_noskip", dict(backend="numba", skip_empty=False), 9),
            ("torch", dict(backend="torch"), 1),
        ]
        if kw["cone_angle"] > 0:  # empty-cell skipping applies to the constant step only
            variants = [("numba", dict(backend="numba"), 9), variants[2]]
        for label, extra, reps in variants:
            sec = timed(
                lambda extra=extra, kw=kw: march_rays(
                    o,
                    d,
                    occ,
                    spec,
                    0.05,
                    15.0,
                    max_samples_per_ray=1024,
                    jitter=torch.Generator().manual_seed(0),
                    **kw,
                    **extra,
                ),
                reps,
                label=f"{name}/{label}",
            )
            res[label] = {
                "ms": round(sec * 1e3, 2),
                "cpu_ms": CPU_MS[f"{name}/{label}"],
                "rays_per_s": round(n_rays / sec),
                "samples_per_s": round(s.n_samples / sec),
            }
        out[name] = res
    return out


def bench_compositing(n_rays: int = 4096, per_ray: int = 64) -> dict:
    g = torch.Generator().manual_seed(0)
    counts = torch.full((n_rays,), per_ray)
    ts = (torch.arange(per_ray) * 0.02).repeat(n_rays)
    samples = PackedSamples.from_counts(counts, ts, ts + 0.02)
    s = samples.n_samples
    sig = (torch.rand(s, generator=g) ** 4 * 300).requires_grad_()
    rgb = torch.rand(s, 3, generator=g).requires_grad_()
    bg = torch.ones(3)

    out: dict = {"n_samples": s}
    for backend in ("numba", "torch"):

        def step(backend=backend):
            sig.grad = rgb.grad = None
            r = composite(sig, rgb, samples, n_rays, bg, backend)
            loss = (r.rgb**2).sum() + r.depth.sum() + r.opacity.sum()
            loss.backward()

        t = time.perf_counter()
        step()
        first = time.perf_counter() - t
        fwd = timed(
            lambda backend=backend: composite(
                sig.detach(), rgb.detach(), samples, n_rays, bg, backend
            ),
            9,
            label=f"fwd/{backend}",
        )
        sec = timed(step, 9, label=f"fwd_bwd/{backend}")
        out[backend] = {
            "first_call_s": round(first, 3),
            "forward_ms": round(fwd * 1e3, 2),
            "forward_cpu_ms": CPU_MS[f"fwd/{backend}"],
            "fwd_bwd_ms": round(sec * 1e3, 2),
            "fwd_bwd_cpu_ms": CPU_MS[f"fwd_bwd/{backend}"],
            "fwd_bwd_samples_per_s": round(s / sec),
        }
    return out


def bench_ngp_grid() -> dict:
    density = lambda p: p.norm(dim=-1)  # noqa: E731 - cheap stand-in for the field
    out = {}
    for res in (64, 128):
        grid = NgpGrid(BOX, NgpGridConfig(max_resolution=res))
        g = torch.Generator().manual_seed(0)
        full = timed(lambda grid=grid, g=g: grid.update(0, density, None, g), 3, f"full{res}")
        part = timed(lambda grid=grid, g=g: grid.update(10_000, density, None, g), 3, f"half{res}")
        out[f"res{res}"] = {
            "cells": grid.spec.n_cells,
            "resolution": list(grid.spec.resolution),
            "full_update_s": round(full, 4),
            "full_update_cpu_s": round(CPU_MS[f"full{res}"] / 1e3, 4),
            "half_update_s": round(part, 4),
        }
    return out


def main() -> None:
    import argparse

    argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0]).parse_args()  # --help, and no stray flag
    t = time.perf_counter()
    result: dict = {
        "threads": {"torch": torch.get_num_threads(), "numba": numba.get_num_threads()},
        "OMP_WAIT_POLICY": os.environ["OMP_WAIT_POLICY"],
    }
    # The torch marching twin allocates ~GB of temporaries, which slows what runs after it: last.
    result["ngp_grid_update"] = bench_ngp_grid()
    result["compositing_4096x64"] = bench_compositing()
    result["marching_4096_rays"] = bench_marching()
    result["bench_seconds"] = round(time.perf_counter() - t, 1)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
