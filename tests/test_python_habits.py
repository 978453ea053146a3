"""Python habits (issue 32, D): relayrl.evaluate, record_video(env=), train(callbacks=), SAC's
learning-rate schedule, dir(relayrl)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from space_envs import Spaces
from toy_envs import Countdown, Repeated

import relayrl
from relayrl.config import load_toml
from relayrl.errors import UserError
from relayrl.plot import seed_groups
from relayrl.training.run_dir import RunDir

TINY = {"algo": "dqn", "env": {"id": "toy_envs:Countdown", "check": False},
        "train": {"total_steps": 200, "initial_collect_steps": 50, "checkpoint_interval": 100,
                  "policy_save_interval": 100, "log_interval": 50},
        "eval": {"interval": 50, "episodes": 2}, "agent": {"batch_size": 8}}


class Growing(Countdown):
    """Countdown of 2 steps whose reward is 1 + the episode index: returns 2, 4, 6, 8, ..."""

    def __init__(self, render_mode: str | None = None) -> None:
        super().__init__(length=2, render_mode=render_mode)

    def step(self, action):
        obs, _, terminated, truncated, info = super().step(action)
        return obs, 1.0 + self.episode, terminated, truncated, info


class MoreActions(Countdown):
    """Countdown's observations with a third action: not the Discrete(2) a TINY run's policy gives."""

    def __init__(self, render_mode: str | None = None) -> None:
        super().__init__(render_mode=render_mode)
        self.action_space = gym.spaces.Discrete(3)


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("habits") / "run"
    relayrl.train(TINY, root, progress=False)
    return root


def test_evaluate_returns_mean_and_std_as_sb3():
    mean, std = relayrl.evaluate(lambda obs: 0, Growing(), episodes=4)  # one copy: returns 2, 4, 6, 8
    assert (mean, std) == (5.0, pytest.approx(math.sqrt(5.0)))
    result = relayrl.evaluate(lambda obs: 1, lambda: Countdown(length=3), episodes=5, seed=1)
    assert isinstance(result, relayrl.EvalResult) and (result.mean, result.std) == (3.0, 0.0)


def test_evaluate_a_run_dir_and_a_loaded_policy(run_dir):
    assert tuple(relayrl.evaluate(run_dir, episodes=3)) == (3.0, 0.0)  # the run's own env
    policy = relayrl.load_policy(run_dir)
    assert repr(policy) == ("LoadedPolicy(kind='q_greedy', observations=Box(shape=(2,), dtype=float32), "
                            "deterministic=True, env_steps=200)")
    assert tuple(relayrl.evaluate(policy, "toy_envs:Countdown", episodes=3)) == (3.0, 0.0)
    assert tuple(relayrl.evaluate(run_dir, Countdown(length=4), episodes=2)) == (4.0, 0.0)
    # a greedy policy has no sampling mode: SB3-style code asking for one gets the greedy actions
    assert tuple(relayrl.evaluate(run_dir, Countdown(), episodes=3, deterministic=False)) == (3.0, 0.0)
    assert policy.predict(np.zeros(2, np.float32), deterministic=False)[0] == policy(np.zeros(2, np.float32))
    with pytest.raises(UserError, match=r"an \(observation, info\) pair, what env.reset\(\) returns"):
        policy.predict(Countdown().reset(seed=0))  # SB3 habit from the old Gym API
    with pytest.raises(UserError, match=r"env.s observations \(Box\(.*shape=\(4,\).* do not fit the policy"):
        relayrl.evaluate(policy, "CartPole-v1")  # said before any episode, in the env's terms


def test_an_env_whose_actions_or_discrete_sizes_are_not_the_policys_is_one_line(run_dir, tmp_path):
    # Only the observations' shapes were compared: a Discrete(2) policy ran on a Discrete(3) env
    # (never taking the third action), a [-2, 2] one on a [-1, 1] env, and a Discrete(16)
    # observation policy on Discrete(64) raised torch's one-hot IndexError.
    with pytest.raises(UserError, match=r"^this env's actions \(Discrete\(3\)\) are not the policy's \(trained on "
                                        r"toy_envs:Countdown\): it gives Discrete\(2\) actions$"):
        relayrl.evaluate(run_dir, MoreActions(), episodes=1)
    with pytest.raises(UserError, match=r"this env's actions \(Discrete\(3\)\) are not the policy's"):
        relayrl.record_video(run_dir, tmp_path / "v.mp4", env=MoreActions)
    assert not (tmp_path / "v.mp4").exists()
    lake = {**TINY, "env": {"id": "FrozenLake-v1", "kwargs": {"is_slippery": False}}}
    relayrl.train(lake, tmp_path / "lake", progress=False)
    with pytest.raises(UserError, match=r"^this env's observations \(Discrete\(64\)\) do not fit the policy \(trained "
                                        r"on FrozenLake-v1\): it takes Discrete\(16\) observations$"):
        relayrl.evaluate(tmp_path / "lake", "FrozenLake8x8-v1", episodes=1)
    relayrl.train({**TINY, "algo": "sac", "env": {"id": "Pendulum-v1"}}, tmp_path / "sac", progress=False)
    rescaled = lambda: gym.wrappers.RescaleAction(gym.make("Pendulum-v1"), np.float32(-1), np.float32(1))  # noqa: E731
    with pytest.raises(UserError, match=r"this env's actions \(Box\(-1, 1, .*not the policy's \(trained on "
                                        r"Pendulum-v1\): it gives Box\(-2, 2"):
        relayrl.evaluate(tmp_path / "sac", rescaled, episodes=1)
    assert relayrl.evaluate(tmp_path / "sac", "Pendulum-v1", episodes=1).mean < 0  # its own env still runs


def test_evaluate_bad_input_is_one_line():
    with pytest.raises(UserError, match="episodes=0"):
        relayrl.evaluate(lambda o: 0, Countdown(), episodes=0)
    with pytest.raises(UserError, match=r"^episodes=True is not valid; it must be an integer >= 1$"):
        relayrl.evaluate(lambda o: 0, Countdown(), episodes=True)
    for cap in (-5, 2.5, "7"):  # as `relayrl eval --max-episode-steps` refuses them, not Gymnasium's TypeError
        with pytest.raises(UserError, match=rf"^max_episode_steps={cap!r} is not valid; it must be an integer >= 1, "
                                            r"or 0 for the env's own time limit$"):
            relayrl.evaluate(lambda o: 0, Countdown(), episodes=1, max_episode_steps=cap)
    with pytest.raises(UserError, match="not a policy"):
        relayrl.evaluate(3, Countdown())
    with pytest.raises(UserError, match="env=None"):
        relayrl.evaluate(lambda o: 0)
    vector = gym.vector.SyncVectorEnv([Countdown, Countdown])
    with pytest.raises(UserError, match="env=SyncVectorEnv is a vector env; give one env, an env id, or a callable"):
        relayrl.evaluate(lambda o: 0, vector)
    vector.close()


@pytest.mark.parametrize("seed", [-1, "a", 1.5, True])
def test_a_seed_that_is_no_seed_is_one_line_not_a_broken_policy_file(run_dir, seed):
    # evaluate() raised Gymnasium's or NumPy's own error (TypeError for "a"); load_policy said the
    # policy file "does not hold a complete ... policy" and blamed the file.
    with pytest.raises(UserError, match=rf"^seed={seed!r} is not valid; it must be an integer in \[0, "):
        relayrl.evaluate(run_dir, episodes=1, seed=seed)
    with pytest.raises(UserError, match=rf"^seed={seed!r} is not valid"):
        relayrl.load_policy(run_dir, deterministic=False, seed=seed)
    assert relayrl.load_policy(run_dir, seed=np.int64(3)) is not None


def test_max_episode_steps_cuts_an_env_instances_episodes_as_it_does_an_ids_and_a_factorys():
    # An instance with a time limit of its own ran its episodes to that limit: the setting was ignored.
    def timed():
        return gym.wrappers.TimeLimit(Countdown(length=50), 100)

    for env in (timed(), timed):
        returns, lengths = relayrl.evaluate(lambda o: 0, env, episodes=2, max_episode_steps=5,
                                            return_episode_rewards=True)
        assert lengths == [5, 5], env
    assert relayrl.evaluate(lambda o: 0, timed(), episodes=1, return_episode_rewards=True)[1] == [50]


def test_load_policy_given_a_list_of_runs_says_one_policy_per_call(run_dir):
    with pytest.raises(UserError, match=r"is not a run directory or a policy file; one policy per call: "
                                        r"\[relayrl.load_policy\(d\) for d in run_dirs\]"):
        relayrl.load_policy([run_dir, run_dir])  # was pathlib's TypeError ("not list")


def test_load_policy_takes_a_configs_device_names_and_says_which_it_cannot_use(run_dir):
    # "auto" (a config's device) and "gpu" raised torch's RuntimeError; "cuda" on a machine
    # without CUDA, torch's AssertionError ("Torch not compiled with CUDA enabled").
    policy = relayrl.load_policy(run_dir, device="auto")
    assert policy(np.zeros(2, np.float32)) in (0, 1)
    assert relayrl.load_policy(run_dir, device=torch.device("cpu"))(np.zeros(2, np.float32)) in (0, 1)
    with pytest.raises(UserError, match=r"^device='gpu' is not a device; valid: cpu, cuda, cuda:N, auto$"):
        relayrl.load_policy(run_dir, device="gpu")
    if not torch.cuda.is_available():
        with pytest.raises(UserError, match=r"^device='cuda' but CUDA is not available here"):
            relayrl.load_policy(run_dir, device="cuda")


def test_a_cuda_index_past_the_machines_gpus_is_one_line(monkeypatch):
    """A cluster's `device = "cuda:1"` on a one-GPU workstation (torch: "invalid device ordinal")."""
    from relayrl.training.process import resolve_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert resolve_device("cuda:0") == torch.device("cuda:0")
    with pytest.raises(UserError, match=r"^device='cuda:1' but this machine has 1 CUDA device; valid: cuda:0 to "
                                        r"cuda:0, cuda, cpu, auto$"):
        resolve_device("cuda:1")
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)
    with pytest.raises(UserError, match=r"^device='cuda:0' but this machine has 0 CUDA devices; valid: cpu, auto$"):
        resolve_device("cuda:0")


