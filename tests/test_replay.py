"""Uniform replay: contents, wrap-around, discounts at boundaries, sampling, checkpoints."""

import numpy as np
import torch

from relayrl.replay import UniformReplay
from relayrl.specs import ArraySpec, DiscreteSpec
from relayrl.types import Transition

OBS = ArraySpec((2,), torch.float32)
ACT = DiscreteSpec(3)


def transitions(start, b, terminated=None, truncated=None):
    ids = torch.arange(start, start + b, dtype=torch.float32)
    obs = torch.stack([ids, ids], 1)
    return Transition(obs, ids.long() % 3, ids, obs + 0.5,
                      torch.tensor(terminated if terminated is not None else [False] * b),
                      torch.tensor(truncated if truncated is not None else [False] * b))


def test_insert_batches_and_wrap_around_keep_the_newest():
    r = UniformReplay(5, OBS, ACT, gamma=0.9, seed=0)
    r(transitions(0, 3))
    r(transitions(3, 3))  # wraps: slot 0 now holds item 5
    assert r.size == 5
    assert sorted(r.reward.tolist()) == [1.0, 2.0, 3.0, 4.0, 5.0]
    assert torch.equal(r.next_obs[0], torch.tensor([5.5, 5.5]))


def test_discount_is_zero_after_termination_and_gamma_after_truncation():
    r = UniformReplay(4, OBS, ACT, gamma=0.9, seed=0)
    r(transitions(0, 3, terminated=[True, False, False], truncated=[False, True, False]))
    assert torch.allclose(r.discount[:3], torch.tensor([0.0, 0.9, 0.9]))


def test_sample_returns_only_inserted_items_with_matching_fields():
    r = UniformReplay(100, OBS, ACT, gamma=0.99, seed=1)
    r(transitions(0, 7))
    b = r.sample(256)
    assert b.obs.shape == (256, 2) and b.action.shape == (256,) and b.weight is None
    assert set(b.reward.tolist()) <= set(range(7))
    assert len(set(b.reward.tolist())) == 7  # uniform over all 7 items
    assert torch.equal(b.next_obs, b.obs + 0.5)
    assert torch.equal(b.action, b.reward.long() % 3)


def test_state_dict_round_trip_continues_the_same_samples():
    a = UniformReplay(10, OBS, ACT, gamma=0.99, seed=3)
    a(transitions(0, 12))
    a.sample(4)
    state = a.state_dict()
    b = UniformReplay(10, OBS, ACT, gamma=0.99, seed=99)
    b.load_state_dict(state)
    assert b.size == a.size
    for x, y in zip(a.sample(8), b.sample(8), strict=False):
        if x is not None:
            assert torch.equal(x, y)
    a(transitions(20, 1))
    b(transitions(20, 1))
    assert np.array_equal(a.reward.numpy(), b.reward.numpy())
