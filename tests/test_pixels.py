"""Pixel preprocessing, frame-stack dedup in the replay, conv Q-networks and epsilon schedules,
against hand-made frames (no ROM needed)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from relayrl.agents.dqn import DQNAgent, DQNConfig
from relayrl.agents.dqn.update import DQNUpdate
from relayrl.config import Config, from_dict
from relayrl.core import Observer
from relayrl.envs import make_env
from relayrl.envs.pixels import SkipFrame, frame_stack_of, mario_preprocessing
from relayrl.errors import ConfigError, UserError
from relayrl.export import load_policy
from relayrl.nn.encoders import ConvEncoder, Encoded
from relayrl.policies import RandomPolicy
from relayrl.replay import Table
from relayrl.schedules import exponential_schedule
from relayrl.specs import ArraySpec, DiscreteSpec, spec_from_space
from relayrl.training.actor import Actor
from relayrl.training.replay_setup import build_replay, frame_stack
from relayrl.types import Batch, Transition


def shade(episode: int, t: int) -> int:
    """A distinct gray level per (episode, inner step)."""
    return (40 * episode + 3 * t) % 250


class PixelCountdown(gym.Env):
    """Uniform RGB frames [24, 24, 3] of gray level shade(episode, t); reward t after step t.

    Episodes alternate between 9 and 30 inner steps (terminated), so with skip 4 and a time
    limit some end by termination and some by truncation."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 60}

    def __init__(self, render_mode: str | None = None, size: int = 24) -> None:
        self.observation_space = gym.spaces.Box(0, 255, (size, size, 3), np.uint8)
        self.action_space = gym.spaces.Discrete(3)
        self.render_mode, self.size = render_mode, size
        self.t, self.episode = 0, -1

    def frame(self) -> np.ndarray:
        return np.full((self.size, self.size, 3), shade(self.episode, self.t), np.uint8)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.t, self.episode = 0, self.episode + 1
        return self.frame(), {}

    def step(self, action):
        self.t += 1
        return self.frame(), float(self.t), self.t >= (9 if self.episode % 2 == 0 else 30), False, {}

    def render(self):
        return self.frame()


class StackedPixelCountdown(gym.Wrapper):
    """PixelCountdown under the Mario tutorial's stack, as a `package.module:Class` env id."""

    def __init__(self, render_mode: str | None = None) -> None:
        super().__init__(mario_preprocessing(PixelCountdown(render_mode)))


def gray(level: int) -> int:
    """Gymnasium's luma of a uniform (level, level, level) frame, as a uint8."""
    return int(np.uint8(np.sum(np.full(3, level) * np.array([0.2125, 0.7154, 0.0721]))))


def test_skip_frame_sums_rewards_and_returns_the_last_frame():
    env = SkipFrame(PixelCountdown(), 4)
    env.reset()
    obs, reward, terminated, _, _ = env.step(0)
    assert reward == 1 + 2 + 3 + 4 and obs[0, 0, 0] == shade(0, 4) and not terminated
    env.step(0)
    obs, reward, terminated, _, _ = env.step(0)  # inner steps 9 (terminates) stops the repeat
    assert terminated and reward == 9 and obs[0, 0, 0] == shade(0, 9)


def test_max_pool_skip_takes_the_max_of_the_last_two_frames():
    class Flicker(PixelCountdown):  # odd inner steps are black: a sprite that flickers
        def frame(self):
            return np.zeros_like(super().frame()) if self.t % 2 else super().frame()

    env = mario_preprocessing(Flicker(), max_pool=True)
    env.reset()
    obs, reward, *_ = env.step(0)
    assert reward == 10 and (obs[-1] == gray(shade(0, 4))).all()
    plain = mario_preprocessing(Flicker())
    plain.reset()
    assert (plain.step(0)[0][-1] == gray(shade(0, 4))).all()  # step 4 is even: lit either way


def test_grayscale_resize_and_stack_of_hand_made_frames():
    env = mario_preprocessing(PixelCountdown())
    assert env.observation_space.shape == (4, 84, 84) and env.observation_space.dtype == np.uint8
    obs, _ = env.reset()
    assert obs.dtype == np.uint8 and obs.shape == (4, 84, 84)
    assert [int(f[0, 0]) for f in obs] == [gray(shade(0, 0))] * 4  # reset padding repeats frame 0
    obs, *_ = env.step(0)
    assert [int(f[0, 0]) for f in obs] == [gray(shade(0, 0))] * 3 + [gray(shade(0, 4))]
    obs, *_ = env.step(0)
    assert [int(f[5, 7]) for f in obs] == [gray(shade(0, t)) for t in (0, 0, 4, 8)]