def test_device_auto_without_a_gpu_says_the_run_trains_on_the_cpu(tmp_path, capfd):
    config = relayrl.load_config("dqn-cartpole-fast", ["train.total_steps=200", "train.initial_collect_steps=100",
                                                       "eval.interval=0", "eval.episodes=1", "device=auto"])
    relayrl.train(config, tmp_path / "run", progress=False)
    said = 'device = "auto" finds no CUDA GPU here (torch.cuda.is_available() is False): the run trains on the CPU'
    assert (said in capfd.readouterr().err) == (not torch.cuda.is_available())


def test_record_video_with_env(run_dir, tmp_path):
    factory = lambda render_mode=None: Countdown(render_mode=render_mode)  # noqa: E731
    out = relayrl.record_video(run_dir, tmp_path / "a.mp4", env=factory)
    assert out.stat().st_size > 0
    made = Countdown(render_mode="rgb_array")
    assert relayrl.record_video(run_dir, tmp_path / "b.mp4", env=made).stat().st_size > 0
    with pytest.raises(UserError, match="render_mode='rgb_array'"):
        relayrl.record_video(run_dir, tmp_path / "c.mp4", env=Countdown())
    with pytest.raises(UserError, match="must take render_mode"):
        relayrl.record_video(run_dir, tmp_path / "d.mp4", env=lambda: Countdown())
    other = lambda render_mode=None: Repeated(Countdown(render_mode=render_mode))  # noqa: E731
    with pytest.raises(UserError, match=r"this env's observations \(Box\(.*shape=\(4,\).*\) do not fit the policy"):
        relayrl.record_video(run_dir, tmp_path / "e.mp4", env=other)
    assert not (tmp_path / "e.mp4").exists()


def test_record_video_takes_the_runs_policy_file_or_config_as_eval_does(run_dir, tmp_path):
    # was "'.../policy/policy.pt' is a file, not a run directory", though the error for a checkpoint
    # given as a policy says video takes "the run directory or its policy/policy.pt"
    factory = lambda render_mode=None: Countdown(render_mode=render_mode)  # noqa: E731
    for given in (run_dir / "policy" / "policy.pt", run_dir / "config.toml"):
        assert relayrl.record_video(given, tmp_path / f"{given.stem}.mp4", env=factory).stat().st_size > 0
    lone = tmp_path / "shared" / "policy.pt"
    lone.parent.mkdir()
    lone.write_bytes((run_dir / "policy" / "policy.pt").read_bytes())
    with pytest.raises(UserError, match=r"is a file, not a run directory"):
        relayrl.record_video(lone, tmp_path / "lone.mp4", env=factory)


def test_video_shows_every_state_of_each_episode_including_the_last(run_dir, tmp_path):
    import imageio.v2 as imageio

    factory = lambda render_mode=None: Countdown(length=3, render_mode=render_mode)  # noqa: E731
    path = relayrl.record_video(run_dir, tmp_path / "v.mp4", episodes=2, env=factory)
    shades = [round(float(frame.mean()) / 40) for frame in imageio.get_reader(path)]
    assert shades == [0, 1, 2, 3, 0, 1, 2, 3]  # states t = 0..3 (Countdown renders 40 t), twice


@pytest.mark.parametrize("given", [{"episodes": 0}, {"episodes": -1}, {"max_steps": 0}])
def test_video_refuses_no_episodes_instead_of_recording_one(run_dir, tmp_path, given):
    factory = lambda render_mode=None: Countdown(render_mode=render_mode)  # noqa: E731
    with pytest.raises(UserError, match=f"{next(iter(given))}=-?[0-9] is not valid; it must be an integer >= 1"):
        relayrl.record_video(run_dir, tmp_path / "v.mp4", env=factory, **given)
    assert not (tmp_path / "v.mp4").exists()


class OddFrames(Countdown):
    """Countdown rendering 15x21 frames: sides H.264 (yuv420p) does not take as they are."""

    def render(self):
        return np.full((15, 21, 3), 40 * self.t % 255, np.uint8)


@pytest.mark.parametrize("suffix", [".mp4", ".mkv"])
def test_video_of_frames_with_odd_sides_is_a_playable_file(run_dir, tmp_path, suffix):
    import imageio.v2 as imageio

    factory = lambda render_mode=None: OddFrames(render_mode=render_mode)  # noqa: E731
    path = relayrl.record_video(run_dir, tmp_path / f"v{suffix}", env=factory)
    frames = imageio.mimread(path)  # ffmpeg wrote an empty file here before
    assert len(frames) == 4 and frames[0].shape == (16, 22, 3)  # one edge row and column repeated


