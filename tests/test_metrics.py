"""Batch-aware metrics at batch sizes 1, 7 and 32, against hand-computed values, through the
compiled accumulation (metrics_fast, numba) and the NumPy one."""

import math

import numpy as np
import pytest
import torch

from relayrl.compile import numba_available
from relayrl.metrics import (
    AverageEpisodeLength,
    AverageReturn,
    EnvironmentSteps,
    EpisodeStats,
    NumberOfEpisodes,
)
from relayrl.types import Transition


@pytest.fixture(autouse=True, params=["compiled", "numpy"])
def accumulation(request, monkeypatch):
    if request.param == "numpy":
        monkeypatch.setenv("RELAYRL_NUMBA", "0")
        assert EpisodeStats()._accumulate is None
    elif not numba_available():
        pytest.skip("the compiled accumulation needs numba (pip install relayrl[fast]) and RELAYRL_NUMBA not 0")
    else:
        assert EpisodeStats()._accumulate is not None
    return request.param


def step(rewards, terminated, truncated=None):
    b = len(rewards)
    z = torch.zeros(b, 1)
    return Transition(z, torch.zeros(b, dtype=torch.long), torch.tensor(rewards, dtype=torch.float32), z,
                      torch.tensor(terminated), torch.tensor(truncated or [False] * b))


def make():
    stats = EpisodeStats(buffer_size=10)
    return stats, EnvironmentSteps(), AverageReturn(stats), AverageEpisodeLength(stats), NumberOfEpisodes(stats)


def test_batch_of_one():
    stats, steps, ret, length, n = make()
    assert math.isnan(ret.result())
    for r, done in [(1.0, False), (2.0, False), (3.0, True), (10.0, True)]:
        t = step([r], [done])
        stats(t)
        steps(t)
    assert steps.result() == 4
    assert n.result() == 2
    assert ret.result() == pytest.approx((6.0 + 10.0) / 2)
    assert length.result() == pytest.approx((3 + 1) / 2)


def test_batch_of_seven_without_being_told_the_size():
    stats, steps, ret, length, n = make()
    # env i gets reward i every step; env i ends its episode at step i+1 (i < 3), by
    # termination for even i and truncation for odd i; envs 3..6 never end.
    for s in range(3):
        done = [i == s for i in range(7)]
        term = [d and i % 2 == 0 for i, d in enumerate(done)]
        trunc = [d and i % 2 == 1 for i, d in enumerate(done)]
        t = step([float(i) for i in range(7)], term, trunc)
        stats(t)
        steps(t)
    assert steps.result() == 21
    assert n.result() == 3
    # env 0: 1 step * 0 = 0; env 1: 2 steps * 1 = 2; env 2: 3 steps * 2 = 6
    assert ret.result() == pytest.approx((0 + 2 + 6) / 3)
    assert length.result() == pytest.approx((1 + 2 + 3) / 3)


def test_window_keeps_the_last_episodes_and_state_round_trips():
    stats = EpisodeStats(buffer_size=2)
    for r in (1.0, 2.0, 3.0):
        stats(step([r], [True]))
    assert list(stats.returns) == [2.0, 3.0]
    other = EpisodeStats(buffer_size=2)
    other.load_state_dict(stats.state_dict())
    assert list(other.returns) == [2.0, 3.0] and other.episodes == 3


