"""Adam with the fused kernel called directly.

`torch.optim.Adam(fused=True).step()` wraps the kernel in Python (profiler hooks,
param-group bookkeeping) that, for small RL networks on a CPU, costs more than the math
(docs/benchmarks.md has the figures). Same update as torch.optim.Adam (no weight decay, no
amsgrad); state_dict round-trips.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, cast

import torch


class FastAdam:
    def __init__(self, params: Iterable[torch.Tensor], lr: float, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8) -> None:
        self.params = [p for p in params if p.requires_grad]
        self.betas = betas
        self.eps = eps
        self._data = [p.detach() for p in self.params]
        self.exp_avg = [torch.zeros_like(p) for p in self._data]
        self.exp_avg_sq = [torch.zeros_like(p) for p in self._data]
        # One step counter per tensor, as the kernel expects, on the params' one device (an agent's
        # networks share it): views of one tensor, so counting a step is one op
        # (torch._foreach_add_ on CPU loops over the tensors one by one).
        devices = {p.device for p in self._data}
        if len(devices) != 1:
            raise ValueError("FastAdam takes trainable parameters on one device; got them on "
                             f"{sorted(map(str, devices))}")
        device = devices.pop()
        self._steps_flat = torch.zeros(len(self._data), dtype=torch.float32, device=device)
        self.steps = list(self._steps_flat.unbind(0))
        # On a GPU the kernel reads the learning rate from a device tensor, so a step captured
        # in a CUDA graph (nn/graphed.py) follows a schedule that changes it.
        self._lr_tensor = torch.tensor(float(lr), device=device) if device.type == "cuda" else None
        self._lr = float(lr)

    @property
    def lr(self) -> float:
        return self._lr

    @lr.setter
    def lr(self, value: float) -> None:
        if value != self._lr and self._lr_tensor is not None:
            self._lr_tensor.fill_(value)
        self._lr = float(value)

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    @torch.no_grad()
    def step(self, grads: list[torch.Tensor] | None = None) -> None:
        """One Adam step from the params' `.grad`, or from `grads` (same order as the params)
        when the caller computed gradients without autograd. A parameter without a gradient (a
        user's encoder's layer its forward pass leaves out) is left as it is, as torch.optim.Adam
        leaves it: its moments and step count too."""
        if grads is None:
            grads = cast("list[torch.Tensor]", [p.grad for p in self.params])
        elif len(grads) != len(self.params):
            raise ValueError(f"FastAdam.step() got {len(grads)} gradients for {len(self.params)} parameters")
        data, exp_avg, exp_avg_sq, steps = self._data, self.exp_avg, self.exp_avg_sq, self.steps
        if any(g is None for g in grads):
            keep = [i for i, g in enumerate(grads) if g is not None]
            if not keep:
                return
            data, grads, exp_avg, exp_avg_sq, steps = ([t[i] for i in keep]
                                                       for t in (data, grads, exp_avg, exp_avg_sq, steps))
            for step in steps:
                step.add_(1.0)
        else:
            self._steps_flat.add_(1.0)
        lr = self._lr if self._lr_tensor is None else self._lr_tensor
        torch._fused_adam_(data, grads, exp_avg, exp_avg_sq, [], steps, amsgrad=False, lr=lr, beta1=self.betas[0],
                           beta2=self.betas[1], weight_decay=0.0, eps=self.eps, maximize=False)

    def state_dict(self) -> dict[str, Any]:
        return {"lr": self.lr, "exp_avg": [t.clone() for t in self.exp_avg],
                "exp_avg_sq": [t.clone() for t in self.exp_avg_sq], "steps": [t.clone() for t in self.steps]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.lr = float(state["lr"])
        for dst_list, key in ((self.exp_avg, "exp_avg"), (self.exp_avg_sq, "exp_avg_sq"), (self.steps, "steps")):
            for dst, src in zip(dst_list, state[key], strict=True):
                dst.copy_(src)
