"""Whole-run checkpoints: a run resumed from a checkpoint is the uninterrupted run, bit for bit."""

import contextlib
import json
import multiprocessing
import os
import random
import shutil
import signal
import subprocess
import sys
import threading
import time
import warnings

import numpy as np
import pytest
import torch
from procs import children_running, running

import relayrl
from relayrl.training.checkpoint import list_checkpoints, load_latest_checkpoint
from relayrl.training.run_dir import RunDir, checkpoint_step

DQN = ["env.id=CartPole-v1", "train.total_steps=1500", "train.initial_collect_steps=200",
       "eval.interval=500", "eval.episodes=3", "train.checkpoint_interval=500",
       "train.collect_steps=100", "train.gradient_steps=20", "agent.hidden=[32,32]"]
SAC = ["env.id=Pendulum-v1", "train.total_steps=900", "train.initial_collect_steps=200",
       "eval.interval=300", "eval.episodes=2", "train.checkpoint_interval=300", "train.collect_steps=30",
       "train.gradient_steps=3", "agent.actor_hidden=[16]", "agent.critic_hidden=[16]", "agent.batch_size=32",
       "train.torch_threads=1"]
TIMES = ("wall_time_s", "eval_s")


def comparable(run_dir):
    return [{k: v for k, v in r.items() if k not in TIMES} for r in RunDir(run_dir).read_metrics()]


def cut_back(src, dst):
    """A copy of finished run `src` as a crash just before its final checkpoint would have
    left it: resuming starts from the checkpoint before (two are kept)."""
    shutil.copytree(src, dst)
    *older, final = list_checkpoints(dst / "checkpoints")
    assert older, "the run wrote only one checkpoint"
    final.unlink()


def assert_same_state(a, b):
    sa, sb = (load_latest_checkpoint(d / "checkpoints") for d in (a, b))
    assert sa["env_steps"] == sb["env_steps"]
    for key, ta in sa["agent"].items():
        if isinstance(ta, dict):
            for name, t in ta.items():
                if torch.is_tensor(t):
                    assert torch.equal(t, sb["agent"][key][name]), f"agent.{key}.{name} differs"


# The plain dqn and sac runs: tests/test_conformance.py, for every algorithm in the registry.
@pytest.mark.parametrize("preset,over", [
    ("dqn-cartpole-fast", DQN + ["env.num_envs=3", "env.vectorization=async", "replay.n_step=3"]),
    ("sac-pendulum", SAC + ["env.num_envs=7", "train.collect_steps=7", "train.gradient_steps=1",
                            "train.pull_interval=28",  # the checkpoint at 602 falls between pulls
                            "agent.lr_end=0.0"]),  # the learning rates follow their schedule across the resume
    ("sac-pendulum", SAC + ["env.id=relayrl/StatelessPendulum-v0", "env.num_envs=6", "train.collect_steps=6"]),
], ids=["dqn-3async-nstep", "sac-7envs-stale-actor", "sac-6stateless"])
def test_resumed_run_is_bit_identical_to_the_uninterrupted_one(tmp_path, preset, over):
    cfg = relayrl.load_config(preset, over, seed=3)
    relayrl.train(cfg, tmp_path / "full", progress=False)
    cut_back(tmp_path / "full", tmp_path / "resumed")
    assert load_latest_checkpoint(tmp_path / "resumed" / "checkpoints")["actor"]["env"] is not None
    relayrl.train(cfg, tmp_path / "resumed", resume=True, progress=False)
    assert comparable(tmp_path / "resumed") == comparable(tmp_path / "full")
    assert_same_state(tmp_path / "full", tmp_path / "resumed")


@pytest.mark.parametrize("workers", ["1", "2"])
def test_async_run_gives_the_in_process_runs_numbers(tmp_path, workers):
    """The copies' slices (main process and workers) must not change a single number."""
    over = DQN + ["env.num_envs=3", "env.max_episode_steps=40", f"env.num_workers={workers}"]
    for v in ("sync", "async"):
        cfg = relayrl.load_config("dqn-cartpole-fast", over + [f"env.vectorization={v}"], seed=3)
        relayrl.train(cfg, tmp_path / v, progress=False)
    assert comparable(tmp_path / "async") == comparable(tmp_path / "sync")
    assert_same_state(tmp_path / "sync", tmp_path / "async")


@pytest.mark.parametrize("env, envs", [("Unpicklable", ["env.num_envs=1"]),
                                       ("Unpicklable", ["env.num_envs=3", "env.vectorization=async"]),
                                       ("ConstructorPickled", ["env.num_envs=1"])],
                         ids=["1", "3async", "ezpickle"])
def test_env_that_cannot_be_pickled_resumes_with_new_episodes(tmp_path, capsys, env, envs):
    """Envs whose pickle keeps only their constructor's arguments (Gymnasium's EzPickle: MuJoCo,
    Box2D) count as unpicklable: a copy would be a new simulator, not the one mid-episode. Their
    resumed runs start new episodes, seeded, so two resumes from one checkpoint agree."""
    over = DQN + [f"env.id=toy_envs:{env}", "env.max_episode_steps=50"] + envs
    cfg = relayrl.load_config("dqn-cartpole-fast", over, seed=3)
    relayrl.train(cfg, tmp_path / "full", progress=False)
    said = capsys.readouterr().err  # while it trains, once: not only when it is resumed
    assert said.count("checkpoints hold no env state (") == 1
    why = {"Unpicklable": "the env cannot be pickled mid-episode", "ConstructorPickled": "ConstructorPickled pickles "
           "only its constructor's arguments (Gymnasium's EzPickle"}[env]  # the copies' own reason, in this process
    assert f"checkpoints hold no env state ({why}" in said
    cut_back(tmp_path / "full", tmp_path / "resumed")
    assert load_latest_checkpoint(tmp_path / "resumed" / "checkpoints")["actor"]["env"] is None
    shutil.copytree(tmp_path / "resumed", tmp_path / "again")
    result = relayrl.train(cfg, tmp_path / "resumed", resume=True, progress=False)
    assert result.final["step"] == 1500
    said = capsys.readouterr().err
    assert "the resumed run starts new episodes" in said
    assert said.count("checkpoints hold no env state") == 1  # once a process: by the resume, not at its checkpoints
    relayrl.train(cfg, tmp_path / "again", resume=True, progress=False)
    assert comparable(tmp_path / "again") == comparable(tmp_path / "resumed")


def test_gymnasiums_box2d_envs_are_not_snapshotted_mid_episode():
    pytest.importorskip("Box2D")
    import gymnasium as gym

    from relayrl.envs.gym import env_snapshot

    env = gym.make("LunarLander-v3")
    env.reset(seed=0)
    assert env_snapshot(env) is None  # unpickled, it would be an un-reset lander
    assert env_snapshot(gym.make("CartPole-v1")) is not None


def test_a_run_a_callback_stopped_at_its_first_evaluation_resumes_to_the_uninterrupted_run(tmp_path):
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=600"] + DQN[2:])
    relayrl.train(cfg, tmp_path / "full", progress=False)
    stopped = relayrl.train(cfg, tmp_path / "cut", progress=False, callbacks=[lambda row: False])
    assert stopped.stopped_early
    relayrl.train(cfg, tmp_path / "cut", resume=True, progress=False)
    assert comparable(tmp_path / "cut") == comparable(tmp_path / "full")  # one step-0 evaluation, not two


def test_an_evaluation_uses_up_its_seed_index_only_where_it_covers_a_new_grid_boundary():
    from relayrl.training.triggers import covers_boundary

    assert covers_boundary(0, 500, 0)  # the untrained policy's
    assert covers_boundary(503, 500, 1)  # a batched step just past the first boundary
    assert not covers_boundary(300, 500, 1)  # where a callback stopped the run, between 0 and 500
    assert covers_boundary(1500, 500, 3)  # on Ray: the last boundary, which the final evaluation covers
    assert not covers_boundary(1700, 500, 4)  # a last step between boundaries
    assert covers_boundary(2048, 500, 1)  # one rollout over four boundaries: one evaluation, one index


