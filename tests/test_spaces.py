"""Every space kind each algorithm takes, end to end: a few steps of training on
`space_envs:Spaces`, then the loaded policy and the exported program are called on what
`env.reset()` returns (one observation, a batch, NumPy and torch) and the env is stepped with
the action; plus the encoders, the packed layout of Dict / Tuple observations, the messages for
spaces an algorithm does not take, and a Discrete-observation env that must be learnt."""

from __future__ import annotations

import importlib.util
import json

import gymnasium as gym
import numpy as np
import pytest
import torch
from space_envs import OBS_KINDS, FlatEncoder, Spaces, observation_space, stacked
from torch import nn

import relayrl
from relayrl.errors import UserError
from relayrl.export import EnvShaped
from relayrl.frames import frame_layout, image_layout
from relayrl.nn.encoders import ConvEncoder, DictEncoder, OneHot, make_encoder
from relayrl.specs import (
    PackedSpec,
    is_image,
    spec_from_space,
    spec_from_state,
    spec_state,
    unpack,
)

# algo -> the action kinds it takes
# (box_scalar: Box shape (), box2d: Box (2, 2): actions that travel flat, in the env's shape at its ends)
# (box_fixed: low == high in one dimension, which holds one value; SAC refuses it)
# (box_unbounded: an infinite bound; PPO clips to it, as Stable-Baselines3 does; SAC refuses it)
# (box_f16, multi_discrete_i32: spaces of another dtype than the one stored; actions reach the env in it)
ACTIONS = {"dqn": ("discrete",), "sac": ("box", "box_scalar", "box2d", "box_f16"),
           "ppo": ("discrete", "box", "box_scalar", "box2d", "box_fixed", "box_f16", "box_unbounded", "multi_discrete",
                   "multi_discrete_i32", "multi_binary")}
CASES = ([(algo, obs, ACTIONS[algo][0]) for algo in ACTIONS for obs in OBS_KINDS]
         + [("sac", "box", act) for act in ACTIONS["sac"][1:]]
         + [("ppo", obs, act) for act in ACTIONS["ppo"][1:] for obs in ("box", "dict")])
ONNX = {("dqn", "dict", "discrete"), ("sac", "tuple", "box"), ("ppo", "image_hwc", "multi_discrete"),
        ("ppo", "dict", "multi_binary"), ("sac", "box", "box2d"), ("ppo", "dict", "box_scalar")}


def short_config(algo: str, obs: str, act: str, vectorization: str = "sync"):
    preset = {"dqn": "dqn-cartpole-fast", "sac": "sac-pendulum", "ppo": "ppo-cartpole"}[algo]
    over = ["env.id=space_envs:Spaces", f"env.kwargs={{obs = '{obs}', act = '{act}'}}", "env.num_envs=2",
            "train.total_steps=96", "eval.interval=96", "eval.episodes=2", "env.max_episode_steps=16",
            "train.checkpoint_interval=0", f"env.vectorization={vectorization}"]
    if algo == "ppo":
        over += ["train.collect_steps=16", "agent.batch_size=16", "agent.n_epochs=1", "agent.hidden=[16]"]
    elif algo == "sac":
        over += ["train.initial_collect_steps=32", "agent.batch_size=8", "agent.actor_hidden=[16]",
                 "agent.critic_hidden=[16]"]
    else:
        over += ["train.initial_collect_steps=32", "agent.batch_size=8", "agent.hidden=[16]"]
    return relayrl.load_config(preset, over)


def stack(obs_list):
    """A batch of observations as a vector env returns it (a dict / tuple of stacked entries)."""
    first = obs_list[0]
    if isinstance(first, dict):
        return {k: np.stack([o[k] for o in obs_list]) for k in first}
    if isinstance(first, tuple):
        return tuple(np.stack([np.asarray(o[i]) for o in obs_list]) for i in range(len(first)))
    return np.stack([np.asarray(o) for o in obs_list])


def to_torch(obs):
    if isinstance(obs, dict):
        return {k: torch.as_tensor(v) for k, v in obs.items()}
    if isinstance(obs, tuple):
        return tuple(torch.as_tensor(np.asarray(v)) for v in obs)
    return torch.as_tensor(np.asarray(obs))


def assert_valid(space: gym.Space, action) -> None:
    a = np.asarray(action)  # in the space's own dtype (contains checks it)
    assert space.contains(int(a) if isinstance(space, gym.spaces.Discrete) else a), (action, a.dtype, space)


@pytest.mark.parametrize(("algo", "obs", "act"), CASES)
def test_trained_policy_takes_the_envs_own_observations(algo, obs, act, tmp_path):
    # actions travel in the env's shape to worker processes too (async: one copy in a worker)
    vectorization = "async" if act in ("box_scalar", "box2d") and obs == "box" else "sync"
    relayrl.train(short_config(algo, obs, act, vectorization), tmp_path, progress=False)
    policy = relayrl.load_policy(tmp_path)
    env = Spaces(obs, act)
    assert policy.action_space == env.action_space  # SB3's model.action_space, from the file
    assert type(policy.observation_space) is type(env.observation_space)
    assert policy.observation_space.shape == env.observation_space.shape
    o, _ = env.reset(seed=0)
    assert policy.observation_space.contains(policy.observation_space.sample())
    a = policy(o)
    assert_valid(env.action_space, a)
    if isinstance(env.action_space, gym.spaces.Box):  # an array of the space's shape, a scalar Box's too
        assert isinstance(a, np.ndarray) and a.shape == env.action_space.shape, (type(a), np.shape(a))
    env.step(a)
    # a batch, NumPy and torch: the same actions as one at a time
    obs_list = [env.reset(seed=s)[0] for s in range(3)]
    batched = policy(stack(obs_list))
    np.testing.assert_allclose(batched, np.stack([np.asarray(policy(x)) for x in obs_list]), atol=1e-6)
    np.testing.assert_allclose(policy(to_torch(stack(obs_list))).numpy(), batched, atol=1e-6)
    for a in batched:
        assert_valid(env.action_space, a)
    # evaluation in the mode the policy was not loaded in (SB3's evaluate_policy(deterministic=False))
    for deterministic in (True, False):
        returns, _ = relayrl.evaluate(policy, lambda: Spaces(obs, act), episodes=2, deterministic=deterministic,
                                      return_episode_rewards=True)
        assert len(returns) == 2
    # the exported program takes the env's observation: one input, or one per Dict / Tuple entry
    has_onnx = all(importlib.util.find_spec(m) for m in ("onnx", "onnxscript", "onnxruntime"))
    formats = ("pt2", "onnx") if (algo, obs, act) in ONNX and has_onnx else ("pt2",)
    for fmt in formats:
        path = relayrl.export_policy(tmp_path, format=fmt)
        sig = json.loads(path.with_name(path.name + ".json").read_text())
        inputs = sig["inputs"] if "inputs" in sig else [sig["input"]]
        assert ("input" in sig) != ("inputs" in sig)  # one tensor's, or every entry's: never the first alone
        entries = ([o[i["name"]] for i in inputs] if isinstance(o, dict)
                   else [o[int(i["name"])] for i in inputs] if isinstance(o, tuple) else [o])
        feeds = [np.asarray(e)[None] for e in entries]  # as the env gives them: the program takes their dtype
        assert [f.dtype.name for f in feeds] == [i["dtype"] for i in inputs]
        if fmt == "pt2":
            out = torch.export.load(path).module()(*map(torch.from_numpy, feeds)).numpy()
        else:
            import onnxruntime

            session = onnxruntime.InferenceSession(str(path))
            out = session.run(None, {i["name"]: f for i, f in zip(inputs, feeds, strict=True)})[0]
        np.testing.assert_allclose(out[0], np.asarray(policy(o)), atol=1e-5)


