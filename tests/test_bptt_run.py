"""algo = "bptt" as a run (the bptt-pendulum preset) and stateless envs in the train loop."""
import json
import os
import re
import signal
import warnings

import numpy as np
import pytest
import torch

import relayrl
from relayrl.errors import ConfigError, UserError
from relayrl.training.run_dir import RunDir

SHORT = ["train.total_steps=96000", "eval.interval=32000"]  # 30 iterations, a row every 10


def test_bptt_run_writes_rows_a_loadable_policy_and_improves(tmp_path):
    result = relayrl.train(relayrl.load_config("bptt-pendulum", SHORT), tmp_path / "b", progress=False)
    (process,) = json.loads((tmp_path / "b" / "history.json").read_text())  # its runs' one process, recorded
    assert process["env_step"] == 0 and process["versions"]["torch"] == torch.__version__
    rows = RunDir(tmp_path / "b").read_metrics()
    # every run's evaluations: at step 0, every eval.interval env steps and at the end, each of
    # eval.episodes whole episodes of the env (Pendulum's 200 steps), as relayrl eval runs them
    assert [r["step"] for r in rows] == [0, 32000, 64000, 96000] and rows[-1]["train_step"] == 30
    assert all(r["average_episode_length"] == 200.0 and r["episodes"] == 10 for r in rows)
    assert rows[-1]["bptt/mean_reward"] > rows[1]["bptt/mean_reward"]  # the loss goes down
    assert "bptt/mean_reward" not in rows[0]  # no iteration before step 0
    assert result.final["bptt/final50_mean_reward"] == pytest.approx(
        sum(r["bptt/mean_reward"] for r in rows[1:]) / 3, rel=1e-6)  # 30 iterations < 50: all of them
    assert all(-1700 < r["average_return"] < 0 for r in rows)  # 200 steps of rewards in [-16.3, 0]
    actions = relayrl.load_policy(tmp_path / "b")(torch.randn(7, 3) * 5)  # export: tests/test_conformance.py
    assert actions.shape == (7, 1) and actions.abs().max() <= 2.0
    assert relayrl.plot_run(tmp_path / "b").stat().st_size > 10_000  # two panels, like the tutorial's
    assert not (tmp_path / "b" / "checkpoints").exists()  # it writes none: no empty folder looks like one lost
    with warnings.catch_warnings():
        # the saved float64 bounds of its action space: no precision warning
        warnings.filterwarnings("error", message=".*precision lowered")
        policy = relayrl.load_policy(tmp_path / "b")
        assert policy.action_space.low.dtype == np.float32
        assert relayrl.evaluate(policy, episodes=1).mean < 0  # its check that the env fits the policy


def test_bptt_refuses_other_envs(tmp_path):  # resume and CLI errors: tests/test_conformance.py
    with pytest.raises(ConfigError, match="trains through relayrl/StatelessPendulum-v0 only"):
        relayrl.train(relayrl.load_config("bptt-pendulum", SHORT + ["env.id=Pendulum-v1"]), tmp_path / "x",
                      progress=False)
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("setting, why", [("env.num_envs=4", "set agent.batch_size"),
                                          ("env.kwargs={'g': 5.0}", "trains and evaluates through"),
                                          ("env.max_episode_steps=50", "trains and evaluates through"),
                                          ("distributed.address='auto'", "Ray actors"),
                                          ("train.checkpoint_interval=100", "checkpoints")])
def test_bptt_refuses_settings_it_would_ignore(tmp_path, setting, why):
    toml = setting.replace("{'g': 5.0}", "{g = 5.0}")
    with pytest.raises(ConfigError, match=f"{re.escape(setting)} does not apply to algo='bptt'.*{why}"):
        relayrl.train(relayrl.load_config("bptt-pendulum", SHORT + [toml]), tmp_path / "x", progress=False)
    assert not (tmp_path / "x").exists()


def test_bptt_runs_in_one_process_only(tmp_path):
    with pytest.raises(ConfigError, match=r"distributed.num_actors=2 does not apply to algo='bptt': it runs in one "
                                          r"process only; leave it at 0 \(distributed.num_actors works with dqn, "
                                          r"sac, ppo\)$"):
        relayrl.train(relayrl.load_config("bptt-pendulum", SHORT + ["distributed.num_actors=2"]), tmp_path / "x",
                      progress=False)
    assert not (tmp_path / "x").exists()


def test_sac_trains_on_a_batch_of_stateless_pendulums(tmp_path):
    over = ["env.id=relayrl/StatelessPendulum-v0", "env.num_envs=16", "train.total_steps=800",
            "train.initial_collect_steps=320", "train.collect_steps=16", "train.gradient_steps=2",
            "eval.interval=400", "eval.episodes=3", "agent.actor_hidden=[32]", "agent.critic_hidden=[32]",
            "agent.batch_size=64", "train.torch_threads=1"]
    result = relayrl.train(relayrl.load_config("sac-pendulum", over), tmp_path / "s", progress=False)
    assert result.final["step"] == 800 and result.final["losses/critic_loss"] > 0
    assert result.final["average_episode_length"] == 200.0  # the stateless pendulum's time limit