def test_batch_of_32_with_episodes_ending_at_different_steps_and_a_mid_episode_round_trip():
    # env i: reward i + 1 per step, episodes of (i % 5) + 1 steps, over 12 batched steps; the
    # stats are checkpointed after step 5 (most envs mid-episode) and continued in a copy.
    def run(stats, steps_range):
        for s in steps_range:
            done = [(s + 1) % (i % 5 + 1) == 0 for i in range(32)]
            stats(step([float(i + 1) for i in range(32)], done))

    stats = EpisodeStats(buffer_size=1000)
    run(stats, range(5))
    resumed = EpisodeStats(buffer_size=1000)
    resumed.load_state_dict(stats.state_dict())
    run(stats, range(5, 12))
    run(resumed, range(5, 12))
    lengths = [i % 5 + 1 for i in range(32) for _ in range(12 // (i % 5 + 1))]
    returns = [(i % 5 + 1) * (i + 1) for i in range(32) for _ in range(12 // (i % 5 + 1))]
    for s in (stats, resumed):
        assert NumberOfEpisodes(s).result() == len(lengths)
        assert AverageReturn(s).result() == pytest.approx(sum(returns) / len(returns))
        assert AverageEpisodeLength(s).result() == pytest.approx(sum(lengths) / len(lengths))


def test_float_returns_are_summed_exactly_in_float64():
    # Both accumulations add each float32 reward to a float64 running sum in step order, so
    # the episode returns equal a plain Python sum to the last bit.
    rng = np.random.default_rng(0)
    rewards = rng.standard_normal((60, 7)).astype(np.float32) * 3.7
    ended = rng.random((60, 7)) < 0.1
    stats = EpisodeStats(buffer_size=None)
    running, expected, lengths = [0.0] * 7, [], []
    since = [0] * 7
    for s in range(60):
        stats(step(rewards[s].tolist(), ended[s].tolist()))
        for i in range(7):
            running[i] += float(rewards[s, i])
            since[i] += 1
            if ended[s, i]:
                expected.append(running[i])
                lengths.append(since[i])
                running[i], since[i] = 0.0, 0
    assert list(stats.returns) == expected and list(stats.lengths) == lengths and len(expected) > 20
    assert stats._ret.tolist() == running


def test_finished_episodes_not_yet_logged_survive_a_checkpoint():
    steps = [0]
    stats = EpisodeStats()
    stats.step_fn = lambda: steps[0]
    for t in range(3):
        steps[0] = t + 1
        stats(Transition(torch.zeros(2, 1), torch.zeros(2), torch.ones(2), torch.zeros(2, 1),
                         torch.tensor([False, t == 2]), torch.zeros(2, dtype=torch.bool)))
    again = EpisodeStats()
    again.load_state_dict(stats.state_dict())
    assert again.take_finished() == stats.take_finished() == [(3, 3.0, 3)]


@pytest.mark.parametrize("batch", [1, 7])
def test_steps_from_a_device_are_read_once_per_collect_call_with_the_same_results(batch, monkeypatch):
    # On a GPU each batched step's rewards and done flags are staged and read in one host copy
    # at flush(): the windows, episode counts, info values and each episode's env step must be
    # what reading every step at once gives. (CPU tensors stand in for a device's here.)
    import relayrl.metrics as metrics

    rng = np.random.default_rng(batch)
    steps_ = [(rng.normal(size=batch).tolist(), (rng.random(batch) < 0.2).tolist(),
               (rng.random(batch) < 0.1).tolist()) for _ in range(40)]

    def run(staged: bool) -> EpisodeStats:
        monkeypatch.setattr(metrics, "on_device", lambda x: staged)
        stats, counter = EpisodeStats(buffer_size=None), EnvironmentSteps()
        stats.step_fn = lambda: counter.value
        for i, (r, term, trunc) in enumerate(steps_):
            t = step(r, term, trunc)._replace(episode_info={"x": torch.full((batch,), float(i))})
            counter(t)
            stats(t)
            if i % 9 == 8:  # the Actor flushes at the end of each collect call
                stats.flush()
        assert not staged or stats._staged or len(steps_) % 9 == 0  # the last 4 steps wait for flush
        return stats

    direct, staged = run(False), run(True)
    a, b = staged.state_dict(), direct.state_dict()  # state_dict reads what is staged first
    running_a, running_b = a.pop("running"), b.pop("running")
    assert a == b
    assert all(np.array_equal(x, y) for x, y in zip(running_a, running_b, strict=True))
    assert staged.episodes == direct.episodes > 0
    assert staged.take_finished() == direct.take_finished()


def test_tensorboard_gets_one_point_per_step_with_the_mean_of_the_episodes_that_ended_there():
    from relayrl.training.report import step_means

    finished = [(10, 1.0, 10), (20, 2.0, 20), (20, 4.0, 10), (20, 6.0, 30), (35, -1.5, 5)]
    assert step_means(finished) == [(10, 1.0, 10.0), (20, 4.0, 20.0), (35, -1.5, 5.0)]
    assert step_means([]) == []


@pytest.mark.parametrize("value, shown", [(-0.001, "0.00"), (-0.004999, "0.00"), (-0.005001, "-0.01"), (0.0, "0.00"),
                                          (-12.345, "-12.35"), (3.0, "3.00")])
def test_printed_returns_never_show_minus_zero(value, shown):
    from relayrl.training.report import rounded

    assert f"{rounded(value):.2f}" == shown
