"""Ray marching: packed bookkeeping, occupancy-only samples, numba == torch bit for bit."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from virus_nerf.grid.base import GridSpec, cell_index
from virus_nerf.render import PackedSamples, march_rays, ray_box_interval
from virus_nerf.scene_box import SceneBox

BOX = SceneBox((-4.5, -4.0, 0.0), (4.5, 4.0, 2.6))
SPEC = GridSpec.from_box(BOX, 32)  # (32, 29, 10)


def _rays(n: int, seed: int, spread: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    lo = torch.tensor(BOX.lo)
    size = torch.tensor(BOX.size.tolist(), dtype=torch.float32)
    centre = lo + size / 2
    o = centre + (torch.rand(n, 3, generator=g) - 0.5) * size * spread  # spread > 1: some outside
    d = torch.randn(n, 3, generator=g)
    return o, d / d.norm(dim=1, keepdim=True)


def _room_occupancy(spec: GridSpec, seed: int = 0) -> torch.Tensor:
    """Walls, floor and a few furniture blocks plus sparse noise (~20-30 % occupied)."""
    rx, ry, rz = spec.resolution
    occ = torch.zeros(rx, ry, rz, dtype=torch.bool)
    occ[:2], occ[-2:], occ[:, :2], occ[:, -2:], occ[:, :, :1] = True, True, True, True, True
    g = torch.Generator().manual_seed(seed)
    for _ in range(6):
        x, y = (
            int(torch.randint(2, rx - 6, (1,), generator=g)),
            int(torch.randint(2, ry - 6, (1,), generator=g)),
        )
        occ[x : x + 4, y : y + 3, : rz // 2] = True
    occ |= torch.rand(rx, ry, rz, generator=g) < 0.03
    return occ


def _same(a: PackedSamples, b: PackedSamples) -> None:
    assert torch.equal(a.ray_offsets, b.ray_offsets)
    assert torch.equal(a.ray_indices, b.ray_indices)
    assert torch.equal(a.t_starts, b.t_starts)
    assert torch.equal(a.t_ends, b.t_ends)


def test_bookkeeping_bounds_occupancy_and_max_samples():
    o, d = _rays(400, seed=1, spread=1.6)  # some origins outside the box, some rays miss
    occ = _room_occupancy(SPEC)
    g = torch.Generator().manual_seed(0)
    near = torch.rand(400, generator=g) * 0.5
    far = 2.0 + torch.rand(400, generator=g) * 6.0
    s = march_rays(
        o,
        d,
        occ,
        SPEC,
        near,
        far,
        step_size=0.02,
        max_samples_per_ray=40,
        jitter=torch.Generator().manual_seed(3),
        backend="numba",
    )
    s.check()  # offsets consistent, ray_indices sorted, t_start < t_end
    assert s.n_rays == 400 and s.n_samples > 1000
    assert s.ray_indices.dtype == torch.int64 and s.t_starts.dtype == torch.float32
    assert bool((s.ray_indices[1:] >= s.ray_indices[:-1]).all())
    per_ray_sorted = (s.t_starts[1:] > s.t_starts[:-1]) | (s.ray_indices[1:] != s.ray_indices[:-1])
    assert bool(per_ray_sorted.all())
    t_min, t_max = ray_box_interval(o, d, SPEC, near, far)
    ri = s.ray_indices
    assert bool((s.t_starts >= t_min[ri].float() - 1e-6).all())
    assert bool((s.t_ends <= t_max[ri].float() + 1e-6).all())
    assert bool((s.t_starts >= near[ri] - 1e-6).all()) and bool((s.t_ends <= far[ri] + 1e-6).all())
    for t in (s.t_starts, s.t_ends):
        p = o[ri] + t[:, None] * d[ri]
        assert BOX.padded(1e-4).contains(p.numpy()).all()
    mid = s.positions(o, d)
    np.testing.assert_allclose(mid, o[ri] + s.midpoints[:, None] * d[ri], atol=1e-6)
    cells = cell_index(mid.double(), SPEC)
    assert bool((cells >= 0).all()) and bool(occ.reshape(-1)[cells].all())
    counts = s.counts
    assert int(counts.max()) == 40 and int((counts == 40).sum()) > 10  # the cap binds
    missed = t_max <= t_min
    assert int(missed.sum()) > 5 and int(counts[missed].sum()) == 0


def test_single_occupied_cell_gets_all_samples_and_a_missing_ray_none():
    occ = torch.zeros(SPEC.resolution, dtype=torch.bool)
    ijk = (10, 12, 4)
    occ[ijk] = True
    centre = SPEC.cell_centers()[
        (ijk[0] * SPEC.resolution[1] + ijk[1]) * SPEC.resolution[2] + ijk[2]
    ]
    o, _ = _rays(64, seed=2, spread=0.9)
    d = centre - o
    d = d / d.norm(dim=1, keepdim=True)
    miss_o = centre + torch.tensor([0.0, 0.0, 1.0])  # a ray parallel to x one metre above it
    o = torch.cat([o, miss_o[None]])
    d = torch.cat([d, torch.tensor([[1.0, 0.0, 0.0]])])
    for backend in ("numba", "torch"):
        s = march_rays(
            o,
            d,
            occ,
            SPEC,
            0.0,
            100.0,
            step_size=0.005,
            max_samples_per_ray=1000,
            jitter=torch.Generator().manual_seed(0),
            backend=backend,
        )
        s.check()
        cells = cell_index(s.positions(o, d).double(), SPEC)
        flat = (ijk[0] * SPEC.resolution[1] + ijk[1]) * SPEC.resolution[2] + ijk[2]
        assert bool((cells == flat).all())
        counts = s.counts
        assert bool((counts[:64] >= 1).all()) and int(counts[64]) == 0
        # a ray through the centre crosses >= min(cell edge) of the cell: at least ~edge/step samples
        assert int(counts[:64].min()) >= math.floor(float(SPEC.cell_size.min()) / 0.005) - 1


def test_all_occupied_constant_step_without_jitter_is_a_regular_grid_from_the_entry():
    occ = torch.ones(SPEC.resolution, dtype=torch.bool)
    o = torch.tensor([[-6.0, 0.1, 1.3], [0.0, 0.0, 1.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8]])
    s = march_rays(
        o,
        d,
        occ,
        SPEC,
        0.0,
        100.0,
        step_size=0.1,
        max_samples_per_ray=10_000,
        jitter=None,
        backend="numba",
    )
    first = s.t_starts[s.ray_offsets[:-1]]
    np.testing.assert_allclose(
        first.numpy(), [1.5, 0.0], atol=1e-6
    )  # enters at x=-4.5 / starts in box
    ray0 = s.t_starts[s.ray_indices == 0]
    np.testing.assert_allclose(np.diff(ray0.numpy()), 0.1, atol=1e-5)
    assert int(s.counts[0]) == 90  # 9 m of box in 0.1 m steps
    assert abs(float(s.t_ends[s.ray_offsets[1] - 1]) - 10.5) < 1e-5  # last interval ends at exit
    # ray 1 leaves through the top face z=2.6 at t=2.0: 20 samples of 0.1 m
    assert int(s.counts[1]) == 20


def test_jitter_is_one_fraction_of_the_first_step_and_reproducible():
    occ = torch.ones(SPEC.resolution, dtype=torch.bool)
    o, d = _rays(200, seed=4)
    kw = dict(near=0.0, far=100.0, step_size=0.05, max_samples_per_ray=5, backend="numba")
    a = march_rays(o, d, occ, SPEC, jitter=torch.Generator().manual_seed(7), **kw)
    b = march_rays(o, d, occ, SPEC, jitter=torch.Generator().manual_seed(7), **kw)
    c = march_rays(o, d, occ, SPEC, jitter=torch.Generator().manual_seed(8), **kw)
    _same(a, b)
    assert not torch.equal(a.t_starts, c.t_starts)
    t_min, _ = ray_box_interval(o, d, SPEC, 0.0, 100.0)
    offset = a.t_starts[a.ray_offsets[:-1]] - t_min.float()
    assert bool((offset >= -1e-6).all()) and bool((offset < 0.05 + 1e-6).all())
    assert float(offset.std()) > 0.01  # spread over the step, not constant


def test_cone_steps_grow_with_distance_and_are_clamped():
    occ = torch.ones(SPEC.resolution, dtype=torch.bool)
    o = torch.tensor([[-4.4, 0.0, 1.0]])
    d = torch.tensor([[1.0, 0.0, 0.0]])
    s = march_rays(
        o,
        d,
        occ,
        SPEC,
        0.0,
        100.0,
        step_size=0.01,
        max_samples_per_ray=10_000,
        cone_angle=0.01,
        max_step=0.05,
        backend="numba",
    )
    ts = s.t_starts.double().numpy()
    dt = np.diff(ts)
    expect = np.clip(ts[:-1] * 0.01, 0.01, 0.05)
    np.testing.assert_allclose(dt, expect, rtol=1e-5, atol=1e-6)
    assert dt.min() == pytest.approx(0.01, abs=1e-6) and dt.max() == pytest.approx(0.05, abs=1e-6)


@pytest.mark.parametrize("cone", [0.0, 0.004])
@pytest.mark.parametrize("skip", [True, False])
def test_numba_equals_torch_exactly(cone, skip):
    occ = _room_occupancy(SPEC, seed=5)
    o, d = _rays(300, seed=6, spread=1.3)
    # add axis-parallel rays lying exactly on cell borders (the hardest case for skipping)
    cs = torch.from_numpy(SPEC.cell_size).float()
    lo = torch.tensor(BOX.lo)
    border = lo + torch.tensor([0.0, 7.0, 3.0]) * cs
    o = torch.cat([o, border[None], (lo + torch.tensor([5.0, 0.0, 2.0]) * cs)[None]])
    d = torch.cat([d, torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])])
    g = torch.Generator().manual_seed(11)
    near = torch.rand(o.shape[0], generator=g) * 0.3
    kw = dict(step_size=0.013, max_samples_per_ray=150, cone_angle=cone)
    a = march_rays(
        o,
        d,
        occ,
        SPEC,
        near,
        9.0,
        jitter=torch.Generator().manual_seed(1),
        backend="numba",
        skip_empty=skip,
        **kw,
    )
    b = march_rays(
        o, d, occ, SPEC, near, 9.0, jitter=torch.Generator().manual_seed(1), backend="torch", **kw
    )
    assert a.n_samples > 5000
    _same(a, b)


def test_nothing_occupied_gives_no_samples_and_bad_input_raises():
    o, d = _rays(50, seed=9)
    empty = torch.zeros(SPEC.resolution, dtype=torch.bool)
    for backend in ("numba", "torch"):
        s = march_rays(o, d, empty, SPEC, 0.0, 50.0, 0.02, 100, None, backend)
        assert s.n_samples == 0 and torch.equal(s.ray_offsets, torch.zeros(51, dtype=torch.int64))
    with pytest.raises(ValueError, match="resolution"):
        march_rays(o, d, torch.ones(3, 3, 3, dtype=torch.bool), SPEC)
    with pytest.raises(ValueError, match="step_size"):
        march_rays(o, d, empty, SPEC, step_size=0.0)
