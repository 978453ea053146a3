"""The local loop: determinism, checkpoints, resume, and short learning tests."""

import json

import pytest
import torch

import relayrl
from relayrl.errors import CheckpointError, UserError
from relayrl.training.checkpoint import list_checkpoints, load_latest_checkpoint, save_checkpoint
from relayrl.training.run_dir import RunDir

SMALL = ["env.id=CartPole-v1", "train.total_steps=1500", "train.initial_collect_steps=200",
         "eval.interval=500", "eval.episodes=3", "train.checkpoint_interval=500",
         "train.collect_steps=100", "train.gradient_steps=20", "agent.hidden=[64,64]"]


def rows(run_dir):
    return RunDir(run_dir).read_metrics()


def test_same_seed_same_run_on_cpu(tmp_path):
    for name in ("a", "b"):
        relayrl.train(relayrl.load_config("dqn-cartpole-fast", SMALL, seed=4), tmp_path / name, progress=False)
    a, b = rows(tmp_path / "a"), rows(tmp_path / "b")
    drop = ("wall_time_s", "eval_s")
    assert [{k: v for k, v in r.items() if k not in drop} for r in a] == \
           [{k: v for k, v in r.items() if k not in drop} for r in b]
    c = relayrl.train(relayrl.load_config("dqn-cartpole-fast", SMALL, seed=5), tmp_path / "c", progress=False)
    assert rows(c.run_dir)[-1]["losses/loss"] != a[-1]["losses/loss"]


def test_resume_continues_from_the_last_checkpoint(tmp_path):
    first = relayrl.load_config("dqn-cartpole-fast", SMALL[:1] + ["train.total_steps=1000"] + SMALL[2:])
    relayrl.train(first, tmp_path / "r", progress=False)
    ckpt = load_latest_checkpoint(tmp_path / "r" / "checkpoints")
    assert ckpt["env_steps"] == 1000
    # a later crash would have left rows past the checkpoint: resume drops and redoes them
    with open(tmp_path / "r" / "metrics.jsonl", "a") as f:
        f.write(json.dumps({"step": 1200, "average_return": -1}) + "\n")
    longer = relayrl.load_config("dqn-cartpole-fast", SMALL)
    result = relayrl.train(longer, tmp_path / "r", resume=True, progress=False)
    steps = [r["step"] for r in rows(tmp_path / "r")]
    assert steps == [0, 500, 1000, 1500]
    assert result.final["train_step"] > ckpt["agent"]["train_step"]


def test_checkpoints_can_leave_the_replay_out_and_resume_refills_it(tmp_path, capsys):
    no_replay = ["train.checkpoint_replay=false"]
    first = relayrl.load_config("dqn-cartpole-fast", SMALL[:1] + ["train.total_steps=1000"] + SMALL[2:] + no_replay)
    relayrl.train(first, tmp_path / "r", progress=False)
    assert load_latest_checkpoint(tmp_path / "r" / "checkpoints")["replay"] is None
    longer = relayrl.load_config("dqn-cartpole-fast", SMALL + no_replay)
    result = relayrl.train(longer, tmp_path / "r", resume=True, progress=False)
    assert result.final["step"] == 1500
    err = capsys.readouterr().err
    assert "checkpoints leave the replay out" in err and "the replay refills" in err


def test_resume_needs_a_checkpoint(tmp_path):
    cfg = relayrl.load_config("dqn-cartpole-fast", SMALL)
    RunDir(tmp_path / "r").create()
    (tmp_path / "r" / "config.toml").write_text("")
    with pytest.raises(CheckpointError, match=r"no checkpoint .*: start the run again without --resume"):
        relayrl.train(cfg, tmp_path / "r", resume=True, progress=False)


def test_checkpoints_are_atomic_and_fall_back_past_a_corrupt_one(tmp_path, capsys):
    folder = tmp_path / "ck"
    save_checkpoint(folder, 100, {"x": torch.ones(3), "env_steps": 100})
    save_checkpoint(folder, 200, {"x": torch.zeros(3), "env_steps": 200})
    save_checkpoint(folder, 300, {"x": torch.zeros(3), "env_steps": 300})
    assert [p.name for p in list_checkpoints(folder)] == ["ckpt-000000000200.pt", "ckpt-000000000300.pt"]
    (folder / "ckpt-000000000400.pt.tmp").write_bytes(b"partial")  # a write killed midway
    (folder / "ckpt-000000000300.pt").write_bytes(b"garbage")  # a corrupt newest file
    state = load_latest_checkpoint(folder)
    err = capsys.readouterr().err
    assert state["env_steps"] == 200 and err.count("\n") == 1
    assert err.startswith(f"relayrl: checkpoint {folder / 'ckpt-000000000300.pt'} is unreadable (") and \
        err.endswith("); trying an older one\n")
    (folder / "ckpt-000000000200.pt").write_bytes(b"")
    with pytest.raises(CheckpointError, match="every checkpoint .* unreadable: start the run again with --overwrite"):
        load_latest_checkpoint(folder)
    lines = capsys.readouterr().err.splitlines()
    assert lines[0].endswith("; trying an older one") and lines[1].endswith("; no older one is left")
    assert all(len(line) < 300 for line in lines)  # torch's long explanation cut at a word


