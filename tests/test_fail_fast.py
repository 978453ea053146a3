"""Fail fast, lose nothing: a NaN or inf in rewards, observations or losses stops the run with one
line (exit code 3) before anything non-finite is saved; the last good checkpoint and policy load."""

import math
import os
import warnings
from pathlib import Path

import pytest
import torch

from relayrl.cli import EXIT_NON_FINITE, main
from relayrl.dispatch import train
from relayrl.errors import NonFiniteError
from relayrl.export import load_policy
from relayrl.presets import load_config
from relayrl.training.checkpoint import list_checkpoints, load_latest_checkpoint
from relayrl.training.finite import non_finite_tensor

# Checkpoints and policy every 40 env steps; the env turns non-finite at its 130th step.
TINY = ["train.total_steps=400", "train.initial_collect_steps=20", "eval.interval=40", "eval.episodes=1",
        "train.checkpoint_interval=40", "train.policy_save_interval=40", "train.log_interval=40",
        "env.id=toy_envs:NonFiniteAt", "env.max_episode_steps=20"]
ALGOS = {
    "dqn": ("dqn-cartpole", ["agent.batch_size=8", "agent.hidden=[16]"]),
    "sac": ("sac-pendulum", ["agent.batch_size=8", "agent.actor_hidden=[16]", "agent.critic_hidden=[16]",
                             "env.kwargs.continuous=true", "train.torch_threads=1"]),
    "ppo": ("ppo-cartpole", ["env.num_envs=1", "train.initial_collect_steps=0", "train.collect_steps=20",
                             "agent.batch_size=10", "agent.hidden=[16]", "agent.n_epochs=1"]),
}


def config(algo, *extra):
    preset, own = ALGOS[algo]
    return load_config(preset, TINY + own + list(extra))


def assert_kept_and_finite(run_dir, before_step):
    """The newest checkpoint and the policy are from before `before_step` and hold finite numbers."""
    ckpts = list_checkpoints(run_dir / "checkpoints")
    assert ckpts, "no checkpoint kept"
    state = load_latest_checkpoint(run_dir / "checkpoints")
    assert state["env_steps"] < before_step
    assert non_finite_tensor(state["agent"]) is None
    policy = load_policy(run_dir)
    assert policy.env_steps < before_step
    assert non_finite_tensor(dict(policy.network.state_dict()) if hasattr(policy, "network") else {}) is None


@pytest.mark.parametrize("algo", ALGOS)
@pytest.mark.parametrize("what, value, named", [("reward", "nan", "reward was NaN"),
                                                ("obs", "inf", "observation was inf")])
def test_a_non_finite_reward_or_observation_stops_the_run_and_keeps_what_was_good(
        algo, what, value, named, tmp_path, capfd):
    c = config(algo, "env.kwargs.at=130", f"env.kwargs.what={what!r}", f"env.kwargs.value={value}")  # TOML's nan, inf
    with pytest.raises(NonFiniteError) as e:
        train(c, tmp_path / "run", progress=False)
    message = str(e.value)
    assert message.startswith(f"{named} at env step 130 (env copy 0): check the env's")
    assert "the last good checkpoint (env step 120)" in message and "kept in" in message
    assert "\n" not in message
    assert_kept_and_finite(tmp_path / "run", 130)


def test_an_observation_beyond_float32_is_the_one_line_without_numpys_warning(tmp_path, capfd):
    """A float64 observation of 1e39 becomes inf in relayrl's float32 write: the run's line says
    so; NumPy's "overflow encountered in cast" warning, with its source line, would only precede it."""
    c = config("dqn", "env.kwargs.at=130", "env.kwargs.what='obs64'", "env.kwargs.value=1e39", "env.check=false")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        before = list(warnings.filters)
        with pytest.raises(NonFiniteError, match="^observation was inf at env step 130"):
            train(c, tmp_path / "run", progress=False)
        assert warnings.filters == before  # the run's filter is gone again
    assert not [w for w in caught if "encountered" in str(w.message)], [str(w.message) for w in caught]


