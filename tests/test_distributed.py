"""Distributed training: the replay server's pieces in one process, then real Ray runs.

The Ray tests start a local Ray instance each (~10-20 s with actor start-up); they are
skipped where Ray is not installed, and one test checks the error a user then gets.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
import traceback
from pathlib import Path

import numpy as np
import pytest
import torch
from procs import alive, process_tree

import relayrl
from relayrl.config import from_dict, to_dict
from relayrl.errors import UserError
from relayrl.replay import Fifo, MinSize, Table, TransitionWriter, Uniform
from relayrl.replay.group import WriterGroup, split_chunk
from relayrl.replay.writers import StepChunk
from relayrl.specs import ArraySpec

OBS = ArraySpec((1,), torch.float32)
ACT = ArraySpec((1,), torch.float32)
B = 2


class Stream:
    """Steps of B envs for one writer: obs x, action x, reward x, next obs x + 1; an episode
    ends every `every` steps (truncated) and the next one starts 100 higher, so an item
    pairing two episodes shows as next_obs - obs != 1."""

    def __init__(self, base: float, every: int = 5) -> None:
        self.x = base + 1000.0 * np.arange(B)
        self.t = np.zeros(B, np.int64)
        self.every = every

    def chunk(self, steps: int) -> StepChunk:
        frames, done, finals = [], [], []
        for _ in range(steps):
            frames.append(self.x.copy())
            self.t += 1
            d = self.t % self.every == 0
            done.append(d)
            finals.extend(self.x[d] + 1)
            self.x = np.where(d, self.x + 100, self.x + 1)
        f = np.array(frames, np.float32)[..., None]  # [C, B, 1]
        d = np.array(done)
        return StepChunk(f, f.copy(), f[..., 0].copy(), d, np.zeros_like(d),
                         np.array(finals, np.float32).reshape(-1, 1))

    def jump(self, by: float) -> None:
        """Start over mid-episode (an actor restarted without ending its episodes)."""
        self.x = self.x + by


def group_table(size: int = 200, writers: int = 2, n_step: int = 1) -> tuple[Table, WriterGroup]:
    table = Table("t", size, Uniform(), Fifo(), MinSize(1), seed=0)

    def make(t: Table, index: int, path: Path | None) -> TransitionWriter:
        return TransitionWriter(t, B, OBS, ACT, gamma=0.9, n_step=n_step, rows=64)

    return table, WriterGroup(table, writers, make)


def assert_items_consistent(batch) -> None:
    obs, action, reward, nxt = (x.numpy().reshape(-1) for x in (batch.obs, batch.action, batch.reward, batch.next_obs))
    assert np.array_equal(action, obs) and np.array_equal(reward, obs), "a read mixed up rows of different items"
    assert np.array_equal(nxt - obs, np.ones_like(obs)), "an item spans two episodes"


def test_writer_group_feeds_one_table_from_writers_out_of_phase():
    table, group = group_table()
    a, b = Stream(0.0), Stream(10_000.0, every=7)
    for steps in (3, 5, 1, 8, 4):  # chunks of different lengths, interleaved
        group.write_chunk(0, a.chunk(steps))
        group.write_chunk(1, b.chunk(steps + 2))
    batch, _ = table.sample(150)
    assert_items_consistent(batch)
    owners = set((batch.obs.numpy().reshape(-1) // 10_000).astype(int).tolist())
    assert owners == {0, 1}, "both writers' items are sampled from the one table"
    # Every step of both streams is an item, but each env's newest, whose next row is unwritten.
    assert table.size == (21 + 31) * B - 2 * B


def test_writer_group_restart_drops_the_dead_actors_open_episodes():
    table, group = group_table()
    s = Stream(0.0, every=1000)
    group.write_chunk(0, s.chunk(6))  # episodes still open
    group.restart_episodes(0)
    s.jump(50)  # the restarted actor's envs start new episodes without ending the old ones
    group.write_chunk(0, s.chunk(6))
    batch, _ = table.sample(200)
    assert_items_consistent(batch)
    # Without the restart the two streams would be joined by one item per env.
    assert table.size == 2 * 5 * B


def test_writer_group_evicts_its_own_items_when_its_rows_wrap():
    table, group = group_table(size=1000)
    s = Stream(0.0)
    for _ in range(30):
        group.write_chunk(0, s.chunk(10))  # 300 steps per env into 64 rows: the ring wraps
    batch, _ = table.sample(500)
    assert_items_consistent(batch)
    assert not group.storage.stale(np.flatnonzero(table.slot_key >= 0)).any()


def test_writer_group_checkpoint_round_trip():
    # 3-step items and episodes of different lengths per writer: the writers' n-step
    # windows (and so their items' next-observation rows) differ at the same positions.
    table, group = group_table(n_step=3)
    a, b = Stream(0.0, every=4), Stream(10_000.0, every=7)
    for _ in range(4):
        group.write_chunk(0, a.chunk(6))
        group.write_chunk(1, b.chunk(3))
    state = table.state_dict()
    assert "slot_ref" not in state["storage"]["writers"][0], "the shared slot map is saved once"
    table2, group2 = group_table(n_step=3)
    table2.load_state_dict(state)
    x, _ = table.sample(64)
    y, _ = table2.sample(64)
    for f, g in zip(x, y, strict=True):
        assert (f is None and g is None) or torch.equal(f, g)
    table3, group3 = group_table()
    a, b = Stream(0.0), Stream(10_000.0)
    group3.write_chunk(0, a.chunk(6))
    group3.write_chunk(1, b.chunk(6))
    table4, group4 = group_table()
    table4.load_state_dict(table3.state_dict())
    group4.write_chunk(1, b.chunk(5))  # resumed writers start new episodes and go on
    assert_items_consistent(table4.sample(100)[0])


def test_split_chunk_keeps_final_observations_with_their_steps():
    chunk = Stream(0.0, every=3).chunk(10)
    pieces = split_chunk(chunk, 4)
    assert [p.done.shape[0] for p in pieces] == [4, 4, 2]
    assert sum(len(p.finals) for p in pieces) == len(chunk.finals)
    table, group = group_table()
    for p in pieces:
        group.writers[0].write_chunk(p)
    assert_items_consistent(table.sample(40)[0])


def server_config(**replay) -> dict:
    c = from_dict({"algo": "sac", "env": {"id": "Pendulum-v1", "num_envs": B}, "agent": {"batch_size": 8},
                   "distributed": {"chunk_steps": 16},
                   "replay": {"size": 2000, "min_size_to_sample": 40, **replay}})
    return to_dict(c)


def test_replay_server_drops_chunks_of_a_dead_incarnation(tmp_path):
    from relayrl.distributed.server import ReplayServer

    server = ReplayServer(server_config(), OBS, ACT, str(tmp_path), 1)
    s = Stream(0.0)
    server.register(0, "first")
    assert server.ingest(0, "first", s.chunk(4)) == 4 * B
    server.register(0, "second")  # the actor was restarted
    assert server.ingest(0, "first", s.chunk(4)) == 4 * B, "a chunk from the dead incarnation was taken"
    assert server.ingest(0, "second", s.chunk(4)) == 8 * B


def test_replay_server_takes_nothing_after_its_intake_closed(tmp_path):
    """A halted run counts what the server took once; a chunk a killed actor sent before it
    died, arriving later or let through the rate limiter later, must not change that count."""
    from relayrl.distributed.server import ReplayServer

    server = ReplayServer(server_config(), OBS, ACT, str(tmp_path), 2)
    s = Stream(0.0)
    for i in range(2):
        server.register(i, f"t{i}")
        server.ingest(i, f"t{i}", s.chunk(4))
    size = server.table.size
    write = server.group.write_chunk

    def closed_while_writing(index, chunk):  # the rate limiter held it until a sample asked before the halt
        server.close_intake()
        write(index, chunk)

    server.group.write_chunk = closed_while_writing
    assert server.ingest(1, "t1", s.chunk(4)) == 4 * B
    server.group.write_chunk = write
    grown = server.table.size
    assert grown > size, "the held chunk reached the table"
    assert server.ingest(0, "t0", s.chunk(4)) == 4 * B
    server.register(0, "restarted")  # an incarnation Ray restarted as the run halted
    assert server.ingest(0, "restarted", s.chunk(4)) == 4 * B
    assert server.info()["shipped"] == [4 * B, 4 * B] and server.table.size == grown


def test_halting_the_rollout_actors_closes_the_servers_intake_before_anyone_counts():
    """ActorPool.halt_rollouts, with a stand-in for Ray: the actors are killed, their calls
    forgotten, and the server's intake closed (waited for) before it returns."""
    from relayrl.distributed.actors import ActorPool

    calls: list[str] = []

    class Remote:
        def __init__(self, name: str) -> None:
            self.name = name

        def remote(self) -> str:
            calls.append(f"{self.name}.remote")
            return self.name

    class Server:
        close_intake = Remote("close_intake")

    class FakeRay:
        def kill(self, handle, no_restart: bool) -> None:
            calls.append(f"kill {handle}")

        def get(self, ref):
            calls.append(f"get {ref}")

    pool = ActorPool(FakeRay(), relayrl.load_config("dqn-cartpole-fast", ["distributed.num_actors=2"]), print)
    pool.workers, pool.server, pool.inflight = ["w0", "w1"], Server(), {"call": (0, 64)}
    pool.halt_rollouts()
    assert calls == ["kill w0", "kill w1", "close_intake.remote", "get close_intake"] and not pool.inflight


