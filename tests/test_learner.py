"""The learner's sampling: a uniform burst drawn in chunks gives the batches of one call each,
and chunks an agent prepares ahead (DQN's target Q-values) stay right across target updates."""

import numpy as np
import pytest
import torch

from relayrl.agents.dqn import DQNAgent, DQNConfig
from relayrl.agents.dqn.agent import PreparedBatch
from relayrl.core import Agent
from relayrl.replay import Fifo, MinSize, Table, TransitionWriter, Uniform
from relayrl.specs import ArraySpec, DiscreteSpec
from relayrl.training.learner import Learner
from relayrl.types import Transition


class Recorder(Agent):
    """An agent that only records the batches it is given."""

    def __init__(self) -> None:
        self.batches = []
        self.net = torch.nn.Linear(1, 1)

    def policy_network(self):
        return self.net

    def train(self, batch):
        self.batches.append(batch)
        return {"loss": torch.zeros(())}

    @property
    def train_step(self) -> int:
        return len(self.batches)


def table(obs_shape=(3,), dtype=torch.float32, n=500):
    t = Table("t", 1_000, Uniform(), Fifo(), MinSize(1), seed=7)
    w = TransitionWriter(t, 1, ArraySpec(obs_shape, dtype), DiscreteSpec(2), gamma=0.9, n_step=1, frame_stack=1)
    g = torch.Generator().manual_seed(0)
    no = torch.zeros(1, dtype=torch.bool)
    for i in range(n):
        obs = (torch.rand(1, *obs_shape, generator=g) * 255).to(dtype)
        w(Transition(obs, torch.tensor([i % 2]), torch.tensor([float(i)]), obs, no, no | (i % 50 == 49)))
    w.flush()
    return t


def test_a_uniform_burst_gives_the_batches_of_one_sample_call_each():
    agent = Recorder()
    Learner(agent, table(), batch_size=16, device=torch.device("cpu")).learn(300)  # chunks of 1, 128, 128, 43
    reference = table()
    expected = [reference.sample(16)[0] for _ in range(300)]
    assert len(agent.batches) == 300
    for got, want in zip(agent.batches, expected, strict=True):
        assert all(torch.equal(a, b) for a, b in zip(got[:5], want[:5], strict=True))
        assert got.obs.shape == (16, 3) and got.obs.is_contiguous()


def test_bursts_of_large_observations_are_drawn_in_small_chunks():
    t = table(obs_shape=(4, 84, 84), dtype=torch.uint8, n=200)
    calls = []
    sample = t.sample
    t.sample = lambda n, timeout=None: (calls.append(n), sample(n, timeout))[1]
    learner = Learner(Recorder(), t, batch_size=32, device=torch.device("cpu"))
    learner.learn(40)
    per_batch = 32 * 2 * 4 * 84 * 84  # obs and next_obs dominate
    assert learner._chunk == (32 << 20) // (per_batch + 32 * (8 + 4 + 4))
    assert calls[0] == 32 and set(calls[1:]) <= {32 * learner._chunk, 32 * (39 % learner._chunk)}
    assert sum(calls) == 40 * 32


@pytest.mark.parametrize("double", [False, True])
@pytest.mark.parametrize("fast", [True, False])
def test_target_q_computed_per_chunk_is_the_target_network_s_at_every_step(double, fast):
    """DQNAgent.prepare fills in target Q-values for a whole chunk; the learner must cut chunks
    where the target network changes (every 5 steps here, from a misaligned start), so every
    step's values are those of the target network it trains against, and training matches
    the agent computing them itself."""
    def agent():
        cfg = DQNConfig(hidden=[16], batch_size=16, target_update_period=5, double=double, lr=1e-2)
        torch.manual_seed(0)  # the same initial weights for both
        return DQNAgent(ArraySpec((3,), torch.float32), DiscreteSpec(2), cfg, torch.device("cpu"),
                        np.random.default_rng(0), hand_written=fast)

    chunked, stepwise = agent(), agent()
    stepwise.prepare = lambda batch, steps: batch
    chunked.train(table().sample(16)[0])  # train_step 1: the next update is 4 steps away
    stepwise.train(table().sample(16)[0])
    seen = []
    train = chunked.train

    def checked_train(batch):
        if isinstance(batch, PreparedBatch):
            seen.append(len(seen))
            with torch.no_grad():
                assert torch.allclose(batch.target_q, chunked.target(batch.next_obs), atol=1e-6)
        return train(batch)

    chunked.train = checked_train
    Learner(chunked, table(), batch_size=16, device=torch.device("cpu")).learn(60)
    Learner(stepwise, table(), batch_size=16, device=torch.device("cpu")).learn(60)
    assert len(seen) >= 50  # all but the chunk-size probe and 1-step chunks came prepared
    for a, b in zip(chunked.online.parameters(), stepwise.online.parameters(), strict=True):
        assert torch.allclose(a, b, atol=1e-5)