@pytest.mark.parametrize("algo", sorted(ACTIONS))
def test_float_images_train_a_conv_net_when_asked_for_by_name_and_auto_says_it_flattens(algo, tmp_path, capsys):
    """Frames scaled to [0, 1] (a wrapper dividing by 255): 'auto' flattened them without a word, and
    asking for a conv net was refused, its advice pointing back at 'auto'."""
    config = short_config(algo, "image_float", ACTIONS[algo][0])
    relayrl.train(config, tmp_path / "auto", progress=False)
    assert ("agent.encoder='auto' flattens the float images Box(0, 1, shape=(12, 12, 1), dtype=float32) into the "
            "MLP") in capsys.readouterr().err
    config.agent.encoder = "small_cnn"
    relayrl.train(config, tmp_path / "cnn", progress=False)
    assert "flattens" not in capsys.readouterr().err
    weights = torch.load(tmp_path / "cnn" / "policy" / "policy.pt", weights_only=True)["state_dict"]
    assert any("convs.0.weight" in k for k in weights), sorted(weights)
    policy = relayrl.load_policy(tmp_path / "cnn")
    env = Spaces("image_float", ACTIONS[algo][0])
    o, _ = env.reset(seed=0)
    program = torch.export.load(relayrl.export_policy(tmp_path / "cnn", format="pt2")).module()
    np.testing.assert_allclose(program(torch.from_numpy(o[None])).numpy()[0], np.asarray(policy(o)), atol=1e-5)


@pytest.mark.parametrize("algo", sorted(ACTIONS))
def test_a_users_own_encoder_trains_and_its_policy_loads_and_exports(algo, tmp_path):
    act = ACTIONS[algo][0]
    config = short_config(algo, "dict", act)
    config.agent.encoder = "space_envs:FlatEncoder"
    relayrl.train(config, tmp_path, progress=False)
    FlatEncoder.built = 0
    policy = relayrl.load_policy(tmp_path)  # built again from the module, by name
    assert FlatEncoder.built == 1  # made once: a costly encoder (a pretrained backbone) is paid for once
    env = Spaces("dict", act)
    o, _ = env.reset(seed=0)
    assert_valid(env.action_space, policy(o))
    path = relayrl.export_policy(tmp_path)
    inputs = json.loads(path.with_name(path.name + ".json").read_text())["inputs"]
    feeds = [torch.from_numpy(np.asarray(o[i["name"]])[None]) for i in inputs]
    np.testing.assert_allclose(torch.export.load(path).module()(*feeds).numpy()[0], np.asarray(policy(o)), atol=1e-5)


@pytest.mark.parametrize("algo", sorted(ACTIONS))
def test_a_users_encoder_with_a_layer_it_leaves_unused_trains(algo, tmp_path):
    """Its layer gets no gradient; the optimizers leave it as torch.optim.Adam does."""
    config = short_config(algo, "dict", ACTIONS[algo][0])
    config.agent.encoder = "space_envs:WithSpareLayer"
    relayrl.train(config, tmp_path, progress=False)


def test_a_policy_file_on_its_own_runs_no_encoder_code_unless_trusted(tmp_path, monkeypatch, capsys):
    """A shared policy.pt runs no code (README: What is safe to load): one whose network a user's
    module builds is refused before the module is imported, unless the caller trusts that code;
    in its run directory it is the run's own."""
    import shutil
    import sys

    from relayrl.cli import main

    config = short_config("ppo", "dict", "discrete")
    config.agent.encoder = "space_envs:FlatEncoder"
    relayrl.train(config, tmp_path / "run", progress=False)
    shutil.copy(tmp_path / "run" / "policy" / "policy.pt", tmp_path / "shared.pt")
    monkeypatch.delitem(sys.modules, "space_envs")  # imported again only where trusted
    shared = tmp_path / "shared.pt"
    for load in (lambda: relayrl.load_policy(shared), lambda: relayrl.export_policy(shared)):
        with pytest.raises(UserError, match=r"has its network built by 'space_envs:FlatEncoder', code it would import "
                                            r"and run, which a policy file on its own is not trusted to"):
            load()
        assert "space_envs" not in sys.modules
    assert main(["eval", str(tmp_path / "shared.pt"), "--env", "space_envs:Spaces"]) == 2
    assert "--trust-code" in capsys.readouterr().err
    relayrl.load_policy(tmp_path / "run" / "policy" / "policy.pt")  # the run's own
    relayrl.load_policy(tmp_path / "shared.pt", trust_code=True)
    assert main(["export", str(tmp_path / "shared.pt"), "--trust-code", "--out", str(tmp_path / "p.pt2")]) == 0


def test_a_policy_whose_encoder_code_changed_since_the_run_says_so(tmp_path, monkeypatch):
    config = short_config("ppo", "dict", "discrete")
    config.agent.encoder = "space_envs:FlatEncoder"
    config.train.checkpoint_interval = 96
    relayrl.train(config, tmp_path, progress=False)
    import space_envs

    monkeypatch.setattr(space_envs.FlatEncoder, "__init__", lambda self, space: (
        nn.Module.__init__(self), setattr(self, "linear", nn.LazyLinear(16)))[0])  # 16 features now, not 8
    with pytest.raises(UserError, match=r"its encoder 'space_envs:FlatEncoder' now builds other parameters than the "
                                        r"ones saved \(did its code change since the run\?\)"):
        relayrl.load_policy(tmp_path)
    config.train.total_steps = 192
    with pytest.raises(UserError, match=r"though the run's network settings are the same: agent.encoder='space_envs:"
                                        r"FlatEncoder' now builds other parameters than the run's \(did its code "):
        relayrl.train(config, tmp_path, progress=False, resume=True)



@pytest.mark.parametrize("name, error, note", [
    ("reads_a_missing_entry", KeyError, "called as make(observation_space) with Dict("),
    ("FloatConv", RuntimeError, "on a batch of 1 zero observation: a dict of tensors by entry key ('cell': int64 [1], "
                                "'frame': uint8 [1, 1, 8, 8], 'pos': float32 [1, 2]) (uint8 frames as 0..255"),
])
def test_a_users_encoder_raising_keeps_its_error_with_what_relayrl_gave_it(name, error, note):
    with pytest.raises(error) as caught:
        make_encoder(spec_from_space(Spaces("dict").observation_space), f"space_envs:{name}")
    assert len(caught.value.__notes__) == 1 and note in caught.value.__notes__[0]
    assert caught.value.__notes__[0].startswith("relayrl: raised by ")