def test_the_cli_prints_one_line_and_exits_3(tmp_path, capfd):
    preset, own = ALGOS["dqn"]
    args = ["train", preset, "--run-dir", str(tmp_path / "run"), "--no-progress"]
    for o in TINY + own + ["env.kwargs.at=130"]:
        args += ["--set", o]
    capfd.readouterr()
    assert main(args) == EXIT_NON_FINITE == 3
    err = capfd.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("relayrl:")]
    assert lines == [lines[-1]] and lines[-1].startswith("relayrl: run stopped: reward was NaN at env step 130")
    assert "Traceback" not in err


@pytest.mark.parametrize("algo", ALGOS)
def test_a_non_finite_loss_stops_before_the_weights_are_saved(algo, tmp_path, monkeypatch):
    """A loss that turns NaN (as a diverging learning rate makes it) is named, and no NaN weights
    reach the policy file or a checkpoint."""
    c = config(algo, "env.kwargs.at=100000")
    from relayrl.training.learner import Learner

    real_learn = Learner.learn

    def poisoned(self, iterations):
        real_learn(self, iterations)
        if self.agent.train_step >= 30:  # as a diverged update leaves it: NaN loss and weights
            for p in self.agent.policy_network().parameters():
                p.data.fill_(math.nan)
            first = next(iter(self.last_metrics))
            self.last_metrics = {**self.last_metrics, first: torch.tensor(math.nan)}

    monkeypatch.setattr(Learner, "learn", poisoned)
    with pytest.raises(NonFiniteError, match=r"was NaN by env step [\d,]+ \(train step [\d,]+\): check the learning"):
        train(c, tmp_path / "run", progress=False)
    assert_kept_and_finite(tmp_path / "run", 10**9)


def test_a_diverged_run_with_a_users_encoder_names_it_among_what_to_check(tmp_path, monkeypatch):
    c = config("dqn", "env.kwargs.at=100000", "agent.encoder=tests.space_envs:FlatEncoder")
    from relayrl.training.learner import Learner

    real_learn = Learner.learn

    def poisoned(self, iterations):
        real_learn(self, iterations)
        if self.agent.train_step >= 30:
            self.last_metrics = {**self.last_metrics, "loss": torch.tensor(math.nan)}

    monkeypatch.setattr(Learner, "learn", poisoned)
    with pytest.raises(NonFiniteError, match=r"the reward scale and the env's observations, and "
                                             r"agent.encoder='tests.space_envs:FlatEncoder' \(its outputs on these"):
        train(c, tmp_path / "run", progress=False)


def test_weights_that_went_non_finite_without_a_loss_saying_so_are_never_saved(tmp_path, monkeypatch):
    c = config("dqn", "env.kwargs.at=100000")
    from relayrl.training.learner import Learner

    real_learn = Learner.learn

    def poisoned(self, iterations):
        real_learn(self, iterations)
        if self.agent.train_step >= 30:
            next(self.agent.policy_network().parameters()).data.fill_(math.inf)
            self.last_metrics = {k: torch.zeros(()) for k in self.last_metrics}  # the losses look fine

    monkeypatch.setattr(Learner, "learn", poisoned)
    with pytest.raises(NonFiniteError, match=r"the agent's .* held a NaN or inf by env step"):
        train(c, tmp_path / "run", progress=False)
    assert_kept_and_finite(tmp_path / "run", 10**9)


def test_with_prioritized_replay_the_reward_is_named_not_the_td_error_it_made(tmp_path):
    c = config("dqn", "env.kwargs.at=130", "replay.sampler=prioritized")
    with pytest.raises(NonFiniteError, match=r"^reward was NaN at env step 130 \(env copy 0\)"):
        train(c, tmp_path / "run", progress=False)
    assert_kept_and_finite(tmp_path / "run", 130)


def test_the_env_copy_and_step_are_named_in_a_batch_of_envs(tmp_path):
    """Both copies get NaN rewards from their 70th step: copy 0's is env step 2 * 69 + 1 = 139,
    counting the steps of both copies."""
    c = config("dqn", "env.num_envs=2", "env.kwargs.at=70", "eval.interval=400")  # evaluations stay short of 70
    with pytest.raises(NonFiniteError, match=r"^reward was NaN at env step 139 \(env copy 0\)"):
        train(c, tmp_path / "run", progress=False)


