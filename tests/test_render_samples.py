"""PackedSamples bookkeeping: offsets, ray indices, midpoints, positions, consistency checks."""

from __future__ import annotations

import pytest
import torch

from virus_nerf.render import PackedSamples


def _two_rays() -> PackedSamples:
    # ray 0: two samples, ray 1: none, ray 2: one sample
    return PackedSamples.from_counts(
        torch.tensor([2, 0, 1]), torch.tensor([0.5, 1.0, 2.0]), torch.tensor([1.0, 1.5, 2.2])
    )


def test_from_counts_offsets_indices_midpoints_and_positions():
    s = _two_rays()
    s.check()
    assert s.n_rays == 3 and s.n_samples == 3
    assert s.ray_offsets.tolist() == [0, 2, 2, 3]
    assert s.ray_indices.tolist() == [0, 0, 2]
    assert s.counts.tolist() == [2, 0, 1]
    torch.testing.assert_close(s.midpoints, torch.tensor([0.75, 1.25, 2.1]))
    torch.testing.assert_close(s.deltas, torch.tensor([0.5, 0.5, 0.2]))
    o = torch.tensor([[0.0, 0.0, 0.0], [9.0, 9.0, 9.0], [1.0, 2.0, 3.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])
    torch.testing.assert_close(
        s.positions(o, d), torch.tensor([[0.75, 0.0, 0.0], [1.25, 0.0, 0.0], [1.0, 2.0, 0.9]])
    )


def test_empty_and_inconsistent_samples():
    e = PackedSamples.empty(4)
    e.check()
    assert e.n_rays == 4 and e.n_samples == 0
    with pytest.raises(ValueError, match="counts sum"):
        PackedSamples.from_counts(torch.tensor([2, 2]), torch.zeros(3), torch.ones(3))
    s = _two_rays()
    bad = PackedSamples(torch.tensor([0, 2, 0]), s.t_starts, s.t_ends, s.ray_offsets)
    with pytest.raises(ValueError, match="sorted"):
        bad.check()
    bad = PackedSamples(s.ray_indices, s.t_ends, s.t_starts, s.ray_offsets)
    with pytest.raises(ValueError, match="t_end > t_start"):
        bad.check()
    bad = PackedSamples(s.ray_indices, s.t_starts, s.t_ends, torch.tensor([0, 2, 1, 3]))
    with pytest.raises(ValueError, match="never decrease"):
        bad.check()