def test_a_users_encoder_is_built_from_the_observation_space_and_checked():
    spec = spec_from_space(Spaces("dict").observation_space)
    encoder = make_encoder(spec, "space_envs:FlatEncoder")
    assert encoder.out_dim == 8 and encoder.module.space == gym.spaces.Dict(
        {"cell": gym.spaces.Discrete(4), "frame": gym.spaces.Box(0, 255, (1, 8, 8), np.uint8),
         "pos": gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)})  # a float Box's bounds are not kept
    pair = make_encoder(spec_from_space(Spaces("tuple").observation_space), "space_envs:FlatEncoder")
    assert pair.module.space[1].dtype == np.float32  # the env's float64 entry, in the dtype its batches come in
    flags = make_encoder(spec_from_space(Spaces("box_bool").observation_space), "space_envs:FlatEncoder")
    assert flags.module.space == gym.spaces.Box(0, 1, (3,), bool) and flags.out_dim == 8
    for name, words in (("nosuch_pkg.mod:make", "agent.encoder: 'nosuch_pkg.mod:make': no module 'nosuch_pkg'"),
                        ("space_envs:takes_no_space", r"^agent.encoder='space_envs:takes_no_space' cannot be called "
                                                      r"with the observation space alone \(too many positional "
                                                      r"arguments\); give a function make\(observation_space\)"),
                        ("space_envs:not_a_module", "agent.encoder='space_envs:not_a_module' returned int, not a "
                                                    "torch.nn.Module"),
                        ("space_envs:wrong_shape", r"its module gave dict for a batch of 1 observation of Dict\(.*"
                                                   r"it must give \[B, features\]"),
                        ("space_envs:Squeezed", r"its module gave \(8,\) for a batch of 1 observation of "),
                        ("space_envs:NoFeatures", r"its module gave \(1, 0\) for a batch of 1 observation of .*"
                                                  r"features >= 1")):
        with pytest.raises(UserError, match=words):
            make_encoder(spec, name)
    with pytest.raises(UserError, match=r"agent.encoder='my encoder' is not valid; valid: auto, flatten, nature_cnn, "
                                        r"small_cnn, or package.module:callable"):
        relayrl.load_config("ppo", ["agent.encoder='my encoder'"])
    with pytest.raises(UserError, match=r"agent.encoder='mymodule.make' is not valid; did you mean 'mymodule:make'"):
        relayrl.load_config("ppo", ["agent.encoder='mymodule.make'"])
    with pytest.raises(UserError, match=r"names a function of the script being run, .*'mymodule:make'"):
        relayrl.load_config("ppo", ["agent.encoder='__main__:make'"])
    config = relayrl.load_config("ppo")
    with pytest.raises(UserError, match=r"expected str \(name it as a string: 'space_envs:FlatEncoder'\)"):
        config.agent.encoder = FlatEncoder  # SB3's features_extractor_class=


@pytest.mark.parametrize("kind", OBS_KINDS)
def test_spec_survives_the_policy_file(kind):
    spec = spec_from_space(Spaces(kind).observation_space)
    again = spec_from_state(json.loads(json.dumps(spec_state(spec))))
    assert (type(again), again.shape, again.dtype) == (type(spec), spec.shape, spec.dtype)
    assert is_image(again) == is_image(spec) == (kind in ("image", "image_hwc"))


def test_a_uint8_grid_of_codes_is_numbers_not_an_image():
    board = spec_from_space(gym.spaces.Box(0, 2, (8, 8), np.uint8))
    assert make_encoder(board) is None and not is_image(board)  # an MLP on the codes as they are
    state = spec_state(board)
    assert (state["low"], state["high"]) == (0, 2)  # one number where the bound is the same everywhere
    uneven = spec_from_space(gym.spaces.Box(0, np.arange(64, dtype=np.uint8).reshape(8, 8) + 192, (8, 8), np.uint8))
    again = spec_from_state(json.loads(json.dumps(spec_state(uneven))))
    assert np.array_equal(again.high, uneven.high) and not is_image(again)
    # a policy file from before bounds were kept: its uint8 frames stay an image, as it was trained
    assert is_image(spec_from_state({"kind": "box", "shape": [8, 8], "dtype": "uint8"}))
    asked = make_encoder(board, "small_cnn")  # by name: a conv net on the codes / 255, as SB3 lets one force
    assert isinstance(asked, ConvEncoder)
    with pytest.raises(UserError, match=r"needs image observations \(.*sides >= 8\), got Box\(0, 2, shape=\(4, 4\)"):
        make_encoder(spec_from_space(gym.spaces.Box(0, 2, (4, 4), np.uint8)), "small_cnn")


def test_dict_observations_pack_each_entry_in_its_own_dtype():
    space = gym.spaces.Dict({"img": gym.spaces.Box(0, 255, (2, 3), np.uint8), "v": gym.spaces.Box(-1, 1, (3,)),
                             "n": gym.spaces.Tuple((gym.spaces.Discrete(5), gym.spaces.MultiBinary(2)))})
    spec = spec_from_space(space)
    assert isinstance(spec, PackedSpec) and spec.dtype == torch.uint8
    assert [f.key for f in spec.fields] == ["img", "n.0", "n.1", "v"]
    assert spec.shape[0] == 8 + 8 + 8 + 16  # 6 bytes, 8, 2 and 12, each padded to 8
    obs = [space.sample() for _ in range(4)]
    leaves = unpack(torch.from_numpy(np.stack([spec.pack(o) for o in obs])), spec)
    assert leaves["img"].dtype == torch.uint8 and leaves["v"].dtype == torch.float32
    for i, o in enumerate(obs):
        assert np.array_equal(leaves["img"][i].numpy(), o["img"]) and np.array_equal(leaves["v"][i].numpy(), o["v"])
        assert int(leaves["n.0"][i]) == o["n"][0] and np.array_equal(leaves["n.1"][i].numpy(), o["n"][1])