def test_a_run_a_callback_stopped_between_evaluations_resumes_to_the_uninterrupted_run(tmp_path):
    """The stop's own evaluation (step 300, off the 500-step grid) is one row more; every later
    evaluation keeps the uninterrupted run's seed."""
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN + ["train.log_interval=100"])
    relayrl.train(cfg, tmp_path / "full", progress=False)
    stopped = relayrl.train(cfg, tmp_path / "cut", progress=False, callbacks=[lambda row: row["step"] < 300])
    assert stopped.stopped_early and stopped.final["step"] == 300
    relayrl.train(cfg, tmp_path / "cut", resume=True, progress=False)
    cut = comparable(tmp_path / "cut")
    extra = [r for r in cut if r["step"] == 300 and "average_return" in r]
    assert len(extra) == 1
    assert [r for r in cut if r is not extra[0]] == comparable(tmp_path / "full")


def test_ctrl_c_with_checkpoints_off_says_it_saves_the_policy_only(tmp_path, capsys):
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN + ["train.log_interval=100", "train.checkpoint_interval=0"])

    def ctrl_c_at_700(row):
        if row["step"] == 700:
            os.kill(os.getpid(), signal.SIGINT)

    with pytest.raises(KeyboardInterrupt):
        relayrl.train(cfg, tmp_path / "cut", progress=False, callbacks=[ctrl_c_at_700])
    err = capsys.readouterr().err
    assert "stopping at the end of this iteration to save the policy (train.checkpoint_interval = 0: no " \
           "checkpoint)" in err and "a checkpoint (Ctrl-C" not in err
    assert relayrl.load_policy(tmp_path / "cut").env_steps == 700
    assert not list((tmp_path / "cut" / "checkpoints").glob("*"))


def test_ctrl_c_mid_run_saves_a_checkpoint_there_and_the_resumed_run_is_the_uninterrupted_one(tmp_path, capsys):
    """The first Ctrl-C ends the iteration, saves the policy and a checkpoint at that step
    (no final evaluation), then raises KeyboardInterrupt; resuming gives the uninterrupted run."""
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN + ["train.log_interval=100"])
    relayrl.train(cfg, tmp_path / "full", progress=False)
    seen = []

    def ctrl_c_at_700(row):
        seen.append((row["event"], row["step"]))
        if row["step"] == 700:
            os.kill(os.getpid(), signal.SIGINT)

    root = str(tmp_path / "cut")
    with pytest.raises(KeyboardInterrupt, match=rf"the run stopped at env step 700 with a checkpoint in '{root}': "
                                                rf"relayrl.train\(None, '{root}', resume=True\) continues it"):
        relayrl.train(cfg, tmp_path / "cut", progress=False, callbacks=[ctrl_c_at_700])
    assert seen[-1] == ("log", 700)  # no call after the interrupt
    assert "stopping at the end of this iteration to save a checkpoint (Ctrl-C again stops at once)" in \
        capsys.readouterr().err
    assert load_latest_checkpoint(tmp_path / "cut" / "checkpoints")["env_steps"] == 700  # periodic ones: 500
    assert relayrl.load_policy(tmp_path / "cut").env_steps == 700
    assert RunDir(tmp_path / "cut").trained_to() == 700  # its policy's step (the last evaluation: 500)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handler is put back
    relayrl.train(None, tmp_path / "cut", resume=True, progress=False)  # as the interrupt's message says
    assert comparable(tmp_path / "cut") == comparable(tmp_path / "full")


def test_an_interrupt_between_checkpoints_names_the_checkpoint_a_resume_starts_from(tmp_path):
    """A KeyboardInterrupt that stops at once (a second Ctrl-C, or one a callback raises) leaves
    the last periodic checkpoint: the message said "stopped at env step 700 with a checkpoint"
    as if one were there."""
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN + ["train.log_interval=100"])

    def interrupt_at_700(row):
        if row["step"] == 700:
            raise KeyboardInterrupt

    root = str(tmp_path / "cut")
    with pytest.raises(KeyboardInterrupt, match=rf"^the run stopped at env step 700 with a checkpoint \(env step "
                                                rf"500; the steps after it are trained again\) in '{root}': "):
        relayrl.train(cfg, root, progress=False, callbacks=[interrupt_at_700])
    assert load_latest_checkpoint(tmp_path / "cut" / "checkpoints")["env_steps"] == 500


def tensorboard_points(run_dir, tag):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run_dir / "tb"))  # every event file, with a resumed process's purge applied
    events.Reload()
    return [(e.step, e.value) for e in events.Scalars(tag)]


@pytest.mark.parametrize("stop", ["callback", "interrupt"])
def test_tensorboard_after_a_resume_holds_the_uninterrupted_runs_points_once(tmp_path, stop):
    """A clean stop (a callback's False, as Ctrl-C) checkpoints where it stopped; an interrupt
    that stops at once (as a crash) leaves the checkpoint at 500 and points written up to 700,
    which the resumed run's TensorBoard hides (purge_step), as metrics.jsonl is cut back. Episodes
    that ended before a checkpoint are logged before it is written, so none is logged twice."""
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN + ["train.log_interval=100"])
    relayrl.train(cfg, tmp_path / "full", progress=False)

    def interrupt_at_700(row):
        if row["step"] == 700:
            raise KeyboardInterrupt

    if stop == "callback":
        relayrl.train(cfg, tmp_path / "cut", progress=False, callbacks=[lambda row: row["step"] < 700])
    else:
        with pytest.raises(KeyboardInterrupt):
            relayrl.train(cfg, tmp_path / "cut", progress=False, callbacks=[interrupt_at_700])
    relayrl.train(cfg, tmp_path / "cut", resume=True, progress=False)
    for tag in ("charts/episodic_return", "charts/episodic_length", "charts/epsilon"):
        full = tensorboard_points(tmp_path / "full", tag)
        assert len(full) > 10 and tensorboard_points(tmp_path / "cut", tag) == full, tag


def test_resuming_a_finished_run_writes_no_tensorboard_point_again(tmp_path):
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=600"] + DQN[2:])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    before = {tag: tensorboard_points(tmp_path / "r", tag) for tag in ("perf/sps", "charts/epsilon")}
    relayrl.train(None, tmp_path / "r", resume=True, progress=False)  # nothing is left to train
    assert {tag: tensorboard_points(tmp_path / "r", tag) for tag in before} == before


def test_ctrl_c_in_the_final_evaluation_keeps_the_policy_and_a_checkpoint_and_a_resume_evaluates(tmp_path):
    import toy_envs

    cfg = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=600"] + DQN[2:]
                              + ["env.id=toy_envs:Interrupting", "env.check=false", "eval.interval=0",
                                 "train.log_interval=100", "train.checkpoint_interval=250"])

    def ctrl_c_in_the_final_evaluation(row):
        if row["event"] == "log" and row["step"] == 600:
            toy_envs.INTERRUPT["now"] = True

    with pytest.raises(KeyboardInterrupt, match=r"^the run reached its last env step \(600\) with a checkpoint"):
        relayrl.train(cfg, tmp_path / "r", progress=False, callbacks=[ctrl_c_in_the_final_evaluation])
    assert relayrl.load_policy(tmp_path / "r").env_steps == 600
    assert load_latest_checkpoint(tmp_path / "r" / "checkpoints")["env_steps"] == 600
    assert RunDir(tmp_path / "r").read_metrics() == []  # eval.interval = 0: nothing evaluated yet
    result = relayrl.train(None, tmp_path / "r", resume=True, progress=False)
    assert result.final["step"] == 600 and [r["step"] for r in RunDir(tmp_path / "r").read_metrics()] == [600]


@pytest.mark.parametrize("eval_interval, evaluated", [(400, False), (300, True)])
def test_ctrl_c_in_the_last_iteration_saves_the_end_and_still_stops_the_caller(tmp_path, eval_interval, evaluated):
    # A notebook's loop over seeds goes on only if train() returns: the interrupt is raised after
    # the end is saved. With the last step on the evaluation grid, the loop has evaluated it.
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=600"] + DQN[2:]
                              + ["train.log_interval=100", f"eval.interval={eval_interval}",
                                 "train.checkpoint_interval=250"])

    def ctrl_c_at_the_end(row):
        if row["event"] == "log" and row["step"] == 600:
            os.kill(os.getpid(), signal.SIGINT)

    said = ("and evaluated it: it is complete" if evaluated else
            "with a checkpoint in .*: relayrl.train.* does what was left \\(its final evaluation\\)")
    with pytest.raises(KeyboardInterrupt, match=rf"^the run reached its last env step \(600\) {said}"):
        relayrl.train(cfg, tmp_path / "r", progress=False, callbacks=[ctrl_c_at_the_end])
    assert load_latest_checkpoint(tmp_path / "r" / "checkpoints")["env_steps"] == 600
    assert relayrl.load_policy(tmp_path / "r").env_steps == 600
    steps = [r["step"] for r in RunDir(tmp_path / "r").read_metrics()]
    assert steps[-1] == (600 if evaluated else 400)
    result = relayrl.train(None, tmp_path / "r", resume=True, progress=False)  # what was left, if anything
    assert result.final["step"] == 600 and [r["step"] for r in RunDir(tmp_path / "r").read_metrics()][-1] == 600