def test_rate_limiter_holds_across_clients(tmp_path):
    """Two actors insert and a learner samples, each in its own thread, as in the threaded
    Ray actor: inserts * spi - samples stays in Reverb's window, and both sides block."""
    from relayrl.distributed.server import ReplayServer

    server = ReplayServer(server_config(samples_per_insert=2.0, error_buffer=48.0), OBS, ACT, str(tmp_path), 2)
    lim = server.table.rate_limiter
    seen: list[float] = []
    stop = threading.Event()

    def actor(i: int) -> None:
        server.register(i, "t")
        s = Stream(10_000.0 * i)
        for _ in range(30):
            server.ingest(i, "t", s.chunk(3))

    def monitor() -> None:
        while not stop.is_set():
            with server.table._cv:
                if lim.inserts - lim.deletes >= lim.min_size_to_sample:
                    seen.append(lim.inserts * lim.samples_per_insert - lim.samples)
            time.sleep(0.0005)

    threads = [threading.Thread(target=actor, args=(i,)) for i in range(2)] + [threading.Thread(target=monitor)]
    for t in threads:
        t.start()
    sampled = 0
    while any(t.is_alive() for t in threads[:2]) or server.table.samples_available() >= 8:
        got = server.sample(8, 1, timeout=0.2)
        sampled += 8 * len(got)
        time.sleep(0.002)  # a learner slower than the actors: their inserts must wait
    stop.set()
    threads[2].join()
    assert lim.inserts == 2 * 30 * 3 * B
    assert seen and min(seen) >= lim.min_diff - 1e-9 and max(seen) <= lim.max_diff + 1e-9
    assert max(seen) > lim.max_diff - 2 * 3 * B * 2, "the actors never ran into the limiter: the test proved nothing"
    assert sampled == lim.samples
    assert lim.samples >= lim.inserts * 2.0 - lim.max_diff - 8  # the learner got what the ratio allows


# ---- without Ray ---------------------------------------------------------------------------