def test_encoders_one_hot_and_conv_by_size():
    one_hot = make_encoder(spec_from_space(gym.spaces.Discrete(4)))
    assert isinstance(one_hot, OneHot)
    assert one_hot(torch.tensor([2, 0])).tolist() == [[0, 0, 1, 0], [1, 0, 0, 0]]
    multi = make_encoder(spec_from_space(gym.spaces.MultiDiscrete([2, 3])))
    assert multi(torch.tensor([[1, 2]])).tolist() == [[0, 1, 0, 0, 1]]
    small = make_encoder(spec_from_space(gym.spaces.Box(0, 255, (16, 16, 3), np.uint8)))
    nature = make_encoder(spec_from_space(gym.spaces.Box(0, 255, (4, 84, 84), np.uint8)))
    assert isinstance(small, ConvEncoder) and small.channels_last and small.convs[0].kernel_size == (3, 3)
    assert isinstance(nature, ConvEncoder) and not nature.channels_last and nature.convs[0].kernel_size == (8, 8)
    assert make_encoder(spec_from_space(gym.spaces.Box(-1, 1, (10, 4, 4)))) is None  # an MLP on the flat vector
    frames = torch.randint(0, 256, (2, 16, 16, 3), dtype=torch.uint8)
    assert torch.allclose(small(frames), small(frames.float() / 255.0), atol=1e-5)  # uint8 scaled to [0, 1]
    with pytest.raises(UserError, match="nature_cnn' needs frames of at least 36x36"):
        make_encoder(spec_from_space(gym.spaces.Box(0, 255, (16, 16), np.uint8)), "nature_cnn")
    mixed = make_encoder(spec_from_space(Spaces("dict").observation_space))
    assert isinstance(mixed, DictEncoder) and mixed.out_dim == 4 + 256 + 2


@pytest.mark.parametrize(("shape", "layout", "channels"), [
    ((84, 84), "HW", 1), ((4, 84, 84), "CHW", 4), ((84, 84, 3), "HWC", 3), ((1, 12, 12), "CHW", 1),
    ((64, 64, 12), "HWC", 12),  # four RGB frames side by side (SB3's VecFrameStack): the smaller side is channels
    ((64, 64, 2), "HWC", 2),
    ((12, 8, 8), "CHW", 12), ((16, 10, 10), "CHW", 16),  # FrameStackObservation(12) over 8x8 gray frames
    ((4, 64, 64, 3), "SHWC", 12), ((4, 3, 64, 64), "SCHW", 12),  # FrameStackObservation over RGB frames
    ((2, 2, 64), None, None), ((4, 4), None, None), ((2, 3, 4, 5, 6), None, None),  # no 8x8 frame: a vector
])
def test_frames_are_read_with_the_smaller_outer_side_as_channels(shape, layout, channels):
    spec = spec_from_space(gym.spaces.Box(0, 255, shape, np.uint8))
    assert frame_layout(shape) == layout and spec_state(spec)["layout"] == layout
    encoder = make_encoder(spec)
    if layout is None:
        assert encoder is None
        return
    assert encoder.convs[0].in_channels == channels
    frames = torch.randint(0, 256, (2, *shape), dtype=torch.uint8)
    by_hand = frames.movedim(-1, -3) if layout.endswith("C") else frames  # [B, (S,) C, H, W]
    by_hand = by_hand.reshape(2, channels, *by_hand.shape[-2:]).float() / 255.0
    assert torch.allclose(encoder(frames), encoder.dense(encoder.convs(by_hand)), atol=1e-6)


def test_a_policy_file_whose_frames_this_version_reads_another_way_is_one_line():
    """Files without a "layout" were trained by the former rule ([H, W, C] only for 1, 3 or 4
    channels): where it reads a shape as this rule does, or no conv net reads the frames (a
    flattening or a user's encoder), they load; else they are refused."""
    from relayrl.specs import check_trained_layout

    same = {"kind": "box", "shape": [84, 84, 3], "dtype": "uint8", "low": 0, "high": 255}
    check_trained_layout(same)
    assert image_layout(spec_from_state(same)) == (3, True)
    for shape, before in (([64, 64, 12], "CHW"), ([4, 64, 64, 3], "a flat vector")):
        with pytest.raises(UserError, match=rf"observations were read as {before} when this run was trained; this "
                                            r"version reads them as S?HWC \(the smaller outer side is the channels, "
                                            r"the first where only the last two are equal\): train it again"):
            check_trained_layout({**same, "shape": shape})
    board = {**same, "shape": [64, 64, 12], "high": 2}  # not frames: an MLP either way
    check_trained_layout(board)
    with pytest.raises(UserError, match="were read as CHW"):  # unless a conv encoder was asked for by name
        check_trained_layout(board, any_bounds=True)
    check_trained_layout({**same, "shape": [64, 64, 12], "layout": "HWC"})  # recorded by this version
    with pytest.raises(UserError, match="were read as HWC when .* reads them as CHW"):  # stacked 8x8 frames, once HWC
        check_trained_layout({**same, "shape": [12, 8, 8], "layout": "HWC"})
    packed = {"kind": "packed", "tuple": False, "fields": [{"key": "f", "path": ["f"], "spec": {**same,
                                                                                              "shape": [64, 64, 12]}}]}
    with pytest.raises(UserError, match="were read as CHW"):
        check_trained_layout(packed)


def test_an_old_flattened_policy_on_frames_read_another_way_now_still_loads(tmp_path):
    from relayrl.policies import network_state, saved_network

    spec = spec_from_space(gym.spaces.Box(0, 255, (16, 16, 12), np.uint8))
    net = relayrl.nn.MLP(16 * 16 * 12, [8], 2, "relu")
    state = {**network_state(net, spec, "flatten", [8], "relu")}
    del state["obs_space"]["layout"]  # written before layouts were recorded
    frames = torch.randint(0, 256, (3, 16, 16, 12), dtype=torch.uint8)
    assert torch.equal(saved_network(state, 2)(frames), net(frames))


def test_frames_stacked_by_gymnasiums_wrapper_over_rgb_train_a_conv_net(tmp_path):
    """[S, H, W, C] stacks (FrameStackObservation over RGB frames) get one conv net over S * C
    channels, and the replay keeps each step's newest frame only."""
    config = short_config("dqn", "image_hwc", "discrete")
    config.env.wrappers = ["space_envs:stacked"]
    relayrl.train(config, tmp_path / "r", progress=False)
    policy = relayrl.load_policy(tmp_path / "r")
    assert policy.obs_shape == (3, 10, 10, 3)
    obs, _ = stacked(Spaces("image_hwc")).reset(seed=0)
    assert int(policy(obs)) in (0, 1)
    state = torch.load(tmp_path / "r" / "policy" / "policy.pt", weights_only=True)
    assert state["state_dict"]["encoder.convs.0.weight"].shape[1] == 9


@pytest.mark.parametrize(("algo", "act", "words"), [
    ("dqn", "box", "DQN takes a Discrete action space; this env's action space is Box(-1, 1, shape=(2,)"),
    # a Box of another rank travels flat: the message names the env's own shape, not (4,)
    ("dqn", "box2d", "this env's action space is Box(-1, 1, shape=(2, 2), dtype=float32)"),
    ("sac", "discrete", "SAC takes a Box action space of floats with finite low and high; this env's action "
                        "space is Discrete(2) (DQN and PPO take Discrete actions)"),
    ("sac", "multi_binary", "action space is MultiBinary([2]) (PPO takes MultiBinary actions)"),
    ("sac", "box_fixed", "SAC needs low < high in every action dimension; this env's action space Box([-1. ,  0.5], "
                         "[1. , 0.5], shape=(2,), dtype=float32) has low == high at flat index 1"),
    ("sac", "box_unbounded", "SAC takes a Box action space of floats with finite low and high; this env's action "
                             "space is Box([-inf,  -1.], [inf,  1.], shape=(2,), dtype=float32) (PPO takes a Box "
                             "with infinite bounds; SAC needs finite ones (Gymnasium's ClipAction makes them infinite: "
                             "SAC's actions stay in the env's bounds without it"),
    ("dqn", "box", "shape=(2,), dtype=float32) (SAC and PPO take Box actions)"),
    ("dqn", "multi_discrete", "(PPO takes MultiDiscrete actions)"),
])
def test_an_action_space_an_algorithm_does_not_take_is_one_line(algo, act, words, tmp_path):
    with pytest.raises(UserError, match=words.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")
                       .replace("]", r"\]")):
        relayrl.train(short_config(algo, "box", act), tmp_path, progress=False)


