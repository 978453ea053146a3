"""`algo = "bptt"`: TorchRL's Pendulum tutorial as a run directory (agents/bptt/bptt.py).

No replay, actor or learner: each iteration differentiates the mean reward of `batch_size`
rollouts of `rollout_steps` steps. A row goes to metrics.jsonl every `eval.interval` env steps
(an iteration is batch_size * rollout_steps env steps) with the window's mean rollout return as
`average_return`, so `relayrl plot` draws the tutorial's curve. Runs take seconds to minutes,
so they are not checkpointed; the policy is saved at the end (`relayrl.load_policy` reads it).
"""

from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np

from relayrl.agents.bptt.bptt import BpttLog, train_bptt
from relayrl.config import Config
from relayrl.errors import ConfigError
from relayrl.nn import MLP
from relayrl.policy_file import save_policy_file
from relayrl.training.assembly import RunResult, resolve_device
from relayrl.training.run_dir import MetricsLog, RunDir

ENV_ID = "relayrl/StatelessPendulum-v0"
FINAL_WINDOW = 50  # iterations the learning targets average over


def check_bptt_config(c: Config) -> int:
    """Iterations the config asks for; ConfigError for settings BPTT cannot honour."""
    if c.env.id != ENV_ID:
        raise ConfigError(f"algo='bptt' trains through {ENV_ID} only; env.id={c.env.id!r} is not valid")
    per_iteration = c.agent.batch_size * c.agent.rollout_steps
    if c.train.total_steps < per_iteration:
        raise ConfigError(f"train.total_steps={c.train.total_steps} is less than one iteration "
                          f"(agent.batch_size * agent.rollout_steps = {per_iteration} env steps)")
    return c.train.total_steps // per_iteration


def policy_state(net: MLP, hidden: list[int], env_steps: int) -> dict[str, Any]:
    """The trained Tanh MLP as kind "clamped_mlp" (export.py)."""
    return {"kind": "clamped_mlp", "obs_dim": net.layers[0].in_features, "hidden": list(hidden),
            "action_dim": net.layers[-1].out_features, "activation": "tanh",
            "state_dict": {k: v.detach().cpu() for k, v in net.state_dict().items()},
            "action_low": np.array([-2.0], np.float32), "action_high": np.array([2.0], np.float32),
            "env_id": ENV_ID, "env_steps": env_steps}


def run_bptt(config: Config, rd: RunDir, progress: bool = True) -> dict[str, Any]:
    """Train, writing rows to metrics.jsonl; returns the last row."""
    from torch.utils.tensorboard import SummaryWriter

    from relayrl.training.assembly import log_config

    c, a = config, config.agent
    iterations = check_bptt_config(c)
    per_iteration = a.batch_size * a.rollout_steps
    rows_every = max(1, c.eval.interval // per_iteration)  # iterations per metrics row
    window: list[BpttLog] = []
    history: list[BpttLog] = []
    log, tb = MetricsLog(rd.metrics), SummaryWriter(str(rd.tb))
    log_config(tb, config)
    t0 = time.perf_counter()
    last: dict[str, Any] = {}

    def on_iteration(entry: BpttLog) -> None:
        nonlocal last
        window.append(entry)
        history.append(entry)
        step = (entry.iteration + 1) * per_iteration
        tb.add_scalar("charts/mean_reward", entry.mean_reward, step)
        tb.add_scalar("charts/last_reward", entry.last_reward, step)
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
        log.write(row)
        window.clear()
        last = row
        if progress:
            print(f"iteration {entry.iteration + 1:>5}/{iterations} | mean reward {mean_r:7.3f} | last reward "
                  f"{row['bptt/last_reward']:7.3f} | {row['wall_time_s']:6.1f}s", file=sys.stderr, flush=True)

    try:
        result = train_bptt(a, on_iteration, iterations=iterations, seed=c.seed, device=str(resolve_device(c.device)),
                            torch_threads=c.train.torch_threads)
    finally:
        log.close()
        tb.close()
    save_policy_file(policy_state(result.policy, a.hidden, iterations * per_iteration), rd.policy / "policy.pt")
    return last


class BpttRun:
    """The registry's own run for algo = "bptt": the config is checked when the run is made,
    before anything is written; runs are not resumable (Algorithm.resumable)."""

    def __init__(self, config: Config, rd: RunDir, progress: bool = True) -> None:
        check_bptt_config(config)
        self.config, self.rd, self.progress = config, rd, progress

    def run(self, resume: bool = False) -> RunResult:
        return RunResult(self.rd.root, run_bptt(self.config, self.rd, self.progress))
