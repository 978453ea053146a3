"""Learner: samples batches from replay and runs the agent's gradient steps."""

from __future__ import annotations

import torch

from relayrl.core import Agent
from relayrl.replay import UniformReplay
from relayrl.types import Batch


class Learner:
    """agent + replay. `run(k)` takes k gradient steps; `last_metrics` holds the latest scalars."""

    def __init__(self, agent: Agent, replay: UniformReplay, batch_size: int, device: torch.device) -> None:
        self.agent = agent
        self.replay = replay
        self.batch_size = batch_size
        self.device = device
        self.last_metrics: dict[str, torch.Tensor] = {}

    def run(self, iterations: int) -> None:
        for _ in range(iterations):
            batch = self.replay.sample(self.batch_size)
            if self.device.type != "cpu":
                batch = Batch(*(None if x is None else x.to(self.device, non_blocking=True) for x in batch))
            self.last_metrics = self.agent.train(batch)

    def scalar_metrics(self) -> dict[str, float]:
        """Latest training scalars as floats, named like CleanRL's `losses/...`."""
        out = {}
        for k, v in self.last_metrics.items():
            out[f"losses/{k}"] = float(v.abs().mean() if k == "td_error" else v.float().mean())
        return out