def test_grayscale_weights_and_area_resize():
    half = np.zeros((168, 168, 3), np.uint8)
    half[:, 84:] = (255, 0, 0)  # right half pure red
    env = mario_preprocessing(PixelCountdown(size=168))
    env.unwrapped.frame = lambda: half
    obs, _ = env.reset()
    assert (obs[-1][:, :42] == 0).all() and (obs[-1][:, 42:] == int(255 * 0.2125)).all()


def test_frame_stack_of_detects_only_reset_padded_outer_stacks():
    assert frame_stack_of(mario_preprocessing(PixelCountdown())) == 4
    assert frame_stack_of(gym.wrappers.TimeLimit(mario_preprocessing(PixelCountdown()), 10)) == 4
    assert frame_stack_of(PixelCountdown()) == 1
    zero = gym.wrappers.FrameStackObservation(PixelCountdown(), 4, padding_type="zero")
    assert frame_stack_of(zero) == 1  # stacks start with zeros, not the first frame
    negated = gym.wrappers.TransformObservation(mario_preprocessing(PixelCountdown()), lambda o: o[::-1], None)
    assert frame_stack_of(negated) == 1  # a transform of whole stacks hides the frame order


def test_specs_mark_stacks_and_the_replay_stores_one_frame_per_step(tmp_path):
    env = make_env("test_pixels:StackedPixelCountdown", 2)
    spec = env.observation_spec
    assert spec.shape == (4, 84, 84) and spec.dtype == torch.uint8 and spec.frame_stack == 4
    assert frame_stack(spec) == 4 and frame_stack(ArraySpec((4, 84, 84), torch.uint8)) == 1
    c = from_dict({"replay": {"size": 1000}})
    _, stacked = build_replay(c, spec, env.action_spec, tmp_path)
    _, whole = build_replay(c, ArraySpec((4, 84, 84), torch.uint8), env.action_spec, tmp_path)
    # One env (c.env.num_envs = 1); rows differ only by the stacking look-back (k - 1 rows).
    assert stacked.table.storage.store.frame.nbytes == stacked.table.storage.rows * 84 * 84
    assert whole.table.storage.store.frame.nbytes == whole.table.storage.rows * 4 * 84 * 84
    assert stacked.table.storage.store.nbytes() < whole.table.storage.store.nbytes() / 3


class Naive(Observer):
    """Observer keeping every transition as a plain copy: what a naive replay would store."""

    def __init__(self, gamma: float) -> None:
        self.gamma, self.rows, self.last = gamma, [], {}

    def __call__(self, t: Transition) -> None:
        for i in range(t.obs.shape[0]):
            self.rows.append((t.obs[i].numpy().tobytes(), int(t.action[i]), float(t.reward[i]),
                              t.next_obs[i].numpy().tobytes(), 0.0 if t.terminated[i] else self.gamma))
            self.last[i] = (len(self.rows) - 1, bool(t.terminated[i] | t.truncated[i]))

    def closed(self) -> list[tuple]:
        """The rows a replay holds as items: a running episode's newest step waits for the next
        step, whose observation row is its next observation (as in Reverb's writers)."""
        pending = {row for row, done in self.last.values() if not done}
        return [r for j, r in enumerate(self.rows) if j not in pending]


@pytest.mark.parametrize("num_envs", [1, 2])
def test_stacks_rebuilt_by_the_replay_equal_a_naive_replay_across_episodes(tmp_path, num_envs):
    env = make_env("test_pixels:StackedPixelCountdown", num_envs, max_episode_steps=5)
    c = from_dict({"replay": {"size": 1000}, "env": {"num_envs": num_envs}})
    table, writer = build_replay(c, env.observation_spec, env.action_spec, tmp_path)
    assert writer.table.storage.store.frame_stack == 4
    naive = Naive(c.agent.gamma)
    actor = Actor(env, RandomPolicy(env.action_spec, np.random.default_rng(0)), [writer, naive], seed=0)
    actor.collect(60)
    ends = [r for r in naive.rows if r[4] == 0.0]
    assert ends and len(ends) < len(naive.rows)  # terminations, and truncations by the time limit
    live = np.flatnonzero(table.slot_key >= 0)
    b = writer.table.storage.read(live)
    stored = sorted((o.numpy().tobytes(), int(a), float(r), n.numpy().tobytes(), round(float(d), 6))
                    for o, a, r, n, d in zip(b.obs, b.action, b.reward, b.next_obs, b.discount, strict=True))
    assert b.obs.dtype == torch.uint8 and b.obs.shape[1:] == (4, 84, 84)
    assert stored == sorted((o, a, r, n, round(d, 6)) for o, a, r, n, d in naive.closed())
    assert len(stored) >= 60 - num_envs


