"""PPO's continuous-action and normalisation options: rollouts keep the unclipped Gaussian
sample, the tanh-squashed Gaussian's log-probability, running observation statistics and
reward scaling against NumPy references, and a run with all of them on whose saved, loaded
and exported policies act as the agent does and which resumes bit for bit."""

from __future__ import annotations

import math
import os
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from test_resume import assert_same_state, comparable, cut_back

import relayrl
from relayrl.agents.ppo.agent import PPOAgent
from relayrl.agents.ppo.config import PPOConfig
from relayrl.agents.ppo.distributions import log_prob_entropy
from relayrl.agents.ppo.normalize import ObsNorm, RewardScaler, RunningMeanStd
from relayrl.agents.ppo.policy import deterministic_module
from relayrl.errors import ConfigError
from relayrl.export import load_policy_state
from relayrl.replay import Table
from relayrl.replay.rollouts import RolloutWriter
from relayrl.specs import ArraySpec
from relayrl.training.actor import Actor
from relayrl.training.checkpoint import load_latest_checkpoint
from relayrl.types import StepOutput

BOUNDS = (np.array([-0.1, -1.0], np.float32), np.array([0.1, 3.0], np.float32))


def agent(**kw) -> PPOAgent:
    spec = ArraySpec((2,), torch.float32, *BOUNDS)
    cfg = PPOConfig(**{"hidden": [8], "batch_size": 4, "n_epochs": 2, **kw})
    return PPOAgent(ArraySpec((3,), torch.float32), spec, cfg, torch.device("cpu"), np.random.default_rng(0), 100)


class RecordingEnv:
    """Two copies of a 3-d observation; records the actions it receives."""

    num_envs = 2

    def __init__(self) -> None:
        self.observation_spec = ArraySpec((3,), torch.float32)
        self.action_spec = ArraySpec((2,), torch.float32, *BOUNDS)
        self.received: list[torch.Tensor] = []
        self.gen = torch.Generator().manual_seed(0)

    def reset(self, seed: int | None = None) -> torch.Tensor:
        return torch.randn(2, 3, generator=self.gen)

    def step(self, action: torch.Tensor) -> StepOutput:
        self.received.append(action.clone())
        obs = torch.randn(2, 3, generator=self.gen)
        no = torch.zeros(2, dtype=torch.bool)
        return StepOutput(obs, torch.ones(2), no, no, obs)

    def close(self) -> None:
        pass


@pytest.mark.parametrize("squash", ["clip", "tanh"])
def test_rollout_keeps_the_gaussian_sample_and_the_env_gets_it_bounded(squash):
    a = agent(log_std_init=1.5, squash=squash)
    env, table = RecordingEnv(), Table.queue("rollouts", 1)
    actor = Actor(env, a.collect_policy(), [RolloutWriter(table, 8)])
    actor.collect(16)
    item, _ = table.sample(1)
    stored = torch.as_tensor(item["action"][0]).reshape(16, 2)
    received = torch.cat(env.received)
    low, high = (torch.from_numpy(b) for b in BOUNDS)
    assert ((stored < low) | (stored > high)).any()  # std e^1.5: many samples lie outside the bounds
    expected = (torch.minimum(torch.maximum(stored, low), high) if squash == "clip"
                else (high + low) / 2 + (high - low) / 2 * torch.tanh(stored))
    assert torch.equal(received, expected) and (received >= low).all() and (received <= high).all()
    # PPO's log-probabilities are those of the stored samples: the Gaussian's, not the bounded action's
    obs = torch.as_tensor(item["obs"][0]).reshape(16, 3)
    logp, _, _ = a.evaluate_actions(obs, stored)
    with torch.no_grad():
        mean = a.net.policy(obs)
    gaussian = torch.distributions.Normal(mean, a.net.policy.log_std.exp()).log_prob(stored).sum(-1)
    if squash == "clip":
        assert torch.allclose(logp, gaussian, atol=1e-5)
        clipped = torch.distributions.Normal(mean, a.net.policy.log_std.exp()).log_prob(received).sum(-1)
        assert not torch.allclose(logp, clipped)
    else:  # the Gaussian's minus log |d action / d u|
        u = stored.double()  # (1 - tanh(u)^2 in float32 loses its digits for |u| of a few units)
        jac = torch.log((high - low).double() / 2 * (1 - torch.tanh(u).square())).sum(-1)
        assert torch.allclose(logp.double(), gaussian.double() - jac, atol=1e-4)
    a.train({k: torch.as_tensor(v) for k, v in item.items()})


