"""Instant-NGP occupancy grid (docs/method.md 3.3): warm-up, n/4 + n/4 draws, decay, threshold, resume."""

from __future__ import annotations

import math

import pytest
import torch

from virus_nerf.grid.base import cell_index
from virus_nerf.grid.ngp import NgpGrid, NgpGridConfig
from virus_nerf.scene_box import SceneBox

BOX = SceneBox((0.0, 0.0, 0.0), (4.0, 4.0, 1.0))  # 16 x 16 x 4 cells of 0.25 m at max_res 16
CFG = NgpGridConfig(max_resolution=16, warmup_steps=32, update_interval=16)  # marched at 0.01 m (NgpGrid's default)


class Recorder:
    """density_fn that remembers what it was asked and returns f(points)."""

    def __init__(self, f):
        self.f = f
        self.points: list[torch.Tensor] = []

    def __call__(self, p: torch.Tensor) -> torch.Tensor:
        self.points.append(p.clone())
        return self.f(p)

    @property
    def n(self) -> int:
        return sum(p.shape[0] for p in self.points)


def const(v: float):
    return lambda p: torch.full((p.shape[0],), v)


def test_config_resolution_and_sigma_max():
    assert NgpGrid(BOX).sigma_max == pytest.approx(-math.log(0.99) / 0.01)
    assert NgpGrid(BOX, step_size=0.02).sigma_max == pytest.approx(0.50252, rel=1e-4)
    room = NgpGrid(SceneBox((-4.5, -4.0, 0.0), (4.5, 4.0, 2.6)))
    assert room.spec.resolution == (128, 114, 37)
    grid = NgpGrid(BOX, CFG)
    assert grid.spec.resolution == (16, 16, 4)
    assert grid.occupied.dtype == torch.bool and bool(grid.occupied.all())  # all marched at first


def test_warmup_evaluates_every_cell_at_a_point_inside_it():
    grid = NgpGrid(BOX, CFG)
    rec = Recorder(const(0.0))
    grid.update(0, rec, None, torch.Generator().manual_seed(0))
    pts = torch.cat(rec.points)
    assert rec.n == grid.spec.n_cells
    cells = cell_index(pts.double(), grid.spec)
    assert torch.equal(cells, torch.arange(grid.spec.n_cells))
    centres = grid.spec.cell_centers()
    assert float((pts - centres).abs().max()) < 0.125 and float((pts - centres).std()) > 0.05


def test_after_warmup_a_quarter_uniform_plus_a_quarter_among_occupied():
    grid = NgpGrid(BOX, NgpGridConfig(max_resolution=16, warmup_steps=1, chunk_size=100))
    region = lambda p: ((p[:, 0] < 1.0) * 5.0).float()  # noqa: E731 - x < 1 m: 1/4 of the cells
    grid.update(0, region, None, torch.Generator().manual_seed(0))
    occ_before = grid.occupied.clone()
    assert int(occ_before.sum()) == grid.spec.n_cells // 4
    rec = Recorder(region)
    grid.update(16, rec, None, torch.Generator().manual_seed(1))
    q = grid.spec.n_cells // 4
    assert (
        rec.n == 2 * q and grid.last_n_evaluated == 2 * q and len(rec.points) == 6
    )  # chunks of 100
    pts = torch.cat(rec.points)
    second = cell_index(pts[q:].double(), grid.spec)
    assert bool(occ_before.reshape(-1)[second].all())  # the second quarter only in occupied cells
    first = cell_index(pts[:q].double(), grid.spec)
    share = float(occ_before.reshape(-1)[first].float().mean())
    assert 0.15 < share < 0.35  # the first quarter uniform (a quarter of the cells is occupied)


