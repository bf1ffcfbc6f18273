"""Multiresolution hash encoding (Muller et al. 2022; docs/method.md 3.5), layout and PyTorch backend.

Level l has `resolutions[l]` cells per axis of the unit box, i.e. res+1 vertices per axis; the
resolutions grow geometrically from `base_resolution` to `max_resolution` (N_l = floor(N_min b^l)).
A level whose (res+1)^3 vertices fit the table is indexed densely (one entry per vertex, the
table shrunk to exactly (res+1)^3 entries); otherwise vertex (i, j, k) goes to
(i * 1 ^ j * 2654435761 ^ k * 805459861) mod T. Features of the 8 corners of the cell holding a
point are blended trilinearly. All levels live in one flat (n_entries, F) parameter, level l at
rows offsets[l] .. offsets[l] + sizes[l].

Two backends with the same signature `encode(x (N, 3) in [0,1]^3, table (E, F)) -> (N, L*F)`:
- "torch": gathers + weights in plain PyTorch; autograd gives the table gradient; runs on CUDA.
- "numba": fused CPU kernels (hash_kernels.py); deterministic backward.
"auto" picks numba for CPU tensors and torch otherwise. Neither backend returns a gradient for
the input coordinates: the field never needs one (poses are not optimised through the field),
and dropping it saves the weight-derivative pass. Inputs outside [0,1]^3 are clamped onto the
box surface; NaN coordinates are mapped to 0 (the field masks such points anyway).
"""

from __future__ import annotations

import torch
from torch import nn

from virus_nerf.field.hash_layout import PRIMES, HashGridLayout, LayoutArrays, prepare_coords
from virus_nerf.utils.backend import BACKENDS, resolve_backend

__all__ = ["BACKENDS", "PRIMES", "HashEncoding", "HashGridLayout", "LayoutArrays", "hash_encode", "hash_encode_torch",
           "prepare_coords"]

def hash_encode_torch(x: torch.Tensor, table: torch.Tensor, layout: HashGridLayout) -> torch.Tensor:
    """Plain PyTorch backend: x (N, 3) in [0,1]^3, table (E, F) -> (N, L*F); autograd for table.

    All levels are processed at once; peak memory is about N * L * 8 * 20 bytes.
    """
    x = prepare_coords(x)
    dev = x.device
    n = x.shape[0]
    L, F = layout.n_levels, layout.n_features
    res_f = torch.tensor(layout.resolutions, dtype=torch.float32, device=dev)  # (L,)
    res_i = torch.tensor(layout.resolutions, dtype=torch.int64, device=dev)  # (L,)
    pos = x[:, None, :] * res_f[None, :, None]  # (N, L, 3) float32
    cell = torch.minimum(pos.floor().to(torch.int64), (res_i - 1)[None, :, None])  # (N, L, 3)
    frac = pos - cell.to(torch.float32)  # (N, L, 3) in [0, 1]
    cidx = torch.stack([cell, cell + 1], dim=-1)  # (N, L, 3, 2) vertex coordinate per axis and bit
    wts = torch.stack([1.0 - frac, frac], dim=-1)  # (N, L, 3, 2) linear weight per axis and bit

    # Dense levels form a prefix (resolutions grow). Dense row: i + j (r+1) + k (r+1)^2;
    # hashed row: (i p0 ^ j p1 ^ k p2) & (T-1). Corner order k = dx + 2 dy + 4 dz.
    n_dense = sum(layout.dense)
    parts = []
    if n_dense:
        r1 = res_i[:n_dense] + 1
        stride = torch.stack([torch.ones_like(r1), r1, r1 * r1], dim=-1)  # (Ld, 3)
        t = cidx[:, :n_dense] * stride[None, :, :, None]  # (N, Ld, 3, 2)
        parts.append(t[:, :, 0, None, None, :] + t[:, :, 1, None, :, None] + t[:, :, 2, :, None, None])
    if n_dense < L:
        primes = torch.tensor(PRIMES, dtype=torch.int64, device=dev)  # (3,)
        t = cidx[:, n_dense:] * primes[None, None, :, None]  # (N, Lh, 3, 2)
        h = t[:, :, 0, None, None, :] ^ t[:, :, 1, None, :, None] ^ t[:, :, 2, :, None, None]
        parts.append(h & (layout.table_size - 1))
    rows = torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]  # (N, L, 2dz, 2dy, 2dx)
    offsets = torch.tensor(layout.offsets, dtype=torch.int64, device=dev)
    idx = (rows.reshape(n, L, 8) + offsets[None, :, None]).reshape(-1)  # (N*L*8,)
    w = (
        wts[:, :, 0, None, None, :] * wts[:, :, 1, None, :, None] * wts[:, :, 2, :, None, None]
    ).reshape(n, L, 8)  # (N, L, 8) trilinear weights, sum 1
    feats = table.index_select(0, idx).reshape(n * L, 8, F)  # (N*L, 8, F); 3x faster than table[idx]
    out = torch.bmm(w.reshape(n * L, 1, 8), feats)  # (N*L, 1, F)
    return out.reshape(n, L * F)


def hash_encode(x: torch.Tensor, table: torch.Tensor, layout: HashGridLayout, backend: str = "auto") -> torch.Tensor:
    """Encode x (N, 3) in [0,1]^3 with table (E, F) -> (N, L*F) float32 on the chosen backend."""
    if table.shape != (layout.n_entries, layout.n_features):
        raise ValueError(f"table shape {tuple(table.shape)} does not match layout {(layout.n_entries, layout.n_features)}")
    if resolve_backend(backend, table) == "numba":
        from virus_nerf.field.hash_kernels import hash_encode_numba

        return hash_encode_numba(x, table, layout)
    return hash_encode_torch(x, table, layout)


class HashEncoding(nn.Module):
    """The trainable multiresolution hash grid; table initialised U(-1e-4, 1e-4) from `generator`."""

    def __init__(self, layout: HashGridLayout, backend: str = "auto", generator: torch.Generator | None = None):
        super().__init__()
        if backend not in BACKENDS:
            raise ValueError(f"unknown hash-encoding backend {backend!r}; choose one of {BACKENDS}")
        self.layout = layout
        self.backend = backend
        table = torch.empty(layout.n_entries, layout.n_features, dtype=torch.float32)
        table.uniform_(-1e-4, 1e-4, generator=generator)
        self.table = nn.Parameter(table)  # (E, F)

    @property
    def out_dim(self) -> int:
        return self.layout.out_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x (N, 3) box coordinates in [0,1]^3 -> (N, L*F) float32."""
        return hash_encode(x, self.table, self.layout, self.backend)

    def extra_repr(self) -> str:
        lay = self.layout
        return (
            f"levels={lay.n_levels}, features={lay.n_features}, T=2^{lay.log2_table_size}, "
            f"res={lay.resolutions[0]}..{lay.resolutions[-1]}, dense_levels={sum(lay.dense)}, backend={self.backend}"
        )
