"""Atari through ale-py (the `[atari]` extra, which ships its ROMs) and the Pong presets."""

from __future__ import annotations

import importlib.util
import json
import sys

import gymnasium
import pytest
import torch

import relayrl
from relayrl.envs import make_env
from relayrl.envs.atari import import_ale, raw_screen_note
from relayrl.errors import UserError
from relayrl.presets import list_presets, load_config

needs_ale = pytest.mark.skipif(
    importlib.util.find_spec("ale_py") is None or importlib.util.find_spec("cv2") is None,
    reason="ale-py and OpenCV are not installed (pip install 'relayrl[atari]')")


def test_a_missing_ale_py_is_one_line_naming_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "ale_py", None)  # `import ale_py` now raises ImportError
    with pytest.raises(UserError, match=r"needs ale-py: pip install -e \"\.\[atari\]\" in relayrl's folder"):
        import_ale("relayrl/Atari-Pong-v0")


@pytest.mark.parametrize("env_id, hint", [("relayrl/Atari-Pong-v0", True), ("PongNoFrameskip-v4", True),
                                          ("Pong-v4", True), ("Cartpole-v1", False)])
def test_without_ale_py_atari_ids_say_which_extra_with_each_vectorization(env_id, hint, monkeypatch):
    """The ale-py vector env (ppo-pong, dqn-pong-fast) and the old Gym ids that ale-py registers
    name the extra first, then any near miss of another env's id (Pong-v4: Ant-v4)."""
    from relayrl.envs.make import make_env

    monkeypatch.setitem(sys.modules, "ale_py", None)
    monkeypatch.delitem(gymnasium.registry, env_id, raising=False)  # an earlier test's ale-py registered it
    vectorizations = ["sync", "ale"] if env_id.startswith("relayrl/") else ["sync"]
    for vectorization in vectorizations:
        with pytest.raises(UserError) as e:
            make_env(env_id, 2, vectorization=vectorization)
        assert ("pip install -e \".[atari]\"" in str(e.value)) == hint, str(e.value)
        if hint and "otherwise did you mean" in str(e.value):  # a far near miss (Ant-v4) after the extra
            assert str(e.value).index("[atari]") < str(e.value).index("otherwise did you mean"), str(e.value)


def test_without_ale_py_a_typo_of_a_registered_id_is_named_before_the_atari_extra(monkeypatch):
    """Any CamelCase-v0 id looks like one of ale-py's: a near miss that is a typo comes first."""
    from relayrl.envs.make import make_env

    monkeypatch.setitem(sys.modules, "ale_py", None)
    gymnasium.register("MyCorridor-v0", entry_point="gymnasium.envs.classic_control:CartPoleEnv")
    try:
        with pytest.raises(UserError, match=r"^env.id='MyCoridor-v0' is not a registered Gymnasium id; did you mean "
                                            r"MyCorridor-v0\?; if it is an Atari game's"):
            make_env("MyCoridor-v0", 1)
    finally:
        del gymnasium.registry["MyCorridor-v0"]


def test_ddqn_pong_preset_is_listed_with_standard_settings():
    assert "ddqn-pong" in list_presets()
    c = load_config("ddqn-pong")
    a = c.agent
    assert (c.env.id, a.network, a.double, a.loss, a.batch_size, c.replay.size) == (
        "relayrl/Atari-Pong-v0", "nature_cnn", True, "huber", 32, 100_000)
    assert (c.train.collect_steps, c.train.gradient_steps, a.target_update_period) == (4, 1, 1_000)


@needs_ale
def test_atari_ids_give_uint8_frame_stacks_and_render_the_full_screen():
    env = make_env("relayrl/Atari-Pong-v0", 2, render_mode="rgb_array")
    spec = env.observation_spec
    assert (spec.shape, spec.dtype, spec.frame_stack, env.action_spec.n) == ((4, 84, 84), torch.uint8, 4, 6)
    obs = env.reset(seed=0)
    assert obs.shape == (2, 4, 84, 84) and obs.dtype == torch.uint8
    assert torch.equal(obs[:, 0], obs[:, 3])  # reset padding repeats the first frame
    out = env.step(torch.zeros(2, dtype=torch.int64))
    assert torch.equal(out.obs[:, :3], obs[:, 1:])  # the stack slides by one frame per step
    assert env.render().shape == (210, 160, 3)  # videos show the game, not the 84x84 stack
    assert env.envs[0].metadata["render_fps"] == 15  # 60 frames/s, 4 frames a step
    env.close()


@needs_ale
def test_ale_ids_work_and_unknown_games_say_so():
    assert make_env("ALE/Breakout-v5").observation_spec.shape == (210, 160, 3)
    with pytest.raises(UserError, match="no game 'NoSuchGame'"):
        make_env("relayrl/Atari-NoSuchGame-v0")


