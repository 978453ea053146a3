"""The distributed run: the learner in the driver, everything else in Ray actors.

    replay server (Table + a writer per actor) ◀─ chunks ─ K rollout actors ◀─ pull ─┐
        │ sample (a group of batches per RPC)                                          │
        ▼                                                                              │
    Learner (driver, GPU if any) ─ push ─▶ VariableContainer actor ─ pull ─▶ eval actors

The driver hands each rollout actor collect calls of a few chunks (two queued per actor, so
none waits for the driver), trains on whatever batches the server's rate limiter releases,
and fires the same triggers as the one-process loop. metrics.jsonl has the same schema.
"""

from __future__ import annotations

import math
import os
import signal
import sys
import time
import uuid
from collections import deque
from typing import Any

from relayrl.agents.registry import algorithm
from relayrl.config import Config, to_dict
from relayrl.distributed import require_ray
from relayrl.distributed.remote import RemotePusher, RemoteTable
from relayrl.distributed.server import ReplayServer
from relayrl.distributed.workers import ActorNames, EvalWorker, RolloutWorker
from relayrl.envs import make_env
from relayrl.errors import NonFiniteError, UserError
from relayrl.metrics import EpisodeStats
from relayrl.seeding import EVAL_STRIDE
from relayrl.specs import Spec
from relayrl.training.checkpoint import load_latest_checkpoint
from relayrl.training.finite import FiniteWatch
from relayrl.training.lifecycle import RunCore, RunResult, check_user_env, make_learner, run_to_end, start_process
from relayrl.training.report import say
from relayrl.training.run_dir import RunDir
from relayrl.training.triggers import IntervalTrigger, Progress
from relayrl.training.variables import VariableContainer

CALL_CHUNKS = 4  # chunks per collect call: long enough that a call's RPC costs little
CALLS_QUEUED = 2  # collect calls queued per actor: the next one starts without the driver
# An actor Ray reports unavailable (restarting after a crash, or its connection lost) is asked
# again every RETRY_S; this many such answers in a row count as a second failure.
RETRY_S = 0.2
UNAVAILABLE_LIMIT = 150


