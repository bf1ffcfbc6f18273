"""The NeRF field (docs/method.md 3.5): hash encoding -> density MLP -> (sigma, geometry features);
[SH(direction), features] -> colour MLP -> RGB.

World points in metres are normalised to [0,1]^3 with the SceneBox inside the field only; points
outside the box get sigma = 0 (and rgb = 0: with zero density they never contribute) and are not
evaluated at all.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from virus_nerf.field.config import FieldConfig
from virus_nerf.field.hash_encoding import HashEncoding
from virus_nerf.field.sh import SH_DIM, sh_encode
from virus_nerf.scene_box import SceneBox


class _TruncExp(torch.autograd.Function):
    """exp with a clamped gradient (torch-ngp's trunc_exp): forward exp(min(x, c)), backward
    g * exp(clamp(x, -c, c)), so one huge logit cannot blow up the step."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, clamp: float) -> torch.Tensor:
        ctx.save_for_backward(x)
        ctx.clamp = clamp
        return torch.exp(x.clamp(max=clamp))

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(-ctx.clamp, ctx.clamp)), None


def trunc_exp(x: torch.Tensor, clamp: float = 15.0) -> torch.Tensor:
    return _TruncExp.apply(x, clamp)


def _mlp(n_in: int, hidden: tuple[int, ...], n_out: int, bias: bool) -> nn.Sequential:
    layers: list[nn.Module] = []
    for width in hidden:
        # In-place ReLU: Linear keeps its input, not its output, for backward; ~20 % faster step.
        layers += [nn.Linear(n_in, width, bias=bias), nn.ReLU(inplace=True)]
        n_in = width
    layers.append(nn.Linear(n_in, n_out, bias=bias))
    return nn.Sequential(*layers)


class NerfField(nn.Module):
    """Density and colour of the scene at world points (metres); deterministic init from `seed`."""

    def __init__(
        self,
        box: SceneBox,
        config: FieldConfig | None = None,
        seed: int = 0,
        generator: torch.Generator | None = None,
    ):
        """`generator` (CPU), when given, replaces `seed`; all parameters are drawn from it in a
        fixed order (table, then the Linear layers front to back)."""
        super().__init__()
        self.box = box
        self.config = config if config is not None else FieldConfig.cpu_default()
        cfg = self.config
        gen = generator if generator is not None else torch.Generator().manual_seed(int(seed))
        self.encoding = HashEncoding(cfg.layout, cfg.backend, gen)
        self.density_mlp = _mlp(self.encoding.out_dim, cfg.density_hidden, cfg.geo_feat_dim, cfg.bias)
        self.color_mlp = _mlp(SH_DIM + cfg.geo_feat_dim, cfg.color_hidden, 3, cfg.bias)
        for m in self.modules():  # nn.Linear's default init, but drawn from our generator
            if isinstance(m, nn.Linear):
                nn.init.kaiming_uniform_(m.weight, a=math.sqrt(5.0), generator=gen)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
        # (3,) float32 box corner and size; buffers so .to(device) moves them; rebuilt from `box`.
        self.register_buffer("box_lo", torch.tensor(box.lo, dtype=torch.float32), persistent=False)
        self.register_buffer("box_size", torch.tensor(box.size, dtype=torch.float32), persistent=False)

    def normalise(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World points (N, 3) m -> box coordinates (N, 3) and inside mask (N,) bool (NaN = outside)."""
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"field expects points of shape (N, 3), got {tuple(points.shape)}")
        x = (points.to(torch.float32) - self.box_lo) / self.box_size  # (N, 3)
        inside = ((x >= 0.0) & (x <= 1.0)).all(dim=-1)  # (N,)
        return x, inside

    def _geo(self, x: torch.Tensor) -> torch.Tensor:
        """Box coordinates (M, 3) -> geometry features h (M, geo_feat_dim); h[:, 0] is the density logit."""
        return self.density_mlp(self.encoding(x))

    def _sigma(self, h: torch.Tensor) -> torch.Tensor:
        return trunc_exp(h[:, 0], self.config.density_clamp)  # (M,) 1/m: sigma = exp(h0), the paper's

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """sigma (N,) in 1/m at world points (N, 3) m; no colour (for occupancy-grid updates)."""
        x, inside = self.normalise(points)
        if bool(inside.all()):
            return self._sigma(self._geo(x))
        return self._geometry(x, inside)[0]

    def forward(
        self, points: torch.Tensor, dirs: torch.Tensor, rgb_mask: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """World points (N, 3) m, unit view directions (N, 3) -> sigma (N,) 1/m, rgb (N, 3) in (0, 1).

        rgb_mask (N,) bool, optional: the colour MLP runs only where it is True (rgb 0 elsewhere,
        no gradient), for density-only training of depth-supervised rays.
        """
        if dirs.shape != points.shape:
            raise ValueError(f"dirs shape {tuple(dirs.shape)} must equal points shape {tuple(points.shape)}")
        x, inside = self.normalise(points)
        if rgb_mask is None and bool(inside.all()):
            return self._sigma_rgb(x, dirs)
        sigma, h, idx = self._geometry(x, inside)
        return sigma, self.colour_at(h, idx, dirs, rgb_mask)

    def geometry(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """World points (N, 3) m -> sigma (N,) 1/m (0 outside the box), the geometry features
        h (M, G) of the M points inside the box and their rows idx (M,) in `points`; `colour_at`
        then runs the colour MLP where it is needed (e.g. once the transmittance is known)."""
        return self._geometry(*self.normalise(points))

    def _geometry(self, x: torch.Tensor, inside: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Box coordinates (N, 3) and inside mask (N,) -> (sigma (N,), h (M, G), idx (M,))."""
        idx = inside.nonzero().squeeze(1)  # (M,)
        sigma = x.new_zeros(x.shape[0])
        if idx.numel() == 0:
            return sigma, x.new_zeros(0, self.config.geo_feat_dim), idx
        h = self._geo(x[idx])  # (M, G)
        return sigma.index_copy(0, idx, self._sigma(h)), h, idx

    def colour_at(self, h: torch.Tensor, idx: torch.Tensor, dirs: torch.Tensor,
                  mask: torch.Tensor | None = None) -> torch.Tensor:
        """rgb (N, 3) for the N rows of `dirs` from `geometry`'s h (M, G) and idx (M,): the colour
        MLP runs on the rows inside the box where mask (N,) bool is True (all of them without a
        mask); rgb is 0 elsewhere, with no gradient."""
        rgb = h.new_zeros(dirs.shape[0], 3)
        if mask is None:
            return rgb.index_copy(0, idx, self._rgb(h, dirs[idx])) if idx.numel() else rgb
        sub = mask[idx].nonzero().squeeze(1)  # rows of h that need colour
        if sub.numel():
            rgb = rgb.index_copy(0, idx[sub], self._rgb(h[sub], dirs[idx[sub]]))
        return rgb

    def _rgb(self, h: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        d = sh_encode(dirs.to(torch.float32))  # (M, 16)
        return torch.sigmoid(self.color_mlp(torch.cat([d, h], dim=-1)))  # (M, 3)

    def _sigma_rgb(self, x: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self._geo(x)  # (M, G)
        return self._sigma(h), self._rgb(h, dirs)

    def extra_repr(self) -> str:
        return f"box lo={self.box.lo} hi={self.box.hi}"
