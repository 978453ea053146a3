"""relayrl/MinitaurBullet-v0: pybullet's Minitaur on Gymnasium's API (the `bullet` extra)."""

import re
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch

from relayrl.envs import make_env
from relayrl.errors import UserError

ENV_ID = "relayrl/MinitaurBullet-v0"


@pytest.fixture
def bullet():
    # Per test, not per module: the missing-pybullet test below must run where pybullet is absent.
    return pytest.importorskip("pybullet")


def _actions(n: int) -> np.ndarray:
    return np.random.default_rng(0).uniform(-1, 1, (n, 8)).astype(np.float32)


def test_registered_without_importing_pybullet():
    spec = gym.spec(ENV_ID)
    assert spec.max_episode_steps == 1000
    assert spec.entry_point == "relayrl.envs.minitaur:MinitaurEnv"  # a string: nothing imported yet


def test_missing_pybullet_is_a_user_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "pybullet", None)  # makes `import pybullet` raise ImportError
    message = re.escape("relayrl/MinitaurBullet-v0 needs pybullet: pip install -e \".[bullet]\" in relayrl's folder")
    with pytest.raises(UserError, match=message):
        gym.make(ENV_ID)
    with pytest.raises(UserError, match=message):
        make_env(ENV_ID, 1)


def test_spaces_and_step_types(bullet):
    env = gym.make(ENV_ID)
    try:
        assert env.observation_space.shape == (28,) and env.observation_space.dtype == np.float32
        assert env.action_space == gym.spaces.Box(-1.0, 1.0, (8,), np.float32)
        obs, info = env.reset(seed=0)
        assert obs.shape == (28,) and obs.dtype == np.float32 and isinstance(info, dict)
        assert env.observation_space.contains(obs)
        obs, reward, terminated, truncated, info = env.step(_actions(1)[0])
        assert obs.shape == (28,) and obs.dtype == np.float32
        assert isinstance(reward, float) and terminated is False and truncated is False
    finally:
        env.close()
    # The old-gym and pkg_resources stand-ins exist only while pybullet's module is imported.
    from relayrl.envs.legacy_gym import _GymShim
    from relayrl.envs.minitaur import _parse_version

    assert not isinstance(sys.modules.get("gym"), _GymShim)
    assert getattr(sys.modules.get("pkg_resources"), "parse_version", None) is not _parse_version


def test_seeded_reset_and_actions_are_reproducible(bullet):
    actions = _actions(30)

    def rollout(env: gym.Env, seed: int) -> np.ndarray:
        obs = [env.reset(seed=seed)[0]]
        obs += [env.step(a)[0] for a in actions]
        return np.stack(obs)

    a, b = gym.make(ENV_ID), gym.make(ENV_ID)
    try:
        first = rollout(a, 7)
        np.testing.assert_array_equal(first, rollout(b, 7))  # two envs, same seed
        np.testing.assert_array_equal(first, rollout(a, 7))  # same env, reseeded
        # The seed draws the randomized masses, voltage, damping and friction: it must matter.
        assert not np.array_equal(first, rollout(b, 8))
    finally:
        a.close()
        b.close()


def test_falling_terminates_and_time_limit_truncates(bullet):
    env = gym.make(ENV_ID, max_episode_steps=3)
    try:
        env.reset(seed=0)
        steps = [env.step(np.zeros(8, np.float32))[2:4] for _ in range(3)]
        assert steps == [(False, False), (False, False), (False, True)]
        env.reset(seed=0)
        inner = env.unwrapped._env  # pybullet's MinitaurBulletEnv: turn the robot upside down
        inner._pybullet_client.resetBasePositionAndOrientation(inner.minitaur.quadruped, [0, 0, 0.3], [1, 0, 0, 0])
        _, _, terminated, truncated, _ = env.step(np.zeros(8, np.float32))
        assert terminated and not truncated
    finally:
        env.close()


@pytest.mark.slow  # up to 1000 steps: 4-10 s on a 2-core machine
def test_random_episode_falls_or_is_truncated_at_1000(bullet):
    env = gym.make(ENV_ID)
    try:
        env.reset(seed=2)
        env.action_space.seed(2)
        steps, terminated, truncated = 0, False, False
        while not (terminated or truncated) and steps < 1001:  # 1001: a missing time limit fails, not hangs
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            steps += 1
        assert terminated != truncated
        assert steps == 1000 if truncated else steps <= 1000
    finally:
        env.close()


def test_render_rgb_array(bullet):
    env = gym.make(ENV_ID, render_mode="rgb_array")
    try:
        env.reset(seed=0)
        frame = env.render()
        assert frame.shape == (720, 960, 3) and frame.dtype == np.uint8
        assert frame.std() > 0  # a picture, not a blank buffer
    finally:
        env.close()


def test_make_env_batches_two_copies(bullet):
    env = make_env(ENV_ID, 2)
    try:
        obs = env.reset(seed=0)
        assert obs.shape == (2, 28) and obs.dtype == torch.float32
        out = env.step(torch.from_numpy(_actions(2)))
        assert out.next_obs.shape == (2, 28) and out.reward.shape == (2,)
        assert out.terminated.dtype == torch.bool and not out.truncated.any()
        assert not torch.equal(out.next_obs[0], out.next_obs[1])  # copies are seeded seed + i
    finally:
        env.close()