# ---- plot / video / export: errors are one line, exit 2, and nothing already written is lost ----

@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("runs") / "run"
    c = load_config("dqn-cartpole", ["train.total_steps=60", "train.initial_collect_steps=20", "eval.interval=30",
                                     "eval.episodes=1", "agent.batch_size=8", "env.id=toy_envs:Countdown",
                                     "env.check=false"])
    train(c, run, progress=False)
    return run


def one_line(capfd, args, code=2):
    capfd.readouterr()
    assert main(args) == code
    err = capfd.readouterr().err
    assert err.count("\n") == 1 and err.startswith("relayrl: error: ") and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("command, name", [("plot", "x.png"), ("video", "x.mp4"), ("export", "x.pt2")])
def test_out_under_a_file_is_one_line(command, name, small_run, tmp_path, capfd):
    (tmp_path / "afile").write_text("")
    err = one_line(capfd, [command, str(small_run), "--out", str(tmp_path / "afile" / name)])
    assert "cannot create the folder of" in err and "afile" in err


@pytest.mark.parametrize("command, default", [("plot", "returns.png"), ("video", "video.mp4"),
                                              ("export", "policy.pt2")])
def test_out_as_a_folder_takes_the_default_name_and_a_bare_name_is_one_line(command, default, small_run, tmp_path,
                                                                           capfd):
    err = one_line(capfd, [command, str(small_run), "--out", str(tmp_path / "noext")])
    assert f"has no file extension; give a file name such as noext{Path(default).suffix}" in err
    assert not (tmp_path / "noext").exists()
    assert main([command, str(small_run), "--out", str(tmp_path / "made") + "/"]) == 0
    assert (tmp_path / "made" / default).is_file()
    assert main([command, str(small_run), "--out", str(tmp_path / "made")]) == 0  # the folder exists now


@pytest.mark.parametrize("command, default", [("plot", "returns.png"), ("video", "video.mp4"),
                                              ("export", "policy/policy.pt2")])
def test_a_read_only_run_directory_is_one_line(command, default, small_run, capfd, monkeypatch):
    """As root chmod does not stop writes: the folder is reported unwritable as os.access says."""
    import relayrl.paths

    target = (small_run / default).parent
    real_access = relayrl.paths.os.access
    monkeypatch.setattr(relayrl.paths.os, "access",
                        lambda p, mode: False if Path(p) == target else real_access(p, mode))
    err = one_line(capfd, [command, str(small_run)])
    assert f"cannot write {str(small_run / default)!r}: its folder is not writable; give --out PATH" in err