def test_decay_of_all_cells():
    grid = NgpGrid(BOX, CFG)
    g = torch.Generator().manual_seed(0)
    grid.update(0, const(2.0), None, g)
    assert torch.equal(grid.values, torch.full(grid.spec.resolution, 2.0))
    grid.update(CFG.warmup_steps, const(0.0), None, g)  # post warm-up: some cells evaluated at 0
    torch.testing.assert_close(grid.values, torch.full(grid.spec.resolution, 2.0 * 0.95))
    rec = Recorder(const(1.85))
    grid.update(CFG.warmup_steps + 16, rec, None, g)  # evaluated: max(0.95 * 1.9, 1.85) = 1.85
    v = grid.values.reshape(-1)
    hit = cell_index(torch.cat(rec.points).double(), grid.spec).unique()
    torch.testing.assert_close(v[hit], torch.full((hit.shape[0],), 1.85))
    rest = torch.ones_like(v, dtype=torch.bool)
    rest[hit] = False
    torch.testing.assert_close(v[rest], torch.full((int(rest.sum()),), 1.805))
    assert 0.2 * v.numel() < hit.shape[0] < 0.6 * v.numel()


def test_threshold_is_min_of_mean_and_sigma_max():
    g = torch.Generator().manual_seed(0)
    quarter = lambda lo_v, hi_v: lambda p: torch.where(p[:, 0] < 1.0, hi_v, lo_v)  # noqa: E731
    grid = NgpGrid(BOX, CFG)  # sigma_max = 1.005
    grid.update(0, quarter(0.6, 0.8), None, g)  # mean 0.65 < sigma_max: threshold is the mean
    assert grid.threshold == pytest.approx(0.65, rel=1e-6)
    assert int(grid.occupied.sum()) == grid.spec.n_cells // 4 and bool(grid.occupied[:4].all())
    grid = NgpGrid(BOX, CFG)
    grid.update(0, quarter(2.0, 3.0), None, g)  # mean 2.25 > sigma_max: everything above 1.005
    assert grid.threshold == pytest.approx(grid.sigma_max)
    assert bool(grid.occupied.all())
    grid = NgpGrid(BOX, CFG)
    grid.update(0, quarter(0.0, 0.0), None, g)  # zero everywhere: nothing exceeds 0
    assert not bool(grid.occupied.any())


def test_density_in_one_region_leaves_exactly_that_region_occupied():
    grid = NgpGrid(BOX, CFG)
    g = torch.Generator().manual_seed(5)
    grid.update(0, const(10.0), None, g)  # the untrained field: dense everywhere
    assert bool(grid.occupied.all())

    def block(p):  # a cell-aligned block: x, y in [1, 2) m, all z
        inside = (p[:, 0] >= 1) & (p[:, 0] < 2) & (p[:, 1] >= 1) & (p[:, 1] < 2)
        return inside.float() * 100.0

    expect = torch.zeros(grid.spec.resolution, dtype=torch.bool)
    expect[4:8, 4:8, :] = True
    step = CFG.warmup_steps
    for _ in range(70):  # 10 * 0.95^n falls below sigma_max after ~45 updates
        grid.update(step, block, None, g)
        step += CFG.update_interval
    assert torch.equal(grid.occupied, expect)


def test_state_round_trip_resumes_exactly():
    a = NgpGrid(BOX, CFG)
    fn = lambda p: torch.sin(3 * p[:, 0]).abs() * 3 * p[:, 1]  # noqa: E731
    ga = torch.Generator().manual_seed(0)
    for step in (0, 32, 48):
        a.update(step, fn, None, ga)
    b = NgpGrid(BOX, CFG)
    b.load_state_dict(a.state_dict())
    assert torch.equal(a.values, b.values) and torch.equal(a.occupied, b.occupied)
    rng_state = ga.get_state()
    gb = torch.Generator()
    gb.set_state(rng_state)
    for step in (64, 80):
        a.update(step, fn, None, ga)
        b.update(step, fn, None, gb)
    assert torch.equal(a.values, b.values) and torch.equal(a.occupied, b.occupied)
    assert b.n_updates == 5
    other = NgpGrid(BOX, NgpGridConfig(max_resolution=8))
    with pytest.raises(ValueError, match="resolution"):
        other.load_state_dict(a.state_dict())


def test_constructor_takes_a_spec_and_the_marchers_step():
    from virus_nerf.grid.base import GridSpec

    spec = GridSpec.from_box(BOX, 8)
    grid = NgpGrid(spec, CFG, step_size=0.03)
    assert grid.spec is spec and grid.spec.resolution == (8, 8, 2)
    assert grid.sigma_max == pytest.approx(-math.log(0.99) / 0.03)
    with pytest.raises(ValueError, match="step_size"):
        NgpGrid(BOX, CFG, step_size=0.0)