def test_ppo_squashing_into_a_box_with_a_fixed_dimension_gives_its_value(tmp_path):
    config = short_config("ppo", "box", "box_fixed")
    config.agent.squash = "tanh"
    relayrl.train(config, tmp_path, progress=False)  # no log 0 in the log-probabilities: no NaN stop
    actions = relayrl.load_policy(tmp_path, deterministic=False, seed=0)(np.zeros((16, 3), np.float32))
    assert (actions[:, 1] == 0.5).all() and (np.abs(actions[:, 0]) <= 1).all()


@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_a_loaded_policy_keeps_a_float64_boxs_own_bounds(algo, tmp_path):
    """float32's rounding of -0.3 is below -0.3: a loaded policy's clipped or saturated action must
    not come out there, and its action_space is the env's own."""
    config = short_config(algo, "box", "box_f64")
    if algo == "ppo":
        config.agent.log_std_init = 3.0  # samples far past the bounds: clipped onto them
    relayrl.train(config, tmp_path, progress=False)
    space = Spaces("box", "box_f64").action_space
    policy = relayrl.load_policy(tmp_path, deterministic=False, seed=0)
    got = policy.action_space  # Box's == is np.allclose: the bounds compared exactly
    assert (got.dtype, got.low.tolist(), got.high.tolist()) == (space.dtype, space.low.tolist(), space.high.tolist())
    actions = policy(np.zeros((256, 3), np.float32))
    if algo == "ppo":
        assert (actions[:, 0] == -0.3).any() and (actions[:, 0] == 0.3).any()
    assert all(space.contains(a) for a in actions)
    one = policy(torch.zeros(1, 3))  # the batched tensor path
    assert one.dtype == torch.float64 and bool(((one >= -0.7) & (one <= 0.7)).all())
    program = torch.export.load(relayrl.export_policy(tmp_path)).module()  # the exported policy clips so too
    np.testing.assert_array_equal(program(torch.zeros(4, 3)).numpy(), relayrl.load_policy(tmp_path)(np.zeros((4, 3))))
    bounds = tuple(torch.tensor(b, dtype=torch.float64) for b in ([-0.3, -0.7], [0.3, 0.7]))
    at_bounds = EnvShaped(torch.nn.Identity(), None, torch.float64, bounds)(torch.tensor([[-0.3, 0.3]]))  # float32
    assert at_bounds.tolist() == [[-0.3, 0.30000001192092896]]  # float32's -0.3 is below the bound, its 0.3 inside


def test_ppo_clips_to_an_unbounded_box_and_refuses_to_squash_into_it(tmp_path):
    relayrl.train(short_config("ppo", "box", "box_unbounded"), tmp_path / "clip", progress=False)
    actions = relayrl.load_policy(tmp_path / "clip", deterministic=False, seed=0)(np.zeros((64, 3), np.float32))
    assert np.isfinite(actions).all() and (np.abs(actions[:, 1]) <= 1).all()
    config = short_config("ppo", "box", "box_unbounded")
    config.agent.squash = "tanh"
    with pytest.raises(UserError, match=r"agent.squash='tanh' squashes actions into finite bounds; this env's "
                                        r"action space is Box\(\[-inf,  -1.\], .*: use agent.squash='clip'"):
        relayrl.train(config, tmp_path / "tanh", progress=False)


def test_unsupported_spaces_name_the_space_and_what_is_valid():
    with pytest.raises(UserError, match=r"^observation space Text is not supported; valid observation spaces: Box, "
                                        r"Discrete, MultiDiscrete, MultiBinary, Dict, Tuple$"):
        spec_from_space(gym.spaces.Text(5), "observation")
    # MiniGrid's mission: the entry is named, and how to train on the rest
    mission = gym.spaces.Dict({"image": gym.spaces.Box(0, 255, (7, 7, 3), np.uint8), "mission": gym.spaces.Text(9)})
    with pytest.raises(UserError, match=r"^the observation's entry 'mission': observation space Text is not "
                                        r"supported; .*; an env.wrappers entry that leaves 'mission' out "
                                        r"\(a function of the env returning gymnasium.wrappers.FilterObservation"):
        spec_from_space(mission, "observation")
    nested = gym.spaces.Dict({"pos": gym.spaces.Box(-1, 1, (2,)), "inner": gym.spaces.Tuple(
        (gym.spaces.Discrete(2), gym.spaces.Discrete(3, start=1)))})  # the entry a wrapper must shift is named
    with pytest.raises(UserError, match=r"^the observation's entry 'inner.1': observation space Discrete\(3, "
                                        r"start=1\) starts at 1"):
        spec_from_space(nested, "observation")
    with pytest.raises(UserError, match=r"action space Dict\(.*valid action spaces: .*PPO: Discrete, Box, "
                                        r"MultiDiscrete, MultiBinary"):
        spec_from_space(gym.spaces.Dict({"a": gym.spaces.Discrete(2)}), "action")
    with pytest.raises(UserError, match=r"action space Box\(\[\], \[\], \(0,\), float32\) has no dimensions"):
        spec_from_space(gym.spaces.Box(-1.0, 1.0, (0,), np.float32), "action")
    with pytest.raises(UserError, match=r"action space MultiDiscrete\(\[\]\) has no dimensions"):
        spec_from_space(gym.spaces.MultiDiscrete([]), "action")
    assert spec_from_space(gym.spaces.Box(-1.0, 1.0, (0,), np.float32), "observation").shape == (0,)


