"""Volume rendering (docs/method.md 3.1): analytic answers, numba == torch values and gradients, gradcheck."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from virus_nerf.grid.base import GridSpec
from virus_nerf.render import PackedSamples, composite, march_rays, opacity_front, scan_depth
from virus_nerf.scene_box import SceneBox

BACKENDS = ["numba", "torch"]


@pytest.mark.parametrize("backend", BACKENDS)
def test_two_samples_by_hand(backend):
    s = PackedSamples.from_counts(
        torch.tensor([2, 0]), torch.tensor([0.0, 0.5]), torch.tensor([0.5, 0.75])
    )
    out = composite(
        torch.tensor([1.0, 2.0]),
        torch.tensor([[1.0, 0, 0], [0, 1.0, 0]]),
        s,
        2,
        background=torch.tensor([0.0, 0.0, 1.0]),
        backend=backend,
    )
    a1 = 1 - math.exp(-0.5)  # tau1 = 1 * 0.5
    w2 = math.exp(-0.5) * (1 - math.exp(-0.5))  # tau2 = 2 * 0.25
    np.testing.assert_allclose(out.weights, [a1, w2], rtol=1e-6)
    np.testing.assert_allclose(out.opacity, [1 - math.exp(-1.0), 0.0], rtol=1e-6)
    np.testing.assert_allclose(out.depth, [a1 * 0.25 + w2 * 0.625, 0.0], rtol=1e-6)
    np.testing.assert_allclose(out.rgb[0], [a1, w2, math.exp(-1.0)], rtol=1e-6)
    np.testing.assert_allclose(out.rgb[1], [0, 0, 1], rtol=1e-6)  # no samples: background


@pytest.mark.parametrize("backend", BACKENDS)
def test_opacity_front_is_where_the_accumulated_weight_first_reaches_the_level(backend):
    # ray 0: alphas 0.04, 0.5, 0.5 over [1.0, 1.1), [1.1, 1.2), [1.2, 1.3): weights 0.04, 0.48, 0.24,
    # running sums 0.04, 0.52, 0.76: the level 0.1 is reached in the second interval, which starts at
    # 1.1 m (D / A = (0.04 * 1.05 + 0.48 * 1.15 + 0.24 * 1.25) / 0.76 = 1.1763 m lies behind it);
    # ray 1: alphas 0.05, 0.05: opacity 0.0975; ray 2: no samples
    alphas = torch.tensor([0.04, 0.5, 0.5, 0.05, 0.05], dtype=torch.float64)
    starts = torch.tensor([1.0, 1.1, 1.2, 2.0, 2.1], dtype=torch.float64)
    s = PackedSamples.from_counts(torch.tensor([3, 2, 0]), starts, starts + 0.1)
    sigmas = -torch.log1p(-alphas) / 0.1  # tau = sigma * 0.1 gives these alphas
    out = composite(sigmas, torch.zeros(5, 3, dtype=torch.float64), s, 3, backend=backend)
    np.testing.assert_allclose(scan_depth(out)[0], 0.894 / 0.76, rtol=1e-9)
    front = opacity_front(out, s, level=0.1, min_opacity=0.5)
    np.testing.assert_allclose(front[0], 1.1, rtol=1e-12)
    assert torch.isnan(front[1:]).all()  # ray 1's opacity is under 0.5, ray 2 met nothing
    front = opacity_front(out, s, level=0.5, min_opacity=0.05)
    np.testing.assert_allclose(front[0], 1.1, rtol=1e-12)  # 0.52 >= 0.5 in the second interval too
    assert torch.isnan(front[1])  # opacity 0.0975 >= 0.05 but it never reaches the level 0.5
    np.testing.assert_allclose(opacity_front(out, s, level=0.6, min_opacity=0.5)[0], 1.2, rtol=1e-12)
    with pytest.raises(ValueError, match="level"):
        opacity_front(out, s, level=0.0)


def _slab_render(backend: str, sigma: float, a: float, thick: float, background=None):
    """Rays along +x through an all-occupied box; density sigma for x in [a, a + thick]."""
    box = SceneBox((0.0, 0.0, 0.0), (4.0, 1.0, 1.0))
    spec = GridSpec.from_box(box, 64)
    o = torch.tensor([[0.0, 0.5, 0.5], [0.0, 0.2, 0.7], [0.0, 0.9, 0.1]])
    d = torch.tensor([[1.0, 0.0, 0.0]]).expand(3, 3)
    s = march_rays(
        o,
        d,
        torch.ones(spec.resolution, dtype=torch.bool),
        spec,
        0.0,
        10.0,
        step_size=0.001,
        max_samples_per_ray=10_000,
        backend=backend,
    )
    x = s.positions(o, d)[:, 0]
    sig = torch.where((x > a) & (x < a + thick), sigma, 0.0)
    rgb = torch.tensor([0.2, 0.5, 0.9]).expand(s.n_samples, 3)
    return composite(sig, rgb, s, 3, background=background, backend=backend)


@pytest.mark.parametrize("backend", BACKENDS)
def test_slab_opacity_depth_colour_and_background(backend):
    sigma, a, thick = 4.0, 1.0, 0.5
    bg = torch.tensor([1.0, 0.0, 0.5])
    out = _slab_render(backend, sigma, a, thick, background=bg)
    opa = 1 - math.exp(-sigma * thick)
    np.testing.assert_allclose(out.opacity, opa, rtol=1e-5)
    # D = int_a^{a+L} t sigma exp(-sigma (t - a)) dt
    depth = a * opa + 1 / sigma - math.exp(-sigma * thick) * (thick + 1 / sigma)
    np.testing.assert_allclose(out.depth, depth, atol=1e-3)  # midpoint rule, 1 mm steps
    np.testing.assert_allclose(
        out.rgb, (opa * torch.tensor([0.2, 0.5, 0.9]) + (1 - opa) * bg).expand(3, 3), rtol=1e-5
    )
    np.testing.assert_allclose(scan_depth(out), depth / opa, atol=1e-3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_opaque_wall_depth_and_thin_slab_scan_is_nan(backend):
    out = _slab_render(backend, 200.0, 2.0, 1.0)  # opaque: A = 1, D = a + 1/sigma
    np.testing.assert_allclose(out.opacity, 1.0, atol=1e-6)
    np.testing.assert_allclose(out.depth, 2.0 + 1 / 200.0, atol=1e-3)
    np.testing.assert_allclose(out.rgb, torch.tensor([0.2, 0.5, 0.9]).expand(3, 3), rtol=1e-5)
    thin = _slab_render(backend, 1.0, 2.0, 0.3)  # A = 0.26 < 0.5
    assert torch.isnan(scan_depth(thin)).all()
    assert not torch.isnan(scan_depth(thin, min_opacity=0.2)).any()


def _random_batch(seed: int, dtype=torch.float32, n_rays: int = 40):
    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, 30, (n_rays,), generator=g)
    counts[3] = 0
    s_tot = int(counts.sum())
    dt = torch.rand(s_tot, generator=g) * 0.05 + 0.001  # (S,) interval lengths
    starts = []  # increasing starts within each ray, gaps where cells were empty
    for c in counts.tolist():
        steps = torch.rand(c, generator=g) * 0.1 + 0.01
        starts.append(0.2 + torch.cumsum(steps, 0) - steps)
    ts = torch.cat(starts)
    samples = PackedSamples.from_counts(counts, ts, ts + dt)
    sig = (torch.rand(s_tot, generator=g) ** 3 * 200).to(dtype).requires_grad_()
    rgb = torch.rand(s_tot, 3, generator=g).to(dtype).requires_grad_()
    bg = torch.rand(3, generator=g).to(dtype).requires_grad_()
    return samples, sig, rgb, bg, g


def _loss_grads(out, sig, rgb, bg, g):
    """A loss touching every output with random upstream weights."""
    wr = torch.rand(out.rgb.shape, generator=g, dtype=out.rgb.dtype)
    wd = torch.rand(out.depth.shape, generator=g, dtype=out.rgb.dtype)
    wa = torch.rand(out.opacity.shape, generator=g, dtype=out.rgb.dtype)
    ww = torch.rand(out.weights.shape, generator=g, dtype=out.rgb.dtype)
    loss = (
        ((out.rgb - wr) ** 2).sum()
        + (wd * out.depth).sum()
        + (wa * out.opacity**2).sum()
        + (ww * out.weights).sum()
    )
    return torch.autograd.grad(loss, [sig, rgb, bg])


@pytest.mark.parametrize("eps", [0.0, 1e-4, 0.05])
def test_numba_and_torch_agree_on_values_and_gradients(eps):
    res = {}
    for backend in BACKENDS:
        samples, sig, rgb, bg, g = _random_batch(seed=0)
        out = composite(sig, rgb, samples, samples.n_rays, bg, backend, early_stop_eps=eps)
        res[backend] = (out, _loss_grads(out, sig, rgb, bg, g))
    (a, ga), (b, gb) = res["numba"], res["torch"]
    for name in ("rgb", "depth", "opacity", "weights"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=1e-5, atol=1e-7)
    for x, y in zip(ga, gb, strict=True):
        torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6)
    if eps > 0:  # terminated samples carry no weight and no gradient, and some rays terminate
        samples = _random_batch(seed=0)[0]
        w = a.weights.detach()
        ri = samples.ray_indices
        cum = torch.zeros(samples.n_rays).index_add(0, ri, w)
        assert float((1 - cum).min()) < 2 * eps
        assert int((w == 0).sum()) > 10 and bool((ga[0][w == 0] == 0).all())


def test_early_termination_changes_little():
    samples, sig, rgb, bg, _ = _random_batch(seed=1)
    full = composite(sig, rgb, samples, samples.n_rays, bg, "numba")
    cut = composite(sig, rgb, samples, samples.n_rays, bg, "numba", early_stop_eps=1e-4)
    torch.testing.assert_close(full.opacity, cut.opacity, atol=1e-4, rtol=0)
    assert int((cut.weights == 0).sum()) > int((full.weights == 0).sum())


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("eps", [0.0, 0.1])
def test_gradcheck_float64(backend, eps):
    g = torch.Generator().manual_seed(3)
    counts = torch.tensor([3, 0, 5, 1])
    ts = torch.cat(
        [
            torch.tensor([0.1, 0.3, 0.35]),
            torch.tensor([0.0, 0.2, 0.4, 0.6, 0.8]),
            torch.tensor([1.0]),
        ]
    )
    samples = PackedSamples.from_counts(
        counts, ts, ts + torch.tensor([0.2, 0.05, 0.3, 0.2, 0.2, 0.2, 0.2, 0.1, 0.4])
    )
    sig = (torch.rand(9, generator=g, dtype=torch.float64) * 6).requires_grad_()
    rgb = torch.rand(9, 3, generator=g, dtype=torch.float64).requires_grad_()
    bg = torch.rand(3, generator=g, dtype=torch.float64).requires_grad_()

    def fn(s, c, b):
        out = composite(s, c, samples, 4, b, backend, early_stop_eps=eps)
        return out.rgb, out.depth, out.opacity, out.weights

    assert torch.autograd.gradcheck(fn, (sig, rgb, bg), eps=1e-6, atol=1e-7)


def test_bad_shapes_raise():
    samples, sig, rgb, bg, _ = _random_batch(seed=2)
    with pytest.raises(ValueError, match="n_rays"):
        composite(sig, rgb, samples, samples.n_rays + 1)
    with pytest.raises(ValueError, match="rgbs"):
        composite(sig, rgb[:-1], samples, samples.n_rays)


class _SoftColumn(torch.nn.Module):
    """A field of density 1 /m for x in [1, 3] m and 0 elsewhere (a soft object 2 m deep), grey."""

    def __init__(self):
        super().__init__()
        self.unused = torch.nn.Parameter(torch.zeros(1))  # SceneModel reads its device from here

    def forward(self, positions, dirs, rgb_mask=None):
        x = positions[:, 0]
        sigma = ((x >= 1.0) & (x <= 3.0)).to(positions.dtype)  # (S,) 1 /m inside, 0 outside
        return sigma, torch.full((len(positions), 3), 0.5, dtype=positions.dtype)


def test_the_scan_ranges_of_a_soft_object_at_d_over_a_and_at_its_opacity_front():
    from virus_nerf.engine.model import SceneModel
    from virus_nerf.grid.ngp import NgpGrid, NgpGridConfig
    from virus_nerf.scene_box import SceneBox

    box = SceneBox((-4.0, -1.0, -1.0), (4.0, 1.0, 1.0))
    grid = NgpGrid(GridSpec.from_box(box, 32), NgpGridConfig(), step_size=0.01)  # every cell occupied
    model = SceneModel(_SoftColumn(), grid, step_size=0.01, near=0.01, max_samples=1024)
    origins, dirs = np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0]])
    # opacity over the 2 m: 1 - e^-2 = 0.865 >= 0.5; D / A = 1 + 1 - 2 e^-2 / (1 - e^-2) = 1.687 m,
    # the mean depth of the light the column stops, 0.69 m inside it; the opacity reaches 0.1 at
    # 1 + ln(1 / 0.9) = 1.105 m and 0.5 at 1 + ln 2 = 1.693 m (within a step of 0.01 m)
    assert model.ranges(origins, dirs)[0] == pytest.approx(1.687, abs=0.01)
    assert model.ranges(origins, dirs, front=0.1)[0] == pytest.approx(1.105, abs=0.01)
    assert model.ranges(origins, dirs, front=0.5)[0] == pytest.approx(1.693, abs=0.01)
    assert np.isnan(model.ranges(np.array([[0.0, 0.0, 0.0]]), np.array([[-1.0, 0.0, 0.0]]), front=0.1)[0])
