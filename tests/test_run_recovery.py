"""Runs that fail are recoverable: nothing blocks a retry, --overwrite, --resume checks what it
resumes, total_steps is a hard end, and a bad --run-dir is one line."""

import json
import os
import shutil
import subprocess
import sys
import time

import pytest

from relayrl.cli import main
from relayrl.dispatch import train
from relayrl.errors import UserError
from relayrl.export import load_policy
from relayrl.presets import load_config
from relayrl.training.checkpoint import list_checkpoints
from relayrl.training.run_dir import RunDir

TINY = ["train.total_steps=60", "train.initial_collect_steps=20", "eval.interval=30", "eval.episodes=2",
        "train.checkpoint_interval=30", "train.policy_save_interval=0", "agent.batch_size=8",
        "env.id=toy_envs:Countdown", "env.check=false"]


class Result:
    def __init__(self, returncode, stderr):
        self.returncode, self.stderr = returncode, stderr


@pytest.fixture
def cli(capfd):
    """`relayrl ARGS` in this process (subprocesses would spend most of the time importing torch)."""

    def call(args, env=None):
        capfd.readouterr()
        code = main(args)
        return Result(code, capfd.readouterr().err)

    return call


def sets(overrides):
    return [a for o in overrides for a in ("--set", o)]


def test_a_run_that_fails_to_build_writes_nothing(tmp_path):
    with pytest.raises(UserError):
        train(load_config("dqn-cartpole", TINY + ["env.id=toy_envs:NotAnEnv"]), tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()


def test_a_run_that_failed_before_its_first_checkpoint_is_taken_over(tmp_path, cli):
    run = tmp_path / "run"
    broken = TINY + ["env.id=toy_envs:Broken", "train.checkpoint_interval=1000"]
    with pytest.raises(ValueError, match="lost its state"):  # the env's own error, as from a simulator
        cli(["train", "dqn-cartpole", "--run-dir", str(run), "--no-progress", *sets(broken)])
    assert (run / "config.toml").exists() and not list_checkpoints(run / "checkpoints")
    r = cli(["train", "dqn-cartpole", "--run-dir", str(run), "--no-progress", *sets(TINY)])
    assert r.returncode == 0, r.stderr
    assert "stopped before its first checkpoint: starting over in it" in r.stderr
    assert "toy_envs:Countdown" in (run / "config.toml").read_text()
    assert [row["step"] for row in RunDir(run).read_metrics()] == [0, 30, 60]


def test_each_checkpoint_comes_after_the_metrics_rows_before_it_are_on_disk(tmp_path, monkeypatch):
    """A node's crash keeps what was fsynced: a checkpoint that outlived the rows before it would
    resume past a gap in metrics.jsonl without a word."""
    from relayrl.training import checkpoint
    from relayrl.training.run_dir import MetricsLog

    order: list[str] = []
    sync, save = MetricsLog.sync, checkpoint.save_checkpoint
    monkeypatch.setattr(MetricsLog, "sync", lambda self: (order.append("sync"), sync(self))[1])
    monkeypatch.setattr(checkpoint, "save_checkpoint", lambda *a, **k: (order.append("checkpoint"), save(*a, **k))[1])
    train(load_config("dqn-cartpole", TINY + ["train.checkpoint_interval=30"]), tmp_path / "run", progress=False)
    assert order.count("checkpoint") >= 2
    assert all(order[i - 1] == "sync" for i, what in enumerate(order) if what == "checkpoint")


def test_metrics_lines_that_are_no_row_of_a_run_are_passed_over(tmp_path):
    (tmp_path / "config.toml").write_text("")
    (tmp_path / "metrics.jsonl").write_bytes(b'{"step": 0, "average_return": 9.0}\n'
                                             b'\xff\xfe not text\n'  # bytes a crash or a disk left there
                                             b'[1, 2]\n{"step": "late"}\n"a note"\n'  # lines added by hand
                                             b'{"step": 30, "average_return": 12.0}\n{"step": 6')
    assert [row["step"] for row in RunDir(tmp_path).read_metrics()] == [0, 30]
    assert RunDir(tmp_path).truncate_metrics(10) == ([{"step": 0, "average_return": 9.0}], 2)  # 2 lines not JSON


def test_a_resume_says_when_metrics_jsonl_held_a_line_cut_short(tmp_path, capsys):
    run = tmp_path / "run"
    c = load_config("dqn-cartpole", TINY)
    train(c, run, progress=False)
    text = (run / "metrics.jsonl").read_text()
    (run / "metrics.jsonl").write_text(text[:-40])  # the last row cut short, as a full disk leaves it
    capsys.readouterr()
    train(load_config(str(run / "config.toml"), ["train.total_steps=90"]), run, resume=True, progress=False)
    assert "metrics.jsonl held 1 line cut short (a crash or a full disk while it was written), now left out: the " \
           "evaluation rows written there are lost" in capsys.readouterr().err
    assert [row["step"] for row in RunDir(run).read_metrics()] == [0, 30, 90]


def test_a_finished_runs_lost_last_row_is_evaluated_again_as_it_was(tmp_path):
    """The final checkpoint is written after the final evaluation counted its seed index: the
    rebuilt row took the next index and differed from the one lost (357.8 -> 348.5)."""
    run = tmp_path / "run"
    train(load_config("dqn-cartpole", TINY + ["env.id=CartPole-v1"]), run, progress=False)  # returns vary by seed
    rows = (run / "metrics.jsonl").read_text().splitlines(keepends=True)
    (run / "metrics.jsonl").write_text("".join(rows[:-1]) + rows[-1][:20])
    train(None, run, resume=True, progress=False)
    drop = ("wall_time_s", "eval_s")
    again = [{k: v for k, v in r.items() if k not in drop} for r in RunDir(run).read_metrics()]
    assert again == [{k: v for k, v in json.loads(r).items() if k not in drop} for r in rows]


@pytest.mark.parametrize("lost", ["deleted", "emptied"])
def test_a_resume_says_when_metrics_jsonl_lost_its_rows(tmp_path, capsys, lost):
    """A metrics.jsonl deleted before a resume lost the run's history without a word."""
    run = tmp_path / "run"
    train(load_config("dqn-cartpole", TINY), run, progress=False)
    (run / "metrics.jsonl").unlink() if lost == "deleted" else (run / "metrics.jsonl").write_text("")
    capsys.readouterr()
    train(load_config(str(run / "config.toml"), ["train.total_steps=90"]), run, resume=True, progress=False)
    assert "metrics.jsonl held no row (deleted or emptied?): the evaluation rows before env step 60 are lost" \
        in capsys.readouterr().err


def test_a_run_with_a_checkpoint_is_kept_unless_overwrite(tmp_path, cli):
    run = tmp_path / "run"
    train(load_config("dqn-cartpole", TINY), run, progress=False)
    before = (run / "metrics.jsonl").read_text()
    r = cli(["train", "dqn-cartpole", "--run-dir", str(run), *sets(TINY)])
    assert r.returncode == 2 and "already holds a run" in r.stderr and "--overwrite" in r.stderr
    assert (run / "metrics.jsonl").read_text() == before
    r = cli(["train", "dqn-cartpole", "--run-dir", str(run), "--no-progress", "--overwrite",
             *sets(TINY + ["train.total_steps=40"])])
    assert r.returncode == 0, r.stderr
    assert "--overwrite: replacing the run" in r.stderr
    assert RunDir(run).read_metrics()[-1]["step"] == 40
    assert [p.name for p in list_checkpoints(run / "checkpoints")] == ["ckpt-000000000030.pt", "ckpt-000000000040.pt"]


def test_a_finished_run_without_checkpoints_is_kept(tmp_path):
    run = tmp_path / "run"
    train(load_config("dqn-cartpole", TINY + ["train.checkpoint_interval=0"]), run, progress=False)
    with pytest.raises(UserError, match=r"already holds a run \(finished, with no checkpoint to resume from\); "
                                        r"pass --overwrite") as e:
        train(load_config("dqn-cartpole", TINY), run, progress=False)
    assert "--resume" not in str(e.value)
    train(load_config("dqn-cartpole", TINY + ["train.total_steps=30"]), run, progress=False, overwrite=True)
    assert RunDir(run).read_metrics()[-1]["step"] == 30


def test_overwrite_refuses_a_folder_that_is_not_a_run(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(UserError, match="is not a relayrl run directory"):
        train(load_config("dqn-cartpole", TINY), tmp_path, progress=False, overwrite=True)
    assert (tmp_path / "notes.txt").read_text() == "mine"


def test_a_new_run_in_a_folder_of_other_files_says_so_and_leaves_them(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    (tmp_path / "policy").mkdir()
    (tmp_path / "policy" / "mine.txt").write_text("mine too")
    train(load_config("dqn-cartpole", TINY), tmp_path, progress=False)
    assert f"run directory {str(tmp_path)!r} holds other files: the run is written beside them" in \
        capsys.readouterr().err
    assert (tmp_path / "notes.txt").read_text() == "mine" and (tmp_path / "policy" / "mine.txt").exists()
    train(load_config("dqn-cartpole", TINY + ["train.checkpoint_interval=0"]), tmp_path / "empty", progress=False)
    assert "holds other files" not in capsys.readouterr().err  # an empty or new folder: nothing to say


@pytest.mark.parametrize("args, fragment", [
    (["sac-pendulum"], "algo='sac' but the run in"),
    (["dqn-cartpole", "--set", "env.id=Acrobot-v1"], "env.id='Acrobot-v1' but the run in"),
    (["--set", "env.id=Acrobot-v1"], "; resume with the run's own config.toml: leave out PRESET|CONFIG.toml and "
                                     "--set env.id"),
])
def test_resume_with_another_algorithm_or_env_is_one_line(tmp_path, cli, args, fragment):
    run = tmp_path / "run"
    train(load_config("dqn-cartpole", TINY), run, progress=False)
    before = (run / "metrics.jsonl").read_text()
    r = cli(["train", *args, "--run-dir", str(run), "--resume"])
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert fragment in line
    assert (run / "metrics.jsonl").read_text() == before
    # The run's own preset is accepted, and the run's config.toml is what resumes.
    r = cli(["train", "dqn-cartpole", "--run-dir", str(run), "--resume", "--no-progress",
             "--set", "env.id=toy_envs:Countdown", "--set", "train.total_steps=90"])
    assert r.returncode == 0, r.stderr
    assert RunDir(run).read_metrics()[-1]["step"] == 90


def test_resume_naming_the_runs_preset_checks_the_set_against_the_runs_own_config(tmp_path, cli):
    # The run's rollout is 128 env steps where ppo's default is 2,048: a new total of 384 is valid
    # for the run, and only the run's config.toml decides that.
    run = tmp_path / "run"
    tiny_ppo = ["env.id=toy_envs:Countdown", "train.collect_steps=128", "train.total_steps=256", "eval.episodes=1"]
    assert cli(["train", "ppo", "--run-dir", str(run), "--no-progress", *sets(tiny_ppo)]).returncode == 0
    r = cli(["train", "ppo", "--run-dir", str(run), "--resume", "--no-progress", "--set", "env.id=toy_envs:Countdown",
             "--set", "train.total_steps=384"])
    assert r.returncode == 0, r.stderr
    assert RunDir(run).read_metrics()[-1]["step"] == 384
    r = cli(["train", "ppo", "--run-dir", str(run), "--resume", "--set", "env.id=CartPole-v1"])
    assert r.returncode == 2 and "env.id='CartPole-v1' but the run in" in r.stderr
    r = cli(["train", "ppo", "--run-dir", str(run), "--resume", "--set", "env={id='CartPole-v1'}"])  # all of [env]
    assert r.returncode == 2 and "env is a section; set its keys one by one, e.g. --set env.id=..." in r.stderr


def test_total_steps_below_initial_collect_steps_is_honoured(tmp_path):
    result = train(load_config("dqn-cartpole", TINY + ["train.total_steps=25", "train.initial_collect_steps=50"]),
                   tmp_path / "run", progress=False)
    assert result.final["step"] == 25 and result.final["train_step"] == 0


def test_interrupt_before_the_first_checkpoint_does_not_offer_resume(tmp_path, cli_env):
    run = tmp_path / "run"
    slow = TINY + ["env.id=toy_envs:Sleepy", "train.total_steps=100000", "train.checkpoint_interval=100000"]
    p = subprocess.Popen([sys.executable, "-m", "relayrl.cli", "train", "dqn-cartpole", "--run-dir", str(run),
                          "--no-progress", *sets(slow)], env=cli_env, stderr=subprocess.PIPE, text=True)
    while not (run / "metrics.jsonl").exists() and p.poll() is None:
        time.sleep(0.02)
    p.send_signal(2)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    assert "interrupted before the first checkpoint: nothing to resume" in err and "--resume" not in err


def test_a_run_that_trained_but_stopped_before_its_first_checkpoint_is_kept(tmp_path, cli):
    """Only a run that stopped before training is taken over: one that trained keeps its
    policy and metrics until --overwrite."""
    run = tmp_path / "run"
    cfg = load_config("dqn-cartpole", TINY + ["train.total_steps=200", "train.checkpoint_interval=0",
                                              "train.log_interval=50"])
    assert train(cfg, run, progress=False, callbacks=[lambda row: row["step"] < 100]).stopped_early
    assert not list((run / "checkpoints").glob("*")) and RunDir(run).trained_to() == 100
    r = cli(["train", "dqn-cartpole", "--run-dir", str(run), "--no-progress", *sets(TINY)])
    assert r.returncode == 2 and "Traceback" not in r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert "stopped at env step 100, before its first checkpoint" in line and "--overwrite" in line
    assert load_policy(run).env_steps == 100 and RunDir(run).trained_to() == 100
    from relayrl.cli import _interrupted_line, build_parser

    args = build_parser().parse_args(["train", "dqn", "--run-dir", str(run)])
    assert "the policy and metrics so far stay in" in _interrupted_line("interrupted", args)
    r = cli(["train", "dqn-cartpole", "--run-dir", str(run), "--no-progress", "--overwrite", *sets(TINY)])
    assert r.returncode == 0, r.stderr


def test_run_dir_bad_places_are_one_line_and_missing_parents_are_made(tmp_path, cli):
    (tmp_path / "file").write_text("keep")
    for run_dir, fragment in [(tmp_path / "file", "is a file, not a directory"),
                              (tmp_path / "file" / "run", "is a file, not a directory")]:
        r = cli(["train", "dqn-cartpole", "--run-dir", str(run_dir)])
        assert r.returncode == 2 and "Traceback" not in r.stderr
        (line,) = r.stderr.strip().splitlines()
        assert fragment in line
    assert (tmp_path / "file").read_text() == "keep"
    r = cli(["train", "dqn-cartpole", "--run-dir", str(tmp_path / "a" / "b" / "run"), "--no-progress",
             *sets(TINY)])
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "a" / "b" / "run" / "config.toml").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write anywhere")
def test_run_dir_in_an_unwritable_folder_is_one_line(tmp_path, cli):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        r = cli(["train", "dqn-cartpole", "--run-dir", str(locked / "run")])
    finally:
        locked.chmod(0o700)
    assert r.returncode == 2 and "no permission to write in" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("folder", ["tb", "checkpoints", "policy"])
def test_a_run_directory_with_a_read_only_folder_is_one_line_before_the_run(tmp_path, monkeypatch, folder):
    run = tmp_path / "run"
    (run / folder).mkdir(parents=True)
    access = os.access  # as a read-only mount answers, to root too (a chmod would not stop root)
    monkeypatch.setattr(os, "access", lambda path, mode, **kw: os.path.basename(path) != folder and
                        access(path, mode, **kw))
    with pytest.raises(UserError, match=rf"no permission to write in '.*run/{folder}': make it writable"):
        train(load_config("dqn-cartpole", TINY), run, progress=False)
    assert [p.name for p in run.iterdir()] == [folder] and not any((run / folder).iterdir())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses /proc")
def test_run_dir_that_cannot_be_created_is_one_line(cli):
    """/proc refuses new folders even to root."""
    r = cli(["train", "dqn-cartpole", "--run-dir", "/proc/relayrl-nope/run", "--no-progress", *sets(TINY)])
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "cannot be created" in r.stderr.strip().splitlines()[-1]


def test_a_run_running_in_a_directory_is_never_taken_over_or_resumed_under_it(tmp_path):
    import fcntl

    run = tmp_path / "busy"
    run.mkdir()
    (run / "config.toml").write_text('algo = "dqn"\n')
    (run / "metrics.jsonl").write_text('{"step": 0}\n')  # no checkpoint: would be taken over
    with open(run / ".lock", "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)  # as the running run's process holds it
        for kwargs in ({}, {"overwrite": True}, {"resume": True}):
            with pytest.raises(UserError, match="a run is running in"):
                train(load_config("dqn-cartpole-fast", TINY), run, progress=False, **kwargs)
    assert (run / "metrics.jsonl").read_text() == '{"step": 0}\n'
    train(load_config("dqn-cartpole-fast", TINY), run, progress=False)  # released: taken over


def test_resume_keeps_the_runs_seed(tmp_path):
    train(load_config("dqn-cartpole-fast", TINY, seed=1), tmp_path / "r", progress=False)
    longer = TINY + ["train.total_steps=90"]
    with pytest.raises(UserError, match="a resumed run keeps its seed"):
        train(load_config("dqn-cartpole-fast", longer, seed=2), tmp_path / "r", resume=True, progress=False)
    assert train(load_config("dqn-cartpole-fast", longer, seed=1), tmp_path / "r", resume=True,
                 progress=False).final["step"] == 90


def test_overwriting_a_memmap_run_keeps_the_new_runs_replay_files(tmp_path, capsys):
    memmap = TINY + ["replay.storage='memmap'"]
    train(load_config("dqn-cartpole-fast", memmap), tmp_path / "m", progress=False)
    train(load_config("dqn-cartpole-fast", memmap), tmp_path / "m", progress=False, overwrite=True)
    assert any((tmp_path / "m" / "replay").iterdir())
    capsys.readouterr()
    train(load_config("dqn-cartpole-fast", memmap + ["train.total_steps=90"]), tmp_path / "m", resume=True,
          progress=False)
    assert "replay files were overwritten" not in capsys.readouterr().err


def test_an_env_error_mid_run_says_what_is_kept_and_a_fixed_env_resumes(tmp_path, capfd):
    """The env's own exception propagates (it is the user's to read), ending with what the run
    keeps and how it goes on: a checkpoint at the step it reached, without the envs' state; a
    resume trains on from there to the end with new episodes."""
    run = tmp_path / "run"
    flaky = TINY + ["env.id=toy_envs:BrokenAt", "env.kwargs={at = 45}", "train.checkpoint_interval=20"]
    with pytest.raises(RuntimeError, match="simulator lost connection") as caught:
        train(load_config("dqn-cartpole", flaky), run, progress=False)
    note = " ".join(getattr(caught.value, "__notes__", []))
    assert "the run stopped at env step 44" in note and "checkpoint (env step 44)" in note
    assert ("the env failed at env step 44: writing a checkpoint there, without the envs' state (a resume starts "
            "new episodes)") in capfd.readouterr().err
    assert [p.name for p in list_checkpoints(run / "checkpoints")] == ["ckpt-000000000040.pt", "ckpt-000000000044.pt"]
    # which copy and which env step raised it: the env's traceback says neither
    assert "relayrl: raised by step() of env copy 0" in note and "relayrl: raised at env step 45 of training" in note
    assert f"relayrl train --run-dir {run} --resume" in note
    # new envs count their steps from 0 again: this one fails again only past the run's end
    assert train(None, run, resume=True, progress=False).final["step"] == 60
    err = capfd.readouterr().err
    assert "resumed from env step 44" in err
    assert ("this checkpoint was written where the env failed, without the envs' state: the resumed run starts new "
            "episodes") in err


@pytest.mark.parametrize("preset, over", [
    ("ppo-cartpole", ["train.collect_steps=16", "agent.batch_size=8", "env.num_envs=1",
                      "train.initial_collect_steps=0"]),  # the rollout gathered so far is its writer's alone
    ("dqn-cartpole", ["train.initial_collect_steps=50"]),  # inside the random warm-up: a resume would not finish it
])
def test_no_checkpoint_is_written_where_the_env_failed_if_a_resume_would_not_go_on_from_it(tmp_path, preset, over):
    broken = ["env.id=toy_envs:BrokenAt", "env.kwargs={at = 45}", "train.checkpoint_interval=1000"]
    c = load_config(preset, TINY + broken + over)
    with pytest.raises(RuntimeError, match="simulator lost connection"):
        train(c, tmp_path / "run", progress=False)
    assert not list_checkpoints(tmp_path / "run" / "checkpoints")


def test_a_failure_outside_the_env_writes_no_checkpoint_of_its_own(tmp_path, monkeypatch):
    """An update that raised may have left the weights half-changed: the last checkpoint stays."""
    from relayrl.agents.dqn.agent import DQNAgent

    def broken(self, *args, **kwargs):
        raise RuntimeError("an update's bug")

    monkeypatch.setattr(DQNAgent, "train", broken)
    with pytest.raises(RuntimeError, match="an update's bug"):
        train(load_config("dqn-cartpole", TINY + ["train.checkpoint_interval=20"]), tmp_path / "run", progress=False)
    assert not list_checkpoints(tmp_path / "run" / "checkpoints")


def test_an_evaluation_envs_error_says_it_came_from_an_evaluation(tmp_path):
    """The training envs are fine (at = 0: never); the evaluation envs' third step raises."""
    broken = TINY + ["env.id=toy_envs:BrokenAt", "env.kwargs={at = 0}", "eval.env_kwargs={at = 3}"]
    with pytest.raises(RuntimeError, match="simulator lost connection") as caught:
        train(load_config("dqn-cartpole", broken), tmp_path / "run", progress=False)
    note = " ".join(getattr(caught.value, "__notes__", []))
    assert "relayrl: raised by step() of env copy 0" in note and "relayrl: raised in an evaluation episode" in note
    assert "of training" not in note


def test_an_evaluation_envs_reset_error_says_it_came_from_an_evaluation(tmp_path):
    """The evaluation envs' third reset is the second evaluation's first (each of the two copies
    reset at the start of the first and once when its episode ended)."""
    broken = TINY + ["env.id=toy_envs:ResetBreaksAt", "env.kwargs={at = 0}", "eval.env_kwargs={at = 3}"]
    with pytest.raises(RuntimeError, match="simulator refused to reset") as caught:
        train(load_config("dqn-cartpole", broken), tmp_path / "run", progress=False)
    note = " ".join(getattr(caught.value, "__notes__", []))
    assert "relayrl: raised by reset() of env copy 0" in note and "relayrl: raised in an evaluation episode" in note


@pytest.mark.parametrize("vectorization, late, shape", [
    ("sync", "wider", "(3,)"), ("async", "wider", "(3,)"),
    ("sync", "scalar", "()"), ("sync", "row", "(1, 2)"),  # ones NumPy would broadcast into the row without a word
])
def test_an_observation_that_stops_fitting_mid_run_is_one_line(tmp_path, cli, vectorization, late, shape):
    run = tmp_path / "run"
    over = TINY + ["env.id=toy_envs:ShapeShifts", f"env.kwargs={{at = 45, late = '{late}'}}",
                   f"env.vectorization={vectorization}"]
    r = cli(["train", "dqn-cartpole", "--run-dir", str(run), "--no-progress", *sets(over)])
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert f"the observation from step() of env copy 0 has shape {shape} but observation_space is Box(" in r.stderr


@pytest.mark.parametrize("vectorization", ["sync", "async"])
def test_a_dict_observation_that_loses_a_key_mid_run_names_the_copy_and_method(tmp_path, cli, vectorization):
    over = TINY + ["env.id=toy_envs:KeyLost", "env.kwargs={at = 45}", f"env.vectorization={vectorization}"]
    r = cli(["train", "dqn-cartpole", "--run-dir", str(tmp_path / "run"), "--no-progress", *sets(over)])
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert ("relayrl: error: the observation from step() of env copy 0 is ['x']; observation_space is a Dict with "
            "keys ['x', 'y']; the run stopped at env step 44") in r.stderr, r.stderr


@pytest.mark.parametrize("vectorization", ["sync", "async"])
@pytest.mark.parametrize("late, entry, fragment", [
    ("fraction", "", "step() of env copy 0 holds float32 values that are not whole numbers (such as "),
    ("negative", "", "step() of env copy 0 holds -"),
    ("list", "", "step() of env copy 0 holds 300, outside uint8's range"),
    ("fraction", "frame", "step() of env copy 0['frame'] holds float32 values that are not whole numbers"),
    ("negative", "frame", "step() of env copy 0['frame'] holds -"),
], ids=["fraction", "negative", "list", "dict-fraction", "dict-negative"])
def test_an_observation_a_uint8_space_would_change_mid_run_is_one_line(tmp_path, cli, vectorization, late, entry,
                                                                        fragment):
    run = tmp_path / "run"
    over = TINY + ["env.id=toy_envs:CastsAt", f"env.kwargs={{at = 45, late = '{late}', entry = '{entry}'}}",
                   f"env.vectorization={vectorization}"]
    r = cli(["train", "dqn-cartpole", "--run-dir", str(run), "--no-progress", *sets(over)])
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert f"the observation from {fragment}" in r.stderr and "Box(0, 255, (2,), uint8)" in r.stderr
    assert RunDir(run).read_metrics()  # the run's rows before it stay


@pytest.mark.parametrize("entry", ["", "frame"])
def test_int64_observations_a_uint8_space_keeps_train_as_they_are(tmp_path, cli, entry):
    r = cli(["train", "dqn-cartpole", "--run-dir", str(tmp_path / "run"), "--no-progress",
             *sets(TINY + ["env.id=toy_envs:CastsAt", f"env.kwargs={{entry = '{entry}'}}"])])
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("blocker, kind", [("checkpoints", "file"), ("config.toml", "directory")])
def test_a_run_directory_whose_entries_are_blocked_is_one_line(tmp_path, cli, blocker, kind):
    run = tmp_path / "run"
    run.mkdir()
    (run / blocker).mkdir() if kind == "directory" else (run / blocker).write_text("mine")
    for extra in ([], ["--overwrite"]):
        r = cli(["train", "dqn-cartpole", "--run-dir", str(run), "--no-progress", *extra, *sets(TINY)])
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert f"'{blocker}' there is a {kind}, where a run keeps its" in r.stderr
    assert (run / blocker).exists()


def test_an_env_whose_close_raises_after_the_run_finished_leaves_a_finished_run(tmp_path, cli):
    """Every file is written when the envs are closed: the env's failing close() is one line, the
    run's result stands, and the evaluation env is closed too."""
    import toy_envs

    toy_envs.CloseRaises.closed = 0
    r = cli(["train", "dqn-cartpole", "--run-dir", str(tmp_path / "run"), "--no-progress",
             *sets(TINY + ["env.id=toy_envs:CloseRaises", "env.num_envs=2"])])
    assert r.returncode == 0, r.stderr
    assert ("the run finished and its files are written; then closing its envs raised RuntimeError: the "
            "simulator's socket was already gone") in r.stderr
    assert toy_envs.CloseRaises.closed >= 4  # both training copies, then the evaluation env's
    assert load_policy(tmp_path / "run") is not None


def test_a_crash_leaves_no_policy_older_than_the_last_checkpoint(tmp_path):
    """policy_save_interval 0 (no periodic saves): the checkpoints at step 30 and where the env
    failed (44) saved the policy with them."""
    run = tmp_path / "run"
    c = load_config("dqn-cartpole", TINY + ["env.id=toy_envs:BrokenAt", "env.kwargs.at=45", "eval.interval=0"])
    with pytest.raises(RuntimeError, match="simulator lost connection"):
        train(c, run, progress=False)
    assert [int(p.stem.split("-")[1]) for p in list_checkpoints(run / "checkpoints")] == [30, 44]
    assert load_policy(run).env_steps == 44


def test_a_run_keeps_the_policy_of_its_best_evaluation_as_it_was_evaluated(tmp_path):
    import torch

    config = load_config("dqn-cartpole-fast", ["train.total_steps=4000", "eval.interval=1000", "eval.episodes=2",
                                               "train.checkpoint_interval=0"], seed=0)
    train(config, tmp_path / "run", progress=False)
    rows = RunDir(tmp_path / "run").read_metrics()
    top = max(rows, key=lambda row: row["average_return"])  # the first of equal ones
    saved = torch.load(tmp_path / "run" / "policy" / "best.pt", weights_only=True)
    assert (saved["env_steps"], saved["average_return"]) == (top["step"], top["average_return"])
    policy = load_policy(tmp_path / "run" / "policy" / "best.pt")
    assert policy.env_steps == top["step"]
    config.eval.keep_best = False
    train(config, tmp_path / "off", progress=False)
    assert not (tmp_path / "off" / "policy" / "best.pt").exists()


@pytest.mark.parametrize("then", ["deleted", "replaced"])
def test_a_run_directory_deleted_mid_run_stops_the_run_writing_nothing_more(tmp_path, capfd, then):
    """A user's `rm -rf` of a run under way (a callback here, at the first evaluation after step 0;
    "replaced": another run started in the same place since): the run stops in one line and
    recreates nothing (its checkpoint and policy writes made the folders again)."""
    run = tmp_path / "run"

    def remove(row):
        if row.get("step") == 30:
            shutil.rmtree(run)
            if then == "replaced":
                run.mkdir()
                (run / ".lock").touch()
                (run / "config.toml").write_text("# another run's\n")

    with pytest.raises(UserError) as caught:
        train(load_config("dqn-cartpole", TINY), run, progress=False, callbacks=[remove])
    assert str(caught.value) == (f"the run directory {str(run)!r} was deleted (or replaced by another run's) while "
                                 "this run trained: nothing more is written there; the run stopped at env step 30")
    if then == "deleted":
        assert not run.exists()
    else:  # the other run's files as it left them
        assert sorted(p.name for p in run.iterdir()) == [".lock", "config.toml"]
        assert (run / "config.toml").read_text() == "# another run's\n"
    assert "Traceback" not in capfd.readouterr().err


def test_a_run_directory_too_long_for_the_files_a_run_writes_is_one_line_before_the_run(tmp_path):
    """Near PATH_MAX the directory could be made but TensorBoard's log file could not: two
    tracebacks (its writer thread's too) and a half-made run directory."""
    limit = os.pathconf(tmp_path, "PC_PATH_MAX")
    run = tmp_path / "d"
    while len(str(run)) < limit - 40:
        run = run / ("d" * min(200, limit - 40 - len(str(run))))
    with pytest.raises(UserError, match=rf"^--run-dir is {len(str(run)):,} characters long: the files a run writes "
                                        rf"in it .* would pass the system's limit of {limit:,} characters for a path"):
        train(load_config("dqn-cartpole", TINY), run, progress=False)
    assert not (tmp_path / "d").exists()