# evaluations at 0, 500, 1000, 1500 in the loop; at 0, 400, 800, 1200 and a final one off the
# grid (which uses up no seed index); only the final one, which uses one up
@pytest.mark.parametrize("eval_interval,final_writes,eval_count", [(500, 1, 4), (400, 2, 4), (0, 2, 1)])
def test_the_last_checkpoint_is_written_again_only_where_the_final_evaluation_may_change_it(
        tmp_path, monkeypatch, eval_interval, final_writes, eval_count):
    """1,500 steps, a checkpoint every 500: where the loop evaluated at step 1,500, its
    checkpoint there is the final one (a large replay is not written twice); where the final
    evaluation came after it, the checkpoint is written again and holds that evaluation's count."""
    from relayrl.training import checkpoint

    written = []
    save = checkpoint.save_checkpoint
    monkeypatch.setattr(checkpoint, "save_checkpoint",
                        lambda folder, steps, state, keep=2: written.append(steps) or save(folder, steps, state, keep))
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN + [f"eval.interval={eval_interval}"])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    assert written == [500, 1000] + [1500] * final_writes
    assert load_latest_checkpoint(tmp_path / "r" / "checkpoints")["eval_count"] == eval_count


def test_an_ignored_sigint_leaves_sigterm_to_stop_at_the_iterations_end():
    from relayrl import interrupts

    got = []
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)  # a background job's
    try:
        with interrupts.stop_request(got.append):
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
        assert got == [signal.SIGTERM]
    finally:
        signal.signal(signal.SIGINT, old)
    # what the console says a second signal does: a SIGTERM's sender may have no Ctrl-C to press
    assert interrupts.again(signal.SIGINT) == "Ctrl-C again stops at once"
    assert interrupts.again(signal.SIGTERM) == "a second signal stops at once"


def test_resuming_a_run_already_past_total_steps_says_so(tmp_path, capsys):
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=600"] + DQN[2:])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    fewer = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=300"] + DQN[2:])
    fewer.agent.lr = 5e-4
    relayrl.train(fewer, tmp_path / "r", resume=True, progress=False)
    said = capsys.readouterr().err
    assert "the run is at env step 600, past train.total_steps=300: nothing is left to train" in said
    # recorded as any resume's --set: the checkpoint written at the end holds them, and a resume
    # that extends the run goes on with them (config.toml kept the old ones, and the next resume
    # said it differed from its checkpoint, "edited by hand")
    assert "now in config.toml: agent.lr: 0.0023 -> 0.0005; train.total_steps: 600 -> 300" in said
    assert "schedules" not in said
    relayrl.train(None, tmp_path / "r", resume=True, progress=False)
    assert "differs" not in capsys.readouterr().err
    assert relayrl.load_config(str(tmp_path / "r" / "config.toml")).agent.lr == 5e-4


def test_resume_with_another_network_is_one_line_and_keeps_the_run(tmp_path):
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=600"] + DQN[2:])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    before = (tmp_path / "r" / "metrics.jsonl").read_text()
    config_before = (tmp_path / "r" / "config.toml").read_text()
    wider = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=900", "agent.hidden=[48,32]"]
                                + DQN[2:-1])
    with pytest.raises(relayrl.errors.UserError, match=r"--resume: agent.hidden=\[48, 32\] but the run in .* has "
                                                       r"\[32, 32\]; a resumed run keeps its networks"):
        relayrl.train(wider, tmp_path / "r", resume=True, progress=False)
    # the same activation, sizes and encoder, but an env whose observations changed shape: found on loading
    other = relayrl.load_config(str(tmp_path / "r" / "config.toml"), ["train.total_steps=900",
                                                                     "env.wrappers=['toy_envs:Repeated']"])
    with pytest.raises(relayrl.errors.UserError, match=r"the env's observations are Box\(.*shape=\(8,\), .* but "
                                                       r"the run was trained on Box\(.*shape=\(4,\), .*: resume with "
                                                       r"the env settings the run started with"):
        relayrl.train(other, tmp_path / "r", resume=True, progress=False)
    assert (tmp_path / "r" / "metrics.jsonl").read_text() == before
    assert (tmp_path / "r" / "config.toml").read_text() == config_before  # the refused settings are not kept


def test_resume_with_overrides_records_them_in_config_toml(tmp_path, capsys):
    """`--resume --set ...` goes on with the new settings, and config.toml says so, so that
    `relayrl eval` and the next plain resume use them too."""
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=600"] + DQN[2:])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    capsys.readouterr()
    longer = relayrl.load_config(str(tmp_path / "r" / "config.toml"), ["train.total_steps=900", "agent.lr=0.002"])
    relayrl.train(longer, tmp_path / "r", resume=True, progress=False)
    assert ("resumed with changed settings, now in config.toml: agent.lr: 0.0023 -> 0.002; "
            "train.total_steps: 600 -> 900") in capsys.readouterr().err
    saved = relayrl.load_config(str(tmp_path / "r" / "config.toml"))
    assert (saved.train.total_steps, saved.agent.lr) == (900, 0.002)
    plain = relayrl.load_config(str(tmp_path / "r" / "config.toml"), ["train.total_steps=1200"])
    relayrl.train(plain, tmp_path / "r", resume=True, progress=False)
    assert "changed settings, now in config.toml: train.total_steps: 900 -> 1200\n" in capsys.readouterr().err
    assert relayrl.load_config(str(tmp_path / "r" / "config.toml")).agent.lr == 0.002


@pytest.mark.parametrize("preset,over,lrs", [
    ("dqn-cartpole-fast", DQN + ["agent.lr_end=-1.0"], {"agent.lr": ("optimizer", 0.002)}),  # constant
    ("sac-pendulum", SAC, {"agent.actor_lr": ("actor_opt", 0.001), "agent.critic_lr": ("critic_opt", 0.002),
                           "agent.alpha_lr": ("alpha_opt", 0.0005)}),
], ids=["dqn", "sac"])
def test_a_resume_that_changes_a_constant_learning_rate_trains_with_it(tmp_path, preset, over, lrs):
    """The optimizers took their learning rate back from the checkpoint, so `--resume --set
    agent.lr=...` was logged and written to config.toml but did not change the training."""
    cfg = relayrl.load_config(preset, over + ["train.checkpoint_interval=300"])
    total = cfg.train.total_steps
    cfg.train.total_steps = total // 2
    relayrl.train(cfg, tmp_path / "r", progress=False)
    longer = relayrl.load_config(str(tmp_path / "r" / "config.toml"),
                                 [f"train.total_steps={total}"] + [f"{k}={lr}" for k, (_, lr) in lrs.items()])
    relayrl.train(longer, tmp_path / "r", resume=True, progress=False)
    agent = load_latest_checkpoint(tmp_path / "r" / "checkpoints")["agent"]
    assert {key: agent[key]["lr"] for key, _ in lrs.values()} == {key: lr for key, lr in lrs.values()}


@pytest.mark.parametrize("autotune,alpha", [(False, 0.05), (True, None)])
def test_a_resume_that_changes_a_fixed_sac_alpha_trains_with_it(tmp_path, autotune, alpha):
    """A fixed alpha (agent.autotune_alpha = false) is a setting, as a constant lr is: a resume
    with another agent.init_alpha uses it. A tuned one goes on from where tuning left it."""
    over = SAC + [f"agent.autotune_alpha={str(autotune).lower()}", "agent.init_alpha=0.2"]
    relayrl.train(relayrl.load_config("sac-pendulum", over + ["train.total_steps=300"]), tmp_path / "r",
                  progress=False)
    tuned = float(load_latest_checkpoint(tmp_path / "r" / "checkpoints")["agent"]["log_alpha"])
    relayrl.train(relayrl.load_config(str(tmp_path / "r" / "config.toml"),
                                      ["train.total_steps=600", "agent.init_alpha=0.05"]),
                  tmp_path / "r", resume=True, progress=False)
    log_alpha = float(load_latest_checkpoint(tmp_path / "r" / "checkpoints")["agent"]["log_alpha"])
    if alpha is not None:
        assert log_alpha == pytest.approx(np.log(alpha))
    else:
        assert tuned != pytest.approx(np.log(0.2)) and log_alpha != pytest.approx(np.log(0.05))


