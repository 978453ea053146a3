"""PPO on Ray: the learner-side filter of stale rollouts and the driver's asking again,
without Ray; then one 2-actor run (an actor crashes and is restarted) and its resume.

The Ray tests start a local Ray instance each (~10-20 s with actor start-up); they are
skipped where Ray is not installed."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from test_resume import cut_back

import relayrl
from relayrl.distributed.actors import ActorPool
from relayrl.distributed.onpolicy import RolloutCollection, RolloutShares
from relayrl.metrics import EpisodeStats


def share(actor: int, t: int = 3, b: int = 2) -> dict[str, np.ndarray]:
    """A [t, b] share whose every reward is the actor's index (to tell them apart when joined)."""
    return {"obs": np.full((t, b, 4), actor, np.float32), "reward": np.full((t, b), actor, np.float32),
            "terminated": np.zeros((t, b), bool)}


def test_shares_keep_the_current_version_and_drop_stale_ones():
    shares = RolloutShares(version=5, needed=2)
    assert not shares.offer(1, 4, share(1))  # collected before the latest update
    assert not shares.offer(0, 4, share(0))
    assert (shares.dropped, shares.dropped_steps) == (2, 12) and not shares.ready()  # all stale: none kept
    assert shares.offer(1, 5, share(1)) and not shares.ready()
    assert shares.offer(0, 5, share(0)) and shares.ready()
    assert not shares.offer(0, 5, share(0)), "a share past the K needed joined the rollout"
    assert shares.dropped == 3
    rollout = shares.take()  # joined in actor order, whichever came first: [T, K x B]
    assert rollout["obs"].shape == (3, 4, 4) and rollout["terminated"].shape == (3, 4)
    assert rollout["reward"][0].tolist() == [0, 0, 1, 1]
    assert not shares.ready() and shares.kept == []


def test_shares_kept_of_an_old_version_are_dropped_when_it_advances():
    shares = RolloutShares(version=1, needed=2)
    shares.offer(0, 1, share(0))
    shares.advance(2)
    assert (shares.dropped, shares.version, shares.kept) == (1, 2, [])
    restored = RolloutShares(0, 2)
    restored.load_state_dict(shares.state_dict())
    assert (restored.dropped, restored.dropped_steps) == (1, 6)


def driver(k: int = 2) -> tuple[RolloutCollection, list[tuple[int, int]]]:
    """A Ray PPO run's collection bookkeeping with fake actors: `calls` logs (actor, T) asked;
    the lines it says are in `.said`."""
    calls: list[tuple[int, int]] = []

    def worker(i: int) -> SimpleNamespace:
        return SimpleNamespace(collect=SimpleNamespace(remote=lambda t: calls.append((i, t)) or object()))

    config = relayrl.load_config("ppo-cartpole", ["env.num_envs=2", f"distributed.num_actors={k}"])
    pool = ActorPool(SimpleNamespace(), config, print)
    pool.workers = [worker(i) for i in range(k)]
    run = RolloutCollection(config, pool, EpisodeStats())
    run.shares, run.share_steps = RolloutShares(7, k), 3
    run.said = []
    return run, calls


def answer(run: RolloutCollection, i: int, version: int) -> None:
    """Actor i's call answers with a share collected with `version`."""
    ref = next(r for r, (j, _) in run.pool.inflight.items() if j == i)
    del run.pool.inflight[ref]
    run._take(i, {"rollout": share(i), "policy_version": version, "returns": [], "lengths": [], "info": {}},
              run.said.append)


def test_driver_asks_each_actor_once_per_version_and_again_after_a_stale_share():
    run, calls = driver()
    run._top_up()
    run._top_up()  # a second round asks nothing more: each actor has its call
    assert calls == [(0, 3), (1, 3)]
    # Both answers were collected with an older version (calls made before the update): both
    # are dropped, said, and both actors are asked again -- the learner does not wait on them.
    answer(run, 0, 6)
    answer(run, 1, 6)
    assert run.shares.dropped == 2 and len(run.said) == 2 and "stale" in run.said[0]
    assert calls[2:] == [(0, 3), (1, 3)]
    answer(run, 1, 7)
    answer(run, 0, 7)
    assert run.shares.ready() and len(calls) == 4, "an actor was asked for a share no one needs"


def test_driver_has_a_live_actor_cover_for_one_that_is_restarting():
    run, calls = driver()
    run._top_up()
    del run.pool.inflight[next(r for r, (j, _) in run.pool.inflight.items() if j == 0)]  # actor 0 died
    run.pool.dead.add(0)
    answer(run, 1, 7)
    assert calls[-1] == (1, 3), "actor 1 was not asked for the share actor 0 owed"
    answer(run, 1, 7)
    assert run.shares.ready() and len(calls) == 3