def test_spaces_are_described_with_their_bounds_and_kind():
    from relayrl.specs import describe

    assert describe(spec_from_space(gym.spaces.Box(-3, 3, (2,), np.int64))) == "Box(-3, 3, shape=(2,), dtype=int64)"
    # the env's own dtype, not the one relayrl stores (int32 as int64, float64 as float32)
    assert describe(spec_from_space(gym.spaces.Box(0, 9, (2,), np.int32))) == "Box(0, 9, shape=(2,), dtype=int32)"
    in_dict = spec_from_space(gym.spaces.Dict({"x": gym.spaces.Box(-1.0, 1.0, (1,), np.float64)}))
    assert describe(in_dict) == "Dict(x: Box(-1, 1, shape=(1,), dtype=float64))"
    low, high = np.array([-1.0, 0.5], np.float32), np.array([1.0, 0.5], np.float32)
    assert describe(spec_from_space(gym.spaces.Box(low, high))) == ("Box([-1. ,  0.5], [1. , 0.5], shape=(2,), "
                                                                    "dtype=float32)")
    assert describe(spec_from_space(gym.spaces.Box(-np.inf, np.inf, (3,)))).startswith("Box(-inf, inf, ")
    tup = gym.spaces.Tuple((gym.spaces.Discrete(32), gym.spaces.Discrete(11)))
    assert describe(spec_from_space(tup)) == "Tuple(Discrete(32), Discrete(11))"
    for role in ("observation", "action"):  # actions are flattened inside: named in the env's own shape
        assert describe(spec_from_space(gym.spaces.MultiDiscrete([[2, 3], [4, 5]]), role)) == \
            "MultiDiscrete([[2, 3], [4, 5]])"
        assert describe(spec_from_space(gym.spaces.MultiBinary([2, 3]), role)) == "MultiBinary([2, 3])"
        box = spec_from_space(gym.spaces.Box(-1.0, 1.0, (2, 2)), role)
        assert describe(box).endswith("shape=(2, 2), dtype=float32)")


def test_loaded_policy_says_what_it_takes(tmp_path):
    relayrl.train(short_config("dqn", "discrete", "discrete"), tmp_path, progress=False)
    policy = relayrl.load_policy(tmp_path)
    assert int(policy(3)) in (0, 1) and policy(np.array([0, 1, 2])).shape == (3,)
    with pytest.raises(UserError, match=r"outside this policy's Discrete\(4\) space"):
        policy(7)
    for batch in (torch.tensor([0, 7]), torch.tensor([0, -1])):  # int64 batches, the dtype passed straight through
        with pytest.raises(UserError, match=r"outside this policy's Discrete\(4\) space"):
            policy(batch)  # was torch's "index 7 is out of bounds" from the one-hot
    with pytest.raises(UserError, match=r"takes Discrete\(4\) observations"):
        policy(np.zeros((2, 3)))
    with pytest.raises(UserError, match=r"takes Discrete\(4\) observations: an array of numbers .*, not a dict"):
        policy({"cell": 1})
    with pytest.raises(UserError, match=r"observations: an array of numbers .*, not a str like abc"):
        policy("abc")
    with pytest.raises(UserError, match=r"observation holds NaN or inf; give finite values"):
        policy(np.array([np.inf]))


def test_a_loaded_policy_refuses_nan_observations_however_they_come(tmp_path):
    relayrl.train(short_config("sac", "dict", "box"), tmp_path, progress=False)
    policy = relayrl.load_policy(tmp_path)
    obs = Spaces("dict", "box").reset(seed=0)[0]
    with pytest.raises(UserError, match=r"observation\['pos'\] holds NaN or inf"):
        policy({**obs, "pos": np.array([np.nan, 0.0], np.float32)})
    relayrl.train(short_config("sac", "box", "box"), tmp_path / "box", progress=False)
    policy = relayrl.load_policy(tmp_path / "box")
    with pytest.raises(UserError, match="observation holds NaN or inf"):
        policy(torch.full((4, 3), float("nan")))  # a batched tensor of the policy's own dtype
    needs_grad = torch.zeros((4, 3), requires_grad=True)  # a batch from a differentiable rollout
    np.testing.assert_array_equal(policy(needs_grad).numpy(), policy(np.zeros((4, 3), np.float32)))  # was
    # "Can't call numpy() on Tensor that requires grad" from the CPU MLP


def test_a_discrete_entry_of_a_dict_outside_its_range_is_one_line(tmp_path):
    relayrl.train(short_config("dqn", "dict", "discrete"), tmp_path, progress=False)
    policy = relayrl.load_policy(tmp_path)
    obs = observation_space("dict").sample()
    policy(obs)
    with pytest.raises(UserError, match=r"observation\['cell'\] 4 is outside this policy's Discrete\(4\) space"):
        policy({**obs, "cell": 4})
    with pytest.raises(UserError, match=r"observation\['cell'\] 7.0 is outside this policy's Discrete\(4\) space"):
        policy({**obs, "cell": 7.0})  # a float holding a whole number is checked as the env's value
    policy({**obs, "pos": torch.zeros(2, requires_grad=True)})  # a tensor needing grad is read as it is
    batch = {k: np.stack([v] * 3) for k, v in obs.items()}
    with pytest.raises(UserError, match=r"observation\['pos'\] has shape \(2, 2\).*as observation\['cell'\]'s B = 3"):
        policy({**batch, "pos": np.zeros((2, 2), np.float32)})  # batches of 3 and of 2
    # integer entries take floats holding the env's values, and refuse fractions (frames scaled to [0, 1])
    assert policy({**obs, "frame": obs["frame"].astype(np.float32)}) == policy(obs)
    with pytest.raises(UserError, match=r"observation\['frame'\] holds float32 values that are not whole numbers in "
                                        r"uint8's range; this policy takes Box\(0, 255, shape=\(1, 8, 8\), "
                                        r"dtype=uint8\) values as the env gives them"):
        policy({**obs, "frame": obs["frame"].astype(np.float32) / 255.0 + 0.5 / 255})


def test_an_image_policy_takes_the_envs_frames_as_numbers_and_bits_in_range(tmp_path):
    relayrl.train(short_config("dqn", "image", "discrete"), tmp_path / "image", progress=False)
    policy = relayrl.load_policy(tmp_path / "image")
    frame = Spaces("image").reset(seed=0)[0]
    assert policy(frame.astype(np.float64)) == policy(frame)  # as the env gives them, in another dtype
    with pytest.raises(UserError, match="not whole numbers in uint8's range.*not scaled to \\[0, 1\\]"):
        policy(frame.astype(np.float32) / 255.0 + 0.5 / 255)
    with pytest.raises(UserError, match="not whole numbers in uint8's range"):
        policy(frame.astype(np.float32) + 300)  # would wrap round in a uint8
    # integers too: an int64 300 (or -1) would wrap to 44 (255) and act on another frame
    assert policy(frame.astype(np.int64)) == policy(frame)
    for wrapped in (frame.astype(np.int64) + 300, frame.astype(np.int64) - 1):
        with pytest.raises(UserError, match=r"observation holds values outside uint8's range \[0, 255\]"):
            policy(wrapped)
    relayrl.train(short_config("dqn", "tuple", "discrete"), tmp_path / "f64", progress=False)
    with pytest.raises(UserError, match=r"observation\['1'\] holds values outside float32's range"):
        relayrl.load_policy(tmp_path / "f64")((1, np.array([1e300, 0.0])))  # float64: would turn inf
    relayrl.train(short_config("dqn", "multi_binary", "discrete"), tmp_path / "bits", progress=False)
    with pytest.raises(UserError, match=r"observation \[0, 2, 1\] is outside this policy's MultiBinary\(\[3\]\)"):
        relayrl.load_policy(tmp_path / "bits")(np.array([0, 2, 1], np.int8))
    relayrl.train(short_config("dqn", "box_i32", "discrete"), tmp_path / "counts", progress=False)
    with pytest.raises(UserError, match=r"not whole numbers in int64's range; .* values as the env gives them$"):
        relayrl.load_policy(tmp_path / "counts")(np.array([0.5, 1.0, 2.0]))  # counts, not frames: no frame advice