def test_python_resume_without_a_config_goes_on_with_the_runs_own(tmp_path, capsys):
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=600"] + DQN[2:])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    with pytest.raises(relayrl.errors.UserError, match="config=None continues a run with its own config.toml"):
        relayrl.train(None, tmp_path / "r", progress=False)
    longer = relayrl.load_config(str(tmp_path / "r" / "config.toml"), ["train.total_steps=900"])
    relayrl.train(longer, tmp_path / "r", resume=True, progress=False)
    capsys.readouterr()
    result = relayrl.train(None, tmp_path / "r", resume=True, progress=False)  # nothing left: as the CLI says
    assert "nothing is left to train" in capsys.readouterr().err and result.final["step"] == 900


def test_a_resume_that_changes_total_steps_says_which_schedules_it_stretches(tmp_path, capsys):
    cfg = relayrl.load_config("dqn", ["train.total_steps=400", "agent.lr_end=0.00001", "eval.episodes=1",
                                      "train.checkpoint_interval=200", "agent.batch_size=8"])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    capsys.readouterr()
    relayrl.train(relayrl.load_config(str(tmp_path / "r" / "config.toml"), ["train.total_steps=800"]),
                  tmp_path / "r", resume=True, progress=False)
    assert ("the schedules over train.total_steps (agent.lr_end=1e-05, agent.epsilon_decay_steps=-1) now run to "
            "env step 800: from env step 400 on they follow the new length") in capsys.readouterr().err
    plain = relayrl.load_config("dqn", ["train.total_steps=400", "eval.episodes=1", "agent.epsilon_decay_steps=100"])
    assert plain.agent.over_total_steps() == []


def test_an_old_ppo_runs_config_toml_with_a_replay_section_still_evaluates_and_resumes(tmp_path, capsys):
    cfg = relayrl.load_config("ppo-cartpole", ["train.total_steps=1024", "train.collect_steps=512",
                                               "agent.batch_size=64", "agent.n_epochs=1", "eval.episodes=1",
                                               "train.checkpoint_interval=512"])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    toml = tmp_path / "r" / "config.toml"
    toml.write_text(toml.read_text() + "\n[replay]\nsize = 5000\n")  # taken, and unused, before it was refused
    capsys.readouterr()
    longer = relayrl.load_config(str(toml), ["train.total_steps=1536"])
    said = capsys.readouterr().err
    assert "config.toml: replay.size=5000 left out (algo='ppo' learns without a replay table)" in said
    relayrl.train(longer, tmp_path / "r", resume=True, progress=False)
    with pytest.raises(relayrl.errors.UserError, match="replay.size=5000 is not valid for algo='ppo'"):
        relayrl.load_config("ppo-cartpole", ["replay.size=5000"])  # a new config is still told


def test_resume_refuses_another_number_of_envs(tmp_path):
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=600"] + DQN[2:])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    more = relayrl.load_config("dqn-cartpole-fast", DQN + ["env.num_envs=2"])
    with pytest.raises(relayrl.errors.UserError, match="env.num_envs=2 but the run in .* has 1"):
        relayrl.train(more, tmp_path / "r", resume=True, progress=False)
    # async: the refusal closes the env's worker processes (a notebook would keep them otherwise)
    more = relayrl.load_config("dqn-cartpole-fast", DQN + ["env.num_envs=2", "env.vectorization=async"])
    with pytest.raises(relayrl.errors.UserError, match="env.num_envs=2 but the run in .* has 1"):
        relayrl.train(more, tmp_path / "r", resume=True, progress=False)
    assert not [p for p in multiprocessing.active_children() if p.name.startswith("relayrl-env")]


def test_resume_refuses_another_replay_size_in_one_line(tmp_path):
    """The checkpoint holds the table at its size: another size was a ValueError from the restore."""
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=600"] + DQN[2:])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    size = cfg.replay.size
    more = relayrl.load_config("dqn-cartpole-fast", DQN + [f"replay.size={size + 1}"])
    with pytest.raises(relayrl.errors.UserError, match=f"replay.size={size + 1} but the run in .* has {size}; its "
                                                       "checkpoint holds a replay table of that size"):
        relayrl.train(more, tmp_path / "r", resume=True, progress=False)


def test_resume_refuses_another_rollout_length_in_one_line(tmp_path):
    """PPO's checkpoint holds its rollout table: another train.collect_steps trained on, then
    failed mid-run (a ValueError from the table), with the new value already in config.toml."""
    small = ["train.total_steps=128", "train.collect_steps=64", "agent.batch_size=32", "agent.n_epochs=1",
             "eval.interval=0", "eval.episodes=1"]
    relayrl.train(relayrl.load_config("ppo-cartpole", small), tmp_path / "r", progress=False)
    before = (tmp_path / "r" / "config.toml").read_text()
    more = relayrl.load_config(str(tmp_path / "r" / "config.toml"),
                               ["train.total_steps=256", "train.collect_steps=128"])
    with pytest.raises(relayrl.errors.UserError, match="train.collect_steps=128 but the run in .* has 64; its "
                                                       "checkpoint holds a rollout table of that many env steps"):
        relayrl.train(more, tmp_path / "r", resume=True, progress=False)
    assert (tmp_path / "r" / "config.toml").read_text() == before


def test_a_run_whose_checkpoints_hold_no_rollout_table_resumes_with_another_rollout_length(tmp_path):
    """train.checkpoint_replay = false: the checkpoint holds no rollout table, and a new length
    works (as on Ray, whose actors size their shares from the config)."""
    small = ["train.total_steps=128", "train.collect_steps=64", "agent.batch_size=32", "agent.n_epochs=1",
             "eval.interval=0", "eval.episodes=1", "train.checkpoint_replay=false"]
    relayrl.train(relayrl.load_config("ppo-cartpole", small), tmp_path / "r", progress=False)
    more = relayrl.load_config(str(tmp_path / "r" / "config.toml"),
                               ["train.total_steps=384", "train.collect_steps=128"])
    assert relayrl.train(more, tmp_path / "r", resume=True, progress=False).final["step"] == 384


@pytest.mark.parametrize("key, edit", [("seed", ("seed = 0 ", "seed = 5 ")),
                                       ("env.num_envs", ("num_envs = 1 ", "num_envs = 2 "))])
def test_a_config_toml_edited_by_hand_is_checked_against_the_checkpoint(key, edit, tmp_path):
    """The config.toml a resume reads was changed after the checkpoint: the checkpoint's own
    config says what the run is, in one line."""
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=600"] + DQN[2:])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    toml = tmp_path / "r" / "config.toml"
    assert edit[0] in toml.read_text()
    toml.write_text(toml.read_text().replace(edit[0], edit[1]))
    rows = (tmp_path / "r" / "metrics.jsonl").read_text()
    longer = relayrl.load_config(str(toml), ["train.total_steps=900"])
    with pytest.raises(relayrl.errors.UserError, match=f"the run's checkpoint was written with {key}="):
        relayrl.train(longer, tmp_path / "r", resume=True, progress=False)
    assert (tmp_path / "r" / "metrics.jsonl").read_text() == rows  # nothing written