@pytest.mark.parametrize("network", ["nature_cnn", "mario_cnn"])
def test_conv_q_networks_shapes_and_uint8_scaling(network):
    cfg = DQNConfig(network=network)
    agent = DQNAgent(ArraySpec((4, 84, 84), torch.uint8), DiscreteSpec(6), cfg, torch.device("cpu"),
                     np.random.default_rng(0))
    net = agent.online
    assert isinstance(net, Encoded) and isinstance(net.encoder, ConvEncoder) and type(agent.update) is DQNUpdate
    assert net.encoder.dense[0].in_features == 3136  # 64 x 7 x 7 at 84x84, as in Mnih et al. 2015
    x = torch.randint(0, 256, (5, 4, 84, 84), dtype=torch.uint8)
    q = net(x)
    assert q.shape == (5, 6) and q.dtype == torch.float32
    torch.testing.assert_close(q, net(x.float() / 255.0))
    other = DQNAgent(ArraySpec((2, 60, 40), torch.uint8), DiscreteSpec(3), cfg, torch.device("cpu"),
                     np.random.default_rng(0)).online
    assert other(torch.zeros(1, 2, 60, 40, dtype=torch.uint8)).shape == (1, 3)


def test_conv_dqn_trains_on_uint8_batches_and_its_saved_policy_acts_the_same(tmp_path):
    cfg = DQNConfig(network="nature_cnn", double=True, target_update_period=2, lr=1e-3)
    agent = DQNAgent(ArraySpec((4, 84, 84), torch.uint8), DiscreteSpec(3), cfg, torch.device("cpu"),
                     np.random.default_rng(0))
    g = torch.Generator().manual_seed(0)
    obs = torch.randint(0, 256, (8, 4, 84, 84), dtype=torch.uint8, generator=g)
    batch = Batch(obs, torch.randint(0, 3, (8,), generator=g), torch.ones(8), obs.flip(0), torch.full((8,), 0.99), None)
    before = agent.online(obs).detach()
    for _ in range(3):
        metrics = agent.train(batch)
    assert torch.isfinite(metrics["loss"]) and not torch.equal(before, agent.online(obs).detach())
    torch.save(agent.policy_state(), tmp_path / "policy.pt")
    policy = load_policy(tmp_path / "policy.pt")
    assert torch.equal(policy(obs), agent.eval_policy()(obs))


@pytest.mark.parametrize("dict_obs", [False, True])
def test_a_saved_policy_takes_flipped_frames(tmp_path, dict_obs):
    # img[..., ::-1] (BGR -> RGB) and np.flip give views with negative strides, which torch.as_tensor
    # refuses: the policy raised torch's ValueError instead of acting
    frame = gym.spaces.Box(0, 255, (16, 16, 3), np.uint8)
    space = gym.spaces.Dict({"image": frame, "vec": gym.spaces.Box(-1.0, 1.0, (2,), np.float32)}) if dict_obs else frame
    agent = DQNAgent(spec_from_space(space, "observation"), DiscreteSpec(3), DQNConfig(), torch.device("cpu"),
                     np.random.default_rng(0))
    torch.save(agent.policy_state(), tmp_path / "policy.pt")
    policy = load_policy(tmp_path / "policy.pt")
    frames = np.random.default_rng(0).integers(0, 256, (5, 16, 16, 3), dtype=np.uint8)[..., ::-1]
    one, batch = frames[0], frames
    if dict_obs:
        vec = np.zeros((5, 2), np.float32)
        one, batch = {"image": frames[0], "vec": vec[0]}, {"image": frames, "vec": vec}
    copied = {k: np.ascontiguousarray(v) for k, v in batch.items()} if dict_obs else np.ascontiguousarray(batch)
    assert np.array_equal(policy(batch), policy(copied))
    assert policy(one) == policy(copied)[0] and policy.predict(one)[0] == policy(copied)[0]