@pytest.mark.parametrize("interval, steps", [(100, [0, 120, 200, 320, 400]), (1000, [0, 400]), (0, [400])])
def test_bptt_evaluates_where_every_run_does(tmp_path, interval, steps):
    """At step 0, at the first iteration at or past each multiple of eval.interval (iterations of
    40 env steps here), and at the end; the same rows from the same seed."""
    over = ["train.total_steps=400", "agent.batch_size=4", "agent.rollout_steps=10", "eval.episodes=2",
            f"eval.interval={interval}"]
    runs = [RunDir(relayrl.train(relayrl.load_config("bptt-pendulum", over), tmp_path / f"b{i}",
                                 progress=False).run_dir).read_metrics() for i in range(2)]
    assert [r["step"] for r in runs[0]] == steps
    drop = ("wall_time_s", "eval_s")
    assert [{k: v for k, v in r.items() if k not in drop} for r in runs[0]] == \
           [{k: v for k, v in r.items() if k not in drop} for r in runs[1]]


def test_bptt_with_eval_interval_zero_writes_one_row_at_the_end(tmp_path):
    cfg = relayrl.load_config("bptt-pendulum", ["train.total_steps=192000", "eval.interval=0", "eval.episodes=3"])
    (row,) = RunDir(relayrl.train(cfg, tmp_path / "b", progress=False).run_dir).read_metrics()  # 60 iterations
    assert row["step"] == 192000 and row["episodes"] == 3
    assert row["bptt/final50_mean_reward"] != row["bptt/mean_reward"]  # the last 50 iterations against all 60


def test_relayrl_config_refuses_what_a_bptt_run_would(capsys):
    from relayrl.cli import main

    assert main(["config", "bptt-pendulum", "--set", "env.num_envs=2"]) == 2
    assert "env.num_envs=2 does not apply to algo='bptt'" in capsys.readouterr().err


def test_bptt_ctrl_c_keeps_the_policy_trained_so_far(tmp_path, monkeypatch, capsys):
    """A bptt run has no checkpoints: the first Ctrl-C ends the iteration and saves its policy
    there (the CLI then says the policy stays), instead of losing the whole run's training."""
    from relayrl.agents.bptt import trainer

    real = trainer.train_bptt

    def ctrl_c_in_iteration_12(config, callback, **kwargs):
        def on_iteration(entry):
            callback(entry)
            if entry.iteration == 11:
                os.kill(os.getpid(), signal.SIGINT)
        return real(config, on_iteration, **kwargs)

    monkeypatch.setattr(trainer, "train_bptt", ctrl_c_in_iteration_12)
    root = str(tmp_path / "b")
    with pytest.raises(KeyboardInterrupt, match=f"the run stopped at env step 38,400; its policy and metrics are in "
                                                f"'{root}'"):
        relayrl.train(relayrl.load_config("bptt-pendulum", SHORT), root, progress=False)
    assert "stopping at the end of this iteration to save the policy" in capsys.readouterr().err
    assert relayrl.load_policy(root).env_steps == 12 * 32 * 100
    assert [r["step"] for r in RunDir(root).read_metrics()] == [0, 32000]  # no final evaluation, as any run's
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handler is put back


def test_bptt_says_its_evaluations_without_a_progress_bar_too(tmp_path, capsys):
    relayrl.train(relayrl.load_config("bptt-pendulum", SHORT + ["eval.episodes=2"]), tmp_path / "b", progress=False)
    err = capsys.readouterr().err
    assert "evaluations: mean return and length of 2 episodes" in err
    assert [line.split("|")[0].split()[1] for line in err.splitlines() if line.startswith("step")] == \
           ["0", "32,000", "64,000", "96,000"]


def test_a_full_disk_under_a_bptt_run_is_one_error_line(tmp_path, monkeypatch):
    import errno

    from relayrl.training.run_dir import MetricsLog

    def write(self, row):
        raise OSError(errno.ENOSPC, "No space left on device", "metrics.jsonl")

    monkeypatch.setattr(MetricsLog, "write", write)
    with pytest.raises(UserError, match=r"^cannot write 'metrics.jsonl': No space left on device: free some space; "
                                        r"algo='bptt' runs have no checkpoints: a new run starts over$"):
        relayrl.train(relayrl.load_config("bptt-pendulum", SHORT), tmp_path / "b", progress=False)


def test_bptt_refusals_show_values_as_toml_writes_them():
    with pytest.raises(ConfigError, match=r"^env.check=false does not apply to algo='bptt': .*; leave it at true$"):
        relayrl.load_config("bptt-pendulum", ["env.check=false"])


def test_bptt_from_python_without_its_preset_or_with_an_env_factory_says_what_it_takes(tmp_path):
    with pytest.raises(ConfigError, match=r"env.id='CartPole-v1' is not valid \(set env.id = "
                                          r"'relayrl/StatelessPendulum-v0'\)$"):
        relayrl.train({"algo": "bptt"}, tmp_path / "x", progress=False)
    with pytest.raises(UserError, match=r"^env=<factory> works with the Actor \+ Learner runs \(dqn, "
                                        r"sac, ppo\); algo='bptt' trains through its own env"):
        relayrl.train("bptt-pendulum", tmp_path / "y", env=lambda: None, progress=False)
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()