def test_a_setting_edited_by_hand_in_config_toml_is_named_on_resume(tmp_path, capsys):
    """A key a resumed run may change (agent.lr), edited in config.toml rather than given with
    --set, is named against the checkpoint's settings; --set changes keep their own line."""
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=600"] + DQN[2:])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    toml = tmp_path / "r" / "config.toml"
    toml.write_text(toml.read_text().replace(f"lr = {cfg.agent.lr} ", "lr = 0.01 ").replace("total_steps = 600 ",
                                                                                             "total_steps = 900 "))
    capsys.readouterr()
    relayrl.train(relayrl.load_config(str(toml)), tmp_path / "r", resume=True, progress=False)
    err = capsys.readouterr().err
    assert (f"config.toml differs from the settings its checkpoint was written with (edited by hand, or a resume "
            f"stopped before its first checkpoint): agent.lr: {cfg.agent.lr!r} -> 0.01; train.total_steps: 600 -> "
            f"900\n") in err
    assert "resumed with changed settings" not in err  # nothing given with --set
    assert "the schedules over train.total_steps (" in err  # the checkpoint's total was 600
    relayrl.train(relayrl.load_config(str(toml), ["train.total_steps=1200"]), tmp_path / "r", resume=True,
                  progress=False)
    err = capsys.readouterr().err
    assert "config.toml differs" not in err  # the checkpoints since hold the edit
    assert "resumed with changed settings, now in config.toml: train.total_steps: 900 -> 1200\n" in err


def test_a_run_whose_checkpoints_leave_the_replay_out_resumes_with_another_replay_size(tmp_path):
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=600", "train.checkpoint_replay=false"]
                              + DQN[2:])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    more = relayrl.load_config(str(tmp_path / "r" / "config.toml"), [f"replay.size={cfg.replay.size + 1}"])
    relayrl.train(more, tmp_path / "r", resume=True, progress=False)


def test_a_memmap_run_whose_config_toml_was_edited_keeps_its_replay_files(tmp_path):
    """The checkpoint's config is checked before the run is built: building would lay the
    memmap files out again for the edited size."""
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN + ["replay.storage=memmap", "replay.size=300"])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    files = {f.name: f.read_bytes() for f in (tmp_path / "r" / "replay").iterdir()}
    toml = tmp_path / "r" / "config.toml"
    toml.write_text(toml.read_text().replace("size = 300 ", "size = 400 "))
    with pytest.raises(relayrl.errors.UserError, match="checkpoint was written with replay.size=300, but the config "
                                                       "resumed with has 400: set replay.size = 300 in"):
        relayrl.train(relayrl.load_config(str(toml), ["train.total_steps=1800"]), tmp_path / "r", resume=True,
                      progress=False)
    assert {f.name: f.read_bytes() for f in (tmp_path / "r" / "replay").iterdir()} == files


def test_a_memmap_replay_written_past_its_checkpoint_says_the_resume_is_not_bit_exact(tmp_path, capsys):
    """A killed run's memmap files went on past its last checkpoint: the items whose rows were
    overwritten are dropped on resume, and the log says so."""
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN + ["replay.storage=memmap", "replay.size=300",
                                                          "train.checkpoint_keep=0"])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    for late in sorted((tmp_path / "r" / "checkpoints").iterdir())[1:]:  # as if killed after the first
        late.unlink()
    capsys.readouterr()
    relayrl.train(None, tmp_path / "r", resume=True, progress=False)
    assert ("the replay files were written after this checkpoint: 300 replay items it held are gone and the envs start "
            "new episodes, so this resume is not bit for bit") in capsys.readouterr().err


def test_a_run_that_fails_while_it_is_built_leaves_no_env_worker(tmp_path):
    bad = relayrl.load_config("dqn-cartpole-fast", DQN + ["env.num_envs=2", "env.vectorization=async",
                                                          "replay.storage=memmap"])
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "replay").write_text("a file where the memmap replay's folder goes")
    with pytest.raises(relayrl.errors.UserError, match="needs a folder at .*replay, but a file is in the way"):
        relayrl.train(bad, tmp_path / "r", progress=False)  # the replay's storage is built after the env
    assert not [p for p in multiprocessing.active_children() if p.name.startswith("relayrl-env")]


@pytest.mark.parametrize("size", [10**15, 2**63 - 1])  # 8 PB of keys alone; more bytes than NumPy can address
def test_a_run_too_large_for_memory_is_one_line_and_writes_nothing(size, tmp_path, monkeypatch):
    from relayrl.training import replay_setup

    monkeypatch.setattr(replay_setup, "available_host_memory", lambda: None)  # as off Linux: the allocation says it
    huge = relayrl.load_config("dqn-cartpole-fast", DQN + [f"replay.size={size}"])
    with pytest.raises(relayrl.errors.UserError, match=r"not enough memory to build the run \(.*\): lower "
                                                       rf"replay.size={size:,} or the networks' sizes"):
        relayrl.train(huge, tmp_path / "r", progress=False)
    assert not (tmp_path / "r").exists()


