"""Packed ray samples (nerfacc style, docs/method.md 2): no padding, one row per kept sample.

A batch of R rays yields S samples in total; sample j belongs to ray `ray_indices[j]` and covers
the interval [t_starts[j], t_ends[j]] in metres along that ray's unit direction. Samples are sorted
by ray and, within a ray, by distance, so ray r owns the contiguous slice
`ray_offsets[r]:ray_offsets[r + 1]`. Rays that hit no occupied cell own an empty slice.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class PackedSamples:
    """S samples of R rays; t in metres along the unit ray direction."""

    ray_indices: torch.Tensor  # (S,) int64, sorted ascending
    t_starts: torch.Tensor  # (S,) float32 metres
    t_ends: torch.Tensor  # (S,) float32 metres, > t_starts
    ray_offsets: torch.Tensor  # (R + 1,) int64: ray r owns samples ray_offsets[r]:ray_offsets[r+1]

    @property
    def n_rays(self) -> int:
        return int(self.ray_offsets.shape[0]) - 1

    @property
    def n_samples(self) -> int:
        return int(self.ray_indices.shape[0])

    @property
    def midpoints(self) -> torch.Tensor:
        """(S,) metres: centre of each sample interval, where the field is evaluated."""
        return (self.t_starts + self.t_ends) * 0.5

    @property
    def deltas(self) -> torch.Tensor:
        """(S,) metres: length of each sample interval (delta_j of docs/method.md 3.1)."""
        return self.t_ends - self.t_starts

    @property
    def counts(self) -> torch.Tensor:
        """(R,) int64 samples per ray."""
        return self.ray_offsets[1:] - self.ray_offsets[:-1]

    def positions(self, origins: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        """World points (S, 3) at the sample midpoints of rays origins (R, 3), directions (R, 3)."""
        o = origins[self.ray_indices]  # (S, 3)
        d = directions[self.ray_indices]  # (S, 3)
        return o + self.midpoints.to(o.dtype)[:, None] * d

    def to(self, device: torch.device | str) -> PackedSamples:
        return PackedSamples(
            self.ray_indices.to(device),
            self.t_starts.to(device),
            self.t_ends.to(device),
            self.ray_offsets.to(device),
        )

    @staticmethod
    def from_counts(
        counts: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor
    ) -> PackedSamples:
        """Build from per-ray sample counts (R,) and ray-sorted intervals (S,)."""
        counts = counts.to(torch.int64)
        offsets = torch.zeros(counts.shape[0] + 1, dtype=torch.int64, device=counts.device)
        torch.cumsum(counts, 0, out=offsets[1:])
        ray_indices = torch.repeat_interleave(
            torch.arange(counts.shape[0], device=counts.device), counts
        )
        if ray_indices.shape[0] != t_starts.shape[0] or t_starts.shape != t_ends.shape:
            raise ValueError(
                f"counts sum to {ray_indices.shape[0]} samples but t_starts has "
                f"{tuple(t_starts.shape)} and t_ends {tuple(t_ends.shape)}"
            )
        return PackedSamples(ray_indices, t_starts, t_ends, offsets)

    def select(self, keep: torch.Tensor) -> PackedSamples:
        """The samples where keep (S,) bool is True, still packed by ray (rays keep their index;
        a ray may end up with none)."""
        counts = torch.zeros(self.n_rays, dtype=torch.int64, device=keep.device).index_add_(
            0, self.ray_indices, keep.to(torch.int64)
        )  # (R,) kept samples per ray
        return PackedSamples.from_counts(counts, self.t_starts[keep], self.t_ends[keep])

    @staticmethod
    def empty(n_rays: int, device: torch.device | str = "cpu") -> PackedSamples:
        z = torch.zeros(0, device=device)
        return PackedSamples(
            torch.zeros(0, dtype=torch.int64, device=device),
            z,
            z.clone(),
            torch.zeros(n_rays + 1, dtype=torch.int64, device=device),
        )

    def check(self) -> None:
        """Raise ValueError if the bookkeeping is inconsistent (for tests and debugging)."""
        s = self.n_samples
        if self.t_starts.shape != (s,) or self.t_ends.shape != (s,):
            raise ValueError("t_starts / t_ends must be (S,) like ray_indices")
        off = self.ray_offsets
        if off[0] != 0 or off[-1] != s or bool((off[1:] < off[:-1]).any()):
            raise ValueError("ray_offsets must start at 0, end at S and never decrease")
        expect = torch.repeat_interleave(torch.arange(self.n_rays, device=off.device), self.counts)
        if not torch.equal(expect, self.ray_indices):
            raise ValueError("ray_indices disagree with ray_offsets (not sorted by ray?)")
        if bool((self.t_ends <= self.t_starts).any()):
            raise ValueError("every sample needs t_end > t_start")
