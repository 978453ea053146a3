"""SAC's hand-written updates (agents/sac/losses_fast.py + nn.mlp_fast) against autograd on the
losses of losses.py; the networks' own backward passes are tested in test_nn.py."""

import numpy as np
import pytest
import torch

from relayrl.agents.sac import SACAgent, SACConfig
from relayrl.agents.sac.update import HandWrittenSACUpdate, SACUpdate
from relayrl.config_fields import ACTIVATION_NAMES
from relayrl.specs import ArraySpec
from relayrl.types import Batch

OBS = ArraySpec((3,), torch.float32, -np.ones(3), np.ones(3))
ACT = ArraySpec((2,), torch.float32, np.array([-2.0, 0.0]), np.array([2.0, 1.0]))


def pair(**kw):
    """Two agents in the same state: one on hand-written gradients, one on autograd."""
    cfg = SACConfig(actor_hidden=[16, 16], critic_hidden=[16, 16], batch_size=8, **kw)
    agents = []
    for hand_written in (True, False):
        torch.manual_seed(0)
        agents.append(SACAgent(OBS, ACT, cfg, torch.device("cpu"), np.random.default_rng(0),
                               hand_written=hand_written))
    fast, slow = agents
    assert isinstance(fast.update, HandWrittenSACUpdate) and type(slow.update) is SACUpdate
    return fast, slow


def batch(n=8, seed=0, weighted=False):
    g = torch.Generator().manual_seed(seed)
    action = torch.stack([torch.rand(n, generator=g) * 4 - 2, torch.rand(n, generator=g)], dim=1)
    weight = torch.rand(n, generator=g) + 0.5 if weighted else None
    return Batch(torch.randn(n, 3, generator=g), action, torch.randn(n, generator=g),
                 torch.randn(n, 3, generator=g), torch.full((n,), 0.99), weight)


def params(agent):
    return [p.detach().clone() for p in [*agent.actor.parameters(), *agent.critic.parameters(),
                                         *agent.target_critic.parameters(), agent.log_alpha]]


@pytest.mark.parametrize("activation", ACTIVATION_NAMES)
@pytest.mark.parametrize("options", [
    {},
    {"weighted": True},
    {"grad_clip": 0.05},  # small enough that every step is clipped
    {"autotune_alpha": False},
    {"log_std_min": -0.2, "log_std_max": 0.1},  # most log-stds clamped: their gradient is cut
])
def test_updates_equal_autograds(activation, options):
    options = dict(options)
    weighted = options.pop("weighted", False)
    fast, slow = pair(activation=activation, **options)
    for step in range(5):
        b = batch(seed=step, weighted=weighted)
        mf, ms = fast.train(b), slow.train(b)
        for key in ms:
            assert torch.allclose(mf[key], ms[key].detach(), rtol=1e-5, atol=1e-6), key
        for a, b_ in zip(params(fast), params(slow), strict=True):
            assert torch.allclose(a, b_, rtol=1e-5, atol=1e-6)
    assert fast.gen.get_state().equal(slow.gen.get_state())  # the same noise draws
