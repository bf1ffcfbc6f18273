"""NeRF field (docs/method.md 3.5): multiresolution hash encoding (numba CPU / PyTorch), SH direction
encoding, density and colour MLPs.

The names below load on first use (PEP 562), so that `virus_nerf.field.config` (a run's config,
its flags, `train --help`) does not pull in torch."""

_LAZY = {
    "FieldConfig": "virus_nerf.field.config",
    "NerfField": "virus_nerf.field.field",
    "trunc_exp": "virus_nerf.field.field",
    "HashEncoding": "virus_nerf.field.hash_encoding",
    "HashGridLayout": "virus_nerf.field.hash_layout",
    "hash_encode": "virus_nerf.field.hash_encoding",
    "hash_encode_torch": "virus_nerf.field.hash_encoding",
    "SH_DIM": "virus_nerf.field.sh",
    "sh_encode": "virus_nerf.field.sh",
}
__all__ = ["FieldConfig", "NerfField", "trunc_exp", "HashEncoding", "HashGridLayout", "hash_encode",
           "hash_encode_torch", "SH_DIM", "sh_encode"]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
