"""A start without a preset (issue 32, C): each algorithm's own defaults, from the CLI and from
Python, never another algorithm's; presets load exactly as before."""

from __future__ import annotations

import copy
import dataclasses
import json

import pytest

import relayrl
from relayrl.agents.registry import ALGORITHMS
from relayrl.cli import main
from relayrl.config import Config, _merge, class_defaults, dotted, from_dict, to_dict
from relayrl.errors import ConfigError
from relayrl.presets import _files, list_presets, load_config, preset_dict

STARTABLE = ("dqn", "ppo", "sac")


@pytest.mark.parametrize("algo", STARTABLE)
def test_a_dict_naming_only_algo_and_env_takes_that_algorithms_defaults(algo):
    c = from_dict({"algo": algo, "env": {"id": "Pendulum-v1" if algo == "sac" else "CartPole-v1"}})
    got = dotted(to_dict(c))
    for key, value in dotted(ALGORITHMS[algo].defaults).items():
        if key != "env.id":
            assert got[key] == value, key
    assert isinstance(c.agent, ALGORITHMS[algo].config)


def test_ppo_from_python_is_not_dqn_ish():
    # Issue 32: {"algo": "ppo"} took collect_steps = 1 (a gradient step per env step).
    for c in (from_dict({"algo": "ppo"}), Config(algo="ppo"), relayrl.load_config("ppo")):
        assert (c.train.collect_steps, c.train.initial_collect_steps, c.train.total_steps) == (2048, 0, 100_000)
        assert (c.agent.batch_size, c.agent.n_epochs, c.agent.lr, c.agent.hidden) == (64, 10, 3e-4, [64, 64])
    assert Config(algo="sac").env.id == "Pendulum-v1" and Config(algo="sac").replay.size == 1_000_000


def test_setting_algo_afterwards_keeps_what_the_user_changed():
    c = Config()
    c.train.total_steps = 777
    c.env.id = "Pendulum-v1"
    c.algo = "ppo"
    assert type(c.agent).__name__ == "PPOConfig"
    assert (c.train.total_steps, c.env.id, c.train.collect_steps) == (777, "Pendulum-v1", 2048)
    c.algo = "dqn"
    assert c.train.collect_steps == 4 and c.agent.batch_size == 32 and c.train.total_steps == 777


@pytest.mark.parametrize("algo", ["dqn", "ppo", "sac"])
def test_dataclasses_replace_of_a_config_keeps_it_and_changes_only_what_is_named(algo):
    # A sweep's habit: replace(base, seed=s). PPO's and SAC's raised AttributeError ('DQNConfig'
    # object has no attribute ...): the agent section was rebased against DQN's defaults.
    base = relayrl.load_config(algo, ["train.total_steps=7000"])
    base.agent.gamma = 0.9
    c = dataclasses.replace(base, seed=4)
    assert c.seed == 4 and dotted(to_dict(c)) == {**dotted(to_dict(base)), "seed": 4}
    section = Config(algo=algo, agent=ALGORITHMS[algo].config(gamma=0.8))
    assert dotted(to_dict(section)) == {**dotted(to_dict(Config(algo=algo))), "agent.gamma": 0.8}


