"""Adam for the field without torch's optimiser class: torch's own update (its documented
functional form, `torch.optim.adam.adam`) and `torch.optim.Adam`'s state_dict.

Why not `torch.optim.Adam` itself: `torch.optim.Optimizer`'s constructor and step import
torch._dynamo (2.4 s on a 2-core machine, measured: `import torch._dynamo` after torch and numba),
which every training command (`train`, `map-bag`, the ROS 2 node, each ablation or tune run)
paid at start-up for a compiler it never uses. The update is torch's, called with the arguments
`torch.optim.Adam.step` passes (fused on CPU and CUDA), so the numbers are the same bit for bit
(tests/test_adam.py checks it against torch.optim.Adam), and a checkpoint's optimizer state is
the dict torch.optim.Adam writes and reads: checkpoints of earlier releases resume, and these
load into torch.optim.Adam.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
from torch.optim.adam import adam as adam_update


class Adam:
    """One group of parameters, no weight decay, no AMSGrad (what the Mapper trains with).

    param_groups[0]["lr"] is the learning rate of the next step (the Mapper sets it each step);
    `state_dict` / `load_state_dict` read and write torch.optim.Adam's format."""

    def __init__(self, params: Iterable[torch.nn.Parameter], lr: float, betas: tuple[float, float], eps: float,
                 fused: bool | None = None) -> None:
        params = list(params)
        if not params:
            raise ValueError("Adam: no parameters to optimise")
        self.params = params
        self.param_groups = [{
            "lr": lr, "betas": tuple(betas), "eps": eps, "weight_decay": 0, "amsgrad": False, "maximize": False,
            "foreach": None, "capturable": False, "differentiable": False, "fused": fused,
            "decoupled_weight_decay": False, "params": params,
        }]
        self.state: dict[int, dict[str, torch.Tensor]] = {}  # parameter index -> step, exp_avg, exp_avg_sq

    def zero_grad(self, set_to_none: bool = True) -> None:
        for p in self.params:
            if p.grad is None:
                continue
            if set_to_none:
                p.grad = None
            else:
                p.grad.detach_().zero_()

    def _moments(self, i: int, p: torch.Tensor, fused: bool) -> dict[str, torch.Tensor]:
        """Parameter i's state, made at its first gradient as torch.optim.Adam makes it (the
        step counter a float32 on the parameter's device when fused, else a CPU scalar)."""
        if i not in self.state:
            step = (torch.zeros((), dtype=torch.float32, device=p.device) if fused
                    else torch.tensor(0.0, dtype=torch.get_default_dtype()))
            self.state[i] = {"step": step, "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                             "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)}
        return self.state[i]

    @torch.no_grad()
    def step(self) -> None:
        """One update of every parameter that has a gradient."""
        group = self.param_groups[0]
        fused = bool(group.get("fused"))
        params, grads, states = [], [], []
        for i, p in enumerate(self.params):
            if p.grad is None:
                continue
            if p.grad.is_sparse:
                raise RuntimeError("Adam: sparse gradients are not supported")
            params.append(p)
            grads.append(p.grad)
            states.append(self._moments(i, p, fused))
        if not params:
            return
        beta1, beta2 = group["betas"]
        adam_update(params, grads, [s["exp_avg"] for s in states], [s["exp_avg_sq"] for s in states], [],
                    [s["step"] for s in states], foreach=group.get("foreach"), capturable=False,
                    differentiable=False, fused=group.get("fused"), grad_scale=None, found_inf=None,
                    has_complex=any(torch.is_complex(p) for p in params), decoupled_weight_decay=False,
                    amsgrad=False, beta1=beta1, beta2=beta2, lr=group["lr"], weight_decay=0.0, eps=group["eps"],
                    maximize=False)

    def state_dict(self) -> dict:
        """torch.optim.Adam's state_dict: the state by parameter index, the group with indices
        (the tensors are this optimiser's own, as torch's: copy before training on)."""
        group = {k: v for k, v in self.param_groups[0].items() if k != "params"}
        group["params"] = list(range(len(self.params)))
        return {"state": {i: dict(s) for i, s in sorted(self.state.items())}, "param_groups": [group]}

    def load_state_dict(self, state_dict: dict) -> None:
        """A state_dict of this class or of torch.optim.Adam over the same parameters (one group;
        the caller checked the shapes: Mapper._check_optimizer_state): the moments cast to each
        parameter's dtype and device, the step counter as torch.optim.Adam keeps it."""
        groups = state_dict["param_groups"]
        if len(groups) != 1 or len(groups[0]["params"]) != len(self.params):
            raise ValueError(f"Adam: expected the state of one group of {len(self.params)} parameters")
        saved_group = groups[0]
        group = {k: v for k, v in saved_group.items() if k != "params"}
        group["params"] = self.params
        fused = bool(group.get("fused"))
        state = {}
        for i, saved in state_dict["state"].items():
            p = self.params[int(i)]
            one = {}
            for k, v in saved.items():
                if k != "step":
                    one[k] = v.to(dtype=p.dtype, device=p.device)
                    continue
                if not isinstance(v, torch.Tensor):  # a number: torch before 1.12 kept the counter so
                    v = torch.tensor(float(v), dtype=torch.get_default_dtype())
                one[k] = v.to(dtype=torch.float32, device=p.device) if fused else v
            state[int(i)] = one
        self.param_groups, self.state = [group], state
