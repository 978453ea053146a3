"""Policies: schedules, epsilon-greedy rates, random actions, the lean CPU inference paths."""

import numpy as np
import pytest
import torch

from relayrl.config_fields import ACTIVATION_NAMES
from relayrl.nn import MLP
from relayrl.nn.mlp_fast import MLPInference
from relayrl.policies import EpsilonGreedyPolicy, GreedyPolicy, RandomPolicy
from relayrl.schedules import linear_schedule
from relayrl.specs import ArraySpec, DiscreteSpec


def test_linear_schedule_end_points_and_constant():
    f = linear_schedule(1.0, 0.1, 100)
    assert f(0) == 1.0 and f(50) == pytest.approx(0.55) and f(100) == pytest.approx(0.1) and f(10**6) == 0.1
    assert linear_schedule(1.0, 0.2, 0)(0) == 0.2


@pytest.mark.parametrize("activation", ACTIVATION_NAMES)
@pytest.mark.parametrize("rows", [7, 50])  # the NumPy path and the addmm path (see MLPInference)
def test_cpu_inference_matches_the_module(activation, rows):
    torch.manual_seed(0)
    net = MLP(4, [256, 256], 3, activation)
    obs = torch.randn(rows, 4)
    cpu = MLPInference(net)
    assert cpu.suits_numpy(rows) == (rows == 7)
    with torch.no_grad():
        np.testing.assert_allclose(cpu(obs), net(obs).numpy(), rtol=1e-5, atol=1e-6)
        assert torch.equal(GreedyPolicy(net, torch.device("cpu"))(obs), net(obs).argmax(1))
    # both paths read the parameters' memory: they follow in-place weight updates
    greedy = GreedyPolicy(net, torch.device("cpu"))
    with torch.no_grad():
        net.layers[-1].bias.add_(torch.tensor([0.0, 0.0, 1e6]))
    assert (greedy(obs) == 2).all()
    with torch.no_grad():
        net.load_state_dict({k: torch.zeros_like(v) for k, v in net.state_dict().items()})
    assert (cpu(obs) == 0).all()


def test_cpu_inference_leaves_the_parameters_alone():
    net = MLP(4, [256, 256], 2)  # requires_grad on: the lean path must neither fail nor build a graph
    before = [p.detach().clone() for p in net.parameters()]
    out = MLPInference(net)(torch.randn(64, 4))
    assert out.shape == (64, 2) and out.dtype == np.float32
    assert all(torch.equal(a, p) for a, p in zip(before, net.parameters(), strict=True))
    assert all(p.grad is None for p in net.parameters())


def test_numpy_path_serves_small_batches_and_torch_large_ones():
    wide = MLPInference(MLP(3, [256, 256], 2))  # ~67k multiply-adds per row
    assert wide.suits_numpy(1) and wide.suits_numpy(7) and not wide.suits_numpy(8) and not wide.suits_numpy(32)
    narrow = MLPInference(MLP(4, [64, 64], 2))
    assert narrow.suits_numpy(64) and not narrow.suits_numpy(1024)
    torch.manual_seed(0)
    net = MLP(4, [256, 256], 3)
    greedy = GreedyPolicy(net, torch.device("cpu"))
    for rows in (1, 7, 8, 64):  # both sides of the switch give the network's argmax
        obs = torch.randn(rows, 4)
        with torch.no_grad():
            assert torch.equal(greedy(obs), net(obs).argmax(1))


def test_epsilon_greedy_explores_at_the_scheduled_rate_per_batch_element():
    net = MLP(4, [8], 4)
    with torch.no_grad():
        net.layers[-1].bias.copy_(torch.tensor([0.0, 0.0, 0.0, 100.0]))  # greedy action is 3
    step = [0]
    policy = EpsilonGreedyPolicy(GreedyPolicy(net, torch.device("cpu")), 4, linear_schedule(1.0, 0.2, 1000),
                                 lambda: step[0], np.random.default_rng(0))
    obs = torch.zeros(7, 4)
    actions = torch.cat([policy(obs) for _ in range(2000)])
    assert abs((actions != 3).float().mean().item() - 0.75) < 0.02  # eps 1: 3 of 4 random differ
    step[0] = 10_000
    actions = torch.cat([policy(obs) for _ in range(2000)])
    assert abs((actions != 3).float().mean().item() - 0.2 * 0.75) < 0.02


def test_random_policy_respects_specs():
    rng = np.random.default_rng(0)
    a = RandomPolicy(DiscreteSpec(3), rng)(torch.zeros(500, 1))
    assert a.shape == (500,) and set(a.tolist()) == {0, 1, 2}
    spec = ArraySpec((2,), torch.float32, np.array([-1.0, 0.0]), np.array([1.0, 5.0]))
    c = RandomPolicy(spec, rng)(torch.zeros(500, 1))
    assert c.shape == (500, 2) and c.dtype == torch.float32
    assert (c[:, 0] >= -1).all() and (c[:, 1] <= 5).all() and c[:, 1].max() > 4


@pytest.mark.parametrize("kwargs,steps,wrappers,line,given", [
    ({}, 50, [], "CartPole-v1 is the env the policy was trained on: env.max_episode_steps=50 applies", 0),
    ({"sutton_barto_reward": True}, 50, [], "CartPole-v1 is the env the policy was trained on: env.kwargs "
                                            "{'sutton_barto_reward': True} applies", 30),  # the caller's limit
    ({}, 50, [], None, 30),  # nothing of the run applies: nothing to say
    ({"sutton_barto_reward": True}, 50, [], "env.kwargs {'sutton_barto_reward': True} and env.max_episode_steps=50 "
                                            "apply", 0),
    ({}, 0, ["m:W"], "CartPole-v1 is the env the policy was trained on: its env.wrappers ['m:W'] do not apply "
                     "(a policy file runs no code; from its run directory, or with --trust-code, they do)", 0),
])
def test_evaluating_on_the_env_a_policy_records_says_what_of_its_run_applies(kwargs, steps, wrappers, line, given):
    from relayrl.evaluation import named_env
    from relayrl.loaded_policy import LoadedPolicy

    policy = LoadedPolicy.__new__(LoadedPolicy)  # only what named_env reads
    policy.env_id, policy.env_kwargs, policy.max_episode_steps, policy.env_wrappers = (
        "CartPole-v1", kwargs, steps, wrappers)
    said: list[str] = []
    env = named_env("CartPole-v1", policy, 2, given, say=said.append)
    env.close()
    assert (len(said) == 1 and line in said[0]) if line else not said, said