def _flip_a_bit_of_the_tensor(path, tensor):
    """Flip one bit of `tensor`'s bytes where torch.save stored them in `path` (bit rot)."""
    data = bytearray(path.read_bytes())
    at = data.find(tensor.numpy().tobytes())
    assert at > 0
    data[at + 5] ^= 0x10
    path.write_bytes(bytes(data))


def test_a_checkpoint_whose_bytes_changed_is_passed_over_for_the_one_before(tmp_path, capsys):
    folder = tmp_path / "ck"
    first, second = torch.arange(64.0), torch.arange(64.0) * 3
    save_checkpoint(folder, 100, {"x": first, "env_steps": 100})
    save_checkpoint(folder, 200, {"x": second, "env_steps": 200})
    _flip_a_bit_of_the_tensor(folder / "ckpt-000000000200.pt", second)
    assert torch.load(folder / "ckpt-000000000200.pt")["x"].ne(second).sum() == 1  # torch reads it without a word
    state = load_latest_checkpoint(folder)
    assert state["env_steps"] == 100 and torch.equal(state["x"], first)
    err = capsys.readouterr().err
    assert ("ckpt-000000000200.pt is unreadable (ValueError: its bytes changed after it was written (BadZipFile: "
            "Bad CRC-32") in err
    assert err.endswith("; trying an older one\n")


def test_a_file_written_without_checksums_is_read_unchecked(tmp_path):
    from torch.utils.serialization import config

    folder = tmp_path / "ck"
    saved = config.save.compute_crc32
    config.save.compute_crc32 = False  # each record's CRC stored as 0
    try:
        save_checkpoint(folder, 100, {"x": torch.ones(3), "env_steps": 100})
    finally:
        config.save.compute_crc32 = saved
    assert load_latest_checkpoint(folder)["env_steps"] == 100


@pytest.mark.parametrize("other", [[1, 2], {"weights": 1}])
def test_a_file_that_is_no_checkpoint_under_a_checkpoints_name_is_passed_over(tmp_path, capsys, other):
    folder = tmp_path / "ck"
    save_checkpoint(folder, 100, {"x": torch.ones(3), "env_steps": 100})
    torch.save(other, folder / "ckpt-000000000200.pt")  # another program's file, or a copy put there by hand
    assert load_latest_checkpoint(folder)["env_steps"] == 100
    assert "that is not a relayrl checkpoint); trying an older one" in capsys.readouterr().err


def test_dqn_refuses_continuous_actions(tmp_path):
    with pytest.raises(UserError, match="DQN takes a Discrete action space"):
        relayrl.train(relayrl.load_config("dqn-cartpole-fast", ["env.id=Pendulum-v1"]), tmp_path / "p",
                      progress=False)
    assert not (tmp_path / "p").exists()


@pytest.mark.parametrize("double", [False, True])
def test_dqn_learns_a_bandit(tmp_path, double):
    cfg = relayrl.load_config("dqn-cartpole-fast", [
        "env.id=toy_envs:BetterAction", "train.total_steps=600", "train.initial_collect_steps=100",
        "train.collect_steps=1", "train.gradient_steps=1", "agent.hidden=[64,64]", "agent.lr=1e-3",
        "eval.interval=600", "eval.episodes=20", "agent.epsilon_decay_steps=300", f"agent.double={str(double).lower()}",
        "agent.target_update_period=20"])
    result = relayrl.train(cfg, tmp_path / "b", progress=False)
    assert result.final["average_return"] == 1.0


def test_tutorial_preset_learns_cartpole_quickly(tmp_path):
    """TF-Agents' tutorial settings: at least one evaluation of 150+ within 4,000 iterations."""
    cfg = relayrl.load_config("dqn-cartpole", ["train.total_steps=4100", "train.checkpoint_interval=0"])
    result = relayrl.train(cfg, tmp_path / "t", progress=False)
    best = max(r["average_return"] for r in rows(result.run_dir))
    assert best >= 150, rows(result.run_dir)


def test_rate_limiter_gives_the_configured_gradient_steps(tmp_path):
    # 1,300 collected after 200 initial steps, in iterations of 100: 20 gradient steps each,
    # plus one iteration's worth of Reverb's error buffer, granted once min size is reached.
    cfg = relayrl.load_config("dqn-cartpole-fast", SMALL + ["train.checkpoint_interval=0"])
    result = relayrl.train(cfg, tmp_path / "g", progress=False)
    # The writer's one-step lag: 199 items at step 200, or 200 when an episode ended at step 200
    # (its final row closes the last item at once).
    assert result.final["train_step"] in (13 * 20 + 20 - 1, 13 * 20 + 20)