def test_policy_files_and_checkpoints_of_the_former_conv_q_network_load(tmp_path):
    """Before the Atari net was the Nature CNN encoder + a linear head it was its own module:
    its policy files ("network", "obs_shape", keys convs.* / head.0.* / head.2.*) and agent
    states load as today's network, acting the same."""
    import relayrl
    from relayrl.policy_file import save_policy_file

    cfg = DQNConfig(network="nature_cnn", target_update_period=100)
    agent = DQNAgent(ArraySpec((4, 84, 84), torch.uint8), DiscreteSpec(6), cfg, torch.device("cpu"),
                     np.random.default_rng(0))
    renames = {"encoder.convs.": "convs.", "encoder.dense.0.": "head.0.", "head.layers.0.": "head.2."}

    def former(state_dict):
        return {next(o + k[len(n):] for n, o in renames.items() if k.startswith(n)): v for k, v in state_dict.items()}

    weights = {k: v.detach().clone() for k, v in agent.online.state_dict().items()}
    save_policy_file({"kind": "q_greedy", "network": "nature_cnn", "obs_shape": [4, 84, 84], "num_actions": 6,
                      "state_dict": former(weights), "env_id": "relayrl/Atari-Pong-v0"}, tmp_path / "old.pt")
    frames = torch.randint(0, 256, (3, 4, 84, 84), dtype=torch.uint8)
    assert torch.equal(relayrl.load_policy(tmp_path / "old.pt")(frames), agent.eval_policy()(frames))
    state = agent.state_dict()
    again = DQNAgent(ArraySpec((4, 84, 84), torch.uint8), DiscreteSpec(6), cfg, torch.device("cpu"),
                     np.random.default_rng(1))
    assert state["target"] is not None
    again.load_state_dict({**state, "online": former(state["online"]), "target": former(state["target"])})
    assert all(torch.equal(v, weights[k]) for k, v in again.online.state_dict().items())


@pytest.mark.parametrize("obs, said", [
    (ArraySpec((4,), torch.float32), "needs uint8 frames .*: use agent.network='mlp' \\(the default\\) for "
                                     "observations that are not frames$"),
    (ArraySpec((4, 12, 12), torch.uint8), "needs frames of at least 36x36, got .*: use agent.network='mlp' with "
                                          "agent.encoder='auto' or 'small_cnn'"),
    # frames the network does not take, the encoder suggested fits their size
    (ArraySpec((20, 20), torch.uint8), "needs uint8 frames .*: use agent.network='mlp' with agent.encoder='auto' or "
                                       "'small_cnn'"),
    (ArraySpec((40, 40, 3), torch.uint8), "needs uint8 frames .*: use agent.network='mlp' with agent.encoder='auto' "
                                          "or 'nature_cnn'"),
])
def test_conv_network_needs_image_observations(obs, said):
    with pytest.raises(UserError, match=said):
        DQNAgent(obs, DiscreteSpec(2), DQNConfig(network="nature_cnn"), torch.device("cpu"), np.random.default_rng(0))


def test_exponential_epsilon_schedule():
    eps = exponential_schedule(1.0, 0.1, 0.99999975)
    assert eps(0) == 1.0
    assert eps(1) == pytest.approx(0.99999975)
    assert eps(1_000_000) == pytest.approx(0.99999975 ** 1_000_000)  # ~0.779, the tutorial's value
    assert eps(10_000_000) == 0.1  # floored: 0.99999975^1e7 ~ 0.082
    agent = DQNAgent(ArraySpec((2,), torch.float32), DiscreteSpec(2),
                     DQNConfig(epsilon_schedule="exponential", epsilon_end=0.1), torch.device("cpu"),
                     np.random.default_rng(0))
    steps = [0]
    policy = agent.collect_policy(lambda: steps[0])
    assert policy.epsilon(0) == 1.0
    steps[0] = 4_000_000
    assert policy.epsilon(steps[0]) == pytest.approx(0.99999975 ** 4_000_000)


def test_config_keys_for_pixels_are_checked():
    c = from_dict({"agent": {"network": "nature_cnn", "epsilon_schedule": "exponential"}})
    assert c.agent.network == "nature_cnn" and Config().agent.network == "mlp"
    for bad in ({"network": "resnet"}, {"epsilon_schedule": "cosine"}, {"epsilon_decay": 1.5}):
        with pytest.raises(ConfigError):
            from_dict({"agent": bad})


@pytest.mark.parametrize("encoder", ["small_cnn", "flatten", "tests.space_envs:FlatEncoder"])
def test_an_encoder_beside_the_conv_network_is_refused_not_ignored(encoder):
    # agent.network builds the Nature CNN whatever agent.encoder says: naming one was silently unused
    with pytest.raises(ConfigError, match="agent.encoder.*does not apply with agent.network='nature_cnn'"):
        from_dict({"agent": {"network": "nature_cnn", "encoder": encoder}})
    for fine in ("auto", "nature_cnn"):
        assert from_dict({"agent": {"network": "nature_cnn", "encoder": fine}}).agent.encoder == fine


def test_a_table_writer_rejects_stacked_specs_that_do_not_match():
    with pytest.raises(ValueError, match="frame_stack"):
        from relayrl.replay import TransitionWriter

        TransitionWriter(Table("t", 10), 1, ArraySpec((3, 84, 84), torch.uint8), DiscreteSpec(2), gamma=0.9,
                         frame_stack=4)