@pytest.mark.parametrize(("preset", "over"), [
    ("dqn-cartpole-fast", ["train.total_steps=5000", "train.initial_collect_steps=500",
                           "agent.epsilon_decay_steps=4000"]),
    ("ppo-cartpole", ["train.total_steps=4096"]),
    # a linear Q on one-hot states is tabular Q-learning
    ("dqn-cartpole-fast", ["agent.hidden=[]", "agent.lr=0.01", "agent.target_update_period=25",
                           "train.total_steps=10000", "agent.epsilon_decay_steps=5000"]),
])
def test_frozen_lake_is_learnt_from_its_discrete_observations(preset, over, tmp_path):
    """FrozenLake (not slippery) is learnt only when its one integer observation is one-hot:
    fed as a number, DQN and PPO stayed at 0 after 20,000 steps."""
    cfg = relayrl.load_config(preset, ["env.id=FrozenLake-v1", "env.kwargs={is_slippery = false}",
                                       "eval.episodes=1", "train.checkpoint_interval=0", *over], seed=0)
    cfg.eval.interval = cfg.train.total_steps
    result = relayrl.train(cfg, tmp_path, progress=False)
    assert result.final["average_return"] == 1.0


def test_ppo_multi_discrete_and_multi_binary_log_probs_by_hand():
    from relayrl.agents.ppo.distributions import greedy_logits_action, log_prob_entropy

    logits = torch.tensor([[0.0, 1.0, 2.0, 0.5, -1.0]])  # MultiDiscrete([2, 3]): blocks [0, 1] and [2, 0.5, -1]
    logp, ent = log_prob_entropy(logits, None, torch.tensor([[1, 0]]), nvec=(2, 3))
    p1, p2 = torch.softmax(logits[0, :2], 0), torch.softmax(logits[0, 2:], 0)
    assert torch.allclose(logp, (p1[1].log() + p2[0].log()).reshape(1))
    assert torch.allclose(ent, (-(p1 * p1.log()).sum() - (p2 * p2.log()).sum()).reshape(1))
    assert greedy_logits_action(logits, (2, 3), False).tolist() == [[1, 0]]
    bern = torch.tensor([[0.3, -2.0]])  # MultiBinary(2)
    logp, ent = log_prob_entropy(bern, None, torch.tensor([[1, 0]], dtype=torch.int8), binary=True)
    q = torch.sigmoid(bern[0])
    assert torch.allclose(logp, (q[0].log() + (1 - q[1]).log()).reshape(1))
    assert torch.allclose(ent, (-(q * q.log() + (1 - q) * (1 - q).log())).sum().reshape(1))
    assert greedy_logits_action(bern, (), True).tolist() == [[1, 0]]


def test_packed_rows_unpack_to_what_the_env_returned():
    for kind in ("dict", "tuple"):
        env = Spaces(kind)
        spec = spec_from_space(env.observation_space)
        obs, _ = env.reset(seed=1)
        again = spec.observation(spec.pack(obs))
        assert env.observation_space.contains(again)
        assert np.array_equal(spec.pack(again), spec.pack(obs))


def test_evaluate_hands_a_users_function_the_envs_own_dict_observations():
    seen = []

    def policy(obs):
        seen.append(obs)
        return int(obs["cell"] >= 2)  # the target, read from the Dict: every step pays 1

    mean, std = relayrl.evaluate(policy, lambda: Spaces("dict"), episodes=2)
    assert isinstance(seen[0], dict) and set(seen[0]) == {"cell", "frame", "pos"}
    assert (mean, std) == (8.0, 0.0)


def test_evaluate_hands_a_users_function_a_scalar_box_observation_as_the_env_gives_it():
    """A Box of shape () observation is a 0-d array from the env: the same to the user's function."""
    class Scalar(gym.Env):
        observation_space = gym.spaces.Box(-1.0, 1.0, (), np.float32)
        action_space = gym.spaces.Discrete(2)

        def reset(self, seed=None, options=None):
            super().reset(seed=seed)
            return np.zeros((), np.float32), {}

        def step(self, action):
            return np.zeros((), np.float32), 1.0, True, False, {}

    seen = []
    relayrl.evaluate(lambda obs: seen.append(obs) or 0, Scalar, episodes=2)
    assert all(isinstance(o, np.ndarray) and o.shape == () for o in seen), seen


def test_a_nan_inside_a_dict_observation_stops_the_run(tmp_path):
    from relayrl.errors import NonFiniteError

    cfg = short_config("dqn", "dict", "discrete")
    cfg.env.kwargs = {**cfg.env.kwargs, "nan_at": 40}
    cfg.env.num_envs = 1
    with pytest.raises(NonFiniteError, match="observation was NaN at env step 40 "):
        relayrl.train(cfg, tmp_path, progress=False)


class _OutOfRange(gym.Env):
    """Discrete(4) observations, the 30th of each episode 7."""

    observation_space = gym.spaces.Discrete(4)
    action_space = gym.spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return 0, {}

    def step(self, action):
        self.t += 1
        return (7 if self.t == 30 else 1), 0.0, False, self.t >= 50, {}


@pytest.mark.parametrize("vectorization", ["sync", "async"])
def test_a_step_observation_outside_the_envs_own_space_is_one_line(vectorization, tmp_path):
    cfg = relayrl.load_config("dqn", ["env.check=false", "train.total_steps=200", "env.num_envs=2",
                                      f"env.vectorization={vectorization}"])
    with pytest.raises(UserError, match=r"the env's step returned observation 7, outside its own observation "
                                        r"space Discrete\(4\)"):
        relayrl.train(cfg, tmp_path, progress=False, env=_OutOfRange)


class _DictOutOfRange(gym.Env):
    """A Dict observation whose Discrete(4) entry is 9 at reset (`at="reset"`) or 7 at step 30."""

    observation_space = gym.spaces.Dict({"cell": gym.spaces.Discrete(4), "pos": gym.spaces.Box(-1, 1, (2,))})
    action_space = gym.spaces.Discrete(2)

    def __init__(self, at: str = "step") -> None:
        self.at = at

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return {"cell": 9 if self.at == "reset" else 0, "pos": np.zeros(2, np.float32)}, {}

    def step(self, action):
        self.t += 1
        return {"cell": 7 if self.t == 30 else 1, "pos": np.zeros(2, np.float32)}, 0.0, False, self.t >= 50, {}