def test_distributed_without_ray_is_one_clear_error(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` now raises ImportError
    import relayrl.distributed.driver  # noqa: F401  (importable without Ray)

    config = relayrl.load_config("dqn-cartpole-fast", ["distributed.num_actors=2"])
    with pytest.raises(UserError, match=re.escape('pip install -e ".[ray]" in relayrl\'s folder')):
        relayrl.train(config, tmp_path / "run", progress=False)
    assert not (tmp_path / "run" / "config.toml").exists()
    from relayrl.cli import main

    assert main(["train", "dqn-cartpole-fast", "--run-dir", str(tmp_path / "r2"),
                 "--set", "distributed.num_actors=2"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pip install -e \".[ray]\"" in err


def test_bad_distributed_config_is_refused():
    with pytest.raises(UserError, match="distributed.num_actors"):
        relayrl.load_config("sac-pendulum", ["distributed.num_actors=-1"])
    with pytest.raises(UserError, match="distributed.chunk_steps"):
        relayrl.load_config("sac-pendulum", ["distributed.chunk_steps=0"])


# ---- real Ray runs ----------------------------------------------------------------------------

needs_ray = pytest.mark.skipif(importlib.util.find_spec("ray") is None,
                               reason="distributed runs need Ray (pip install 'relayrl[ray]')")

SAC_SMALL = ["agent.actor_hidden=[32, 32]", "agent.critic_hidden=[32, 32]", "agent.batch_size=32",
             "train.total_steps=800", "train.initial_collect_steps=200", "train.checkpoint_interval=400",
             "train.policy_save_interval=400", "eval.interval=400", "eval.episodes=2", "replay.size=2000",
             "distributed.chunk_steps=50", "distributed.pull_interval=100", "train.torch_threads=1"]


def rows(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]


@needs_ray
@pytest.mark.parametrize("envs", [[], ["env.num_envs=2", "env.vectorization=async"]], ids=["1env", "2async"])
def test_two_rollout_actors_train_sac_and_write_the_run_directory(tmp_path, envs, monkeypatch, capsys):
    # 2async: each Ray actor forks an env worker process beside itself
    from relayrl.training.heartbeat import ProgressLines

    monkeypatch.setattr(ProgressLines, "interval_s", 0.5)
    config = relayrl.load_config("sac-pendulum", SAC_SMALL + ["distributed.num_actors=2"] + envs)
    result = relayrl.train(config, tmp_path / "run", progress=True)  # pytest's stderr is no TTY: lines, no bar
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("step ") and "/800 (" in line]
    assert lines and all(" | actors 2/2 | " in line for line in lines), lines  # the bar's field, without a bar
    r = rows(tmp_path / "run")
    local_keys = {"step", "train_step", "average_return", "average_episode_length", "episodes", "wall_time_s",
                  "eval_s", "train/average_return", "train/episodes"}
    assert all(local_keys <= row.keys() for row in r)
    assert [row["step"] for row in r][0] == 0 and r[-1]["step"] == 800 == result.final["step"]
    # The rate limiter (1 sample per insert at batch 32) decides the learner's steps: every
    # item after min_size gives one gradient step, within the error buffer.
    assert 0.8 * 600 <= r[-1]["train_step"] <= 600 + 2 * 50 + 1
    assert r[-1]["train/episodes"] >= 2 and r[-1]["actors_alive"] == 2
    assert (tmp_path / "run" / "policy" / "policy.pt").exists()
    assert relayrl.load_policy(tmp_path / "run").env_steps == 800
    # best.pt: an evaluated policy as it was evaluated (the learner moved on while the eval actor ran)
    best = torch.load(tmp_path / "run" / "policy" / "best.pt", weights_only=True)
    assert (best["env_steps"], best["average_return"]) in [(row["step"], row["average_return"]) for row in r]
    assert relayrl.load_policy(tmp_path / "run" / "policy" / "best.pt").env_steps == best["env_steps"]
    assert list((tmp_path / "run" / "checkpoints").glob("ckpt-*.pt"))
    import ray

    assert not ray.is_initialized(), "the run left its Ray instance running"


@needs_ray
def test_a_killed_rollout_actor_is_restarted_and_the_run_finishes(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("RELAYRL_CRASH_MARKER", str(tmp_path / "crashed"))
    over = ["env.id=toy_envs:CrashOnce", "train.total_steps=1200", "train.initial_collect_steps=200",
            "eval.interval=600", "eval.episodes=2", "distributed.num_actors=2", "distributed.chunk_steps=50",
            "train.checkpoint_interval=0"]
    config = relayrl.load_config("dqn-cartpole-fast", over)
    relayrl.train(config, tmp_path / "run", progress=False)
    assert (tmp_path / "crashed").exists(), "no actor crashed: the test proved nothing"
    err = capsys.readouterr().err
    assert "died" in err and "restarts it" in err
    r = rows(tmp_path / "run")
    assert r[-1]["step"] == 1200 and r[-1]["train_step"] > 0


@needs_ray
def test_an_env_error_in_a_rollout_actor_names_that_actors_env_step(tmp_path):
    """The actor counts its own env steps (the run's are the sum over the actors): the note
    says whose they are."""
    over = ["env.id=toy_envs:BrokenAt", "env.kwargs={at = 45}", "train.total_steps=400",
            "train.initial_collect_steps=100", "eval.interval=0", "eval.episodes=1", "distributed.num_actors=1",
            "distributed.chunk_steps=50", "train.checkpoint_interval=0"]
    with pytest.raises(RuntimeError, match="simulator lost connection") as caught:
        relayrl.train(relayrl.load_config("dqn-cartpole-fast", over), tmp_path / "run", progress=False)
    said = str(caught.value) + " ".join(getattr(caught.value, "__notes__", []))
    assert "relayrl: raised at env step 45 of rollout actor 0" in said and "of training" not in said
    shown = "".join(traceback.format_exception(caught.value))  # the remote traceback's notes, said once
    assert shown.count("relayrl: raised by step() of env copy 0") == 1
    assert shown.count("relayrl: raised at env step 45") == 1 and shown.count("the run stopped at") == 1


@needs_ray
def test_an_env_error_in_a_rollout_actor_names_the_env_steps_the_replay_server_took_and_checkpoints_them(tmp_path):
    # A collect call of 400 steps (4 chunks of 100) fails at its 301st step and never answers:
    # the driver has heard of no steps, the replay server took the call's first 3 chunks; the
    # one-process run stops at 300 too, with its checkpoint at 300.
    config = relayrl.load_config("sac-pendulum", SAC_SMALL + [
        "distributed.num_actors=1", "distributed.chunk_steps=100", "train.checkpoint_interval=100",
        "env.id=toy_envs:BrokenAt", "env.kwargs={at = 301, continuous = true}", "env.check=false"])
    with pytest.raises(RuntimeError, match="simulator lost connection") as e:
        relayrl.train(config, tmp_path / "run", progress=False)
    notes = "\n".join(getattr(e.value, "__notes__", []))
    assert "relayrl: the run stopped at env step 300 on the error above" in notes
    # the checkpoints due at 100, 200 and 300 are one, at 300 (where the driver heard of the steps)
    assert checkpoint_steps(tmp_path / "run") == [300] and "the last good checkpoint (env step 300)" in notes
    import ray

    assert not ray.is_initialized(), "the run left its Ray instance running"


def checkpoint_steps(run: Path) -> list[int]:
    return sorted(int(f.name[5:17]) for f in (run / "checkpoints").glob("ckpt-*.pt"))


@needs_ray
@pytest.mark.parametrize("sig, code, group", [(signal.SIGINT, 130, True),  # Ctrl-C in a terminal: the whole group
                                              (signal.SIGINT, 130, False), (signal.SIGTERM, 143, False)])  # kill
def test_ctrl_c_stops_every_actor_and_the_run_resumes(tmp_path, cli_env, sig, code, group):
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "relayrl", "train", "sac-pendulum", "--run-dir", str(run), "--no-progress"]
    sets = [a for o in SAC_SMALL + ["distributed.num_actors=2", "train.total_steps=1600",
                                    "train.checkpoint_interval=200"] for a in ("--set", o)]
    p = subprocess.Popen(cmd + sets, env=cli_env, stderr=subprocess.PIPE, text=True, start_new_session=group)
    try:
        deadline = time.monotonic() + 240
        while not list((run / "checkpoints").glob("ckpt-*.pt")) and p.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        assert p.poll() is None, f"the run ended before the interrupt: {p.stderr.read() if p.stderr else ''}"
        tree = process_tree(p.pid)
        assert len(tree) > 3, "no Ray processes were seen under the run"
        before = checkpoint_steps(run)
        os.killpg(p.pid, sig) if group else p.send_signal(sig)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == code, err
    assert "resume with --resume" in err and "Traceback" not in err, err
    if sig == signal.SIGINT:  # the run stops at its loop's next turn and saves a checkpoint there; Ray lives on
        assert "stopping at the end of this iteration" in err, err
        assert checkpoint_steps(run)[-1] >= before[-1]
        assert relayrl.load_policy(run).env_steps == checkpoint_steps(run)[-1]  # the final save: one env step
    deadline = time.monotonic() + 90  # Ray's own processes take tens of seconds to go on a loaded machine
    while alive(tree - {p.pid}) and time.monotonic() < deadline:
        time.sleep(0.5)
    assert not alive(tree - {p.pid}), "processes of the interrupted run are still alive"
    # Evaluations run beside training: a checkpoint may come before the first eval row.
    steps_at_interrupt = max((row["step"] for row in rows(run)), default=0)
    latest = checkpoint_steps(run)[-1]
    done = subprocess.run(cmd + ["--resume"], env=cli_env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert f"resumed from env step {latest:,} " in done.stderr  # the checkpoint's name is what it resumes from
    r = rows(run)
    steps = [row["step"] for row in r]
    assert steps == sorted(set(steps)), "metrics.jsonl has repeated or unordered rows after the resume"
    assert steps[-1] == 1600 and steps_at_interrupt < 1600


def test_server_stores_stacked_frames_once_and_rebuilds_the_stacks(tmp_path):
    """Pixel runs on Ray: actors ship the newest frame per step (`stack_steps`), the server's
    writers store it once and sampled stacks equal the env's own (padding with the first frame)."""
    from relayrl.distributed.server import ReplayServer
    from relayrl.replay.writers import stack_steps
    from relayrl.types import Transition

    k, every = 2, 4
    obs_spec = ArraySpec((k, 3, 3), torch.uint8, frame_stack=k)
    server = ReplayServer(server_config(), obs_spec, ACT, str(tmp_path), 1)
    server.register(0, "t")
    frame = lambda v: torch.full((B, 3, 3), v, dtype=torch.uint8)  # noqa: E731  all envs alike
    t, ep, staged = 0, 0, []
    hist = [frame(1)] * k  # the stack at an episode's start: its first frame repeated
    for _ in range(23):
        t += 1
        done = t % every == 0
        nxt = hist[1:] + [frame(1 + 10 * ep + t % every if not done else 1 + 10 * ep + every)]
        term = torch.full((B,), done)
        staged.append(Transition(torch.stack(hist, 1), torch.zeros(B, 1), torch.ones(B), torch.stack(nxt, 1),
                                 term, torch.zeros(B, dtype=torch.bool)))
        if done:
            ep += 1
            hist = [frame(1 + 10 * ep)] * k
        else:
            hist = nxt
        if len(staged) == 5:
            server.ingest(0, "t", stack_steps(staged, k))
            staged = []
    live = np.flatnonzero(server.table.slot_key >= 0)
    batch = server.table.storage.read(live)
    obs, nxt = batch.obs.numpy()[:, :, 0, 0].astype(int), batch.next_obs.numpy()[:, :, 0, 0].astype(int)
    assert obs.shape[1] == k and len(live) > 10
    step = obs[:, 1] % 10  # 1 + position in the episode
    assert np.array_equal(obs[:, 0], np.where(step == 1, obs[:, 1], obs[:, 1] - 1)), "a stack crossed an episode start"
    assert np.array_equal(nxt[:, 1], obs[:, 1] + 1) and np.array_equal(nxt[:, 0], obs[:, 1])
    assert server.group.storage.storages[0].store.frame.shape[-2:] == (3, 3)  # one frame per row, not a stack


@needs_ray
def test_a_nan_reward_a_rollout_actor_collected_stops_the_run_in_one_line(tmp_path):
    from relayrl.errors import NonFiniteError

    config = relayrl.load_config("sac-pendulum", SAC_SMALL + [
        "distributed.num_actors=1", "env.id=toy_envs:NonFiniteAt", "env.kwargs={at = 300, continuous = true}",
        "env.check=false"])
    with pytest.raises(NonFiniteError) as e:
        relayrl.train(config, tmp_path / "run", progress=False)
    assert "reward was NaN at" in str(e.value) and "\n" not in str(e.value)
    assert relayrl.load_policy(tmp_path / "run").env_steps < 300
    import ray

    assert not ray.is_initialized(), "the run left its Ray instance running"


@needs_ray
def test_a_memmap_folder_another_run_holds_is_refused_before_any_actor_starts(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "config.toml").write_text("")
    (tmp_path / "shared").mkdir()
    (tmp_path / "shared" / "run.txt").write_text(str(tmp_path / "a"))  # run a holds the folder
    over = ["distributed.num_actors=1", "replay.storage=memmap", "replay.path=shared", "train.total_steps=600"]
    with pytest.raises(relayrl.errors.UserError, match="holds the replay of the run in"):
        relayrl.train(relayrl.load_config("dqn-cartpole-fast", over), tmp_path / "b", progress=False)
    import ray

    assert not ray.is_initialized()


@needs_ray
def test_eval_env_kwargs_that_change_the_spaces_are_refused_before_any_actor_starts(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(Path(__file__).parent))  # toy_envs
    over = ["distributed.num_actors=1", "env.id=toy_envs:Resized", "eval.env_kwargs={size=3}",
            "train.total_steps=600"]
    with pytest.raises(relayrl.errors.UserError, match="give evaluation envs observations"):
        relayrl.train(relayrl.load_config("dqn-cartpole-fast", over), tmp_path / "run", progress=False)
    import ray

    assert not ray.is_initialized()


@needs_ray
def test_a_ray_cluster_that_is_not_there_is_one_line(tmp_path):
    import socket

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    from relayrl.errors import UserError

    config = relayrl.load_config("sac-pendulum", ["distributed.num_actors=1",
                                                  f"distributed.address=127.0.0.1:{port}"])
    with pytest.raises(UserError, match=r"no Ray cluster answers at distributed.address=.*ray start --head"):
        relayrl.train(config, tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()


@needs_ray
def test_an_env_a_ray_worker_cannot_make_is_one_line_naming_the_worker(tmp_path):
    # The driver makes the env (its checks pass); the rollout actor's node cannot: the user
    # gets the worker's own one-line reason, not Ray's 60-line ActorDiedError.
    config = relayrl.load_config("dqn-cartpole-fast", ["distributed.num_actors=1", "train.total_steps=600",
                                                       "env.id=toy_envs:MadeOnlyInTheDriver"])
    with pytest.raises(UserError) as e:
        relayrl.train(config, tmp_path / "run", progress=False)
    assert str(e.value) == ("an actor could not start on a Ray worker: no module 'remoteonly' on this node "
                            "(the test's stand-in)")
    import ray

    assert not ray.is_initialized()


@needs_ray
def test_an_id_registered_only_in_the_users_script_trains_on_ray_actors(tmp_path):
    """gymnasium.register in the user's script (the driver's process) is not in a Ray worker's
    fresh registry: the run takes it there, so that the id that trains in one process trains on Ray."""
    import gymnasium

    gymnasium.register("relayrl-test/ScriptRegistered-v0", entry_point="toy_envs:Countdown", kwargs={"length": 7})
    try:
        config = relayrl.load_config("dqn-cartpole-fast", [
            "distributed.num_actors=1", "env.id=relayrl-test/ScriptRegistered-v0", "train.total_steps=400",
            "train.initial_collect_steps=100", "eval.interval=0", "eval.episodes=1", "distributed.chunk_steps=50",
            "train.checkpoint_interval=0"])
        result = relayrl.train(config, tmp_path / "run", progress=False)
    finally:
        del gymnasium.registry["relayrl-test/ScriptRegistered-v0"]
    assert result.final["step"] == 400 and result.final["average_episode_length"] == 7.0


def test_actors_not_yet_placed_are_waited_for_with_a_line_every_so_often(monkeypatch):
    # A cluster without the CPUs the actors ask for places them when some come free: the run
    # says what it waits for instead of hanging without a word.
    from types import SimpleNamespace

    from relayrl.distributed import actors

    waits = iter([(["a"], ["b"]), (["a"], ["b"]), (["a", "b"], [])])
    said: list[str] = []
    fake_ray = SimpleNamespace(
        wait=lambda pending, num_returns, timeout: next(waits), get=lambda calls: [1, 2],
        available_resources=lambda: {"CPU": 0.0}, cluster_resources=lambda: {"CPU": 2.0},
        nodes=lambda: [{"Alive": True, "Resources": {"CPU": 2.0}}, {"Alive": False, "Resources": {"CPU": 8.0}}],
        exceptions=SimpleNamespace(RayActorError=RuntimeError))
    pool = actors.ActorPool(fake_ray, relayrl.load_config("ppo-cartpole", ["distributed.num_actors=2"]), said.append)
    pool.wait_started(["a", "b"])
    assert said == ["waiting for 1 actor to start: rollout actors ask for 1 CPU each (distributed.actor_cpus), "
                    "the Ray cluster has 0 of 2 CPUs free; this run's 1 started rollout actor holds 1"] * 2
    # an actor larger than any node's CPUs: said at once, not only that it waits
    waits = iter([(["a", "b"], [])])
    said.clear()
    pool = actors.ActorPool(fake_ray, relayrl.load_config("ppo-cartpole", [
        "distributed.num_actors=2", "distributed.actor_cpus=3"]), said.append)
    pool.wait_started(["a", "b"])
    assert said == ["no node of the Ray cluster has 3 CPUs (the largest has 2): the rollout actors start only once "
                    "a node that large joins (an autoscaling cluster adds one); a lower distributed.actor_cpus "
                    "starts them now"]


def test_a_running_cluster_and_an_empty_address_is_one_line(monkeypatch):
    # Ray joins the cluster RAY_ADDRESS names, and then refuses the local instance's CPU count.
    from types import SimpleNamespace

    from relayrl.distributed.actors import init_ray

    def init(**kw):
        raise ValueError("When connecting to an existing cluster, num_cpus and num_gpus must not be provided.")

    monkeypatch.setenv("RAY_ADDRESS", "10.0.0.1:6379")
    fake_ray = SimpleNamespace(is_initialized=lambda: False, init=init)
    config = relayrl.load_config("sac-pendulum", ["distributed.num_actors=1"])
    with pytest.raises(UserError, match=r"^RAY_ADDRESS='10.0.0.1:6379' names a Ray cluster to join, and "
                                        r"distributed.address is empty .* set distributed.address=auto"):
        init_ray(fake_ray, config)


def test_more_local_actors_than_a_machine_can_hold_is_one_line_before_ray_starts(monkeypatch):
    """Each actor is a process holding torch: 100,000 of them on a local instance exhaust the
    machine's memory; a cluster takes any number."""
    from types import SimpleNamespace

    from relayrl.distributed import actors

    def init(**kw):
        raise AssertionError("ray.init is not reached")

    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    monkeypatch.setattr(actors.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})
    fake_ray = SimpleNamespace(is_initialized=lambda: False, init=init)
    config = relayrl.load_config("ppo-cartpole", ["distributed.num_actors=33"])
    with pytest.raises(UserError, match=r"^distributed.num_actors=33 starts as many worker processes on this machine "
                                        r"\(a local Ray instance\); at most 32 here"):
        actors.init_ray(fake_ray, config)
    started = []
    config.distributed.num_actors = 32
    actors.init_ray(SimpleNamespace(is_initialized=lambda: False, init=lambda **kw: started.append(kw)), config)
    assert started[0]["num_cpus"] == 33


def test_auto_with_a_ray_address_where_nothing_listens_is_one_line_at_once(monkeypatch):
    """Ray would wait for the head RAY_ADDRESS names (minutes, in warnings): the address is tried first."""
    from types import SimpleNamespace

    from relayrl.distributed.actors import init_ray

    def init(**kw):
        raise AssertionError("ray.init is not reached")

    monkeypatch.setenv("RAY_ADDRESS", "127.0.0.1:1")
    fake_ray = SimpleNamespace(is_initialized=lambda: False, init=init)
    config = relayrl.load_config("sac-pendulum", ["distributed.num_actors=1", "distributed.address=auto"])
    with pytest.raises(UserError, match=r"^no Ray cluster answers at distributed.address='auto'.* \(RAY_ADDRESS="
                                        r"'127.0.0.1:1'\)"):
        init_ray(fake_ray, config)


def test_a_sigterm_inside_ray_init_reaches_the_clis_handler(monkeypatch):
    """Ray's handler, in place during ray.init, exits with 15 and no line: the CLI's handler
    (here one raising TimeoutError) takes the signal, and stays in place."""
    import signal
    from types import SimpleNamespace

    from relayrl.distributed.actors import init_ray

    def ours(signum, frame):
        raise TimeoutError("the CLI's stop")

    def init(**kw):
        signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(signum))  # as Ray's
        signal.raise_signal(signal.SIGTERM)

    before = signal.signal(signal.SIGTERM, ours)
    try:
        with pytest.raises(TimeoutError, match="the CLI's stop"):
            init_ray(SimpleNamespace(is_initialized=lambda: False, init=init),
                     relayrl.load_config("sac-pendulum", ["distributed.num_actors=1"]))
        assert signal.getsignal(signal.SIGTERM) is ours
    finally:
        signal.signal(signal.SIGTERM, before)


def test_an_actor_whose_env_fails_to_build_is_the_workers_one_line_and_ray_is_shut_down():
    from types import SimpleNamespace

    from relayrl.distributed import actors

    class ActorDied(RuntimeError):
        pass

    failure = ("The actor died because of an error raised in its creation task, ray::RolloutWorker.__init__()\n"
               "Traceback (most recent call last):\n  File \"mymod.py\", line 5, in __init__\n"
               "OSError: WorkerFails: no device /dev/fake on this node")

    def get(calls):
        raise ActorDied(failure)

    shut = []
    fake_ray = SimpleNamespace(wait=lambda pending, num_returns, timeout: (pending, []), get=get,
                               exceptions=SimpleNamespace(RayActorError=ActorDied), is_initialized=lambda: False,
                               shutdown=lambda: shut.append(1),
                               nodes=lambda: [{"Alive": True, "Resources": {"CPU": 2}}])
    pool = actors.ActorPool(fake_ray, relayrl.load_config("ppo-cartpole", ["distributed.num_actors=1"]), print)
    with pytest.raises(UserError, match=r"^an actor could not start on a Ray worker: OSError: WorkerFails: no device "
                                        r"/dev/fake on this node$"):
        pool.wait_started(["a"])
    pool.owns_ray = True  # as `start` sets it before ray.init, which an interrupt may cut short
    pool.close()
    assert shut == [1]


def test_an_address_without_actors_says_the_run_is_one_process(tmp_path, capsys):
    config = relayrl.load_config("dqn-cartpole-fast", ["distributed.address=auto", "train.total_steps=300",
                                                       "train.initial_collect_steps=100", "eval.episodes=1"])
    relayrl.train(config, tmp_path / "run", progress=False)
    assert "with distributed.num_actors=0: the run trains in this process" in capsys.readouterr().err


@needs_ray
@pytest.mark.parametrize("preset, over", [
    ("dqn-cartpole-fast", ["train.initial_collect_steps=200", "distributed.chunk_steps=50"]),
    ("ppo-cartpole", ["env.num_envs=2", "train.collect_steps=64", "agent.hidden=[16]", "agent.n_epochs=2",
                      "agent.batch_size=32"])])
def test_a_callback_stops_a_distributed_run_with_its_policy_and_checkpoint(tmp_path, preset, over):
    """A callback's False stops a Ray run as it stops one process: the loop ends at its next
    turn, the final evaluation, policy and checkpoint are written there."""
    config = relayrl.load_config(preset, over + ["train.total_steps=100000", "eval.interval=400", "eval.episodes=1",
                                                 "train.checkpoint_interval=100000", "distributed.num_actors=2",
                                                 "train.torch_threads=1"])
    result = relayrl.train(config, tmp_path / "run", progress=False,
                           callbacks=[lambda row: row.get("event") != "eval" or row["step"] < 400])
    assert result.stopped_early
    steps = checkpoint_steps(tmp_path / "run")
    assert steps and 400 <= steps[-1] < 100000
    last = rows(tmp_path / "run")[-1]
    assert last["step"] == steps[-1] and last["step"] < 100000
    assert relayrl.load_policy(tmp_path / "run").env_steps == steps[-1]


@pytest.mark.parametrize("env_id", ["__main__:MyEnv", "mymodule:<lambda>"])
def test_an_env_made_in_the_script_is_refused_for_ray_in_one_line(tmp_path, env_id):
    """Ray's workers import env.id; one the script itself made cannot be (no Ray needed to say so)."""
    config = relayrl.load_config("dqn-cartpole-fast", [f"env.id={env_id}", "distributed.num_actors=2"])
    with pytest.raises(UserError, match="Ray's workers cannot import: put it in a module"):
        relayrl.train(config, tmp_path / "run", progress=False)
    assert not (tmp_path / "run" / "metrics.jsonl").exists()


def fake_eval_driver(calls: list[str], losses: dict[str, float]):
    """A RayDriver with fake Ray, pusher, actors and report: evaluate_now's order of calls and
    the rows it records, without a Ray instance."""
    from collections import deque
    from types import SimpleNamespace

    from relayrl.distributed.driver import RayDriver
    from relayrl.seeding import RunSeeds
    from relayrl.training.triggers import EvalSeeds

    class Pusher:
        last_ref, version = "push", 1

        def push(self, force: bool = False) -> None:
            calls.append("push")

    def evaluate(seed: int) -> str:
        calls.append("evaluate")
        return "eval"

    rows: list[dict] = []
    stats = {"train/average_return": float("nan"), "train/episodes": 0}
    report = SimpleNamespace(training_state=lambda: {**stats, **losses},
                             record_eval=lambda p, result, eval_s, **kw: rows.append({"p": p, **kw}))
    d = object.__new__(RayDriver)
    d.config = relayrl.load_config("dqn-cartpole-fast", ["distributed.num_actors=1"])
    d.ray = SimpleNamespace(get=lambda ref: calls.append(f"get {ref}") or {"policy_version": 1},
                            wait=lambda refs, timeout: (refs, []))
    d.pusher, d.seeds, d.evals, d.eval_seeds = Pusher(), RunSeeds(0), deque(), EvalSeeds(d.config.eval.interval)
    d.pool = SimpleNamespace(eval_workers=[SimpleNamespace(evaluate=SimpleNamespace(remote=evaluate))], alive=1)
    d.collection = SimpleNamespace(eval_extra=dict)
    d.core = SimpleNamespace(report=report, wall_time=lambda: 0.0, best_policy=None)
    return d, rows


def test_an_evaluation_on_ray_waits_for_the_push_of_the_weights_it_evaluates():
    # Ray orders nothing between the learner's push (to the variable container) and the eval
    # actor's pull: unwaited, the step-0 evaluation could run the eval actor's own untrained
    # network (policy_version 0) instead of the learner's.
    from relayrl.training.triggers import Progress

    calls: list[str] = []
    d, _ = fake_eval_driver(calls, {})
    d.evaluate_now(Progress(0, 0))
    assert calls == ["push", "get push", "evaluate"]


def test_a_ray_evaluation_row_has_the_training_state_of_its_step_not_of_its_answer():
    # The eval actor answers while the learner trains on: the row written then must not carry
    # losses and training returns from later steps (a step-0 row with losses from training).
    from relayrl.training.triggers import Progress

    losses: dict[str, float] = {}
    d, rows = fake_eval_driver([], losses)
    d.evaluate_now(Progress(0, 0))
    losses["losses/loss"] = 1.5  # the learner trained before the evaluation answered
    d.settle_evals()
    assert rows[0]["p"] == Progress(0, 0)
    assert "losses/loss" not in rows[0]["at_step"] and rows[0]["at_step"]["train/episodes"] == 0


def test_every_rollout_actor_given_up_is_one_line(tmp_path):
    # An env that kills its worker process each time: past max_restarts the run stops with one
    # line (the CLI's exit 2), not Ray's chained ActorDiedError traceback.
    from types import SimpleNamespace

    from relayrl.distributed.actors import ActorPool

    said: list[str] = []
    config = relayrl.load_config("dqn-cartpole-fast", ["distributed.num_actors=1", "distributed.max_restarts=0"])
    pool = ActorPool(SimpleNamespace(), config, said.append)
    with pytest.raises(UserError) as e:
        try:
            raise RuntimeError("Ray's ActorDiedError")
        except RuntimeError as died:
            pool._on_death(0, died)
    assert str(e.value) == ("every rollout actor died, each past distributed.max_restarts=0 (the lines above say "
                            "why)")
    assert e.value.__suppress_context__
    assert said == ["rollout actor 0 died (RuntimeError) and is not restarted again (distributed.max_restarts=0)"]


@pytest.mark.parametrize("answer, expected", [
    ([b"\x00\x00", b"\x18\x04\x00\x00\x00\x00\x00"], True),  # a gRPC server's SETTINGS, in two pieces
    ([b"HTTP/1.0 400 Bad request\r\n\r\n"], False),  # python -m http.server, a dashboard
    ([b"\x15\x03\x03\x00\x02\x02\x46"], None),  # a TLS alert: a head that takes TLS, which Ray says itself
])
def test_what_listens_at_distributed_address_is_told_apart_by_its_answer_to_http2s_preface(answer, expected):
    """Ray retries an address where something else listens for minutes: the preface tells a
    Ray head (gRPC) from another service at once."""
    import socket

    from relayrl.distributed.actors import HTTP2_PREFACE, speaks_http2

    server = socket.create_server(("127.0.0.1", 0))
    got: list[bytes] = []

    def serve() -> None:
        conn, _ = server.accept()
        with conn:
            got.append(conn.recv(len(HTTP2_PREFACE)))
            for piece in answer:
                conn.sendall(piece)
                time.sleep(0.05)

    thread = threading.Thread(target=serve)
    thread.start()
    try:
        assert speaks_http2("127.0.0.1", server.getsockname()[1], timeout=5) is expected
    finally:
        thread.join(timeout=5)
        server.close()
    assert got == [HTTP2_PREFACE]


def test_a_run_inside_a_running_ray_says_its_address_is_not_joined():
    """Inside a Ray Tune trial (or after the user's ray.init), distributed.address was ignored
    without a word."""
    from types import SimpleNamespace

    from relayrl.distributed.actors import ActorPool

    said: list[str] = []

    def stop(*args, **kwargs):
        raise RuntimeError("stop here")

    fake = SimpleNamespace(is_initialized=lambda: True, remote=stop)
    config = relayrl.load_config("ppo-cartpole", ["distributed.num_actors=1", "distributed.address='10.0.0.1:6379'"])
    with pytest.raises(RuntimeError, match="stop here"):
        ActorPool(fake, config, said.append).start(object, None)
    assert said == ["distributed.address='10.0.0.1:6379' is not joined: Ray is running in this process already "
                    "(ray.init was called), and the run's actors go on that instance"]


@needs_ray
def test_a_replay_server_that_dies_is_one_line_that_says_what_is_kept(tmp_path):
    """Killing the replay server's process printed Ray's 80-line traceback through the learner's poll."""
    import ray

    def kill_the_server(row):
        if row.get("step") == 400:
            server = next(a["name"] for a in ray.util.list_named_actors(all_namespaces=True)
                          if a["name"].endswith("-replay"))
            ray.kill(ray.get_actor(server), no_restart=True)

    config = relayrl.load_config("sac-pendulum", SAC_SMALL + ["distributed.num_actors=1", "train.total_steps=4000"])
    with pytest.raises(relayrl.UserError) as caught:
        relayrl.train(config, tmp_path / "run", progress=False, callbacks=[kill_the_server])
    said = str(caught.value)
    assert said.startswith("the run's replay server (ReplayServer, a Ray actor) died: its process was killed or its "
                           "node lost; the run stopped at env step "), said
    assert "the last good checkpoint (env step 400)" in said and "--resume" in said


@needs_ray
def test_an_env_module_missing_on_a_ray_worker_says_so_for_that_node(tmp_path, monkeypatch):
    """The one-process advice ("run relayrl from the folder that holds it", naming the worker's own
    folder) sent a cluster user to the wrong place."""
    monkeypatch.setenv("RELAYRL_DRIVER_PID", str(os.getpid()))
    over = ["env.id=driver_only_env:Env", "env.check=false", "train.total_steps=400", "train.initial_collect_steps=100",
            "eval.interval=0", "eval.episodes=1", "distributed.num_actors=1", "train.checkpoint_interval=0"]
    with pytest.raises(relayrl.UserError) as caught:
        relayrl.train(relayrl.load_config("dqn-cartpole-fast", over), tmp_path / "run", progress=False)
    assert str(caught.value).startswith("an actor could not start on a Ray worker: env.id='driver_only_env:Env': "
                                        "module 'driver_only_env' does not import on the Ray worker on node "), \
        str(caught.value)
    assert "(ModuleNotFoundError: No module named 'simulator'): every node needs the driver's code" in str(caught.value)


@needs_ray
@pytest.mark.parametrize("address", ["auto", ""])
def test_a_cluster_file_left_by_a_killed_head_is_one_line_not_a_wait(tmp_path, monkeypatch, address):
    """A head killed without `ray stop` leaves Ray's file naming it: an empty address was told a
    cluster "is running" and to use auto, and auto waited for it for minutes."""
    import socket

    with socket.socket() as s:  # a port nothing listens on once closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    (tmp_path / "ray").mkdir()
    (tmp_path / "ray" / "ray_current_cluster").write_text(f"127.0.0.1:{port}\n")
    monkeypatch.setenv("RAY_TMPDIR", str(tmp_path))
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    over = ["distributed.num_actors=1", f"distributed.address={address!r}", "train.total_steps=400"]
    with pytest.raises(relayrl.UserError, match=rf"joins the cluster that Ray's file '.*ray_current_cluster' names "
                                                rf"\(127.0.0.1:{port}\), where nothing answers: a head stopped without "
                                                r"`ray stop` leaves it; `ray stop --force` clears it"):
        relayrl.train(relayrl.load_config("dqn-cartpole-fast", over), tmp_path / "run", progress=False)
