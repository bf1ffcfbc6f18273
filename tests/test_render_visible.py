"""Skipping hidden samples in training (MarchConfig.min_transmittance, docs/method.md 10).

The two-pass render (densities of every sample without gradients, then the full field only where
the transmittance is still >= eps) must give the same renders and the same gradients as rendering
every sample, up to terms of order eps.
"""

from __future__ import annotations

import math

import torch

from virus_nerf.engine.model import SceneModel
from virus_nerf.field.field import FieldConfig, NerfField
from virus_nerf.grid.base import GridSpec
from virus_nerf.grid.ngp import NgpGrid, NgpGridConfig
from virus_nerf.render import PackedSamples
from virus_nerf.render.compositing import transmittance
from virus_nerf.scene_box import SceneBox


def test_transmittance_by_hand():
    """Ray 0: sigma 1, 2, 3 /m over 0.5 m steps -> T = 1, e^-0.5, e^-1.5; ray 1: one sample, T = 1;
    ray 2: no samples."""
    samples = PackedSamples.from_counts(
        torch.tensor([3, 1, 0]),
        torch.tensor([0.0, 0.5, 1.0, 2.0]),
        torch.tensor([0.5, 1.0, 1.5, 2.25]),
    )
    t = transmittance(torch.tensor([1.0, 2.0, 3.0, 7.0]), samples)
    expected = torch.tensor([1.0, math.exp(-0.5), math.exp(-1.5), 1.0], dtype=torch.float64)
    assert torch.allclose(t, expected, rtol=1e-12)


def test_select_keeps_packing():
    samples = PackedSamples.from_counts(
        torch.tensor([3, 2]), torch.tensor([0.0, 1.0, 2.0, 0.0, 1.0]), torch.tensor([1.0, 2.0, 3.0, 1.0, 2.0])
    )
    sub = samples.select(torch.tensor([True, True, False, False, False]))
    sub.check()
    assert sub.ray_offsets.tolist() == [0, 2, 2]
    assert sub.ray_indices.tolist() == [0, 0]
    assert sub.t_ends.tolist() == [1.0, 2.0]


def _model(min_transmittance: float) -> SceneModel:
    box = SceneBox((-2.0, -2.0, -1.0), (2.0, 2.0, 1.0))
    # the density logit's output bias at 3: ~20 /m everywhere, so light dies within ~0.5 m and most
    # samples are hidden
    field = NerfField(box, FieldConfig(log2_table_size=12, max_resolution=64, bias=True), seed=3)
    with torch.no_grad():
        field.density_mlp[-1].bias[0] = 3.0
    grid = NgpGrid(GridSpec.from_box(box, 32), NgpGridConfig(), step_size=0.05)  # all cells occupied
    return SceneModel(field, grid, step_size=0.05, near=0.05, max_samples=256, min_transmittance=min_transmittance)


def _render_and_grads(model: SceneModel, generator_seed: int = 5, visible_share: float = 1.0):
    g = torch.Generator().manual_seed(1)
    origins = torch.zeros(64, 3)
    directions = torch.nn.functional.normalize(torch.randn(64, 3, generator=g), dim=1)
    model.field.zero_grad(set_to_none=True)
    out, stats = model.render(origins, directions, visible_share=visible_share)
    loss = (out.rgb - 0.3).square().sum() + (out.depth - 0.4).square().sum() + out.opacity.sum()
    loss.backward()
    grads = [p.grad.clone() for p in model.field.parameters()]
    return out, stats, grads


def test_visible_pass_matches_full_render():
    """eps = 1e-6 on a uniform 20 /m fog (every sample near the cut-off, the worst case for the
    gradients): renders and gradients agree to 1e-3 (the error shrinks in proportion to eps)."""
    full_out, full_stats, full_grads = _render_and_grads(_model(0.0))
    two_pass = _model(1e-6)
    # as after a step that found most samples hidden
    vis_out, vis_stats, vis_grads = _render_and_grads(two_pass, visible_share=0.0)
    assert full_stats.n_samples == vis_stats.n_samples  # the same marched samples
    assert vis_stats.n_trained < 0.5 * vis_stats.n_samples  # most of them hidden and skipped
    assert full_stats.n_trained == full_stats.n_samples
    for a, b in ((full_out.rgb, vis_out.rgb), (full_out.depth, vis_out.depth), (full_out.opacity, vis_out.opacity)):
        assert torch.allclose(a, b, atol=1e-3)
    for a, b in zip(full_grads, vis_grads, strict=True):
        # each skipped sample's share is below eps = 1e-4 of a visible one's; hash collisions
        # add up thousands of them per table entry, so compare whole tensors, not entries
        assert a.norm() > 0
        assert (a - b).norm() <= 1e-3 * a.norm()
    # the NeRF-Update still sees every marched sample's density
    assert torch.allclose(full_stats.sigma, vis_stats.sigma, rtol=1e-5)


def test_without_gradients_every_sample_is_rendered():
    model = _model(1e-4)
    with torch.no_grad():
        out, stats = model.render(torch.zeros(8, 3), torch.tensor([[1.0, 0.0, 0.0]] * 8))
    assert stats.n_trained == stats.n_samples


def test_one_pass_path_trains_every_density_and_skips_hidden_colour():
    """While most samples are visible (visible_share above TWO_PASS_BELOW) a step takes one pass:
    every density with gradients, colour only where T >= eps; renders and gradients again match
    the full render (here exactly for the density path up to the hidden colours' < eps weight)."""
    full_out, _, full_grads = _render_and_grads(_model(0.0))
    model = _model(1e-6)
    out, stats, grads = _render_and_grads(model)  # a new mapper starts at 1.0: the one-pass path
    assert stats.n_trained == stats.n_samples  # every density trained
    assert stats.visible_share < 0.5  # measured: the next step takes the two-pass path
    for a, b in ((full_out.rgb, out.rgb), (full_out.depth, out.depth), (full_out.opacity, out.opacity)):
        assert torch.allclose(a, b, atol=1e-3)
    for a, b in zip(full_grads, grads, strict=True):
        assert (a - b).norm() <= 1e-3 * a.norm()
    _, stats2, _ = _render_and_grads(model, visible_share=stats.visible_share)
    assert stats2.n_trained < stats2.n_samples  # two-pass now