@pytest.mark.parametrize("vectorization", ["sync", "async"])
@pytest.mark.parametrize("at, value", [("step", 7), ("reset", 9)])
def test_a_dict_entry_outside_its_space_is_one_line_at_step_and_reset(at, value, vectorization, tmp_path):
    cfg = relayrl.load_config("dqn", ["env.check=false", "train.total_steps=200", "env.num_envs=2",
                                      f"env.vectorization={vectorization}"])
    with pytest.raises(UserError, match=rf"the env's {at} returned observation\['cell'\] {value}, outside its own "
                                        r"observation space Discrete\(4\)"):
        relayrl.train(cfg, tmp_path, progress=False, env=lambda: _DictOutOfRange(at))


@pytest.mark.parametrize("flat_key", ["a.b", "a/b"])
def test_dict_keys_that_become_one_name_when_joined_are_one_line(flat_key):
    nested = gym.spaces.Dict({"b": gym.spaces.Discrete(3)})
    space = gym.spaces.Dict({flat_key: gym.spaces.Box(-1, 1, (2,)), "a": nested})
    with pytest.raises(UserError, match="are one name once nested keys are joined with '.': rename"):
        make_encoder(spec_from_space(space))


@pytest.mark.parametrize("space", [gym.spaces.Discrete(4), gym.spaces.MultiDiscrete([2, 3]), gym.spaces.MultiBinary(3),
                                   gym.spaces.Box(-1, 1, (3,))])
def test_a_conv_encoder_asked_for_non_image_observations_is_one_line(space):
    with pytest.raises(UserError, match="agent.encoder='nature_cnn' needs image observations"):
        make_encoder(spec_from_space(space), "nature_cnn")


@pytest.mark.parametrize("space", [gym.spaces.Box(0, 255, (64, 64, 1), np.uint8),
                                   gym.spaces.Dict({"frame": gym.spaces.Box(0, 255, (4, 84, 84), np.uint8)})])
def test_dqns_atari_network_on_other_frames_names_their_layout_and_the_way_round(space):
    from relayrl.agents.dqn.config import DQNConfig
    from relayrl.agents.dqn.networks import q_network

    cfg = DQNConfig()
    cfg.network = "nature_cnn"
    with pytest.raises(UserError, match=r"needs uint8 frames \[C, H, W\], channels first .* are (Box|Dict)\(.*use "
                                        r"agent.network='mlp' with agent.encoder"):
        q_network(spec_from_space(space), spec_from_space(gym.spaces.Discrete(2), "action"), cfg)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_a_loaded_policy_on_cuda_takes_a_multidiscrete_batch_on_cuda(tmp_path):
    """The batched tensor path checks a MultiDiscrete's values against its nvec on the
    observations' device (a CPU nvec against CUDA observations was a device mismatch)."""
    relayrl.train(short_config("dqn", "multi_discrete", "discrete"), tmp_path, progress=False)
    policy = relayrl.load_policy(tmp_path, device="cuda")
    obs = torch.tensor([[0, 2], [1, 0]], device="cuda")
    assert policy(obs).device.type == "cuda"
    with pytest.raises(UserError, match="outside this policy's"):
        policy(torch.tensor([[0, 3]], device="cuda"))


@pytest.mark.parametrize("algo", ["dqn", "ppo"])
def test_a_users_encoder_acts_and_is_evaluated_in_eval_mode_and_learns_in_train_mode(tmp_path, algo):
    """Acting and a run's evaluations ran a user's encoder in train mode (Dropout on, BatchNorm
    updating its statistics on the evaluation's episodes), while relayrl eval ran it in eval mode;
    a BatchNorm1d encoder failed at once on its probe's batch of one."""
    from space_envs import NormedEncoder

    small = {"train": {"total_steps": 512, "initial_collect_steps": 0 if algo == "ppo" else 128,
                       "collect_steps": 128, "policy_save_interval": 0, "checkpoint_interval": 0},
             "eval": {"interval": 256, "episodes": 2}, "env": {"id": "CartPole-v1", "num_envs": 2},
             "agent": {"encoder": "space_envs:NormedEncoder", "batch_size": 32}}
    NormedEncoder.calls.clear()
    relayrl.train({"algo": algo, **small}, tmp_path / "a", progress=False)
    # batches of 2: acting (2 env copies) and evaluating (2 episodes), in eval mode; the learner's
    # batches (32 transitions, a rollout of 128) learn in train mode
    assert {training for training, _, b in NormedEncoder.calls if b == 2} == {False}
    assert (True, True) in {(training, grad) for training, grad, b in NormedEncoder.calls if b != 2}
    # evaluations leave the weights and statistics alone: a run without them saves the same policy
    relayrl.train({"algo": algo, **small, "eval": {"interval": 0, "episodes": 2}}, tmp_path / "b", progress=False)
    a, b = (torch.load(tmp_path / r / "policy" / "policy.pt", weights_only=True) for r in ("a", "b"))
    assert _equal_tensors(a, b)


def _equal_tensors(a, b) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_equal_tensors(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_equal_tensors(x, y) for x, y in zip(a, b, strict=True))
    return torch.equal(a, b) if isinstance(a, torch.Tensor) else a == b


def test_a_policy_torch_export_cannot_trace_is_one_line_for_either_format(tmp_path, capsys):
    """An encoder with a Python branch on a tensor's value trained, then pt2 export printed ~300
    lines of torch's, and ONNX's line carried terminal colours and advised pt2, which fails too."""
    relayrl.train({"algo": "ppo", "env": {"id": "CartPole-v1"}, "agent": {"encoder": "space_envs:Branching"},
                   "train": {"total_steps": 128, "collect_steps": 64}, "eval": {"interval": 0, "episodes": 1}},
                  tmp_path / "r", progress=False)
    for fmt in ("pt2", "onnx"):
        if fmt == "onnx":
            pytest.importorskip("onnxscript")
        capsys.readouterr()
        with pytest.raises(UserError) as e:
            relayrl.export_policy(tmp_path / "r", tmp_path / f"p.{fmt}")
        assert "def forward" not in capsys.readouterr().err  # torch's graph dump, ~300 lines
        said = str(e.value)
        assert "\n" not in said and "\x1b" not in said and "use --format pt2" not in said, said
        assert said.startswith("this policy cannot be exported") and "torch.where" in said, said


def test_a_dicts_float_grid_stays_flattened_when_a_conv_net_is_named():
    """Float images take a conv net as a whole observation only: a Dict's stacked vector entry
    ([10, 8]) is flattened under nature_cnn / small_cnn, as runs before float images were taken
    built it (their checkpoints and policy files load)."""
    space = gym.spaces.Dict({"image": gym.spaces.Box(0, 255, (84, 84, 3), np.uint8),
                             "history": gym.spaces.Box(-1.0, 1.0, (10, 8), np.float32)})
    for kind in ("nature_cnn", "small_cnn"):
        parts = make_encoder(spec_from_space(space), kind).parts
        assert (type(parts["image"]), type(parts["history"]).__name__) == (ConvEncoder, "Flatten")
    with pytest.raises(UserError, match="needs image observations"):  # nor is it an image on its own
        make_encoder(spec_from_space(space["history"]), "small_cnn")