@pytest.mark.parametrize("num_envs", [1, 7])
def test_update_to_data_ratio_does_not_change_with_num_envs(tmp_path, num_envs):
    # 1 gradient step per collected env step; with 7 envs an iteration collects 7 steps and
    # must be followed by 7 gradient steps, not 1.
    cfg = relayrl.load_config("dqn-cartpole", [f"env.num_envs={num_envs}", "env.id=CartPole-v1",
                                               "train.total_steps=800", "train.initial_collect_steps=100",
                                               "eval.interval=800", "eval.episodes=2", "agent.hidden=[16]",
                                               "train.checkpoint_interval=0", "agent.batch_size=8"])
    result = relayrl.train(cfg, tmp_path / "u", progress=False)
    trained_on = result.final["step"] - 100
    assert abs(result.final["train_step"] - trained_on) <= 2 * num_envs, result.final


@pytest.mark.parametrize("extra", [["replay.sampler='prioritized'", "replay.n_step=3"], ["replay.n_step=2"]])
def test_dqn_learns_a_bandit_with_prioritized_and_n_step_replay(tmp_path, extra):
    cfg = relayrl.load_config("dqn-cartpole-fast", [
        "env.id=toy_envs:BetterAction", "train.total_steps=600", "train.initial_collect_steps=100",
        "train.collect_steps=1", "train.gradient_steps=1", "agent.hidden=[64,64]", "agent.lr=1e-3",
        "eval.interval=600", "eval.episodes=20", "agent.epsilon_decay_steps=300", "agent.target_update_period=20",
        *extra])
    result = relayrl.train(cfg, tmp_path / "b", progress=False)
    assert result.final["average_return"] == 1.0


def test_memmap_replay_run_resumes_from_its_files(tmp_path):
    over = SMALL + ["replay.storage='memmap'"]
    relayrl.train(relayrl.load_config("dqn-cartpole-fast", over + ["train.total_steps=1000"]),
                  tmp_path / "m", progress=False)
    assert (tmp_path / "m" / "replay" / "frame.npy").exists()
    ckpt = load_latest_checkpoint(tmp_path / "m" / "checkpoints")
    assert "memmap" in ckpt["replay"]["storage"]["store"]["columns"]  # the checkpoint refers to the files
    result = relayrl.train(relayrl.load_config("dqn-cartpole-fast", over), tmp_path / "m", resume=True,
                           progress=False)
    assert result.final["step"] == 1500


@pytest.mark.parametrize("setting, message", [
    ("replay.sampler='sumtree'", "replay.sampler='sumtree' is not valid; valid: uniform, prioritized"),
    ("replay.error_buffer=10.0", "replay.error_buffer=10 is too small"),
])
def test_bad_replay_settings_fail_before_anything_is_written(tmp_path, setting, message):
    with pytest.raises(UserError, match=message.replace("(", r"\(")):
        relayrl.train(relayrl.load_config("dqn-cartpole-fast", SMALL + [setting]), tmp_path / "x", progress=False)
    assert not (tmp_path / "x").exists()


def test_the_progress_bar_moves_between_log_rows(tmp_path, monkeypatch):
    """A slow env's log rows are far apart: in a terminal the bar still moves each second."""
    import io

    import tqdm

    moves: list[int] = []

    class TerminalBar(tqdm.tqdm):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **{**kwargs, "disable": False, "file": io.StringIO()})

        def update(self, n=1):
            moves.append(self.n + n)
            return super().update(n)

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr(tqdm, "tqdm", TerminalBar)
    monkeypatch.setattr("sys.stderr", Terminal())
    over = ["env.id=toy_envs:Sleepy", "env.check=false", "train.total_steps=1400", "train.log_interval=100000",
            "eval.interval=0", "eval.episodes=1", "train.initial_collect_steps=100", "train.checkpoint_interval=0"]
    relayrl.train(relayrl.load_config("dqn-cartpole", over), tmp_path / "run")  # 2 ms a step: ~3 s
    assert len([m for m in moves if 0 < m < 1400]) >= 1, moves


@pytest.mark.parametrize("keep, expected", [(2, [400, 500]), (0, [100, 200, 300, 400, 500]), (1, [500])])
def test_checkpoint_keep_says_how_many_of_the_newest_stay(tmp_path, keep, expected):
    cfg = relayrl.load_config("dqn-cartpole-fast", ["train.total_steps=500", "train.initial_collect_steps=50",
                                                    "train.collect_steps=50", "train.checkpoint_interval=100",
                                                    f"train.checkpoint_keep={keep}",
                                                    "eval.interval=0", "eval.episodes=1", "train.torch_threads=1"])
    relayrl.train(cfg, tmp_path / "r", progress=False)
    assert [int(p.stem.split("-")[1]) for p in list_checkpoints(tmp_path / "r" / "checkpoints")] == expected


def test_the_console_says_once_what_an_evaluation_line_holds(tmp_path, capsys):
    relayrl.train(relayrl.load_config("dqn-cartpole-fast", SMALL), tmp_path / "r",
                  progress=False)
    err = capsys.readouterr().err
    legend = "evaluations: mean return and length of 3 episodes of the policy acting without exploration"
    assert err.count(legend) == 1 and err.index(legend) < err.index("eval return"), err