def test_a_memmap_folder_is_recorded_absolute_and_another_run_cannot_share_it(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    small = DQN[:1] + ["train.total_steps=300", "replay.storage=memmap", "replay.path=shared"] + DQN[2:]
    relayrl.train(relayrl.load_config("dqn-cartpole-fast", small), tmp_path / "a", progress=False)
    assert relayrl.load_config(str(tmp_path / "a" / "config.toml")).replay.path == str(tmp_path / "shared")
    with pytest.raises(relayrl.errors.UserError, match="holds the replay of the run in .*a'; give this run"):
        relayrl.train(relayrl.load_config("dqn-cartpole-fast", small), tmp_path / "b", progress=False)
    monkeypatch.chdir(tmp_path / "a")  # a resume from elsewhere finds the run's own files
    more = relayrl.load_config(str(tmp_path / "a" / "config.toml"), ["train.total_steps=400"])
    relayrl.train(more, tmp_path / "a", resume=True, progress=False)
    assert not (tmp_path / "a" / "shared").exists()


def test_a_copied_run_directory_with_its_own_memmap_replay_resumes(tmp_path):
    small = DQN[:1] + ["train.total_steps=300", "replay.storage=memmap"] + DQN[2:]
    relayrl.train(relayrl.load_config("dqn-cartpole-fast", small), tmp_path / "a", progress=False)
    shutil.copytree(tmp_path / "a", tmp_path / "b")  # its replay/run.txt still names run a
    more = relayrl.load_config(str(tmp_path / "b" / "config.toml"), ["train.total_steps=400"])
    assert relayrl.train(more, tmp_path / "b", resume=True, progress=False).final["step"] == 400


WRITER = """
import sys, torch
from pathlib import Path
from relayrl.training.checkpoint import list_checkpoints, save_checkpoint
folder = Path(sys.argv[1])
x = torch.arange(2_000_000, dtype=torch.float32)  # 8 MB: each write takes a while
done = list_checkpoints(folder)
i = int(done[-1].stem.split("-")[1]) if done else 0
print("ready", flush=True)
while True:
    i += 1
    save_checkpoint(folder, i, {"env_steps": i, "x": x + i})
"""


def test_sigkill_at_any_moment_leaves_a_readable_checkpoint(tmp_path):
    folder = tmp_path / "ck"
    rng = random.Random(0)
    x = torch.arange(2_000_000, dtype=torch.float32)
    mid_write = 0
    for _ in range(12):
        p = subprocess.Popen([sys.executable, "-c", WRITER, str(folder)], stdout=subprocess.PIPE, text=True)
        assert p.stdout is not None and p.stdout.readline() == "ready\n"
        time.sleep(rng.uniform(0.05, 0.5))
        p.send_signal(signal.SIGKILL)
        p.wait()
        mid_write += any(folder.glob("*.tmp"))
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # a warning here means an unreadable checkpoint
            for ckpt in list_checkpoints(folder):
                state = torch.load(ckpt, weights_only=False)
                assert torch.equal(state["x"], x + state["env_steps"])
    assert mid_write > 0, "no kill landed inside a write; the test proved nothing"


def test_run_killed_at_a_random_moment_resumes_to_the_uninterrupted_result(tmp_path):
    over = DQN[:1] + ["train.total_steps=3000", "train.torch_threads=1"] + DQN[2:]
    relayrl.train(relayrl.load_config("dqn-cartpole-fast", over, seed=3), tmp_path / "full", progress=False)
    cmd = [sys.executable, "-m", "relayrl", "train", "dqn-cartpole-fast", "--run-dir", str(tmp_path / "killed"),
           "--no-progress"]
    sets = [a for o in over for a in ("--set", o)]
    p = subprocess.Popen(cmd + sets + ["--seed", "3"], stderr=subprocess.DEVNULL)
    while not list_checkpoints(tmp_path / "killed" / "checkpoints") and p.poll() is None:
        time.sleep(0.02)
    time.sleep(random.Random(1).uniform(0.0, 1.0))
    p.send_signal(signal.SIGKILL)
    assert p.wait() == -signal.SIGKILL, "the run ended before the kill"
    # The preset may be left out: a resumed run takes the config saved in its directory.
    resume = [sys.executable, "-m", "relayrl", "train", "--run-dir", str(tmp_path / "killed"), "--resume",
              "--no-progress"]
    done = subprocess.run(resume, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert comparable(tmp_path / "killed") == comparable(tmp_path / "full")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("envs", [[], ["env.num_envs=3", "env.vectorization=async", "env.num_workers=2"]],
                         ids=["1env", "3async"])
def test_sigterm_stops_a_run_like_ctrl_c_and_it_resumes(tmp_path, envs):
    over = DQN[:1] + ["train.total_steps=3000", "train.torch_threads=1"] + DQN[2:] + envs
    cmd = [sys.executable, "-m", "relayrl", "train", "dqn-cartpole-fast", "--run-dir", str(tmp_path / "run"),
           "--no-progress", *[a for o in over for a in ("--set", o)]]
    p = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    while not list_checkpoints(tmp_path / "run" / "checkpoints") and p.poll() is None:
        time.sleep(0.02)
    workers = children_running(p.pid)
    assert len(workers) == (2 if envs else 0)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 143, err  # 128 + SIGTERM: handled, not killed (-15)
    assert "relayrl: terminated; resume with --resume from the last checkpoint" in err
    assert "Ctrl-C again" not in err  # where it says what a second signal does, it names no Ctrl-C
    assert "Traceback" not in err
    assert not [w for w in workers if running(w)], "env workers outlived the run"
    done = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert RunDir(tmp_path / "run").read_metrics()[-1]["step"] == 3000


@pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="no SIGHUP")
@pytest.mark.parametrize("output", ["log-file", "closed-terminal", "pipe-reader-gone"])
def test_sighup_stops_a_run_with_a_checkpoint_also_when_its_terminal_is_gone(tmp_path, output):
    """A closed terminal (a lost SSH session) sends SIGHUP: the run stops as on SIGTERM, with a
    checkpoint at the step it stopped at, and exits 129. Where its output was the terminal, or a
    pipe whose reader (`| tee log`) ended with it, the stop's lines go nowhere instead of failing
    it with EIO or EPIPE; where it was a file, they are there."""
    import pty

    over = DQN[:1] + ["train.total_steps=100000", "train.torch_threads=1"] + DQN[2:]
    cmd = [sys.executable, "-m", "relayrl", "train", "dqn-cartpole-fast", "--run-dir", str(tmp_path / "run"),
           "--no-progress", *[a for o in over for a in ("--set", o)]]
    log = tmp_path / "log.txt"

    def as_in_a_terminal() -> None:  # a test run under nohup passes SIGHUP on ignored
        signal.signal(signal.SIGHUP, signal.SIG_DFL)

    started = {"stdin": subprocess.DEVNULL, "preexec_fn": as_in_a_terminal}
    if output == "closed-terminal":
        reader, slave = pty.openpty()
        p = subprocess.Popen(cmd, stdout=slave, stderr=slave, **started)
        os.close(slave)
    elif output == "pipe-reader-gone":
        p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, **started)
        reader = p.stdout.fileno()
    else:
        with open(log, "w") as out:
            p = subprocess.Popen(cmd, stdout=out, stderr=out, **started)
    checkpoints = tmp_path / "run" / "checkpoints"
    while not list_checkpoints(checkpoints) and p.poll() is None:
        if output != "log-file":  # read what it writes, as a terminal or tee does, so its writes never block
            os.set_blocking(reader, False)
            with contextlib.suppress(OSError):
                os.read(reader, 65536)
        time.sleep(0.02)
    time.sleep(0.5)
    if output == "closed-terminal":
        os.close(reader)  # the terminal is gone: every write to it now fails with EIO
    elif output == "pipe-reader-gone":
        p.stdout.close()  # tee ended with the terminal: every write now fails with EPIPE
    p.send_signal(signal.SIGHUP)
    assert p.wait(timeout=60) == 128 + signal.SIGHUP
    # a checkpoint at the step the run stopped at (where it saved its policy), which may be a
    # periodic one's step where the signal came right after it
    stopped = RunDir(tmp_path / "run").trained_to()
    assert checkpoint_step(list_checkpoints(checkpoints)[-1]) == stopped, "no checkpoint at the stop"
    assert RunDir(tmp_path / "run").read_metrics()  # its log is whole
    if output == "log-file":
        said = log.read_text()
        assert "relayrl: hung up (the terminal closed); resume with --resume" in said and "Traceback" not in said


@pytest.mark.parametrize("stop, output", [("ctrl-c", "pipe"), ("none", "pipe"), ("none", "terminal")])
def test_a_run_whose_output_pipe_loses_its_reader_goes_on(tmp_path, stop, output):
    """`relayrl train ... | head -3`: the reader closes, and the run died at its next line (EPIPE),
    exit 1, no checkpoint. `... | tee log` and Ctrl-C: tee ends with the same SIGINT, and the stop's
    own lines failed the stop. The run's lines go nowhere now: it trains to its end, or stops
    with a checkpoint and exit 130."""
    steps = "100000" if stop == "ctrl-c" else "1500"
    over = DQN[:1] + [f"train.total_steps={steps}", "train.torch_threads=1"] + DQN[2:]
    cmd = [sys.executable, "-m", "relayrl", "train", "dqn-cartpole-fast", "--run-dir", str(tmp_path / "run"),
           *[a for o in over for a in ("--set", o)]]

    def as_in_a_terminal() -> None:  # a test run in the background of a script passes SIGINT on ignored
        signal.signal(signal.SIGINT, signal.SIG_DFL)

    if output == "terminal":  # a terminal closed without SIGHUP (its session kept): writes fail with EIO
        import pty

        reader, slave = pty.openpty()
        p = subprocess.Popen(cmd, stdout=slave, stderr=slave, stdin=subprocess.DEVNULL, preexec_fn=as_in_a_terminal)
        os.close(slave)
        os.read(reader, 100)
        os.close(reader)
    else:
        p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                             preexec_fn=as_in_a_terminal)
        p.stdout.readline()  # its first line, as head -1 reads it
        p.stdout.close()
    checkpoints = tmp_path / "run" / "checkpoints"
    if stop == "none":
        assert p.wait(timeout=120) == 0
        assert RunDir(tmp_path / "run").read_metrics()[-1]["step"] == 1500
        return
    while not list_checkpoints(checkpoints) and p.poll() is None:
        time.sleep(0.02)
    time.sleep(0.5)
    p.send_signal(signal.SIGINT)
    assert p.wait(timeout=60) == 130
    stopped = RunDir(tmp_path / "run").trained_to()  # where it saved its policy at the stop
    assert checkpoint_step(list_checkpoints(checkpoints)[-1]) == stopped, "no checkpoint at the stop"


@pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="no SIGHUP")
def test_a_signal_whose_handler_python_cannot_put_back_leaves_the_others_handled(monkeypatch):
    """A handler set outside Python (getsignal gives None) cannot be swapped and put back: that
    signal is left alone, Ctrl-C and SIGTERM are still held during a write."""
    from relayrl import interrupts

    real = signal.getsignal
    monkeypatch.setattr(signal, "getsignal", lambda s: None if s == signal.SIGHUP else real(s))
    before = real(signal.SIGINT)
    with interrupts.deferred():
        assert real(signal.SIGINT) is not before  # held
    assert real(signal.SIGINT) is before


@pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="no SIGHUP")
def test_under_nohup_sighup_stays_ignored():
    """nohup ignores SIGHUP so that a run outlives its terminal: relayrl neither stops on it nor
    holds it during a write."""
    from relayrl import cli, interrupts

    before = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        assert signal.SIGHUP not in cli._stop_signals()
        with interrupts.deferred():
            assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGHUP)
        with interrupts.stop_request(lambda signum: pytest.fail("a stop was requested")):
            os.kill(os.getpid(), signal.SIGHUP)
    finally:
        signal.signal(signal.SIGHUP, before)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("sig, code, what", [(signal.SIGTERM, 143, "terminated"), (signal.SIGINT, 130, "interrupted")])
