"""The conv Q-network for frames (Mnih et al. 2015)."""

from __future__ import annotations

import torch
from torch import nn

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
