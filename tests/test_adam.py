"""engine/adam.py against its reference, torch.optim.Adam: the same parameters and moments bit
for bit over steps with a changing learning rate and gradients that come and go, state_dicts
each reads from the other, and a training process that never imports torch._dynamo."""

from __future__ import annotations

import copy
import subprocess
import sys

import pytest
import torch

from virus_nerf.engine.adam import Adam


def _params(seed: int) -> list[torch.nn.Parameter]:
    g = torch.Generator().manual_seed(seed)
    return [torch.nn.Parameter(torch.randn(shape, generator=g)) for shape in ((64, 2), (7,), (3, 5, 2))]


def _grads(step: int, n: int) -> list[torch.Tensor | None]:
    g = torch.Generator().manual_seed(1000 + step)
    grads = [torch.randn(shape, generator=g) for shape in ((64, 2), (7,), (3, 5, 2))][:n]
    if step % 3 == 1:
        grads[1] = None  # a parameter without a gradient this step keeps its state
    return grads


def _state_equal(a: dict, b: dict) -> None:
    assert a["param_groups"] == b["param_groups"]
    assert a["state"].keys() == b["state"].keys()
    for i in a["state"]:
        assert a["state"][i].keys() == b["state"][i].keys()
        for k, v in a["state"][i].items():
            w = b["state"][i][k]
            assert v.dtype == w.dtype and v.device == w.device and torch.equal(v, w), (i, k)


@pytest.mark.parametrize("fused", [True, False])
def test_the_same_numbers_and_state_dict_as_torch_adam(fused):
    ours, ref = _params(0), _params(0)
    mine = Adam(ours, lr=0.01, betas=(0.9, 0.99), eps=1e-15, fused=fused)
    theirs = torch.optim.Adam(ref, lr=0.01, betas=(0.9, 0.99), eps=1e-15, fused=fused)
    _state_equal(mine.state_dict(), theirs.state_dict())
    for step in range(8):
        lr = 0.01 * 0.5 ** (step / 7)  # the Mapper sets the rate of each step
        for opt in (mine, theirs):
            opt.param_groups[0]["lr"] = lr
        for params in (ours, ref):
            for p, g in zip(params, _grads(step, len(params)), strict=True):
                p.grad = None if g is None else g.clone()
        mine.step()
        theirs.step()
        mine.zero_grad()
        theirs.zero_grad()
        for p, q in zip(ours, ref, strict=True):
            assert torch.equal(p, q)
    _state_equal(mine.state_dict(), theirs.state_dict())
    assert mine.state_dict()["state"][1]["step"].item() == 5.0  # 8 steps, 3 without a gradient


def test_each_resumes_from_the_others_state_dict():
    """A checkpoint of an earlier release (torch.optim.Adam's state) continues here as it would
    have there, and the other way round."""
    base = _params(1)
    ref_opt = torch.optim.Adam(base, lr=0.02, betas=(0.8, 0.95), eps=1e-8, fused=True)
    for step in range(3):
        for p, g in zip(base, _grads(step, 3), strict=True):
            p.grad = g
        ref_opt.step()
    saved = copy.deepcopy(ref_opt.state_dict())  # as a checkpoint holds it (both share tensors otherwise)
    ours = [torch.nn.Parameter(p.detach().clone()) for p in base]
    mine = Adam(ours, lr=0.5, betas=(0.5, 0.5), eps=1.0, fused=True)  # the saved group's values win
    mine.load_state_dict(saved)
    back = [torch.nn.Parameter(p.detach().clone()) for p in base]
    again = torch.optim.Adam(back, lr=0.5, fused=True)
    again.load_state_dict(copy.deepcopy(mine.state_dict()))
    for step in range(3, 6):
        for params in (base, ours, back):
            for p, g in zip(params, _grads(step, 3), strict=True):
                p.grad = None if g is None else g.clone()
        for opt in (ref_opt, mine, again):
            opt.step()
        for p, q, r in zip(base, ours, back, strict=True):
            assert torch.equal(p, q) and torch.equal(p, r)
    assert mine.param_groups[0]["lr"] == 0.02 and mine.param_groups[0]["betas"] == (0.8, 0.95)


def test_a_training_step_does_not_import_torch_dynamo():
    """torch.optim's optimiser class imports torch._dynamo (2.4 s of every training command's
    start-up on 2 cores); a Mapper's training step does not (a process of its own: this one may
    have imported it already)."""
    script = """
import sys, numpy as np
from virus_nerf.engine.mapper import warm_up
from virus_nerf.engine.config import MapperConfig
warm_up(MapperConfig())
print('torch._dynamo' in sys.modules)
"""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "False"