@needs_ale
def test_older_gym_atari_ids_resolve_and_raw_screens_name_the_preprocessed_id():
    # An SB3 or CleanRL user's PongNoFrameskip-v4 is registered by importing ale-py, as ALE/... is.
    env = make_env("PongNoFrameskip-v4")
    assert env.observation_spec.shape == (210, 160, 3)
    env.close()
    note = raw_screen_note("PongNoFrameskip-v4", {}, [])
    assert note is not None and "relayrl/Atari-Pong-v0 with env.kwargs repeat_action_probability=0.0 is the " \
        "same game under it" in note
    assert "relayrl/Atari-Breakout-v0 is the same game" in (raw_screen_note("ALE/Breakout-v5", {}, []) or "")
    # the user's env.kwargs count, and a random frame skip is not "the same game"
    assert "Atari-Pong-v0 with env.kwargs repeat_action_probability=0.0, full_action_space=True is the same" in (
        raw_screen_note("ALE/Pong-v5", {"repeat_action_probability": 0.0, "full_action_space": True}, []) or "")
    assert "is its game with a fixed frame skip" in (raw_screen_note("Pong-v4", {}, []) or "")
    # preprocessed already, or not an ALE screen: no note
    assert raw_screen_note("ALE/Breakout-v5", {}, ["mymod:preprocess"]) is None
    assert raw_screen_note("ALE/Breakout-v5", {"obs_type": "ram"}, []) is None
    for other in ("relayrl/Atari-Pong-v0", "CartPole-v0", "MountainCar-v0"):
        assert raw_screen_note(other, {}, []) is None


@needs_ale
# dqn-pong-fast: 4 ale-py vector envs here (8 in the preset), 2 gradient steps per 8 env steps
@pytest.mark.parametrize("preset, extra", [("ddqn-pong", []), ("dqn-pong-fast", ["env.num_envs=4"])])
def test_pong_presets_run_a_few_hundred_steps(tmp_path, preset, extra):
    config = load_config(preset, [
        "train.total_steps=300", "train.initial_collect_steps=100", "replay.size=1000", "agent.batch_size=8",
        "agent.target_update_period=10", "eval.interval=300", "eval.episodes=1", "env.max_episode_steps=60",
        "train.checkpoint_interval=0", "train.policy_save_interval=300", "device=cpu", *extra])
    result = relayrl.train(config, tmp_path / "run", progress=False)
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [0, 300]
    assert abs(rows[-1]["train_step"] - 200 // 4) <= 2  # one per 4 env steps after the first 100
    assert "losses/loss" in rows[-1] and "losses/q" in rows[-1]
    assert result.final["average_episode_length"] == 60
    policy = relayrl.load_policy(tmp_path / "run")
    assert policy(torch.zeros(3, 4, 84, 84, dtype=torch.uint8)).shape == (3,)
    assert relayrl.plot_run(tmp_path / "run").stat().st_size > 10_000
    video = relayrl.record_video(tmp_path / "run", max_steps=20)
    assert video.stat().st_size > 0


def test_ppo_pong_preset_is_cleanrls_five_minute_settings():
    config = load_config("ppo-pong")
    assert (config.algo, config.env.num_envs, config.env.vectorization) == ("ppo", 16, "ale")
    assert config.env.kwargs == {"repeat_action_probability": 0.0}
    agent = config.agent
    assert (agent.encoder, agent.hidden, agent.shared) == ("nature_cnn", [], True)
    assert (agent.lr, agent.lr_end, agent.clip_range, agent.clip_range_vf) == (2.5e-4, 0.0, 0.2, 0.2)
    assert (agent.n_epochs, agent.batch_size, agent.ent_coef, agent.max_grad_norm) == (3, 256, 0.01, 0.5)
    assert agent.vf_coef == 0.25  # CleanRL's vf_coef 0.5 weighs half the squared error
    assert config.train.collect_steps // config.env.num_envs == 128  # CleanRL's num_steps
    assert config.train.collect_steps // agent.batch_size == 8  # CleanRL's num_minibatches


@needs_ale
def test_ppo_pong_preset_trains_a_few_rollouts_and_its_policy_loads(tmp_path):
    config = load_config("ppo-pong", [
        "env.num_envs=2", "train.collect_steps=64", "agent.batch_size=32", "train.total_steps=192",
        "eval.interval=192", "eval.episodes=1", "env.max_episode_steps=60", "train.policy_save_interval=192",
        "device=cpu"])
    result = relayrl.train(config, tmp_path / "run", progress=False)
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [0, 192]
    assert result.final["average_episode_length"] == 60
    policy = relayrl.load_policy(tmp_path / "run")
    assert policy(torch.zeros(3, 4, 84, 84, dtype=torch.uint8)).shape == (3,)


@needs_ale
def test_importing_relayrl_envs_registers_every_shipped_game_without_importing_ale_py():
    """gymnasium.make gives the env a loaded policy acts on; ale-py's own import (seconds) waits for a game."""
    import subprocess

    code = ("import sys, gymnasium, relayrl.envs\n"
            "ids = [i for i in gymnasium.registry if i.startswith('relayrl/Atari-')]\n"
            "assert 'ale_py' not in sys.modules and len(ids) > 100, (len(ids), 'ale_py' in sys.modules)\n"
            "import ale_py\n"
            "gymnasium.register_envs(ale_py)\n"
            "v5 = {i[4:-3] for i in gymnasium.registry if i.startswith('ALE/') and i.endswith('-v5')}\n"
            "assert {i[len('relayrl/Atari-'):-3] for i in ids} == v5\n"  # every game, none it lacks
            "env = gymnasium.make('relayrl/Atari-Breakout-v0')\n"
            "obs, _ = env.reset(seed=0)\n"
            "print(len(ids), obs.shape, obs.dtype, 'relayrl/Atari-MontezumaRevenge-v0' in ids)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[1:] == ["(4,", "84,", "84)", "uint8", "True"]