def test_a_signal_to_the_whole_process_group_stops_an_async_run_cleanly(tmp_path, cli_env, sig, code, what):
    """Ctrl-C in a terminal, systemd and Slurm signal every process of the group, env workers
    included: the run must still stop as on a signal to the main process alone."""
    over = ["env.id=toy_envs:Sleepy", "env.num_envs=2", "env.vectorization=async", "env.num_workers=1",
            "train.total_steps=100000", "train.initial_collect_steps=100000", "eval.episodes=1"]
    cmd = [sys.executable, "-m", "relayrl", "train", "dqn-cartpole-fast", "--run-dir", str(tmp_path / "run"),
           "--no-progress", *[a for o in over for a in ("--set", o)]]
    p = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, env=cli_env, start_new_session=True)
    deadline = time.monotonic() + 60
    while not (workers := children_running(p.pid)) and p.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert workers, "no env worker started"
    time.sleep(2.0)  # past the first evaluation (0.4 s), into collection: ~2 ms env steps on both sides
    os.killpg(p.pid, sig)
    _, err = p.communicate(timeout=60)
    assert p.returncode == code, err
    # Still in the random warm-up, before the first checkpoint: no --resume is offered.
    assert f"relayrl: {what} before the first checkpoint: nothing to resume" in err and "Traceback" not in err, err
    assert not [w for w in workers if running(w)], "env workers outlived the run"


def test_policy_loads_and_evaluates_at_any_moment_of_a_run(tmp_path):
    over = DQN[:1] + ["train.total_steps=100000", "train.policy_save_interval=100", "train.torch_threads=1"] + DQN[2:]
    run = tmp_path / "live"
    cmd = [sys.executable, "-m", "relayrl", "train", "dqn-cartpole-fast", "--run-dir", str(run), "--no-progress"]
    p = subprocess.Popen(cmd + [a for o in over for a in ("--set", o)], stderr=subprocess.DEVNULL)
    try:
        seen = []
        while len(set(seen)) < 5:  # loads race the run's atomic replacements of policy.pt
            assert p.poll() is None, "the run ended early"
            if (run / "policy" / "policy.pt").exists():
                seen.append(relayrl.load_policy(run).env_steps)
        assert seen == sorted(seen) and seen[0] is not None
        r = subprocess.run([sys.executable, "-m", "relayrl", "eval", str(run), "--episodes", "2"],
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        assert json.loads(r.stdout)["policy_env_steps"] >= seen[-1]
    finally:
        p.kill()
        p.wait()


def test_eval_before_a_run_saved_any_policy_says_so(tmp_path):
    RunDir(tmp_path / "r").create()
    (tmp_path / "r" / "config.toml").write_text("")
    with pytest.raises(relayrl.errors.UserError, match="has not saved a policy yet"):
        relayrl.load_policy(tmp_path / "r")


@pytest.mark.parametrize("size, wraps", [(800, False), (300, True)])
def test_memmap_replay_resumed_from_an_older_checkpoint(tmp_path, capsys, size, wraps):
    # 500 steps between checkpoints: a ring of ~850 rows (size 800) still holds the episodes
    # open at the older checkpoint, one of ~320 (size 300) has overwritten every row since. The
    # seed has an episode open, with rows, at that checkpoint (one that ends exactly there
    # leaves no rows to be overwritten, and nothing to say).
    over = DQN + ["replay.storage='memmap'", f"replay.size={size}", "train.initial_collect_steps=100"]
    cfg = relayrl.load_config("dqn-cartpole-fast", over, seed=0)
    run_dir = tmp_path / "m"
    relayrl.train(cfg, run_dir, progress=False)
    list_checkpoints(run_dir / "checkpoints")[-1].unlink()  # as if killed while writing it
    from relayrl.training.local import LocalDriver

    run = LocalDriver(cfg, RunDir(run_dir), False)
    run.restore()
    live = np.flatnonzero(run.replay.slot_key >= 0)
    assert not run.replay.storage.stale(live).any() and (live.size == 0) == wraps
    said = capsys.readouterr().err
    assert "the replay files were written after this checkpoint: " in said  # the rows of 500 steps, both sizes
    assert ("the envs start new episodes" in said) == wraps
    run.actor.collect(5)  # continued (or new) episodes insert only items whose rows hold their steps
    live = np.flatnonzero(run.replay.slot_key >= 0)
    assert live.size > 0 and not run.replay.storage.stale(live).any()
    run.env.close()
    run.eval_env.close()
    assert relayrl.train(cfg, run_dir, resume=True, progress=False).final["step"] == 1500


def test_resume_naming_a_preset_with_other_networks_uses_the_runs_own_config(tmp_path):
    """README: with --resume the preset may be given too; the run's own config.toml is what counts."""
    from relayrl.cli import main

    cfg = relayrl.load_config("dqn", ["env.id=CartPole-v1", "train.total_steps=600", "train.checkpoint_interval=300",
                                      "eval.interval=300", "eval.episodes=2", "train.initial_collect_steps=100"])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    assert relayrl.load_config("dqn-cartpole-fast").agent.hidden != cfg.agent.hidden
    assert main(["train", "dqn-cartpole-fast", "--run-dir", str(tmp_path / "r"), "--resume", "--no-progress",
                 "--set", "train.total_steps=900"]) == 0
    assert RunDir(tmp_path / "r").read_metrics()[-1]["step"] == 900


def test_resume_with_env_settings_that_change_the_space_is_one_line_and_keeps_the_run(tmp_path):
    """[H, W, C] frames turned [C, H, W] by an env kwarg fit the same conv weights (and a run
    without its replay in the checkpoint has no other store to notice): the spaces the
    checkpoint records refuse it before anything is loaded or rewritten."""
    over = ["env.id=space_envs:Spaces", "env.kwargs={obs = 'image_hwc'}", "train.total_steps=200",
            "train.initial_collect_steps=50", "eval.interval=0", "train.checkpoint_interval=100",
            "agent.hidden=[16]", "agent.batch_size=8"]
    for keep_replay in ("true", "false"):
        root = tmp_path / keep_replay
        relayrl.train(relayrl.load_config("dqn", [*over, f"train.checkpoint_replay={keep_replay}"]), root,
                      progress=False)
        before = {f: (root / f).read_text() for f in ("config.toml", "metrics.jsonl")}
        other = relayrl.load_config(str(root / "config.toml"), ["train.total_steps=300",
                                                                 "env.kwargs={obs = 'image_chw'}"])
        with pytest.raises(relayrl.errors.UserError,
                           match=r"^the env's observations are Box\(0, 255, shape=\(3, 10, 10\), dtype=uint8\) but "
                                 r"the run was trained on Box\(0, 255, shape=\(10, 10, 3\), dtype=uint8\)"):
            relayrl.train(other, root, resume=True, progress=False)
        assert {f: (root / f).read_text() for f in before} == before
        relayrl.train(relayrl.load_config(str(root / "config.toml"), ["train.total_steps=300"]), root, resume=True,
                      progress=False)


def test_a_resume_that_changes_how_the_envs_are_made_starts_new_episodes_with_them(tmp_path, capsys):
    """The checkpoint's envs, pickled mid-episode, were made with its env.kwargs: a resume that
    changes them (a simulator setting fixed after a crash) trains on envs made with the new ones."""
    over = ["env.id=toy_envs:Countdown", "env.kwargs={length = 1000}", "env.check=false", "train.total_steps=200",
            "train.initial_collect_steps=50", "eval.interval=0", "eval.episodes=1", "train.checkpoint_interval=100",
            "agent.hidden=[16]", "agent.batch_size=8", "env.max_episode_steps=2000"]
    relayrl.train(relayrl.load_config("dqn", over), tmp_path / "run", progress=False)
    capsys.readouterr()
    resumed = relayrl.load_config(str(tmp_path / "run" / "config.toml"),
                                  ["train.total_steps=300", "env.kwargs={length = 5}"])
    result = relayrl.train(resumed, tmp_path / "run", resume=True, progress=False)
    assert "env.kwargs changed: the envs start new episodes with the new settings" in capsys.readouterr().err
    assert result.final["train/average_return"] == 5.0  # episodes of the new length were trained on
    assert result.final["train/episodes"] == 20  # 100 steps / 5: none of the old envs' episode was kept


def test_ctrl_c_in_the_random_warm_up_says_where_the_run_stopped(tmp_path):
    """Python's own KeyboardInterrupt (no stop requested: the warm-up stops at once) gets the same
    message a requested stop gets."""
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=100000"] + DQN[2:]
                              + ["env.id=toy_envs:Sleepy", "env.check=false",  # 2 ms a step: a long warm-up
                                 "train.initial_collect_steps=50000", "eval.interval=0"])
    timer = threading.Timer(1.5, lambda: os.kill(os.getpid(), signal.SIGINT))
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt, match=r"before its first checkpoint: nothing to resume; a new run in "
                                                    r"'.*r' starts over in it$"):
            relayrl.train(cfg, tmp_path / "r", progress=False)
    finally:
        timer.cancel()
    # as said: a new run takes the folder over without overwrite=True
    relayrl.train(relayrl.load_config("dqn-cartpole-fast", DQN), tmp_path / "r", progress=False)