# ---- real Ray runs ----------------------------------------------------------------------------

needs_ray = pytest.mark.skipif(importlib.util.find_spec("ray") is None,
                               reason="distributed runs need Ray (pip install 'relayrl[ray]')")

# 2 actors x 2 CartPole copies, rollouts of 64 env steps (16 per copy): 15 updates of 2 x 2 minibatches
# and a last rollout of 40 steps (10 per copy) cut short by total_steps, collected but not trained
# on (as in one process). The envs' 150th step, where CrashOnce crashes, comes in the 10th rollout.
SMALL = ["env.id=toy_envs:CrashOnce", "env.num_envs=2", "train.collect_steps=64", "train.total_steps=1000",
         "agent.hidden=[16]", "agent.n_epochs=2", "agent.batch_size=32", "eval.interval=1000", "eval.episodes=1",
         "train.checkpoint_interval=512", "train.policy_save_interval=512", "train.log_interval=256",
         "distributed.num_actors=2", "train.torch_threads=1"]


def rows(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def ray_run(tmp_path_factory):
    """A 2-actor PPO run in which a rollout actor crashes once; (run dir, stderr)."""
    import os

    tmp = tmp_path_factory.mktemp("ppo-ray")
    os.environ["RELAYRL_CRASH_MARKER"] = str(tmp / "crashed")
    try:
        import io
        from contextlib import redirect_stderr

        err = io.StringIO()
        with redirect_stderr(err):
            relayrl.train(relayrl.load_config("ppo-cartpole", SMALL), tmp / "run", progress=False)
    finally:
        del os.environ["RELAYRL_CRASH_MARKER"]
    assert (tmp / "crashed").exists(), "no actor crashed: the test proved nothing"
    return tmp / "run", err.getvalue()


@needs_ray
def test_two_actors_train_ppo_through_a_restart(ray_run, capsys):
    run, err = ray_run
    assert "rollout actor" in err and "restarts it" in err
    r = rows(run)
    assert [row["step"] for row in r] == [0, 1000]
    # Every update is one whole rollout of both actors' shares: 15 of 2 epochs x 2 minibatches.
    assert r[-1]["train_step"] == 15 * 2 * 2 and r[-1]["train/episodes"] > 0
    assert all(row["stale_rollouts"] == row["stale_env_steps"] // 32 for row in r)  # present, in shares of 32
    assert r[-1]["actors_alive"] == 2
    assert relayrl.load_policy(run).env_steps == 1000
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    tb = EventAccumulator(str(run / "tb"), size_guidance={"scalars": 0})
    tb.Reload()
    assert [e.step for e in tb.Scalars("charts/stale_rollouts")][-1] == 1000
    from relayrl.cli import main

    assert main(["eval", str(run), "--episodes", "2"]) == 0
    assert json.loads(capsys.readouterr().out)["episodes"] == 2
    import ray

    assert not ray.is_initialized(), "the run left its Ray instance running"


@needs_ray
def test_ppo_on_ray_resumes_from_its_checkpoint(ray_run, tmp_path, capsys):
    run, _ = ray_run
    cut_back(run, tmp_path / "run")  # as if it crashed before its final checkpoint: resumes from 512
    config = relayrl.load_config("ppo-cartpole", SMALL)
    relayrl.train(config, tmp_path / "run", resume=True, progress=False)
    assert "resumed from env step 512" in capsys.readouterr().err
    r = rows(tmp_path / "run")
    assert [row["step"] for row in r] == [0, 1000] and r[-1]["train_step"] == 15 * 2 * 2
    assert relayrl.load_policy(tmp_path / "run").env_steps == 1000
    # the weights' versions go on from the checkpoint's (the resume's first push of its weights is one more)
    assert rows(run)[-1]["policy_version"] <= r[-1]["policy_version"] <= rows(run)[-1]["policy_version"] + 1


@pytest.mark.slow
@needs_ray
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ppo_cartpole_on_two_ray_actors_ends_at_500_within_100k(tmp_path, seed):
    # The preset's 8 env copies as 2 actors x 4: the same rollout, 8 copies x 32 steps
    # (docs/benchmarks.md has the seeds' runs, and those of 2 actors x 8 copies x 16 steps)
    config = relayrl.load_config("ppo-cartpole", ["distributed.num_actors=2", "env.num_envs=4"], seed=seed)
    relayrl.train(config, tmp_path / "r", progress=False)
    r = rows(tmp_path / "r")
    assert r[-1]["step"] == 100_000 and r[-1]["average_return"] >= 500, r
    assert r[-1]["stale_rollouts"] == 0  # no actor died: every share was of the current version
