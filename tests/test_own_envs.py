"""A user's own env: found from their project folder, Gymnasium's `module:EnvId-v0`, env.kwargs,
env.wrappers, an env factory in Python, episode caps, and the env checker."""

import functools
import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
import toy_envs

from relayrl.cli import main
from relayrl.config import from_dict, load_toml, save_toml
from relayrl.dispatch import factory_env_id, train
from relayrl.envs import make_env
from relayrl.errors import UserError
from relayrl.presets import load_config
from relayrl.training.evaluate import EVAL_MAX_EPISODE_STEPS, evaluate, make_eval_env
from relayrl.training.run_dir import RunDir

SRC = str(Path(__file__).resolve().parents[1] / "src")
TINY = ["train.total_steps=60", "train.initial_collect_steps=20", "eval.interval=30", "eval.episodes=2",
        "train.checkpoint_interval=30", "train.policy_save_interval=0", "agent.batch_size=8"]

README = Path(__file__).resolve().parents[1] / "README.md"


def readme_env() -> str:
    """The quick start's own env class (README.md, `# mygame/envs.py`), as a user would copy it."""
    text = README.read_text()
    start = text.index("# mygame/envs.py")
    return text[start:text.index("```", start)]


def policy_of(action: int):
    return lambda obs: torch.full((obs.shape[0],), action, dtype=torch.int64)


@pytest.fixture
def project(tmp_path):
    """A user's project folder holding its own package, and a `relayrl` console script
    outside it (the script's folder, not the current one, starts its import path)."""
    (tmp_path / "proj" / "mygame").mkdir(parents=True)
    (tmp_path / "proj" / "mygame" / "__init__.py").write_text("")
    registered = '\ngym.register("Corridor-v0", entry_point="mygame.envs:Corridor", max_episode_steps=20)\n'
    (tmp_path / "proj" / "mygame" / "envs.py").write_text(readme_env() + registered)
    (tmp_path / "bin").mkdir()
    script = tmp_path / "bin" / "relayrl"
    # What pip's console-script wrapper runs.
    script.write_text("import sys\nfrom relayrl.cli import main\nsys.exit(main())\n")
    env = {**os.environ, "PYTHONPATH": SRC}  # the project folder is not on it
    return tmp_path / "proj", script, env


