"""Networks built from specs. Shared by agents; each agent picks heads and sizes."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

ACTIVATIONS: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "relu": torch.relu,
    "tanh": torch.tanh,
    "elu": F.elu,
}


class MLP(nn.Module):
    """in_dim -> hidden... -> out_dim with an activation between layers, none after the last.

    One module whose forward calls F.linear directly: calling nn.Linear modules costs about
    18 us of Python hook machinery per layer on CPU, more than the matmul of a small net.
    Parameters live in `layers` (plain nn.Linear), so state_dicts look as usual.
    """

    def __init__(self, in_dim: int, hidden: list[int], out_dim: int, activation: str = "relu") -> None:
        super().__init__()
        sizes = [in_dim, *hidden, out_dim]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:], strict=False))
        self.activation = activation
        self._act = ACTIVATIONS[activation]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() != 2:
            x = x.reshape(x.shape[0], -1)  # [B, *obs_shape] -> [B, obs_dim]
        if x.dtype != torch.float32:
            x = x.float()
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            x = F.linear(x, layer.weight, layer.bias)
            if i < last:
                x = self._act(x)
        return x


# (out_channels, kernel, stride) per conv, then the hidden dense width: Mnih et al. 2015
# ("Human-level control through deep RL"). The Mario tutorial's net is this one layer for
# layer (3136 -> 512 -> actions on 84x84 inputs), so "mario_cnn" names the same architecture.
NATURE_CONVS = ((32, 8, 4), (64, 4, 2), (64, 3, 1))
NATURE_HIDDEN = 512
CONV_NETWORKS = ("nature_cnn", "mario_cnn")


class ConvQNet(nn.Module):
    """[B, C, H, W] frames (uint8 0..255, or floats already in [0, 1]) -> [B, out_dim].

    Takes uint8 stacks straight from the replay and scales them by 1/255 inside, so frames
    cross to the GPU and sit in memory as one byte per pixel. Channels C = stacked frames.
    """

    def __init__(self, obs_shape: tuple[int, ...], out_dim: int,
                 convs: tuple[tuple[int, int, int], ...] = NATURE_CONVS, hidden: int = NATURE_HIDDEN) -> None:
        super().__init__()
        if len(obs_shape) != 3:
            raise ValueError(f"a conv Q-network needs image observations [C, H, W], got {list(obs_shape)}")
        self.obs_shape = tuple(obs_shape)
        layers: list[nn.Module] = []
        channels = obs_shape[0]
        for out_channels, kernel, stride in convs:
            layers += [nn.Conv2d(channels, out_channels, kernel, stride), nn.ReLU()]
            channels = out_channels
        self.convs = nn.Sequential(*layers, nn.Flatten())
        with torch.no_grad():  # the flattened size for this frame size (3136 at 84x84)
            flat = self.convs(torch.zeros(1, *obs_shape)).shape[1]
        self.head = nn.Sequential(nn.Linear(flat, hidden), nn.ReLU(), nn.Linear(hidden, out_dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dtype == torch.uint8:
            x = x.float().mul_(1.0 / 255.0)  # [B, C, H, W] in [0, 1]
        elif x.dtype != torch.float32:
            x = x.float()
        return self.head(self.convs(x))  # [B, out_dim]


def tf_agents_init_(net: MLP) -> None:
    """TF-Agents' QNetwork init, as in its DQN tutorial.

    Hidden: VarianceScaling(scale=2, fan_in, truncated normal), zero bias. Head: uniform
    (-0.03, 0.03) weights and bias -0.2, so initial Q-values start small and equal.
    """
    layers = list(net.layers)
    for layer in layers[:-1]:
        # Keras truncates at 2 std and divides std by 0.8796 to keep the variance.
        std = math.sqrt(2.0 / layer.in_features) / 0.87962566103423978
        nn.init.trunc_normal_(layer.weight, std=std, a=-2 * std, b=2 * std)
        nn.init.zeros_(layer.bias)
    nn.init.uniform_(layers[-1].weight, -0.03, 0.03)
    nn.init.constant_(layers[-1].bias, -0.2)


_NP_ACTIVATIONS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "relu": lambda x: np.maximum(x, 0.0, out=x),
    "tanh": lambda x: np.tanh(x, out=x),
    "elu": lambda x: np.where(x > 0, x, np.expm1(np.minimum(x, 0.0))),
}


# Above this many multiply-adds per forward pass torch's CPU matmul (MKL's sgemm) beats NumPy's
# OpenBLAS; below it torch's per-op dispatch dominates. Measured crossovers (1 thread): 8 rows
# at width 256, ~48 at 128, ~64 at 64. [32, 256] x [256, 256] on one thread (2026-11-23): MKL
# 140-155 us, OpenBLAS 395-400 us, oneDNN's linear 240 us. (OpenBLAS on 2 threads takes ~80 us,
# but its threads spin on the core the envs step on and slow them as much.)
NUMPY_MAX_MACS = 500_000


class NumpyMLP:
    """CPU inference through NumPy views that share memory with an MLP's parameters.

    For the small batches an actor feeds (one env, a few rows) a NumPy forward pass is 3-4x
    faster than torch's on CPU, where per-op dispatch costs more than the math; `suits(rows)`
    says whether a batch is small enough. The views follow in-place updates (optimizer steps,
    load_state_dict), so they never go stale.
    """

    def __init__(self, net: MLP) -> None:
        if any(p.device.type != "cpu" or p.dtype != torch.float32 for p in net.parameters()):
            raise ValueError("NumpyMLP needs a float32 MLP on the CPU")
        self.layers = [(layer.weight.detach().numpy().T, layer.bias.detach().numpy()) for layer in net.layers]
        self._act = _NP_ACTIVATIONS[net.activation]
        self.max_rows = max(1, NUMPY_MAX_MACS // sum(w.size for w, _ in self.layers))

    def suits(self, rows: int) -> bool:
        return rows <= self.max_rows

    def __call__(self, x: np.ndarray) -> np.ndarray:
        if x.ndim != 2:
            x = x.reshape(x.shape[0], -1)  # [B, *obs_shape] -> [B, obs_dim]
        if x.dtype != np.float32:
            x = x.astype(np.float32)
        last = len(self.layers) - 1
        for i, (w_t, b) in enumerate(self.layers):
            x = x @ w_t + b  # [B, out]
            if i < last:
                x = self._act(x)
        return x


_INPLACE_ACTIVATIONS: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "relu": torch.relu_,
    "tanh": torch.tanh_,
    "elu": F.elu_,
}


class CpuMLP:
    """An actor's inference-only forward pass of a float32 MLP on the CPU: [B, in] tensor ->
    [B, out] NumPy array.

    Small batches go through `NumpyMLP`. The rest go through torch.addmm on detached views of
    the weights, with in-place activations: at 32 rows through (256, 256) that is ~150 us
    against the module call's ~210-230 us (2026-11-23, one thread), as it skips the module
    call, the parameter lookups and F.linear's dispatch, and allocates one tensor per layer
    instead of two. The views share memory with the parameters, so they follow in-place updates
    (optimizer steps, load_state_dict, weight pulls) and never go stale.
    """

    def __init__(self, net: MLP) -> None:
        self.numpy = NumpyMLP(net)  # checks float32 and CPU
        self.layers = [(layer.weight.detach().t(), layer.bias.detach()) for layer in net.layers]  # [in, out], [out]
        self._act_ = _INPLACE_ACTIVATIONS[net.activation]

    def __call__(self, obs: torch.Tensor) -> np.ndarray:
        if self.numpy.suits(obs.shape[0]):
            return self.numpy(obs.numpy())
        x = obs.reshape(obs.shape[0], -1) if obs.dim() != 2 else obs  # [B, *obs_shape] -> [B, obs_dim]
        if x.dtype != torch.float32:
            x = x.float()
        x = x.detach()  # no graph (the weights are detached views already)
        last = len(self.layers) - 1
        for i, (w_t, b) in enumerate(self.layers):
            x = torch.addmm(b, x, w_t)  # [B, out]
            if i < last:
                x = self._act_(x)
        return x.numpy()
