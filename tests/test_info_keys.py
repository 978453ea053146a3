"""`env.info_keys`: info values at episode ends, averaged like returns, logged and plotted."""

import numpy as np
import pytest
import torch

import relayrl
from relayrl.envs import make_env
from relayrl.errors import UserError
from relayrl.metrics import EpisodeStats
from relayrl.training.evaluate import evaluate
from relayrl.training.run_dir import RunDir


class Zeros:
    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.zeros(obs.shape[0], dtype=torch.int64)


def run_steps(env, stats, steps):
    from relayrl.types import Transition

    obs = env.reset(seed=0)
    for _ in range(steps):
        action = Zeros()(obs)
        out = env.step(action)
        stats(Transition(obs, action, out.reward, out.next_obs, out.terminated, out.truncated, out.episode_info))
        obs = out.obs


@pytest.mark.parametrize("num_envs", [1, 7])
def test_episode_end_values_reach_the_stats_window(num_envs):
    # Travel(length 3): copy i's k-th episode ends at x = 10 k + 3; 9 steps end 3 episodes a copy
    env = make_env("toy_envs:Travel", num_envs, info_keys=["x"])
    stats = EpisodeStats(buffer_size=None)
    run_steps(env, stats, 9)
    assert sorted(stats.info["x"]) == sorted([3.0, 13.0, 23.0] * num_envs)
    assert stats.info_means() == {"x": pytest.approx(13.0)}
    # the window is the returns' window: the newest 2 episodes are the last step's copies 6 and 7
    small = EpisodeStats(buffer_size=2)
    run_steps(make_env("toy_envs:Travel", num_envs, info_keys=["x"]), small, 9)
    assert list(small.info["x"]) == [23.0, 23.0] if num_envs > 1 else [13.0, 23.0]


def test_steps_without_episode_ends_carry_no_info_and_no_keys_cost_nothing():
    env = make_env("toy_envs:Travel", 2, info_keys=["x"])
    env.reset(seed=0)
    assert env.step(torch.zeros(2, dtype=torch.int64)).episode_info is None  # step 1 of 3
    plain = make_env("toy_envs:Travel", 2)
    plain.reset(seed=0)
    for _ in range(3):
        out = plain.step(torch.zeros(2, dtype=torch.int64))
    assert bool(out.terminated.all()) and out.episode_info is None


@pytest.mark.parametrize("workers", [1, 2])
def test_async_envs_read_the_ended_episodes_info_not_the_resets(workers):
    env = make_env("toy_envs:Travel", 2, vectorization="async", info_keys=["x"], num_workers=workers)
    try:
        stats = EpisodeStats(buffer_size=None)
        run_steps(env, stats, 6)
        assert sorted(stats.info["x"]) == [3.0, 3.0, 13.0, 13.0]
    finally:
        env.close()


@pytest.mark.parametrize("key, message", [
    ("y", "env.info_keys: 'y' is not in the env's info at an episode's end; keys there: ['name', 'x']"),
    ("name", "env.info_keys: info['name'] = 'travel' is not a number"),
])
def test_bad_info_keys_fail_with_one_clear_line(key, message):
    env = make_env("toy_envs:Travel", 1, info_keys=[key])
    env.reset(seed=0)
    with pytest.raises(UserError) as e:
        for _ in range(3):
            env.step(torch.zeros(1, dtype=torch.int64))
    assert str(e.value) == message


def test_a_bad_info_value_mid_collection_says_the_env_steps_taken_before_it(tmp_path):
    """The first episode ends at env step 3, inside the random warm-up's one collect call (which
    started at 0): the run's line counts the 2 steps taken before it."""
    config = relayrl.load_config("dqn", ["env.id=toy_envs:Travel", "env.info_keys=['name']", "env.check=false",
                                         "train.initial_collect_steps=50", "train.total_steps=100", "eval.interval=0"])
    with pytest.raises(UserError) as e:
        relayrl.train(config, tmp_path / "run", progress=False)
    assert str(e.value).startswith("env.info_keys: info['name'] = 'travel' is not a number; the run stopped at "
                                   "env step 2: ")


def test_an_info_value_in_a_one_element_array_says_its_shape():
    from relayrl.envs.gym import episode_info

    with pytest.raises(UserError) as e:
        episode_info(("x",), 1, [0], lambda i: {"x": np.array([1.5])})
    assert str(e.value) == ("env.info_keys: info['x'] = array([1.5]) is not a number (an array of shape (1,): give "
                            "one number, such as x.item())")


