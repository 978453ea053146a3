"""The data passed between layers: one batched env step, and a batch of transitions."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

# `env.info_keys` values at episode ends: key -> float64 [B], NaN for copies whose episode
# did not end this step. None when no keys are asked for (the common case costs nothing).
EpisodeInfo = dict[str, np.ndarray]


class StepOutput(NamedTuple):
    """What a batched env returns from `step`. All tensors have leading dim B (num_envs).

    `next_obs` is the true observation after the action, also at an episode's end; `obs` is
    the observation the next action is taken from: equal to `next_obs` except where an
    episode ended and the env was reset. Keeping both means no transition ever pairs an
    auto-reset observation with the previous episode's action.
    """

    next_obs: torch.Tensor  # [B, *obs_shape]
    reward: torch.Tensor  # [B] float32
    terminated: torch.Tensor  # [B] bool: the MDP ended, do not bootstrap
    truncated: torch.Tensor  # [B] bool: cut by a time limit, bootstrap from next_obs
    obs: torch.Tensor  # [B, *obs_shape]
    episode_info: EpisodeInfo | None = None


class Transition(NamedTuple):
    """One batched step as seen by observers (metrics, replay writers)."""

    obs: torch.Tensor  # [B, *obs_shape]
    action: torch.Tensor  # [B, *act_shape]
    reward: torch.Tensor  # [B]
    next_obs: torch.Tensor  # [B, *obs_shape]
    terminated: torch.Tensor  # [B] bool
    truncated: torch.Tensor  # [B] bool
    episode_info: EpisodeInfo | None = None  # for metrics; writers ignore it


class Batch(NamedTuple):
    """A sampled training batch."""

    obs: torch.Tensor  # [N, *obs_shape]
    action: torch.Tensor  # [N, *act_shape]
    reward: torch.Tensor  # [N]
    next_obs: torch.Tensor  # [N, *obs_shape]
    discount: torch.Tensor  # [N] gamma^n for bootstrapping, 0 where the episode terminated
    weight: torch.Tensor | None  # [N] importance weights; None means all ones (uniform replay)