@pytest.mark.parametrize("algo", ["dqn", "ppo", "sac"])
def test_callbacks_see_every_eval_and_log_and_false_stops(algo, tmp_path):
    cfg = {"algo": algo, "env": {"id": "Pendulum-v1" if algo == "sac" else "toy_envs:Countdown", "check": False},
           "train": {"total_steps": 1_000, "initial_collect_steps": 0 if algo == "ppo" else 50,
                     "collect_steps": 50 if algo == "ppo" else 1, "checkpoint_interval": 10_000,
                     "policy_save_interval": 10_000, "log_interval": 50},
           "eval": {"interval": 100, "episodes": 1}, "agent": {"batch_size": 16}}
    rows: list[dict] = []
    evaluated: list[int] = []

    def cb(row):
        rows.append(row)
        if row["event"] == "eval":  # the policy file is the policy just evaluated (SB3's "save best" needs it)
            evaluated.append(relayrl.load_policy(tmp_path / "r").env_steps)
        # stop at the 2nd evaluation after 0; NumPy's False stops as Python's does (None goes on)
        return np.logical_not(row["event"] == "eval" and row["step"] >= 200)

    result = relayrl.train(cfg, tmp_path / "r", progress=False, callbacks=[cb])
    assert evaluated == [0, 100, 200]
    assert result.stopped_early and result.final["step"] == 200
    evals = [r for r in rows if r["event"] == "eval"]
    assert [r["step"] for r in evals] == [0, 100, 200] and "average_return" in evals[0]
    logs = [r for r in rows if r["event"] == "log"]
    assert len(logs) == 3 and logs[-1]["step"] == 150 and "perf/sps" in logs[-1]  # one per log_interval
    assert rows[-1] is evals[-1]  # nothing more after the False (the log row at 200 is not sent)
    rd = tmp_path / "r"
    assert (rd / "checkpoints" / "ckpt-200.pt").exists() or any((rd / "checkpoints").glob("*200*"))
    assert relayrl.load_policy(rd).env_steps == 200
    metrics = (rd / "metrics.jsonl").read_text().splitlines()
    assert len(metrics) == 3 and '"event"' not in metrics[0]  # metrics.jsonl's rows as before


def test_a_callback_that_returned_false_is_not_called_again_and_the_others_still_are(tmp_path):
    stopper, logger = [], []

    def stop_at_50(row):
        stopper.append((row["event"], row["step"]))
        return row["step"] < 50

    relayrl.train({**TINY, "eval": {"interval": 100, "episodes": 2}}, tmp_path / "r", progress=False,
                  callbacks=[stop_at_50, lambda row: logger.append((row["event"], row["step"]))])
    (_, at), = [r for r in stopper if r[0] == "log"]  # the first log row, just past 50 (collect steps of 4)
    assert stopper == [("eval", 0), ("log", at)]
    assert logger == [("eval", 0), ("log", at), ("eval", at)]  # the stop's own evaluation reaches the other


def test_a_callback_that_raises_propagates_and_keeps_the_checkpoint(tmp_path):
    def cb(row):
        if row["step"] >= 150:
            raise RuntimeError("mine")

    with pytest.raises(RuntimeError, match="mine"):
        relayrl.train(TINY, tmp_path / "r", progress=False, callbacks=[cb])
    assert list((tmp_path / "r" / "checkpoints").glob("ckpt-*"))


def test_a_callback_that_raises_before_the_first_checkpoint_says_how_to_start_again(tmp_path):
    """Nothing to resume from: a plain retrain of the directory is refused (it holds a run past
    step 0), so the note says --overwrite."""
    def cb(row):
        if row["step"] > 0:
            raise RuntimeError("mine")

    config = {**TINY, "train": {**TINY["train"], "checkpoint_interval": 100_000}}
    with pytest.raises(RuntimeError, match="mine") as caught:
        relayrl.train(config, tmp_path / "r", progress=False, callbacks=[cb])
    note = " ".join(caught.value.__notes__)
    assert "no checkpoint to resume from: a new run there starts over (with --overwrite" in note, note


def test_callbacks_refused_where_not_supported(tmp_path):
    with pytest.raises(UserError, match="trains by its own loop"):  # bptt: no Actor + Learner loop
        relayrl.train(relayrl.load_config("bptt-pendulum"), tmp_path / "r", callbacks=[print])
    with pytest.raises(UserError, match="not callable"):
        relayrl.train(TINY, tmp_path / "r", callbacks=[3])


def test_a_callback_that_cannot_take_one_row_is_refused_before_the_run_starts(tmp_path):
    # SB3's old (locals, globals) callbacks raised TypeError from the step-0 evaluation, with the
    # run directory made and a half run in it.
    def two(locals_, globals_):
        return True

    for cb in (two, lambda: True):
        with pytest.raises(UserError, match=r"cannot be called with one argument; a callback takes the metrics row"):
            relayrl.train(TINY, tmp_path / "r", callbacks=[lambda row: None, cb])
        assert not (tmp_path / "r").exists()

    class Pruner:
        def __call__(self, row, *rest, trial=None):
            return True

    from relayrl.dispatch import _check_callbacks

    assert len(_check_callbacks([print, Pruner(), lambda row, k=1: None], True)) == 3


@pytest.mark.parametrize("fast", [True, False])
def test_sac_lr_schedule_reaches_every_optimizer(fast):
    from relayrl.agents.sac.agent import SACAgent
    from relayrl.agents.sac.config import SACConfig
    from relayrl.specs import ArraySpec
    from relayrl.types import Batch

    obs = ArraySpec((3,), torch.float32, -np.ones(3), np.ones(3))
    act = ArraySpec((1,), torch.float32, np.array([-2.0]), np.array([2.0]))
    cfg = SACConfig(lr_end=0.0, batch_size=4, actor_lr=1e-3, critic_lr=2e-3, alpha_lr=3e-3)
    agent = SACAgent(obs, act, cfg, torch.device("cpu"), np.random.default_rng(0), total_steps=1000,
                     hand_written=fast)
    agent.set_progress(500)
    assert (agent.actor_opt.lr, agent.critic_opt.lr, agent.alpha_opt.lr) == pytest.approx((5e-4, 1e-3, 1.5e-3))
    assert agent.scalars(500)["learning_rate"] == pytest.approx(5e-4)
    agent.set_progress(1000)  # lr 0: a gradient step leaves every weight where it was
    before = [p.detach().clone() for p in [*agent.actor.parameters(), *agent.critic.parameters(), agent.log_alpha]]
    g = torch.Generator().manual_seed(0)
    batch = Batch(obs=torch.randn(4, 3, generator=g), action=torch.rand(4, 1, generator=g) * 4 - 2,
                  reward=torch.randn(4, generator=g), discount=torch.ones(4),
                  next_obs=torch.randn(4, 3, generator=g), weight=None)
    agent.train(batch)
    after = [*agent.actor.parameters(), *agent.critic.parameters(), agent.log_alpha]
    assert all(torch.equal(a, b) for a, b in zip(before, after, strict=True))
    constant = SACAgent(obs, act, SACConfig(), torch.device("cpu"), np.random.default_rng(0), total_steps=1000)
    constant.set_progress(900)
    assert constant.actor_opt.lr == 3e-4  # the default stays constant


def test_dir_shows_the_public_api():
    names = dir(relayrl)
    for name in ("train", "evaluate", "load_policy", "record_video", "load_config", "Config", "EvalResult",
                 "RunResult"):
        assert name in names and name in relayrl.__all__
    assert callable(relayrl.evaluate)
    assert not {"Any", "TYPE_CHECKING", "annotations", "ModuleType"} & set(names)


def test_help_says_what_train_returns():
    from relayrl.training.lifecycle import RunResult

    doc = RunResult.__doc__ or ""
    assert not doc.startswith("RunResult(")  # the dataclass's own: its signature, nothing about the fields
    for field in ("run_dir", "final", "stopped_early", "last evaluation row"):
        assert field in doc
    assert "returns a `RunResult`" in (relayrl.train.__doc__ or "")