def test_a_resume_with_kwargs_given_as_tuples_in_python_changes_nothing(tmp_path, capsys):
    """config.toml keeps (2, 3) as [2, 3]: the same settings, so the envs go on mid-episode."""
    over = ["env.id=toy_envs:Tupled", "env.check=false", "train.total_steps=200", "train.initial_collect_steps=50",
            "eval.interval=0", "eval.episodes=1", "train.checkpoint_interval=100", "agent.hidden=[16]",
            "agent.batch_size=8", "env.max_episode_steps=2000"]
    cfg = relayrl.load_config("dqn", over)
    cfg.env.kwargs = {"length": 1000, "dims": (2, 3)}
    relayrl.train(cfg, tmp_path / "run", progress=False)
    capsys.readouterr()
    resumed = relayrl.load_config(str(tmp_path / "run" / "config.toml"), ["train.total_steps=300"])
    result = relayrl.train(resumed, tmp_path / "run", resume=True, progress=False)
    assert "changed: the envs start new episodes" not in capsys.readouterr().err
    assert result.final["train/episodes"] == 0  # the 1,000-step episodes went on


@pytest.mark.parametrize(("steps", "last_eval", "evaluated"), [(130, 0, True), (90, 0, False), (130, 130, False)])
def test_an_interrupted_runs_end_evaluates_only_a_boundary_no_evaluation_covered(steps, last_eval, evaluated):
    """`finish` after an interrupt (evaluate=False): a Ray run's count can cross an interval
    boundary after its loop ended, and its resume would start past it, so that evaluation runs
    there; with no boundary crossed, or one evaluated at this step, none does."""
    from types import SimpleNamespace

    from relayrl.training.lifecycle import finish
    from relayrl.training.triggers import IntervalTrigger, Progress

    calls: list[object] = []
    evaluation = IntervalTrigger(100, lambda p: None)  # its last boundary fired: 0
    report = SimpleNamespace(last_eval={"step": last_eval}, write_scalars=lambda *a: None, run_sps=lambda p: (0.0, 0.0),
                             scalars_step=-1)
    core = SimpleNamespace(check_finite=lambda p, weights: None, evaluation=evaluation, report=report,
                           rd=SimpleNamespace(gone_line=lambda: None),
                           policy_saver=SimpleNamespace(save=lambda p: calls.append("policy")),
                           config=SimpleNamespace(train=SimpleNamespace(checkpoint_interval=0)))
    driver = SimpleNamespace(core=core, evaluate_now=lambda p: calls.append(("evaluate", p.env_steps)),
                             settle_evals=lambda: calls.append("settle"))
    finish(driver, Progress(steps, 7), evaluate=False)
    assert calls == ([("evaluate", steps)] if evaluated else []) + ["settle", "policy"]


def test_an_interrupt_at_the_last_step_before_its_checkpoint_says_which_checkpoint_resumes(tmp_path):
    # A callback's KeyboardInterrupt on the last evaluation row comes before the end's checkpoint:
    # the resume trains again from the one before, which the line names.
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=600"] + DQN[2:]
                              + ["eval.interval=300", "train.checkpoint_interval=250"])

    def interrupt_at_the_last_row(row):
        if row["event"] == "eval" and row["step"] == 600:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt, match=r"^the run stopped at env step 600 with a checkpoint \(env step 500; "
                                                r"the steps after it are trained again\)"):
        relayrl.train(cfg, tmp_path / "r", progress=False, callbacks=[interrupt_at_the_last_row])


def test_ctrl_c_in_the_last_iteration_of_a_run_without_checkpoints_still_evaluates_its_end(tmp_path):
    # no checkpoint a resume could evaluate from: the final evaluation runs, then the interrupt goes on
    cfg = relayrl.load_config("dqn-cartpole-fast", DQN[:1] + ["train.total_steps=600"] + DQN[2:]
                              + ["train.log_interval=100", "eval.interval=400", "train.checkpoint_interval=0"])

    def ctrl_c_at_the_end(row):
        if row["event"] == "log" and row["step"] == 600:
            os.kill(os.getpid(), signal.SIGINT)

    with pytest.raises(KeyboardInterrupt, match=r"^the run stopped at env step 600; its policy and metrics are in"):
        relayrl.train(cfg, tmp_path / "r", progress=False, callbacks=[ctrl_c_at_the_end])
    assert [r["step"] for r in RunDir(tmp_path / "r").read_metrics()][-1] == 600


def test_a_memmap_replay_the_disk_cannot_hold_is_one_line_before_its_files_are_made(tmp_path, monkeypatch):
    """The files are sparse: a full disk killed the run with SIGBUS mid-write, hours in, with no line."""
    from relayrl.training import replay_setup

    real = shutil.disk_usage

    def small(path):  # 1 KiB free: the run's 1,500 CartPole transitions take ~36 KiB
        return real(path)._replace(free=1024)

    monkeypatch.setattr(replay_setup.shutil, "disk_usage", small)
    config = relayrl.load_config("dqn-cartpole-fast", DQN + ["replay.storage=memmap"])
    with pytest.raises(relayrl.UserError, match=r"^replay.storage=memmap: 1,500 transitions of .* take ~0.0 GiB in "
                                                r"'.*replay', whose disk has 0.0 GiB free \(a full disk would kill"):
        relayrl.train(config, tmp_path / "run", progress=False)
    assert not (tmp_path / "run" / "replay").exists()
    monkeypatch.setattr(replay_setup.shutil, "disk_usage", real)
    relayrl.train(config, tmp_path / "run", progress=False)


@pytest.mark.skipif(not os.path.exists("/proc/meminfo"), reason="Linux's MemAvailable")
def test_a_replay_size_whose_bookkeeping_outgrows_memory_is_one_line_before_the_table_is_made(tmp_path):
    """replay.size=3e9 (a typo on a shared server) took 13 GB in the table's constructor, before any
    line or run directory, and went on."""
    from relayrl.training.replay_setup import available_host_memory

    size = available_host_memory() // 50  # 96 bytes a slot: about twice what is available
    config = relayrl.load_config("dqn-cartpole-fast", DQN + [f"replay.size={size}"])
    with pytest.raises(relayrl.UserError, match=rf"^replay.size={size:,} keeps ~.* GiB of host memory for its slots "
                                                r"from the start \(96 bytes each, however few items it holds\), more "
                                                r"than the .* GiB available here: lower replay.size$"):
        relayrl.train(config, tmp_path / "r", progress=False)
    assert not (tmp_path / "r").exists()


def test_history_json_records_each_process_its_software_and_what_a_resume_changed(tmp_path):
    """config.toml said nothing of the torch build, machine or thread count a bit-exact repeat needs,
    and held the settings of the last resume only."""
    import json

    relayrl.train(relayrl.load_config("dqn-cartpole-fast", DQN), tmp_path / "r", progress=False)
    longer = relayrl.load_config(str(tmp_path / "r" / "config.toml"), ["train.total_steps=2000", "agent.lr=0.01"])
    relayrl.train(longer, tmp_path / "r", resume=True, progress=False)
    first, second = json.loads((tmp_path / "r" / "history.json").read_text())
    assert (first["env_step"], second["env_step"]) == (0, 1500) and "changed" not in first
    assert second["changed"] == ["agent.lr: 0.0023 -> 0.01", "train.total_steps: 1500 -> 2000"]
    for entry in (first, second):
        assert entry["versions"]["torch"] == torch.__version__ and entry["versions"]["relayrl"] == relayrl.__version__
        assert entry["torch_threads"] == 1 and entry["cpu"] and entry["platform"]