@pytest.mark.parametrize("env_id", ["mygame.envs:Corridor", "mygame.envs:Corridor-v0"])
def test_console_script_finds_the_users_package_in_the_current_directory(project, env_id):
    """The README's own-env command, shrunk, from the user's project folder."""
    proj, script, env = project
    sets = [a for o in TINY + [f"env.id={env_id}", "env.kwargs={length=3}"] for a in ("--set", o)]
    r = subprocess.run([sys.executable, str(script), "train", "dqn-cartpole-fast", "--run-dir", "run",
                        "--no-progress", *sets], cwd=proj, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert RunDir(proj / "run").read_metrics()[-1]["step"] == 60
    # Corridor-v0 is registered with a time limit; the bare class has none: evaluation caps it, and
    # says so where the cap ended an episode
    assert not env_id.endswith("-v0") or "are cut at" not in r.stderr


@pytest.mark.parametrize("env_id", ["mygame.envs:Corridor", "mygame.envs:Corridor-v0"])
def test_a_python_script_in_another_folder_finds_the_users_package_in_the_current_directory(project, env_id):
    """`python scripts/train.py` from the project: the script's folder starts the import path, as
    the console script's does; the current directory is tried last, as the CLI puts it."""
    proj, script, env = project
    script.write_text(f"from relayrl.envs import make_env\nprint(make_env({env_id!r}).observation_spec)\n")
    r = subprocess.run([sys.executable, str(script)], cwd=proj, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "ArraySpec" in r.stdout, r.stderr


def test_a_missing_package_is_one_line_saying_what_was_tried(project):
    proj, script, env = project
    r = subprocess.run([sys.executable, str(script), "train", "dqn-cartpole", "--set", "env.id=nopkg.envs:Corridor"],
                       cwd=proj, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert "no module 'nopkg' in the current directory" in line and str(proj) in line
    assert "PYTHONPATH" in line and "pip install -e" in line
    assert not (proj / "runs").exists()
    # the package is found, its module is not: the line names the package's folder, not the import path
    r = subprocess.run([sys.executable, str(script), "train", "dqn-cartpole", "--set", "env.id=mygame.nope:Corridor"],
                       cwd=proj, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert f"package 'mygame' ({proj / 'mygame'}) has no module 'nope'" in line and "PYTHONPATH" not in line
    (proj / "solo.py").write_text("X = 1\n")  # a module, not a package
    r = subprocess.run([sys.executable, str(script), "train", "dqn-cartpole", "--set", "env.id=solo.nope:Corridor"],
                       cwd=proj, env=env, capture_output=True, text=True, timeout=120)
    (line,) = r.stderr.strip().splitlines()
    assert r.returncode == 2 and f"'solo' ({proj / 'solo.py'}) is a module, not a package" in line


def test_an_error_inside_the_users_module_is_one_line(project):
    proj, script, env = project
    (proj / "mygame" / "bad.py").write_text("import numpy\nraise RuntimeError('oops')\n")
    r = subprocess.run([sys.executable, str(script), "train", "dqn-cartpole", "--set", "env.id=mygame.bad:Env"],
                       cwd=proj, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert "raised RuntimeError: oops" in line and "bad.py:2" in line
    (proj / "mygame" / "typo.py").write_text("def step(self)\n    pass\n")  # a SyntaxError names its own place
    r = subprocess.run([sys.executable, str(script), "train", "dqn-cartpole", "--set", "env.id=mygame.typo:Env"],
                       cwd=proj, env=env, capture_output=True, text=True, timeout=120)
    (line,) = r.stderr.strip().splitlines()
    assert r.returncode == 2 and "raised SyntaxError: " in line and "(typo.py, line 1)" in line
    assert "frozen" not in line


def test_module_colon_registered_id_and_module_colon_factory_function():
    env = make_env("toy_envs:ToyCountdown-v0", 1)  # registered with length=2 when toy_envs is imported
    assert evaluate(env, policy_of(0), 2)["average_episode_length"] == 2.0
    env = make_env("toy_envs:make_countdown", 1, kwargs={"length": 5})
    assert evaluate(env, policy_of(0), 2)["average_episode_length"] == 5.0
    with pytest.raises(UserError, match="has no 'Nope-v0' and registers no Gymnasium id"):
        make_env("toy_envs:Nope-v0")


@pytest.mark.parametrize("vectorization", ["sync", "async"])
def test_kwargs_and_wrappers_apply_in_order_in_every_env(vectorization):
    made = {"kwargs": {"length": 4}, "wrappers": ["toy_envs:double_reward", "toy_envs:shift_obs"]}
    env = make_env("toy_envs:Countdown", 3, vectorization=vectorization, num_workers=1, **made)
    try:
        obs = env.reset(seed=0)
        assert obs[:, 0].tolist() == [100.0] * 3  # shift_obs ran
        out = env.step(torch.zeros(3, dtype=torch.int64))
        assert out.reward.tolist() == [2.0] * 3  # double_reward ran
    finally:
        env.close()
    result = evaluate(make_eval_env("toy_envs:Countdown", 2, **made), policy_of(0), 2)
    assert result["average_episode_length"] == 4.0 and result["average_return"] == 8.0


def test_kwargs_reach_gymnasium_make():
    env = make_env("CartPole-v1", 1, kwargs={"sutton_barto_reward": True})
    env.reset(seed=0)
    assert env.step(torch.zeros(1, dtype=torch.int64)).reward.tolist() == [0.0]  # Sutton-Barto pays 0 per step
    with pytest.raises(UserError, match="takes no argument 'nope'") as caught:
        make_env("toy_envs:Countdown", 1, kwargs={"nope": 1})
    assert "a preset sets" not in str(caught.value)  # a class of one's own: no preset's kwargs to blame


def test_a_registered_envs_rejected_kwarg_value_is_one_line():
    """FrozenLake's map_name="8X8" raises KeyError in its constructor: a typo in env.kwargs."""
    with pytest.raises(UserError, match=r"does not take the values given \(KeyError: '8X8'\); arguments passed "
                                        r"\(env.kwargs, and eval.env_kwargs to evaluation envs\): "
                                        r"\{'map_name': '8X8'\}"):
        make_env("FrozenLake-v1", 1, kwargs={"map_name": "8X8"})
    make_env("FrozenLake-v1", 1, kwargs={"map_name": "8x8"}, max_episode_steps=50).close()  # a valid value


def test_a_registered_envs_unknown_kwarg_names_its_near_miss_and_its_own_arguments():
    with pytest.raises(UserError) as e:
        make_env("CartPole-v1", 1, kwargs={"sutton_barto_rewrd": True})
    assert str(e.value) == ("env.id='CartPole-v1' takes no argument 'sutton_barto_rewrd' (env.kwargs, or "
                            "eval.env_kwargs for evaluation); did you mean 'sutton_barto_reward'? (its own arguments: "
                            "sutton_barto_reward, render_mode)")
    # none near: the env.kwargs of a preset for another env (ppo-lunarlander-continuous's continuous=true)
    with pytest.raises(UserError, match=r"takes no argument 'continuous' \(env.kwargs, or eval.env_kwargs for "
                                        r"evaluation\) \(its own arguments: .*\); "
                                        r"env.kwargs a preset sets stay when --set env.id changes the env: "
                                        r"--set 'env.kwargs=\{\}' clears them$"):
        make_env("CartPole-v1", 1, kwargs={"continuous": True})


def test_a_registered_envs_failure_on_a_kwarg_value_is_one_line():
    """A value the env's constructor fails on (a ZeroDivisionError of MuJoCo's frame_skip=0): env.kwargs'."""
    import gymnasium

    def make(size: int) -> gymnasium.Env:
        return gymnasium.make("CartPole-v1") if 1 / size else None

    gymnasium.register("relayrl-test/DividesBySize-v0", entry_point=make)
    try:
        with pytest.raises(UserError, match=r"does not take the values given \(ZeroDivisionError: division by zero\)"):
            make_env("relayrl-test/DividesBySize-v0", 1, kwargs={"size": 0})
    finally:
        del gymnasium.registry["relayrl-test/DividesBySize-v0"]


def test_render_mode_human_without_a_display_is_one_line(monkeypatch):
    """GLFW (MuJoCo) aborts the whole process on a window without a display, past any except."""
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if not sys.platform.startswith("linux"):
        pytest.skip("displays are looked for on Linux only")
    with pytest.raises(UserError, match=r"render_mode='human' opens a window, and this machine has no display"):
        make_env("CartPole-v1", 1, kwargs={"render_mode": "human"})


def test_bad_wrappers_are_one_line():
    with pytest.raises(UserError, match="is not package.module:Callable"):
        make_env("CartPole-v1", wrappers=["toy_envs.double_reward"])
    with pytest.raises(UserError, match="has no callable 'nope'"):
        make_env("CartPole-v1", wrappers=["toy_envs:nope"])
    with pytest.raises(UserError, match=r"has no callable 'ClipActoin'; did you mean gymnasium.wrappers:ClipAction\?$"):
        make_env("Pendulum-v1", wrappers=["gymnasium.wrappers:ClipActoin"])
    with pytest.raises(UserError, match="TimeLimit cannot be called with the env alone"):
        make_env("CartPole-v1", wrappers=["gymnasium.wrappers:TimeLimit"])  # needs max_episode_steps
    # a wrapper's own failure keeps its traceback, which says it came from env.wrappers
    with pytest.raises(NotImplementedError) as e:
        make_env("CartPole-v1", wrappers=["toy_envs:refuses_the_env"])
    notes = e.value.__notes__
    assert any(n.startswith("relayrl: raised by env.wrappers' toy_envs:refuses_the_env over") for n in notes)


def test_kwargs_and_wrappers_survive_config_toml_and_resume(tmp_path):
    config = load_config("dqn-cartpole", TINY + ["env.id=toy_envs:Countdown", "env.kwargs={length=5}",
                                                 'env.wrappers=["toy_envs:double_reward"]'])
    save_toml(config, tmp_path / "c.toml")
    again = from_dict(load_toml(tmp_path / "c.toml"))
    assert again.env.kwargs == {"length": 5} and again.env.wrappers == ["toy_envs:double_reward"]
    assert load_config("dqn-cartpole", ["env.kwargs.length=5"]).env.kwargs == {"length": 5}
    train(config, tmp_path / "run", progress=False)
    saved = load_config(str(tmp_path / "run" / "config.toml"), ["train.total_steps=90"])
    train(saved, tmp_path / "run", resume=True, progress=False)
    rows = RunDir(tmp_path / "run").read_metrics()
    assert rows[-1]["step"] == 90
    assert {(r["average_episode_length"], r["average_return"]) for r in rows} == {(5.0, 10.0)}


def test_eval_env_kwargs_apply_to_evaluations_only(tmp_path):
    """Training episodes take env.kwargs; evaluations, `relayrl.evaluate` of the run and the
    policy file's record take eval.env_kwargs over them (the other keys stay)."""
    from relayrl.evaluation import evaluate as evaluate_run
    from relayrl.export import load_policy

    config = load_config("dqn-cartpole", TINY + ["env.id=toy_envs:Countdown", "env.kwargs={length=5, truncate_at=9}",
                                                 "eval.env_kwargs={length=7}", "train.policy_save_interval=30"])
    result = train(config, tmp_path / "run", progress=False)
    rows = RunDir(tmp_path / "run").read_metrics()
    assert {r["average_episode_length"] for r in rows if "average_episode_length" in r} == {7.0}
    assert result.final["train/average_return"] == 5.0  # a reward of 1 a step
    assert evaluate_run(tmp_path / "run", episodes=2).mean == 7.0
    assert load_policy(tmp_path / "run").env_kwargs == {"length": 7, "truncate_at": 9}
    assert config.eval_env_kwargs() == {"length": 7, "truncate_at": 9} and config.env.kwargs["length"] == 5


def test_a_constructors_own_type_error_is_its_own_and_a_missing_argument_one_line(tmp_path):
    config = load_config("dqn-cartpole", TINY + ["env.id=toy_envs:BuggyInit", "env.kwargs={length=4}"])
    with pytest.raises(TypeError, match=r"_grid\(\) takes 2 positional arguments but 3 were given"):
        train(config, tmp_path / "a", progress=False)  # not blamed on env.kwargs: its traceback shows where
    config = load_config("dqn-cartpole", TINY + ["env.id=toy_envs:NeedsSize"])
    with pytest.raises(UserError, match=r"^env.id='toy_envs:NeedsSize' does not take the arguments given \(missing a "
                                        r"required argument: 'size'\); arguments passed \(env.kwargs, and "
                                        r"eval.env_kwargs to evaluation envs\): none$"):
        train(config, tmp_path / "b", progress=False)


def test_eval_env_kwargs_that_change_the_spaces_are_one_line(tmp_path):
    config = load_config("dqn-cartpole", TINY + ["env.id=toy_envs:Countdown", "eval.env_kwargs={nope=1}"])
    with pytest.raises(UserError, match=r"^env.id='toy_envs:Countdown' takes no argument 'nope' \(env.kwargs, or "
                                        r"eval.env_kwargs for evaluation\) \(its own arguments: length, truncate_at"):
        train(config, tmp_path / "a", progress=False)
    config = load_config("dqn-cartpole", TINY + ["env.id=toy_envs:Resized", "eval.env_kwargs={size=3}"])
    with pytest.raises(UserError, match=r"eval.env_kwargs \{'size': 3\} give evaluation envs observations .* but "
                                        "the training envs' are"):
        train(config, tmp_path / "b", progress=False)


@pytest.mark.parametrize("vectorization", ["sync", "async"])
def test_train_takes_an_env_factory(tmp_path, vectorization):
    config = load_config("dqn-cartpole", TINY + ["env.num_envs=2", f"env.vectorization={vectorization}",
                                                 "env.num_workers=1"])
    result = train(config, tmp_path / "run", progress=False, env=lambda: toy_envs.Countdown(length=6))
    assert result.final["average_episode_length"] == 6.0
    assert config.env.id == "CartPole-v0"  # the caller's config is left as it was
    saved = load_toml(tmp_path / "run" / "config.toml")
    assert saved["env"]["id"].startswith("test_own_envs:") and saved["env"]["id"].endswith("<lambda>")
    # Resumed with the same factory given again.
    again = load_config(str(tmp_path / "run" / "config.toml"), ["train.total_steps=90"])
    result = train(again, tmp_path / "run", resume=True, progress=False, env=lambda: toy_envs.Countdown(length=6))
    assert result.final["step"] == 90 and result.final["average_episode_length"] == 6.0
    with pytest.raises(UserError, match="records an env factory given to relayrl.train"):
        train(again, tmp_path / "run", resume=True, progress=False)  # without it


class _Factory:
    def __call__(self):
        return toy_envs.Countdown(length=6)


@pytest.mark.parametrize("factory, recorded", [
    (functools.partial(toy_envs.Countdown, length=6), "toy_envs:<partial(Countdown, length=6)>"),
    (_Factory(), f"{__name__}:<_Factory>"),
], ids=["partial", "callable_object"])
def test_a_factory_no_import_finds_asks_for_itself_again(tmp_path, factory, recorded, capsys):
    train(load_config("dqn-cartpole", TINY), tmp_path / "run", progress=False, env=factory)
    saved = load_toml(tmp_path / "run" / "config.toml")["env"]["id"]
    assert saved == recorded
    # said when the run starts, not first when the run is evaluated
    assert (f"the env factory is recorded as env.id={saved!r}, which no import finds: `relayrl eval` needs --env "
            "ENV_ID, a video relayrl.record_video(run_dir, env=...) in Python") in capsys.readouterr().err
    assert main(["eval", str(tmp_path / "run")]) == 2
    assert "pass the same env= again in Python" in capsys.readouterr().err
    assert main(["eval", str(tmp_path / "run"), "--env", "toy_envs:Countdown"]) == 0


def test_an_importable_factory_is_recorded_so_the_cli_can_evaluate_it(tmp_path, capsys):
    train(load_config("dqn-cartpole", TINY), tmp_path / "run", progress=False, env=toy_envs.make_countdown)
    assert load_toml(tmp_path / "run" / "config.toml")["env"]["id"] == "toy_envs:make_countdown"
    assert "no import finds" not in capsys.readouterr().err


def test_an_env_without_a_time_limit_is_capped_and_the_log_says_so(tmp_path, capfd):
    config = load_config("dqn-cartpole", TINY + ["env.id=toy_envs:Endless", "env.check=false"])
    result = train(config, tmp_path / "a", progress=False)
    err = capfd.readouterr().err
    assert result.final["average_episode_length"] == EVAL_MAX_EPISODE_STEPS
    assert f"evaluation episodes that do not end by themselves are cut at {EVAL_MAX_EPISODE_STEPS:,} steps" in err
    assert err.count("no registered time limit") == 1  # once, not at every evaluation
    config = load_config("dqn-cartpole", TINY + ["env.id=toy_envs:Endless", "env.max_episode_steps=7"])
    result = train(config, tmp_path / "b", progress=False)
    assert result.final["average_episode_length"] == 7.0
    assert result.final["train/episodes"] == 60 // 7  # training episodes are cut too
    assert "no registered time limit" not in capfd.readouterr().err
    train(load_config("dqn-cartpole", TINY + ["env.id=toy_envs:Countdown"]), tmp_path / "c", progress=False)
    assert "no registered time limit" not in capfd.readouterr().err  # it ends its episodes itself: nothing cut


def test_the_cap_counts_only_the_episodes_it_ended():
    from relayrl.envs.gym import GymBatchEnv

    for cap, length, truncate_at, cut in ((5, 5, 0, 0), (5, 9, 5, 0), (3, 9, 0, 1)):  # ended by the env: not cut
        env = GymBatchEnv([functools.partial(toy_envs.Countdown, length=length, truncate_at=truncate_at)])
        env.cap_episodes(cap)
        env.reset(seed=0)
        for _ in range(cap):
            out = env.step(torch.zeros(1, dtype=torch.int64))
        assert bool(out.terminated[0] or out.truncated[0]) and env.episodes_cut == cut, (cap, length, truncate_at)
        env.close()


def test_a_registered_env_without_a_time_limit_is_capped_too_but_not_an_atari_game():
    env = make_eval_env("CliffWalking-v1", 2)  # a policy that never reaches the goal walks forever
    assert env.capped_at == EVAL_MAX_EPISODE_STEPS
    env.close()
    if importlib.util.find_spec("ale_py") is not None:
        env = make_eval_env("ALE/Pong-v5", 1)  # a game of Pong outlasts the cap; ALE ends it itself
        assert env.capped_at == 0
        env.close()


def test_a_users_env_is_checked_once_unless_turned_off(tmp_path, capfd):
    config = load_config("dqn-cartpole", TINY + ["env.id=toy_envs:Sloppy"])
    train(config, tmp_path / "a", progress=False)
    err = capfd.readouterr().err
    assert err.count("does not call `super().reset(seed=seed)`") == 1 and "env.check = false" in err
    config = load_config("dqn-cartpole", TINY + ["env.id=toy_envs:Sloppy", "env.check=false"])
    train(config, tmp_path / "b", progress=False)
    assert "env check" not in capfd.readouterr().err


@pytest.mark.parametrize("env_id, kwargs, message", [
    ("toy_envs:ResetBreaksAt", "{at = 1}", "simulator refused to reset"),  # the check's own first reset
    ("toy_envs:BrokenAt", "{at = 1}", "simulator lost connection"),  # its one step
])
def test_an_env_raising_in_the_check_keeps_its_error_with_a_note_of_where(env_id, kwargs, message, tmp_path):
    config = load_config("dqn-cartpole", TINY + [f"env.id={env_id}", f"env.kwargs={kwargs}"])
    with pytest.raises(RuntimeError, match=message) as caught:
        train(config, tmp_path / "run", progress=False)
    assert caught.value.__notes__ == [
        "relayrl: raised by the env in relayrl's check before training (reset() of one fresh copy, then a step of "
        "a random action)"]


class _DictActionsItCannotTake(gym.Env):
    """A Dict action space its own step() cannot take: relayrl's refusal of the space comes
    before its check's step of a random action reaches it."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = gym.spaces.Dict({"a": gym.spaces.Discrete(2)})

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(2, np.float32), {}

    def step(self, action):
        raise AssertionError("stepped")


def test_an_action_space_relayrl_cannot_take_is_refused_before_the_env_is_stepped(tmp_path):
    config = load_config("ppo", ["train.total_steps=2048"])
    with pytest.raises(UserError, match=r"action space Dict\('a': Discrete\(2\)\) is not supported; valid action "
                                        r"spaces: DQN: Discrete; SAC: Box; PPO: Discrete, Box"):
        train(config, tmp_path / "run", progress=False, env=_DictActionsItCannotTake)


def test_float64_observations_are_one_line_and_the_checks_after_it_still_run():
    """Gymnasium's checker asserts that float64 observations are "not within the observation
    space" (of values inside its bounds) and stops there: the seed it ignores went unsaid."""
    from relayrl.envs.make import check_env

    lines = check_env("toy_envs:SloppyFloat64")
    assert lines[0] == ("observations come as float64 where observation_space is Box(-inf, inf, (2,), float32): "
                        "relayrl casts them to float32 (return float32 arrays, or declare the space's dtype, to "
                        "silence this line)")
    assert any("does not call `super().reset(seed=seed)`" in line for line in lines)
    assert lines[-1].startswith("runs of this env with the same seed will not repeat: call super().reset(seed=seed)")
    assert not any("not within the observation space" in line for line in lines)
    assert not any("will not repeat" in line for line in check_env("CartPole-v1"))


class _GridOfFloats(gym.Env):
    """A Dict observation whose int64 entry comes as float64 (and another as a list)."""

    observation_space = gym.spaces.Dict({"pos": gym.spaces.Box(0, 4, (2,), np.int64),
                                         "goal": gym.spaces.Box(0, 4, (2,), np.int64)})
    action_space = gym.spaces.Discrete(4)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return {"pos": np.zeros(2), "goal": [4, 4]}, {}

    def step(self, action):
        return {"pos": np.ones(2), "goal": [4, 4]}, 0.0, False, False, {}


def test_dict_entries_in_other_dtypes_are_named_and_the_checks_after_them_still_run():
    from relayrl.envs.make import check_env

    lines = check_env("x", factory=_GridOfFloats)
    assert lines[0] == ("observation entries come in other dtypes than their spaces': ['pos'] as float64 where its "
                        "space is Box(0, 4, (2,), int64); relayrl casts them (return arrays of the spaces' dtypes, or "
                        "declare those dtypes, to silence this line)")
    assert not any("not within the observation space" in line for line in lines)


class _NumpyFlags(_GridOfFloats):
    """Flags of NumPy's bool (what `pos >= goal` of arrays gives), seeded and in its spaces."""

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return {"pos": np.zeros(2, np.int64), "goal": np.full(2, 4, np.int64)}, {}

    def step(self, action):
        pos = np.ones(2, np.int64)
        return {"pos": pos, "goal": np.full(2, 4, np.int64)}, 0.0, np.all(pos >= 4), np.bool_(False), {}


def test_flags_of_numpys_bool_are_no_finding():
    """Gymnasium's checker asserts `truncated is False`: np.False_ failed it ("something has gone
    very wrong") and its later checks never ran."""
    from relayrl.envs.make import check_env

    assert check_env("x", factory=_NumpyFlags) == []


@pytest.mark.parametrize("env_id", ["toy_envs:Maskable", "toy_envs:MaskInInfo"])
def test_an_env_with_action_masks_is_told_they_are_not_read(env_id):
    """MaskablePPO's masks: no relayrl algorithm reads them, which the run once left unsaid."""
    from relayrl.envs.make import check_env

    assert any("relayrl does not read them" in line for line in check_env(env_id))
    assert not any("action masks" in line for line in check_env("toy_envs:Countdown"))


def test_env_num_workers_without_async_says_the_copies_step_here(tmp_path, capfd):
    """SB3's n_envs with SubprocVecEnv is env.num_workers with env.vectorization='async': the
    workers alone (sync, the default) would be a setting silently unused."""
    workers = TINY + ["env.id=toy_envs:Countdown", "env.num_envs=2", "env.num_workers=1"]
    train(load_config("dqn-cartpole", workers), tmp_path / "a", progress=False)
    said = "env.num_workers=1 with env.vectorization='sync': the 2 env copies step in this process"
    assert said in capfd.readouterr().err
    train(load_config("dqn-cartpole", workers + ["env.vectorization=async"]), tmp_path / "b", progress=False)
    assert "env.num_workers=1 with" not in capfd.readouterr().err


def test_the_check_says_nothing_of_an_unbounded_box(tmp_path, capfd):
    """CartPole's own space (infinite bounds) through a factory: relayrl takes such a Box, so
    Gymnasium's "minimum value is -infinity" is no finding."""
    config = load_config("dqn-cartpole", TINY)
    train(config, tmp_path / "a", progress=False, env=lambda: gym.make("CartPole-v1"))
    assert "env check" not in capfd.readouterr().err


def test_the_check_leaves_the_run_as_it_would_be_without_it(tmp_path):
    for check in ("true", "false"):
        config = load_config("dqn-cartpole", TINY + ["env.id=toy_envs:BetterAction", f"env.check={check}"])
        train(config, tmp_path / check, progress=False)
    strip = [{k: v for k, v in r.items() if not k.endswith("_s")} for r in RunDir(tmp_path / "true").read_metrics()]
    assert strip == [{k: v for k, v in r.items() if not k.endswith("_s")}
                     for r in RunDir(tmp_path / "false").read_metrics()]
    assert np.isfinite(strip[-1]["average_return"])


@pytest.mark.parametrize("algo_preset", ["dqn-cartpole", "sac-pendulum", "ppo-cartpole"])
@pytest.mark.parametrize("env_id, fragment", [
    ("toy_envs:FourValueStep", "step() returned 4 values; Gymnasium envs return 5: obs, reward, terminated, "
                               "truncated, info (the old Gym API's obs, reward, done, info"),
    ("toy_envs:WrongShapeObs", "the observation from reset() has shape (3,) but observation_space is "
                               "Box(-inf, inf, (2,), float32) (shape (2,))"),
    ("toy_envs:OldReset", "the env's reset() takes no seed: Gymnasium envs define reset(self, *, seed=None, "
                          "options=None)"),
    ("toy_envs:NoActionSpace", "the env has no action_space (a gymnasium.spaces.Space): set self.action_space"),
    ("toy_envs:NoneReward", "the reward from step() is None; it must be a number"),
    ("toy_envs:time_limited_seed_only_reset", "the env's reset() takes no options: Gymnasium envs define "
                                              "reset(self, *, seed=None, options=None)"),
])
def test_what_will_break_the_run_stops_it_before_training_in_one_line(algo_preset, env_id, fragment, tmp_path,
                                                                        capfd):
    from relayrl.cli import main

    run = tmp_path / "run"
    code = main(["train", algo_preset, "--run-dir", str(run), "--no-progress", "--set", f"env.id={env_id}",
                 "--set", "train.total_steps=100000", "--set", "train.initial_collect_steps=0"])
    err = capfd.readouterr().err
    assert code == 2
    assert err == f"relayrl: error: env.id={env_id!r}: {fragment}" + err.split(fragment)[1]
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not run.exists()  # nothing trained, nothing written


@pytest.mark.parametrize("vectorization", ["sync", "async"])
@pytest.mark.parametrize(("env_id", "fragment"), [
    ("toy_envs:OldReset", "the env's reset() takes no seed"),
    ("toy_envs:time_limited_seed_only_reset", "the env's reset() takes no options"),
    ("toy_envs:NoActionSpace", "the env has no action_space"),
    ("toy_envs:BareReset", "reset() of env copy 0 returned a ndarray; Gymnasium envs return (obs, info)"),
])
def test_an_env_off_the_gymnasium_api_is_one_line_with_the_check_off(env_id, fragment, vectorization, tmp_path):
    config = load_config("dqn-cartpole", TINY + [f"env.id={env_id}", "env.check=false", "env.num_envs=2",
                                                 f"env.vectorization={vectorization}", "env.num_workers=1"])
    with pytest.raises(UserError, match=re.escape(fragment)):
        train(config, tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("vectorization", ["sync", "async"])
@pytest.mark.parametrize(("env_id", "fragment"), [
    ("toy_envs:FourValueStep", "step() of env copy 0 returned 4 values; Gymnasium envs return 5"),
    ("toy_envs:ArrayReward", "the reward from step() of env copy 0 has shape (1,); it must be one number"),
    ("toy_envs:NoneReward", "the reward from step() of env copy 0 is None; it must be a number"),
    ("toy_envs:TextReward", "the reward from step() of env copy 0 is '1.0'; it must be a number"),
])
def test_a_step_off_the_gymnasium_api_is_one_line_with_the_check_off(env_id, fragment, vectorization, tmp_path):
    """Found at the first step (the step-0 evaluation's, through the cap on an env without a
    time limit) rather than by the start's check: the same line, naming the copy."""
    config = load_config("dqn-cartpole", TINY + [f"env.id={env_id}", "env.check=false", "env.num_envs=2",
                                                 f"env.vectorization={vectorization}", "env.num_workers=1"])
    with pytest.raises(UserError, match=re.escape(fragment)):
        train(config, tmp_path / "run", progress=False)


def test_an_env_factory_async_envs_cannot_pickle_is_one_line(tmp_path):
    import threading

    lock = threading.Lock()
    config = load_config("dqn-cartpole", TINY + ["env.num_envs=2", "env.vectorization=async", "env.num_workers=1"])
    with pytest.raises(UserError, match=r"^env.vectorization='async' sends the env factory to its worker processes "
                                        r"pickled, and it cannot be pickled \(TypeError: cannot pickle '_thread.lock"):
        train(config, tmp_path / "run", progress=False, env=lambda: lock and toy_envs.Countdown())
    assert not (tmp_path / "run").exists()


def test_an_env_factorys_broken_env_is_one_line_too(tmp_path):
    config = load_config("dqn-cartpole", TINY)
    with pytest.raises(UserError, match=r"^the env from the factory given to relayrl.train: step\(\) returned 4"):
        train(config, tmp_path / "run", progress=False, env=lambda: toy_envs.FourValueStep())
    assert not (tmp_path / "run").exists()


def test_what_relayrl_casts_or_tolerates_stays_a_warning(tmp_path, capfd):
    """float64 observations of the space's shape are cast; the checker's line is a warning."""
    config = load_config("dqn-cartpole", TINY + ["env.id=toy_envs:Float64Obs", "env.max_episode_steps=5"])
    result = train(config, tmp_path / "run", progress=False)
    assert result.final["step"] == 60
    assert "env check (env.check = false turns it off)" in capfd.readouterr().err


@pytest.mark.parametrize("space, obs, fragment", [
    (gym.spaces.Box(0, 1, (2,), np.float32), np.zeros(2, np.float64), None),  # cast
    (gym.spaces.Box(0, 1, (2,), np.float32), np.full(2, 7.0, np.float32), None),  # out of bounds: harmless
    (gym.spaces.Box(0, 1, (2,), np.float32), np.zeros((1, 2)), "has shape (1, 2)"),
    (gym.spaces.Box(0, 1, (2,), np.float32), np.array(["a", "b"]), "not numbers"),
    (gym.spaces.Discrete(3), 2, None),
    (gym.spaces.Discrete(3), np.array([2]), "has shape (1,)"),
    (gym.spaces.Dict({"a": gym.spaces.Discrete(2)}), {"b": 1}, "Dict with keys ['a']"),
    (gym.spaces.Tuple((gym.spaces.Discrete(2),) * 2), (1,), "a Tuple of 2"),
    # an integer space: whole floats are cast without loss; fractions or wrapped values are not
    (gym.spaces.Box(0, 255, (2, 2), np.uint8), np.full((2, 2), 3.0, np.float32), None),
    (gym.spaces.Box(0, 255, (2, 2), np.uint8), np.full((2, 2), 0.5, np.float32),
     "holds float32 values that are not whole numbers (such as 0.5) but observation_space is Box(0, 255, (2, 2), "
     "uint8), which keeps uint8 integers: declare a float32 Box (frames scaled to [0, 1]"),
    (gym.spaces.Box(0, 255, (2,), np.uint8), np.array([1, 300]), "holds 300, outside uint8's range [0, 255]"),
    (gym.spaces.Box(0, 255, (2,), np.uint8), np.array([1, 256]), "holds 256, outside"),  # would train as 0
    (gym.spaces.Box(0, 10, (2,), np.int32), np.array([1, 300]), None),  # outside the bounds only: harmless
    (gym.spaces.Discrete(3), 1.5, "not whole numbers (such as 1.5)"),
    (gym.spaces.MultiBinary(2), np.array([True, False]), None),
])
def test_the_probe_flags_only_what_cannot_be_read(space, obs, fragment):
    from relayrl.envs.observations import observation_problem

    problem = observation_problem(obs, space, "step()")
    assert (problem is None) if fragment is None else (fragment in problem)


def test_an_env_id_recorded_for_a_python_factory_is_known_as_one():
    from relayrl.envs.resolve import names_python_factory

    # what only the same env= makes again (the Ctrl-C advice names env= for these, and make_env refuses them)
    assert names_python_factory("__main__:make_env") and names_python_factory("tests.envs:<lambda>")
    assert not names_python_factory("toy_envs:make_countdown") and not names_python_factory("CartPole-v1")
    assert not names_python_factory("relayrl/Atari-Pong-v0")


def test_a_run_says_when_its_wrappers_change_the_rewards_its_evaluations_report():
    from relayrl.envs.make import reward_wrappers, statistics_wrappers, wrapper_layers

    def rewards(*args, **kw):
        return reward_wrappers(wrapper_layers(*args, **kw))

    assert rewards("CartPole-v1", wrappers=["gymnasium.wrappers:NormalizeReward"]) == ["NormalizeReward"]
    # A function returning one (README's pattern), behind an observation wrapper
    assert rewards("toy_envs:Countdown", wrappers=["toy_envs:double_reward", "toy_envs:shift_obs"]) == [
        "TransformReward"]
    assert rewards("CartPole-v1", wrappers=["toy_envs:shift_obs"]) == []  # observations only
    assert rewards("CartPole-v1") == []
    assert rewards("CartPole-v1", wrappers=["not_a_module_here:Wrap"]) == []  # the run says what is wrong
    state = np.random.get_state()[1].copy()
    rewards("CartPole-v1", wrappers=["toy_envs:double_reward"])
    assert np.array_equal(np.random.get_state()[1], state)  # a checked run is the unchecked one
    layers = wrapper_layers("CartPole-v1", wrappers=["gymnasium.wrappers:NormalizeObservation", "toy_envs:shift_obs"])
    assert statistics_wrappers(layers) == ["NormalizeObservation"] and reward_wrappers(layers) == []


def test_reward_wrapper_note_is_in_the_log(tmp_path, capsys):
    config = load_config("dqn-cartpole", TINY + ['env.wrappers=["toy_envs:double_reward"]'])
    train(config, tmp_path / "run", progress=False)
    err = capsys.readouterr().err
    assert "env.wrappers put TransformReward over the env: evaluations report returns of those rewards" in err
    # the training returns too, which a CleanRL user reads as the raw RecordEpisodeStatistics ones
    assert "and so do the training returns (train/average_return, TensorBoard's charts/episodic_return)" in err
    config = load_config("dqn-cartpole", TINY + ['env.wrappers=["gymnasium.wrappers:NormalizeObservation"]'])
    train(config, tmp_path / "run2", progress=False)
    err = capsys.readouterr().err
    assert "env.wrappers put NormalizeObservation over the env: its running statistics live in each env copy" in err
    assert "PPO's agent.normalize_obs keeps the statistics with the policy" in err


def test_an_env_id_naming_a_class_of_the_script_itself_says_to_give_it_as_env(monkeypatch):
    """A notebook's `config.env.id = "__main__:Corridor"` was told about an env= never given."""
    import sys
    import types

    from relayrl.envs.resolve import resolve_env_fn

    main = types.ModuleType("__main__")
    main.Corridor = toy_envs.Countdown
    monkeypatch.setitem(sys.modules, "__main__", main)
    with pytest.raises(UserError, match=r"^env.id='__main__:Corridor' names Corridor of the script or notebook "
                                        r"itself, which no other process imports: give it as env=Corridor"):
        resolve_env_fn("__main__:Corridor")
    with pytest.raises(UserError, match="records an env factory given to relayrl.train"):
        resolve_env_fn("__main__:Other")  # not there: a factory recorded by another process


class _Settings:
    """An object without a repr of its own: its default one names its address, another in every process."""


def test_a_partials_recorded_arguments_leave_out_addresses_and_an_earlier_versions_record_resumes(tmp_path):
    settings = _Settings()
    factory = functools.partial(toy_envs.Countdown, length=6)
    assert "0x" not in factory_env_id(functools.partial(toy_envs.Countdown, settings))
    config = load_config("dqn-cartpole", TINY)
    train(config, tmp_path / "run", progress=False, env=factory)
    old = (tmp_path / "run" / "config.toml").read_text().replace("toy_envs:<partial(Countdown, length=6)>",
                                                                   "functools:<partial>")
    (tmp_path / "run" / "config.toml").write_text(old)  # as the version before recorded every partial
    for path in (tmp_path / "run" / "checkpoints").glob("ckpt-*.pt"):  # in its checkpoints too
        state = torch.load(path, weights_only=False)
        state["config"]["env"]["id"] = "functools:<partial>"
        torch.save(state, path)
    longer = load_config(str(tmp_path / "run" / "config.toml"), ["train.total_steps=120"])
    train(longer, tmp_path / "run", resume=True, progress=False, env=factory)
    assert load_toml(tmp_path / "run" / "config.toml")["env"]["id"] == "functools:<partial>"
