"""env.vectorization = "ale" (ale-py's C++ vector env for Atari ids) and the dqn-pong-fast preset."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch

from relayrl.config import Config
from relayrl.envs import make_env
from relayrl.errors import ConfigError, UserError
from relayrl.presets import list_presets, load_config

needs_ale = pytest.mark.skipif(
    importlib.util.find_spec("ale_py") is None or importlib.util.find_spec("cv2") is None,
    reason="ale-py and OpenCV are not installed (pip install 'relayrl[atari]')")

PONG = "relayrl/Atari-Pong-v0"


@needs_ale
def test_ale_vector_env_gives_what_the_gymnasium_path_gives():
    ale = make_env(PONG, 3, vectorization="ale", kwargs={"noop_max": 0})
    gym = make_env(PONG, 3, kwargs={"noop_max": 0})
    a, g = ale.observation_spec, gym.observation_spec
    assert (a.shape, a.dtype, a.frame_stack) == (g.shape, g.dtype, g.frame_stack) == ((4, 84, 84), torch.uint8, 4)
    assert ale.action_spec == gym.action_spec
    obs = ale.reset(seed=0)
    # Without no-op starts both show the game's first frame, pixel for pixel, repeated over the stack.
    assert torch.equal(obs, gym.reset(seed=0))
    assert torch.equal(obs[:, 0], obs[:, 3]) and not obs.is_pinned()
    out = ale.step(torch.zeros(3, dtype=torch.int64))
    assert out.obs.shape == (3, 4, 84, 84) and out.obs.dtype == torch.uint8
    assert torch.equal(out.obs[:, :3], obs[:, 1:])  # the stack slides by one frame per step
    assert out.reward.dtype == torch.float32 and out.terminated.dtype == torch.bool
    ale.close()
    gym.close()


@needs_ale
def test_without_sticky_actions_both_paths_play_the_same_games_frame_for_frame():
    # Sticky actions off and no no-op starts make Pong deterministic: the two paths must then agree
    # on every stack, reward and episode end, across auto-resets, whatever the actions.
    kwargs = {"repeat_action_probability": 0.0, "noop_max": 0}
    ale, gym = make_env(PONG, 2, vectorization="ale", kwargs=kwargs), make_env(PONG, 2, kwargs=kwargs)
    assert torch.equal(ale.reset(seed=0), gym.reset(seed=0))
    rng, ends = np.random.default_rng(0), 0
    for _ in range(1_000):
        action = torch.from_numpy(rng.integers(0, 6, 2))
        a, g = ale.step(action), gym.step(action)
        for field in ("next_obs", "reward", "terminated", "truncated", "obs"):
            assert torch.equal(getattr(a, field), getattr(g, field)), field
        ends += int(a.terminated.sum())
    assert ends >= 1  # random play loses a game in ~850 steps
    ale.close()
    gym.close()


@needs_ale
@pytest.mark.parametrize("vectorization", ["sync", "ale"])
def test_game_settings_reach_the_game_and_wrong_ones_are_refused_in_one_line(vectorization):
    full = make_env(PONG, 1, vectorization=vectorization, kwargs={"full_action_space": True})
    assert full.action_spec.n == 18
    full.close()
    with pytest.raises(UserError, match=r"repeat_action_probability=1.5 is not valid; it must be a number in \[0, 1\]"):
        make_env(PONG, 1, vectorization=vectorization, kwargs={"repeat_action_probability": 1.5})
    with pytest.raises(UserError, match="full_action_space='yes' is not valid; it must be true or false"):
        make_env(PONG, 1, vectorization=vectorization, kwargs={"full_action_space": "yes"})


@needs_ale
@pytest.mark.parametrize("terminates", [False, True])
def test_a_cut_episode_ends_as_in_the_other_envs(terminates):
    env = make_env(PONG, 2, max_episode_steps=20, time_limit_terminates=terminates, vectorization="ale")
    obs = env.reset(seed=1)
    for t in range(1, 21):
        out = env.step(torch.ones(2, dtype=torch.int64))
        assert torch.equal(out.next_obs[:, :3], obs[:, 1:])  # next_obs is the true last stack
        ended = out.terminated if terminates else out.truncated
        assert ended.tolist() == [t == 20] * 2
        assert not (out.truncated if terminates else out.terminated).any()
        if t < 20:
            assert out.obs is out.next_obs
        else:  # reset within the step: obs is a new episode's stack, the first frame repeated
            assert all(torch.equal(out.obs[:, i], out.obs[:, 0]) for i in range(4))
            assert not torch.equal(out.obs, out.next_obs)
        obs = out.obs
    out = env.step(torch.ones(2, dtype=torch.int64))  # the new episode goes on from the reset stack
    assert torch.equal(out.next_obs[:, :3], obs[:, 1:]) and not out.truncated.any()
    env.close()


@needs_ale
def test_a_game_over_gives_the_final_stack_and_the_raw_score():
    env = make_env(PONG, 8, vectorization="ale", info_keys=["lives"])
    obs = env.reset(seed=0)
    returns = torch.zeros(8)
    for _ in range(3_000):  # a random Pong game lasts 750-1,000 steps
        out = env.step(torch.randint(0, 6, (8,)))
        returns += out.reward
        if out.terminated.any():
            i = int(out.terminated.nonzero()[0])
            assert torch.equal(out.next_obs[i, :3], obs[i, 1:])  # the last frame, not the reset one
            assert all(torch.equal(out.obs[i, k], out.obs[i, 0]) for k in range(4))
            assert -21 <= returns[i] <= -15 and returns[i] == int(returns[i])  # the game's score
            assert out.episode_info is not None and out.episode_info["lives"][i] == 0
            break
        obs = out.obs
    else:
        pytest.fail("no Pong game ended within 3,000 steps")
    env.close()


@needs_ale
def test_ale_vectorization_refuses_what_it_cannot_do_in_one_line():
    with pytest.raises(UserError, match="needs an Atari id relayrl/Atari-<Game>-v0"):
        make_env("CartPole-v1", 2, vectorization="ale")
    with pytest.raises(UserError, match=r"env.kwargs \['terminal_on_life_loss'\] are not supported"):
        make_env(PONG, 2, vectorization="ale", kwargs={"terminal_on_life_loss": True})
    with pytest.raises(UserError, match="env.wrappers is not supported with env.vectorization='ale'"):
        make_env(PONG, 2, vectorization="ale", wrappers=["os:getcwd"])
    with pytest.raises(UserError, match="no game 'NoSuchGame'"):
        make_env("relayrl/Atari-NoSuchGame-v0", 2, vectorization="ale")


@needs_ale
def test_evaluations_of_an_ale_run_step_in_ale_py_where_its_kwargs_allow():
    from relayrl.envs.ale_vector import AleBatchEnv
    from relayrl.envs.gym import GymBatchEnv
    from relayrl.training.evaluate import evaluate, make_eval_env

    ale = make_eval_env(PONG, 5, vectorization="ale", kwargs={"noop_max": 0})
    assert isinstance(ale, AleBatchEnv) and ale.num_envs == 5
    gym = make_eval_env(PONG, 5, kwargs={"noop_max": 0})  # a sync run's, and relayrl eval's default
    assert isinstance(gym, GymBatchEnv)
    assert torch.equal(ale.reset(seed=3), gym.reset(seed=3))  # the same first frames
    # Life-loss episodes (eval.env_kwargs) are the Gymnasium path's: evaluated there, not refused.
    lives = make_eval_env(PONG, 2, vectorization="ale", kwargs={"terminal_on_life_loss": False})
    assert isinstance(lives, GymBatchEnv)
    # eval/<info key> values describe the episode that ended: ale-py's describe the next one
    with_info = make_eval_env(PONG, 2, vectorization="ale", info_keys=["episode_frame_number"])
    assert isinstance(with_info, GymBatchEnv)
    with_info.close()
    out = evaluate(ale, lambda obs: torch.zeros(len(obs), dtype=torch.int64), 5, seed=0)
    assert out["episodes"] == 5 and -21 <= out["average_return"] <= -15  # NOOP loses nearly every point
    for env in (ale, gym, lives):
        env.close()


@needs_ale
def test_relayrl_eval_of_an_ale_run_directory_steps_in_ale_py(tmp_path):
    from relayrl.config import save_toml
    from relayrl.envs.ale_vector import AleBatchEnv
    from relayrl.evaluation import recorded_env

    save_toml(load_config("dqn-pong-fast"), tmp_path / "config.toml")
    env, env_id = recorded_env(tmp_path, 3)
    assert isinstance(env, AleBatchEnv) and (env.num_envs, env_id) == (3, PONG)
    env.close()


def test_config_takes_ale_and_names_it_among_the_valid_values():
    c = Config()
    c.env.vectorization = "ale"
    c.validate()
    c.env.vectorization = "cpp"
    with pytest.raises(ConfigError, match="valid: sync, async, ale"):
        c.validate()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="pinned memory needs CUDA")
@needs_ale
def test_frames_come_in_pinned_memory_on_a_cuda_run():
    env = make_env(PONG, 2, vectorization="ale", device="cuda")
    assert env.reset(seed=0).is_pinned()
    out = env.step(torch.zeros(2, dtype=torch.int64))
    assert out.obs.is_pinned() and out.next_obs.is_pinned()
    env.close()


def test_dqn_pong_fast_preset_is_listed_and_says_its_target_is_not_met():
    assert "NOT met" in list_presets()["dqn-pong-fast"]
    c = load_config("dqn-pong-fast")
    c.validate()
    a = c.agent
    assert (c.env.id, c.env.vectorization, c.env.num_envs, c.replay.n_step, a.double) == (PONG, "ale", 8, 3, True)
    ref = load_config("ddqn-pong")  # the Nature-style reference is left as it was
    assert (ref.env.num_envs, ref.env.vectorization, ref.replay.n_step, ref.agent.lr) == (1, "sync", 1, 1e-4)
