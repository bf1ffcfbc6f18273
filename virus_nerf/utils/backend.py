"""Which implementation of a fused kernel runs: the numba CPU kernels or their PyTorch twins.

Every kernel pair (hash encoding, marching, compositing) resolves its `backend` knob here, so
"auto" means the same thing everywhere: numba when all tensors are on the CPU, PyTorch
otherwise (CUDA).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:  # tensors are only read here; a config checks its backend knob without torch
    import torch

Backend = Literal["auto", "numba", "torch"]
BACKENDS: tuple[str, ...] = ("auto", "numba", "torch")


def resolve_backend(backend: str, *tensors: torch.Tensor) -> Literal["numba", "torch"]:
    """`auto` -> numba when every tensor is on the CPU (the numba kernels are CPU-only)."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be 'auto', 'numba' or 'torch', got {backend!r}")
    on_cpu = all(t.device.type == "cpu" for t in tensors)
    if backend == "numba" and not on_cpu:
        raise ValueError("the numba backend needs CPU tensors; use backend='torch' on other devices")
    if backend == "auto":
        return "numba" if on_cpu else "torch"
    return backend  # type: ignore[return-value]
