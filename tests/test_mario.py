"""relayrl/SuperMarioBros-1-1-v0: gym-super-mario-bros on Gymnasium's API and NumPy 2 (the `mario` extra)."""

import importlib.util
import os
import pickle
import re
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from relayrl.envs import mario
from relayrl.errors import UserError

ENV_ID = "relayrl/SuperMarioBros-1-1-v0"
RIGHT, RIGHT_A = 0, 1

needs_mario = pytest.mark.skipif(
    importlib.util.find_spec("nes_py") is None or importlib.util.find_spec("gym_super_mario_bros") is None,
    reason="the [mario] extra is not installed: pip install 'relayrl[mario]'")



@pytest.fixture(scope="module")
def env():
    env = mario.MarioEnv(render_mode="rgb_array")  # ~1 s: plays past the title screen
    yield env
    env.close()


def test_registered_by_entry_point_string():
    spec = gym.spec(ENV_ID)
    assert spec.entry_point == "relayrl.envs.mario:MarioEnv"  # a string: nes-py is imported only by make
    assert spec.max_episode_steps == mario.MAX_EPISODE_FRAMES


def test_missing_extra_is_a_user_error(monkeypatch):
    monkeypatch.setattr(mario, "_modules", None)  # forget a load done by an earlier test
    monkeypatch.setitem(sys.modules, "nes_py", None)  # find_spec then reports it missing
    message = re.escape(f"({ENV_ID} and the ddqn-mario preset's {ENV_ID.replace('-v0', '-pixels-v0')}) need "
                        "nes-py: pip install -e \".[mario]\" in relayrl's folder")
    with pytest.raises(UserError, match=message):
        mario.MarioEnv()


@needs_mario
def test_gymnasium_api(env):
    assert env.action_space == gym.spaces.Discrete(2)
    assert env.action_meanings == ["right", "right A"]  # the tutorial's [["right"], ["right", "A"]]
    assert env._action_bytes == [0b10000000, 0b10000001]  # nes-py's JoypadSpace bitmaps
    assert env.observation_space == gym.spaces.Box(0, 255, (240, 256, 3), np.uint8)
    obs, info = env.reset(seed=0)
    assert obs.shape == (240, 256, 3) and obs.dtype == np.uint8 and env.observation_space.contains(obs)
    assert info["x_pos"] == 40 and info["flag_get"] is False and info["world"] == 1 and info["stage"] == 1
    obs, reward, terminated, truncated, info = env.step(RIGHT)
    assert isinstance(reward, float) and terminated is False and truncated is False
    assert all(type(v) in (int, bool, str) for v in info.values())  # no NumPy scalars in logs
    frame = env.render()
    assert frame.shape == (240, 256, 3) and frame.dtype == np.uint8 and np.array_equal(frame, obs)


@needs_mario
def test_check_env():
    made = gym.make(ENV_ID, render_mode="rgb_array")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # any warning of Gymnasium's checker (or a NumPy overflow) fails
            check_env(made.unwrapped)
    finally:
        made.close()


@needs_mario
def test_holding_right_moves_mario_and_frames_are_copies(env):
    obs0, info = env.reset()
    start = info["x_pos"]
    frames, total = [obs0], 0.0
    for _ in range(120):
        obs, reward, terminated, _, info = env.step(RIGHT)
        frames.append(obs)
        total += reward
        assert not terminated
    # 1-1 starts with open ground: 120 frames of walking right move Mario ~100 pixels.
    assert info["x_pos"] > start + 60
    assert total > 0  # reward = x progress + clock penalty
    assert not np.array_equal(frames[0], frames[-1])
    again, info = env.reset()  # resets restore the stage's start and leave returned frames alone
    assert info["x_pos"] == start and np.array_equal(again, obs0) and np.array_equal(frames[0], obs0)


@needs_mario
def test_deterministic_and_terminates_on_death(env):
    def episode() -> tuple[list[float], int]:
        env.reset(seed=1)
        rewards = []
        for t in range(3000):  # walking right, Mario meets the first Goomba within ~400 frames
            _, reward, terminated, truncated, _ = env.step(RIGHT)
            rewards.append(reward)
            if terminated or truncated:
                return rewards, t
        raise AssertionError("no death in 3000 frames of walking right")

    first, second = episode(), episode()
    assert first == second
    assert first[0][-1] == -15.0  # the -25 death penalty, clipped to the reward range [-15, 15]


@needs_mario
def test_not_picklable(env):
    from relayrl.envs.gym import env_snapshot

    with pytest.raises(TypeError, match="cannot be pickled"):
        pickle.dumps(env)  # would otherwise copy a raw pointer to the C++ emulator
    assert env_snapshot(env) is None  # checkpoints then start new episodes on resume


@needs_mario
def test_rom_ships_with_the_package_and_parses_under_numpy2(env):
    path = mario._rom_path()
    assert os.path.isfile(path) and path.startswith(os.path.dirname(importlib.util.find_spec(
        "gym_super_mario_bros").origin))
    rom = sys.modules[f"{mario._NES}._rom"].ROM(path)  # raised OverflowError under NumPy 2 unpatched
    assert (rom.prg_rom_size, rom.chr_rom_size, rom.mapper) == (32, 8, 0)
    assert rom.prg_rom.size == 32 * 1024 and rom.chr_rom.size == 8 * 1024


@needs_mario
def test_no_old_gym_and_real_packages_untouched():
    # A fresh interpreter: neither `gym` nor the real nes_py / gym_super_mario_bros get imported.
    code = ("import sys; from relayrl.envs.mario import MarioEnv; MarioEnv().step(0); "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('gym', 'nes_py', 'gym_super_mario_bros')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


@needs_mario
def test_preprocessed_is_the_tutorials_stack():
    pytest.importorskip("cv2", reason="pixel preprocessing resizes with OpenCV: pip install 'relayrl[atari]'")
    env = mario.make_preprocessed(render_mode="rgb_array")
    try:
        assert env.observation_space.shape == (4, 84, 84) and env.observation_space.dtype == np.uint8
        obs, info = env.reset()
        assert obs.shape == (4, 84, 84) and obs.dtype == np.uint8 and "x_pos" in info
        obs, reward, terminated, truncated, info = env.step(RIGHT_A)
        assert obs.shape == (4, 84, 84) and not terminated and not truncated
        assert env.render().shape == (240, 256, 3)  # full RGB frames for videos
    finally:
        env.close()


@needs_mario
def test_ddqn_mario_preset_runs_a_few_hundred_steps(tmp_path):
    import relayrl

    over = ["train.total_steps=300", "train.initial_collect_steps=100", "replay.size=1000", "eval.interval=300",
            "eval.episodes=1", "train.checkpoint_interval=0", "device=cpu", "env.max_episode_steps=100"]
    result = relayrl.train(relayrl.load_config("ddqn-mario", over), tmp_path / "run", progress=False)
    assert result.final["step"] == 300 and result.final["train_step"] > 0
    assert relayrl.load_policy(tmp_path / "run").env_steps == 300
    # the preset's info_keys: how far Mario got per episode (he starts at x = 40, moving right)
    assert result.final["eval/x_pos"] > 40 and result.final["train/x_pos"] > 40
    assert result.final["eval/flag_get"] == 0.0
