"""DQN's gradient step on the online network, chosen once when the agent is built: the
autograd reference (`dqn_loss` + `backward()`); on CUDA, the reference replayed from a CUDA
graph (`nn.graphed`); on CPU, its hand-written twin for MLP Q-networks
(`losses_fast.dqn_loss_and_grads`: the same values, with less per-update overhead). Both
subclass the reference; tests/test_dqn_fast.py and
tests/test_graphed.py compare them with it."""

from __future__ import annotations

from typing import Any, cast

import torch
from torch import nn

from relayrl.agents.dqn.config import DQNConfig
from relayrl.agents.dqn.losses import dqn_loss
from relayrl.agents.dqn.losses_fast import dqn_loss_and_grads
from relayrl.nn import MLP, mlp_fast
from relayrl.nn.graphed import GraphedStep, compiled, cuda_graphs_enabled
from relayrl.optim import FastAdam
from relayrl.types import Batch

Tensor = torch.Tensor


class DQNUpdate:
    """The reference: `dqn_loss`, autograd, torch's norm clip, the optimizer step. The agent
    counts steps and moves the target network; an update does the rest."""

    def __init__(self, online: nn.Module, target: nn.Module | None, optimizer: FastAdam, cfg: DQNConfig) -> None:
        self.online, self.target, self.optimizer, self.cfg = online, target, optimizer, cfg
        self.params = list(online.parameters())
        self.loss = compiled(self.losses)  # the losses themselves unless RELAYRL_COMPILE asks (nn/graphed.py)

    def losses(self, batch: Batch, target_q: Tensor | None) -> tuple[Tensor, dict[str, Tensor]]:
        cfg = self.cfg
        return dqn_loss(self.online, self.target, batch, double=cfg.double, loss=cfg.loss,
                        huber_delta=cfg.huber_delta, target_q=target_q)

    def __call__(self, batch: Batch, target_q: Tensor | None) -> dict[str, Tensor]:
        """One loss, gradient, clip and optimizer step; `target_q` [N, A]: the target network's
        Q(next_obs, .) computed ahead (None: computed here)."""
        cfg = self.cfg
        loss, metrics = self.loss(batch, target_q)
        self.optimizer.zero_grad()
        loss.backward()
        if cfg.grad_clip > 0:
            metrics["grad_norm"] = torch.nn.utils.clip_grad_norm_(self.params, cfg.grad_clip)
        self.optimizer.step()
        return metrics

    def target_q(self, next_obs: Tensor) -> Tensor:
        """The target network's Q-values [N, A] of `next_obs` (called without gradients)."""
        assert self.target is not None
        return self.target(next_obs)


class HandWrittenDQNUpdate(DQNUpdate):
    """`DQNUpdate` for MLP Q-networks (`mlp_fast.supports`), with the gradients written into
    one flat buffer (so clipping is one norm and one multiply)."""

    def __init__(self, online: nn.Module, target: nn.Module | None, optimizer: FastAdam, cfg: DQNConfig) -> None:
        super().__init__(online, target, optimizer, cfg)
        # make_update checked mlp_fast.supports: a plain MLP (the target its copy)
        self.fast_online = mlp_fast.MLPFast(cast(MLP, online))
        self.fast_target = mlp_fast.MLPFast(cast(MLP, target)) if target is not None else None
        self.flat_grad, self.grads = mlp_fast.grad_buffers(online)

    def __call__(self, batch: Batch, target_q: Tensor | None) -> dict[str, Tensor]:
        cfg = self.cfg
        _, metrics, grads = dqn_loss_and_grads(self.fast_online, self.fast_target, batch, double=cfg.double,
                                               loss=cfg.loss, huber_delta=cfg.huber_delta, target_q=target_q,
                                               out=self.grads)
        if cfg.grad_clip > 0:
            metrics["grad_norm"] = mlp_fast.clip_flat_grad_norm_(self.flat_grad, cfg.grad_clip)
        self.optimizer.step(grads)
        return metrics

    def target_q(self, next_obs: Tensor) -> Tensor:
        assert self.fast_target is not None
        return self.fast_target.forward(next_obs)[0]


class GraphedDQNUpdate(DQNUpdate):
    """`DQNUpdate` replayed from a CUDA graph per batch signature (`nn.graphed.GraphedStep`)."""

    def __init__(self, online: nn.Module, target: nn.Module | None, optimizer: FastAdam, cfg: DQNConfig) -> None:
        super().__init__(online, target, optimizer, cfg)
        self.graphed = GraphedStep(self._reference)

    def _reference(self, *fields: Tensor | None) -> dict[str, Tensor]:
        return DQNUpdate.__call__(self, Batch(*cast("tuple[Any, ...]", fields[:-1])), fields[-1])  # as passed below

    def __call__(self, batch: Batch, target_q: Tensor | None) -> dict[str, Tensor]:
        return self.graphed(*batch, target_q)


def make_update(online: nn.Module, target: nn.Module | None, optimizer: FastAdam, cfg: DQNConfig,
                hand_written: bool = True) -> DQNUpdate:
    """The step of the module doc (RELAYRL_CUDA_GRAPHS=0 turns graphs off, `hand_written=False` the twin)."""
    if cuda_graphs_enabled(next(online.parameters()).device):
        return GraphedDQNUpdate(online, target, optimizer, cfg)
    twin = hand_written and mlp_fast.supports(online)
    return (HandWrittenDQNUpdate if twin else DQNUpdate)(online, target, optimizer, cfg)