class RayDriver:
    """The run with its envs in K rollout actors, evaluations in eval actors and the replay in a
    server actor; the learner trains here. `distributed/onpolicy.py` is the on-policy variant
    (PPO): no server, rollouts to the driver."""

    worker_class: type = RolloutWorker

    def __init__(self, config: Config, rd: RunDir, progress: bool = True) -> None:
        c = self.config = config
        self.rd = rd
        self.seeds, self.device = start_process(c)
        self.ray = require_ray()
        self.num_actors = c.distributed.num_actors
        self.eval_count = 0
        self.accepted = [0] * self.num_actors  # env steps the replay server took from each actor
        self.failures = [0] * self.num_actors
        self.unavailable = [0] * self.num_actors  # ActorUnavailableError answers in a row
        self.tokens: list[str | None] = [None] * self.num_actors  # each actor's incarnation, from its last answer
        self.restart_counted = [False] * self.num_actors  # this spell of "unavailable" already counted a restart
        self.retry_at = [0.0] * self.num_actors  # monotonic time before which actor i is not asked again
        self.restarting: set[int] = set()
        self.dead: set[int] = set()
        self.inflight: dict[Any, tuple[int, int]] = {}  # collect call -> (actor, env steps asked)
        self.evals: deque[tuple[Any, Progress, float, float, int, int]] = deque()  # in flight, oldest first
        self._owns_ray = False
        self.workers: list[Any] = []
        self.eval_workers: list[Any] = []
        self.server: Any = None
        self.variables: Any = None
        check_user_env(c, None, say)
        # specs (and a bad env id fails here)
        probe = make_env(c.env.id, 1, c.env.max_episode_steps, kwargs=c.env.kwargs, wrappers=c.env.wrappers)
        obs_spec, act_spec = probe.observation_spec, probe.action_spec
        probe.close()
        entry = algorithm(c.algo)
        self.agent = entry.make_agent(c.agent, obs_spec, act_spec, self.device, self.seeds.generator("exploration"),
                                     c.train.total_steps)
        self.stats = EpisodeStats()
        self.stats.step_fn = self.env_steps
        finite = FiniteWatch(c.env.num_envs, obs_spec)  # a Ray run's actors check what they collect
        try:
            table, pusher = self.connect(obs_spec, act_spec)
            self.learner = make_learner(c, self.agent, table, self.device, pusher, entry.replay == "rollouts")
            self.core = RunCore(c, rd, self.agent, self.learner, self.stats, finite, env_steps=self.env_steps,
                                checkpoint_state=self.checkpoint_state,
                                evaluation=IntervalTrigger(c.eval.interval, self._interval_eval),
                                show_progress=progress, postfix=self.postfix, extra_scalars=self.extra_scalars)
        except BaseException:  # Ray actors: none is left behind by a failure here
            self.close()
            raise

    def connect(self, obs_spec: Spec, act_spec: Spec) -> tuple[Any, Any]:
        """Start the actors; the replay the learner samples from and where it pushes weights."""
        c = self.config
        self._start_actors(obs_spec, act_spec)
        self.table = RemoteTable(self.server, c.agent.batch_size)
        self.pusher = RemotePusher(self.variables, self.agent, c.distributed.push_interval)
        return self.table, self.pusher

    def train(self, resume: bool = False) -> RunResult:
        return run_to_end(self, resume)

    def evaluate_now(self, p: Progress) -> None:
        self.submit_eval(p)

    def extra_scalars(self) -> dict[str, float]:
        """TensorBoard scalars of the driver's own."""
        return {}

    def settle_evals(self) -> None:
        self._finish_evals(until=0)

    def announce(self) -> None:
        self.core.say(f"distributed: {self.num_actors} rollout actors x {self.config.env.num_envs} envs, "
                 f"{len(self.eval_workers)} eval actors, learner on {self.device}")

    # ---- actors -------------------------------------------------------------------------
    def _start_actors(self, obs_spec: Any, act_spec: Any) -> None:
        ray, c, d = self.ray, self.config, self.config.distributed
        self._init_ray()
        cfg = to_dict(c)
        path = list(sys.path)
        # Restartable actors find the server and the container by name: Ray cannot promise to
        # keep actor handles passed as constructor arguments alive for a restart.
        names = ActorNames(f"relayrl-{uuid.uuid4().hex[:12]}")
        self.server = self._start_server(names, cfg, obs_spec, act_spec)
        self.variables = ray.remote(num_cpus=0, max_concurrency=self.num_actors + 8)(VariableContainer).options(
            name=names.variables).remote(copy=True)
        worker = ray.remote(num_cpus=d.actor_cpus, max_restarts=d.max_restarts, max_task_retries=0)(self.worker_class)
        self.workers = [worker.remote(cfg, i, names, path) for i in range(self.num_actors)]
        evaluator = ray.remote(num_cpus=0, max_restarts=d.max_restarts, max_task_retries=0)(EvalWorker)
        self.eval_workers = [evaluator.remote(cfg, names, path) for _ in range(d.num_eval_actors)]
        ray.get([w.pid.remote() for w in self.workers + self.eval_workers])  # env errors surface here

    def _start_server(self, names: ActorNames, cfg: dict[str, Any], obs_spec: Spec, act_spec: Spec) -> Any:
        """The replay server actor (None where the run has none)."""
        return self.ray.remote(num_cpus=0, max_concurrency=self.num_actors + 8)(ReplayServer).options(
            name=names.server).remote(cfg, obs_spec, act_spec, str(self.rd.root), self.num_actors)

    def _init_ray(self) -> None:
        ray, d = self.ray, self.config.distributed
        if not ray.is_initialized():
            kw: dict[str, Any] = {"include_dashboard": False, "logging_level": "ERROR"}
            on_sigterm = signal.getsignal(signal.SIGTERM)
            if d.address:
                ray.init(address=d.address, **kw)
            else:  # a local instance with room for every actor's CPU reservation
                ray.init(num_cpus=max(os.cpu_count() or 1, math.ceil(self.num_actors * d.actor_cpus) + 1), **kw)
            if callable(on_sigterm):
                # Ray's core replaces SIGTERM's handler in the driver with one that dumps a
                # stack and exits; the CLI's (stop like Ctrl-C: actors shut down) goes back.
                signal.signal(signal.SIGTERM, on_sigterm)
            self._owns_ray = True

    def close(self) -> None:
        """Stop every actor (and the local Ray instance this run started): no orphan processes."""
        ray = self.ray
        if not ray.is_initialized():
            return
        for handle in [*self.workers, *self.eval_workers, self.server, self.variables]:
            if handle is not None:
                try:
                    ray.kill(handle, no_restart=True)
                except Exception:  # already gone
                    pass
        if self._owns_ray:
            ray.shutdown()

    def env_steps(self) -> int:
        return sum(self.accepted)

    def postfix(self) -> dict[str, str]:
        alive = self.num_actors - len(self.dead) - len(self.restarting)
        return {"actors": f"{alive}/{self.num_actors}"}

    def _call_steps(self) -> int:
        b = self.config.env.num_envs
        return -(-CALL_CHUNKS * self.config.distributed.chunk_steps // b) * b

    def _submit(self, i: int) -> None:
        """Queue a collect call on actor i for its share of the steps still to take."""
        if i in self.dead or time.monotonic() < self.retry_at[i]:
            return
        c = self.config
        asked = sum(n for _, n in self.inflight.values())
        remaining = c.train.total_steps - self.env_steps() - asked
        if remaining <= 0:
            return
        b = c.env.num_envs
        n = -(-min(self._call_steps(), remaining) // b) * b
        explore = self.env_steps() + asked < c.train.initial_collect_steps
        ref = self.workers[i].collect.remote(n, self.env_steps(), explore)
        self.inflight[ref] = (i, n)

    def _poll_workers(self) -> bool:
        ray = self.ray
        if not self.inflight:
            return False
        ready, _ = ray.wait(list(self.inflight), num_returns=len(self.inflight), timeout=0)
        for ref in ready:
            if ref not in self.inflight:  # dropped with its actor's failure below
                continue
            i, _ = self.inflight.pop(ref)
            try:
                r = ray.get(ref)
            except getattr(ray.exceptions, "ActorUnavailableError", ()) as e:  # Ray >= 2.2x; maybe not a death
                self._on_actor_unavailable(i, e)
                continue
            except ray.exceptions.RayActorError as e:
                self._on_actor_death(i, e)
                continue
            self.unavailable[i] = 0
            if self.tokens[i] is not None and r["token"] != self.tokens[i] and not self.restart_counted[i]:
                # A new incarnation that no failed call announced: it crashed while idle.
                self._count_restart(i, "it crashed")
            self.tokens[i] = r["token"]
            self.restart_counted[i] = False
            self.restarting.discard(i)
            self._take(i, r)
        self._top_up()
        return bool(ready)

    def _take(self, i: int, r: dict[str, Any]) -> None:
        """What a collect call of actor i answered; the actor's next call."""
        if r.get("non_finite"):  # run_to_end adds what the run keeps
            raise NonFiniteError(r["non_finite"])
        self.accepted[i] = max(self.accepted[i], int(r["accepted"]))
        self.stats.add_finished(r["returns"], r["lengths"], r["info"])
        self._submit(i)

    def _top_up(self) -> None:
        """Give every live actor its CALLS_QUEUED calls while steps remain. Steps that a failed
        actor's calls had asked for are free again: the other actors must take them, or a run
        whose calls all ended before a failure would stop short of total_steps."""
        queued = [0] * self.num_actors
        for i, _ in self.inflight.values():
            queued[i] += 1
        for i in range(self.num_actors):
            for _ in range(CALLS_QUEUED - queued[i]):
                self._submit(i)

    def _retry_pending(self) -> bool:
        """An actor waits out RETRY_S before it is asked again, with steps still to take."""
        now = time.monotonic()
        return any(i not in self.dead and now < self.retry_at[i] for i in range(self.num_actors)) and \
            self.env_steps() < self.config.train.total_steps

    def _drop_calls(self, i: int) -> None:
        """Forget actor i's calls in flight (queued behind the one that failed: they fail too);
        count the steps the replay server already took from it."""
        for ref in [r for r, (j, _) in self.inflight.items() if j == i]:
            del self.inflight[ref]
        if self.server is None:
            return
        shipped = self.ray.get(self.server.info.remote())["shipped"]
        self.accepted[i] = max(self.accepted[i], int(shipped[i]))

    def _on_actor_unavailable(self, i: int, error: Exception) -> None:
        # Ray says the actor may come back: it crashed and Ray is restarting it, or the
        # connection dropped. Count one restart for the whole spell (its queued calls and
        # those sent while it restarts fail the same way, and one crash must not use up every
        # restart) and ask again every RETRY_S until it answers; UNAVAILABLE_LIMIT
        # answers in a row count as a death of their own.
        self.unavailable[i] += 1
        if self.unavailable[i] > UNAVAILABLE_LIMIT:
            self.unavailable[i] = 0
            self._on_actor_death(i, error)
            return
        self._drop_calls(i)
        self.restarting.add(i)
        self.retry_at[i] = time.monotonic() + RETRY_S
        if not self.restart_counted[i]:
            self.restart_counted[i] = True
            self._count_restart(i, type(error).__name__)

    def _on_actor_death(self, i: int, error: Exception) -> None:
        self._drop_calls(i)
        self.tokens[i] = None  # its next incarnation is this restart, counted here
        self._count_restart(i, type(error).__name__)

    def _count_restart(self, i: int, why: str) -> None:
        d = self.config.distributed
        self.failures[i] += 1
        if self.failures[i] > d.max_restarts:
            self.dead.add(i)
            self.restarting.discard(i)
            self.core.say(f"rollout actor {i} died and is not restarted again "
                          f"(distributed.max_restarts={d.max_restarts})")
            if len(self.dead) == self.num_actors:
                raise RuntimeError("every rollout actor died; continue from the last checkpoint with --resume")
            return
        self.restarting.add(i)
        self.core.say(f"rollout actor {i} died ({why}); Ray restarts it and it goes on from the "
                 f"latest weights (restart {self.failures[i]} of at most {d.max_restarts})")
        self._top_up()

    # ---- evaluation ---------------------------------------------------------------------
    def _interval_eval(self, p: Progress) -> None:
        # The last collect call can cross the final interval while the learner still has
        # steps to take; the final evaluation, after them, covers that boundary.
        if p.env_steps < self.config.train.total_steps:
            self.submit_eval(p)

    def submit_eval(self, p: Progress) -> None:
        n = len(self.eval_workers)
        self._finish_evals(until=n - 1)  # one in flight per eval actor; rows stay in step order
        self.pusher.push(force=True)  # the eval actor evaluates these weights (or newer)
        seed = self.seeds.base("evaluation") + EVAL_STRIDE * self.eval_count
        w = self.eval_count % n
        self.evals.append((self.eval_workers[w].evaluate.remote(seed), p, time.perf_counter(), self.core.wall_time(), w,
                           seed))
        self.eval_count += 1

    def _finish_evals(self, until: int | None = None) -> None:
        """Record finished evaluations, oldest first; wait for them while more than `until`
        are in flight (None: never wait)."""
        ray = self.ray
        while self.evals:
            ref, p, t0, wall, w, seed = self.evals[0]
            must = until is not None and len(self.evals) > until
            if not must and not ray.wait([ref], timeout=0)[0]:
                return
            try:
                result = ray.get(ref)
            except ray.exceptions.RayActorError as e:  # restarted by Ray: evaluate again
                self.core.say(f"eval actor {w} died ({type(e).__name__}); Ray restarts it and the evaluation "
                              "is repeated")
                self.evals[0] = (self.eval_workers[w].evaluate.remote(seed), p, t0, wall, w, seed)
                continue
            self.evals.popleft()
            version = result.pop("policy_version")
            self.core.report.record_eval(p, result, time.perf_counter() - t0, wall_time_s=wall,
                             extra={"policy_version": version, "actors_alive": self.num_actors - len(self.dead),
                                    **self.eval_extra()})

    def eval_extra(self) -> dict[str, Any]:
        """Fields of the run's own in each metrics.jsonl row."""
        return {}

    # ---- checkpoints ----------------------------------------------------------------------
    def checkpoint_state(self) -> dict[str, Any]:
        c = self.config
        return {
            "version": 2,
            "distributed": {"num_actors": self.num_actors},
            "config": to_dict(c),
            "agent": self.agent.state_dict(),
            **self._collection_state(),
            "episode_stats": self.stats.state_dict(),
            "eval_count": self.eval_count,
            "wall_time_s": self.core.wall_time(),
            **self.core.process_state(),
        }

    def _collection_state(self) -> dict[str, Any]:
        """The replay server's contents and the env steps it took from each actor."""
        server = self.ray.get(self.server.state_dict.remote(self.config.train.checkpoint_replay))
        return {"replay": server["table"],
                "shipped": server["shipped"] if server["table"] is not None else list(self.accepted)}

    def _restore_collection(self, state: dict[str, Any]) -> None:
        self.ray.get(self.server.load_state_dict.remote({"table": state["replay"], "shipped": state["shipped"]}))
        if state["replay"] is None:
            self.core.say("the checkpoint has no replay contents (train.checkpoint_replay = false): "
                     "the replay refills from the resumed policy before learning continues")
        self.accepted = [int(x) for x in state["shipped"]]

    def restore(self) -> None:
        c = self.config
        state = load_latest_checkpoint(self.rd.checkpoints)
        saved = state.get("distributed")
        if saved is None:
            raise UserError("this run was trained in one process; resume it with distributed.num_actors=0 "
                            "(its replay is laid out for one actor)")
        if saved["num_actors"] != self.num_actors or state["config"]["env"]["num_envs"] != c.env.num_envs:
            raise UserError(f"the run being resumed has distributed.num_actors={saved['num_actors']} and "
                            f"env.num_envs={state['config']['env']['num_envs']} (its replay is laid out per actor "
                            f"and env copy); resume with the same")
        self.agent.load_state_dict(state["agent"])
        self._restore_collection(state)
        self.stats.load_state_dict(state["episode_stats"])
        self.stats.reset_running()
        self.eval_count = int(state["eval_count"])
        self.core.wall_offset = float(state["wall_time_s"])
        self.core.load_process_state(state)
        steps = self.env_steps()
        self.core.resume_at(steps)
        self.core.say(f"resumed from env step {steps:,} (train step {self.agent.train_step:,}); "
                 f"the {self.num_actors} rollout actors start new episodes")

    # ---- the loop -------------------------------------------------------------------------
    def iterate(self) -> None:
        ray = self.ray
        self.pusher.push(force=True)
        self.core.sps_log.rates.reset(self.core.progress())
        for i in range(self.num_actors):
            for _ in range(CALLS_QUEUED):
                self._submit(i)
        collected_at = None  # the sample request current when collection ended
        while True:
            moved = self._poll_workers()
            n = 0 if self.core.collect_only else self.table.poll()
            if n:
                self.core.step_schedules(self.env_steps())
                self.learner.run(n)
            self.core.fire_triggers()
            self._finish_evals()
            if not self.inflight and not self._retry_pending():
                if collected_at is None:
                    collected_at = self.table.requests
                # Collection is over: stop once a sample request sent after it found the rate
                # limiter allowing nothing more (the one-process loop's last `available_steps`).
                if self.core.collect_only or (not n and self.table.last_empty and self.table.answered > collected_at):
                    break
            if not n and not moved:  # nothing to do: sleep until an actor or the server answers
                waiting = [*self.inflight] if self.core.collect_only else [*self.inflight, self.table.pending]
                if waiting:
                    ray.wait(waiting, num_returns=1, timeout=RETRY_S if self._retry_pending() else 1.0)
                else:
                    time.sleep(RETRY_S)  # only an actor waiting to be asked again
