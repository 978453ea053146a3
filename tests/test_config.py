"""Config: presets, --set overrides, type checks, TOML round trip."""

import pytest

from relayrl.config import from_dict, load_toml, save_toml, to_dict
from relayrl.errors import ConfigError
from relayrl.presets import list_presets, load_config


def test_presets_load_and_describe_themselves():
    names = list_presets()
    assert {"dqn-cartpole", "dqn-cartpole-fast"} <= set(names)
    assert all(desc for desc in names.values())
    c = load_config("dqn-cartpole")
    assert c.env.id == "CartPole-v0" and c.agent.hidden == [100, 50] and c.agent.gamma == 1.0


def test_overrides_are_typed():
    c = load_config("dqn-cartpole", ["agent.lr=0.01", "agent.hidden=[32, 32]", "env.id=CartPole-v1",
                                      "agent.double=true", "agent.gamma=1"], seed=7)
    assert c.agent.lr == 0.01 and c.agent.hidden == [32, 32] and c.env.id == "CartPole-v1"
    assert c.agent.double is True and c.agent.gamma == 1.0 and isinstance(c.agent.gamma, float)
    assert c.seed == 7


@pytest.mark.parametrize("override, fragment", [
    ("agent.lrr=0.1", "unknown config key 'agent.lrr'; did you mean 'agent.lr'?"),
    ("train.total_step=5", "unknown config key 'train.total_step'; did you mean 'train.total_steps'?"),
    ("agent.zzz=1", "unknown config key 'agent.zzz'; valid: agent.hidden"),
    ("nope=1", "unknown config key 'nope'"),
    ("train.total_steps=abc", "train.total_steps='abc' has the wrong type; expected int"),
    ("train.total_steps=1.5", "expected int"),
    ("agent.double=1", "expected bool"),
    ("agent.hidden=[1, 'a']", "agent.hidden[1]"),
    ("agent.loss=l1", "agent.loss='l1' is not valid; valid: huber, mse"),
    ("eval.episodes=0", "eval.episodes=0 is not valid"),
    ("train=3", "train is a section"),
    ("novalue", "is not KEY=VALUE"),
])
def test_bad_overrides_fail_with_a_clear_message(override, fragment):
    with pytest.raises(ConfigError, match=None) as e:
        load_config("dqn-cartpole", [override])
    assert fragment in str(e.value)


def test_unknown_preset_lists_valid_ones():
    with pytest.raises(ConfigError, match="unknown preset 'dqn-cartpol'; did you mean 'dqn-cartpole'.*valid: bptt-"):
        load_config("dqn-cartpol")


def test_toml_round_trip(tmp_path):
    c = load_config("dqn-cartpole-fast", ["seed=3"])
    save_toml(c, tmp_path / "c.toml")
    assert to_dict(from_dict(load_toml(tmp_path / "c.toml"))) == to_dict(c)
    assert to_dict(load_config(str(tmp_path / "c.toml"))) == to_dict(c)


def test_bptt_switch_is_named_fast():
    assert load_config("bptt-pendulum").agent.fast is True
    assert load_config("bptt-pendulum", ["agent.fast=false"]).agent.fast is False
    with pytest.raises(ConfigError, match="unknown config key 'agent.fused'"):
        load_config("bptt-pendulum", ["agent.fused=false"])


@pytest.mark.parametrize("algo", [["dqn"], {"a": 1}, 3])
def test_an_algo_that_is_not_a_name_is_one_config_error(algo):
    from relayrl.config import from_dict
    from relayrl.errors import ConfigError

    with pytest.raises(ConfigError, match="is not known"):
        from_dict({"algo": algo})