def test_train_takes_a_config_toml_path_and_a_run_directory_gets_a_hint(run_dir, tmp_path):
    from relayrl.config import from_dict, save_toml

    save_toml(from_dict(TINY), tmp_path / "my.toml")
    result = relayrl.train(str(tmp_path / "my.toml"), tmp_path / "run", progress=False)
    assert result.final["step"] == 200
    with pytest.raises(UserError, match=r"config=3 is not a config: give a Config"):
        relayrl.train(3, tmp_path / "other", progress=False)
    with pytest.raises(UserError, match=r"is a run directory, not a preset: continue it with `relayrl train "
                                        r"--run-dir .* --resume` \(in Python: resume=True\), or start a new run "
                                        r"from its settings with"):
        relayrl.load_config(str(run_dir))


def test_plot_of_a_run_under_way_without_evaluations_says_when_it_gets_one(tmp_path):
    from relayrl.config import from_dict, save_toml

    for interval, why in ((0, "its eval.interval is 0, so it evaluates once, at the end of training"),
                          (50, "train first")):
        run = tmp_path / f"run{interval}"
        run.mkdir()  # a run under way writes config.toml first and metrics.jsonl at its evaluations
        save_toml(from_dict({**TINY, "eval": {"interval": interval, "episodes": 2}}), run / "config.toml")
        with pytest.raises(UserError, match=rf"has no evaluations yet; {why}"):
            relayrl.plot_run(run)


def test_plot_panels_follow_what_the_run_logged(run_dir, tmp_path):
    from relayrl.plot import panels_for

    dqn = [{"step": 0, "losses/loss": 1.0, "losses/q": 2.0}]
    sac = [{"step": 0, "losses/critic_loss": 1.0, "losses/actor_loss": -1.0, "losses/q": 2.0}]
    assert [k for k, _ in panels_for(dqn, False)] == ["average_episode_length", "losses/loss", "losses/q"]
    assert [k for k, _ in panels_for(sac, False)] == ["average_episode_length", "losses/critic_loss", "losses/q"]
    assert panels_for([{"step": 0}], False) == []  # PPO: the returns alone
    # a run with one evaluation plots (its axis starts at 0)
    one = tmp_path / "one"
    relayrl.train({**TINY, "train": {**TINY["train"], "total_steps": 40, "initial_collect_steps": 40}}, one,
                  progress=False)
    assert relayrl.plot_run(one).stat().st_size > 0
    from matplotlib.figure import Figure

    from relayrl.plot import _steps_axis

    ax = Figure().subplots()
    _steps_axis(ax, [500])
    assert ax.get_xlim()[0] == 0 and ax.get_xlim()[1] > 500  # the one point inside the axis, not on its edge


def test_several_runs_plot_in_one_panel(run_dir, tmp_path, capsys):
    """A sweep's runs compared: compare.png beside them, or --out where they are in several folders."""
    from relayrl.cli import main

    sweep = tmp_path / "sweep"
    for seed in (1, 2):
        relayrl.train({**TINY, "seed": seed}, sweep / f"seed{seed}", progress=False)
    capsys.readouterr()
    assert main(["plot", str(sweep / "seed1"), str(sweep / "seed2")]) == 0
    assert capsys.readouterr().out.strip() == str(sweep / "compare.png") and (sweep / "compare.png").stat().st_size
    # the sweep's folder stands for its runs; `plot sweep/*` also matches the compare.png plotted before
    assert main(["plot", str(sweep)]) == 0 and capsys.readouterr().out.strip() == str(sweep / "compare.png")
    assert main(["plot", *sorted(str(p) for p in sweep.iterdir())]) == 0
    assert main(["plot", str(sweep / "seed1"), str(sweep / "seed1"), str(sweep / "seed2")]) == 0
    assert "'" + str(sweep / "seed1") + "' is given twice: drawn once" in capsys.readouterr().err
    # one setting's seeds are one curve (mean, min-max band); another setting is a curve of its own
    relayrl.train({**TINY, "seed": 1, "agent": {"lr": 3e-4}}, sweep / "other", progress=False)
    runs = [RunDir(sweep / n) for n in ("seed1", "other", "seed2")]
    assert seed_groups(runs) == [[0, 2], [1]]
    assert relayrl.plot_run([r.root for r in runs]).stat().st_size > 0
    assert "different envs" not in capsys.readouterr().err
    relayrl.train({**TINY, "env": {"id": "toy_envs:make_countdown"}}, sweep / "elsewhere", progress=False)
    relayrl.plot_run([sweep / "seed1", sweep / "elsewhere"])  # returns of another env: said, drawn all the same
    assert "the runs are on different envs (seed1: toy_envs:Countdown, elsewhere: toy_envs:make_countdown)" \
        in capsys.readouterr().err
    with pytest.raises(UserError, match="in different folders: give --out PATH"):
        relayrl.plot_run([sweep / "seed1", run_dir])
    assert relayrl.plot_run([sweep / "seed1", run_dir], tmp_path / "both.svg").stat().st_size > 0
    # plot_run(a, b), as the command line's `plot A B`, wrote a's plot over b's returns.png
    with pytest.raises(UserError, match=r"is another run's directory: to plot several runs in one panel give them "
                                        r"as one list, plot_run\(\["):
        relayrl.plot_run(sweep / "seed1", sweep / "seed2")
    assert not (sweep / "seed2" / "returns.png").exists()
    assert relayrl.plot_run(sweep / "seed1", sweep / "seed1") == sweep / "seed1" / "returns.png"
    (sweep / "empty").mkdir()
    assert main(["plot", str(sweep / "seed1"), str(sweep / "empty")]) == 2
    assert "is not a relayrl run directory (no config.toml)" in capsys.readouterr().err
    # a run with no evaluation yet (one stopped before its first) is left out, with a line saying so
    stopped = sweep / "stopped"
    stopped.mkdir()
    (stopped / "config.toml").write_text((sweep / "seed2" / "config.toml").read_text())
    capsys.readouterr()
    assert main(["plot", str(sweep / "seed1"), str(stopped)]) == 0
    assert "metrics.jsonl' has no evaluations yet: left out of the plot" in capsys.readouterr().err
    with pytest.raises(UserError, match="has no evaluations yet; train first"):  # none has any: nothing to plot
        relayrl.plot_run([stopped, stopped])


def test_a_seed_groups_curve_says_where_it_ends_early_and_when_runs_share_a_seed(tmp_path, capsys, monkeypatch):
    """A seed still running cut the group's mean back to its last step without a word, and copies
    of one run (one seed) were labelled as several seeds."""
    import shutil

    for seed in (1, 2):
        relayrl.train({**TINY, "seed": seed}, tmp_path / f"s{seed}", progress=False)
    running = tmp_path / "s3"
    running.mkdir()
    (running / "config.toml").write_text((tmp_path / "s2" / "config.toml").read_text().replace("seed = 2", "seed = 3"))
    (running / "metrics.jsonl").write_text("".join((tmp_path / "s2" / "metrics.jsonl").read_text()
                                                   .splitlines(keepends=True)[:2]))
    capsys.readouterr()
    relayrl.plot_run([tmp_path / n for n in ("s1", "s2", "s3")])
    assert "s1, s2, s3: their mean is drawn to env step 54, the last all 3 evaluated at (the longest goes to 200)" \
        in capsys.readouterr().err
    monkeypatch.chdir(tmp_path)  # relative paths give a relative one back, as one run's plot does
    assert relayrl.plot_run(["s1", "s2"]) == Path("compare.png")
    shutil.copytree(tmp_path / "s1", tmp_path / "copy")
    relayrl.plot_run([tmp_path / "s1", tmp_path / "copy"])
    assert "s1, copy share a seed (1, 1): their band is not a spread over seeds" in capsys.readouterr().err


