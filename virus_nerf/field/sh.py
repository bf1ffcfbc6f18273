"""Real spherical harmonics up to degree 3 ("degree 4" = 16 components, as in Instant-NGP).

Used as the direction encoding of the colour MLP (docs/method.md 3.5). The basis is the standard
orthonormal real SH on the unit sphere (integral of Y_i Y_j over the sphere = delta_ij), without
the Condon-Shortley phase; order (l, m) = (0,0), (1,-1), (1,0), (1,1), (2,-2) .. (3,3), with
m < 0 the sin(|m| phi) terms. Constants are derived from their closed forms, not typed in.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

SH_DIM = 16

_C0 = 0.5 * math.sqrt(1.0 / math.pi)  # Y_00 = 0.28209...
_C1 = math.sqrt(3.0 / (4.0 * math.pi))  # Y_1m = 0.48860... * (y, z, x)
_C2 = (
    0.5 * math.sqrt(15.0 / math.pi),  # xy, yz, xz
    0.25 * math.sqrt(5.0 / math.pi),  # 3z^2 - 1
    0.25 * math.sqrt(15.0 / math.pi),  # x^2 - y^2
)
_C3 = (
    0.25 * math.sqrt(35.0 / (2.0 * math.pi)),  # (3x^2 - y^2) y ; (x^2 - 3y^2) x
    0.5 * math.sqrt(105.0 / math.pi),  # xyz
    0.25 * math.sqrt(21.0 / (2.0 * math.pi)),  # y (5z^2 - 1) ; x (5z^2 - 1)
    0.25 * math.sqrt(7.0 / math.pi),  # z (5z^2 - 3)
    0.25 * math.sqrt(105.0 / math.pi),  # (x^2 - y^2) z
)


def sh_encode(dirs: torch.Tensor, normalise: bool = True) -> torch.Tensor:
    """Directions (N, 3) -> (N, 16) real SH values of degree 0..3 at the unit direction.

    `normalise` rescales the input to unit length first (cheap insurance; the ray directions
    handed in are meant to be unit already).
    """
    if dirs.ndim != 2 or dirs.shape[1] != 3:
        raise ValueError(f"SH encoding expects directions of shape (N, 3), got {tuple(dirs.shape)}")
    d = F.normalize(dirs, dim=-1) if normalise else dirs
    x, y, z = d.unbind(-1)  # (N,) each
    xx, yy, zz = x * x, y * y, z * z
    out = torch.stack(
        [
            torch.full_like(x, _C0),
            _C1 * y,
            _C1 * z,
            _C1 * x,
            _C2[0] * x * y,
            _C2[0] * y * z,
            _C2[1] * (3.0 * zz - 1.0),
            _C2[0] * x * z,
            _C2[2] * (xx - yy),
            _C3[0] * (3.0 * xx - yy) * y,
            _C3[1] * x * y * z,
            _C3[2] * y * (5.0 * zz - 1.0),
            _C3[3] * z * (5.0 * zz - 3.0),
            _C3[2] * x * (5.0 * zz - 1.0),
            _C3[4] * (xx - yy) * z,
            _C3[0] * (xx - 3.0 * yy) * x,
        ],
        dim=-1,
    )  # (N, 16)
    return out
