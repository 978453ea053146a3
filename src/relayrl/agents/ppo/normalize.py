"""Running observation normalisation and reward scaling, as Stable-Baselines3's VecNormalize.

Observations: clip((obs - mean) / sqrt(var + 1e-8), -10, 10), with the running mean and
variance of the observations seen so far. `ObsNorm` holds them as buffers of the policy
network, so the checkpoint, the actors' pulled copies, the saved policy and the exported
program all normalise alike.

Rewards: clip(reward / sqrt(var(R) + 1e-8), -10, 10), where R is each env copy's discounted
return so far (R <- gamma R + reward, set to 0 where an episode ends) and var(R) the running
variance of R over every copy and step.

Statistics are float64 (NumPy's in SB3) and start as SB3's RunningMeanStd: mean 0, var 1,
count 1e-4.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

CLIP = 10.0
EPS = 1e-8
PRIOR_COUNT = 1e-4


class RunningMeanStd(nn.Module):
    """Mean and (population) variance over every row folded in, per element of `shape`."""

    # Buffers, declared for the type checker (Module's __getattr__ types them Tensor | Module).
    mean: torch.Tensor
    var: torch.Tensor
    count: torch.Tensor

    def __init__(self, shape: tuple[int, ...] = ()) -> None:
        super().__init__()
        self.register_buffer("mean", torch.zeros(shape, dtype=torch.float64))
        self.register_buffer("var", torch.ones(shape, dtype=torch.float64))
        self.register_buffer("count", torch.tensor(PRIOR_COUNT, dtype=torch.float64))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Fold in a batch x [N, *shape]."""
        self.update_steps(x[None])

    @torch.no_grad()
    def update_steps(self, x: torch.Tensor) -> torch.Tensor:
        """Fold in T batches x [T, N, *shape], in order; returns the variance after each [T, *shape].

        Pooled sums over the data shifted by the current mean (which keeps the sums of squares
        small): after t batches, with n_t rows in all (the prior's count included), S1 and S2
        the sums of the shifted rows and of their squares, the mean moves by S1 / n_t and
        var_t = (var * count + S2 - S1^2 / n_t) / n_t, as folding the batches in one by one.
        """
        d = x.to(self.mean.device, torch.float64) - self.mean
        t_len, n = d.shape[0], d.shape[1]
        if n == 0:
            return self.var.expand(t_len, *self.var.shape)
        counts = self.count + n * torch.arange(1, t_len + 1, dtype=torch.float64, device=d.device)
        counts = counts.reshape(-1, *([1] * self.mean.dim()))
        s1, s2 = d.sum(1).cumsum(0), d.square().sum(1).cumsum(0)  # [T, *shape]
        var = (self.var * self.count + s2 - s1.square() / counts) / counts
        self.mean.add_(s1[-1] / counts[-1])
        self.var.copy_(var[-1])
        self.count.copy_(counts[-1].reshape(()))
        return var


class ObsNorm(RunningMeanStd):
    """obs [B, *shape] -> the normalised observation, flat [B, D], in obs's float dtype (float32
    for integer and bool observations, whose dtype would cut the normalised values)."""

    def __init__(self, dim: int) -> None:
        super().__init__((dim,))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        super().update(x.reshape(x.shape[0], -1))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        obs = obs.reshape(obs.shape[0], -1)  # a Box of any rank, as the MLP takes it
        out = obs.dtype if obs.is_floating_point() else torch.float32
        z = (obs.to(self.mean.dtype) - self.mean) / torch.sqrt(self.var + EPS)  # float64, as SB3's NumPy arithmetic
        return z.clamp(-CLIP, CLIP).to(out)

    def saved(self) -> dict[str, list[float]]:
        """What a saved policy holds of it (plain lists: see policy_file.py)."""
        return {"obs_mean": self.mean.cpu().tolist(), "obs_var": self.var.cpu().tolist()}

    @classmethod
    def from_saved(cls, state: dict[str, Any]) -> ObsNorm:
        norm = cls(len(state["obs_mean"]))
        norm.mean.copy_(torch.as_tensor(state["obs_mean"], dtype=torch.float64))
        norm.var.copy_(torch.as_tensor(state["obs_var"], dtype=torch.float64))
        return norm


class RewardScaler:
    """Scales a rollout's rewards [T, B] step by step, with per-copy discounted returns that
    carry over from one rollout to the next (the rollouts of one set of env copies, in order)."""

    def __init__(self, gamma: float) -> None:
        self.gamma = gamma
        self.rms = RunningMeanStd()
        self.returns: torch.Tensor | None = None  # [B] float64, made at the first rollout

    @torch.no_grad()
    def __call__(self, reward: torch.Tensor, done: torch.Tensor) -> torch.Tensor:
        """reward [T, B], done [T, B] (terminated or truncated) -> scaled rewards [T, B] float32."""
        t_len, b = reward.shape
        if self.returns is None or self.returns.shape[0] != b:
            self.returns = torch.zeros(b, dtype=torch.float64)
        r = reward.detach().to("cpu", torch.float64)
        ended = done.detach().cpu()
        returns = torch.empty(t_len, b, dtype=torch.float64)  # R after each step, before its episode-end reset
        ret = self.returns
        for t in range(t_len):
            ret = ret * self.gamma + r[t]
            returns[t] = ret
            ret = ret.masked_fill(ended[t], 0.0)
        self.returns = ret
        var = self.rms.update_steps(returns)  # [T]: var(R) with each step's returns folded in
        out = (r / torch.sqrt(var[:, None] + EPS)).clamp(-CLIP, CLIP)
        return out.to(reward.device, torch.float32)

    def state_dict(self) -> dict[str, Any]:
        return {"rms": {k: v.clone() for k, v in self.rms.state_dict().items()},
                "returns": None if self.returns is None else self.returns.clone()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.rms.load_state_dict(state["rms"])
        self.returns = None if state["returns"] is None else state["returns"].clone()
