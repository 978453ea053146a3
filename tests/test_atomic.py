"""Files written atomically leave the old file or the new one, and no temp file, on failure;
what a failed build made is closed."""

from __future__ import annotations

import signal

import gymnasium as gym
import pytest
import torch

from relayrl import atomic
from relayrl.envs.gym import GymBatchEnv


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temp_file(tmp_path):
    path = tmp_path / "f.json"
    atomic.write_text(path, "old")

    def fail(f):
        f.write(b"half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        atomic.write_with(path, fail)
    assert path.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.json"]


def test_a_full_disk_is_one_line_that_says_what_is_kept(tmp_path):
    import errno

    from relayrl.errors import UserError

    path = tmp_path / "ckpt.pt"
    atomic.write_text(path, "old")

    def full(f):
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError:  # as torch's zip writer reports it: a RuntimeError raised while handling the OSError
            raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 64 vs 0") from None

    with pytest.raises(UserError, match=r"^cannot write '.*ckpt.pt': No space left on device \(its previous version"):
        atomic.write_with(path, full)
    assert path.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.pt"]


@pytest.mark.parametrize("cause, fix", [
    ("EFBIG", r"File too large \(its previous version, if any, is kept\): raise the file-size limit \(ulimit -f\)$"),
    (None, r"the write stopped short \(torch: .*unexpected pos 64 vs 0; its previous version, if any, is kept\): "
           r"the disk is full or a file-size limit \(ulimit -f\) was reached$"),  # torch's, its OSError lost
])
def test_a_file_size_limit_is_one_line_that_says_what_is_kept(cause, fix, tmp_path):
    import errno

    from relayrl.errors import UserError

    path = tmp_path / "ckpt.pt"
    atomic.write_text(path, "old")

    def cut(f):
        if cause is not None:
            raise OSError(getattr(errno, cause), "File too large")
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 64 vs 0")

    with pytest.raises(UserError, match=r"^cannot write '.*ckpt.pt': " + fix):
        atomic.write_with(path, cut)
    assert path.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.pt"]


def test_an_unwritable_line_says_what_to_do_for_each_cause(tmp_path):
    import errno

    full = atomic.unwritable(RuntimeError("tensorboard"))
    assert full is None
    for code, fix in ((errno.ENOSPC, "free some space"), (errno.EFBIG, "raise the file-size limit (ulimit -f)"),
                      (errno.EACCES, f"make {str(tmp_path / 'tb')!r} writable")):
        error = OSError(code, "refused", str(tmp_path / "tb" / "events"))
        assert atomic.unwritable(error) is error
        assert atomic.unwritable_line(error, tmp_path).endswith(f": refused: {fix}")


@pytest.mark.parametrize("code, text", [("EROFS", "Read-only file system"), ("EACCES", "Permission denied")])
def test_a_folder_that_cannot_be_written_is_one_line_that_says_what_is_kept(code, text, tmp_path, monkeypatch):
    import errno

    from relayrl.errors import UserError

    path = tmp_path / "checkpoints" / "ckpt.pt"
    path.parent.mkdir()
    atomic.write_text(path, "old")

    def refused(name, mode="r"):  # as open() is answered in a read-only mount, or a folder of another user's
        raise OSError(getattr(errno, code), text, str(name))

    monkeypatch.setattr(atomic, "open", refused, raising=False)
    with pytest.raises(UserError, match=rf"^cannot write '.*ckpt.pt': {text} \(its previous version, if any, is "
                                        r"kept\): make '.*checkpoints' writable$"):
        atomic.torch_save({"a": 1}, path)
    assert path.read_text() == "old" and sorted(p.name for p in path.parent.iterdir()) == ["ckpt.pt"]


def test_torch_save_round_trips_and_replaces(tmp_path):
    path = tmp_path / "x.pt"
    atomic.torch_save({"a": torch.arange(3)}, path)
    atomic.torch_save({"a": torch.arange(4)}, path)
    assert torch.load(path, weights_only=True)["a"].tolist() == [0, 1, 2, 3]
    assert [p.name for p in tmp_path.iterdir()] == ["x.pt"]


def test_a_failed_export_leaves_no_temp_file_and_no_signature(tmp_path, monkeypatch):
    import relayrl
    from relayrl.export import export_policy

    run = tmp_path / "run"
    relayrl.train(relayrl.load_config("dqn-cartpole", ["train.total_steps=200", "train.initial_collect_steps=100",
                                                       "eval.episodes=1", "eval.interval=200"]), run, progress=False)
    monkeypatch.setattr(torch.export, "save", lambda *a, **k: (_ for _ in ()).throw(OSError("no space left")))
    from relayrl.errors import UserError

    with pytest.raises(UserError, match="cannot write .*p.pt2': no space left"):  # one line from the CLI
        export_policy(run, tmp_path / "out" / "p.pt2")
    assert list((tmp_path / "out").iterdir()) == []


class _Closing(gym.Env):
    closed: list[int] = []

    def __init__(self, i: int) -> None:
        self.i = i
        self.observation_space = gym.spaces.Box(-1, 1, (1,))
        self.action_space = gym.spaces.Discrete(2)

    def close(self) -> None:
        _Closing.closed.append(self.i)


def test_a_copy_that_fails_to_build_closes_the_ones_already_made():
    def third_fails(i):
        def make():
            if i == 2:
                raise RuntimeError("simulator licence")
            return _Closing(i)
        return make

    _Closing.closed = []
    with pytest.raises(RuntimeError, match="simulator licence"):
        GymBatchEnv([third_fails(i) for i in range(3)])
    assert _Closing.closed == [0, 1]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_an_interrupt_during_a_write_acts_once_the_file_is_in_place(tmp_path, sig, capsys):
    def on_term(signum, frame):
        raise KeyboardInterrupt  # as the CLI's SIGTERM handler does (a Terminated)

    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        def write(f):
            f.write(b"new ")
            signal.raise_signal(sig)  # Ctrl-C or kill in the middle of the write
            f.write(b"file")

        with pytest.raises(KeyboardInterrupt):
            atomic.write_with(tmp_path / "f", write)
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert (tmp_path / "f").read_bytes() == b"new file"
    assert capsys.readouterr().err == "relayrl: stopping once the file being written is complete\n"
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # handlers put back


def test_ctrl_c_while_a_checkpoint_is_written_still_prunes_to_the_last_two(tmp_path, monkeypatch):
    from relayrl.training.checkpoint import list_checkpoints, save_checkpoint

    for step in (1, 2):
        save_checkpoint(tmp_path, step, {"step": step})
    write = atomic.torch_save

    def interrupted(obj, path, tmp_name=None):
        write(obj, path, tmp_name)
        signal.raise_signal(signal.SIGINT)  # Ctrl-C just after the new file is in place

    monkeypatch.setattr(atomic, "torch_save", interrupted)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(tmp_path, 3, {"step": 3})
    assert [p.name for p in list_checkpoints(tmp_path)] == ["ckpt-000000000002.pt", "ckpt-000000000003.pt"]


def test_both_signals_inside_a_write_act_and_the_terminate_wins(tmp_path):
    class Terminated(KeyboardInterrupt):
        pass

    def on_term(signum, frame):
        raise Terminated

    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        def write(f):
            signal.raise_signal(signal.SIGINT)
            signal.raise_signal(signal.SIGTERM)
            f.write(b"x")

        with pytest.raises(Terminated):  # the CLI then exits 143, as for a kill
            atomic.write_with(tmp_path / "f", write)
        assert signal.getsignal(signal.SIGTERM) is on_term
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_interrupts_pass_through_off_the_main_thread(tmp_path):
    import threading

    done = []
    thread = threading.Thread(target=lambda: (atomic.write_text(tmp_path / "f", "x"), done.append(1)))
    thread.start()
    thread.join()
    assert done and (tmp_path / "f").read_text() == "x"


def test_an_interrupt_in_a_write_inside_a_write_is_said_once(tmp_path, capsys):
    from relayrl import interrupts

    with pytest.raises(KeyboardInterrupt), interrupts.deferred():
        atomic.write_with(tmp_path / "f", lambda f: (f.write(b"x"), signal.raise_signal(signal.SIGINT)))
    assert capsys.readouterr().err.count("stopping once the file being written is complete") == 1
    assert (tmp_path / "f").read_bytes() == b"x"


def test_a_refusal_outside_the_run_directory_is_not_taken_for_the_runs_write(tmp_path):
    """A user's env reading a file it may not: its own error with its traceback, not "make the
    folder writable"; a full disk counts wherever it is met."""
    import errno

    run = tmp_path / "run"
    inside = OSError(errno.EACCES, "Permission denied", str(run / "tb" / "events"))
    outside = OSError(errno.EACCES, "Permission denied", str(tmp_path / "data" / "map.json"))
    unnamed = OSError(errno.EROFS, "Read-only file system")  # TensorBoard's writer names no file
    full = OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "data" / "cache"))
    assert atomic.unwritable(inside, run) is inside and atomic.unwritable(unnamed, run) is unnamed
    assert atomic.unwritable(outside, run) is None and atomic.unwritable(outside) is outside
    assert atomic.unwritable(full, run) is full