def test_tanh_log_prob_by_hand_and_against_torch_transforms():
    mean, log_std, u, scale = torch.tensor([[0.2]]), torch.tensor([math.log(0.5)]), torch.tensor([[0.7]]), 2.0
    logp, entropy = log_prob_entropy(mean, log_std, u, torch.tensor([scale]))
    # N(0.7; 0.2, 0.5): z = 1, log N = -1/2 - log 0.5 - log sqrt(2 pi); minus log(2 (1 - tanh(0.7)^2))
    by_hand = -0.5 - math.log(0.5) - 0.5 * math.log(2 * math.pi) - math.log(scale * (1 - math.tanh(0.7) ** 2))
    assert logp.item() == pytest.approx(by_hand, abs=1e-6) and by_hand == pytest.approx(-0.964398, abs=1e-6)
    assert entropy.item() == pytest.approx(-by_hand, abs=1e-6)  # SB3's estimate: -log pi
    td = torch.distributions
    torch.manual_seed(0)
    m, ls, x = torch.randn(6, 2), torch.tensor([-0.3, 0.4]), torch.randn(6, 2) * 2
    loc, sc = torch.tensor([1.0, 0.0]), torch.tensor([2.0, 0.5])
    ref = td.TransformedDistribution(td.Normal(m, ls.exp()), [td.TanhTransform(), td.AffineTransform(loc, sc)])
    logp, _ = log_prob_entropy(m, ls, x, sc)
    assert torch.allclose(logp, ref.log_prob(loc + sc * torch.tanh(x)).sum(-1), atol=1e-4)
    far, _ = log_prob_entropy(torch.zeros(1, 1), torch.zeros(1), torch.tensor([[30.0]]), torch.ones(1))
    assert torch.isfinite(far).all()  # tanh(30) is 1 in float32: the log-det stays finite


def test_tanh_deterministic_action_is_the_squashed_mean_in_every_form():
    a = agent(squash="tanh")
    with torch.no_grad():
        a.net.policy.mlp.layers[-1].bias.copy_(torch.tensor([3.0, -0.5]))
    obs = torch.randn(5, 3)
    with torch.no_grad():
        mean = a.net.policy(obs)
    low, high = (torch.from_numpy(b) for b in BOUNDS)
    expected = (high + low) / 2 + (high - low) / 2 * torch.tanh(mean)
    assert torch.allclose(a.eval_policy()(obs), expected)
    state = a.policy_state()
    assert state["squash"] == "tanh" and torch.allclose(deterministic_module(state)(obs), expected)
    with pytest.raises(ConfigError, match="agent.squash"):
        PPOConfig(squash="sigmoid").validate()


