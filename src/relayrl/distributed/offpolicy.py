"""Off-policy collection on Ray (registry replay "transitions": DQN, SAC).

    replay server (Table + a writer per actor) ◀─ chunks ─ K rollout actors ◀─ pull ─┐
        │ sample (a group of batches per RPC)                                          │
        ▼                                                                              │
    Learner (driver, GPU if any) ─ push ─▶ VariableContainer actor ─ pull ─▶ eval actors

The driver hands each rollout actor collect calls of a few chunks (two queued per actor, so
none waits for the driver) and trains on whatever batches the server's rate limiter releases.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from relayrl.config import Config, to_dict
from relayrl.core import Agent
from relayrl.distributed.actors import RETRY_S, ActorPool
from relayrl.distributed.remote import RemotePusher, RemoteTable
from relayrl.distributed.server import ReplayServer
from relayrl.distributed.workers import RolloutWorker
from relayrl.errors import NonFiniteError
from relayrl.metrics import EpisodeStats
from relayrl.specs import Spec
from relayrl.training.checkpoint import NO_REPLAY, replay_lost
from relayrl.training.lifecycle import RunCore
from relayrl.training.report import plural

CALL_CHUNKS = 4  # chunks per collect call: long enough that a call's RPC costs little
CALLS_QUEUED = 2  # collect calls queued per actor: the next one starts without the driver


class ReplayCollection:
    """Rollout actors ship transitions to the replay server; the env steps it took from each
    actor are the run's env steps."""

    def __init__(self, config: Config, pool: ActorPool, stats: EpisodeStats) -> None:
        self.config, self.pool, self.stats = config, pool, stats
        self.accepted = [0] * pool.num_actors  # env steps the replay server took from each actor

    def start(self, rd_root: str, obs_spec: Spec, act_spec: Spec, agent: Agent) -> tuple[RemoteTable, RemotePusher]:
        c, k = self.config, self.pool.num_actors

        def server(ray: Any, name: str) -> Any:
            return ray.remote(num_cpus=0, max_concurrency=k + 8)(ReplayServer).options(
                name=name).remote(to_dict(c), obs_spec, act_spec, rd_root, k)

        self.pool.start(RolloutWorker, server)
        self.table = RemoteTable(self.pool.server, c.agent.batch_size)
        self.pusher = RemotePusher(self.pool.variables, agent, c.distributed.push_interval)
        return self.table, self.pusher

    def env_steps(self) -> int:
        return sum(self.accepted)

    def layout(self) -> str:
        return f"{plural(self.pool.num_actors, 'rollout actor')} x {plural(self.config.env.num_envs, 'env')}"

    def postfix(self) -> dict[str, str]:
        return self.pool.postfix()

    def eval_extra(self) -> dict[str, Any]:
        return {}

    def extra_scalars(self) -> dict[str, float]:
        return {}

    def _submit(self, i: int) -> None:
        """Queue a collect call on actor i for its share of the steps still to take."""
        if not self.pool.may_ask(i):
            return
        c = self.config
        asked = self.pool.asked()
        remaining = c.train.total_steps - self.env_steps() - asked
        if remaining <= 0:
            return
        b = c.env.num_envs
        n = -(-min(CALL_CHUNKS * c.distributed.chunk_steps, remaining) // b) * b  # whole batched steps
        explore = self.env_steps() + asked < c.train.initial_collect_steps
        self.pool.ask(i, n, n, self.env_steps(), explore)

    def _top_up(self) -> None:
        """Give every live actor its CALLS_QUEUED calls while steps remain (a failed actor's steps
        included: a run whose calls all ended before a failure would stop short otherwise)."""
        queued = [0] * self.pool.num_actors
        for i, _ in self.pool.inflight.values():
            queued[i] += 1
        for i in range(self.pool.num_actors):
            for _ in range(CALLS_QUEUED - queued[i]):
                self._submit(i)

    def _take(self, i: int, r: dict[str, Any]) -> None:
        if r.get("non_finite"):  # run_to_end adds what the run keeps
            raise NonFiniteError(r["non_finite"])
        self.accepted[i] = max(self.accepted[i], int(r["accepted"]))
        self.stats.add_finished(r["returns"], r["lengths"], r["info"])
        self._submit(i)

    def _count_shipped(self, actors: Iterable[int]) -> None:
        """Count the steps the replay server took from `actors` that no answer reported (their
        calls failed, or were halted)."""
        shipped = self.pool.ray.get(self.pool.server.info.remote())["shipped"]
        for i in actors:
            self.accepted[i] = max(self.accepted[i], int(shipped[i]))

    def _poll(self) -> bool:
        """Take what the actors answered and ask them again; True when any answered."""
        moved = self.pool.poll(self._take, lambda i: self._count_shipped([i]))
        self._top_up()
        return moved

    def _retry_pending(self) -> bool:
        return self.pool.retry_pending() and self.env_steps() < self.config.train.total_steps

    def iterate(self, core: RunCore, finish_evals: Callable[[], None]) -> None:
        try:
            self._iterate(core, finish_evals)
        except NonFiniteError:  # what the server took holds the non-finite number: nothing more is kept
            raise
        except Exception:
            # A collect call that failed (the env's exception, an actor's last death) never
            # answered, nor did the calls behind it: the steps their actors shipped are counted
            # from the server, with the actors ended first so that the count holds still.
            # run_to_end names the run's env steps by it, and a checkpoint due by then is written.
            try:
                self.pool.halt_rollouts()
                self._count_shipped(range(self.pool.num_actors))
            except Exception:  # the server gone too: the driver's count stands
                pass
            else:
                core.checkpoint_if_due()
            raise

    def _iterate(self, core: RunCore, finish_evals: Callable[[], None]) -> None:
        self.pusher.push(force=True)
        core.sps_log.reset(core.progress())
        self._top_up()
        collected_at = None  # the sample request current when collection ended
        while not core.report.stop_requested:  # a callback's False, Ctrl-C
            moved = self._poll()
            n = 0 if core.collect_only else self.table.poll()
            if n:
                core.step_schedules(self.env_steps())
                core.learner.learn(n)
            core.fire_triggers()
            finish_evals()
            if not self.pool.inflight and not self._retry_pending():
                if collected_at is None:
                    collected_at = self.table.requests
                    if not core.collect_only:  # the learner may lag the actors by seconds: no silent wait
                        core.say(f"all {self.env_steps():,} env steps collected: the learner takes the gradient "
                                 f"steps the replay still allows (at train step {core.agent.train_step:,})")
                # Collection is over: stop once a sample request sent after it found the rate
                # limiter allowing nothing more (the one-process loop's last `available_steps`).
                if core.collect_only or (not n and self.table.last_empty and self.table.answered > collected_at):
                    break
            if not n and not moved:  # nothing to do: sleep until an actor or the server answers
                also = [] if core.collect_only else [self.table.pending]
                self.pool.wait(also, RETRY_S if self._retry_pending() else 1.0)
        if core.report.stop_requested:  # the count the final save is named by: what the server took
            self.pool.halt_rollouts()
            self._count_shipped(range(self.pool.num_actors))

    def state_dict(self) -> dict[str, Any]:
        server = self.pool.ray.get(self.pool.server.state_dict.remote(self.config.train.checkpoint_replay))
        shipped = server["shipped"] if server["table"] is not None else list(self.accepted)
        # The server may hold steps this driver has not heard of yet: a resume starts from its count.
        return {"replay": server["table"], "shipped": shipped, "env_steps": int(sum(shipped))}

    def load_state_dict(self, state: dict[str, Any], say: Callable[[str], None]) -> None:
        lost = self.pool.ray.get(self.pool.server.load_state_dict.remote({"table": state["replay"],
                                                                          "shipped": state["shipped"]}))
        if state["replay"] is None:
            say(NO_REPLAY)
        elif lost:
            say(replay_lost(lost))
        self.accepted = [int(x) for x in state["shipped"]]