def test_a_failed_write_is_one_line_and_keeps_the_file_there(small_run, tmp_path, capfd, monkeypatch):
    out = tmp_path / "returns.png"
    assert main(["plot", str(small_run), "--out", str(out)]) == 0
    before = out.read_bytes()
    import matplotlib.figure

    def full_disk(self, *args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", full_disk)
    err = one_line(capfd, ["plot", str(small_run), "--out", str(out)])
    assert f"cannot write {str(out)!r}: No space left on device" in err
    assert out.read_bytes() == before and not list(tmp_path.glob("*.tmp*"))


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc")
@pytest.mark.parametrize("command", ["video", "plot", "export"])
def test_out_in_a_folder_access_calls_writable_but_that_takes_no_file_is_one_line_before_any_work(
        command, small_run, capfd):
    """os.access says root may write in /proc; no file can be made there: said before the
    episodes are rendered, not after."""
    err = one_line(capfd, [command, str(small_run), "--out", "/proc/relayrl-out.png" if command == "plot"
                           else "/proc/relayrl-out.mp4" if command == "video" else "/proc/relayrl-out.pt2"])
    assert "cannot write --out '/proc/relayrl-out." in err


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_chmod_read_only_run_directory_is_one_line(small_run, capfd):
    os.chmod(small_run, 0o555)
    try:
        err = one_line(capfd, ["plot", str(small_run)])
        assert "is not writable" in err
    finally:
        os.chmod(small_run, 0o755)


def test_video_of_an_env_that_does_not_render_is_one_line(small_run, tmp_path, capfd):
    import shutil

    run = tmp_path / "norender"
    shutil.copytree(small_run, run)
    text = (run / "config.toml").read_text().replace("toy_envs:Countdown", "toy_envs:NoRender")
    (run / "config.toml").write_text(text)
    err = one_line(capfd, ["video", str(run)])
    assert "env 'toy_envs:NoRender' renders no frames: render() returned None; relayrl video needs render()" in err
    assert not (run / "video.mp4").exists()


def test_video_of_an_env_whose_render_raises_is_one_line(small_run, tmp_path, capfd):
    import shutil

    run = tmp_path / "cartpole"
    shutil.copytree(small_run, run)
    (run / "config.toml").write_text((run / "config.toml").read_text().replace("toy_envs:Countdown",
                                                                               "toy_envs:RenderRaises"))
    err = one_line(capfd, ["video", str(run)])
    assert "cannot render: render() raised RuntimeError: no display" in err
    for env, said in [("NoRenderMethod", "render() raised NotImplementedError (the env has no render());"),
                      ("NoRenderMode", "relayrl video makes the env with render_mode='rgb_array': give the class a "
                                       "render_mode argument")]:
        (run / "config.toml").write_text((run / "config.toml").read_text().replace("toy_envs:RenderRaises",
                                                                                   f"toy_envs:{env}"))
        assert said in one_line(capfd, ["video", str(run)])
        (run / "config.toml").write_text((run / "config.toml").read_text().replace(f"toy_envs:{env}",
                                                                                   "toy_envs:RenderRaises"))


def test_a_non_finite_reward_in_an_evaluation_stops_the_run_in_one_line(tmp_path):
    # The first evaluation, of the untrained policy, meets the NaN before any training step.
    c = config("dqn", "env.kwargs.at=5")
    with pytest.raises(NonFiniteError, match=r"^reward was NaN in an evaluation episode \(env copy 0\): check"):
        train(c, tmp_path / "run", progress=False)


def test_a_non_finite_observation_in_an_evaluation_stops_the_run_in_one_line(tmp_path):
    """The policy would act on it and the evaluation report a return that means nothing."""
    c = config("dqn", "env.kwargs.at=5", "env.kwargs.what='obs'")
    with pytest.raises(NonFiniteError, match=r"^observation was NaN in an evaluation episode \(env copy 0\): check "
                                             r"the env's observations"):
        train(c, tmp_path / "run", progress=False)


def test_an_evaluation_ignores_what_a_copy_past_its_quota_returns():
    import gymnasium as gym
    import numpy as np

    from relayrl.envs.gym import GymBatchEnv
    from relayrl.training.evaluate import evaluate

    class NaNAfterOneEpisode(gym.Env):
        observation_space = gym.spaces.Box(-1, 1, (1,), np.float32)
        action_space = gym.spaces.Discrete(2)

        def __init__(self, length):
            self.length, self.episodes = length, 0

        def reset(self, seed=None, options=None):
            super().reset(seed=seed)
            self.t, self.episodes = 0, self.episodes + 1
            return np.zeros(1, np.float32), {}

        def step(self, action):
            self.t += 1
            reward = float("nan") if self.episodes > 1 else 1.0
            return np.zeros(1, np.float32), reward, self.t >= self.length, False, {}

    # Copy 0's one counted episode ends at step 2; it then steps on, uncounted, while copy 1 finishes.
    env = GymBatchEnv([lambda: NaNAfterOneEpisode(2), lambda: NaNAfterOneEpisode(10)])
    result = evaluate(env, lambda obs: torch.zeros(len(obs), dtype=torch.int64), episodes=2, seed=0)
    assert result["average_return"] == 6.0 and result["episodes"] == 2


def test_a_non_finite_action_is_the_agents_finding_not_the_envs():
    """A diverged agent's NaN action makes the env return NaN observations at the same step: the
    action is named; a NaN observation the action was chosen on is the env's, as before."""
    from relayrl.training.finite import FiniteWatch
    from relayrl.types import Transition

    def step(obs, action, next_obs):
        t = torch.tensor
        return Transition(t([obs]), t([[action]]), t([0.0]), t([next_obs]), t([False]), t([False]))

    watch = FiniteWatch(1)
    watch(step(0.0, 0.5, 0.0))
    watch(step(0.0, math.nan, math.nan))
    assert watch.check() == ("the agent's action was NaN at env step 2 (env copy 0): the agent diverged: check the "
                             "learning rate (too high diverges), the reward scale and the env's observations")
    assert watch.found_action
    watch(step(math.nan, math.nan, math.nan))
    assert watch.check().startswith("observation was NaN at env step 3 (env copy 0): check the env's observations")
    assert not watch.found_action


@pytest.mark.parametrize("where", ["metrics", "tensorboard"])
def test_a_full_disk_under_metrics_or_tensorboard_is_one_line_and_keeps_the_checkpoints(where, tmp_path, capfd,
                                                                                      monkeypatch):
    """The atomic files (checkpoints, policy, config) say a full disk themselves; metrics.jsonl's
    appends and TensorBoard's writer (whose thread raises first, then the run's next scalar) too."""
    import errno

    from relayrl.training.run_dir import MetricsLog

    run = tmp_path / "run"
    full = OSError(errno.ENOSPC, "No space left on device", str(run / "metrics.jsonl"))
    if where == "metrics":
        real_write = MetricsLog.write

        def write(self, row):
            if row["step"] >= 80:
                raise full
            real_write(self, row)

        monkeypatch.setattr(MetricsLog, "write", write)
    else:
        from torch.utils.tensorboard import SummaryWriter

        real_scalar = SummaryWriter.add_scalar

        def add_scalar(self, tag, value, step=None, *args, **kwargs):
            if step is not None and step >= 80:
                raise full
            real_scalar(self, tag, value, step, *args, **kwargs)

        monkeypatch.setattr(SummaryWriter, "add_scalar", add_scalar)
    args = ["train", "dqn-cartpole", "--run-dir", str(run), "--no-progress"]
    capfd.readouterr()
    assert main(args + [a for o in TINY + ALGOS["dqn"][1] + ["env.kwargs.at=100000"] for a in ("--set", o)]) == 2
    err = capfd.readouterr().err
    assert "Traceback" not in err and "Exception in thread" not in err, err
    assert (f"relayrl: error: cannot write {str(run / 'metrics.jsonl')!r}: No space left on device: free some "
            "space; the run stopped at env step 80: the last good checkpoint (env step 40)") in err
    assert [int(p.stem.split("-")[1]) for p in list_checkpoints(run / "checkpoints")] == [40]


@pytest.mark.parametrize("cause", ["full", "deleted"])
def test_tensorboards_writer_thread_stopped_by_a_full_disk_prints_nothing_of_its_own(capsys, tmp_path, cause):
    """Nor where its folder was deleted (the run directory removed mid-run): the run's next
    write says either in one line."""
    import errno
    import threading

    from relayrl.training.process import writer_thread_quiet

    gone = tmp_path / "run" / "tb" / "events.out.tfevents.1"

    class _AsyncWriterThread(threading.Thread):  # tensorboard's name for its writer thread
        def run(self):
            if cause == "full":
                raise OSError(errno.ENOSPC, "No space left on device")
            open(gone, "ab")  # as its gfile appends; a missing file of an existing folder is not quiet

    seen = []
    before = threading.excepthook
    threading.excepthook = seen.append
    try:
        with writer_thread_quiet():
            for thread in (_AsyncWriterThread(), threading.Thread(target=lambda: 1 / 0)):
                thread.start()
                thread.join()
        assert [type(args.exc_value) for args in seen] == [ZeroDivisionError]  # others' errors still go through
    finally:
        threading.excepthook = before