def test_a_nested_sweep_folder_plots_and_partial_env_factories_are_told_apart(tmp_path, capsys):
    """`relayrl plot nest` of nest/lr1/s0 ... said 'not a relayrl run directory'; runs of
    functools.partial(Env, length=L) were recorded alike and drawn as one setting's seeds."""
    import functools
    import shutil

    from toy_envs import Countdown

    from relayrl.cli import main

    for length in (2, 4):
        relayrl.train({**TINY, "seed": length}, tmp_path / f"len{length}", progress=False,
                      env=functools.partial(Countdown, length=length))
    saved = [load_toml(tmp_path / f"len{n}" / "config.toml")["env"]["id"] for n in (2, 4)]
    assert saved == ["toy_envs:<partial(Countdown, length=2)>", "toy_envs:<partial(Countdown, length=4)>"]
    assert seed_groups([RunDir(tmp_path / "len2"), RunDir(tmp_path / "len4")]) == [[0], [1]]
    nest = tmp_path / "nest"
    for lr, run in (("lr1", "len2"), ("lr2", "len4")):
        shutil.copytree(tmp_path / run, nest / lr / "s0")
    capsys.readouterr()
    assert main(["plot", str(nest)]) == 0 and capsys.readouterr().out.strip() == str(nest / "compare.png")
    for lr in ("lr1", "lr2"):  # two seeds of one lambda: drawn as one setting, said to be a guess
        shutil.copytree(tmp_path / "len2", nest / lr / "s1")
        config = nest / lr / "s1" / "config.toml"
        config.write_text(config.read_text().replace("<partial(Countdown, length=2)>", "<lambda>")
                          .replace("seed = 2", "seed = 9"))
        (nest / lr / "s0" / "config.toml").write_text(config.read_text().replace("seed = 9", "seed = 8"))
    relayrl.plot_run(nest)
    assert ("lr1/s0, lr1/s1, lr2/s0, lr2/s1 were trained on env factories given in Python "
            "(env.id='toy_envs:<lambda>') that their config.toml cannot tell apart") in capsys.readouterr().err


def test_the_progress_bar_ends_at_the_last_step_with_the_last_evaluation(tmp_path, monkeypatch):
    import io

    import tqdm

    bars = []

    class Bar:  # tqdm as a terminal shows it (pytest has none, where tqdm does nothing)
        def __init__(self, total, initial=0, **kwargs):
            self.n, self.total, self.disable, self.postfix = initial, total, False, {}
            bars.append(self)

        def update(self, k):
            self.n += k

        def set_postfix(self, fields):
            self.postfix = dict(fields)

        def write(self, text):
            pass

        def close(self):
            pass

    class Terminal(io.StringIO):  # a bar is made on a terminal only
        def isatty(self):
            return True

    monkeypatch.setattr(tqdm, "tqdm", Bar)
    monkeypatch.setattr("sys.stderr", Terminal())
    cfg = {**TINY, "train": {**TINY["train"], "total_steps": 130, "log_interval": 50}}
    result = relayrl.train(cfg, tmp_path / "run", progress=True)
    assert bars[0].n == 130  # not the last log boundary (100)
    assert bars[0].postfix["eval"] == f"{result.final['average_return']:.1f}"



def test_train_leaves_the_callers_torch_threads_flushing_and_generator_as_they_were(tmp_path):
    threads, flushing = torch.get_num_threads(), torch.tensor([1e-39]).item() == 0.0  # (other tests' runs)
    torch.set_num_threads(2)
    torch.set_flush_denormal(False)
    try:
        torch.manual_seed(123)
        expected = torch.rand(1)
        torch.manual_seed(123)
        relayrl.train({**TINY, "train": {**TINY["train"], "torch_threads": 1}}, tmp_path / "r", progress=False)
        assert torch.get_num_threads() == 2  # the run used 1
        assert torch.tensor([1e-39]).item() != 0.0  # the run flushed denormals; the caller does not
        assert torch.equal(torch.rand(1), expected)  # the caller's generator, not the run's seed
    finally:
        torch.set_num_threads(threads)
        torch.set_flush_denormal(flushing)


def test_runs_started_in_threads_take_turns_and_repeat_their_seeds(tmp_path, capsys):
    """Optuna's n_jobs > 1 runs trials in threads: two runs at once drew network weights from one
    global torch generator, so a seed gave another run. The second waits for the first, and says so."""
    import json
    import threading

    def rows(root):
        return [{k: v for k, v in json.loads(line).items() if k not in ("wall_time_s", "eval_s")}
                for line in (root / "metrics.jsonl").read_text().splitlines()]

    alone = relayrl.train({**TINY, "seed": 1}, tmp_path / "alone", progress=False).run_dir
    events: list[str] = []
    second_started = threading.Event()
    other = threading.Thread(target=lambda: relayrl.train({**TINY, "seed": 1}, tmp_path / "b", progress=False,
                                                          callbacks=[lambda row: (events.append("b"),
                                                                                  second_started.set())]))

    def first(row):
        events.append("a")
        if not other.is_alive() and len(events) == 1:
            other.start()
            second_started.wait(timeout=3)  # it did start, while this run was under way

    relayrl.train(TINY, tmp_path / "a", progress=False, callbacks=[first])
    other.join()
    assert events == sorted(events) and "b" in events  # every "a" before the first "b"
    assert rows(tmp_path / "b") == rows(alone)
    assert "another relayrl.train is running in this process: this one starts when it ends" in capsys.readouterr().err


def test_a_resume_leaves_the_callers_numpy_and_python_generators_as_they_were(tmp_path):
    """A checkpoint holds the process's NumPy and Python generators (for envs drawing from them);
    restoring them is the run's business only."""
    import random

    relayrl.train(TINY, tmp_path / "r", progress=False)
    np.random.seed(7)
    random.seed(7)
    expected = (np.random.rand(), random.random())
    np.random.seed(7)
    random.seed(7)
    longer = relayrl.load_config(str(tmp_path / "r" / "config.toml"), ["train.total_steps=300"])
    relayrl.train(longer, tmp_path / "r", resume=True, progress=False)
    assert (np.random.rand(), random.random()) == expected