def test_no_target_network_or_one_copied_every_step_leaves_batches_as_sampled():
    for period, tau in ((1, 1.0), (1, 0.5)):
        cfg = DQNConfig(hidden=[16], batch_size=16, target_update_period=period, tau=tau)
        a = DQNAgent(ArraySpec((3,), torch.float32), DiscreteSpec(2), cfg, torch.device("cpu"),
                     np.random.default_rng(0))
        assert a.prepare_horizon() == 0
        batch = table().sample(64)[0]
        assert a.prepare(batch, 4) is batch


def test_a_prepared_chunk_keeps_its_type_when_moved_to_the_device():
    """What an agent's `prepare` returns (DQN's PreparedBatch) reaches `train` as the same type,
    every tensor moved (the meta device stands in for a GPU)."""
    class Preparing(Recorder):
        def prepare_horizon(self) -> int:
            return 10

        def prepare(self, batch, steps):
            return PreparedBatch(*batch, target_q=torch.zeros(batch.reward.shape[0], 2))

    agent = Preparing()
    Learner(agent, table(), batch_size=16, device=torch.device("meta")).learn(12)
    assert all(type(b) is PreparedBatch for b in agent.batches[1:])  # the first draws one batch alone
    assert all(x.device.type == "meta" for b in agent.batches for x in b if x is not None)
    assert agent.batches[-1].target_q.shape == (16, 2)


def test_available_steps_of_a_table_without_a_rate_is_refused_not_astronomical():
    """MinSize (the Table's default) allows any number of samples: `learn(available_steps())`
    ran 2**62 // batch steps, without end."""
    learner = Learner(Recorder(), table(), batch_size=32, device=torch.device("cpu"))
    with pytest.raises(ValueError, match=r"^the table's rate limiter sets no samples-per-insert rate \(MinSize"):
        learner.available_steps()
    learner.learn(3)
    assert learner.agent.train_step == 3


def test_an_actor_takes_plain_functions_as_its_policy_and_observers():
    """TF-Agents' observers are plain callables: they lacked the Policy's env_action and the
    Observer's flush."""
    from relayrl.envs import make_env
    from relayrl.training.actor import Actor

    seen = []
    actor = Actor(make_env("CartPole-v1", 2), lambda obs: torch.zeros(obs.shape[0], dtype=torch.int64),
                  [seen.append], seed=0)
    actor.collect(10)
    assert len(seen) == 5 and actor.env_steps == 10 and seen[0].action.tolist() == [0, 0]
    with pytest.raises(TypeError, match=r"^a policy is a relayrl.core.Policy .* or a plain function obs -> action, "
                                        r"not int$"):
        Actor(make_env("CartPole-v1", 1), 5, [])

    class Squashing:  # a Policy's env_action without its other methods: a wrapper would drop it
        def __call__(self, obs):
            return torch.zeros(obs.shape[0], dtype=torch.int64)

        def env_action(self, action):
            return action

    with pytest.raises(TypeError, match=r"^a policy is a relayrl.core.Policy \(subclass it: .*, not Squashing$"):
        Actor(make_env("CartPole-v1", 1), Squashing(), [])
