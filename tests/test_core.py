"""The declared contract (core.py): every registered agent is a `core.Agent` whose policies are
`core.Policy`s, the loop's observers and envs are `core.Observer`s / `core.BatchedEnv`s, and the
optional methods' defaults are the "nothing to do" answers the loop relies on. The loop calls
these methods directly, so no caller probes for them by name."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

from relayrl.agents.registry import ALGORITHMS
from relayrl.core import Agent, BatchedEnv, Observer, Policy
from relayrl.envs import make_env
from relayrl.metrics import EnvironmentSteps, EpisodeStats
from relayrl.specs import ArraySpec, DiscreteSpec
from relayrl.training.finite import FiniteWatch
from relayrl.types import Batch

SRC = Path(__file__).resolve().parents[1] / "src" / "relayrl"
OBS = ArraySpec((3,), torch.float32, -np.ones(3), np.ones(3))
SPACES = {"dqn": DiscreteSpec(2), "sac": ArraySpec((1,), torch.float32, np.array([-2.0]), np.array([2.0])),
          "ppo": DiscreteSpec(2)}


def inherits(obj, protocol) -> bool:
    """`obj`'s class subclasses `protocol`, so it has the protocol's defaults (the protocols are
    not runtime-checkable: isinstance cannot answer)."""
    return protocol in type(obj).__mro__


@pytest.mark.parametrize("name", [a.name for a in ALGORITHMS.values() if a.agent])
def test_every_agent_is_a_core_agent_with_core_policies(name):
    spec = ALGORITHMS[name]
    agent = spec.make_agent(spec.config(), OBS, SPACES[name], torch.device("cpu"), np.random.default_rng(0), 100)
    assert inherits(agent, Agent)
    collect = agent.collect_policy(lambda: 0, None)
    assert inherits(collect, Policy) and inherits(agent.eval_policy(), Policy)
    action = collect(torch.zeros(2, 3))
    assert collect.env_action(action).shape == action.shape
    collect.load_state_dict(collect.state_dict())
    agent.set_progress(10)
    device_policy = agent.device_collect_policy()
    assert device_policy is None or inherits(device_policy, Policy)


def test_optional_methods_default_to_nothing_to_do():
    class Minimal(Agent):
        pass

    agent = Minimal()
    batch = Batch(*(torch.zeros(4) for _ in range(5)), None)
    assert agent.prepare_horizon() == 0 and agent.prepare(batch, 3) is batch
    assert agent.device_collect_policy() is None and agent.set_progress(5) is None

    class Identity(Policy):
        def __call__(self, obs):
            return obs

    policy, action = Identity(), torch.ones(2)
    assert policy.env_action(action) is action and policy.state_dict() == {}
    for observer in (EnvironmentSteps(), EpisodeStats(), FiniteWatch(2)):
        assert inherits(observer, Observer)
        observer.flush()

    class Frozen(BatchedEnv):
        pass

    assert Frozen().get_state() is None
    with pytest.raises(NotImplementedError):
        Frozen().set_state([b""])


def test_the_loop_s_envs_are_batched_envs():
    env = make_env("CartPole-v1")
    try:
        assert inherits(env, BatchedEnv) and env.get_state() is not None
    finally:
        env.close()


def test_no_caller_probes_the_contract_by_name():
    contract = ("prepare", "prepare_horizon", "set_progress", "device_collect_policy", "env_action", "flush",
                "get_state", "set_state", "state_dict", "load_state_dict")
    names = "|".join(contract)
    probe = re.compile(rf"""(getattr|hasattr)\([^)]*["']({names})["']""")
    found = [f"{p.relative_to(SRC)}:{i}" for p in SRC.rglob("*.py")
             for i, line in enumerate(p.read_text().splitlines(), 1) if probe.search(line)]
    assert not found, found

