"""The colour of what lies beyond the box, by view direction (a box grown while driving).

A box grown from the first frame (grid/extent.py, `grow`) does not yet hold the far walls the
cameras already see. A camera ray to such a wall leaves the box with most of its transmittance
left; against a black background its colour can only come from density inside the box, so the
colour loss builds a false wall at the box's side, which the field must unlearn once the box
has grown past it. A learned background gives those rays somewhere else to put their colour:
rgb = sum_j w_j c_j + (1 - opacity) * background(direction).

The background is an equirectangular table of colour logits over azimuth (x-y plane, wrapping
round) and elevation, read bilinearly, sigmoid-squashed; all logits start at 0 (grey 0.5), so
the table draws nothing from the field's random generator.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F


class DirectionalBackground(nn.Module):
    """rgb (R, 3) in (0, 1) of unit view directions (R, 3): a (3, n_elevation, n_azimuth) table."""

    def __init__(self, n_azimuth: int = 90, n_elevation: int = 45):
        super().__init__()
        self.n_azimuth, self.n_elevation = int(n_azimuth), int(n_elevation)
        self.logits = nn.Parameter(torch.zeros(1, 3, self.n_elevation, self.n_azimuth))

    def forward(self, dirs: torch.Tensor) -> torch.Tensor:
        d = dirs.to(self.logits.dtype)
        azimuth = torch.atan2(d[:, 1], d[:, 0])  # (R,) in (-pi, pi]
        elevation = torch.asin(d[:, 2].clamp(-1.0, 1.0))  # (R,) in [-pi/2, pi/2]
        n = self.n_azimuth
        # one column of the other end on each side, so azimuth wraps round without a seam; the
        # padded table's cell centres are the table's own, hence the n / (n + 2) scale (align_corners=False)
        table = torch.cat([self.logits[..., -1:], self.logits, self.logits[..., :1]], dim=-1)
        u = azimuth / math.pi * (n / (n + 2))
        v = elevation / (math.pi / 2)
        grid = torch.stack([u, v], dim=-1)[None, :, None, :]  # (1, R, 1, 2)
        logits = F.grid_sample(table, grid, mode="bilinear", padding_mode="border", align_corners=False)
        return torch.sigmoid(logits[0, :, :, 0].t())  # (R, 3)
