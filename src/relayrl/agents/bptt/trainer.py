"""`algo = "bptt"`: TorchRL's Pendulum tutorial (agents/bptt/bptt.py) as a trainer that the
direct driver (training/direct.py) runs into a run directory.

No replay, actor or learner: each iteration differentiates the mean reward of `batch_size`
rollouts of `rollout_steps` steps. The driver evaluates the policy as every run's is and adds
the means of `scalars` over the iterations since its last row (the tutorial's curve), with
`final_scalars` in the last row. Runs take seconds to minutes, so they are not checkpointed;
the policy is saved at the end (`relayrl.load_policy` reads it).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from relayrl.agents.bptt.bptt import BpttLog, train_bptt
from relayrl.agents.bptt.config import ENV_ID, BpttConfig
from relayrl.nn import MLP

FINAL_WINDOW = 50  # iterations the tutorial's learning targets average over


def policy_state(net: MLP, hidden: list[int], env_steps: int) -> dict[str, Any]:
    """The Tanh MLP as kind "clamped_mlp" (export.py), at `env_steps`."""
    return {"kind": "clamped_mlp", "obs_dim": net.layers[0].in_features, "hidden": list(hidden),
            "action_dim": net.layers[-1].out_features, "activation": "tanh",
            "state_dict": {k: v.detach().cpu().clone() for k, v in net.state_dict().items()},
            "action_low": np.array([-2.0], np.float32), "action_high": np.array([2.0], np.float32),
            "env_id": ENV_ID, "env_steps": env_steps}


def scalars(entry: BpttLog) -> dict[str, float]:
    """An iteration's scalars, as metrics rows and TensorBoard name them."""
    return {"bptt/mean_reward": entry.mean_reward, "bptt/last_reward": entry.last_reward,
            "losses/loss": -entry.mean_reward, "losses/grad_norm": entry.grad_norm,
            "charts/learning_rate": entry.lr}


def final_scalars(history: list[dict[str, float]]) -> dict[str, float]:
    """The tutorial's targets, over the last FINAL_WINDOW iterations' `scalars`."""
    tail = history[-FINAL_WINDOW:]
    return {f"bptt/final{FINAL_WINDOW}_{k}": float(np.mean([h[f"bptt/{k}"] for h in tail]))
            for k in ("mean_reward", "last_reward")}


def train(cfg: BpttConfig, iterations: int, seed: int, device: torch.device, torch_threads: int,
          on_iteration: Callable[[int, dict[str, float], Callable[[], dict[str, Any]]], None],
          stop: Callable[[], bool]) -> dict[str, Any]:
    """Train for `iterations`; `on_iteration(env_steps, scalars, state)` after each, and once at
    env step 0 with no scalars, where `state()` is the policy's state at that step. `stop()` True
    ends training after the current iteration. Returns the trained policy's state."""
    per_iteration = cfg.iteration_steps()
    training: MLP | None = None  # the network train_bptt made, trained in place

    def at_start(net: MLP) -> None:
        nonlocal training
        training = net
        on_iteration(0, {}, lambda: policy_state(net, cfg.hidden, 0))

    def each(entry: BpttLog) -> None:
        steps = (entry.iteration + 1) * per_iteration
        assert training is not None  # on_start ran before the first iteration
        net = training
        on_iteration(steps, scalars(entry), lambda: policy_state(net, cfg.hidden, steps))

    result = train_bptt(cfg, each, iterations=iterations, seed=seed, device=str(device), torch_threads=torch_threads,
                        stop=stop, on_start=at_start)
    return policy_state(result.policy, cfg.hidden, len(result.mean_reward) * per_iteration)