def pooled(data: np.ndarray, prior_count: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance of the rows of `data` pooled with the prior (mean 0, var 1)."""
    n = data.shape[0]
    mean = data.sum(0) / (n + prior_count)
    var = (prior_count * (1.0 + mean**2) + ((data - mean) ** 2).sum(0)) / (n + prior_count)
    return mean, var


def test_running_stats_and_obs_normalisation_match_numpy():
    rng = np.random.default_rng(0)
    batches = [rng.normal(3.0, 2.0, (n, 4)) * [1, 10, 0.1, 1] for n in (1, 7, 50, 3)]
    norm = ObsNorm(4)
    for x in batches:
        norm.update(torch.from_numpy(x).float())
    data = np.concatenate([x.astype(np.float32) for x in batches]).astype(np.float64)
    mean, var = pooled(data)
    assert np.allclose(norm.mean.numpy(), mean, rtol=1e-12) and np.allclose(norm.var.numpy(), var, rtol=1e-10)
    assert norm.count.item() == pytest.approx(len(data) + 1e-4)
    obs = np.vstack([data[:5], [[1e6, -1e6, 0, 3]]]).astype(np.float32)  # the last row is clipped
    expected = np.clip((obs - mean) / np.sqrt(var + 1e-8), -10, 10).astype(np.float32)
    assert np.allclose(norm(torch.from_numpy(obs)).numpy(), expected, atol=1e-6)
    assert norm(torch.from_numpy(obs))[-1, :2].tolist() == [10.0, -10.0]
    square = ObsNorm(4)  # a [2, 2] Box: the same statistics, per entry of the flattened observation
    for x in batches:
        square.update(torch.from_numpy(x).float().reshape(-1, 2, 2))
    assert torch.equal(square.mean, norm.mean) and torch.equal(square.var, norm.var)
    assert torch.equal(square(torch.from_numpy(obs).reshape(-1, 2, 2)), norm(torch.from_numpy(obs)))
    scalar = RunningMeanStd()
    scalar.update(torch.tensor([1.0, 2.0, 4.0]))
    assert scalar.mean.item() == pytest.approx(pooled(np.array([1.0, 2.0, 4.0]))[0])


def brute_force_scaled(reward: np.ndarray, done: np.ndarray, gamma: float) -> np.ndarray:
    """SB3's VecNormalize reward scaling step by step, with var(R) the pooled variance of every
    discounted return seen so far (every copy, every step) recomputed from scratch."""
    t_len, b = reward.shape
    ret, seen, out = np.zeros(b), [], np.zeros((t_len, b))
    for t in range(t_len):
        ret = ret * gamma + reward[t]
        seen.extend(ret)
        _, var = pooled(np.array(seen))
        out[t] = np.clip(reward[t] / np.sqrt(var + 1e-8), -10, 10)
        ret[done[t]] = 0.0
    return out


def test_reward_scaling_matches_a_brute_force_reference_over_episode_ends():
    rng = np.random.default_rng(2)
    t_len, b = 12, 3
    reward = rng.normal(1.0, 3.0, (2 * t_len, b)).astype(np.float32)
    done = rng.random((2 * t_len, b)) < 0.2
    done[t_len - 1, 0] = True  # an episode ends on a rollout's last step
    scaler = RewardScaler(0.9)
    got = [scaler(torch.from_numpy(reward[i:i + t_len]), torch.from_numpy(done[i:i + t_len]))
           for i in (0, t_len)]  # two rollouts in a row: the returns carry over
    expected = brute_force_scaled(reward.astype(np.float64), done, 0.9)
    assert np.allclose(torch.cat(got).numpy(), expected, rtol=1e-6)
    copy = RewardScaler(0.9)
    copy.load_state_dict(scaler.state_dict())
    r, d = torch.ones(2, b), torch.zeros(2, b, dtype=torch.bool)
    assert torch.equal(copy(r, d), scaler(r, d))


NORMALISED = ["env.id=toy_envs:Reach", "env.num_envs=4", "train.total_steps=1536", "train.collect_steps=256",
              "agent.batch_size=64", "agent.n_epochs=2", "agent.lr=3e-3", "eval.interval=512",
              "eval.episodes=5", "train.checkpoint_interval=512", "agent.squash=tanh", "agent.normalize_obs=true",
              "agent.normalize_reward=true", "agent.shared=true"]


@pytest.fixture(scope="module")
def normalised_run(tmp_path_factory):
    cfg = relayrl.load_config("ppo-cartpole", NORMALISED, seed=4)
    root = tmp_path_factory.mktemp("norm") / "full"
    relayrl.train(cfg, root, progress=False)
    return cfg, root


def test_normalised_run_resumes_bit_exact(normalised_run, tmp_path):
    cfg, root = normalised_run
    cut_back(root, tmp_path / "resumed")
    relayrl.train(cfg, tmp_path / "resumed", resume=True, progress=False)
    assert comparable(tmp_path / "resumed") == comparable(root)
    assert_same_state(root, tmp_path / "resumed")
    full, resumed = (load_latest_checkpoint(d / "checkpoints")["agent"]["reward_scaler"]
                     for d in (root, tmp_path / "resumed"))
    assert torch.equal(full["returns"], resumed["returns"])
    assert all(torch.equal(full["rms"][k], resumed["rms"][k]) for k in full["rms"])


def test_normalised_policy_saved_loaded_exported_and_pulled_acts_as_the_agent(normalised_run, tmp_path):
    cfg, root = normalised_run
    ckpt = load_latest_checkpoint(root / "checkpoints")
    a = PPOAgent(ArraySpec((2,), torch.float32), ArraySpec((2,), torch.float32, -2 * np.ones(2, np.float32),
                                                          2 * np.ones(2, np.float32)),
                 cfg.agent, torch.device("cpu"), np.random.default_rng(0), cfg.train.total_steps)
    a.load_state_dict(ckpt["agent"])
    stats = a.net.policy.obs_norm
    assert stats.count.item() == pytest.approx(cfg.train.total_steps + 1e-4)  # every rollout's observations
    # The acting copy pulled the statistics with the weights: it collected the last rollout
    # with those of every rollout before it (the agent took that rollout in after training on it).
    pulled_count = ckpt["actor"]["puller"]["params"][-1]
    assert pulled_count.item() == pytest.approx(cfg.train.total_steps - cfg.train.collect_steps + 1e-4)
    obs = torch.randn(9, 2) * 3
    expected = a.eval_policy()(obs)
    state = load_policy_state(root)
    assert state["obs_mean"] == stats.mean.tolist() and state["squash"] == "tanh"
    assert torch.equal(relayrl.load_policy(root)(obs), expected)
    program = torch.export.load(relayrl.export_policy(root, tmp_path / "policy.pt2")).module()
    assert torch.allclose(program(obs), expected, atol=1e-6)
    ort = pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    session = ort.InferenceSession(str(relayrl.export_policy(root, tmp_path / "policy.onnx", format="onnx")),
                                   providers=["CPUExecutionProvider"])
    assert np.allclose(session.run(None, {"obs": obs.numpy()})[0], expected.numpy(), atol=1e-5)


@pytest.mark.parametrize("preset", ["ppo-lunarlander", "ppo-lunarlander-continuous"])
def test_lunarlander_presets_without_box2d_say_which_extra_in_one_line(preset, cli_env, tmp_path):
    fake = tmp_path / "site" / "Box2D"  # an installed-but-broken Box2D: importing it fails, as when it is missing
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError('No module named Box2D')\n")
    env = {**cli_env, "PYTHONPATH": str(fake.parent) + os.pathsep + cli_env["PYTHONPATH"]}
    r = subprocess.run([sys.executable, "-m", "relayrl", "train", preset, "--run-dir", str(tmp_path / "z")],
                       capture_output=True, text=True, env=env, timeout=300)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0] == ("relayrl: error: env.id='LunarLander-v3' needs "
                        "Gymnasium's box2d dependencies: pip install -e \".[box2d]\" in relayrl's folder")


def test_ppo_builds_linear_heads_for_an_empty_hidden_list_and_refuses_a_zero_size():
    net = agent(hidden=[]).net
    assert [layer.weight.shape for layer in net.policy.mlp.layers] == [(2, 3)]
    assert [layer.weight.shape for layer in net.critic.layers] == [(1, 3)]
    with pytest.raises(ConfigError, match=r"agent.hidden=\[0\] is not valid; give positive sizes, or \[\] for"):
        PPOConfig(hidden=[0]).validate()


def test_a_linear_ppo_policy_acts_alike_through_the_numpy_forward_and_torch(tmp_path):
    config = relayrl.load_config("ppo", ["env.id=CartPole-v1", "agent.hidden=[]", "train.total_steps=4096",
                                         "eval.interval=4096", "eval.episodes=1"])
    relayrl.train(config, tmp_path / "run", progress=False)
    policy = relayrl.load_policy(tmp_path / "run")
    obs = torch.randn(64, 4)
    module = deterministic_module(load_policy_state(tmp_path / "run"))
    assert torch.equal(policy(obs), module(obs))


def test_ppo_initialises_its_own_conv_encoder_orthogonally_and_a_users_not_at_all():
    from relayrl.agents.ppo.networks import PPONetworks
    from relayrl.specs import DiscreteSpec
    frames = ArraySpec((4, 84, 84), torch.uint8, np.zeros((4, 84, 84)), np.full((4, 84, 84), 255))
    net = PPONetworks(frames, DiscreteSpec(6), [], "relu", True, 0.0, encoder="nature_cnn")
    layers = [m for m in net.policy.encoder.modules() if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear))]
    assert len(layers) == 4
    for layer in layers:  # rows orthogonal with norm sqrt(2): W W^T = 2 I
        w = layer.weight.detach().reshape(layer.weight.shape[0], -1).double()
        assert torch.allclose(w @ w.T, 2 * torch.eye(w.shape[0], dtype=torch.float64), atol=1e-4)
        assert not layer.bias.any()
    users = PPONetworks(ArraySpec((3,), torch.float32), DiscreteSpec(2), [], "relu", True, 0.0,
                        encoder="test_ppo_features:constant_encoder")
    assert (users.policy.encoder.module.weight == 0.5).all()


def constant_encoder(space) -> torch.nn.Module:
    """A user's encoder with its own initialisation."""
    layer = torch.nn.Linear(3, 5)
    torch.nn.init.constant_(layer.weight, 0.5)
    return layer


@pytest.mark.parametrize("space", [gym.spaces.Box(0, 1, (3,), bool), gym.spaces.Box(0, 100, (3,), np.int32)])
def test_normalize_obs_takes_bool_and_integer_boxes_as_floats(space):
    from relayrl.agents.ppo.normalize import ObsNorm

    norm = ObsNorm(3)
    obs = torch.as_tensor(np.stack([space.sample() for _ in range(8)]))
    norm.update(obs)
    z = norm(obs)
    expected = (obs.double() - norm.mean) / torch.sqrt(norm.var + 1e-8)
    assert z.dtype == torch.float32 and torch.allclose(z, expected.clamp(-10, 10).float(), atol=1e-5)
