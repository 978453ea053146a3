"""`algo = "bptt"`: TorchRL's Pendulum tutorial (agents/bptt/bptt.py) as a trainer the direct
driver (training/direct.py) runs into a run directory.

No replay, actor or learner: each iteration differentiates the mean reward of `batch_size`
rollouts of `rollout_steps` steps. A row goes to metrics.jsonl every `eval.interval` env steps
(an iteration is batch_size * rollout_steps env steps; 0: one row, at the end, over the last 50
iterations) with the window's mean rollout return as `average_return`, so `relayrl plot` draws
the tutorial's curve. Runs take seconds to minutes,
so they are not checkpointed; the policy is saved at the end (`relayrl.load_policy` reads it).
"""

from __future__ import annotations

import dataclasses
import time
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from relayrl.agents.bptt.bptt import BpttLog, train_bptt
from relayrl.config import algo_defaults
from relayrl.errors import ConfigError
from relayrl.nn import MLP

if TYPE_CHECKING:
    from relayrl.config import Config

ENV_ID = "relayrl/StatelessPendulum-v0"
FINAL_WINDOW = 50  # iterations the learning targets average over


def check_config(c: Config) -> int:
    """Iterations the config asks for; ConfigError for settings BPTT cannot honour."""
    if c.env.id != ENV_ID:
        raise ConfigError(f"algo='bptt' trains through {ENV_ID} only; env.id={c.env.id!r} is not valid")
    _check_unused(c)
    per_iteration = c.agent.batch_size * c.agent.rollout_steps
    if c.train.total_steps < per_iteration:
        raise ConfigError(f"train.total_steps={c.train.total_steps} is less than one iteration "
                          f"(agent.batch_size * agent.rollout_steps = {per_iteration} env steps)")
    return c.train.total_steps // per_iteration


# The [env], [train] and [eval] keys a bptt run reads; the others set the actor-learner loop it
# does not run, so a value other than the default is refused rather than silently ignored.
USED = ("env.id", "train.total_steps", "train.torch_threads", "eval.interval")
WHY_UNUSED = {
    "env.num_envs": "each iteration rolls out agent.batch_size pendulums as one batch (set agent.batch_size)",
    "eval.episodes": "it runs no evaluation episodes (a metrics row averages the training rollouts of its "
                     "eval.interval env steps)",
}


def _check_unused(c: Config) -> None:
    defaults = algo_defaults(c.algo)
    for name in ("env", "train", "eval"):
        section, default_section = getattr(c, name), getattr(defaults, name)
        for f in dataclasses.fields(section):
            key, value, default = f"{name}.{f.name}", getattr(section, f.name), getattr(default_section, f.name)
            if key not in USED and value != default:
                why = WHY_UNUSED.get(key, f"it trains through {ENV_ID} by itself, without the env copies, "
                                          "collection, checkpoints and evaluations this key sets")
                raise ConfigError(f"{key}={value!r} does not apply to algo='bptt': {why}; leave it at {default!r}")


def policy_state(net: MLP, hidden: list[int], env_steps: int) -> dict[str, Any]:
    """The trained Tanh MLP as kind "clamped_mlp" (export.py)."""
    return {"kind": "clamped_mlp", "obs_dim": net.layers[0].in_features, "hidden": list(hidden),
            "action_dim": net.layers[-1].out_features, "activation": "tanh",
            "state_dict": {k: v.detach().cpu() for k, v in net.state_dict().items()},
            "action_low": np.array([-2.0], np.float32), "action_high": np.array([2.0], np.float32),
            "env_id": ENV_ID, "env_steps": env_steps}


def train(config: Config, device: torch.device, write_row: Callable[[dict[str, Any]], None],
          add_scalar: Callable[[str, float, int], None], say: Callable[[str], None] | None,
          stop: Callable[[], bool] | None = None) -> dict[str, Any]:
    """Train; rows go to `write_row`, per-iteration scalars to `add_scalar`, a console line per
    row to `say` (None: quiet); `stop()` True ends training after the current iteration.
    Returns the trained policy's state (`policy_state`), at the env step it reached."""
    c, a = config, config.agent
    iterations = check_config(c)
    per_iteration = a.batch_size * a.rollout_steps
    # iterations per metrics row; eval.interval 0: one row, at the end, over the last FINAL_WINDOW
    rows_every = max(1, c.eval.interval // per_iteration) if c.eval.interval > 0 else iterations
    window: deque[BpttLog] = deque(maxlen=None if c.eval.interval > 0 else FINAL_WINDOW)
    history: list[BpttLog] = []
    t0 = time.perf_counter()

    def on_iteration(entry: BpttLog) -> None:
        window.append(entry)
        history.append(entry)
        step = (entry.iteration + 1) * per_iteration
        add_scalar("charts/mean_reward", entry.mean_reward, step)
        add_scalar("charts/last_reward", entry.last_reward, step)
        if len(window) < rows_every and entry.iteration + 1 < iterations:
            return
        mean_r = float(np.mean([w.mean_reward for w in window]))
        row = {"step": step, "train_step": entry.iteration + 1, "average_return": mean_r * a.rollout_steps,
               "average_episode_length": float(a.rollout_steps), "bptt/mean_reward": mean_r,
               "bptt/last_reward": float(np.mean([w.last_reward for w in window])),
               "losses/loss": -mean_r, "losses/grad_norm": float(np.mean([w.grad_norm for w in window])),
               "lr": entry.lr, "wall_time_s": round(time.perf_counter() - t0, 3)}
        if entry.iteration + 1 == iterations:
            tail = history[-FINAL_WINDOW:]
            row["bptt/final50_mean_reward"] = float(np.mean([h.mean_reward for h in tail]))
            row["bptt/final50_last_reward"] = float(np.mean([h.last_reward for h in tail]))
        write_row(row)
        window.clear()
        if say is not None:
            say(f"iteration {entry.iteration + 1:>5}/{iterations} | mean reward {mean_r:7.3f} | last reward "
                f"{row['bptt/last_reward']:7.3f} | {row['wall_time_s']:6.1f}s")

    result = train_bptt(a, on_iteration, iterations=iterations, seed=c.seed, device=str(device),
                        torch_threads=c.train.torch_threads, stop=stop)
    return policy_state(result.policy, a.hidden, len(result.mean_reward) * per_iteration)