def test_runs_started_in_the_same_second_get_their_own_default_directories(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("time.strftime", lambda fmt: "20261127-081716")  # the same second each time
    roots = [relayrl.train({**TINY, "train": {**TINY["train"], "total_steps": 60}}, progress=False).run_dir
             for _ in range(3)]
    assert [r.name for r in roots] == ["dqn-toy_envs_Countdown-s0-20261127-081716",
                                       "dqn-toy_envs_Countdown-s0-20261127-081716-2",
                                       "dqn-toy_envs_Countdown-s0-20261127-081716-3"]


def test_runs_started_at_once_in_several_processes_claim_their_own_default_directories(tmp_path, monkeypatch):
    """Two runs that both chose a name before either made its folder shared it: the second failed
    on the first's lock. Each claims its name by making the folder; one left empty goes again."""
    from relayrl.config import from_dict
    from relayrl.dispatch import default_run_dir

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("time.strftime", lambda fmt: "20261127-081716")
    config = from_dict(TINY)
    with default_run_dir(config) as first, default_run_dir(config) as second:
        assert first != second and first.is_dir() and second.is_dir()
        (first / "config.toml").write_text("")  # a run that wrote something keeps its folder
    assert first.is_dir() and not second.exists()
    (tmp_path / "other").mkdir()
    monkeypatch.chdir(tmp_path / "other")
    with pytest.raises(UserError):
        relayrl.train({**TINY, "env": {"id": "toy_envs:NoSuchEnv"}}, progress=False)
    assert not (tmp_path / "other" / "runs").exists()  # bad input: nothing written, no folder left


def test_evaluating_a_loaded_policy_that_samples_repeats_with_the_same_seed(tmp_path):
    cfg = {"algo": "ppo", "env": {"id": "Pendulum-v1"}, "train": {"total_steps": 128, "collect_steps": 64},
           "eval": {"interval": 0, "episodes": 1}, "agent": {"batch_size": 32, "n_epochs": 1}}
    relayrl.train(cfg, tmp_path / "r", progress=False)
    policy = relayrl.load_policy(tmp_path / "r")
    runs = [relayrl.evaluate(policy, "Pendulum-v1", episodes=1, deterministic=False, seed=s) for s in (0, 0, 1)]
    assert runs[0] == runs[1] != runs[2]
    assert relayrl.evaluate(tmp_path / "r", episodes=1, deterministic=False, seed=0) == runs[0]  # as from the path


def test_train_given_an_env_instance_or_an_id_says_what_env_takes(tmp_path):
    with pytest.raises(UserError, match=r"is an env instance: relayrl makes its own copies .*env=lambda: Countdown"):
        relayrl.train(TINY, tmp_path / "a", progress=False, env=Countdown())
    with pytest.raises(UserError, match=r"is an env instance: .*; set env.id='CartPole-v1' \(and env.kwargs\)"):
        relayrl.train(TINY, tmp_path / "a", progress=False, env=gym.make("CartPole-v1"))
    with pytest.raises(UserError, match=r"env='CartPole-v1' is an env id: set it as the config's env.id"):
        relayrl.train(TINY, tmp_path / "b", progress=False, env="CartPole-v1")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_load_policy_takes_what_names_a_run(run_dir):
    """The run directory, its policy/ folder or file, or its config.toml (as `relayrl eval` takes)."""
    obs = np.zeros(2, np.float32)
    actions = {int(relayrl.load_policy(p)(obs)) for p in (run_dir, run_dir / "policy", run_dir / "policy" / "policy.pt",
                                                           run_dir / "config.toml")}
    assert len(actions) == 1


@pytest.mark.parametrize("env_id, answer, fragment", [
    ("CartPole-v1", lambda o: 5, r"answered 5 \(int64, shape \(\)\) to one observation; this env takes Discrete\(2\)"),
    ("CartPole-v1", lambda o: "x", r"answered x .* this env takes Discrete\(2\) actions"),
    ("CartPole-v1", lambda o: 1.5, r"answered 1.5 \(float64, shape \(\)\) to one observation"),
    ("Pendulum-v1", lambda o: np.array([0.5, 0.5]), r"shape \(2,\)\) to one observation; this env takes Box\(-2, 2"),
    # a [2, 2] Box travels flat inside relayrl: the message names the env's shape once, as the env has it
    (lambda: Spaces("box", "box2d"), lambda o: np.zeros(3), r"this env takes Box\(-1, 1, shape=\(2, 2\), "
                                                            r"dtype=float32\) actions$"),
])
def test_a_callable_policy_answering_what_the_env_does_not_take_is_one_line(env_id, answer, fragment):
    with pytest.raises(UserError, match=fragment):
        relayrl.evaluate(answer, env_id, episodes=1)


def test_a_callable_policy_may_answer_a_scalar_where_the_env_takes_one_value():
    assert relayrl.evaluate(lambda o: 0.0, "Pendulum-v1", episodes=1) == relayrl.evaluate(
        lambda o: np.zeros(1, np.float32), "Pendulum-v1", episodes=1)


def test_a_vector_env_given_as_env_says_how_relayrl_batches(tmp_path):
    vec = gym.vector.SyncVectorEnv([lambda: gym.make("CartPole-v1")] * 2)
    with pytest.raises(UserError, match="is a vector env: relayrl makes and batches its own copies; give a callable"):
        relayrl.train(TINY, tmp_path / "r", env=vec)
    vec.close()


def test_evaluate_gives_each_episode_as_sb3s_return_episode_rewards_does():
    returns, lengths = relayrl.evaluate(lambda o: 0, "toy_envs:Countdown", episodes=3, return_episode_rewards=True)
    assert returns == [3.0, 3.0, 3.0] and lengths == [3, 3, 3]
    assert tuple(relayrl.evaluate(lambda o: 0, "toy_envs:Countdown", episodes=3)) == (3.0, 0.0)


def test_a_callable_policy_may_answer_a_whole_float_index_and_is_told_about_sb3s_pair():
    assert relayrl.evaluate(lambda o: 1.0, "CartPole-v1", episodes=1) == relayrl.evaluate(
        lambda o: 1, "CartPole-v1", episodes=1)
    with pytest.raises(UserError, match=r"answered a pair \(action, None\), as SB3's predict\(\) does"):
        relayrl.evaluate(lambda o: (np.zeros(1, np.float32), None), "Pendulum-v1", episodes=1)


def test_loading_and_evaluating_a_policy_leave_the_callers_torch_generator_as_it_was(run_dir, tmp_path):
    """Building a saved policy's networks draws initial weights before the saved ones replace
    them: a notebook's own torch.manual_seed stream must not move."""
    for act in (lambda: relayrl.load_policy(run_dir), lambda: relayrl.evaluate(run_dir, Countdown(), episodes=1),
                lambda: relayrl.load_policy(run_dir).reseeded(3),
                lambda: relayrl.export_policy(run_dir, tmp_path / "p.pt2")):
        torch.manual_seed(1)
        expected = torch.rand(3)
        torch.manual_seed(1)
        act()
        assert torch.equal(torch.rand(3), expected)


def test_plot_run_leaves_the_callers_matplotlib_backend_and_figures_alone(run_dir, tmp_path):
    import matplotlib

    before = matplotlib.get_backend()
    matplotlib.use("pdf")  # a stand-in for a notebook's inline backend
    try:
        relayrl.plot_run(run_dir, tmp_path / "r.png")
        assert matplotlib.get_backend() == "pdf" and (tmp_path / "r.png").stat().st_size > 1000
        import matplotlib.pyplot as plt

        assert plt.get_fignums() == []
    finally:
        matplotlib.use(before)


def test_video_refuses_a_file_that_is_no_video_before_playing_and_leaves_sdl_as_it_was(run_dir, tmp_path, monkeypatch):
    import os

    played = []
    factory = lambda render_mode=None: played.append(1) or Countdown(render_mode=render_mode)  # noqa: E731
    with pytest.raises(UserError, match=r"\.txt is not a video format relayrl writes; valid: \.mp4, \.gif"):
        relayrl.record_video(run_dir, tmp_path / "x.txt", env=factory)
    assert not played
    monkeypatch.delenv("SDL_VIDEODRIVER", raising=False)
    relayrl.record_video(run_dir, tmp_path / "v.gif", env=factory)
    assert "SDL_VIDEODRIVER" not in os.environ and (tmp_path / "v.gif").stat().st_size > 100


def test_video_says_how_far_it_is_while_rendering_takes_long(run_dir, tmp_path, monkeypatch, capsys):
    """MuJoCo's software EGL renders a 1,000-step episode in minutes: a line every so often."""
    import relayrl.video

    monkeypatch.setattr(relayrl.video, "PROGRESS_S", 0.0)
    relayrl.record_video(run_dir, tmp_path / "v.gif", episodes=2, env=lambda render_mode=None: Countdown(
        render_mode=render_mode))
    said = capsys.readouterr().err
    assert "video: 2 frames so far, episode 1 of 2" in said and "episode 2 of 2" in said


def test_video_renders_mujoco_through_egl_without_a_display_and_keeps_a_users_choice(run_dir, tmp_path, monkeypatch):
    """Without a display MuJoCo's default GLFW prints warnings, then fails: EGL renders without
    one. Set for the video only; a user's own MUJOCO_GL stays."""
    import os
    import sys

    seen = []
    factory = lambda render_mode=None: seen.append(os.environ.get("MUJOCO_GL")) or Countdown(render_mode=render_mode)  # noqa: E731
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    relayrl.record_video(run_dir, tmp_path / "v.gif", env=factory)
    assert seen[-1] == ("egl" if sys.platform.startswith("linux") else None) and "MUJOCO_GL" not in os.environ
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    relayrl.record_video(run_dir, tmp_path / "v.gif", env=factory)
    assert seen[-1] == "osmesa" == os.environ["MUJOCO_GL"]
    monkeypatch.delenv("MUJOCO_GL")
    monkeypatch.setenv("DISPLAY", ":0")
    relayrl.record_video(run_dir, tmp_path / "v.gif", env=factory)
    assert seen[-1] is None  # a display: MuJoCo's own choice


@pytest.mark.parametrize("algo, env_id", [("dqn", "toy_envs:Countdown"), ("sac", "Pendulum-v1")])
def test_a_notebooks_float64_default_dtype_trains_loads_and_exports_and_stays(tmp_path, algo, env_id):
    # torch.set_default_dtype(torch.float64) in a notebook: relayrl's networks are float32 all the same
    before = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        relayrl.train({**TINY, "algo": algo, "env": {"id": env_id, "check": False}}, tmp_path / "run", progress=False)
        assert torch.get_default_dtype() == torch.float64
        policy = relayrl.load_policy(tmp_path / "run")
        assert torch.get_default_dtype() == torch.float64
        obs = np.zeros((2, *policy.observation_space.shape))  # float64, as the notebook makes them
        assert policy(obs).shape[0] == 2 and policy(torch.as_tensor(obs)).shape[0] == 2
        relayrl.export_policy(tmp_path / "run")
        assert torch.get_default_dtype() == torch.float64
    finally:
        torch.set_default_dtype(before)


@pytest.mark.parametrize("algo, env_id", [("dqn", "toy_envs:Countdown"), ("sac", "Pendulum-v1"),
                                          ("ppo", "toy_envs:Countdown")])
def test_a_loaded_policy_pickles_and_copies_for_joblib_and_multiprocessing(tmp_path, algo, env_id):
    import copy
    import pickle

    config = {**TINY, "algo": algo, "env": {"id": env_id, "check": False}}
    if algo == "ppo":
        config = {**config, "train": {**TINY["train"], "collect_steps": 64, "initial_collect_steps": 0}}
    relayrl.train(config, tmp_path / "run", progress=False)
    policy = relayrl.load_policy(tmp_path / "run")
    obs = np.zeros((3, *policy.observation_space.shape), np.float32)
    for other in (pickle.loads(pickle.dumps(policy)), copy.deepcopy(policy)):
        np.testing.assert_array_equal(other(obs), policy(obs))
        assert other.action_space == policy.action_space


def test_a_notebooks_numpy_integers_count_and_seed_as_pythons(run_dir, tmp_path):
    result = relayrl.evaluate(run_dir, episodes=np.int64(2), seed=np.int64(3), max_episode_steps=np.int32(50))
    assert result == relayrl.evaluate(run_dir, episodes=2, seed=3, max_episode_steps=50)
    with pytest.raises(UserError, match=r"^episodes=np.True_ is not valid; it must be an integer >= 1$"):
        relayrl.evaluate(run_dir, episodes=np.bool_(True))
    path = relayrl.record_video(run_dir, tmp_path / "v.gif", episodes=np.int64(1), seed=np.int64(2))
    assert path.stat().st_size > 0
    with pytest.raises(UserError, match=r"^seed=-1 is not valid; it must be an integer in \[0, "):
        relayrl.record_video(run_dir, tmp_path / "w.gif", seed=-1)
    config = relayrl.load_config("dqn")
    config.env.kwargs = {"sutton_barto_reward": np.bool_(True)}
    with pytest.raises(UserError, match=r"^env.kwargs.sutton_barto_reward=np.True_ is a NumPy bool; .*give "
                                        r"np.True_.item\(\)"):
        relayrl.train(config, tmp_path / "run", progress=False)


@pytest.mark.parametrize("device", ["meta", "mps"])
def test_a_device_relayrl_does_not_run_on_is_one_line(run_dir, device):
    with pytest.raises(UserError, match=rf"^device='{device}': relayrl runs on the CPU or a CUDA GPU; valid: cpu, "):
        relayrl.load_policy(run_dir, device=device)


def test_a_run_directory_under_home_is_expanded_as_a_shell_would(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    result = relayrl.train(TINY, "~/runs/one", progress=False)
    assert result.run_dir == tmp_path / "runs" / "one" and (tmp_path / "runs" / "one" / "config.toml").is_file()
    assert relayrl.load_policy("~/runs/one").env_steps == 200
    assert relayrl.plot_run("~/runs/one", out="~/plots/") == tmp_path / "plots" / "returns.png"


def test_a_batch_of_no_observations_is_one_line(run_dir):
    policy = relayrl.load_policy(run_dir)
    for empty in (np.zeros((0, 2), np.float32), torch.zeros(0, 2)):
        with pytest.raises(UserError, match=r"^a batch of 0 observations: give one observation, or a batch"):
            policy(empty)


@pytest.mark.parametrize("nvec, shape", [([3], (1,)), ([[3]], (1, 1)), ([3, 2], (2,))])
def test_a_ppo_policy_of_a_one_entry_multidiscrete_gives_actions_of_its_shape(tmp_path, nvec, shape):
    space = gym.spaces.MultiDiscrete(nvec)

    class Env(Countdown):
        def __init__(self) -> None:
            super().__init__()
            self.action_space = space

        def step(self, action):
            assert space.contains(action), action  # what training sends
            return super().step(0)

    config = {**TINY, "algo": "ppo", "env": {"id": "toy_envs:Countdown", "check": False},
              "train": {**TINY["train"], "collect_steps": 64, "initial_collect_steps": 0}}
    relayrl.train(config, tmp_path / "run", progress=False, env=Env)
    for deterministic in (True, False):
        policy = relayrl.load_policy(tmp_path / "run", deterministic=deterministic)
        one = policy(np.zeros(2, np.float32))
        assert one.shape == shape and space.contains(one)
        assert policy(np.zeros((4, 2), np.float32)).shape == (4, *shape)


def test_a_float64_default_also_holds_for_a_sampling_policy_and_tilde_folders(run_dir, tmp_path, monkeypatch):
    before = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:  # the other mode's networks are built later, at predict() or evaluate(deterministic=False)
        assert relayrl.evaluate(run_dir, episodes=1, deterministic=False).mean > 0
    finally:
        torch.set_default_dtype(before)
    monkeypatch.setenv("HOME", str(tmp_path))
    (tmp_path / "vids").mkdir()
    assert relayrl.record_video(run_dir, "~/vids", episodes=1, seed=None) == tmp_path / "vids" / "video.mp4"


def test_evaluating_a_model_that_samples_from_torch_repeats_with_the_seed_and_leaves_torchs_stream():
    """An SB3 model's predict(deterministic=False) draws from torch's global generator: two
    evaluations with seed=0 differed, and each moved the caller's stream on."""
    class Sampler:  # SB3's spelling: predict(obs, deterministic) -> (action, state)
        def predict(self, obs, deterministic=True):
            return int(torch.rand(()) < 0.5), None

    torch.manual_seed(123)
    before = torch.get_rng_state()
    first = relayrl.evaluate(Sampler(), "CartPole-v1", episodes=4, deterministic=False, return_episode_rewards=True)
    assert torch.equal(torch.get_rng_state(), before)
    assert relayrl.evaluate(Sampler(), "CartPole-v1", episodes=4, deterministic=False,
                            return_episode_rewards=True) == first
    # unseeded: the draws go on from the caller's stream, neither repeated nor put back
    relayrl.evaluate(Sampler(), "CartPole-v1", episodes=2, deterministic=False, seed=None)
    assert not torch.equal(torch.get_rng_state(), before)


@pytest.mark.parametrize("progress", [False, True])  # True: no terminal under pytest, so no bar either
def test_a_run_without_a_progress_bar_leaves_the_start_method_free_and_no_thread(tmp_path, progress):
    """A disabled tqdm bar still made a multiprocessing lock, which fixed the start method (a
    notebook's later set_start_method('spawn') raised), and left tqdm's monitor thread running."""
    import subprocess
    import sys

    code = ("import multiprocessing as mp, threading, relayrl, tests_tiny as t\n"
            f"relayrl.train(t.TINY, {str(tmp_path / 'r')!r}, progress={progress})\n"
            "print(mp.get_start_method(allow_none=True), sorted(th.name for th in threading.enumerate()))\n"
            "mp.set_start_method('spawn')\n")
    (tmp_path / "tests_tiny.py").write_text(f"TINY = {TINY!r}\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       cwd=tmp_path, env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert r.returncode == 0, r.stderr
    assert r.stdout.split("\n")[-2] == "None ['MainThread']"


def test_a_callbacks_row_holds_none_where_metrics_jsonl_holds_null(tmp_path):
    """Before the first training episode ends, train/average_return is NaN: a callback got the
    float, and json.dumps(row) in it wrote NaN, which is not JSON."""
    import json

    rows: list[dict] = []
    cfg = {**TINY, "env": {**TINY["env"], "kwargs": {"length": 1000}}}  # no episode ends in the run
    relayrl.train(cfg, tmp_path / "r", progress=False, callbacks=[rows.append])
    logs = [r for r in rows if r["event"] == "log"]
    assert logs and all(r["train/average_return"] is None for r in logs)
    for r in rows:
        json.dumps(r, allow_nan=False)


def test_a_run_dir_that_is_no_path_is_one_line():
    with pytest.raises(UserError, match=r"^run_dir=5 is not a folder's path: give a str or a Path"):
        relayrl.train(TINY, 5)
    with pytest.raises(UserError, match=r"^run_dir='' is not a folder's path"):  # a shell variable left unset
        relayrl.train(TINY, "")


def test_an_empty_run_dir_flag_is_one_line_and_starts_nothing(tmp_path, monkeypatch, capsys):
    from relayrl.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["train", "ppo", "--run-dir", ""]) == 2
    assert capsys.readouterr().err.strip() == ("relayrl: error: --run-dir '' is empty: give a folder (or leave "
                                               "--run-dir out for a new one under ./runs)")
    assert not (tmp_path / "runs").exists()


def test_a_run_result_gives_every_evaluation_and_the_best_for_a_sweeps_objective(tmp_path):
    """An Optuna objective had the last evaluation only (one noisy point) and parsed metrics.jsonl
    for the rest; the exceptions a study catches were not under relayrl."""
    result = relayrl.train({**TINY, "env": {"id": "CartPole-v1"}}, tmp_path / "r", progress=False)
    rows = RunDir(tmp_path / "r").read_metrics()
    assert result.evaluations == rows and result.final == rows[-1]
    assert result.best["average_return"] == max(r["average_return"] for r in rows)
    best = relayrl.load_policy(tmp_path / "r" / "policy" / "best.pt")
    assert best.env_steps == result.best["step"]


def test_the_best_row_of_equal_returns_is_the_one_best_pt_keeps(tmp_path):
    """Returns tie at a capped env's maximum: `result.best` named the latest, best.pt the first."""
    from relayrl.training.lifecycle import RunResult

    (tmp_path / "config.toml").write_text("")
    rows = [{"step": 0, "average_return": 9.0}, {"step": 10, "average_return": 500.0},
            {"step": 20, "average_return": 500.0}]
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert RunResult(tmp_path, rows[-1]).best["step"] == 10
    assert issubclass(relayrl.ConfigError, relayrl.UserError) and relayrl.NonFiniteError is not None
    with pytest.raises(relayrl.UserError):
        relayrl.train({**TINY, "agent": {"lr": -1}}, tmp_path / "bad", progress=False)


def test_a_quiet_run_says_nothing_and_leaves_other_threads_output(tmp_path, capsys):
    """README advised contextlib.redirect_stderr to silence a sweep's trials: with Optuna's
    n_jobs > 1 threads it swapped sys.stderr for every thread and left it a StringIO."""
    import sys
    import threading

    before = sys.stderr
    result = relayrl.train(TINY, tmp_path / "q", quiet=True)
    assert result.final["step"] == 200 and capsys.readouterr().err == ""
    errors: list[BaseException] = []

    def loud() -> None:
        try:
            relayrl.train(TINY, tmp_path / "loud", progress=False)
        except BaseException as e:  # noqa: BLE001  (the test's thread reports it)
            errors.append(e)

    thread = threading.Thread(target=loud)
    thread.start()
    relayrl.train(TINY, tmp_path / "q2", quiet=True)
    thread.join()
    assert not errors and sys.stderr is before
    assert "eval return" in capsys.readouterr().err  # the other thread's lines


def test_a_bad_config_fails_at_once_while_another_threads_run_trains(tmp_path):
    """Optuna's n_jobs > 1: a trial's ConfigError waited for the other thread's run to end."""
    import threading

    started, release = threading.Event(), threading.Event()

    def hold(row):  # the other run, held inside its first evaluation until the bad trial has failed
        started.set()
        release.wait(timeout=20)

    other = threading.Thread(target=relayrl.train, args=(TINY, tmp_path / "other"),
                             kwargs={"progress": False, "callbacks": [hold]})
    other.start()
    try:
        assert started.wait(timeout=60)
        with pytest.raises(relayrl.ConfigError, match="agent.lr=-1"):
            relayrl.train({**TINY, "agent": {"lr": -1}}, tmp_path / "bad", progress=False)
        assert other.is_alive()  # it failed while the other run was still held, not after it
    finally:
        release.set()
        other.join(timeout=60)


def test_a_run_that_names_its_own_folder_says_where_when_it_starts(tmp_path, monkeypatch, capsys):
    """A class of students starting runs without a run directory could not tell, mid-run, which
    folder under ./runs was theirs: the command said it at the end, Python never."""
    monkeypatch.chdir(tmp_path)
    result = relayrl.train({**TINY, "env": {"id": "CartPole-v1"}}, progress=False)
    err = capsys.readouterr().err
    assert err.splitlines()[0] == f"relayrl: the run is written to {str(result.run_dir)!r}", err
    relayrl.train({**TINY, "env": {"id": "CartPole-v1"}}, tmp_path / "given", progress=False)
    assert "the run is written to" not in capsys.readouterr().err  # a folder given is known