def test_an_info_value_whose_repr_spans_lines_is_still_one_line():
    from relayrl.envs.gym import episode_info

    with pytest.raises(UserError) as e:
        episode_info(("m",), 1, [0], lambda i: {"m": np.ones((2, 2))})
    assert str(e.value) == ("env.info_keys: info['m'] = array([[1., 1.], [1., 1.]]) is not a number (an array of "
                            "shape (2, 2): give one number, such as x.item())")
    with pytest.raises(UserError) as e:
        episode_info(("m",), 1, [0], lambda i: {"m": np.zeros((50, 50))})
    assert "\n" not in str(e.value) and "info['m'] = array([[0., 0., 0., " in str(e.value)
    assert "... is not a number (an array of shape (50, 50)" in str(e.value)


def test_info_keys_with_an_env_whose_info_is_not_a_dict_is_one_line():
    from relayrl.envs.gym import episode_info

    with pytest.raises(UserError, match=r"^env.info_keys: the env's info at an episode's end is NoneType None, not a "):
        episode_info(("x",), 2, [1], lambda i: None)


def test_stateless_envs_refuse_info_keys():
    with pytest.raises(UserError, match="env.info_keys is not supported by stateless envs"):
        make_env("relayrl/StatelessPendulum-v0", 2, info_keys=["x"])


def test_stats_window_survives_a_state_dict_round_trip():
    stats = EpisodeStats(buffer_size=3)
    run_steps(make_env("toy_envs:Travel", 2, info_keys=["x"]), stats, 9)
    again = EpisodeStats(buffer_size=3)
    again.load_state_dict(stats.state_dict())
    assert list(again.info["x"]) == list(stats.info["x"]) and again.info["x"].maxlen == 3


def test_evaluate_averages_info_over_exactly_the_counted_episodes():
    # 5 episodes on 2 copies: copy 0 counts 3 (x = 3, 13, 23), copy 1 counts 2 (x = 3, 13)
    env = make_env("toy_envs:Travel", 2, info_keys=["x"])
    result = evaluate(env, Zeros(), episodes=5, seed=0)
    assert result["episodes"] == 5
    assert result["eval/x"] == pytest.approx(np.mean([3, 13, 23, 3, 13]))


def test_a_run_logs_and_plots_info_keys(tmp_path):
    config = relayrl.load_config("dqn-cartpole-fast", [
        "env.id=toy_envs:Travel", "env.info_keys=[\"x\"]", "train.total_steps=300",
        "train.initial_collect_steps=50", "eval.interval=150", "eval.episodes=2", "agent.hidden=[8]",
        "train.checkpoint_interval=0"])
    relayrl.train(config, tmp_path / "run", progress=False)
    rows = RunDir(tmp_path / "run").read_metrics()
    assert [r["step"] for r in rows] == [0, 300]
    assert rows[0]["eval/x"] == 3.0 and "train/x" not in rows[0]  # no training episode yet
    # training episodes of length 3 on one copy: the window holds the newest 10 of them
    assert rows[-1]["train/x"] == pytest.approx(np.mean([10 * k + 3 for k in range(90, 100)]))
    from relayrl.plot import plot_run

    assert plot_run(tmp_path / "run").stat().st_size > 0


def test_an_info_that_is_not_a_dict_is_shown_on_one_line():
    from relayrl.envs.gym import episode_info

    with pytest.raises(UserError) as e:
        episode_info(("x",), 1, [0], lambda i: np.zeros((3, 3)))
    assert "\n" not in str(e.value) and "is ndarray [[0. 0. 0.] [0. 0. 0.] [0. 0. 0.]], not a dict" in str(e.value)


@pytest.mark.parametrize("text, width, shown", [
    ("short", 60, "short"),
    ("array([[1., 1.],\n       [1., 1.]])", 60, "array([[1., 1.], [1., 1.]])"),
    ("x" * 100, 10, "xxxxxxx..."),
])
def test_one_line_joins_lines_and_cuts_to_its_width(text, width, shown):
    from relayrl.errors import one_line

    assert one_line(text, width) == shown and len(one_line(text, width)) <= width
