"""NeRF field (docs/method.md 3.5): multiresolution hash encoding (numba CPU / PyTorch), SH direction
encoding, density and colour MLPs."""

from virus_nerf.field.field import FieldConfig, NerfField, trunc_exp
from virus_nerf.field.hash_encoding import (
    HashEncoding,
    HashGridLayout,
    hash_encode,
    hash_encode_torch,
)
from virus_nerf.field.sh import SH_DIM, sh_encode

__all__ = [
    "FieldConfig",
    "NerfField",
    "trunc_exp",
    "HashEncoding",
    "HashGridLayout",
    "hash_encode",
    "hash_encode_torch",
    "SH_DIM",
    "sh_encode",
]