@pytest.mark.parametrize("total, decay", [(100_000, 10_000), (5_000, 500)])
def test_dqn_without_a_preset_explores_over_a_tenth_of_its_run(total, decay):
    """SB3's exploration_fraction 0.1: a short run is not left exploring to its end."""
    import numpy as np
    import torch

    from relayrl.agents.dqn import DQNAgent
    from relayrl.specs import ArraySpec, DiscreteSpec

    c = relayrl.load_config("dqn", [f"train.total_steps={total}"])
    agent = DQNAgent(ArraySpec((4,), torch.float32), DiscreteSpec(2), c.agent, torch.device("cpu"),
                     np.random.default_rng(0), total)
    eps = agent.epsilon_schedule()
    assert eps(0) == 1.0 and eps(decay // 2) == pytest.approx(0.525) and eps(decay) == eps(total) == 0.05
    with pytest.raises(ConfigError, match="agent.epsilon_decay_steps=-2 is not valid"):
        relayrl.load_config("dqn", ["agent.epsilon_decay_steps=-2"])


def test_the_users_keys_win_over_the_defaults():
    c = from_dict({"algo": "ppo", "train": {"collect_steps": 256}, "agent": {"lr": 1e-3}})
    assert c.train.collect_steps == 256 and c.agent.lr == 1e-3 and c.train.log_interval == 2048


@pytest.mark.parametrize("preset", sorted(_files()))
def test_presets_load_exactly_as_on_the_config_classes_defaults(preset):
    # A preset names every key where its algorithm's defaults differ from the classes' own, so
    # it is what it was before algorithms had defaults (`relayrl config PRESET` unchanged).
    data = preset_dict(preset)
    before = class_defaults()
    object.__setattr__(before, "agent", ALGORITHMS[data.get("algo", "dqn")].config())
    object.__setattr__(before, "algo", data.get("algo", "dqn"))
    _merge(before, copy.deepcopy(data), "", before.algo)
    assert to_dict(load_config(preset)) == to_dict(before)


def test_a_saved_config_round_trips(tmp_path):
    from relayrl.config import load_toml, save_toml

    for algo in STARTABLE:
        c = load_config(algo)
        save_toml(c, tmp_path / "c.toml")
        assert to_dict(from_dict(load_toml(tmp_path / "c.toml"))) == to_dict(c)
    c = load_config("dqn", ["env.kwargs={\"é\" = 2, \"a b\" = 1}"])  # keys TOML must quote
    save_toml(c, tmp_path / "k.toml")
    assert from_dict(load_toml(tmp_path / "k.toml")).env.kwargs == {"é": 2, "a b": 1}
    lines = (tmp_path / "c.toml").read_text().splitlines()
    assert [line for line in lines if line.startswith("total_steps = ")][0].endswith("  # env steps")  # explained


def test_presets_lists_the_algorithm_configs():
    listed = list_presets()
    for algo in STARTABLE:
        assert "Stable-Baselines3" in listed[algo]
    assert "bptt" not in listed


def test_cli_config_and_bad_names(capsys):
    assert main(["config", "ppo"]) == 0
    out = capsys.readouterr().out
    assert 'algo = "ppo"' in out and "collect_steps = 2048" in out
    assert main(["train", "ppx", "--run-dir", "unused"]) == 2
    assert "did you mean 'ppo'" in capsys.readouterr().err
    assert main(["train", "bptt", "--run-dir", "unused"]) == 2
    err = capsys.readouterr().err
    assert "bptt-pendulum" in err and err.count("\n") == 1
    with pytest.raises(ConfigError, match="algo='nope' is not known"):
        Config(algo="nope")


def test_cli_train_ppo_without_a_preset(tmp_path, capsys):
    run = tmp_path / "run"
    code = main(["train", "ppo", "--set", "env.id=CartPole-v1", "--set", "train.total_steps=512",
                 "--set", "train.collect_steps=256", "--set", "eval.episodes=2", "--run-dir", str(run),
                 "--no-progress"])
    assert code == 0
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert rows[-1]["step"] == 512 and rows[-1]["train_step"] > 0
    assert 'algo = "ppo"' in (run / "config.toml").read_text()


def test_docs_list_each_algorithms_defaults():
    from relayrl.docs_config import render

    text = render()
    assert "## Defaults per algorithm" in text
    table = text.split("## Defaults per algorithm")[1]
    for algo in STARTABLE:
        assert f"`{algo}`" in table
        for key in dotted(ALGORITHMS[algo].defaults):
            assert f"| `{key}` |" in table


def test_a_run_on_a_new_env_with_an_algorithms_defaults_says_how_long_it_trains(tmp_path, capsys):
    """No preset and no length chosen: the run says the defaults it took for its length and
    evaluations and where every setting is; a chosen length, or a preset's, is not said."""
    stop_at_once = [lambda row: False]  # the step-0 evaluation's row stops the run
    relayrl.train(load_config("dqn", ["env.id=Acrobot-v1"]), tmp_path / "r", progress=False, callbacks=stop_at_once)
    assert (f"dqn's defaults on Acrobot-v1: 100,000 env steps (train.total_steps), evaluated every 10,000 env steps "
            f"and at the end, 10 episodes each (eval.interval, eval.episodes); every setting is in "
            f"{str(tmp_path / 'r' / 'config.toml')!r} (`relayrl config dqn` says what each key does)\n"
            ) in capsys.readouterr().err
    for name, overrides in (("dqn", ["env.id=Acrobot-v1", "train.total_steps=96"]),
                            ("dqn-cartpole-fast", ["env.id=Acrobot-v1"]), ("dqn", [])):
        relayrl.train(load_config(name, overrides), tmp_path / "r", progress=False, callbacks=stop_at_once,
                      overwrite=True)
        assert "defaults" not in capsys.readouterr().err
