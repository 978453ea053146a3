"""PPO's hand-written update (agents/ppo/losses_fast.py + nn.mlp_fast) against autograd on the
losses of losses.py; the networks' own backward passes are tested in test_nn.py."""

import numpy as np
import pytest
import torch

from relayrl.agents.ppo.agent import PPOAgent
from relayrl.agents.ppo.config import PPOConfig
from relayrl.agents.ppo.policy import PPOPolicy
from relayrl.agents.ppo.update import HandWrittenPPOUpdate, PPOUpdate
from relayrl.specs import ArraySpec, DiscreteSpec

OBS = ArraySpec((3,), torch.float32)
BOX = ArraySpec((2,), torch.float32, np.array([-2.0, 0.0]), np.array([2.0, 1.0]))


def pair(action_spec, **kw):
    """Two agents in the same state: one on hand-written gradients, one on autograd."""
    cfg = PPOConfig(**{"hidden": [16, 16], "batch_size": 8, "n_epochs": 3, **kw})
    agents = []
    for hand_written in (True, False):
        torch.manual_seed(0)
        agents.append(PPOAgent(OBS, action_spec, cfg, torch.device("cpu"), np.random.default_rng(0), total_steps=100,
                               hand_written=hand_written))
    fast, slow = agents
    assert isinstance(fast.update, HandWrittenPPOUpdate) and type(slow.update) is PPOUpdate
    return fast, slow


def rollout(discrete: bool, seed: int, t: int = 5, b: int = 4):
    g = torch.Generator().manual_seed(seed)
    action = (torch.randint(0, 3, (1, t, b), generator=g) if discrete
              else torch.randn(1, t, b, 2, generator=g) * 1.5)
    done = torch.rand(1, t, b, generator=g)
    return {"obs": torch.randn(1, t, b, 3, generator=g), "action": action, "reward": torch.randn(1, t, b, generator=g),
            "next_obs": torch.randn(1, t, b, 3, generator=g), "terminated": done < 0.1, "truncated": done > 0.9}


@pytest.mark.parametrize("discrete", [True, False])
@pytest.mark.parametrize("options", [
    {},
    {"activation": "relu", "ent_coef": 0.01},
    {"activation": "elu", "normalize_advantage": False, "ent_coef": 0.1},
    {"activation": "leaky_relu"}, {"activation": "silu"}, {"activation": "gelu"},
    {"max_grad_norm": 0.0, "lr": 1e-2},
    {"max_grad_norm": 0.05, "clip_range": 0.02, "lr": 3e-2},  # clipped norms and many clipped ratios
    {"hidden": [], "ent_coef": 0.01},  # linear heads: no hidden layer to backpropagate through
])
def test_updates_equal_autograds(discrete, options):
    fast, slow = pair(DiscreteSpec(3) if discrete else BOX, **options)
    for seed in range(4):
        r = rollout(discrete, seed)
        mf, ms = fast.train(r), slow.train(r)
        for key in ms:
            assert torch.allclose(mf[key], ms[key], rtol=1e-4, atol=1e-6, equal_nan=True), key
        for a, b in zip(fast.net.parameters(), slow.net.parameters(), strict=True):
            assert torch.allclose(a, b, rtol=1e-4, atol=1e-6)
    assert fast.train_step == slow.train_step == 4 * 3 * 3
    assert 0.0 < float(ms["clip_fraction"]) or "clip_range" not in options


def test_shared_networks_and_value_clipping_stay_on_autograd():
    for kw in ({"shared": True}, {"clip_range_vf": 0.2}):
        cfg = PPOConfig(hidden=[8], **kw)
        agent = PPOAgent(OBS, DiscreteSpec(3), cfg, torch.device("cpu"), np.random.default_rng(0))
        assert type(agent.update) is PPOUpdate


@pytest.mark.parametrize("discrete", [True, False])
@pytest.mark.parametrize("shared", [False, True])
def test_collect_policy_on_numpy_acts_as_the_torch_path(discrete, shared):
    """The policy's NumPy forward pass (MLPInference) against the same network run by torch
    (wrapped so that the policy cannot see it is an MLP), with the same noise draws."""
    cfg = PPOConfig(hidden=[16, 16], shared=shared)
    agent = PPOAgent(OBS, DiscreteSpec(3) if discrete else BOX, cfg, torch.device("cpu"), np.random.default_rng(0))
    fast = agent.collect_policy()
    net = agent.policy_network()
    slow = PPOPolicy(torch.nn.Sequential(net), net.log_std, None if discrete else (BOX.low, BOX.high),
                     torch.device("cpu"), False, np.random.default_rng(0))
    fast.rng = np.random.default_rng(0)
    with torch.no_grad():
        for layer in net.mlp.layers:  # logits far from uniform, so that samples differ by state
            layer.weight.mul_(30.0)
    obs = torch.randn(64, 3)
    a, b = fast.sample(obs), slow.sample(obs)  # the draws, before clipping
    assert a.dtype == b.dtype and a.shape == b.shape
    assert torch.equal(a, b) if discrete else torch.allclose(a, b, atol=1e-5)
