"""PPO on a stateless torch env: env, policy, rollout and GAE stay torch tensors on the run's
device (the CPU here; a GPU run keeps them on the GPU the same way), the policy's noise comes
from a torch generator that checkpoints, and a fixed seed gives the same run, resumed or not.
The preset's learning test (`ppo-stateless-pendulum`) is slow."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_resume import assert_same_state, comparable, cut_back

import relayrl
from relayrl.agents.ppo.agent import PPOAgent
from relayrl.agents.ppo.config import PPOConfig
from relayrl.agents.ppo.device_policy import PPODevicePolicy
from relayrl.agents.ppo.policy import PPOPolicy
from relayrl.policy_file import load_policy_file
from relayrl.replay import rollouts
from relayrl.replay.rollouts_torch import TensorItemStorage, TensorRolloutWriter, tensor_rollout_queue
from relayrl.specs import ArraySpec, DiscreteSpec
from relayrl.training.run_dir import RunDir
from relayrl.types import Transition

ENVS, PER_ENV = 16, 8
TINY = [f"env.num_envs={ENVS}", f"train.collect_steps={ENVS * PER_ENV}", "train.total_steps=512",
        "eval.interval=256", "eval.episodes=2", "train.checkpoint_interval=256", "train.policy_save_interval=256",
        "train.log_interval=128", "agent.batch_size=32", "agent.n_epochs=2", "agent.hidden=[16]"]
CPU = torch.device("cpu")


def train(path, over=(), seed=0, resume=False):
    cfg = relayrl.load_config("ppo-stateless-pendulum", [*TINY, "device=cpu", *over], seed=seed)
    relayrl.train(cfg, path, resume=resume, progress=False)
    return RunDir(path).read_metrics()


def test_collection_keeps_tensors_on_the_device_without_numpy(tmp_path, monkeypatch):
    seen = []
    original = PPOAgent.train

    def spy(self, rollout):
        seen.append(rollout)
        return original(self, rollout)

    def no_numpy(x):
        raise AssertionError(f"the stateless rollout went through NumPy: {type(x)}")

    monkeypatch.setattr(PPOAgent, "train", spy)
    monkeypatch.setattr(rollouts, "to_numpy", no_numpy)  # the NumPy writer's only conversion
    rows = train(tmp_path / "run")
    assert len(seen) == 512 // (ENVS * PER_ENV) and rows[-1]["step"] == 512
    for r in seen:
        assert set(r) == set(rollouts.FIELDS)
        assert all(isinstance(v, torch.Tensor) and v.device == CPU for v in r.values())
        assert r["obs"].shape == (1, PER_ENV, ENVS, 3) and r["obs"].dtype == torch.float32
        assert r["action"].shape == (1, PER_ENV, ENVS, 1) and r["action"].dtype == torch.float32
        assert r["reward"].shape == (1, PER_ENV, ENVS) and r["truncated"].dtype == torch.bool
        # each step's next_obs is the next step's obs, except where an episode was cut
        cut = r["truncated"][0, :-1]
        same = (r["next_obs"][0, :-1] == r["obs"][0, 1:]).all(-1)
        assert bool((same | cut).all())
    assert seen[0]["obs"].data_ptr() != seen[1]["obs"].data_ptr()  # a fresh rollout each time


def test_tensor_queue_hands_out_the_written_tensors_once_and_checkpoints_live_items():
    table = tensor_rollout_queue("q", 1, CPU)
    writer = TensorRolloutWriter(table, 2, CPU)
    for t in range(2):
        obs = torch.full((3, 2), float(t))
        writer(Transition(obs, torch.zeros(3, 1), torch.ones(3), obs + 1, torch.zeros(3, dtype=torch.bool),
                          torch.zeros(3, dtype=torch.bool)))
    assert table.size == 1 and writer.pending() == 0
    state = table.state_dict()
    assert list(state["storage"]["items"]) == [0]  # the one live rollout, as CPU copies
    item, _ = table.sample(1)
    assert item["obs"][0, :, 0, 0].tolist() == [0.0, 1.0]
    assert item["obs"].data_ptr() == writer.arrays["obs"].data_ptr()  # no copy on the way
    assert table.size == 0 and table.state_dict()["storage"]["items"] == {}
    restored = tensor_rollout_queue("q", 1, CPU)
    restored.load_state_dict(state)
    assert restored.sample(1)[0]["reward"].equal(item["reward"])
    storage = TensorItemStorage(2, CPU)
    storage.write(np.array([1, 0]), {"x": torch.tensor([[1.0], [2.0]])})
    assert storage.read(np.array([0, 1]))["x"].tolist() == [[2.0], [1.0]]


@pytest.mark.parametrize("discrete", [False, True])
def test_device_policy_samples_the_collect_policys_distribution(discrete):
    """PPODevicePolicy draws from PPOPolicy's distribution: the same mean / std, or the same
    category frequencies, within sampling error; a restored generator repeats its draws."""
    act = DiscreteSpec(3) if discrete else ArraySpec((2,), torch.float32, np.full(2, -2.0), np.full(2, 2.0))
    agent = PPOAgent(ArraySpec((4,), torch.float32), act, PPOConfig(log_std_init=-1.0), CPU,
                     np.random.default_rng(0))
    obs = torch.randn(1, 4).expand(20_000, 4)
    device, host = agent.device_collect_policy(), agent.collect_policy()
    assert isinstance(device, PPODevicePolicy) and isinstance(host, PPOPolicy)
    state = device.state_dict()
    a, b = device.env_action(device(obs)), host(obs)
    assert a.device == CPU and a.shape == b.shape and a.dtype == b.dtype
    if discrete:
        fa, fb = (torch.bincount(x, minlength=3).double() / len(x) for x in (a, b))
        assert torch.allclose(fa, fb, atol=0.02)
    else:
        assert torch.allclose(a.mean(0), b.mean(0), atol=0.02) and torch.allclose(a.std(0), b.std(0), atol=0.02)
    device.load_state_dict(state)
    assert device.env_action(device(obs)).equal(a)
    if not discrete:  # the rollout keeps the Gaussian sample; the env gets it clipped
        u = torch.linspace(-5.0, 5.0, 22).reshape(11, 2)
        assert device.env_action(u).equal(u.clamp(-2.0, 2.0))


def test_same_seed_same_run_and_resume_is_bit_exact(tmp_path):
    a = train(tmp_path / "a", seed=3)
    b = train(tmp_path / "b", seed=3)
    assert comparable(tmp_path / "a") == comparable(tmp_path / "b") and "losses/approx_kl" in a[-1]
    weights = [load_policy_file(tmp_path / d / "policy" / "policy.pt")["state_dict"]["layers.0.weight"]
               for d in ("a", "b")]
    assert weights[0].equal(weights[1])
    assert train(tmp_path / "c", seed=4)[-1]["average_return"] != b[-1]["average_return"]
    cut_back(tmp_path / "a", tmp_path / "resumed")
    train(tmp_path / "resumed", seed=3, resume=True)
    assert comparable(tmp_path / "resumed") == comparable(tmp_path / "a")
    assert_same_state(tmp_path / "a", tmp_path / "resumed")


def test_envs_that_end_their_episodes_together_write_one_tensorboard_point_per_step(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    train(tmp_path, ["train.total_steps=6400", "eval.interval=0", "train.log_interval=3200"])  # 2 episodes each
    tb = EventAccumulator(str(tmp_path / "tb"), size_guidance={"scalars": 0})
    tb.Reload()
    lengths = [(e.step, e.value) for e in tb.Scalars("charts/episodic_length")]
    assert lengths == [(3200, 200.0), (6400, 200.0)]  # the 16 copies' 200-step episodes, not 16 points a step
    returns = [e.value for e in tb.Scalars("charts/episodic_return")]
    assert len(returns) == 2 and all(-3300 < r < 0 for r in returns)  # a mean of Pendulum returns (>= -16.3 a step)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_preset_ends_better_than_minus_300(tmp_path, seed):
    # 1,024 stateless Pendulums, 1.5M env steps; 200-step episodes, so returns are Pendulum-v1's.
    # BENCHMARKS.md has the seeds' runs.
    cfg = relayrl.load_config("ppo-stateless-pendulum", ["device=cpu"], seed=seed)
    relayrl.train(cfg, tmp_path / "r", progress=False)
    rows = RunDir(tmp_path / "r").read_metrics()
    assert rows[-1]["step"] >= 1_500_000 and rows[-1]["average_return"] > -300, rows
