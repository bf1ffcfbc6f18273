"""NerfField: presets, outputs, box masking, determinism, gradients, backend parity, trunc_exp."""

from __future__ import annotations

import math

import pytest
import torch

from virus_nerf.field import FieldConfig, NerfField, trunc_exp
from virus_nerf.scene_box import SceneBox

BOX = SceneBox((-2.0, -1.0, -0.5), (6.0, 4.0, 2.5))  # 8 x 5 x 3 m, anisotropic
SMALL = FieldConfig(n_levels=6, log2_table_size=12, base_resolution=4, max_resolution=64)


def world_points(n: int, seed: int = 0, margin: float = 0.0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    lo, size = torch.tensor(BOX.lo), torch.tensor(BOX.size, dtype=torch.float32)
    return lo - margin + torch.rand(n, 3, generator=g) * (size + 2 * margin)  # (n, 3) metres


def unit_dirs(n: int, seed: int = 1) -> torch.Tensor:
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=torch.Generator().manual_seed(seed)), dim=-1)


def test_presets():
    paper, cpu = FieldConfig.paper(), FieldConfig.cpu_default()
    assert (paper.n_levels, paper.n_features, paper.log2_table_size) == (16, 2, 19)
    assert paper.layout.resolutions[0] == 16 and paper.layout.resolutions[-1] == 1024
    assert cpu.log2_table_size == 16 and cpu.layout.resolutions[-1] == 512
    assert FieldConfig.from_dict(cpu.to_dict()) == cpu
    with pytest.raises(ValueError, match="unknown FieldConfig keys"):
        FieldConfig.from_dict({"n_level": 3})
    with pytest.raises(ValueError, match="backend"):
        FieldConfig(backend="gpu")
    f = NerfField(BOX, SMALL)
    n_mlp = 12 * 64 + 64 * 16 + 32 * 64 + 64 * 64 + 64 * 3  # 6 levels x F=2 inputs, no biases
    assert sum(p.numel() for m in (f.density_mlp, f.color_mlp) for p in m.parameters()) == n_mlp
    assert f.encoding.table.shape == (SMALL.layout.n_entries, 2)


def test_outputs_ranges_and_outside_box():
    f = NerfField(BOX, SMALL, seed=3)
    pts = world_points(500, margin=1.0)  # some outside
    pts[0] = torch.tensor([float("nan"), 0.0, 0.0])
    pts[1] = torch.tensor(BOX.hi)  # on the box corner: inside
    inside = torch.from_numpy(BOX.contains(pts.numpy()))
    assert 50 < int((~inside).sum()) < 450
    sigma, rgb = f(pts, unit_dirs(500))
    assert sigma.shape == (500,) and rgb.shape == (500, 3)
    assert torch.all(sigma[~inside] == 0) and torch.all(rgb[~inside] == 0)
    assert torch.all(sigma[inside] > 0)
    assert torch.all((rgb[inside] > 0) & (rgb[inside] < 1))
    torch.testing.assert_close(f.density(pts), sigma, rtol=0, atol=0)
    # all outside
    far = torch.full((4, 3), 100.0)
    assert torch.equal(f.density(far), torch.zeros(4))


def test_determinism_and_seed():
    a, b, c = NerfField(BOX, SMALL, seed=5), NerfField(BOX, SMALL, seed=5), NerfField(BOX, SMALL, seed=6)
    for (ka, pa), (_, pb) in zip(a.state_dict().items(), b.state_dict().items(), strict=True):
        assert torch.equal(pa, pb), ka
    assert not torch.equal(a.encoding.table, c.encoding.table)
    assert not torch.equal(a.density_mlp[0].weight, c.density_mlp[0].weight)
    d = NerfField(BOX, SMALL, generator=torch.Generator().manual_seed(5))  # generator == seed
    assert all(torch.equal(p, q) for p, q in zip(a.parameters(), d.parameters(), strict=True))
    pts, dirs = world_points(3000), unit_dirs(3000)
    grads = []
    for _ in range(2):
        a.zero_grad(set_to_none=True)
        sigma, rgb = a(pts, dirs)
        (sigma.mean() + (rgb * torch.linspace(0, 1, 3)).sum()).backward()
        grads.append([p.grad.clone() for p in a.parameters()])
    for g0, g1 in zip(*grads, strict=True):
        assert torch.equal(g0, g1)
    s2, r2 = b(pts, dirs)
    assert torch.equal(s2, sigma) and torch.equal(r2, rgb)


def test_gradients_reach_table_and_every_mlp_layer():
    f = NerfField(BOX, SMALL, seed=0)
    pts = world_points(2000, margin=0.5)
    sigma, rgb = f(pts, unit_dirs(2000))
    (sigma.sum() + rgb.sum()).backward()
    for name, p in f.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name
    # density() alone reaches the table and the density MLP, not the colour MLP
    f.zero_grad(set_to_none=True)
    f.density(pts).sum().backward()
    assert f.encoding.table.grad.abs().sum() > 0
    assert all(p.grad is None for p in f.color_mlp.parameters())


def test_numba_and_torch_fields_agree():
    pts, dirs = world_points(1500), unit_dirs(1500)
    outs = {}
    for backend in ("numba", "torch"):
        cfg = FieldConfig(**{**SMALL.to_dict(), "backend": backend})
        f = NerfField(BOX, cfg, seed=11)
        with torch.no_grad():
            f.encoding.table.normal_(0, 1, generator=torch.Generator().manual_seed(1))  # non-trivial features
        sigma, rgb = f(pts, dirs)
        (sigma.log().sum() + rgb.sum()).backward()
        outs[backend] = (sigma, rgb, f.encoding.table.grad, f.density_mlp[0].weight.grad)
    for a, b in zip(outs["numba"], outs["torch"], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


def test_trunc_exp():
    x = torch.tensor([-20.0, 0.0, 2.0, 20.0], requires_grad=True)
    y = trunc_exp(x, 15.0)
    torch.testing.assert_close(y.detach(), torch.tensor([math.exp(-20), 1.0, math.exp(2), math.exp(15)]))
    y.sum().backward()
    torch.testing.assert_close(x.grad, torch.tensor([math.exp(-15), 1.0, math.exp(2), math.exp(15)]))
