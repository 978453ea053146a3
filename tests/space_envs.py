"""An env for every observation and action space kind, importable as `space_envs:Spaces`.

Each step the observation shows a target in {0, 1}; the reward is 1 when the action "says"
that target (its first entry, >= 0.5 for Box actions), else 0. Episodes end after `length`
steps. What the observation looks like depends on `obs` (the target is in every kind).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from torch import nn

OBS_KINDS = ("box", "box2d", "box_i32", "box_bool", "discrete", "multi_discrete", "multi_binary", "image", "image_hwc",
             "board", "dict", "tuple")
ACTION_KINDS = ("discrete", "box", "box_scalar", "box2d", "box_fixed", "box_f16", "box_unbounded", "multi_discrete",
                "multi_discrete_i32", "multi_binary")


def observation_space(kind: str) -> gym.Space:
    return {
        "box": spaces.Box(-1.0, 1.0, (3,), np.float32),
        "box2d": spaces.Box(-1.0, 1.0, (2, 3), np.float32),
        "box_i32": spaces.Box(0, 10, (3,), np.int32),  # stored as int64: exports take int32
        "box_bool": spaces.Box(0, 1, (3,), bool),
        "discrete": spaces.Discrete(4),
        "multi_discrete": spaces.MultiDiscrete([2, 3]),
        "multi_binary": spaces.MultiBinary(3),
        "image": spaces.Box(0, 255, (1, 12, 12), np.uint8),
        "image_hwc": spaces.Box(0, 255, (10, 10, 3), np.uint8),
        "image_chw": spaces.Box(0, 255, (3, 10, 10), np.uint8),  # image_hwc's conv weights: not in OBS_KINDS
        "board": spaces.Box(0, 2, (8, 8), np.uint8),  # cell codes, not pixels: an MLP on the numbers
        "image_float": spaces.Box(0.0, 1.0, (12, 12, 1), np.float32),  # frames scaled already: not in OBS_KINDS
        "dict": spaces.Dict({"frame": spaces.Box(0, 255, (1, 8, 8), np.uint8), "cell": spaces.Discrete(4),
                             "pos": spaces.Box(-1.0, 1.0, (2,), np.float32)}),
        "tuple": spaces.Tuple((spaces.Discrete(2), spaces.Box(-1.0, 1.0, (2,), np.float64))),
    }[kind]


def action_space(kind: str) -> gym.Space:
    return {"discrete": spaces.Discrete(2), "box": spaces.Box(-1.0, 1.0, (2,), np.float32),
            "box_scalar": spaces.Box(-1.0, 1.0, (), np.float32), "box2d": spaces.Box(-1.0, 1.0, (2, 2), np.float32),
            "box_fixed": spaces.Box(np.array([-1.0, 0.5], np.float32), np.array([1.0, 0.5], np.float32)),  # low == high
            "box_f16": spaces.Box(-1.0, 1.0, (2,), np.float16),  # policies act in float32
            # float64 bounds whose float32 roundings (-0.30000001, 0.30000001) lie outside them: not in ACTION_KINDS
            "box_f64": spaces.Box(np.array([-0.3, -0.7]), np.array([0.3, 0.7]), (2,), np.float64),
            "box_unbounded": spaces.Box(np.array([-np.inf, -1.0], np.float32), np.array([np.inf, 1.0], np.float32)),
            "multi_discrete": spaces.MultiDiscrete([2, 3]),
            "multi_discrete_i32": spaces.MultiDiscrete([2, 3], np.int32),
            "multi_binary": spaces.MultiBinary(2)}[kind]


class Spaces(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, obs: str = "box", act: str = "discrete", length: int = 8, nan_at: int = 0,
                 render_mode: str | None = None) -> None:
        self.obs_kind, self.act_kind, self.length = obs, act, length
        self.nan_at, self.steps = nan_at, 0  # nan_at > 0: a Dict observation's "pos" turns NaN at that step
        self.observation_space = observation_space(obs)
        self.action_space = action_space(act)
        self.render_mode = render_mode
        self.t = 0
        self.target = 0

    def _obs(self):
        g = self.target
        k = self.obs_kind
        if k == "box":
            return np.array([g, 0.5, -0.5], np.float32)
        if k == "box2d":
            return np.array([[g, 0, 0], [0, 0, -g]], np.float32)
        if k == "box_i32":
            return np.array([g, 5, 10], np.int32)
        if k == "box_bool":
            return np.array([g, 1 - g, self.t % 2], bool)
        if k == "discrete":
            return 2 * g + self.t % 2
        if k == "multi_discrete":
            return np.array([g, self.t % 3])
        if k == "multi_binary":
            return np.array([g, 1 - g, self.t % 2], np.int8)
        if k in ("image", "image_hwc", "image_chw"):
            img = np.zeros(self.observation_space.shape, np.uint8)
            img[..., :4, :] = 255 * g if k != "image_hwc" else 0
            if k == "image_hwc":
                img[:4] = 255 * g
            return img
        if k == "image_float":
            img = np.zeros(self.observation_space.shape, np.float32)
            img[:4] = g
            return img
        if k == "board":
            board = np.zeros((8, 8), np.uint8)
            board[self.t % 8, 0], board[0, 7] = 1, 2 * g
            return board
        if k == "dict":
            frame = np.full((1, 8, 8), 255 * g, np.uint8)
            pos = np.array([g, np.nan if 0 < self.nan_at <= self.steps else 0.0], np.float32)
            return {"cell": 2 * g, "frame": frame, "pos": pos}
        return (g, np.array([0.0, g], np.float64))

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        self.target = int(self.np_random.integers(2))
        return self._obs(), {}

    def step(self, action):
        if self.act_kind.startswith("box"):  # an action of another shape is a bug (Gymnasium does not check)
            assert np.shape(action) == self.action_space.shape, (np.shape(action), self.action_space)
            # an array, as Box.contains takes it (a NumPy scalar draws Gymnasium's casting warning)
            assert isinstance(action, np.ndarray), (type(action), self.action_space)
        if self.act_kind != "discrete":  # nor of another dtype: an env may check action_space.contains
            assert np.asarray(action).dtype == self.action_space.dtype, (np.asarray(action).dtype, self.action_space)
        a = np.asarray(action).reshape(-1)
        said = int(a[0] >= 0.5) if self.act_kind.startswith("box") else int(a[0])
        reward = float(said == self.target)
        self.t += 1
        self.steps += 1
        self.target = int(self.np_random.integers(2))
        return self._obs(), reward, self.t >= self.length, False, {}

    def render(self):
        return np.full((16, 16, 3), 120 * self.target, np.uint8)


class FlatEncoder(nn.Module):
    """A user's own encoder (agent.encoder = "space_envs:FlatEncoder"): every entry of the
    observation flattened as floats, then one linear layer (its input size found on first use)."""

    built = 0  # how many were made (a costly encoder should be made once per load)

    def __init__(self, space: gym.Space) -> None:
        super().__init__()
        FlatEncoder.built += 1
        self.space = space
        self.linear = nn.LazyLinear(8)

    def forward(self, obs):
        parts = obs.values() if isinstance(obs, dict) else [obs]
        return torch.relu(self.linear(torch.cat([p.reshape(p.shape[0], -1).float() for p in parts], dim=1)))


class WithSpareLayer(FlatEncoder):
    """FlatEncoder with a layer its forward pass leaves out (an SB3 extractor's habit): no grad."""

    def __init__(self, space: gym.Space) -> None:
        super().__init__(space)
        self.spare = nn.Linear(4, 4)


class NormedEncoder(nn.Module):
    """A user's encoder with BatchNorm1d and Dropout, which act otherwise in train and eval mode;
    `calls` records (training, grad enabled, batch) of each forward pass."""

    calls: list[tuple[bool, bool, int]] = []

    def __init__(self, space: gym.Space) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Flatten(), nn.LazyLinear(8), nn.BatchNorm1d(8), nn.Dropout(0.1), nn.ReLU())

    def forward(self, obs):
        NormedEncoder.calls.append((self.training, torch.is_grad_enabled(), obs.shape[0]))
        return self.net(obs.float())


