"""Hand-written DQN gradients (agents/dqn/losses_fast.py) against dqn_loss + autograd; the MLP's
own backward is tested in test_nn.py."""

import copy

import numpy as np
import pytest
import torch

from relayrl.agents.dqn import DQNAgent, DQNConfig, dqn_loss
from relayrl.agents.dqn.losses_fast import dqn_loss_and_grads
from relayrl.agents.dqn.update import DQNUpdate, HandWrittenDQNUpdate
from relayrl.config_fields import ACTIVATION_NAMES
from relayrl.nn import MLP
from relayrl.nn.mlp_fast import clip_flat_grad_norm_, grad_buffers
from relayrl.specs import ArraySpec, DiscreteSpec
from relayrl.types import Batch


def make_batch(n=32, obs_dim=5, actions=3, weighted=False, seed=0):
    g = torch.Generator().manual_seed(seed)
    return Batch(
        obs=torch.randn(n, obs_dim, generator=g),
        action=torch.randint(actions, (n,), generator=g),
        reward=torch.randn(n, generator=g) * 3,  # large TD errors: both Huber branches
        next_obs=torch.randn(n, obs_dim, generator=g),
        discount=(torch.rand(n, generator=g) > 0.2).float() * 0.99,
        weight=torch.rand(n, generator=g) + 0.5 if weighted else None,
    )


def nets(activation, with_target, hidden=(16, 8)):
    torch.manual_seed(1)
    online = MLP(5, list(hidden), 3, activation)
    target = None
    if with_target:
        target = copy.deepcopy(online).requires_grad_(False)
        with torch.no_grad():
            for p in target.parameters():
                p.add_(torch.randn_like(p) * 0.1)  # a stale target differs from the online net
    return online, target


@pytest.mark.parametrize("activation", ACTIVATION_NAMES)
@pytest.mark.parametrize("loss", ["mse", "huber"])
@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("mode", ["dqn", "double", "no_target"])
def test_gradients_equal_autograd(activation, loss, weighted, mode):
    online, target = nets(activation, with_target=mode != "no_target")
    batch = make_batch(weighted=weighted)
    kw = dict(double=mode == "double", loss=loss, huber_delta=0.7)
    ref_loss, ref_metrics = dqn_loss(online, target, batch, **kw)
    ref_loss.backward()
    value, metrics, grads = dqn_loss_and_grads(online, target, batch, **kw)
    assert torch.allclose(value, ref_loss, rtol=1e-6, atol=1e-7)
    for key in ("loss", "q", "td_error"):
        assert torch.allclose(metrics[key], ref_metrics[key], rtol=1e-6, atol=1e-6), key
    params = list(online.parameters())
    assert len(grads) == len(params)
    for g, p in zip(grads, params, strict=True):
        assert g.shape == p.shape
        assert torch.allclose(g, p.grad, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("mode", ["dqn", "double"])
def test_a_linear_q_networks_gradients_equal_autograd(mode):
    online, target = nets("relu", with_target=True, hidden=())  # agent.hidden=[]: one linear layer
    batch = make_batch()
    ref_loss, _ = dqn_loss(online, target, batch, double=mode == "double")
    ref_loss.backward()
    _, _, grads = dqn_loss_and_grads(online, target, batch, double=mode == "double")
    assert [g.shape for g in grads] == [(3, 5), (3,)]
    for g, p in zip(grads, online.parameters(), strict=True):
        assert torch.allclose(g, p.grad, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("max_norm", [1e-3, 1e3])  # clipping active / inactive
def test_clipping_equals_torch(max_norm):
    online, target = nets("relu", with_target=True)
    batch = make_batch()
    dqn_loss(online, target, batch, double=False)[0].backward()
    ref_norm = torch.nn.utils.clip_grad_norm_(online.parameters(), max_norm)
    flat, views = grad_buffers(online)
    _, _, grads = dqn_loss_and_grads(online, target, batch, double=False, out=views)
    assert all(g is v for g, v in zip(grads, views, strict=True))
    norm = clip_flat_grad_norm_(flat, max_norm)
    assert torch.allclose(norm, ref_norm, rtol=1e-6)
    for g, p in zip(grads, online.parameters(), strict=True):
        assert torch.allclose(g, p.grad, rtol=1e-5, atol=1e-8)


def train_agent(fast, double, steps=30, seed=0, **kw):
    torch.manual_seed(seed)
    cfg = DQNConfig(**{"hidden": [32, 32], "lr": 1e-3, "double": double, "target_update_period": 7,
                       "grad_clip": 1.0, **kw})
    agent = DQNAgent(ArraySpec((5,), torch.float32), DiscreteSpec(3), cfg, torch.device("cpu"),
                     np.random.default_rng(seed), hand_written=fast)
    assert type(agent.update) is (HandWrittenDQNUpdate if fast else DQNUpdate)
    metrics = [agent.train(make_batch(weighted=i % 2 == 1, seed=i)) for i in range(steps)]
    return agent, metrics


@pytest.mark.parametrize("double", [False, True])
@pytest.mark.parametrize("options", [{}, {"loss": "mse", "grad_clip": 0.0}, {"tau": 0.1, "target_update_period": 1},
                                     {"target_update_period": 1}])  # the last: no target network
def test_agent_updates_equal_autograd_path(double, options):
    fast_agent, fast_metrics = train_agent(True, double, **options)
    ref_agent, ref_metrics = train_agent(False, double, **options)
    assert set(fast_metrics[-1]) == set(ref_metrics[-1]) >= {"loss", "q", "td_error"}
    for a, b in zip(fast_agent.online.parameters(), ref_agent.online.parameters(), strict=True):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6)
    assert torch.allclose(fast_metrics[-1]["td_error"], ref_metrics[-1]["td_error"], rtol=1e-4, atol=1e-5)


def test_agent_is_deterministic():
    _, a = train_agent(True, True)
    _, b = train_agent(True, True)
    for x, y in zip(a, b, strict=True):
        assert all(torch.equal(x[k], y[k]) for k in x)


@pytest.mark.parametrize("double", [False, True])
def test_target_q_given_stands_for_the_target_network(double):
    online, target = nets("relu", with_target=True)
    batch = make_batch()
    with torch.no_grad():
        given, shifted = target(batch.next_obs), target(batch.next_obs) + 1.0
    for fn in (lambda q: dqn_loss(online, target, batch, double=double, target_q=q)[0],
               lambda q: dqn_loss_and_grads(online, target, batch, double=double, target_q=q)[0]):
        assert torch.allclose(fn(given), fn(None), rtol=1e-6)
        assert not torch.allclose(fn(shifted), fn(None), rtol=1e-3)  # the given values are used


def test_both_updates_give_the_target_network_s_q_values():
    for fast in (True, False):
        agent, _ = train_agent(fast, False, steps=3)
        obs = torch.randn(6, 5)
        with torch.no_grad():
            assert torch.allclose(agent.update.target_q(obs), agent.target(obs), atol=1e-6)
