"""Hash-encoding and field throughput on CPU (docs/method.md 10): numba vs plain PyTorch backends.

Run: .venv/bin/python benchmarks/bench_field.py [--n 131072] [--reps 3]
Prints one JSON object. Points are ray-like (4096 rays x 32 samples along random directions in
the unit box), the access pattern of training. Numbers are wall-clock minima over repetitions;
on a shared machine they are noisy (see "load_avg").
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import torch

from virus_nerf.field import FieldConfig, NerfField
from virus_nerf.field.hash_encoding import HashEncoding
from virus_nerf.scene_box import SceneBox


def ray_points(n: int, samples_per_ray: int = 32, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """(n, 3) points in [0,1]^3 along n / samples_per_ray rays, and their unit directions."""
    g = torch.Generator().manual_seed(seed)
    n_rays = n // samples_per_ray
    o = torch.rand(n_rays, 1, 3, generator=g)
    d = torch.nn.functional.normalize(torch.randn(n_rays, 1, 3, generator=g), dim=-1)
    t = torch.linspace(0.0, 0.6, samples_per_ray)[None, :, None]
    x = (o + d * t).clamp(0.0, 1.0).reshape(-1, 3).contiguous()
    dirs = d.expand(n_rays, samples_per_ray, 3).reshape(-1, 3).contiguous()
    return x, dirs


def best_of(fn, reps: int) -> float:
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def bench_encoding(cfg: FieldConfig, backend: str, x: torch.Tensor, reps: int, warm_up: bool = True) -> dict:
    enc = HashEncoding(cfg.layout, backend, torch.Generator().manual_seed(0))
    g_out = torch.ones(x.shape[0], enc.out_dim)

    def fwd():
        with torch.no_grad():
            enc(x)

    def fwd_bwd():
        enc.table.grad = None
        enc(x).backward(g_out)

    if warm_up:
        fwd_bwd()  # numba cache load, allocator
    t_f, t_fb = best_of(fwd, reps), best_of(fwd_bwd, reps)
    n = x.shape[0]
    return {
        "forward_ms": round(t_f * 1e3, 1),
        "forward_backward_ms": round(t_fb * 1e3, 1),
        "forward_samples_per_s": round(n / t_f),
        "forward_backward_samples_per_s": round(n / t_fb),
    }


def bench_field(cfg: FieldConfig, x: torch.Tensor, dirs: torch.Tensor, reps: int) -> dict:
    box = SceneBox((0.0, 0.0, 0.0), (10.0, 8.0, 3.0))
    field = NerfField(box, cfg, seed=0)
    pts = x * torch.tensor([10.0, 8.0, 3.0])

    def fwd_bwd():
        field.zero_grad(set_to_none=True)
        sigma, rgb = field(pts, dirs)
        (sigma.mean() + rgb.mean()).backward()

    fwd_bwd()
    t_fb = best_of(fwd_bwd, reps)
    return {"forward_backward_ms": round(t_fb * 1e3, 1), "forward_backward_samples_per_s": round(x.shape[0] / t_fb)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=4096 * 32, help="points per call")
    ap.add_argument("--reps", type=int, default=3, help="repetitions (numba; the slow torch backend runs once)")
    args = ap.parse_args()
    t_start = time.perf_counter()
    x, dirs = ray_points(args.n)
    presets = {
        "log2_T=16 (cpu_default, N_max 512)": FieldConfig.cpu_default(),
        "log2_T=19 (paper, N_max 1024)": FieldConfig.paper(),
    }
    result: dict = {
        "n_points": args.n,
        "torch_threads": torch.get_num_threads(),
        "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "unset"),
        "cpu": platform.processor() or platform.machine(),
        "load_avg_at_start": os.getloadavg()[0],
        "note": "wall-clock minima; shared 2-core machine, expect +-30 % noise",
        "encoding": {},
        "field_numba": {},
    }
    for name, cfg in presets.items():
        result["encoding"][name] = {
            "numba": bench_encoding(cfg, "numba", x, args.reps),
            "torch": bench_encoding(cfg, "torch", x, 1, warm_up=False),
        }
        result["field_numba"][name] = bench_field(cfg, x, dirs, args.reps)
    result["load_avg_at_end"] = os.getloadavg()[0]
    result["bench_seconds"] = round(time.perf_counter() - t_start, 1)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