class Branching(FlatEncoder):
    """A Python branch on a tensor's value: it trains, but torch.export cannot trace it."""

    def forward(self, obs):
        out = super().forward(obs)
        return out * 2 if out.abs().max() > 3 else out


class NoFeatures(FlatEncoder):
    """A slice that leaves no feature: [B, 0]."""

    def forward(self, obs):
        return super().forward(obs)[:, :0]


def takes_no_space() -> nn.Module:  # make() written without the observation space
    return nn.Identity()


def reads_a_missing_entry(space: gym.spaces.Dict) -> nn.Module:  # a bug of the maker's own
    return nn.Linear(space["missing"].shape[0], 4)


class FloatConv(nn.Module):
    """A conv net ported from SB3, which scales frames to floats before its extractor."""

    def __init__(self, space: gym.Space) -> None:
        super().__init__()
        self.conv = nn.Conv2d(1, 4, 3)

    def forward(self, obs):
        return self.conv(obs["frame"]).flatten(1)


def not_a_module(space: gym.Space) -> int:
    return 3


def wrong_shape(space: gym.Space) -> nn.Module:
    return nn.Identity()  # a Dict's entries, or [B, *shape]: not [B, features]


class Squeezed(FlatEncoder):
    """A common slip: squeeze() drops the batch dimension of a batch of one."""

    def forward(self, obs):
        return super().forward(obs).squeeze()


def stacked(env: gym.Env) -> gym.Env:
    """Three frames stacked along a new first side, as Gymnasium stacks RGB frames: [3, H, W, C]."""
    return gym.wrappers.FrameStackObservation(env, 3)
